"""The packaged online step (AOTInductor) beyond bench_online.py's float64 constant-velocity case:
constant velocity in float32 and the Singer model (6 states, F not nilpotent: the program
discretises with its doubling series, or before that series existed with core's traced
doubling schedule) in float64 and float32, at 1 and 1000 tracks; with ``--eager``, instead, the
eager ``kf.step`` of bench_online.py's float64 constant-velocity filter at one track and of the
Singer model and of an IMM at 1 and 1000 tracks (no packages built); with ``--series``, paired in one
process, the eager Singer step (and an IMM step) with its discretisation series (kept per
parameter version) against the same step discretising with core's ``discretize`` on every call;
with ``--small-batch``, the eager step's joint update against its scalar updates by number of
tracks (what sets ``filters.online.SMALL_BATCH``). Run it against two checkouts to compare them (it uses tl.compile_package / tl.load_package
where the checkout has them, torch's own calls otherwise)::

    PYTHONPATH=/path/to/old python experiments/ab_package_step.py
    PYTHONPATH=$PWD python experiments/ab_package_step.py

1 intra-op thread, median CPU time of 41 timings of 20 calls; each row also prints the largest
difference of the packaged step's filtered mean from the eager step's.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import torch
from torch.export import Dim

import torchsde_lti as tl

sys.path.insert(0, str(Path(__file__).parent))
from _timing import median_s, paired_s  # noqa: E402
from bench_online import build_filter  # noqa: E402
from bench_online import step_args as cv_args  # noqa: E402


def build(name: str, dtype: torch.dtype) -> tl.KalmanFilter:
    if name == "singer":
        sde = tl.models.singer(dim=2, alpha=0.5, q=0.7, dtype=dtype)
    else:
        sde = tl.models.constant_velocity(dim=2, q=0.8, dtype=dtype)
    n = sde.matrices().F.shape[-1]
    R = 0.3 * torch.eye(2, dtype=dtype)
    return tl.KalmanFilter(sde, tl.models.position_observation(sde), R, P0=torch.eye(n, dtype=dtype))


def step_args(b: int, n: int, dtype: torch.dtype, g: torch.Generator) -> tuple[torch.Tensor, ...]:
    cov = torch.eye(n, dtype=dtype).expand(b, n, n).contiguous()
    return (
        torch.randn(b, n, generator=g).to(dtype),
        cov,
        torch.randn(b, 2, generator=g).to(dtype),
        torch.rand(b, generator=g).to(dtype),
    )


def eager_step() -> None:
    """``kf.step`` without gradients: bench_online.py's float64 constant-velocity filter at one
    track, the Singer model (float64, float32) at 1 and 1000 tracks."""
    kf = build_filter(validate=False)
    mean, cov, y, dt = cv_args(1, 0)
    state = tl.KalmanState(mean, cov)
    with torch.no_grad():
        t = median_s(lambda: kf.step(state, y, dt), 101, inner=10)
    print(f"cv float64 B=1 eager kf.step: {t * 1e6:.1f} µs")
    for dtype in (torch.float64, torch.float32):
        kf = build("singer", dtype)
        g = torch.Generator().manual_seed(0)
        for b in (1, 1000):
            mean, cov, y, dt = step_args(b, 6, dtype, g)
            state = tl.KalmanState(mean, cov)
            with torch.no_grad():
                t = median_s(lambda state=state, y=y, dt=dt: kf.step(state, y, dt), 41 if b == 1 else 15, inner=5)
            print(f"singer {str(dtype)[6:]} B={b} eager kf.step: {t * 1e6:.1f} µs")
    imm = _imm_filter()
    g = torch.Generator().manual_seed(1)
    for b in (1, 1000):
        state = imm.initial_state(b)
        y, dt = torch.randn(b, 2, generator=g, dtype=torch.float64), torch.rand(b, generator=g, dtype=torch.float64)
        with torch.no_grad():
            t = median_s(lambda state=state, y=y, dt=dt: imm.step(state, y, dt), 41 if b == 1 else 15, inner=5)
        print(f"imm cv+iou float64 B={b} eager imm.step: {t * 1e6:.1f} µs")


def _imm_filter() -> tl.IMMFilter:
    """An IMM of constant velocity and integrated OU (2-D, float64, positions observed)."""
    cv = tl.models.constant_velocity(dim=2, q=0.5, dtype=torch.float64)
    iou = tl.models.integrated_ou(1.5, 0.05, dim=2, dtype=torch.float64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=torch.float64)
    rates = torch.tensor([[0.0, 0.2], [0.4, 0.0]], dtype=torch.float64)
    return tl.IMMFilter([cv, iou], H, 0.4 * torch.eye(2, dtype=torch.float64), rates, validate_args=False)


def series_vs_discretize() -> None:
    """The eager Singer step with the model's discretisation series (``kf.step``'s default)
    against the same step with core's ``discretize`` on every call, timed in alternation; the
    same for an IMM step (constant velocity + integrated OU, each mode's and the mode chain's
    series, against core's discretize and torch.matrix_exp of Λ dt)."""

    from torchsde_lti.nn._online import evaluated

    for dtype in (torch.float64, torch.float32):
        kf = build("singer", dtype)
        g = torch.Generator().manual_seed(0)
        with torch.no_grad():
            model = evaluated(kf, kf._online_model)
            plain = (*model[:4], None)
            for b in (1, 8, 64, 1000):
                mean, cov, y, dt = step_args(b, 6, dtype, g)
                st = tl.KalmanState(mean, cov)
                a, c = paired_s(
                    lambda st=st, y=y, dt=dt: kf._step(model, st, y, dt),
                    lambda st=st, y=y, dt=dt: kf._step(plain, st, y, dt),
                    41 if b < 1000 else 15,
                    inner=3,
                )
                print(
                    f"singer {str(dtype)[6:]} B={b}: with the series {a * 1e6:.0f} µs, "
                    f"core discretize {c * 1e6:.0f} µs, ratio {a / c:.2f}"
                )
    # an IMM of constant velocity and integrated OU (2-D): each mode's and the chain's series
    imm = _imm_filter()
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        online = evaluated(imm, imm._online_model)
        plain_imm = online._replace(series=None, chain=None)
        for b in (1, 8, 64, 1000):
            state = imm.initial_state(b)
            y, dt = torch.randn(b, 2, generator=g, dtype=torch.float64), torch.rand(b, generator=g, dtype=torch.float64)

            def imm_step(model: object, state=state, y=y, dt=dt) -> None:
                d, Pi = imm._discretize_bank(online.F, online.W, dt, False, model)  # type: ignore[arg-type]
                tl.filters.imm_step(state, y, d.A, d.Q, Pi, online.H, online.R)

            a, c = paired_s(lambda: imm_step(online), lambda: imm_step(plain_imm), 41 if b < 1000 else 15, inner=3)
            print(
                f"imm cv+iou float64 B={b}: with the series {a * 1e6:.0f} µs, core discretize {c * 1e6:.0f} µs, ratio {a / c:.2f}"
            )


def small_batch_crossover() -> None:
    """The eager constant-velocity step (float64 and float32) with the joint update against the
    scalar updates, by number of tracks, timed in alternation: what sets
    ``torchsde_lti.filters.online.SMALL_BATCH``."""

    import torchsde_lti.filters.online as online

    default = online.SMALL_BATCH
    for dtype in (torch.float64, torch.float32):
        kf = build("cv", dtype)
        g = torch.Generator().manual_seed(2)
        for b in (16, 32, 64, 96, 128, 192, 256, 512):
            mean, cov, y, dt = step_args(b, 4, dtype, g)
            state = tl.KalmanState(mean, cov)

            def run(small: int, state=state, y=y, dt=dt) -> None:
                online.SMALL_BATCH = small
                kf.step(state, y, dt)

            with torch.no_grad():
                joint, scalar = paired_s(lambda: run(1 << 30), lambda: run(0), 31, inner=5)
            print(
                f"cv {str(dtype)[6:]} B={b}: joint update {joint * 1e6:.0f} µs, scalar updates "
                f"{scalar * 1e6:.0f} µs, joint / scalar {joint / scalar:.2f}"
            )
    online.SMALL_BATCH = default


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--eager", action="store_true", help="time the eager kf.step only")
    ap.add_argument("--series", action="store_true", help="eager Singer step: the series vs core discretize")
    ap.add_argument("--small-batch", action="store_true", help="eager step: joint vs scalar update by batch size")
    torch.set_num_threads(1)
    args = ap.parse_args()
    if args.eager:
        eager_step()
        return
    if args.series:
        series_vs_discretize()
        return
    if args.small_batch:
        small_batch_crossover()
        return
    helpers = hasattr(tl, "compile_package")
    print("tl.compile_package / tl.load_package" if helpers else "torch's aoti_compile_and_package / aoti_load_package")
    for name, dtype in (("cv", torch.float32), ("singer", torch.float64), ("singer", torch.float32)):
        kf = build(name, dtype)
        n = kf.sde.matrices().F.shape[-1]
        g = torch.Generator().manual_seed(0)
        with torch.no_grad():
            ep = torch.export.export(
                tl.OnlineStep(kf).eval(), step_args(3, n, dtype, g), dynamic_shapes=({0: Dim("B", max=100_000)},) * 4
            )
        path = tempfile.mktemp(suffix=".pt2")
        if helpers:
            run = tl.load_package(tl.compile_package(ep, path))
        else:
            run = torch._inductor.aoti_load_package(torch._inductor.aoti_compile_and_package(ep, package_path=path))
        for b in (1, 1000):
            args = step_args(b, n, dtype, g)
            with torch.no_grad():
                state, _ = kf.step(tl.KalmanState(args[0], args[1]), args[2], args[3])
            err = float((run(*args)[0] - state.mean).abs().max())
            t = median_s(lambda args=args: run(*args), 41, inner=20)
            print(f"{name} {str(dtype)[6:]} B={b}: {t * 1e6:.1f} µs (max |mean − eager| {err:.1e})")


if __name__ == "__main__":
    main()
