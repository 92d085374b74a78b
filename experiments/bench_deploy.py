r"""Benchmark: deploying a trained KalmanFilter (issue 10, item 5) — torch.compile and
torch.export, measured side by side with eager.

Model: 2-D constant velocity (n = 4, m = 2) with R learned (a state_dict checkpoint is saved
and loaded, as after training), irregular dt, float64, no grad.

1. ``torch.compile(kf)``: wall time of the first call (compilation, inductor's caches off)
   and the median of the following calls (no grad), for the default (``algorithm="auto"``:
   under torch.compile the loop as torch's structured scan, one step compiled) and the forced
   associative scan (``algorithm="scan"``: traced whole), at T = 200 and T = 2000, B = 1 — vs
   the same filter eager (``"auto"`` eager runs the associative scan at B = 1).
2. checkpoint → ``torch.export.export`` → ``torch.export.save`` → ``torch.export.load`` →
   run on new tracks of the exported shape: export / save / load times, the exported
   program's run time vs eager, and the largest |difference| of log-likelihood and means.
3. (B = 1) the exported program built by AOTInductor into a .pt2 package
   (``torch._inductor.aoti_compile_and_package``), loaded with ``aoti_load_package`` and run
   on new tracks: build / load / run times vs eager and vs filterpy on the same track.

Shared machine (other sessions run): medians of repeats, noisy. Prints the tables and saves
them to experiments/results/bench_deploy.txt.

    python experiments/bench_deploy.py [--threads 1] [--no-aoti]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch
from _timing import machine_line, median_s, saved
from bench_online import filterpy_cv  # the same filterpy contestant

import torchsde_lti as tl

F64 = torch.float64


def make_filter(algorithm: str = "auto") -> tl.KalmanFilter:
    cv = tl.models.constant_velocity(dim=2, q=1.0, dtype=F64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64)
    return tl.KalmanFilter(
        cv, H, 0.5 * torch.eye(2, dtype=F64), P0=100 * torch.eye(4, dtype=F64), learn=("R",), algorithm=algorithm
    )


def data(B: int, T: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    dt = torch.rand(B, T, generator=g, dtype=F64) * 1.95 + 0.05
    y = torch.randn(B, T, 2, generator=g, dtype=F64).cumsum(1)
    return y, dt


def median_ms(fn, repeats: int = 7) -> float:
    """Median wall milliseconds of ``repeats`` calls (compiled and packaged calls: wall time)."""
    return 1e3 * median_s(fn, repeats, warmup=0, clock=time.perf_counter)


def bench_compile() -> None:
    # cold compiles: no inductor cache from an earlier run of this script
    torch._inductor.config.fx_graph_cache = False
    torch._inductor.config.autotune_local_cache = False
    t0 = time.perf_counter()
    torch.compile(lambda x: 2.0 * x)(torch.zeros(2, dtype=F64))  # inductor's start-up, once per process
    startup = time.perf_counter() - t0
    print("\n### torch.compile(kf), B = 1: first call (compile, caches off) and steady state\n")
    print(f"(inductor's start-up, paid once per process before the first row: {startup:.1f} s)\n")
    print("| T | algorithm | first call (s) | compiled (ms) | eager (ms) | eager / compiled |")
    print("|---|---|---|---|---|---|")
    for T in (200, 2000):
        y, dt = data(1, T, 0)
        for algorithm in ("auto", "scan"):
            torch._dynamo.reset()
            kf = make_filter(algorithm)
            ck = torch.compile(kf)
            with torch.no_grad():
                t0 = time.perf_counter()
                ck(y, dt)
                first = time.perf_counter() - t0
                t_c = median_ms(lambda: ck(y, dt))
                t_e = median_ms(lambda: kf(y, dt))
            print(f"| {T} | {algorithm} | {first:.1f} | {t_c:.2f} | {t_e:.2f} | {t_e / t_c:.2f}× |", flush=True)


def bench_export(B: int, T: int, aoti: bool) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        ckpt, prog = Path(tmp) / "kf.ckpt", Path(tmp) / "kf.pt2"
        trained = make_filter()
        with torch.no_grad():
            trained.R = torch.tensor([[0.4, 0.05], [0.05, 0.6]], dtype=F64)  # "learned"
        torch.save(trained.state_dict(), ckpt)

        kf = make_filter()  # deployment side: same architecture, weights from the checkpoint
        kf.load_state_dict(torch.load(ckpt))
        kf.eval()
        example = data(B, T, 0)
        t0 = time.perf_counter()
        ep = torch.export.export(tl.DeployedFilter(kf), example)
        t_export = time.perf_counter() - t0
        t0 = time.perf_counter()
        torch.export.save(ep, prog)
        t_save = time.perf_counter() - t0
        t0 = time.perf_counter()
        run = torch.export.load(prog).module()
        t_load = time.perf_counter() - t0

        y, dt = data(B, T, 1)  # new tracks
        with torch.no_grad():
            ll, mean = run(y, dt)
            ref = kf(y, dt)
            t_prog = median_ms(lambda: run(y, dt))
            t_eager = median_ms(lambda: kf(y, dt))
        d_ll = float((ll - ref.log_likelihood).abs().max())
        d_mean = float((mean - ref.mean).abs().max())
        print(
            f"| {B} | {T} | {len(ep.graph.nodes)} | {t_export:.1f} | {t_save:.2f} | {t_load:.2f} | "
            f"{t_prog:.2f} | {t_eager:.2f} | {t_eager / t_prog:.2f}× | {d_ll:.1e} / {d_mean:.1e} |",
            flush=True,
        )
        if aoti:
            AOTI_ROWS.append(bench_aoti(ep, Path(tmp) / "kf_aoti.pt2", kf, B, T, t_eager))


AOTI_ROWS: list[str] = []


def filterpy_sequence(y: torch.Tensor, dt: torch.Tensor, R: object) -> Callable[[], None]:
    """filterpy's predict + update over the one track of y (1, T, 2), dt (1, T) (the filter of
    :func:`bench_online.filterpy_cv`, q = 1 as :func:`make_filter`'s)."""
    step, _ = filterpy_cv(R, q=1.0)
    ys, dts = y[0].numpy(), dt[0].numpy()

    def run() -> None:
        for k in range(ys.shape[0]):
            step(ys[k : k + 1], dts[k : k + 1])

    return run


def bench_aoti(
    ep: torch.export.ExportedProgram, path: Path, kf: tl.KalmanFilter, B: int, T: int, t_eager: float
) -> str:
    """AOTInductor: the exported program compiled ahead of time into a .pt2 package (C++
    kernels; needs a C++ compiler to build, only torch to load and run), vs eager and filterpy."""
    t0 = time.perf_counter()
    torch._inductor.aoti_compile_and_package(ep, package_path=str(path))
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    runner = torch._inductor.aoti_load_package(str(path))
    t_load = time.perf_counter() - t0
    y, dt = data(B, T, 2)  # new tracks again
    with torch.no_grad():
        ll, mean = runner(y, dt)
        ref = kf(y, dt)
        t_run = median_ms(lambda: runner(y, dt))
    d_ll = float((ll - ref.log_likelihood).abs().max())
    d_mean = float((mean - ref.mean).abs().max())
    t_fp = median_ms(filterpy_sequence(y, dt, kf.R.detach().numpy())) if B == 1 else float("nan")
    fp = f"{t_fp:.2f} | {t_fp / t_run:.2f}×" if B == 1 else "– | –"
    return (
        f"| {B} | {T} | {t_build:.1f} | {t_load:.3f} | {t_run:.2f} | {t_eager:.2f} | {t_eager / t_run:.2f}× | "
        f"{fp} | {d_ll:.1e} / {d_mean:.1e} |"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-aoti", action="store_true", help="skip the AOTInductor package (needs a C++ compiler)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    with saved("bench_deploy.txt"):
        run(args)


def run(args: argparse.Namespace) -> None:
    print(f"# deploy benchmark ({machine_line()})")
    bench_compile()
    print("\n### checkpoint → torch.export → save → load → run (float64, no grad)\n")
    print(
        "| B | T | graph nodes | export (s) | save (s) | load (s) | exported run (ms) | eager (ms) | "
        "eager / exported | max |Δ| ll / means |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for B, T in ((1, 200), (100, 200)):
        bench_export(B, T, aoti=B == 1 and not args.no_aoti)  # B = 100: 12.8 k nodes, minutes to build
    if AOTI_ROWS:
        print("\n### exported program → AOTInductor package (torch._inductor.aoti_compile_and_package) → load → run\n")
        print(
            "| B | T | build (s) | load (s) | packaged run (ms) | eager (ms) | eager / packaged | filterpy (ms) | "
            "filterpy / packaged | max |Δ| ll / means |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|")
        print("\n".join(AOTI_ROWS))
    print(f"\nat the end: {machine_line()}")


if __name__ == "__main__":
    main()
