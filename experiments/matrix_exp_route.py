# ruff: noqa: B023  (the closures are timed inside the loop that binds them)
r"""Would the default gain from routing small steps to torch.matrix_exp of the Van Loan block (issue 19)?

Accuracy: relative Frobenius errors of A and Q against a 30-digit reference (``tests.reference.mp_doubling``)
on the per-element workload's F (4 elements per n) at ‖F‖_F dt = x, for the naive block
``[[F, W], [0, −Fᵀ]] dt`` and the block with W scaled by the power of two s that makes
‖s W dt‖₁ ≈ 1 (Q = X Aᵀ / s; Q is linear in W), which forces torch's degree-18 Taylor.
Speed: median thread CPU µs at B = 1 (torch at one thread, alternating) of the doubling
(``_doubling.doubling`` of checked inputs) and of the balanced block route including its assembly.

    python experiments/matrix_exp_route.py [--out experiments/results/matrix_exp_route.md]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench_per_element import make_problem

from tests.reference import mp_doubling
from torchsde_lti.core import _doubling
from torchsde_lti.core.validation import sde_inputs


def van_loan(F, W, dt, balance: bool):  # type: ignore[no-untyped-def]
    """(A, Q) from expm([[F, sW], [0, −Fᵀ]] dt), Q = X Aᵀ / s; s = 1 or the balancing power of two."""
    n = F.shape[-1]
    d = dt[..., None, None]
    Fd, Wd = F * d, W * d
    s = torch.ones_like(d)
    if balance:
        s = torch.exp2(torch.round(-torch.log2(Wd.abs().sum(-2).amax(-1, keepdim=True)[..., None])))
    top = torch.cat([Fd, Wd * s], -1)
    E = torch.matrix_exp(torch.cat([top, torch.cat([torch.zeros_like(Fd), -Fd.mT], -1)], -2))
    A = E[..., :n, :n]
    Q = E[..., :n, n:] @ A.mT / s
    return A, 0.5 * (Q + Q.mT)


def accuracy(lines: list[str]) -> None:
    lines += ["| dtype | n | ‖F‖ dt | naive A | naive Q | balanced A | balanced Q |", "|---|---|---|---|---|---|---|"]
    for dtype in (torch.float64, torch.float32):
        for n in (2, 4, 8):
            F, L, Qc, _ = make_problem(n, 4, torch.float64, seed=n)
            for x in (1e-6, 1e-4, 1e-2, 0.1, 0.25, 0.5, 1.0):
                err = np.zeros(4)
                for i in range(4):
                    W = L @ Qc[i] @ L.T
                    dt = x / torch.linalg.matrix_norm(F[i])
                    A_ref, Q_ref, _ = mp_doubling(F[i].numpy(), W.numpy(), None, float(dt), dps=30)
                    for j, bal in enumerate((False, True)):
                        A, Q = (t.double().numpy() for t in van_loan(F[i].to(dtype), W.to(dtype), dt.to(dtype), bal))
                        err[2 * j] = max(err[2 * j], np.linalg.norm(A - A_ref) / np.linalg.norm(A_ref))
                        err[2 * j + 1] = max(err[2 * j + 1], np.linalg.norm(Q - Q_ref) / np.linalg.norm(Q_ref))
                lines.append(f"| {str(dtype)[6:]} | {n} | {x:g} | " + " | ".join(f"{e:.1e}" for e in err) + " |")
                print(lines[-1], flush=True)


def speed(lines: list[str]) -> None:
    def once(fn, inner: int = 200) -> float:  # type: ignore[no-untyped-def]
        t0 = time.thread_time()
        for _ in range(inner):
            fn()
        return (time.thread_time() - t0) / inner * 1e6

    lines += ["", "| dtype | n | doubling (µs) | balanced matrix_exp route (µs) |", "|---|---|---|---|"]
    for dtype in (torch.float64, torch.float32):
        for n in (2, 4, 8):
            F, L, Qc, dt = make_problem(n, 1, dtype)
            x = sde_inputs(F, L, Qc, dt)
            assert x.W is not None
            fns = [lambda: _doubling.doubling(x), lambda: van_loan(x.F, x.W, dt, True)]
            times: list[list[float]] = [[], []]
            for _ in range(15):
                for t, fn in zip(times, fns):
                    t.append(once(fn))
            lines.append(
                f"| {str(dtype)[6:]} | {n} | " + " | ".join(f"{statistics.median(t):.0f}" for t in times) + " |"
            )
            print(lines[-1], flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    lines = [f"# torch.matrix_exp route for small steps (torch {torch.__version__}, load {os.getloadavg()[0]:.2f})", ""]
    accuracy(lines)
    speed(lines)
    lines.append(f"\nload at end {os.getloadavg()[0]:.2f}")
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
