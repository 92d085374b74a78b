# ruff: noqa: B023  (the closures are timed inside the loop that binds them)
r"""Where the time of one small ``discretize`` call goes (B = 1 and 100), beside the naive Van Loan.

Each stage of the default's call (argument checks and conversion ``sde_inputs``, the
doubling, the result check where the host values cannot rule out an overflow) is timed
alone, as median thread CPU time over repeats (``time.thread_time``: robust to other
processes on a shared machine), torch at one thread, next to the naive five lines and a bare
``torch.matrix_exp`` of the (2n, 2n) block. Aten operations per call are counted too.

    python experiments/profile_small_call.py [--out experiments/results/profile_small_call.md]
"""

from __future__ import annotations

import argparse
import collections
import os
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_per_element import default, make_problem, naive_van_loan

from torchsde_lti.core import _doubling, discretization
from torchsde_lti.core.validation import sde_inputs


class _Count(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.ops: collections.Counter[str] = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
        self.ops[str(func.overloadpacket.__name__)] += 1
        return func(*args, **(kwargs or {}))


def ops(fn) -> int:  # type: ignore[no-untyped-def]
    with _Count() as c:
        fn()
    return sum(c.ops.values())


def cpu_us(fn, repeats: int = 7, inner: int = 200) -> float:  # type: ignore[no-untyped-def]
    for _ in range(20):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.thread_time()
        for _ in range(inner):
            fn()
        times.append((time.thread_time() - t0) / inner)
    return statistics.median(times) * 1e6


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    lines = [
        (
            f"# One small discretize call, stage by stage (torch {torch.__version__}, 1 thread, thread CPU µs, "
            f"load {os.getloadavg()[0]:.2f})\n"
        ),
        (
            "| n | dtype | B | naive | default | sde_inputs | doubling | "
            "result check | bare torch.matrix_exp | ops naive / default |"
        ),
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    print("\n".join(lines), flush=True)
    for dtype in (torch.float64, torch.float32):
        for n in (2, 4, 8):
            for B in (1, 100):
                F, L, Qc, dt = make_problem(n, B, dtype)
                x = sde_inputs(F, L, Qc, dt)
                A, Q, G = discretization._run(x, "doubling", False)
                W, d = L @ Qc @ L.mT, dt[:, None, None]  # the naive's Van Loan block
                block = torch.cat([torch.cat([F * d, W * d], -1), torch.cat([torch.zeros_like(F), -F.mT * d], -1)], -2)
                t = {
                    "naive": cpu_us(lambda: naive_van_loan(F, L, Qc, dt)),
                    "default": cpu_us(lambda: default(F, L, Qc, dt)),
                    "sde_inputs": cpu_us(lambda: sde_inputs(F, L, Qc, dt)),
                    "doubling": cpu_us(lambda: _doubling.doubling(x)),
                    "check": cpu_us(lambda: discretization._check_result(x, A, Q, G, "doubling")),
                    "bare": cpu_us(lambda: torch.matrix_exp(block)),
                }
                row = (
                    f"| {n} | {str(dtype)[6:]} | {B} | "
                    + " | ".join(f"{t[k]:.0f}" for k in t)
                    + f" | {ops(lambda: naive_van_loan(F, L, Qc, dt))} / {ops(lambda: default(F, L, Qc, dt))} |"
                )
                lines.append(row)
                print(row, flush=True)
    lines.append(f"\nload at end {os.getloadavg()[0]:.2f}")
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
