"""Benchmark: batched Kalman filtering throughput (track·steps per second) on CPU.

2-D constant-velocity model (n = 4, m = 2), T = 200 steps, B tracks, regular and irregular
dt, float32 and float64. Contestants, run side by side in one process (round-robin over
repeats so machine load hits all of them alike; wall-clock medians):

- ``ours``            tl.KalmanFilter(sde, H, R)(y, dt) — the default (the sequential
                      loop), including the exact discretisation of every step;
- ``ours-scan``       the same with ``algorithm="scan"`` (associative scan);
- ``torch-kf+VL``     torch-kf, per-step (A, Q) from naive Van Loan (torch.matrix_exp of the
                      8×8 block for all B·T steps at once), predict/update loop;
- ``torch-kf+CF``     torch-kf fed closed-form constant-velocity (A, Q) (irregular dt);
- ``torch-kf``        torch-kf's own ``filter`` with constant (A, Q) (regular dt);
- ``simdkalman``      numpy, constant (A, Q) (regular dt);
- ``filterpy``        filterpy in a Python loop over one track (throughput per track; B
                      tracks take B times as long).

Training step: -log-likelihood forward + backward w.r.t. the process-noise intensity q and
(ours) R, irregular dt: ours vs torch-kf + naive Van Loan (and + closed form).

Writes experiments/results/bench_filter[_quick].md (the table).
Usage: python experiments/bench_filter.py [--quick] [--threads N] [--clock wall|cpu]
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from _timing import interleaved_s

import torchsde_lti as tl

T = 200
N, M = 4, 2
Q_INT = 1.0
R_VAR = 0.5
P0_VAR = 100.0
RESULTS = Path(__file__).resolve().parent / "results"


# ----------------------------------------------------------------------------------------
# data and model matrices
# ----------------------------------------------------------------------------------------


def make_data(B: int, regular: bool, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    dt = np.ones((B, T)) if regular else rng.uniform(0.05, 2.0, size=(B, T))
    vel = np.cumsum(rng.standard_normal((B, T, 2)) * np.sqrt(dt)[..., None], axis=1)
    pos = np.cumsum(vel * dt[..., None], axis=1)
    y = pos + math.sqrt(R_VAR) * rng.standard_normal((B, T, 2))
    return y, dt


def cv_continuous(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """F (4, 4) and L Lᵀ pattern for the [x, vx, y, vy] constant-velocity model."""
    F = torch.zeros(N, N, dtype=dtype)
    F[0, 1] = F[2, 3] = 1.0
    W = torch.zeros(N, N, dtype=dtype)
    W[1, 1] = W[3, 3] = 1.0
    return F, W


def van_loan(F: torch.Tensor, W: torch.Tensor, dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Naive Van Loan: expm([[F, W], [0, -Fᵀ]] dt) = [[A, X], [0, A⁻ᵀ]], Q = X Aᵀ."""
    top = torch.cat([F, W], -1)
    bot = torch.cat([torch.zeros_like(F), -F.mT], -1)
    C = torch.cat([top, bot], -2) * dt[..., None, None]
    E = torch.matrix_exp(C)
    A = E[..., :N, :N]
    return A, E[..., :N, N:] @ A.mT


def cv_closed_form(q: torch.Tensor | float, dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A = [[1, dt], [0, 1]], Q = q [[dt³/3, dt²/2], [dt²/2, dt]] per axis (state [x, vx, y, vy])."""
    one, zero = torch.ones_like(dt), torch.zeros_like(dt)
    a = torch.stack([torch.stack([one, dt], -1), torch.stack([zero, one], -1)], -2)
    b = q * torch.stack([torch.stack([dt**3 / 3, dt**2 / 2], -1), torch.stack([dt**2 / 2, dt], -1)], -2)
    z = torch.zeros_like(a)
    A = torch.cat([torch.cat([a, z], -1), torch.cat([z, a], -1)], -2)
    Q = torch.cat([torch.cat([b, z], -1), torch.cat([z, b], -1)], -2)
    return A, Q


def observation(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    H = torch.zeros(M, N, dtype=dtype)
    H[0, 0] = H[1, 2] = 1.0
    return H, R_VAR * torch.eye(M, dtype=dtype)


# ----------------------------------------------------------------------------------------
# contestants: each returns a zero-argument callable doing one full run
# ----------------------------------------------------------------------------------------


def ours(y: torch.Tensor, dt: torch.Tensor, regular: bool, algorithm: str = "sequential") -> Callable[[], object]:
    dtype = y.dtype
    cv = tl.models.constant_velocity(dim=2, q=Q_INT, dtype=dtype)
    H, R = observation(dtype)
    kf = tl.KalmanFilter(cv, H, R, P0=P0_VAR * torch.eye(N, dtype=dtype), algorithm=algorithm)
    dts = dt[0] if regular else dt  # regular grid: one (T,) dt shared by all tracks

    def run() -> object:
        with torch.no_grad():
            return kf(y, dts).mean

    return run


def torchkf_per_step(y: torch.Tensor, dt: torch.Tensor, matrices: str) -> Callable[[], object]:
    import torch_kf

    dtype = y.dtype
    H, R = observation(dtype)
    F, W = cv_continuous(dtype)
    kf = torch_kf.KalmanFilter(torch.eye(N, dtype=dtype), H, torch.eye(N, dtype=dtype), R)
    meas = y.unsqueeze(-1)

    def run() -> object:
        with torch.no_grad():
            A, Q = van_loan(F, Q_INT * W, dt) if matrices == "VL" else cv_closed_form(Q_INT, dt)
            state = torch_kf.GaussianState(
                torch.zeros(y.shape[0], N, 1, dtype=dtype), P0_VAR * torch.eye(N, dtype=dtype).expand(y.shape[0], N, N)
            )
            means, covs = [], []
            for k in range(T):
                state = kf.predict(state, process_matrix=A[:, k], process_noise=Q[:, k])
                state = kf.update(state, meas[:, k])
                means.append(state.mean)
                covs.append(state.covariance)
            return torch.stack(means, 1), torch.stack(covs, 1)

    return run


def torchkf_regular(y: torch.Tensor, dt: torch.Tensor) -> Callable[[], object]:
    import torch_kf

    dtype = y.dtype
    H, R = observation(dtype)
    A, Q = cv_closed_form(Q_INT, dt[0, 0])
    kf = torch_kf.KalmanFilter(A, H, Q, R)
    meas = y.transpose(0, 1).unsqueeze(-1).contiguous()  # (T, B, m, 1)

    def run() -> object:
        with torch.no_grad():
            state = torch_kf.GaussianState(
                torch.zeros(y.shape[0], N, 1, dtype=dtype),
                P0_VAR * torch.eye(N, dtype=dtype).expand(y.shape[0], N, N).clone(),
            )
            return kf.filter(state, meas, update_first=False, return_all=True)

    return run


def simdkalman_regular(y: np.ndarray, dt: np.ndarray) -> Callable[[], object]:
    import simdkalman

    A, Q = (x.numpy() for x in cv_closed_form(Q_INT, torch.tensor(float(dt[0, 0]), dtype=torch.float64)))
    H, R = (x.numpy() for x in observation(torch.float64))
    kf = simdkalman.KalmanFilter(state_transition=A, process_noise=Q, observation_model=H, observation_noise=R)

    def run() -> object:
        return kf.compute(
            y,
            0,
            initial_value=np.zeros(N),
            initial_covariance=P0_VAR * np.eye(N),
            smoothed=False,
            filtered=True,
            states=True,
            covariances=True,
            observations=False,
        )

    return run


def filterpy_one_track(y: np.ndarray, dt: np.ndarray) -> Callable[[], object]:
    from filterpy.kalman import KalmanFilter as FPKalman

    A, Q = (x.numpy() for x in cv_closed_form(Q_INT, torch.as_tensor(dt[0], dtype=torch.float64)))
    H, R = (x.numpy() for x in observation(torch.float64))
    y0 = y[0]

    def run() -> object:
        kf = FPKalman(dim_x=N, dim_z=M)
        kf.x = np.zeros(N)
        kf.P = P0_VAR * np.eye(N)
        kf.H, kf.R = H, R
        out = []
        for k in range(T):
            kf.predict(F=A[k], Q=Q[k])
            kf.update(y0[k])
            out.append(kf.x.copy())
        return out

    return run


# training step -------------------------------------------------------------------------


def ours_train(y: torch.Tensor, dt: torch.Tensor) -> Callable[[], object]:
    dtype = y.dtype
    cv = tl.models.constant_velocity(dim=2, q=Q_INT, dtype=dtype)
    H, R = observation(dtype)
    kf = tl.KalmanFilter(cv, H, R, P0=P0_VAR * torch.eye(N, dtype=dtype), learn=("R",))
    params = list(kf.parameters())
    assert len(params) == 2  # q (through its Positive parametrisation) and R

    def run() -> object:
        for p in params:
            p.grad = None
        loss = -kf(y, dt).log_likelihood.sum()
        loss.backward()
        return loss

    return run


def torchkf_train(y: torch.Tensor, dt: torch.Tensor, matrices: str) -> Callable[[], object]:
    import torch_kf

    dtype = y.dtype
    H, R = observation(dtype)
    F, W = cv_continuous(dtype)
    log_q = torch.zeros((), dtype=dtype, requires_grad=True)
    kf = torch_kf.KalmanFilter(torch.eye(N, dtype=dtype), H, torch.eye(N, dtype=dtype), R)
    meas = y.unsqueeze(-1)

    def run() -> object:
        log_q.grad = None
        q = log_q.exp()
        A, Q = van_loan(F, q * W, dt) if matrices == "VL" else cv_closed_form(q, dt)
        state = torch_kf.GaussianState(
            torch.zeros(y.shape[0], N, 1, dtype=dtype), P0_VAR * torch.eye(N, dtype=dtype).expand(y.shape[0], N, N)
        )
        ll = 0.0
        for k in range(T):
            state = kf.predict(state, process_matrix=A[:, k], process_noise=Q[:, k])
            proj = kf.project(state)
            ll = ll + proj.log_likelihood(meas[:, k])
            state = kf.update(state, meas[:, k], projection=proj)
        loss = -ll.sum()
        loss.backward()
        return loss

    return run


# ----------------------------------------------------------------------------------------
# driver
# ----------------------------------------------------------------------------------------


#: --clock: "wall" the median wall time, "cpu" the minimum process CPU time (one thread), which
#: other processes competing for the cores hardly move.
CLOCKS: dict[str, tuple[Callable[[], float], Callable[[list[float]], float]]] = {
    "wall": (time.perf_counter, statistics.median),
    "cpu": (time.process_time, min),
}


def add_rows(rows: list[dict], task: str, setting: str, dname: str, B: int, res_tp: dict[str, float]) -> None:
    """One table row per contestant of a cell (throughputs ``res_tp`` in track·steps/s), printed."""
    for name, tp in res_tp.items():
        rows.append(
            dict(task=task, setting=setting, dtype=dname, B=B, contestant=name, ms=B * T / tp * 1e3, tp=tp,
                 ratio=res_tp["ours"] / tp)
        )  # fmt: skip
    line = "  ".join(f"{k}={v / 1e6:.3g}M/s" for k, v in res_tp.items())
    print(f"{task} {setting:9s} {dname} B={B:6d} {line}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="B ≤ 1000, float64 only, fewer repeats")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (clock=cpu forces 1)")
    ap.add_argument(
        "--clock",
        choices=("wall", "cpu"),
        default="wall",
        help="wall: median wall time; cpu: best single-thread CPU time (use on a loaded machine)",
    )
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    if args.clock == "cpu":
        args.threads = 1
    torch.set_num_threads(args.threads)
    clock, agg = CLOCKS[args.clock]
    batches = [1, 100, 1000] if args.quick else [1, 100, 1000, 10_000]
    dtypes = [torch.float64] if args.quick else [torch.float64, torch.float32]
    repeats = 3 if args.quick else 5
    rows: list[dict] = []

    # filterpy: one track, throughput per track (independent of B)
    fp = {}
    for regular in (False, True):
        y1, dt1 = make_data(1, regular)
        one_track = {"filterpy": filterpy_one_track(y1, dt1)}
        fp[regular] = T / interleaved_s(one_track, repeats, budget_s=5.0, clock=clock, agg=agg)["filterpy"]

    for dtype in dtypes:
        dname = str(dtype).replace("torch.", "")
        for regular in (False, True):
            setting = "regular" if regular else "irregular"
            for B in batches:
                y_np, dt_np = make_data(B, regular)
                y = torch.tensor(y_np, dtype=dtype)
                dt = torch.tensor(dt_np, dtype=dtype)
                big = B >= 10_000
                fns: dict[str, Callable[[], object]] = {"ours": ours(y, dt, regular)}
                if not big:  # the scan does O(T) extra matrix work; at B = 10⁴ it only loses
                    fns["ours-scan"] = ours(y, dt, regular, algorithm="scan")
                if regular:
                    fns["torch-kf"] = torchkf_regular(y, dt)
                    if dtype == torch.float64:
                        fns["simdkalman"] = simdkalman_regular(y_np, dt_np)
                else:
                    if not big:  # 2·10⁶ 8×8 matrix exponentials: tens of seconds per run
                        fns["torch-kf+VL"] = torchkf_per_step(y, dt, "VL")
                    fns["torch-kf+CF"] = torchkf_per_step(y, dt, "CF")
                res = interleaved_s(fns, 2 if big else repeats, int(not big), budget_s=20.0, clock=clock, agg=agg)
                res_tp = {k: B * T / v for k, v in res.items()}
                if dtype == torch.float64:
                    res_tp["filterpy (1 track)"] = fp[regular]
                add_rows(rows, "filter", setting, dname, B, res_tp)

    # training step (forward + backward), irregular dt
    train_batches = [100, 1000]
    for dtype in dtypes:
        dname = str(dtype).replace("torch.", "")
        for B in train_batches:
            y_np, dt_np = make_data(B, regular=False)
            y = torch.tensor(y_np, dtype=dtype)
            dt = torch.tensor(dt_np, dtype=dtype)
            fns = {
                "ours": ours_train(y, dt),
                "torch-kf+VL": torchkf_train(y, dt, "VL"),
                "torch-kf+CF": torchkf_train(y, dt, "CF"),
            }
            res = interleaved_s(fns, 3, budget_s=30.0, clock=clock, agg=agg)
            res_tp = {k: B * T / v for k, v in res.items()}
            add_rows(rows, "train step", "irregular", dname, B, res_tp)

    write_outputs(rows, args)


def write_outputs(rows: list[dict], args: argparse.Namespace) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    clock = "wall-clock medians" if args.clock == "wall" else "best-of-N process CPU time"
    head = (
        f"T = {T}, 2-D constant velocity (n = 4, m = 2); {clock}, torch {torch.__version__}, "
        f"{args.threads} thread(s), {platform.machine()}; track·steps/s (higher is better); "
        "'ours ×' = our throughput / the contestant's. filterpy is one track in a Python loop "
        "(its throughput does not grow with B).\n\n"
    )
    lines = [
        "| task | dt | dtype | B | contestant | time (ms) | track·steps/s | ours × |",
        "|---|---|---|---:|---|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['task']} | {r['setting']} | {r['dtype']} | {r['B']} | {r['contestant']} | "
            f"{r['ms']:.1f} | {r['tp']:.3g} | {r['ratio']:.2f} |"
        )
    table = "\n".join(lines)
    print()
    print(table)
    suffix = "_quick" if args.quick else ""
    (args.out / f"bench_filter{suffix}.md").write_text(
        "# Kalman filter benchmark (experiments/bench_filter.py"
        + (" --quick" if args.quick else "")
        + ")\n\n"
        + head
        + table
        + "\n"
    )


if __name__ == "__main__":
    main()
