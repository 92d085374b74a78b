r"""The sequential filter over many tracks, all at once or chunk by chunk of tracks (sets
``filters.sequential.CHUNKED_MIN_BYTES`` and ``CHUNK_BYTES``).

Per-track transitions and noises (irregular dt per track: the covariance recursion runs over
every track), constant velocity in 2-D (n = 4) and 1-D (n = 2), 10 % of the reports missing:
``kalman_filter`` on given (B, T, n, n) matrices, and the ``KalmanFilter`` module (its
discretisation, whose results are views of batch-last storage, then the filter).
Each cell alternates the settings within every repeat (paired) and reports the median wall time
per call; the ratio column is chunked / all at once. Forward without autograd (inference) and
forward + backward of the summed log-likelihood with respect to A and Q (training).

Chunks are taken at one intra-op thread only (the caller's setting, or a busy machine's): at
two threads on a shared machine, chunks of 256 KiB made one forward + backward 18× slower
(a parallel region per small op). With ``--threads 2`` the columns show that setting's own
behaviour (all at once unless the machine is busy).

    python experiments/filter_chunks.py [--threads 1] [--repeats 5] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import torch

import torchsde_lti as tl
from torchsde_lti.filters import sequential

OFF = 1 << 62


def problem(n_axes: int, B: int, T: int, dtype: torch.dtype):
    g = torch.Generator().manual_seed(0)
    sde = tl.models.constant_velocity(dim=n_axes, q=1.0).to(dtype)
    H = tl.models.position_observation(sde).to(dtype)
    F, L, Qc = sde.F, sde.L, sde.Qc
    dt = torch.rand(B, T, generator=g, dtype=dtype) + 0.1
    d = tl.discretize(F, L, Qc, dt)
    m = H.shape[0]
    y = torch.randn(B, T, m, generator=g, dtype=dtype).cumsum(1)
    y[torch.rand(B, T, generator=g) < 0.1] = float("nan")
    n = F.shape[-1]
    R = 0.25 * torch.eye(m, dtype=dtype)
    return y, d.A.contiguous(), d.Q.contiguous(), H, R, torch.zeros(n, dtype=dtype), 10.0 * torch.eye(n, dtype=dtype)


def module_problem(n_axes: int, B: int, T: int, dtype: torch.dtype):
    g = torch.Generator().manual_seed(0)
    sde = tl.models.constant_velocity(dim=n_axes, q=1.0)
    H = tl.models.position_observation(sde)
    kf = tl.KalmanFilter(sde, H, 0.25 * torch.eye(H.shape[0])).to(dtype)
    y = torch.randn(B, T, H.shape[0], generator=g, dtype=dtype).cumsum(1)
    y[torch.rand(B, T, generator=g) < 0.1] = float("nan")
    return kf, y, torch.rand(B, T, generator=g, dtype=dtype) + 0.1


def call(args, backward: bool) -> None:
    if len(args) == 3:  # the module: discretisation (batch-last views) and filter
        kf, y, dt = args
        if backward:
            kf.zero_grad()
            kf(y, dt).log_likelihood.sum().backward()
        else:
            with torch.no_grad():
                kf(y, dt)
        return
    y, A, Q, H, R, m0, P0 = args
    if backward:
        A, Q = A.detach().requires_grad_(), Q.detach().requires_grad_()
        tl.kalman_filter(y, A, Q, H, R, m0, P0, algorithm="sequential").log_likelihood.sum().backward()
    else:
        with torch.no_grad():
            tl.kalman_filter(y, A, Q, H, R, m0, P0, algorithm="sequential")


def timed(args, backward: bool, setting: tuple[int, int]) -> float:
    sequential.CHUNKED_MIN_BYTES, sequential.CHUNK_BYTES = setting
    t0 = time.perf_counter()
    call(args, backward)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, nargs="+", default=[1])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    # (chunked from 1 MiB of covariances on, to see where chunks start to pay)
    settings = {
        "all at once": (OFF, OFF),
        "256 KiB": (1 << 20, 1 << 18),
        "1 MiB": (1 << 20, 1 << 20),
        "4 MiB": (1 << 20, 1 << 22),
    }
    lines = [
        f"# Sequential filter, all tracks at once vs chunks of tracks (torch {torch.__version__}, load {os.getloadavg()[0]:.2f})\n",
        "| call | threads | n | dtype | tracks | T | pass | "
        + " | ".join(f"{k} (ms)" for k in settings)
        + " | best chunked / at once |",
        "|---" * (8 + len(settings)) + "|",
    ]
    print("\n".join(lines), flush=True)
    cells = [
        ("kalman_filter", 2, 262144, 8, torch.float32),
        ("kalman_filter", 2, 262144, 4, torch.float64),
        ("kalman_filter", 2, 65536, 8, torch.float64),
        ("kalman_filter", 1, 262144, 8, torch.float64),
        ("kalman_filter", 2, 4096, 50, torch.float64),
        ("KalmanFilter", 2, 262144, 8, torch.float32),
        ("KalmanFilter", 2, 65536, 8, torch.float64),
        ("KalmanFilter", 2, 16384, 16, torch.float64),
    ]
    for threads in a.threads:
        torch.set_num_threads(threads)
        for what, n_axes, B, T, dtype in cells:
            args = problem(n_axes, B, T, dtype) if what == "kalman_filter" else module_problem(n_axes, B, T, dtype)
            for backward in (False, True):
                for s in settings.values():
                    timed(args, backward, s)  # warm-up
                times: dict[str, list[float]] = {k: [] for k in settings}
                for r in range(a.repeats):
                    order = list(settings) if r % 2 == 0 else list(settings)[::-1]
                    for k in order:
                        times[k].append(timed(args, backward, settings[k]))
                med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
                best = min(v for k, v in med.items() if k != "all at once")
                row = (
                    f"| {what} | {threads} | {2 * n_axes} | {str(dtype)[6:]} | {B} | {T} | {'fwd+bwd' if backward else 'fwd'} | "
                    + " | ".join(f"{v:.0f}" for v in med.values())
                    + f" | {best / med['all at once']:.2f} |"
                )
                lines.append(row)
                print(row, flush=True)
    sequential.CHUNKED_MIN_BYTES, sequential.CHUNK_BYTES = 1 << 23, 1 << 20
    lines.append(f"\nload at end {os.getloadavg()[0]:.2f}")
    if a.out:
        a.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
