"""Cost of two KalmanFilter options against the default path (prints a markdown table).

* ``algorithm="square_root"`` vs the default Joseph-form filter: 2-D constant velocity, irregular dt.
* ``unique_dt=True`` vs discretising every step: 2-D Singer model (its F is not nilpotent, so
  every step needs scaling and doubling) with gaps quantised to whole multiples of 0.5 s,
  as real logs (AIS: whole seconds) often are.

B = 1000 tracks, T = 200 steps, float64 and float32, one thread, best of N wall-clock runs of
the forward pass and of forward + backward of the summed log-likelihood.

    python experiments/bench_filter_options.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import torch

import torchsde_lti as tl


def best_time(fn: Callable[[], None], repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def forward_and_training(kf: tl.KalmanFilter, y: torch.Tensor, dt: torch.Tensor, repeats: int) -> tuple[float, float]:
    def forward() -> None:
        with torch.no_grad():
            kf(y, dt)

    def training() -> None:
        kf.zero_grad()
        kf(y, dt).log_likelihood.sum().backward()

    return best_time(forward, repeats), best_time(training, repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)
    B, T = 1000, 200
    gen = torch.Generator().manual_seed(0)
    rows = []
    for dtype in (torch.float64, torch.float32):
        y = torch.randn(B, T, 2, generator=gen, dtype=dtype).cumsum(1)
        dt_irregular = torch.rand(B, T, generator=gen, dtype=dtype) * 2
        dt_quantised = 0.5 * torch.randint(1, 41, (B, T), generator=gen).to(dtype)

        cv = tl.models.constant_velocity(dim=2, q=1.0).to(dtype)
        H = tl.models.position_observation(cv)
        R = 0.25 * torch.eye(2, dtype=dtype)
        base = forward_and_training(tl.KalmanFilter(cv, H, R), y, dt_irregular, args.repeats)
        sqrt = forward_and_training(tl.KalmanFilter(cv, H, R, algorithm="square_root"), y, dt_irregular, args.repeats)
        rows.append(('algorithm="square_root" (constant velocity, irregular dt)', dtype, base, sqrt))

        singer = tl.models.singer(alpha=0.5, q=1.0, dim=2).to(dtype)
        H = tl.models.position_observation(singer)
        every = forward_and_training(tl.KalmanFilter(singer, H, R), y, dt_quantised, args.repeats)
        unique = forward_and_training(tl.KalmanFilter(singer, H, R, unique_dt=True), y, dt_quantised, args.repeats)
        distinct = int(torch.unique(dt_quantised).numel())
        rows.append((f"unique_dt=True (Singer, {distinct} distinct gaps)", dtype, every, unique))

    print(f"B = {B}, T = {T}, 1 thread, best of {args.repeats}; seconds (option / default)\n")
    print(
        "| option | dtype | forward: default | forward: option | ratio | fwd+bwd: default | fwd+bwd: option | ratio |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for name, dtype, (f0, t0), (f1, t1) in rows:
        print(
            f"| {name} | {str(dtype).replace('torch.', '')} | {f0:.3f} | {f1:.3f} | {f1 / f0:.2f}× "
            f"| {t0:.3f} | {t1:.3f} | {t1 / t0:.2f}× |"
        )


if __name__ == "__main__":
    main()
