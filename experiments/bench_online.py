"""Online step, checked sequence and IMM cycle timings, paired A/B between checkouts, 1 thread.

Rows (float64, 2-D models observing the positions, R with a correlation; CPU-time medians):

- ``step_cv_b1`` / ``step_iou_b1`` (and ``_nocheck``): ``kf.step`` at one track, eager, value
  checks on (off); targets (issue 37) ≤ 300 µs constant velocity, ≤ 500 µs integrated OU;
- ``step_cv_b1000`` against ``filterpy_b1000``, a loop over 1000 filterpy filters (predict +
  update with the closed-form constant-velocity A(dt), Q(dt)): target ≥ 20×;
- ``aoti_step_b1`` against ``filterpy_b1``: the step of one track packaged by AOTInductor
  (``tl.OnlineStep`` exported with a dynamic batch, ``tl.compile_package``, ``tl.load_package``;
  built once per process, a C++ compile) and one filterpy filter's predict + update, timed in
  alternation in that process: target ≤ 1.0×;
- ``seq_iou_2000x50`` (and ``_nocheck``): the sequence filter (2,000 tracks × 50 reports, no
  gradients) with value checks on (off): target checked ≤ ~1.2× unchecked;
- ``imm_2000x50`` against ``kf3_2000x50``, the 3 Kalman filters of its modes on the same data
  (``algorithm="sequential"``): target ≤ 3×;
- ``imm_forecast_2000``: ``IMMFilter.forecast`` of that IMM from 2,000 filtered states, each
  to its own lead in 300–900 s (no gradients; the evaluation's call), and ``imm_kstep_grad``:
  forward + backward of the k-step loss (``imm_k_step_nll``, k = 12) on 32 tracks × 100 reports
  (the training call).

Each row runs in a fresh process per checkout, the checkouts alternating (A, B, A, B, …), so
both see the same load; the figure is the median over the rounds of each process's median
(:func:`_timing.median_s`). ``--save`` writes the table to ``experiments/results/bench_online.md``.

    python experiments/bench_online.py --trees /path/to/main . --rounds 3
    python experiments/bench_online.py --trees . --save     # this checkout only
"""

from __future__ import annotations

import argparse
import json
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from _timing import ab_table, across_checkouts, machine_line, saved

ROWS = ("step_cv_b1", "step_cv_b1_nocheck", "step_iou_b1", "step_iou_b1_nocheck", "step_cv_b1000", "filterpy_b1000",
        "aoti_step_b1", "seq_iou_2000x50", "seq_iou_2000x50_nocheck", "imm_2000x50", "kf3_2000x50",
        "imm_forecast_2000", "imm_kstep_grad")  # fmt: skip
#: Rows measured in the process of another (timed in alternation with it).
PAIRED = {"filterpy_b1": "aoti_step_b1"}
#: (name, numerator, denominator) of the ratios printed under the table.
RATIOS = (
    ("filterpy loop / step, 1000 tracks (target ≥ 20)", "filterpy_b1000", "step_cv_b1000"),
    ("packaged step / filterpy predict + update, 1 track (target ≤ 1.0)", "aoti_step_b1", "filterpy_b1"),
    ("checked / unchecked sequence (target ≤ ~1.2)", "seq_iou_2000x50", "seq_iou_2000x50_nocheck"),
    ("IMM / 3 Kalman filters (target ≤ 3)", "imm_2000x50", "kf3_2000x50"),
)
H2 = [[1.0, 0, 0, 0], [0, 0, 1.0, 0]]
R2 = [[0.3, 0.1], [0.1, 0.4]]


def filterpy_cv(
    R: np.ndarray, q: float = 0.8, tracks: int = 1
) -> tuple[Callable[[np.ndarray, np.ndarray], None], list]:
    """A filterpy contestant: ``tracks`` filterpy KalmanFilters of the 2-D constant-velocity model
    (state [x, vx, y, vy], positions observed with noise R, prior 10 I) and ``step(ys, dts)``,
    which predicts each filter over its gap (closed-form A(dt), Q(dt) = q [[dt³/3, dt²/2],
    [dt²/2, dt]] per axis) and updates it with its report."""
    from filterpy.kalman import KalmanFilter as FilterPy

    filters = []
    for _ in range(tracks):
        f = FilterPy(dim_x=4, dim_z=2)
        f.x, f.P, f.H, f.R = np.zeros((4, 1)), 10 * np.eye(4), np.array(H2), np.array(R)
        filters.append(f)

    def step(ys: np.ndarray, dts: np.ndarray) -> None:
        for f, z, h in zip(filters, ys, dts):
            A1 = np.array([[1.0, h], [0.0, 1.0]])
            Q1 = q * np.array([[h**3 / 3, h**2 / 2], [h**2 / 2, h]])
            f.F, f.Q = np.kron(np.eye(2), A1), np.kron(np.eye(2), Q1)
            f.predict()
            f.update(z)

    return step, filters


def measure(row: str) -> dict[str, float]:
    """Seconds of one call of ``row`` (and of the rows paired with it), at 1 thread."""
    import torch
    from _timing import median_s, paired_s

    import torchsde_lti as tl

    torch.set_num_threads(1)
    F64 = torch.float64
    H, R = torch.tensor(H2, dtype=F64), torch.tensor(R2, dtype=F64)
    g = torch.Generator().manual_seed(0)

    def kf_of(model: str, **kw: object) -> tl.KalmanFilter:
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
            state, _ = kf.step(state, y, dt)  # (a state as a tracker holds it: the previous step's)
            return {row: median_s(lambda: kf.step(state, y, dt), 41 if B == 1 else 15, inner=50 if B == 1 else 3)}
    if row == "filterpy_b1000":
        step, _ = filterpy_cv(np.array(R2), tracks=1000)
        ys, dts = np.random.default_rng(0).normal(size=(1000, 2)), np.random.default_rng(1).random(1000) + 0.1
        return {row: median_s(lambda: step(ys, dts), 7)}
    if row == "aoti_step_b1":
        from torch.export import Dim

        kf = kf_of("cv").eval()
        state = kf.initial_state(2)  # (an example batch of 2: export specialises a batch of 1)
        args = (state.mean.contiguous(), state.cov.contiguous(), torch.zeros(2, 2, dtype=F64), torch.ones(2, dtype=F64))
        with torch.no_grad():
            program = torch.export.export(tl.OnlineStep(kf), args, dynamic_shapes=({0: Dim("B", max=1_000_000)},) * 4)
        args = tuple(x[:1].contiguous() for x in args)
        with tempfile.TemporaryDirectory() as tmp:
            run = tl.load_package(tl.compile_package(program, Path(tmp) / "step.pt2"))
            y, dt = torch.randn(1, 2, generator=g, dtype=F64), torch.rand(1, generator=g, dtype=F64) + 0.1
            mean, cov = run(*args[:2], y, dt)[:2]
            step, _ = filterpy_cv(np.array(R2))
            ys, dts = y.numpy(), dt.numpy()
            t_pkg, t_fp = paired_s(lambda: run(mean, cov, y, dt), lambda: step(ys, dts), 41, inner=50)
        return {row: t_pkg, "filterpy_b1": t_fp}
    y = torch.randn(2000, 50, 2, generator=g, dtype=F64).cumsum(1)
    dt = torch.rand(2000, 50, generator=g, dtype=F64) + 0.1
    if row.startswith("seq_"):
        kf = kf_of("iou", validate_args=not row.endswith("_nocheck"))
        with torch.no_grad():
            return {row: median_s(lambda: kf(y, dt), 7)}
    # the IMM cycle vs the Kalman filters of its 3 modes, 2,000 tracks × 50 steps
    sdes = [
        tl.models.constant_velocity(dim=2, q=0.5, dtype=F64),
        tl.models.integrated_ou(1.5, 0.05, dim=2, dtype=F64),
        tl.models.integrated_ou(0.2, 2.0, dim=2, dtype=F64),
    ]
    imm = tl.IMMFilter(sdes, H, R, torch.full((3, 3), 0.1, dtype=F64), P0=10 * torch.eye(4, dtype=F64))
    if row == "imm_2000x50":
        with torch.no_grad():
            return {row: median_s(lambda: imm(y, dt), 5)}
    if row == "imm_forecast_2000":
        with torch.no_grad():
            out = imm(y, dt)
            state = (out.mode_probabilities[:, -1], out.mode_mean[:, -1], out.mode_cov[:, -1])
            lead = 300.0 + 600.0 * torch.rand(2000, 1, generator=g, dtype=F64)
            return {row: median_s(lambda: imm.forecast(state, lead), 7)}
    if row == "imm_kstep_grad":
        from torchsde_lti.evaluation import imm_k_step_nll

        yk = torch.randn(32, 100, 2, generator=g, dtype=F64).cumsum(1)
        dtk = torch.rand(32, 100, generator=g, dtype=F64) + 0.1
        observed = torch.ones_like(yk, dtype=torch.bool)

        def kstep() -> None:
            imm.zero_grad()
            imm_k_step_nll(imm, imm(yk, dtk), yk, dtk, observed, 12).backward()

        return {row: median_s(kstep, 5)}
    kfs = [tl.KalmanFilter(s, H, R, P0=10 * torch.eye(4, dtype=F64), algorithm="sequential") for s in sdes]
    with torch.no_grad():
        return {row: median_s(lambda: [kf(y, dt) for kf in kfs], 5)}


def _cell(t: float) -> str:
    return f"{t * 1e6:.0f} µs" if t < 1e-2 else f"{t * 1e3:.1f} ms"


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--trees", nargs="+", default=["."], help="checkouts to compare (paired, alternating)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--rows", nargs="+", default=list(ROWS))
    parser.add_argument("--save", action="store_true", help="write the table to experiments/results/bench_online.md")
    parser.add_argument("--measure", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(args.measure)))
        return
    results, loads = across_checkouts(__file__, args.rows, args.trees, args.rounds, once={"aoti_step_b1"})
    names = [r for row in args.rows for r in (row, *[p for p, of in PAIRED.items() if of == row])]

    def report() -> None:
        print(
            f"1 thread, CPU-time medians over {args.rounds} alternating rounds; load {min(loads):.1f}–{max(loads):.1f}"
        )
        print(f"({machine_line()})\n")
        medians = ab_table(results, names, args.trees, _cell)
        for label, num, den in RATIOS:
            if all((k, t) in medians for k in (num, den) for t in args.trees):
                cells = " | ".join(f"{medians[(num, t)] / medians[(den, t)]:.2f}" for t in args.trees)
                print(f"| {label} | {cells} |")

    if args.save:
        with saved("bench_online.md"):
            report()
    else:
        report()


if __name__ == "__main__":
    main()
