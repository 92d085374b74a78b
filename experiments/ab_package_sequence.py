"""The packaged sequence filter (AOTInductor, a static (1, T) bucket) of bench_online.py's float64
constant-velocity filter, A/B between checkouts, against filterpy's predict + update loop.

``--build PATH`` exports ``DeployedFilter(kf)`` at B = 1, T = ``--T`` with the torchsde_lti on
the path and packages it (``tl.compile_package``), with the eager log-likelihood beside it
(``PATH.data``); ``--time PATH ...`` loads the packages in one process (they run with torch
alone) and times them in alternation with filterpy over the same reports: 1 intra-op thread,
each repeat 20 calls of each package and 3 filterpy loops, CPU time; per package the median
over repeats and its ratio to filterpy, and the largest difference from the eager result::

    PYTHONPATH=/path/to/old python experiments/ab_package_sequence.py --build /tmp/old.pt2
    PYTHONPATH=$PWD python experiments/ab_package_sequence.py --build /tmp/new.pt2
    python experiments/ab_package_sequence.py --time /tmp/new.pt2 /tmp/old.pt2
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

import torchsde_lti as tl

sys.path.insert(0, str(Path(__file__).parent))
from bench_online import build_filter, filterpy_filter, filterpy_step  # noqa: E402


def reports(T: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    y = torch.randn(1, T, 2, generator=g, dtype=torch.float64).cumsum(1)
    return y, 0.2 + torch.rand(1, T, generator=g, dtype=torch.float64)


def build(path: str, T: int) -> None:
    kf = build_filter(False)
    y, dt = reports(T)
    with torch.no_grad():
        program = torch.export.export(tl.DeployedFilter(kf).eval(), (y, dt))
        log_likelihood = kf(y, dt).log_likelihood
    tl.compile_package(program, path)
    torch.save((y, dt, log_likelihood), path + ".data")


def time_packages(paths: list[str], repeats: int) -> None:
    torch.set_num_threads(1)
    runs = [tl.load_package(p) for p in paths]
    y, dt, log_likelihood = torch.load(paths[0] + ".data")
    zs, hs = y[0].numpy()[:, :, None], dt[0].tolist()

    def filterpy_loop() -> None:
        f = filterpy_filter()
        for z, h in zip(zs, hs):
            filterpy_step(f, z, h)

    times: list[list[float]] = [[] for _ in runs]
    fp: list[float] = []
    for _ in range(repeats):
        for i, run in enumerate(runs):
            t0 = time.process_time()
            for _ in range(20):
                run(y, dt)
            times[i].append((time.process_time() - t0) / 20)
        t0 = time.process_time()
        for _ in range(3):
            filterpy_loop()
        fp.append((time.process_time() - t0) / 3)
    t_fp = statistics.median(fp)
    print(f"B = 1, T = {y.shape[1]}, float64; filterpy loop {t_fp * 1e3:.2f} ms (median of {repeats})")
    print("| package | median | × filterpy's time | max |Δ log-likelihood| vs eager |")
    print("|---|---:|---:|---:|")
    for path, run, ts in zip(paths, runs, times):
        diff = float((run(y, dt)[0] - log_likelihood).abs().max())
        t = statistics.median(ts)
        print(f"| {path} | {t * 1e3:.3f} ms | {t_fp / t:.2f}× faster | {diff:.1e} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--build", metavar="PATH")
    ap.add_argument("--time", nargs="+", metavar="PATH")
    ap.add_argument("--T", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    if args.build:
        build(args.build, args.T)
    if args.time:
        time_packages(args.time, args.repeats)


if __name__ == "__main__":
    main()
