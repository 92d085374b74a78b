"""Hostile-SGD study of the Hurwitz parametrisation (issue 11, item 1).

    python experiments/hurwitz_robustness.py            # full grid: 200 steps, 3 seeds
    python experiments/hurwitz_robustness.py --steps 50 --seeds 1

``LTISDE(F=−I, L=I, Qc=I, F_constraint="hurwitz")`` (n = 2, 3, 4, 6; float32 and float64)
is trained by plain SGD (lr 0.1, 0.5, 1.0) on an unbounded loss with a random sign each step,
``−ξ₁ Σ A − 3 ξ₂ tr Q`` with ξ ∈ {±1} and 8 steps dt ~ U(0, 1) per step (A, Q = the exact
discretisation): the loss pushes F towards the imaginary axis and beyond, and Qc towards 0
and infinity. At every step: F finite, max Re λ(F) < 0 (numpy eigenvalues in float64),
Qc finite and positive definite (by certificate: its Cholesky factor's diagonal is positive
and finite; eigenvalues of Qc as computed are listed too), and (float64) ``right_inverse`` round trip
``‖F(right_inverse(F)) − F‖ / ‖F‖``. Writes ``experiments/results/hurwitz_robustness.md``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch

import torchsde_lti as tl

RESULTS = Path(__file__).resolve().parents[1] / "experiments" / "results"


def hostile_run(n: int, dtype: torch.dtype, lr: float, steps: int, seed: int, round_trip: bool) -> dict[str, float]:
    """One hostile SGD run; returns the worst values seen over all steps."""
    g = torch.Generator().manual_seed(seed)
    eye = torch.eye(n, dtype=dtype)
    sde = tl.LTISDE(-eye, eye, eye, F_constraint="hurwitz")
    opt = torch.optim.SGD(sde.parameters(), lr=lr)
    param = sde.parametrizations.F[0]
    out = {
        "max_re_lambda": -math.inf,
        "max_abs_F": 0.0,
        "min_eig_Qc": math.inf,
        "round_trip": 0.0,
        "nonfinite": 0.0,
        "exceptions": 0.0,
        "out_of_reach": 0.0,
    }
    for _ in range(steps):
        dt = torch.rand(8, generator=g).to(dtype)
        xi = torch.randint(0, 2, (2,), generator=g).to(dtype) * 2 - 1
        try:
            d = sde(dt)
            loss = -(d.A.sum() * xi[0]) - 3.0 * torch.diagonal(d.Q, dim1=-2, dim2=-1).sum() * xi[1]
            opt.zero_grad()
            loss.backward()
            opt.step()
        except (ValueError, RuntimeError):
            out["exceptions"] += 1
            break
        with torch.no_grad():
            F, Qc = sde.F.to(torch.float64), sde.Qc.to(torch.float64)
        if not (bool(torch.isfinite(F).all()) and bool(torch.isfinite(Qc).all())):
            out["nonfinite"] += 1
            break
        out["max_re_lambda"] = max(out["max_re_lambda"], float(np.linalg.eigvals(F.numpy()).real.max()))
        out["max_abs_F"] = max(out["max_abs_F"], float(F.abs().max()))
        c = sde.parametrizations.Qc[0].factor(sde.parametrizations.Qc.original.detach().to(torch.float64))
        if not (bool((torch.diagonal(c) > 0).all()) and bool(torch.isfinite(c).all())):
            out["nonfinite"] += 1
        out["min_eig_Qc"] = min(out["min_eig_Qc"], float(torch.linalg.eigvalsh(Qc).min()))
        if round_trip and dtype == torch.float64:
            try:
                with torch.no_grad():
                    back = param(param.right_inverse(F))
            except ValueError:  # reached, but beyond right_inverse's R = rI preimage
                out["out_of_reach"] += 1
                continue
            out["round_trip"] = max(
                out["round_trip"], float(torch.linalg.matrix_norm(back - F) / torch.linalg.matrix_norm(F))
            )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=RESULTS / "hurwitz_robustness.md")
    args = parser.parse_args()
    torch.set_num_threads(1)
    lines = [
        f"# Hostile SGD on the Hurwitz parametrisation ({args.steps} steps, {args.seeds} seeds per cell)",
        "",
        f"`python experiments/hurwitz_robustness.py --steps {args.steps} --seeds {args.seeds}`; worst over seeds and steps.",
        "",
        "| dtype | n | lr | max Re λ(F) | max abs F | min eig Qc (computed) | round trip (f64) | steps out of reach (f64) | non-finite | exceptions |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for dtype in (torch.float32, torch.float64):
        for n in (2, 3, 4, 6):
            for lr in (0.1, 0.5, 1.0):
                runs = [hostile_run(n, dtype, lr, args.steps, s, True) for s in range(args.seeds)]
                worst = {
                    "max_re_lambda": max(r["max_re_lambda"] for r in runs),
                    "max_abs_F": max(r["max_abs_F"] for r in runs),
                    "min_eig_Qc": min(r["min_eig_Qc"] for r in runs),
                    "round_trip": max(r["round_trip"] for r in runs),
                    "nonfinite": sum(r["nonfinite"] for r in runs),
                    "exceptions": sum(r["exceptions"] for r in runs),
                    "out_of_reach": sum(r["out_of_reach"] for r in runs),
                }
                rt = f"{worst['round_trip']:.1e}" if dtype == torch.float64 else "–"
                line = (
                    f"| {str(dtype).removeprefix('torch.')} | {n} | {lr} | {worst['max_re_lambda']:.3g} | "
                    f"{worst['max_abs_F']:.3g} | {worst['min_eig_Qc']:.3g} | {rt} | {int(worst['out_of_reach'])} | {int(worst['nonfinite'])} | "
                    f"{int(worst['exceptions'])} |"
                )
                print(line, flush=True)
                lines.append(line)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
