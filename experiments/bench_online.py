"""Online step and IMM cycle timings, paired A/B between two checkouts, at 1 intra-op thread.

Rows (float64, 2-D models observing the positions; CPU-time medians, in µs or ms):

- ``kf.step`` at B = 1, eager, value checks on and off: constant velocity (target ≤ 300 µs)
  and integrated OU (target ≤ 500 µs);
- ``kf.step`` at B = 1000 tracks, each with its own gap, against a loop over 1000 filterpy
  filters (predict + update with the closed-form CV A(dt), Q(dt)): target ≥ 20×;
- the IMM sequence filter (3 modes, 2,000 tracks × 50 steps, no gradients) against the 3
  Kalman filters of its modes on the same data (algorithm="sequential"): target ≤ 3×.

Each row runs in a fresh process per checkout, the checkouts alternating (A, B, A, B, …), so
both see the same load; the figure is the median over the rounds of each process's median.

    python experiments/bench_online.py --trees /path/to/main . --rounds 3
    python experiments/bench_online.py --trees .            # this checkout only
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

ROWS = ("step_cv_b1", "step_cv_b1_nocheck", "step_iou_b1", "step_iou_b1_nocheck", "step_cv_b1000",
        "filterpy_b1000", "imm_2000x50", "kf3_2000x50")  # fmt: skip


def _median_cpu(fn, repeat: int, inner: int) -> float:
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.process_time()
        for _ in range(inner):
            fn()
        times.append((time.process_time() - t0) / inner)
    return statistics.median(times)


def measure(row: str) -> float:
    """Seconds of one call of ``row`` (run in a child process at 1 thread)."""
    import numpy as np
    import torch

    import torchsde_lti as tl

    torch.set_num_threads(1)
    F64 = torch.float64
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64)
    R = torch.tensor([[0.3, 0.1], [0.1, 0.4]], dtype=F64)
    g = torch.Generator().manual_seed(0)

    def kf_of(model: str, **kw) -> tl.KalmanFilter:
        sde = (
            tl.models.constant_velocity(dim=2, q=0.8, dtype=F64)
            if model == "cv"
            else tl.models.integrated_ou(0.7, 0.5, dim=2, dtype=F64)
        )
        return tl.KalmanFilter(sde, H, R, P0=10 * torch.eye(4, dtype=F64), **kw)

    if row.startswith("step_"):
        _, model, b, *check = row.split("_")
        B = int(b[1:])
        kf = kf_of(model)
        kf.validate_args = not check
        state = kf.initial_state(B if B > 1 else ())
        y = torch.randn(*state.mean.shape[:-1], 2, generator=g, dtype=F64)
        dt = torch.rand(state.mean.shape[:-1], generator=g, dtype=F64) + 0.1
        with torch.no_grad():
            return _median_cpu(lambda: kf.step(state, y, dt), 41 if B == 1 else 15, 50 if B == 1 else 3)
    if row == "filterpy_b1000":
        from filterpy.kalman import KalmanFilter as FKF

        filters = []
        for _ in range(1000):
            f = FKF(dim_x=4, dim_z=2)
            f.x, f.P, f.H, f.R = np.zeros((4, 1)), 10 * np.eye(4), H.numpy(), R.numpy()
            filters.append(f)
        ys, dts = np.random.default_rng(0).normal(size=(1000, 2)), np.random.default_rng(1).random(1000) + 0.1

        def loop() -> None:
            for f, z, h in zip(filters, ys, dts):
                A1 = np.array([[1.0, h], [0.0, 1.0]])
                Q1 = 0.8 * np.array([[h**3 / 3, h**2 / 2], [h**2 / 2, h]])
                f.F, f.Q = np.kron(np.eye(2), A1), np.kron(np.eye(2), Q1)
                f.predict()
                f.update(z)

        return _median_cpu(loop, 7, 1)
    # the IMM cycle vs the Kalman filters of its 3 modes, 2,000 tracks × 50 steps
    y = torch.randn(2000, 50, 2, generator=g, dtype=F64).cumsum(1)
    dt = torch.rand(2000, 50, generator=g, dtype=F64) + 0.1
    sdes = [
        tl.models.constant_velocity(dim=2, q=0.5, dtype=F64),
        tl.models.integrated_ou(1.5, 0.05, dim=2, dtype=F64),
        tl.models.integrated_ou(0.2, 2.0, dim=2, dtype=F64),
    ]
    if row == "imm_2000x50":
        rates = torch.full((3, 3), 0.1, dtype=F64)
        imm = tl.IMMFilter(sdes, H, R, rates, P0=10 * torch.eye(4, dtype=F64))
        with torch.no_grad():
            return _median_cpu(lambda: imm(y, dt), 5, 1)
    kfs = [tl.KalmanFilter(s, H, R, P0=10 * torch.eye(4, dtype=F64), algorithm="sequential") for s in sdes]
    with torch.no_grad():
        return _median_cpu(lambda: [kf(y, dt) for kf in kfs], 5, 1)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--trees", nargs="+", default=["."], help="checkouts to compare (paired, alternating)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--rows", nargs="+", default=list(ROWS))
    parser.add_argument("--measure", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(args.measure)))
        return
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    results: dict[tuple[str, str], list[float]] = {}
    for row in args.rows:
        for _ in range(args.rounds):
            for tree in args.trees:
                run_env = {**env, "PYTHONPATH": os.path.abspath(tree)}
                out = subprocess.run(
                    [sys.executable, __file__, "--measure", row],
                    env=run_env,
                    capture_output=True,
                    text=True,
                    check=True,
                )
                results.setdefault((row, tree), []).append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f"load: {os.getloadavg()}; 1 thread; CPU-time medians over {args.rounds} alternating rounds")
    print("| row | " + " | ".join(args.trees) + " |")
    print("|---|" + "---|" * len(args.trees))
    for row in args.rows:
        cells = []
        for tree in args.trees:
            t = statistics.median(results[(row, tree)])
            cells.append(f"{t * 1e6:.0f} µs" if t < 1e-2 else f"{t * 1e3:.1f} ms")
        print(f"| {row} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
