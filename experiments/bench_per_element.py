r"""Benchmark: discretisation with PER-ELEMENT parameters (issue 10, item 1 and 2).

Workload: every batch element has its own random Hurwitz F (n, n) (``M = randn/√n``,
``F = M − (max Re λ(M) + 0.5) I``), L = I, its own SPD Qc = C Cᵀ/n + 0.1 I, and dt
log-uniform in [1e-3, 10]. Contestants, side by side in one process, timed round-robin:

* ``default`` — ``tl.discretize(F, L, Qc, dt)`` (scaling and doubling);
* ``naive``   — ``torch.matrix_exp`` of the (B, 2n, 2n) Van Loan block, ``Q = X Aᵀ``
  (the five lines a user writes).

Forward = (A, Q); forward+backward = also ``(A.sum() + Q.sum()).backward()`` w.r.t. F, Qc, dt.
Matrices/s = B / median wall time (warm-up call first); each repeat calls both contestants,
in alternating order (paired). The machine is shared by other
sessions: medians of repeats, still noisy.

    python experiments/bench_per_element.py [--quick] [--threads 1 2]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time

import torch

import torchsde_lti as tl


def naive_van_loan(F, L, Qc, dt):
    """expm([[F, W], [0, -Fᵀ]] dt) = [[A, X], [0, ·]], Q = X Aᵀ. F (B, n, n), dt (B,)."""
    n = F.shape[-1]
    W, d = L @ Qc @ L.mT, dt[:, None, None]
    top = torch.cat([F * d, W * d], -1)
    bottom = torch.cat([torch.zeros_like(top[..., :n]), -F.mT * d], -1)
    E = torch.matrix_exp(torch.cat([top, bottom], -2))
    A = E[:, :n, :n]
    return A, E[:, :n, n:] @ A.mT


def default(F, L, Qc, dt):
    d = tl.discretize(F, L, Qc, dt)
    return d.A, d.Q


CONTESTANTS = {"default": default, "naive": naive_van_loan}


def make_problem(n: int, B: int, dtype: torch.dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    M = torch.randn(B, n, n, generator=g, dtype=f64) / math.sqrt(n)
    shift = torch.linalg.eigvals(M).real.amax(-1) + 0.5
    F = M - shift[:, None, None] * torch.eye(n, dtype=f64)
    C = torch.randn(B, n, n, generator=g, dtype=f64)
    Qc = C @ C.mT / n + 0.1 * torch.eye(n, dtype=f64)
    L = torch.eye(n, dtype=f64)
    dt = torch.exp(torch.empty(B, dtype=f64).uniform_(math.log(1e-3), math.log(10.0), generator=g))
    return F.to(dtype), L.to(dtype), Qc.to(dtype), dt.to(dtype)


CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}


def time_pair(fns, args, backward: bool, repeats: int, budget: float, clock=time.perf_counter) -> dict[str, float]:
    """Median wall time per contestant; each repeat calls every contestant once, alternating
    the order, so that background load hits them alike (paired)."""

    def once(fn) -> float:
        xs = [a.detach().requires_grad_(backward and a.dim() > 0 and i != 1) for i, a in enumerate(args)]
        t0 = clock()
        A, Q = fn(*xs)
        if backward:
            (A.sum() + Q.sum()).backward()
        return clock() - t0

    names = list(fns)
    for name in names:
        once(fns[name])
    times: dict[str, list[float]] = {name: [] for name in names}
    start = time.perf_counter()
    r = 0
    while r < repeats or (time.perf_counter() - start < budget and r < 20 * repeats):
        for name in names if r % 2 == 0 else names[::-1]:
            times[name].append(once(fns[name]))
        r += 1
    return {name: statistics.median(t) for name, t in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--sizes", type=int, nargs="+", default=[2, 4, 8])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 100, 10000])
    ap.add_argument("--dtypes", nargs="+", default=["float64", "float32"])
    ap.add_argument(
        "--clock",
        choices=list(CLOCKS),
        default="wall",
        help="wall time, or the process's CPU time (robust to other processes at 1 thread)",
    )
    args = ap.parse_args()
    repeats = 5 if args.quick else 25
    budget = 0.5 if args.quick else 2.0
    print(
        f"# per-element discretisation benchmark (torch {torch.__version__}, cpu_count {os.cpu_count()}, "
        f"load {os.getloadavg()[0]:.2f}; {args.clock} clock; shared machine: medians of repeats, noisy)\n"
    )
    print("| threads | n | dtype | B | pass | default (mat/s) | naive (mat/s) | default/naive |")
    print("|---|---|---|---|---|---|---|---|")
    for threads in args.threads:
        torch.set_num_threads(threads)
        for dtype_name in args.dtypes:
            dtype = getattr(torch, dtype_name)
            for n in args.sizes:
                for B in args.batches:
                    prob = make_problem(n, B, dtype)
                    for backward in (False, True):
                        res = time_pair(CONTESTANTS, prob, backward, repeats, budget, CLOCKS[args.clock])
                        r = res["naive"] / res["default"]
                        print(
                            f"| {threads} | {n} | {dtype_name} | {B} | {'fwd+bwd' if backward else 'fwd'} | "
                            f"{B / res['default']:.3g} | {B / res['naive']:.3g} | {r:.2f}× |",
                            flush=True,
                        )
    print(f"\nload at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
