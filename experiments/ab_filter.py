r"""Paired A/B of the filter and train-step cells: this checkout against a git revision.

Each cell (2-D constant velocity, T = 200 unless said, float64, 1 thread; a Matérn-3/2 GP
series of N = 4000) runs in a fresh process, alternately with the revision's package (A) and
this checkout's (B), for ``--rounds`` rounds; a cell's time is the median process CPU time
per call over a few seconds (robust to other processes on a shared machine). Reported:
each side's per-round figures and the ratio of their medians (after / before; < 1: faster),
and — independent of the machine's load — the aten operations and host synchronisations
(``.item()`` / ``bool()`` of a tensor) of one call. The cells are those of
experiments/bench_filter.py and bench_filter_choice.py.

    python experiments/ab_filter.py --base-rev 962118b [--rounds 3] [--seconds 3]

Prints the table and saves it to experiments/results/ab_filter.md (``--out``).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

ROOT = Path(__file__).resolve().parents[1]
CELLS = (
    "irregular:auto:1:200",
    "irregular:auto:100:200",
    "irregular:auto:1000:200",
    "regular:auto:1:200",
    "regular:auto:1000:200",
    "train:auto:100:200",
    "train:auto:1000:200",
    "irregular:sequential:1:200",
    "irregular:sequential:10:200",
    "irregular:scan:10:200",
    "irregular:auto:1:10000",
    "irregular:auto:10:10000",
    "gp:auto:1:4000",
)
KINDS = {
    "irregular": "filter, irregular dt",
    "regular": "filter, regular dt (one grid)",
    "train": "train step (fwd+bwd), irregular dt",
    "gp": "Matérn-3/2 GP series",
}


def run_cell(cell: str, seconds: float) -> tuple[float, int, int]:
    """Median process CPU time (ms) of one call of ``cell`` with the importable package, and
    the aten operations and host synchronisations of one call."""
    import numpy as np

    import torchsde_lti as tl  # the package of the side measured (PYTHONPATH)

    torch.set_num_threads(1)
    f64 = torch.float64
    kind, algorithm, B, T = cell.split(":")
    B, T = int(B), int(T)
    # the same filter with either API: algorithm= (this issue) or the parallel= flag before it
    kw = (
        {}
        if algorithm == "auto"
        else ({"algorithm": algorithm} if hasattr(tl, "ALGORITHMS") else {"parallel": algorithm == "scan"})
    )
    if kind == "gp":
        rng = np.random.default_rng(0)
        t = np.sort(rng.uniform(0.0, T / 5.0, T))
        sde = tl.models.matern(1.5, lengthscale=0.7, variance=1.9, dtype=f64)
        kf = tl.KalmanFilter(sde, torch.tensor([[1.0, 0.0]], dtype=f64), torch.tensor([[0.05]], dtype=f64), **kw)
        y = torch.as_tensor(np.sin(t) + 0.3 * rng.standard_normal(T))[:, None]
        dt = torch.as_tensor(np.diff(t, prepend=t[0]))
    else:
        g = torch.Generator().manual_seed(0)
        regular = kind == "regular"
        dt = torch.ones(B, T, dtype=f64) if regular else torch.rand(B, T, generator=g, dtype=f64) * 1.95 + 0.05
        vel = (torch.randn(B, T, 2, generator=g, dtype=f64) * dt.sqrt()[..., None]).cumsum(1)
        y = (vel * dt[..., None]).cumsum(1) + math.sqrt(0.5) * torch.randn(B, T, 2, generator=g, dtype=f64)
        dt = dt[0] if regular else dt
        cv = tl.models.constant_velocity(dim=2, q=1.0, dtype=f64)
        H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=f64)
        kf = tl.KalmanFilter(cv, H, 0.5 * torch.eye(2, dtype=f64), P0=100 * torch.eye(4, dtype=f64), learn=("R",), **kw)

    def call() -> None:
        if kind == "train":
            for p in kf.parameters():
                p.grad = None
            (-kf(y, dt).log_likelihood.sum()).backward()
        else:
            with torch.no_grad():
                kf(y, dt)

    call()
    call()
    times = []
    end = time.perf_counter() + seconds
    while time.perf_counter() < end or len(times) < 3:
        t0 = time.process_time()
        call()
        times.append(time.process_time() - t0)
    counter = Counter()
    with counter:
        call()
    return statistics.median(times) * 1e3, counter.ops, counter.syncs


class Counter(TorchDispatchMode):
    """Counts the aten operations dispatched, and those that read a value to the host."""

    syncing = (torch.ops.aten._local_scalar_dense.default, torch.ops.aten.is_nonzero.default)

    def __init__(self) -> None:
        super().__init__()
        self.ops = self.syncs = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN204
        self.ops += 1
        self.syncs += func in self.syncing
        return func(*args, **(kwargs or {}))


def measure(package_root: Path, cell: str, seconds: float) -> tuple[float, int, int]:
    env = {**os.environ, "PYTHONPATH": str(package_root), "OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, __file__, "--cell", cell, "--seconds", str(seconds)],
        env=env,
        cwd=package_root,
        capture_output=True,
        text=True,
        check=True,
    )
    ms, ops, syncs = out.stdout.strip().splitlines()[-1].split()
    return float(ms), int(ops), int(syncs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base-rev", default="main", help="git revision of the 'before' side (A)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=3.0, help="measuring time per cell and process")
    ap.add_argument("--cells", nargs="+", default=list(CELLS))
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "ab_filter.md")
    ap.add_argument("--cell", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.cell:
        ms, ops, syncs = run_cell(args.cell, args.seconds)
        print(f"{ms:.4f} {ops} {syncs}")
        return
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "base"
        base.mkdir()
        tree = subprocess.run(["git", "archive", args.base_rev], cwd=ROOT, capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(base)], input=tree, check=True)
        rev = subprocess.run(
            ["git", "rev-parse", "--short", args.base_rev], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        load0 = os.getloadavg()[0]
        times: dict[str, dict[str, list[float]]] = {c: {"A": [], "B": []} for c in args.cells}
        counts: dict[str, dict[str, tuple[int, int]]] = {c: {} for c in args.cells}
        for _ in range(args.rounds):
            for cell in args.cells:
                for side, root in (("A", base), ("B", ROOT)):
                    ms, ops, syncs = measure(root, cell, args.seconds)
                    times[cell][side].append(ms)
                    counts[cell][side] = (ops, syncs)
                print(f"  {cell}: A {times[cell]['A'][-1]:.1f} ms, B {times[cell]['B'][-1]:.1f} ms", flush=True)
    lines = [
        f"# Paired A/B: before = {rev} (A), after = {head} plus the working tree (B)",
        "",
        f"`python experiments/ab_filter.py --base-rev {args.base_rev} --rounds {args.rounds} --seconds {args.seconds}`: "
        f"median process CPU time per call (1 thread), each cell in a fresh process, A and B alternating; "
        f"load {load0:.2f} at the start, {os.getloadavg()[0]:.2f} at the end (a shared machine: the per-round "
        "spread is the noise).",
        "",
        "| cell | algorithm | B | T | before (ms), per round | after (ms), per round | after / before (medians) "
        "| aten ops per call, before → after | host syncs per call, before → after |",
        "|---|---|---:|---:|---|---|---:|---:|---:|",
    ]
    for cell in args.cells:
        kind, algorithm, B, T = cell.split(":")
        a, b = times[cell]["A"], times[cell]["B"]
        (ops_a, sync_a), (ops_b, sync_b) = counts[cell]["A"], counts[cell]["B"]
        lines.append(
            f"| {KINDS[kind]} | {algorithm} | {B} | {T} | {' / '.join(f'{x:.1f}' for x in a)} | "
            f"{' / '.join(f'{x:.1f}' for x in b)} | {statistics.median(b) / statistics.median(a):.2f} "
            f"| {ops_a} → {ops_b} | {sync_a} → {sync_b} |"
        )
    text = "\n".join(lines) + "\n"
    print("\n" + text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)


if __name__ == "__main__":
    main()
