r"""Benchmark: discretisation with PER-ELEMENT parameters (issue 10, item 1 and 2).

Workload: every batch element has its own random Hurwitz F (n, n) (``M = randn/√n``,
``F = M − (max Re λ(M) + 0.5) I``), L = I, its own SPD Qc = C Cᵀ/n + 0.1 I, and dt
log-uniform in [1e-3, 10]. Contestants, side by side in one process, timed round-robin:

* ``default`` — ``tl.discretize(F, L, Qc, dt)`` (scaling and doubling);
* ``naive``   — ``torch.matrix_exp`` of the (B, 2n, 2n) Van Loan block, ``Q = X Aᵀ``
  (the five lines a user writes).

Forward = (A, Q); forward+backward = also ``(A.sum() + Q.sum()).backward()`` w.r.t. F, Qc, dt.
Matrices/s = B / median time (``_timing.paired_s``: the two timed in alternation after warm-up
calls; process CPU time with ``--clock cpu``). The machine is shared by other sessions: the load
is printed at the head and the foot. The table is also written to
``experiments/results/bench_per_element[_quick].txt``.

    python experiments/bench_per_element.py [--quick] [--threads 1 2] [--clock cpu]
"""

from __future__ import annotations

import argparse
import math
import time

import torch
from _timing import machine_line, paired_s, saved

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


def time_pair(args, backward: bool, repeats: int, clock=time.perf_counter) -> dict[str, float]:
    """Median time per contestant, the two timed in alternation (``_timing.paired_s``)."""

    def call(fn):
        def once() -> None:
            xs = [a.detach().requires_grad_(backward and a.dim() > 0 and i != 1) for i, a in enumerate(args)]
            A, Q = fn(*xs)
            if backward:
                (A.sum() + Q.sum()).backward()

        return once

    t_default, t_naive = paired_s(call(default), call(naive_van_loan), repeat=repeats, warmup=2, clock=clock)
    return {"default": t_default, "naive": t_naive}


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
    repeats = 7 if args.quick else 25
    with saved("bench_per_element_quick.txt" if args.quick else "bench_per_element.txt"):
        table(args, repeats)


def table(args: argparse.Namespace, repeats: int) -> None:
    """Print the table (default vs naive per threads, dtype, n, B and pass) between two load lines."""
    print(f"# per-element discretisation, {args.clock} clock; {machine_line()}\n")
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
                        res = time_pair(prob, backward, repeats, CLOCKS[args.clock])
                        r = res["naive"] / res["default"]
                        print(
                            f"| {threads} | {n} | {dtype_name} | {B} | {'fwd+bwd' if backward else 'fwd'} | "
                            f"{B / res['default']:.3g} | {B / res['naive']:.3g} | {r:.2f}× |",
                            flush=True,
                        )
    print(f"\nat the end: {machine_line()}")


if __name__ == "__main__":
    main()
