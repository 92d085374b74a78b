"""Which filter algorithm to run: loop vs scan vs square root, and the smoother against a plain loop.

Tables (ms per call, medians of interleaved repeats, ``torch.no_grad``, one process):

- ``choice``: ``kalman_filter`` with ``algorithm="sequential"``, ``"scan"``, ``"square_root"`` on
  a 2-D constant-velocity model (n = 4, m = 2) with irregular dt, B tracks × T steps, float64
  and float32 (cells whose scan would hold more than 10⁶ track·steps are not run);
- ``matern``: one Matérn-3/2 series (B = 1, T = 10⁴), float64 and float32, loop and scan
  (the float32 / float64 ratio of the default);
- ``smoother``: ``rts_smoother`` (loop and scan) at 10⁴ tracks × 100 steps against a plain
  batched RTS loop of ``torch.linalg.solve`` and ``@`` on the same filter result;
- ``options``: the cost of two ``KalmanFilter`` options against the default, B = 1000, T = 200,
  the forward pass and forward + backward of the summed log-likelihood (default and option
  interleaved): ``algorithm="square_root"`` on a 2-D constant-velocity model with irregular dt,
  and ``unique_dt=True`` on a 2-D Singer model (its F is not nilpotent, so every step needs
  scaling and doubling) with gaps quantised to multiples of 0.5 s, as real logs (AIS: whole
  seconds) often are. Not in the default ``--tables``: its table is
  experiments/results/bench_filter_options.md (``--tables options --out`` that file).

Usage: python experiments/bench_filter_choice.py [--tables choice,matern,smoother,options] [--threads 1]
[--repeats 5] [--out FILE] — prints the tables (and writes FILE, default
experiments/results/bench_filter_choice.md). Runs against any checkout that has
``kalman_filter(..., algorithm=, validate_args=)`` and ``rts_smoother(..., algorithm=)``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable, Mapping
from pathlib import Path

import torch
from _timing import interleaved_s

import torchsde_lti as tl
from torchsde_lti.filters import kalman_filter, rts_smoother

RESULTS = Path(__file__).resolve().parent / "results"


def medians(fns: Mapping[str, Callable[[], object]], repeats: int) -> dict[str, float]:
    """ms per call of each function, run in turn (A B C A B C …) after one warm-up each."""
    return {k: 1e3 * s for k, s in interleaved_s(fns, repeats, clock=time.perf_counter).items()}


def cv_problem(B: int, T: int, dtype: torch.dtype, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    dt = torch.rand(B, T, generator=g, dtype=torch.float64) * 1.9 + 0.1
    sde = tl.models.constant_velocity(dim=2, q=1.0, dtype=torch.float64)
    with torch.no_grad():
        d = sde(dt)
    y = torch.randn(B, T, 2, generator=g, dtype=torch.float64).cumsum(1)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=torch.float64)
    kw = dict(y=y, A=d.A, Q=d.Q, H=H, R=0.5 * torch.eye(2, dtype=torch.float64))
    kw.update(m0=torch.zeros(4, dtype=torch.float64), P0=100 * torch.eye(4, dtype=torch.float64))
    return {k: v.to(dtype) for k, v in kw.items()}


def fmt(x: float | None) -> str:
    return "–" if x is None else (f"{x:.0f}" if x >= 100 else f"{x:.1f}")


def table_choice(repeats: int) -> list[str]:
    lines = ["| dtype | B | T | sequential | scan | square_root |", "|---|---:|---:|---:|---:|---:|"]
    for dtype in (torch.float64, torch.float32):
        for B, T in ((1, 200), (10, 200), (100, 200), (1000, 200), (1, 10_000), (10, 10_000), (100, 10_000)):
            kw = cv_problem(B, T, dtype)
            fns = {a: (lambda a=a: kalman_filter(**kw, algorithm=a, validate_args=False)) for a in ALGS}
            if B * T > 1_000_000:
                del fns["scan"]
            if T > 1000:
                del fns["square_root"]
            with torch.no_grad():
                ms = medians(fns, repeats if T <= 1000 else max(3, repeats // 2))
            lines.append(f"| {str(dtype)[6:]} | {B} | {T} | " + " | ".join(fmt(ms.get(a)) for a in ALGS) + " |")
            print(lines[-1], flush=True)
    return lines


ALGS = ("sequential", "scan", "square_root")


def table_matern(repeats: int) -> list[str]:
    T = 10_000
    sde = tl.models.matern(nu=1.5, lengthscale=10.0, variance=1.0, dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    y = torch.sin(torch.arange(T, dtype=torch.float64) / 15.0)[None, :, None] + 0.3 * torch.randn(
        1, T, 1, generator=g, dtype=torch.float64
    )
    with torch.no_grad():
        d = sde(torch.ones(1, T, dtype=torch.float64), series=True)
        P0 = sde.stationary_covariance()
    kw64 = dict(y=y, A=d.A, Q=d.Q, H=tl.models.position_observation(sde), R=0.09 * torch.eye(1, dtype=torch.float64))
    kw64.update(m0=torch.zeros(2, dtype=torch.float64), P0=P0)
    kw32 = {k: v.float() for k, v in kw64.items()}
    fns = {
        f"{a} {name}": (lambda a=a, kw=kw: kalman_filter(**kw, algorithm=a, validate_args=False))
        for a in ("sequential", "scan")
        for name, kw in (("float64", kw64), ("float32", kw32))
    }
    fns["default float64"] = lambda: kalman_filter(**kw64)
    fns["default float32"] = lambda: kalman_filter(**kw32)
    with torch.no_grad():
        ms = medians(fns, repeats)
    lines = [
        "| call (Matérn-3/2, B = 1, T = 10⁴) | float64 ms | float32 ms | float32 / float64 |",
        "|---|---:|---:|---:|",
    ]
    for a in ("sequential", "scan", "default"):
        f64, f32 = ms[f"{a} float64"], ms[f"{a} float32"]
        lines.append(f"| {a} | {fmt(f64)} | {fmt(f32)} | {f32 / f64:.2f} |")
        print(lines[-1], flush=True)
    return lines


def plain_rts(out: tl.filters.FilterResult) -> tuple[torch.Tensor, torch.Tensor]:
    """The textbook batched RTS loop: per step one ``linalg.solve`` and a few ``@``."""
    A, m, P, pm, pP = out.transition, out.mean, out.cov, out.pred_mean, out.pred_cov
    T = m.shape[-2]
    ms, Ps = m[:, -1], P[:, -1]
    means, covs = [ms], [Ps]
    for k in range(T - 2, -1, -1):
        E = torch.linalg.solve(pP[:, k + 1], A[:, k + 1] @ P[:, k]).mT
        ms = m[:, k] + (E @ (ms - pm[:, k + 1]).unsqueeze(-1)).squeeze(-1)
        Ps = P[:, k] + E @ (Ps - pP[:, k + 1]) @ E.mT
        means.append(ms)
        covs.append(Ps)
    return torch.stack(means[::-1], 1), torch.stack(covs[::-1], 1)


def table_smoother(repeats: int) -> list[str]:
    lines = ["| dtype | B × T | plain loop ms | rts_smoother loop ms | plain / ours | rts_smoother scan ms |"]
    lines.append("|---|---|---:|---:|---:|---:|")
    for dtype in (torch.float64, torch.float32):
        kw = cv_problem(10_000, 100, dtype)
        with torch.no_grad():
            out = kalman_filter(**kw, algorithm="sequential", validate_args=False)
            fns = {
                "plain": lambda: plain_rts(out),
                "loop": lambda: rts_smoother(out, algorithm="sequential"),
                "scan": lambda: rts_smoother(out, algorithm="scan"),
            }
            ms = medians(fns, repeats)
            ref, got = plain_rts(out), rts_smoother(out, algorithm="sequential")
            assert torch.allclose(
                ref[0],
                got.mean,
                rtol=1e-3 if dtype == torch.float32 else 1e-9,
                atol=1e-3 if dtype == torch.float32 else 1e-8,
            )
        row = f"| {str(dtype)[6:]} | 10⁴ × 100 | {fmt(ms['plain'])} | {fmt(ms['loop'])} | {ms['plain'] / ms['loop']:.2f} | {fmt(ms['scan'])} |"
        lines.append(row)
        print(row, flush=True)
    return lines


def table_options(repeats: int) -> list[str]:
    B, T = 1000, 200
    gen = torch.Generator().manual_seed(0)
    lines = [
        "| option | dtype | forward: default → option | forward + backward: default → option |",
        "|---|---|---|---|",
    ]
    for dtype in (torch.float64, torch.float32):
        y = torch.randn(B, T, 2, generator=gen, dtype=dtype).cumsum(1)
        dt_irregular = torch.rand(B, T, generator=gen, dtype=dtype) * 2
        dt_quantised = 0.5 * torch.randint(1, 41, (B, T), generator=gen).to(dtype)
        R = 0.25 * torch.eye(2, dtype=dtype)
        cv = tl.models.constant_velocity(dim=2, q=1.0).to(dtype)
        singer = tl.models.singer(alpha=0.5, q=1.0, dim=2).to(dtype)
        distinct = int(torch.unique(dt_quantised).numel())
        cases = (
            ('`algorithm="square_root"` (constant velocity, irregular dt)', cv, dt_irregular, {"algorithm": "square_root"}),
            (f"`unique_dt=True` (Singer, {distinct} distinct gaps)", singer, dt_quantised, {"unique_dt": True}),
        )  # fmt: skip
        for name, sde, dt, option in cases:
            H = tl.models.position_observation(sde)
            kfs = {"default": tl.KalmanFilter(sde, H, R), "option": tl.KalmanFilter(sde, H, R, **option)}
            cells = []
            for backward in (False, True):
                fns = {k: (lambda kf=kf: train_step(kf, y, dt) if backward else kf(y, dt)) for k, kf in kfs.items()}
                with torch.set_grad_enabled(backward):
                    ms = medians(fns, repeats)
                s0, s1 = ms["default"] / 1e3, ms["option"] / 1e3
                cells.append(f"{s0:.3f} → {s1:.3f} s ({s1 / s0:.2g}×)")
            lines.append(f"| {name} | {str(dtype)[6:]} | {cells[0]} | {cells[1]} |")
            print(lines[-1], flush=True)
    return lines


def train_step(kf: tl.KalmanFilter, y: torch.Tensor, dt: torch.Tensor) -> None:
    kf.zero_grad()
    kf(y, dt).log_likelihood.sum().backward()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tables", default="choice,matern,smoother")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=RESULTS / "bench_filter_choice.md")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    lines = [
        f"# filter algorithms (torch {torch.__version__}, {platform.machine()}, {args.threads} thread(s), "
        f"load {load:.1f} at start; a shared machine: medians of {args.repeats} interleaved repeats)",
    ]
    tables = {"choice": table_choice, "matern": table_matern, "smoother": table_smoother, "options": table_options}
    for name in args.tables.split(","):
        lines += ["", f"## {name}", ""] + tables[name](args.repeats)
    lines.append(f"\nload {os.getloadavg()[0]:.1f} at the end")
    args.out.parent.mkdir(exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
