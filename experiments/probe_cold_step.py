"""How much of an online step's time is the step itself, and how much a cold start: ``kf.step``
timed back to back (hot) and right after 35 ms of something else (cold), at B = 1, 100 and 1000
tracks, beside the loop of B filterpy filters it is compared with in ``bench_online.py``.

A live tracker calls its step between other work (reading reports, association, I/O), so the
torch code the step runs is no longer in the CPU's caches and branch predictors when it comes.
``bench_online.py`` times the B = 1000 step in alternation with the filterpy loop (cold); this
probe separates the two regimes and the kind of work in between: a sleep (other processes run
on the core), a pure-Python loop, small numpy products, touching 32 MB, the filterpy loop itself
and ``gc.collect()``. Thread CPU time (``time.thread_time``: our own CPU time, not other
processes'), 1 intra-op thread, float64, medians over repeats; aten operations per step are
counted with a dispatch mode.

    PYTHONPATH=$PWD python experiments/probe_cold_step.py [--repeat 31] [--out experiments/results/probe_cold_step.md]
"""

from __future__ import annotations

import argparse
import gc
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_online import build_filter, filterpy_filter, filterpy_step, step_args  # noqa: E402

import torchsde_lti as tl  # noqa: E402

PAUSE_S = 0.035


class _CountOps(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
        self.count += 1
        return func(*args, **(kwargs or {}))


def _busy_python() -> None:
    t0, x = time.perf_counter(), 0
    while time.perf_counter() - t0 < PAUSE_S:
        x += 1


def _small_numpy() -> None:
    t0, a = time.perf_counter(), np.ones((4, 4))
    while time.perf_counter() - t0 < PAUSE_S:
        a = a @ a.T / 16 + np.eye(4)


def _touch_32mb() -> None:
    np.ones(4_000_000).sum()


def median_ms_after(between: Callable[[], object], fn: Callable[[], object], repeat: int) -> float:
    """Median thread CPU ms of ``fn`` called right after ``between`` (not timed)."""
    times = []
    for _ in range(repeat):
        between()
        t0 = time.thread_time()
        fn()
        times.append(time.thread_time() - t0)
    return 1e3 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=31)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "probe_cold_step.md"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    kf = build_filter(validate=False)
    load_before = os.getloadavg()
    rows = []
    for B in (1, 100, 1000):
        mean, cov, y, dt = step_args(B, 1)
        state = tl.KalmanState(mean, cov)
        fps = [filterpy_filter() for _ in range(B)]
        zs, hs = y.numpy()[:, :, None], dt.tolist()

        def step() -> None:
            with torch.no_grad():
                kf.step(state, y, dt)

        def fp_loop() -> None:
            for f, z, h in zip(fps, zs, hs):
                filterpy_step(f, z, h)

        step()
        with torch.no_grad(), _CountOps() as ops:
            kf.step(state, y, dt)
        pauses: list[tuple[str, Callable[[], object]]] = [
            ("nothing (hot)", lambda: None),
            ("sleep 35 ms", lambda: time.sleep(PAUSE_S)),
            ("Python loop 35 ms", _busy_python),
            ("numpy 4×4 products 35 ms", _small_numpy),
            ("touch 32 MB", _touch_32mb),
            (f"the loop of {B} filterpy filters", fp_loop),
            ("gc.collect()", gc.collect),
        ]
        for _ in range(3):
            step()
            fp_loop()
        fp_hot = median_ms_after(lambda: None, fp_loop, max(5, args.repeat // 3))
        fp_cold = median_ms_after(lambda: time.sleep(PAUSE_S), fp_loop, max(5, args.repeat // 3))
        for name, between in pauses:
            t = median_ms_after(between, step, args.repeat)
            rows.append((B, ops.count, name, t, fp_hot / t, fp_cold / t))
            print(f"B={B:5d} after {name:32s} step {t:7.3f} ms  filterpy hot/step {fp_hot / t:6.1f}", flush=True)
        rows.append((B, ops.count, "(filterpy loop: hot / after a 35 ms sleep)", float("nan"), fp_hot, fp_cold))
    load_after = os.getloadavg()
    lines = [
        "# Online step: hot and cold (experiments/probe_cold_step.py)",
        "",
        f"torch {torch.__version__}, 1 intra-op thread, float64, thread CPU time, medians of {args.repeat} "
        f"(filterpy: {max(5, args.repeat // 3)}); load average {load_before[0]:.2f} before, "
        f"{load_after[0]:.2f} after on {os.cpu_count()} cores (a shared machine).",
        "",
        "| B | aten ops / step | before the step | step (ms) | filterpy loop (hot) / step | "
        "filterpy loop (after sleep) / step |",
        "|---:|---:|---|---:|---:|---:|",
    ]
    for B, n_ops, name, t, r_hot, r_cold in rows:
        if t != t:  # the filterpy row: its times in ms
            lines.append(f"| {B} | | {name} | | {r_hot:.3f} ms | {r_cold:.3f} ms |")
        else:
            lines.append(f"| {B} | {n_ops} | {name} | {t:.3f} | {r_hot:.1f}× | {r_cold:.1f}× |")
    text = "\n".join(lines) + "\n"
    out = Path(args.out)
    previous = out.read_text() if out.exists() else ""
    out.write_text(text + ("\n" + previous if previous else ""))
    print(text)


if __name__ == "__main__":
    main()
