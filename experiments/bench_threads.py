r"""Paired benchmark of the issue-19 speed cells: the default against the naive Van Loan, at 1
and 2 intra-op threads, in one process.

Every repeat calls each contestant once — ``default`` and ``naive`` (experiments/bench_discretize.py's
workload and contestants) at 1 thread and at 2 threads, in alternating order — so that background
load hits all four alike; a cell's figure is the median wall time. Reported per cell: the
default's and the naive's times, the default's speed-up over the naive at each thread count,
and each one's 2-thread / 1-thread time ratio (issue 19's target for the library: ≤ 1.1).
Cells: one F shared by B = 1e5 elements (n = 2, 4), per-element F at B = 1e4 (n = 4) and the
small calls B = 1, 100 (n = 4), forward and forward+backward, float64 and float32, and a
Matérn-3/2 Kalman filter over 4,000 steps (the library alone). The machine's load average
is printed beside the table: read it.

    python experiments/bench_threads.py [--repeats 5] [--out experiments/results/bench_threads.md]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_per_element
from bench_discretize import make_call, make_problem

import torchsde_lti as tl
from torchsde_lti.core import threads as core_threads


def per_element_call(name: str, n: int, B: int, dtype: torch.dtype, backward: bool) -> Callable[[], object]:
    F, L, Qc, dt = bench_per_element.make_problem(n, B, dtype)
    fn = bench_per_element.CONTESTANTS[name]

    def call() -> object:
        if not backward:
            with torch.no_grad():
                return fn(F, L, Qc, dt)
        xs = [x.detach().requires_grad_(i != 1) for i, x in enumerate((F, L, Qc, dt))]
        A, Q = fn(*xs)
        (A.sum() + Q.sum()).backward()
        return None

    return call


def gp_call() -> Callable[[], object]:
    f64, T = torch.float64, 4000
    rng = np.random.default_rng(0)
    t = np.sort(rng.uniform(0.0, T / 5.0, T))
    sde = tl.models.matern(1.5, lengthscale=0.7, variance=1.9, dtype=f64)
    kf = tl.KalmanFilter(sde, torch.tensor([[1.0, 0.0]], dtype=f64), torch.tensor([[0.05]], dtype=f64))
    y = torch.as_tensor(np.sin(t) + 0.3 * rng.standard_normal(T))[:, None]
    dt = torch.as_tensor(np.diff(t, prepend=t[0]))

    def call() -> object:
        with torch.no_grad():
            return kf(y, dt)

    return call


def paired(
    calls: dict[str, Callable[[], object]],
    repeats: int,
    budget: float,
    threads: list[int],
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, float]:
    """Median time (ms) per (name, threads), each repeat alternating the order."""
    keys = [(name, th) for name in calls for th in threads]
    for name, th in keys:
        torch.set_num_threads(th)
        calls[name]()
    times: dict[tuple[str, int], list[float]] = {k: [] for k in keys}
    start, r = time.perf_counter(), 0
    while r < repeats or (time.perf_counter() - start < budget and r < 5 * repeats):
        for name, th in keys if r % 2 == 0 else keys[::-1]:
            torch.set_num_threads(th)
            t0 = clock()
            calls[name]()
            times[(name, th)].append(clock() - t0)
        r += 1
    torch.set_num_threads(1)
    return {f"{name}@{th}": statistics.median(v) * 1e3 for (name, th), v in times.items()}


def unguarded(call: Callable[[], object]) -> Callable[[], object]:
    """``call`` with the library's backward thread guard switched off (the behaviour before it)."""

    def run() -> object:
        guarded = core_threads._guarded
        core_threads._guarded = lambda work, tensors: False
        try:
            return call()
        finally:
            core_threads._guarded = guarded

    return run


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--budget", type=float, default=3.0, help="seconds per cell beyond the repeats")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--only", default="", help="run only the cells whose label contains this")
    ap.add_argument(
        "--clock",
        choices=["wall", "cpu"],
        default="wall",
        help="cpu: process CPU time at 1 thread only (robust to other processes; no 2-thread column)",
    )
    ap.add_argument(
        "--unguarded",
        action="store_true",
        help="also time the default with its backward thread guard off (core.threads.one_thread_backward), "
        "in the forward+backward cells",
    )
    args = ap.parse_args()
    threads = [1] if args.clock == "cpu" else [1, 2]
    clock = time.process_time if args.clock == "cpu" else time.perf_counter
    cells: list[tuple[str, dict[str, Callable[[], object]]]] = []
    for dtype in (torch.float64, torch.float32):
        dn = str(dtype)[6:]
        for n in (2, 4):
            prob = make_problem(n, 100_000)
            for backward in (False, True):
                calls = {k: make_call(k, prob, 100_000, dtype, backward) for k in ("default", "naive")}
                if backward and (n > 2 or args.clock == "wall"):
                    calls.pop("naive")  # naive fwd+bwd at B = 1e5: seconds (n = 2) to tens of seconds a call
                cells.append(
                    (
                        f"shared F, n={n}, B=1e5, {dn}, {'fwd+bwd' if backward else 'fwd'}",
                        {k: v for k, v in calls.items() if v is not None},
                    )
                )
        for B in (1, 100, 10_000):
            for backward in (False, True):
                cells.append(
                    (
                        f"per-element F, n=4, B={B}, {dn}, {'fwd+bwd' if backward else 'fwd'}",
                        {k: per_element_call(k, 4, B, dtype, backward) for k in ("default", "naive")},
                    )
                )
    cells.append(("Matérn-3/2 filter, T=4000, float64", {"default": gp_call()}))
    cells = [c for c in cells if args.only in c[0]]
    if args.unguarded:
        for label, calls in cells:
            if "fwd+bwd" in label:
                calls["unguarded"] = unguarded(calls["default"])
    head = (
        f"# issue-19 speed cells, paired: {args.clock} ms (median), threads {threads} (torch {torch.__version__}, "
        f"cpu_count {os.cpu_count()}, load at start {os.getloadavg()[0]:.2f})\n"
    )
    lines = [
        head,
        (
            "| cell | default 1t | default 2t | default 2t/1t | naive 1t | naive 2t | naive 2t/1t | "
            "default/naive speed-up 1t | 2t |" + (" unguarded 1t | 2t | 2t/1t |" if args.unguarded else "")
        ),
        "|---|---|---|---|---|---|---|---|---|" + ("---|---|---|" if args.unguarded else ""),
    ]
    print("\n".join(lines), flush=True)
    for label, calls in cells:
        t = paired(calls, args.repeats, args.budget, threads, clock)
        d1, d2 = t["default@1"], t.get("default@2", math.nan)
        n1, n2 = t.get("naive@1"), t.get("naive@2", math.nan)
        fmt = lambda v: "—" if v is None else f"{v:.3g}"
        row = (
            f"| {label} | {d1:.3g} | {d2:.3g} | {d2 / d1:.2f} | {fmt(n1)} | {fmt(n2)} | "
            f"{'—' if n1 is None else f'{n2 / n1:.2f}'} | {'—' if n1 is None else f'{n1 / d1:.2f}×'} | "
            f"{'—' if n1 is None else f'{n2 / d2:.2f}×'} |"
        )
        if args.unguarded:
            u1, u2 = t.get("unguarded@1"), t.get("unguarded@2", math.nan)
            row += f" {fmt(u1)} | {fmt(u2)} | {'—' if u1 is None else f'{u2 / u1:.2f}'} |"
        lines.append(row)
        print(row, flush=True)
    lines.append(f"\nload average at end {os.getloadavg()[0]:.2f}")
    print(lines[-1])
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
