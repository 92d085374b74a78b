r"""Benchmark: throughput and accuracy of the discretisation (A, Q) of ``dx = F x dt + L dβ``.

Contestants, side by side in one run:

* ``default``  — ``torchsde_lti.discretize(F, L, Qc, dt)`` (scaling and doubling);
* ``naive``    — Van Loan's block exponential through ``torch.matrix_exp`` of the
  (B, 2n, 2n) block ``[[F, W], [0, -Fᵀ]] dt`` (W = L Qc Lᵀ), ``Q = X Aᵀ`` — the five lines a
  user writes (:func:`naive_van_loan`);
* ``scipy``    — the same block through ``scipy.linalg.expm`` on the stacked (B, 2n, 2n)
  numpy array (float64 only, no autograd);
* ``filterpy`` — ``filterpy.common.van_loan_discretization(F, G, dt)`` in a Python loop, with
  ``G = L chol(Qc)`` so that ``G Gᵀ = W`` (float64 only, no autograd, B ≤ 100).

Throughput workload: F is a random Hurwitz matrix (seed 0): ``M = randn(n, n)/√n``,
``F = M − (max Re λ(M) + 0.5) I``, divided by ``ν = max(‖F‖₁, ‖F‖∞)`` so that ν = 1; L is
(n, s) with s = max(1, n/2), Qc = C Cᵀ + 0.1 I random SPD. F, L, Qc are shared by the batch
(the training case); ``dt`` is per element, log-uniform with ``ν dt ∈ [1e-2, 1e2]``.
Forward = compute (A, Q); forward+backward = also ``(A.sum() + Q.sum()).backward()`` with
respect to F, Qc and dt. Matrices/s = B / median wall time over repeats (after a warm-up call);
contestants are timed round-robin so that background load hits them alike.

Accuracy: the stiff cases of issue 2 against a high-precision reference (mpmath, 50 digits):
for Hurwitz F, ``Q = P∞ − A P∞ Aᵀ`` with ``A = expm(F dt)`` and P∞ from the Lyapunov
equation (the cancellation is harmless at 50 digits); closed forms for the integrated OU and
the nilpotent chain. Reported: relative Frobenius error of Q and whether Q is PSD
(λ_min(sym Q) ≥ −n·eps·‖Q‖₂).

    python experiments/bench_discretize.py            # full run (~8 min on 2 cores)
    python experiments/bench_discretize.py --quick    # ~1 min smoke run
"""

from __future__ import annotations

import argparse
import gc
import math
import platform
import statistics
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import mpmath
import numpy as np
import scipy
import scipy.linalg
import torch
from _timing import machine_line
from filterpy.common import van_loan_discretization

import torchsde_lti as tl
from torchsde_lti.training.outputs import write_json

RESULTS = Path(__file__).resolve().parent / "results"
CONTESTANTS = ("default", "naive", "scipy", "filterpy")
FILTERPY_MAX_BATCH = 100
# torch.matrix_exp's backward exponentiates a (4n, 4n) block: measured peak ≈ 22·B·(4n)²·itemsize
# bytes for the naive forward+backward (1.8 GB at n = 8, B = 1e4, float64). Cells above this
# budget are skipped rather than risking the out-of-memory killer on a shared machine.
NAIVE_BACKWARD_MEMORY_BUDGET = 6e9


# ----------------------------------------------------------------------------------------
# Contestants
# ----------------------------------------------------------------------------------------


def naive_van_loan(
    F: torch.Tensor, L: torch.Tensor, Qc: torch.Tensor, dt: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """What a user writes: expm([[F, W], [0, -Fᵀ]] dt) = [[A, X], [0, A⁻ᵀ]], Q = X Aᵀ.

    F: (n, n), L: (n, s), Qc: (s, s), dt: (B,) -> A, Q: (B, n, n).
    """
    n = F.shape[-1]
    W, d = L @ Qc @ L.mT, dt[:, None, None]
    C = torch.cat([torch.cat([F * d, W * d], -1), torch.cat([torch.zeros_like(F * d), -F.mT * d], -1)], -2)
    E = torch.matrix_exp(C)
    A = E[:, :n, :n]
    return A, E[:, :n, n:] @ A.mT


def default_discretize(
    F: torch.Tensor, L: torch.Tensor, Qc: torch.Tensor, dt: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The library's default method. Shapes as :func:`naive_van_loan`."""
    d = tl.discretize(F, L, Qc, dt)
    return d.A, d.Q


def library_matrix_exp(
    F: torch.Tensor, L: torch.Tensor, Qc: torch.Tensor, dt: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The library's ``method="matrix_exp"`` (accuracy table only), unchecked: the values it
    computes, where a checked call refuses a Q that is not PSD."""
    d = tl.discretize(F, L, Qc, dt, method="matrix_exp", validate_args=False)
    return d.A, d.Q


def scipy_van_loan(F: np.ndarray, W: np.ndarray, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """scipy.linalg.expm on the stacked (B, 2n, 2n) Van Loan blocks. F, W: (n, n); dt: (B,)."""
    n = F.shape[-1]
    C = np.zeros((dt.shape[0], 2 * n, 2 * n), dtype=F.dtype)
    d = dt[:, None, None]
    C[:, :n, :n] = F * d
    C[:, :n, n:] = W * d
    C[:, n:, n:] = -F.T * d
    E = scipy.linalg.expm(C)
    A = E[:, :n, :n]
    return A, E[:, :n, n:] @ np.swapaxes(A, -1, -2)


def filterpy_loop(F: np.ndarray, G: np.ndarray, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """filterpy.common.van_loan_discretization element by element. G Gᵀ = W; dt: (B,)."""
    out = [van_loan_discretization(F, G, float(h)) for h in dt]
    return np.stack([a for a, _ in out]), np.stack([q for _, q in out])


# ----------------------------------------------------------------------------------------
# Throughput
# ----------------------------------------------------------------------------------------


@dataclass
class Problem:
    """Shared parameters and per-element dt of the throughput workload (float64 master copy)."""

    F: torch.Tensor  # (n, n)
    L: torch.Tensor  # (n, s)
    Qc: torch.Tensor  # (s, s)
    dt: torch.Tensor  # (B_max,)


def make_problem(n: int, batch_max: int, seed: int = 0) -> Problem:
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    M = torch.randn(n, n, generator=g, dtype=f64) / math.sqrt(n)
    F = M - (torch.linalg.eigvals(M).real.max() + 0.5) * torch.eye(n, dtype=f64)
    F = F / torch.maximum(F.abs().sum(0).max(), F.abs().sum(1).max())
    s = max(1, n // 2)
    L = torch.randn(n, s, generator=g, dtype=f64)
    C = torch.randn(s, s, generator=g, dtype=f64)
    Qc = C @ C.T + 0.1 * torch.eye(s, dtype=f64)
    dt = 10.0 ** (torch.rand(batch_max, generator=g, dtype=f64) * 4.0 - 2.0)
    return Problem(F, L, Qc, dt)


def make_call(name: str, prob: Problem, batch: int, dtype: torch.dtype, backward: bool) -> Callable[[], object] | None:
    """A zero-argument closure running one contestant once, or None if not applicable."""
    if name in ("scipy", "filterpy"):
        if dtype != torch.float64 or backward:
            return None
        if name == "filterpy" and batch > FILTERPY_MAX_BATCH:
            return None
        F = prob.F.numpy()
        dt = prob.dt[:batch].numpy().copy()
        if name == "scipy":
            W = (prob.L @ prob.Qc @ prob.L.T).numpy()
            return lambda: scipy_van_loan(F, W, dt)
        G = (prob.L @ torch.linalg.cholesky(prob.Qc)).numpy()
        return lambda: filterpy_loop(F, G, dt)
    fn = default_discretize if name == "default" else naive_van_loan
    itemsize = torch.finfo(dtype).bits // 8
    if (
        name == "naive"
        and backward
        and 22 * batch * (4 * prob.F.shape[0]) ** 2 * itemsize > NAIVE_BACKWARD_MEMORY_BUDGET
    ):
        return None
    F, L, Qc = (x.to(dtype) for x in (prob.F, prob.L, prob.Qc))
    dt = prob.dt[:batch].to(dtype)
    if not backward:

        def forward() -> object:
            with torch.no_grad():
                return fn(F, L, Qc, dt)

        return forward

    def forward_backward() -> object:
        Fg, Qg, dg = (x.detach().clone().requires_grad_(True) for x in (F, Qc, dt))
        A, Q = fn(Fg, L, Qg, dg)
        (A.sum() + Q.sum()).backward()
        return Fg.grad

    return forward_backward


@dataclass
class Cell:
    n: int
    dtype: str
    batch: int
    mode: str  # "fwd" or "fwd+bwd"
    times: dict[str, list[float]] = field(default_factory=dict)
    bad: dict[str, float] = field(default_factory=dict)  # fraction of non-finite / non-PSD Q

    def rate(self, name: str) -> float | None:
        t = self.times.get(name)
        return self.batch / statistics.median(t) if t else None


def bad_fraction(Q: torch.Tensor | np.ndarray) -> float:
    """Fraction of elements whose Q has a NaN/Inf or λ_min(sym Q) < −n eps ‖Q‖₂."""
    Q = torch.as_tensor(Q).detach()
    eps = torch.finfo(Q.dtype).eps
    Q = Q.to(torch.float64)
    finite = torch.isfinite(Q).flatten(-2).all(-1)
    Qs = torch.where(finite[:, None, None], 0.5 * (Q + Q.mT), torch.zeros_like(Q))
    ev = torch.linalg.eigvalsh(Qs)
    tol = Q.shape[-1] * eps * ev.abs().amax(-1)
    psd = ev[:, 0] >= -tol
    return float((~(finite & psd)).double().mean())


def time_cell(
    cell: Cell,
    calls: dict[str, Callable[[], object]],
    warm: dict[str, Callable[[], object]],
    repeats: int,
    budget_s: float,
    hard_s: float,
) -> None:
    """Round-robin timing: warm-up once each, then repeat until `repeats` runs, or at least
    3 runs and `budget_s` spent, or at least 1 run and `hard_s` spent (per contestant)."""
    for fn in warm.values():
        fn()
    spent = {k: 0.0 for k in calls}
    active = dict(calls)
    while active:
        for name in list(active):
            t0 = time.perf_counter()
            out = active[name]()
            dt = time.perf_counter() - t0
            if cell.mode == "fwd" and name not in cell.bad:
                Q = out[1]  # type: ignore[index]
                cell.bad[name] = bad_fraction(Q)
            cell.times.setdefault(name, []).append(dt)
            spent[name] += dt
            k = len(cell.times[name])
            if k >= repeats or (k >= 3 and spent[name] > budget_s) or spent[name] > hard_s:
                del active[name]


def run_throughput(quick: bool) -> list[Cell]:
    ns = (2, 4) if quick else (2, 4, 8)
    batches = (1, 100, 10_000) if quick else (1, 100, 10_000, 100_000)
    repeats, budget_s, hard_s = (3, 0.3, 2.0) if quick else (5, 1.5, 12.0)
    cells: list[Cell] = []
    for n in ns:
        prob = make_problem(n, max(batches))
        for dtype in (torch.float32, torch.float64):
            for mode in ("fwd", "fwd+bwd"):
                for batch in batches:
                    cell = Cell(n, str(dtype).replace("torch.", ""), batch, mode)
                    calls, warm = {}, {}
                    for name in CONTESTANTS:
                        c = make_call(name, prob, batch, dtype, mode == "fwd+bwd")
                        if c is not None:
                            calls[name] = c
                            warm[name] = make_call(name, prob, min(batch, 10_000), dtype, mode == "fwd+bwd")  # type: ignore[assignment]
                    gc.collect()  # the previous cell's garbage (large autograd graphs) is not freed inside this one
                    time_cell(cell, calls, warm, repeats, budget_s, hard_s)
                    cells.append(cell)
                    rates = ", ".join(f"{k} {cell.rate(k):.3g}/s" for k in cell.times)
                    print(f"  n={n} {cell.dtype} {mode:7s} B={batch:<6d} {rates}", flush=True)
    return cells


# ----------------------------------------------------------------------------------------
# Accuracy on stiff cases
# ----------------------------------------------------------------------------------------


@dataclass
class Case:
    name: str
    F: np.ndarray
    L: np.ndarray
    Qc: np.ndarray
    dt: float
    reference: str  # "lyapunov", "iou" (integrated OU closed form), "nilpotent"


def stiff_cases() -> list[Case]:
    cases = []
    for kdt in (20.0, 40.0, 60.0):
        k = 1.0
        cases.append(
            Case(
                f"integrated OU k·dt={kdt:g}",
                np.array([[0.0, 1.0], [0.0, -k]]),
                np.array([[0.0], [1.0]]),
                np.array([[1.0]]),
                kdt / k,
                "iou",
            )
        )
    for ldt in (100.0, 1000.0):
        cases.append(
            Case(f"scalar OU λ·dt={ldt:g}", np.array([[-1.0]]), np.array([[1.0]]), np.array([[2.0]]), ldt, "lyapunov")
        )
    nonnormal = np.array([[-1e-3, 1e2], [0.0, -1e3]])
    for dt in (1.0, 50.0):
        cases.append(Case(f"non-normal λ=−1e−3,−1e3 dt={dt:g}", nonnormal, np.eye(2), np.eye(2), dt, "lyapunov"))
    jordan = -np.eye(3) + np.diag([1.0, 1.0], 1)
    for dt in (30.0,):
        cases.append(
            Case(
                f"Jordan block λ=−1 (3×3) dt={dt:g}",
                jordan,
                np.array([[0.0], [0.0], [1.0]]),
                np.array([[1.0]]),
                dt,
                "lyapunov",
            )
        )
    chain = np.diag([1.0, 1.0], 1)
    for dt in (1e-4, 1e3):
        cases.append(
            Case(
                f"nilpotent chain (3×3) dt={dt:g}",
                chain,
                np.array([[0.0], [0.0], [1.0]]),
                np.array([[1.0]]),
                dt,
                "nilpotent",
            )
        )
    return cases


def _mp(a: np.ndarray) -> mpmath.matrix:
    return mpmath.matrix(a.tolist())


def reference_Q(case: Case) -> np.ndarray:
    """Q at mp.dps = 50, by a route independent of Van Loan and of doubling."""
    with mpmath.workdps(50):
        F, L, Qc = _mp(case.F), _mp(case.L), _mp(case.Qc)
        W = L * Qc * L.T
        dt = mpmath.mpf(case.dt)
        n = F.rows
        if case.reference == "lyapunov":
            # vec(F P + P Fᵀ) = (I⊗F + F⊗I) vec P = −vec W, then Q = P∞ − A P∞ Aᵀ.
            K = mpmath.zeros(n * n, n * n)
            for i in range(n):
                for j in range(n):
                    for k in range(n):
                        K[i * n + j, k * n + j] += F[i, k]
                        K[i * n + j, i * n + k] += F[j, k]
            rhs = mpmath.matrix([-W[i, j] for i in range(n) for j in range(n)])
            p = mpmath.lu_solve(K, rhs)
            P = mpmath.matrix(n, n)
            for i in range(n):
                for j in range(n):
                    P[i, j] = p[i * n + j]
            A = mpmath.expm(F * dt)
            Q = P - A * P * A.T
        elif case.reference == "iou":
            k, q = -F[1, 1], Qc[0, 0]
            e1, e2 = mpmath.exp(-k * dt), mpmath.exp(-2 * k * dt)
            Q = mpmath.matrix(2, 2)
            Q[0, 0] = q / k**2 * (dt - 2 * (1 - e1) / k + (1 - e2) / (2 * k))
            Q[0, 1] = Q[1, 0] = q / k * ((1 - e1) / k - (1 - e2) / (2 * k))
            Q[1, 1] = q * (1 - e2) / (2 * k)
        else:  # nilpotent: Q = Σ_{j,k} F^j W (F^k)ᵀ dt^{j+k+1} / (j! k! (j+k+1)), finite sum
            powers = [mpmath.eye(n)]
            for _ in range(n):
                powers.append(F * powers[-1])
            Q = mpmath.zeros(n, n)
            for j in range(n):
                for k in range(n):
                    c = dt ** (j + k + 1) / (mpmath.factorial(j) * mpmath.factorial(k) * (j + k + 1))
                    Q += powers[j] * W * powers[k].T * c
        return np.array(Q.tolist(), dtype=float)


def _contestant_Q(name: str, case: Case, dtype: torch.dtype) -> np.ndarray | None:
    if name in ("scipy", "filterpy") and dtype != torch.float64:
        return None
    dt = np.array([case.dt])
    if name == "scipy":
        return scipy_van_loan(case.F, case.L @ case.Qc @ case.L.T, dt)[1][0]
    if name == "filterpy":
        G = case.L @ np.linalg.cholesky(case.Qc)
        return filterpy_loop(case.F, G, dt)[1][0]
    fn = {"default": default_discretize, "naive": naive_van_loan, "matrix_exp": library_matrix_exp}[name]
    args = [torch.as_tensor(x, dtype=dtype) for x in (case.F, case.L, case.Qc, dt)]
    try:
        _, Q = fn(*args)
    except (ValueError, RuntimeError) as err:  # e.g. a validation error on non-finite output
        print(f"    {name} {dtype} {case.name}: {type(err).__name__}: {err}")
        return np.full((case.F.shape[0],) * 2, np.nan)
    return Q[0].detach().double().numpy()


def judge(Q: np.ndarray, ref: np.ndarray, eps: float) -> tuple[float, bool]:
    """(relative Frobenius error, PSD) of Q against ref."""
    if not np.all(np.isfinite(Q)):
        return math.inf, False
    err = float(np.linalg.norm(Q - ref) / np.linalg.norm(ref))
    ev = np.linalg.eigvalsh(0.5 * (Q + Q.T))
    psd = bool(ev[0] >= -Q.shape[0] * eps * max(abs(ev).max(), np.finfo(float).tiny))
    return err, psd


def run_accuracy() -> list[dict[str, object]]:
    rows = []
    names = ("default", "matrix_exp", "naive", "scipy", "filterpy")
    for case in stiff_cases():
        ref = reference_Q(case)
        for dtype in (torch.float32, torch.float64):
            row: dict[str, object] = {"case": case.name, "dtype": str(dtype).replace("torch.", "")}
            eps = torch.finfo(dtype).eps
            for name in names:
                Q = _contestant_Q(name, case, dtype)
                row[name] = None if Q is None else judge(Q, ref, eps)
            rows.append(row)
    return rows


# ----------------------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------------------


def _fmt_rate(x: float | None) -> str:
    if x is None:
        return "—"
    if x >= 1e6:
        return f"{x / 1e6:.2f} M"
    if x >= 1e3:
        return f"{x / 1e3:.1f} k"
    return f"{x:.0f}"


def throughput_tables(cells: list[Cell]) -> str:
    out = []
    for mode, names in (("fwd", CONTESTANTS), ("fwd+bwd", ("default", "naive"))):
        title = "forward" if mode == "fwd" else "forward + backward (w.r.t. F, Qc, dt)"
        out.append(f"### Matrices/s, {title}\n")
        head = (
            "| n | dtype | B | " + " | ".join(names) + " | " + " | ".join(f"{k}/naive" for k in names if k != "naive")
        )
        if mode == "fwd":
            head += " | bad Q default / naive / scipy"
        out.append(head + " |")
        out.append("|" + "---|" * (head.count("|")))
        for c in cells:
            if c.mode != mode:
                continue
            rates = {k: c.rate(k) for k in names}
            naive = rates["naive"]
            ratio = [f"{rates[k] / naive:.2f}×" if rates[k] and naive else "—" for k in names if k != "naive"]
            few = {k for k in names if c.times.get(k) and len(c.times[k]) < 3}
            vals = [_fmt_rate(rates[k]) + ("†" if k in few else "") for k in names]
            line = f"| {c.n} | {c.dtype} | {c.batch:g} | " + " | ".join(vals) + " | " + " | ".join(ratio)
            if mode == "fwd":
                line += " | " + " / ".join(
                    f"{100 * c.bad[k]:.0f}%" if k in c.bad else "—" for k in ("default", "naive", "scipy")
                )
            out.append(line + " |")
        out.append("")
    out.append("† fewer than 3 timed runs (a single call exceeded the time budget); median of those runs.")
    out.append(
        f"— = not applicable (scipy/filterpy: float64 forward only, filterpy B ≤ {FILTERPY_MAX_BATCH}); naive forward+backward "
        f"skipped where its measured memory model (22·B·(4n)²·itemsize) exceeds {NAIVE_BACKWARD_MEMORY_BUDGET / 1e9:.0f} GB."
    )
    out.append("'bad Q': share of batch elements whose Q is non-finite or not PSD (λ_min(sym Q) < −n·eps·‖Q‖₂).\n")
    return "\n".join(out)


def accuracy_table(rows: list[dict[str, object]]) -> str:
    names = ("default", "matrix_exp", "naive", "scipy", "filterpy")
    out = ["### Accuracy on stiff cases: relative Frobenius error of Q vs mpmath (50 digits); ✓ = PSD, ✗ = not PSD\n"]
    head = "| case | dtype | " + " | ".join(names) + " |"
    out += [head, "|" + "---|" * (len(names) + 2)]
    for r in rows:
        cells = []
        for k in names:
            v = r[k]
            if v is None:
                cells.append("—")
            else:
                err, psd = v  # type: ignore[misc]
                cells.append(("non-finite" if not math.isfinite(err) else f"{err:.1e}") + (" ✓" if psd else " ✗"))
        out.append(f"| {r['case']} | {r['dtype']} | " + " | ".join(cells) + " |")
    out.append(
        '\n`default` = torchsde_lti.discretize (doubling); `matrix_exp` = its method="matrix_exp"; '
        "`naive` = torch.matrix_exp of the 2n block; `scipy` = scipy.linalg.expm of the 2n block; "
        "`filterpy` = filterpy.common.van_loan_discretization.\n"
    )
    return "\n".join(out)


def main() -> None:
    warnings.filterwarnings("ignore", category=RuntimeWarning)  # overflow inside the Van Loan contestants
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="~1 minute smoke run (n ≤ 4, B ≤ 1e4)")
    parser.add_argument(
        "--threads", type=int, default=None, help="torch.set_num_threads (default: leave torch's default)"
    )
    parser.add_argument("--out", type=Path, default=RESULTS, help="directory for the .md and .json")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    stem = ("bench_discretize_quick" if args.quick else "bench_discretize") + (
        f"_t{args.threads}" if args.threads else ""
    )
    start = time.perf_counter()
    header = [
        f"# discretize benchmark{' (--quick)' if args.quick else ''}\n",
        f"- torch {torch.__version__}, numpy {np.__version__}, scipy {scipy.__version__}, mpmath {mpmath.__version__}",
        f"- at the start: {machine_line()}, {platform.processor() or platform.machine()}",
        "- workload: F random Hurwitz (seed 0, ‖F‖ = 1), shared L, Qc; dt log-uniform with ‖F‖·dt ∈ [1e-2, 1e2]",
    ]
    print("\n".join(header), flush=True)
    print("throughput:", flush=True)
    cells = run_throughput(args.quick)
    print("accuracy:", flush=True)
    acc = run_accuracy()
    elapsed = time.perf_counter() - start
    footer = f"- at the end: {machine_line()}; wall time {elapsed:.0f} s\n"
    report = "\n".join(header) + "\n" + footer + "\n" + throughput_tables(cells) + "\n" + accuracy_table(acc)
    print(report)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{stem}.md").write_text(report)
    write_json(
        args.out / f"{stem}.json",  # strict JSON: NaN / inf as null
        {"threads": torch.get_num_threads(), "cells": [c.__dict__ for c in cells], "accuracy": acc},
    )
    print(f"wrote {args.out / (stem + '.md')} and .json")


if __name__ == "__main__":
    main()
