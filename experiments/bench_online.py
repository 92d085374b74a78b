"""Online tracking latency: torchsde_lti's online step (eager, exported, AOTInductor) against
filterpy and Stone Soup, all in the same run, 1 intra-op thread, medians of repeated calls.

Rows (constant-velocity model in 2-D, state [x, vx, y, vy], positions observed, float64):

- online step, B = 1: ``kf.step`` eager (value checks on and off), its parts (the SDE's
  matrices, the exact discretisation, the filter step itself), the exported program
  (``torch.export`` of :class:`~torchsde_lti.OnlineStep`, dynamic batch, traced for Inductor and
  for the eager runtime) and its AOTInductor package; filterpy's ``predict`` + ``update`` with the closed-form CV ``A(dt)``, ``Q(dt)`` set
  before each predict;
- B = 1000 live tracks, each with its own dt: one eager step vs a loop over 1000 filterpy filters;
- sequence B = 1, T = 200: the AOTInductor-packaged sequence filter (:class:`~torchsde_lti.DeployedFilter`
  exported with a dynamic batch and T) vs filterpy over the 200 reports;
- the exported (not AOTI) sequence program, traced for running as it is
  (``DeployedFilter(kf, runtime="eager")``), vs eager ``kf(y, dt)`` at B = 1 and B = 100
  (T = 200), and the program traced for Inductor run the same way;
- Stone Soup's multi-target tracker (tests/test_interop.py's scenario: 4 targets, clutter,
  missed detections) per scan with the learned model through ``torchsde_lti.interop`` vs
  Stone Soup's own ``ConstantVelocity``.

    PYTHONPATH=$PWD python experiments/bench_online.py            # writes experiments/results/bench_online.md
    PYTHONPATH=$PWD python experiments/bench_online.py --quick    # fewer repeats
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

import torchsde_lti as tl
from torchsde_lti.core.discretization import discretize
from torchsde_lti.nn import model_version
from torchsde_lti.nn._online import model_series, series_step

F64 = torch.float64
Q_CV = 0.8
H_NP = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
R_NP = np.array([[0.3, 0.1], [0.1, 0.4]])


def median_s(fn: Callable[[], object], repeat: int, warmup: int = 5, inner: int = 1) -> float:
    """Median CPU seconds (this process, 1 thread) of one call of ``fn`` over ``repeat``
    timings of ``inner`` calls each (a CPU-time clock: a shared machine's other jobs do not
    add their time slices, only their cache and core sharing)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.process_time()
        for _ in range(inner):
            fn()
        times.append((time.process_time() - t0) / inner)
    return statistics.median(times)


def paired_s(
    fa: Callable[[], object], fb: Callable[[], object], repeat: int, warmup: int = 3, inner: int = 1
) -> tuple[float, float]:
    """Median CPU seconds of ``fa`` and of ``fb``, timed in alternation (a, b, a, b, ...) so
    that both see the same load: the ratio of the two is what the targets compare."""
    for _ in range(warmup):
        fa()
        fb()
    ta, tb = [], []
    for _ in range(repeat):
        for fn, out in ((fa, ta), (fb, tb)):
            t0 = time.process_time()
            for _ in range(inner):
                fn()
            out.append((time.process_time() - t0) / inner)
    return statistics.median(ta), statistics.median(tb)


def cv_closed_form(dt: float, q: float = Q_CV) -> tuple[np.ndarray, np.ndarray]:
    """A, Q of the 2-D constant-velocity model over dt (per axis [[1, dt], [0, 1]] and
    q [[dt³/3, dt²/2], [dt²/2, dt]]), state [x, vx, y, vy]."""
    a = np.array([[1.0, dt], [0.0, 1.0]])
    qq = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    A, Q = np.zeros((4, 4)), np.zeros((4, 4))
    A[:2, :2] = A[2:, 2:] = a
    Q[:2, :2] = Q[2:, 2:] = qq
    return A, Q


def filterpy_filter() -> object:
    from filterpy.kalman import KalmanFilter as FPKalman

    f = FPKalman(dim_x=4, dim_z=2)
    f.x = np.zeros((4, 1))
    f.P = 50.0 * np.eye(4)
    f.H = H_NP.copy()
    f.R = R_NP.copy()
    return f


def filterpy_step(f: object, z: np.ndarray, dt: float) -> None:
    f.F, f.Q = cv_closed_form(dt)  # type: ignore[attr-defined]
    f.predict()  # type: ignore[attr-defined]
    f.update(z)  # type: ignore[attr-defined]


def build_filter(validate: bool) -> tl.KalmanFilter:
    cv = tl.models.constant_velocity(dim=2, q=Q_CV, dtype=F64)
    return tl.KalmanFilter(
        cv, torch.tensor(H_NP), torch.tensor(R_NP), P0=50 * torch.eye(4, dtype=F64), validate_args=validate
    )


def step_args(b: int, seed: int) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    mean = torch.randn(b, 4, generator=g, dtype=F64)
    cov = 2.0 * torch.eye(4, dtype=F64).expand(b, 4, 4).contiguous()
    return mean, cov, torch.randn(b, 2, generator=g, dtype=F64), 0.2 + torch.rand(b, generator=g, dtype=F64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "bench_online.md"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    rep = 51 if args.quick else 201
    load_before = os.getloadavg()
    rows: list[tuple[str, float, str]] = []  # (what, seconds, note)
    kf = build_filter(validate=False)
    kf_checked = build_filter(validate=True)
    workdir = Path(tempfile.mkdtemp(prefix="bench_online_"))

    # ---------------------------------------------------------------- B = 1 online step
    mean, cov, y, dt = step_args(1, 0)
    state = tl.KalmanState(mean, cov)
    with torch.no_grad():
        t_eager = median_s(lambda: kf.step(state, y, dt), rep, inner=5)
        t_checked = median_s(lambda: kf_checked.step(state, y, dt), rep, inner=5)
        mats = kf.sde.matrices()
        t_mats = median_s(lambda: kf.sde.matrices(), rep, inner=5)
        t_version = median_s(lambda: model_version(kf), rep, inner=5)
        series = model_series(*mats)
        assert series is not None  # constant velocity: F² = 0
        t_series = median_s(lambda: series_step(series, dt), rep, inner=5)
        t_disc = median_s(lambda: discretize(mats.F, mats.L, mats.Qc, dt, validate_args=False), rep, inner=5)
        A, Q, _ = series_step(series, dt)
        H, R = kf.H, kf.R
        t_kstep = median_s(lambda: tl.filters.kalman_step(state, y, A, Q, H, R), rep, inner=5)
    rows += [
        ("online step B=1, eager (validate_args=False)", t_eager, ""),
        ("online step B=1, eager (validate_args=True)", t_checked, "one fused value check"),
        ("  of which: model_version (the per-version cache's key)", t_version, "sde.matrices() only on a new version"),
        (
            "  of which: exact discretisation (closed-form series, 1 element)",
            t_series,
            "nilpotent F: matrices per version",
        ),
        ("  of which: filters.kalman_step (joint Joseph update)", t_kstep, ""),
        ("  (not in the step) sde.matrices()", t_mats, "parametrisations, once per version"),
        ("  (not in the step) core discretize (doubling, 1 element)", t_disc, "what an F without a closed form takes"),
    ]

    from torch.export import Dim

    t0 = time.perf_counter()
    with torch.no_grad():
        ep_step = torch.export.export(
            tl.OnlineStep(kf).eval(), step_args(3, 1), dynamic_shapes=({0: Dim("B", max=1_000_000)},) * 4
        )
    t_export_step = time.perf_counter() - t0
    prog_step = ep_step.module()
    with torch.no_grad():
        prog_step_eager = torch.export.export(
            tl.OnlineStep(kf, runtime="eager").eval(),
            step_args(3, 1),
            dynamic_shapes=({0: Dim("B", max=1_000_000)},) * 4,
        ).module()
        t_exp_step = median_s(lambda: prog_step(mean, cov, y, dt), rep, inner=5)
        t_exp_step_eager = median_s(lambda: prog_step_eager(mean, cov, y, dt), rep, inner=5)
    t0 = time.perf_counter()
    step_pkg = tl.compile_package(ep_step, workdir / "step.pt2")
    t_compile_step = time.perf_counter() - t0
    run_step = tl.load_package(step_pkg)
    run_step_stock = torch._inductor.aoti_load_package(step_pkg)  # torch's loader object (parses its spec per call)
    got = run_step(mean, cov, y, dt)
    with torch.no_grad():
        ref_state, ref_out = kf.step(state, y, dt)
    assert torch.allclose(got[0], ref_state.mean, atol=1e-9) and torch.allclose(
        got[4], ref_out.log_likelihood, atol=1e-9
    )
    fp = filterpy_filter()
    z, h = y[0].numpy()[:, None], float(dt[0])
    t_aoti_step, t_fp = paired_s(lambda: run_step(mean, cov, y, dt), lambda: filterpy_step(fp, z, h), rep, inner=20)
    t_aoti_stock = median_s(lambda: run_step_stock(mean, cov, y, dt), rep, inner=20)
    rows += [
        (
            "online step B=1, exported program (torch.export, dynamic B)",
            t_exp_step,
            f"export {t_export_step:.1f} s; runtime='inductor'",
        ),
        ("online step B=1, exported program (runtime='eager')", t_exp_step_eager, "batched BLAS / LAPACK calls"),
        ("online step B=1, AOTInductor package", t_aoti_step, f"compile {t_compile_step:.0f} s; tl.load_package"),
        ("  the same package through torch._inductor.aoti_load_package", t_aoti_stock, "its call spec parsed per call"),
        ("filterpy predict+update B=1 (closed-form CV A, Q)", t_fp, ""),
    ]

    # ---------------------------------------------------------------- B = 1000 tracks, own dt
    B = 1000
    meanB, covB, yB, dtB = step_args(B, 2)
    stateB = tl.KalmanState(meanB, covB)
    t_aoti_B = median_s(lambda: run_step(meanB, covB, yB, dtB), max(rep // 4, 11))
    fps = [filterpy_filter() for _ in range(B)]
    zs, hs = yB.numpy()[:, :, None], dtB.tolist()

    def fp_loop() -> None:
        for f, z_, h_ in zip(fps, zs, hs):
            filterpy_step(f, z_, h_)

    def eager_B() -> None:
        with torch.no_grad():
            kf.step(stateB, yB, dtB)

    t_eager_B, t_fp_B = paired_s(eager_B, fp_loop, 9, warmup=1)
    rows += [
        ("online step B=1000 (own dt), eager", t_eager_B, ""),
        ("online step B=1000 (own dt), AOTInductor package", t_aoti_B, ""),
        ("loop of 1000 filterpy filters (predict+update)", t_fp_B, ""),
    ]

    # ---------------------------------------------------------------- sequences
    T = 200
    g = torch.Generator().manual_seed(3)
    y_seq = torch.randn(1, T, 2, generator=g, dtype=F64).cumsum(1)
    dt_seq = 0.2 + torch.rand(1, T, generator=g, dtype=F64)
    Bd, Td = Dim("B", max=100_000), Dim("T", max=100_000)
    t0 = time.perf_counter()
    with torch.no_grad():
        # the example's sizes must not be 0 or 1 (torch.export specialises those): B = 2 here
        ep_seq = torch.export.export(
            tl.DeployedFilter(kf).eval(),
            (y_seq.expand(2, T, 2), dt_seq.expand(2, T)),
            dynamic_shapes={"y": {0: Bd, 1: Td}, "dt": {0: Bd, 1: Td}},
        )
        t_export_seq = time.perf_counter() - t0
        t0 = time.perf_counter()
        ep_seq_eager = torch.export.export(
            tl.DeployedFilter(kf, runtime="eager").eval(),
            (y_seq.expand(2, T, 2), dt_seq.expand(2, T)),
            dynamic_shapes={"y": {0: Bd, 1: Td}, "dt": {0: Bd, 1: Td}},
        )
        t_export_seq_eager = time.perf_counter() - t0
        # AOTInductor cannot yet lower the structured scan with a symbolic T (inductor KeyError in
        # lower_to_while_loop): the package is built for a static (B, T) = (1, 200) bucket
        ep_seq_static = torch.export.export(tl.DeployedFilter(kf).eval(), (y_seq, dt_seq))
    t0 = time.perf_counter()
    seq_pkg = tl.compile_package(ep_seq_static, workdir / "seq.pt2")
    t_compile_seq = time.perf_counter() - t0
    run_seq = tl.load_package(seq_pkg)
    with torch.no_grad():
        assert torch.allclose(run_seq(y_seq, dt_seq)[0], kf(y_seq, dt_seq).log_likelihood, atol=1e-8)
    zs_seq, hs_seq = y_seq[0].numpy()[:, :, None], dt_seq[0].tolist()

    def fp_seq() -> None:
        f = filterpy_filter()
        for z_, h_ in zip(zs_seq, hs_seq):
            filterpy_step(f, z_, h_)

    t_aoti_seq, t_fp_seq = paired_s(lambda: run_seq(y_seq, dt_seq), fp_seq, max(rep // 4, 11), warmup=2)
    rows += [
        (
            "sequence B=1 T=200, AOTInductor package (static (1, 200) bucket)",
            t_aoti_seq,
            f"export {t_export_seq:.0f} s, compile {t_compile_seq:.0f} s",
        ),
        ("sequence B=1 T=200, filterpy (200 predict+update)", t_fp_seq, ""),
    ]
    prog_seq, prog_seq_eager = ep_seq.module(), ep_seq_eager.module()
    for b in (1, 100):
        yb = torch.randn(b, T, 2, generator=g, dtype=F64).cumsum(1)
        dtb = 0.2 + torch.rand(b, T, generator=g, dtype=F64)
        with torch.no_grad():
            assert torch.allclose(prog_seq_eager(yb, dtb)[0], kf(yb, dtb).log_likelihood, atol=1e-8)
            t_e, t_x = paired_s(
                lambda yb=yb, dtb=dtb: kf(yb, dtb),
                lambda yb=yb, dtb=dtb: prog_seq_eager(yb, dtb),
                max(rep // 8, 7),
                warmup=1,
            )
            t_xi = median_s(lambda yb=yb, dtb=dtb: prog_seq(yb, dtb), max(rep // 16, 5), warmup=1)
        rows += [
            (f"sequence B={b} T=200, eager kf(y, dt)", t_e, f"algorithm {kf.algorithm_for(b, T, yb.device)!r}"),
            (
                f"sequence B={b} T=200, exported program (not AOTI)",
                t_x,
                f"runtime='eager': one program for every (B, T), export {t_export_seq_eager:.0f} s",
            ),
            (f"sequence B={b} T=200, exported program (runtime='inductor')", t_xi, "the program AOTI packages"),
        ]

    # ---------------------------------------------------------------- Stone Soup tracker
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from stonesoup.models.transition.linear import (
        CombinedLinearGaussianTransitionModel,
        ConstantVelocity,
    )

    from tests.test_interop import (
        fit_constant_velocity,
        run_stonesoup_tracker,
        stonesoup_scenario,
    )
    from torchsde_lti.interop import stonesoup_transition_model

    _, scans = stonesoup_scenario(scans=60)
    sde = fit_constant_velocity(scans)
    q = float(sde.matrices().Qc[0, 0].detach())
    per_scan = {"learned": [], "stonesoup": []}
    for _ in range(3 if args.quick else 7):
        for name, model in (
            ("learned", stonesoup_transition_model(sde)),
            ("stonesoup", CombinedLinearGaussianTransitionModel([ConstantVelocity(q)] * 2)),
        ):
            per_scan[name].append(run_stonesoup_tracker(model, scans)[1])
    rows += [
        (
            "Stone Soup tracker per scan, learned model via interop",
            statistics.median(per_scan["learned"]),
            "4 targets, clutter, GNN",
        ),
        ("Stone Soup tracker per scan, its own ConstantVelocity", statistics.median(per_scan["stonesoup"]), ""),
    ]

    load_after = os.getloadavg()
    targets = [
        ("online step B=1 eager ≤ 250 µs", t_eager <= 250e-6, f"{t_eager * 1e6:.0f} µs"),
        ("AOTI step ≤ 1.0× filterpy predict+update", t_aoti_step <= t_fp, f"{t_aoti_step / t_fp:.2f}×"),
        ("B=1000 eager ≥ 20× filterpy loop", t_fp_B / t_eager_B >= 20, f"{t_fp_B / t_eager_B:.1f}×"),
        ("sequence B=1 T=200 AOTI ≥ 3× filterpy", t_fp_seq / t_aoti_seq >= 3, f"{t_fp_seq / t_aoti_seq:.1f}×"),
        (
            "exported ≥ 1.0× eager at B=1 and B=100",
            all(
                rows_by(rows, f"sequence B={b} T=200, eager kf(y, dt)")
                / rows_by(rows, f"sequence B={b} T=200, exported program (not AOTI)")
                >= 1.0
                for b in (1, 100)
            ),
            ", ".join(
                f"B={b}: {rows_by(rows, f'sequence B={b} T=200, eager kf(y, dt)') / rows_by(rows, f'sequence B={b} T=200, exported program (not AOTI)'):.2f}×"
                for b in (1, 100)
            ),
        ),
        (
            "Stone Soup learned ≤ its ConstantVelocity per scan",
            statistics.median(per_scan["learned"]) <= statistics.median(per_scan["stonesoup"]),
            f"{statistics.median(per_scan['learned']) / statistics.median(per_scan['stonesoup']):.2f}×",
        ),
    ]
    text = render(rows, targets, load_before, load_after, args.quick)
    print(text)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(text)


def rows_by(rows: list[tuple[str, float, str]], name: str) -> float:
    return next(t for n, t, _ in rows if n == name)


def fmt(seconds: float) -> str:
    if seconds < 1e-3:
        return f"{seconds * 1e6:.1f} µs"
    if seconds < 1:
        return f"{seconds * 1e3:.2f} ms"
    return f"{seconds:.2f} s"


def render(
    rows: list[tuple[str, float, str]],
    targets: list[tuple[str, bool, str]],
    load_before: tuple,
    load_after: tuple,
    quick: bool,
) -> str:
    lines = [
        "# Online tracking latency (experiments/bench_online.py)",
        "",
        f"torch {torch.__version__}, {platform.processor() or platform.machine()}, 1 intra-op thread, float64, "
        f"medians of CPU time (process_time){' (--quick)' if quick else ''}; every ratio of a target from "
        "paired, alternating timings of its two sides; load average "
        f"{load_before[0]:.1f} before, {load_after[0]:.1f} after on {os.cpu_count()} cores (a shared machine: "
        "other jobs ran at the same time).",
        "",
        "| what | median | note |",
        "|---|---:|---|",
        *(f"| {n} | {fmt(t)} | {note} |" for n, t, note in rows),
        "",
        "| target | met | measured |",
        "|---|:---:|---:|",
        *(f"| {n} | {'yes' if ok else 'no'} | {m} |" for n, ok, m in targets),
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
