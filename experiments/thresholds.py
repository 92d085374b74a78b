r"""The benchmark that sets every speed threshold of ``torchsde_lti.core.thresholds``.

Each section forces both sides of one threshold over a range and prints their times side by
side, so the crossover the threshold encodes can be read off (and re-measured on another
machine). Both sides compute the same values (the tests check that); only the time differs.

Times are medians of repeats of the CPU time of the calling thread (``time.thread_time``)
with torch at one thread: on a shared machine the wall clock also counts other processes,
the thread's CPU time much less so. Still noisy: read the crossovers, not the last digit.

    python experiments/thresholds.py [--sections 1 2 ...] [--out experiments/results/thresholds.md]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import math
import os
import statistics
import sys
import time
from collections.abc import Callable, Iterator

import torch

import torchsde_lti as tl
import torchsde_lti.core._doubling as doubling_mod
import torchsde_lti.core._power_series as series_mod
import torchsde_lti.core.linalg as linalg
import torchsde_lti.core.validation as validation
from torchsde_lti.core import thresholds
from torchsde_lti.core.validation import sde_inputs

F64 = torch.float64


def cpu_us(fn: Callable[[], object], repeats: int = 15, budget: float = 0.5) -> float:
    """Median thread CPU time of ``fn`` in µs (after one warm-up call)."""
    fn()
    times: list[float] = []
    start = time.thread_time()
    while len(times) < repeats or (time.thread_time() - start < budget and len(times) < 200):
        t0 = time.thread_time()
        fn()
        times.append(time.thread_time() - t0)
    return statistics.median(times) * 1e6


@contextlib.contextmanager
def patched(module: object, **values: object) -> Iterator[None]:
    """Temporarily set module globals (the thresholds as the code reads them)."""
    saved = {k: getattr(module, k) for k in values}
    for k, v in values.items():
        setattr(module, k, v)
    try:
        yield
    finally:
        for k, v in saved.items():
            setattr(module, k, v)


def per_element_problem(n: int, N: int, dtype: torch.dtype = F64, seed: int = 0, dt_max: float = 10.0):
    """Per-element Hurwitz F, SPD Qc, L = I, dt log-uniform in [1e-3, dt_max]
    (experiments/bench_per_element.py's workload)."""
    g = torch.Generator().manual_seed(seed)
    M = torch.randn(N, n, n, generator=g, dtype=F64) / math.sqrt(n)
    F = M - (torch.linalg.eigvals(M).real.amax(-1) + 0.5)[:, None, None] * torch.eye(n, dtype=F64)
    C = torch.randn(N, n, n, generator=g, dtype=F64)
    Qc = C @ C.mT / n + 0.1 * torch.eye(n, dtype=F64)
    dt = torch.exp(torch.empty(N, dtype=F64).uniform_(math.log(1e-3), math.log(dt_max), generator=g))
    return F.to(dtype), torch.eye(n, dtype=dtype), Qc.to(dtype), dt.to(dtype)


def table(title: str, header: list[str], rows: list[list[object]]) -> str:
    out = [f"\n### {title}\n", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        out.append("| " + " | ".join(f"{v:.0f}" if isinstance(v, float) else str(v) for v in r) + " |")
    return "\n".join(out)


def unrolled_cholesky() -> str:
    rows = []
    for k in (2, 3, 4, 5, 6, 8):
        g = torch.Generator().manual_seed(k)
        X = torch.randn(1000, k, k, generator=g, dtype=F64)
        S = X @ X.mT + torch.eye(k, dtype=F64)

        def fwd_bwd() -> None:
            Sg = S.clone().requires_grad_()
            linalg.cholesky(Sg).sum().backward()

        row: list[object] = [k]
        for bound in (64, 0):  # unrolled, LAPACK
            with patched(linalg, UNROLLED_MAX_DIM=bound):
                row += [cpu_us(lambda: linalg.cholesky(S)), cpu_us(fwd_bwd)]
        rows.append(row)
    return table(
        f"1. UNROLLED_MAX_DIM = {thresholds.UNROLLED_MAX_DIM}: Cholesky of 1000 k×k, µs",
        ["k", "unrolled fwd", "unrolled fwd+bwd", "LAPACK fwd", "LAPACK fwd+bwd"],
        rows,
    )


def batch_last_products() -> str:
    rows = []
    for k in (2, 4, 8, 16, 24):
        for N in (64, 256, 1024, 4096):
            g = torch.Generator().manual_seed(k)
            a, b = (torch.randn(k, k, N, generator=g, dtype=F64) for _ in range(2))
            fma = cpu_us(lambda: linalg._fma_matmul(a, b, None))
            vec = cpu_us(lambda: torch.linalg.vecdot(a.unsqueeze(2), b.unsqueeze(0), dim=1))
            bmm = cpu_us(lambda: (a.permute(2, 0, 1) @ b.permute(2, 0, 1)).permute(1, 2, 0))
            rows.append([k, N, fma, vec, bmm])
    return table(
        f"2. FMA_MAX_INNER = {thresholds.FMA_MAX_INNER}, FMA_MIN_BATCH = {thresholds.FMA_MIN_BATCH}: "
        "batch-last k×k products, µs",
        ["k", "N", "fused multiply-adds", "vecdot", "bmm"],
        rows,
    )


def python_checks() -> str:
    rows = []
    for n, N in ((2, 1), (2, 8), (4, 4), (4, 8), (8, 2), (8, 4), (4, 32)):
        F, L, Qc, dt = per_element_problem(n, N)
        values = F.numel() + L.numel() + Qc.numel() + dt.numel() + N * n * n
        with patched(validation, PYTHON_CHECK_MAX_VALUES=10**9):
            py = cpu_us(lambda: sde_inputs(F, L, Qc, dt), 50)
        with patched(validation, PYTHON_CHECK_MAX_VALUES=-1):
            tensor = cpu_us(lambda: sde_inputs(F, L, Qc, dt), 50)
        rows.append([n, N, values, py, tensor])
    return table(
        f"3. PYTHON_CHECK_MAX_VALUES = {thresholds.PYTHON_CHECK_MAX_VALUES}: sde_inputs with value checks, µs",
        ["n", "N", "values", "Python floats", "tensor ops"],
        rows,
    )


def theta_per_element() -> str:
    rows = []
    for n in (2, 4, 8):
        row: list[object] = [n]
        for N, module, name in (
            (1, series_mod, "THETA_PER_ELEMENT"),
            (100, series_mod, "THETA_PER_ELEMENT"),
            (10_000, doubling_mod, "THETA_SORTED"),
        ):
            x = sde_inputs(*per_element_problem(n, N), validate_args=False)
            for theta in (0.25, 0.5, 1.0, 2.0):
                with patched(module, **{name: theta}):
                    row.append(cpu_us(lambda: doubling_mod.per_element_doubling(x), 5 if N > 100 else 15))
        rows.append(row)
    heads = [f"N = {N}, θ = {t}" for N in ("1", "100", "1e4") for t in (0.25, 0.5, 1, 2)]
    return table(
        f"4. THETA_PER_ELEMENT = {thresholds.THETA_PER_ELEMENT} (few elements), THETA_SORTED = "
        f"{thresholds.THETA_SORTED} (sorted): per-element doubling, µs",
        ["n", *heads],
        [[r[0], *(f"{v:.0f}" for v in r[1:])] for r in rows],
    )


def theta_shared() -> str:
    rows = []
    models = {
        "singer (2-D)": tl.models.singer(alpha=0.6, q=2.0, dim=2, dtype=F64),
        "integrated OU (2-D)": tl.models.integrated_ou(k=0.3, q=0.6, dim=2, dtype=F64),
        "Matérn-5/2": tl.models.matern(2.5, lengthscale=0.7, variance=2.0, dtype=F64),
    }
    dt = torch.rand(100_000, generator=torch.Generator().manual_seed(0), dtype=F64) * 3
    for name, sde in models.items():
        m = sde.matrices()
        F, W = m.F.detach(), (m.L @ m.Qc @ m.L.mT).detach()
        row: list[object] = [name]
        for theta in (0.5, 1.0, 2.0):
            with patched(doubling_mod, THETA_SHARED=theta):
                row.append(cpu_us(lambda: doubling_mod.shared_doubling(F, W, None, dt), 5) / 1e3)
        rows.append(row)
    return table(
        f"5. THETA_SHARED = {thresholds.THETA_SHARED}: one parameter set, dt ~ U(0, 3), N = 1e5, ms",
        ["model", "θ = 0.5", "θ = 1", "θ = 2"],
        [[r[0], *(f"{v:.2f}" for v in r[1:])] for r in rows],
    )


def layouts() -> str:
    rows = []
    for n in (2, 4, 8):
        for N in (64, 256, 1024, 4096):
            x = sde_inputs(*per_element_problem(n, N), validate_args=False)
            with patched(doubling_mod, BATCH_LAST_MAX_DIM=0, FEW_ENTRIES=0):
                first = cpu_us(lambda: doubling_mod.per_element_doubling(x), 9)
            with patched(doubling_mod, BATCH_LAST_MAX_DIM=64, BATCH_LAST_MIN_ELEMENTS=0, FEW_ENTRIES=0):
                last = cpu_us(lambda: doubling_mod.per_element_doubling(x), 9)
            rows.append([n, N, first, last])
    return table(
        f"6. BATCH_LAST_MAX_DIM = {thresholds.BATCH_LAST_MAX_DIM}, BATCH_LAST_MIN_ELEMENTS = "
        f"{thresholds.BATCH_LAST_MIN_ELEMENTS}: sorted per-element doubling, µs",
        ["n", "N", "batch-first bmm", "batch-last FMA"],
        rows,
    )


def shared_min() -> str:
    rows = []
    sde = tl.models.singer(alpha=0.6, q=2.0, dim=2, dtype=F64)
    m = sde.matrices()
    F, L, Qc = m.F.detach(), m.L.detach(), m.Qc.detach()
    for N in (1, 4, 16, 32, 64, 256):
        dt = torch.rand(N, generator=torch.Generator().manual_seed(N), dtype=F64) * 3 + 0.5
        x = sde_inputs(F, L, Qc, dt, validate_args=False)
        element = cpu_us(lambda: doubling_mod.per_element_doubling(x))
        shared = cpu_us(lambda: doubling_mod.shared_doubling(x.F, x.W, None, dt))
        rows.append([N, element, shared])
    return table(
        f"7. SHARED_MIN_ELEMENTS = {thresholds.SHARED_MIN_ELEMENTS}: one parameter set (2-D Singer), µs",
        ["N", "per element", "shared series"],
        rows,
    )


def few_elements() -> str:
    rows = []
    for n in (2, 4, 8):
        for N in (16, 64, 256, 1024, 4096):
            x = sde_inputs(*per_element_problem(n, N), validate_args=False)
            with patched(doubling_mod, FEW_ENTRIES=N * n * n):
                few = cpu_us(lambda: doubling_mod.per_element_doubling(x), 9)
            with patched(doubling_mod, FEW_ENTRIES=0):
                sorted_ = cpu_us(lambda: doubling_mod.per_element_doubling(x), 9)
            rows.append([n, N, few, sorted_])
    return table(
        f"8. FEW_ENTRIES = {thresholds.FEW_ENTRIES} (N n²): per-element doubling, one schedule vs sorted, µs",
        ["n", "N", "one schedule (power series)", "sorted (Horner)"],
        rows,
    )


def parallel_min_work() -> str:
    import torchsde_lti.core.threads as threads_mod

    rows = []
    for n, N in ((2, 10_000), (4, 10_000), (4, 100_000), (8, 10_000), (4, 1_000_000)):
        x = sde_inputs(*per_element_problem(n, 1, seed=1)[:3], torch.rand(N, dtype=F64) * 3, validate_args=False)
        row: list[object] = [n, N, N * n * n]
        for threads in (1, 2):
            torch.set_num_threads(threads)
            with patched(threads_mod, PARALLEL_MIN_WORK=0):  # the caller's threads, whatever the work
                start = time.perf_counter()
                for _ in range(3):
                    doubling_mod.doubling(x)
                row.append((time.perf_counter() - start) / 3 * 1e3)
        torch.set_num_threads(1)
        rows.append(row)
    return table(
        f"9. PARALLEL_MIN_WORK = {thresholds.PARALLEL_MIN_WORK}: one parameter set, wall ms at 1 and 2 "
        "threads (needs an idle machine)",
        ["n", "N", "entries", "1 thread", "2 threads"],
        [[r[0], r[1], r[2], f"{r[3]:.1f}", f"{r[4]:.1f}"] for r in rows],
    )


def chunk_bytes() -> str:
    """Each repeat calls every chunk size once, in turn (the sizes see the same load)."""
    sizes = (0, 1 << 19, 1 << 20, 1 << 21, 1 << 22, 1 << 23)  # 0: one pass
    calls: list[tuple[str, int, torch.dtype, Callable[[], object]]] = []
    for kind in ("shared", "per element"):
        for n in (2, 4):
            for dtype in (F64, torch.float32):
                N = 100_000
                if kind == "shared":
                    F, L, Qc, _ = per_element_problem(n, 1, dtype)
                    dt = per_element_problem(n, N, dtype)[3]
                    x = sde_inputs(F[0], L, Qc[0], dt, validate_args=False)
                else:
                    x = sde_inputs(*per_element_problem(n, N, dtype), validate_args=False)
                calls.append((kind, n, dtype, lambda x=x: doubling_mod.doubling(x)))
    # a filter whose discretisation is one such call: 2-D Singer (n = 6), 1000 tracks of 100 reports
    kf = tl.KalmanFilter(
        tl.models.singer(alpha=0.6, q=2.0, dim=2, dtype=F64),
        torch.tensor([[1.0, 0, 0, 0, 0, 0], [0, 0, 0, 1.0, 0, 0]], dtype=F64),
        0.3 * torch.eye(2, dtype=F64),
    )
    g = torch.Generator().manual_seed(0)
    y, dt = (
        torch.randn(1000, 100, 2, generator=g, dtype=F64).cumsum(1),
        0.1 + torch.rand(1000, 100, generator=g, dtype=F64),
    )
    calls.append(("2-D Singer filter, B = 1000, T = 100", 6, F64, lambda: kf(y, dt)))
    rows = []
    for kind, n, dtype, call in calls:
        times: dict[int, list[float]] = {b: [] for b in sizes}
        for r in range(7):
            for b in sizes if r % 2 else sizes[::-1]:
                with patched(doubling_mod, CHUNK_BYTES=b or 1 << 62, CHUNKED_MIN_BYTES=0), torch.no_grad():
                    t0 = time.thread_time()
                    call()
                    if r:  # (the first round warms up)
                        times[b].append(time.thread_time() - t0)
        rows.append([kind, n, str(dtype)[6:], *(f"{statistics.median(times[b]) * 1e3:.1f}" for b in sizes)])
    return table(
        f"10. CHUNK_BYTES = {thresholds.CHUNK_BYTES}, CHUNKED_MIN_BYTES = {thresholds.CHUNKED_MIN_BYTES}: "
        "N = 1e5 elements (dt log-uniform in [1e-3, 10]; the filter: 1e5 steps), forward, ms by chunk size "
        "(chunked whatever the size)",
        ["call", "n", "dtype", "one pass", "512 KiB", "1 MiB", "2 MiB", "4 MiB", "8 MiB"],
        rows,
    )


def rows_by_products() -> str:
    K = doubling_mod.series_terms(F64, thresholds.THETA_SHARED, 2)
    inv_k = torch.arange(1, K, dtype=F64).reciprocal()
    rows = []
    for N in (256, 1024, 2048, 4096, 8192, 32768):
        x = torch.rand(N, generator=torch.Generator().manual_seed(N), dtype=F64)
        row: list[object] = [N]
        for bound in (1 << 62, 0):  # cumulative product, one product a row
            with patched(doubling_mod, ROWS_BY_PRODUCTS_MIN=bound):
                row.append(cpu_us(lambda: doubling_mod._rows(x, inv_k, False)))
        rows.append(row)
    return table(
        f"11. ROWS_BY_PRODUCTS_MIN = {thresholds.ROWS_BY_PRODUCTS_MIN}: the series rows of one parameter set "
        f"(K = {K}, float64), µs",
        ["N", "cumulative product", "one product a row"],
        rows,
    )


def step_chunk_bytes() -> str:
    """The online steps of many tracks (``filters.online``), each repeat calling every chunk size once, in turn."""
    import torchsde_lti.filters.online as online

    sizes = (0, 1 << 18, 1 << 19, 1 << 20, 1 << 21, 1 << 22)  # 0: one pass
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64)
    cases: list[tuple[str, torch.dtype, torch.nn.Module, int]] = []
    for dtype in (F64, torch.float32):
        kf = tl.KalmanFilter(
            tl.models.constant_velocity(dim=2, q=0.5, dtype=dtype), H.to(dtype), 0.3 * torch.eye(2, dtype=dtype)
        )
        cases += [("kf.step, 2-D constant velocity (n = 4)", dtype, kf, B) for B in (8_000, 32_000, 100_000, 300_000)]
        cases.append(("kf.step, 2-D constant velocity (n = 4)", dtype, kf, 1_000_000))
    imm = tl.IMMFilter(
        [tl.models.constant_velocity(dim=2, q=q, dtype=F64) for q in (0.5, 5.0)],
        H,
        0.3 * torch.eye(2, dtype=F64),
        torch.tensor([[0.0, 0.2], [0.3, 0.0]], dtype=F64),
    )
    cases += [("imm.step, 2 modes (n = 4)", F64, imm, B) for B in (30_000, 300_000)]
    rows = []
    for name, dtype, module, B in cases:
        module.validate_args = False
        g = torch.Generator().manual_seed(B)
        state = module.initial_state(B)
        y, dt = torch.randn(B, 2, generator=g, dtype=dtype), 0.2 + torch.rand(B, generator=g, dtype=dtype)
        times: dict[int, list[float]] = {b: [] for b in sizes}
        for r in range(9 if B < 300_000 else 4):
            for b in sizes if r % 2 else sizes[::-1]:
                with patched(online, STEP_CHUNK_BYTES=b or 1 << 62, CHUNKED_STEP_MIN_BYTES=0), torch.no_grad():
                    t0 = time.thread_time()
                    module.step(state, y, dt)
                    if r:  # (the first round warms up)
                        times[b].append(time.thread_time() - t0)
        rows.append([name, str(dtype)[6:], B, *(f"{statistics.median(times[b]) * 1e3:.2f}" for b in sizes)])
    return table(
        f"12. filters.online STEP_CHUNK_BYTES = {online.STEP_CHUNK_BYTES}, CHUNKED_STEP_MIN_BYTES = "
        f"{online.CHUNKED_STEP_MIN_BYTES}: one online step of B tracks (own dt) from the initial state, ms by "
        "chunk size (chunked whatever the size)",
        ["call", "dtype", "B", "one pass", "256 KiB", "512 KiB", "1 MiB", "2 MiB", "4 MiB"],
        rows,
    )


SECTIONS = {
    1: unrolled_cholesky,
    2: batch_last_products,
    3: python_checks,
    4: theta_per_element,
    5: theta_shared,
    6: layouts,
    7: shared_min,
    8: few_elements,
    9: parallel_min_work,
    10: chunk_bytes,
    11: rows_by_products,
    12: step_chunk_bytes,
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sections", type=int, nargs="+", default=list(SECTIONS))
    ap.add_argument("--out", default=None, help="also write the tables to this file")
    args = ap.parse_args()
    torch.set_num_threads(1)
    buf = io.StringIO()
    head = (
        f"# core thresholds (torch {torch.__version__}, 1 thread, cpu_count {os.cpu_count()}, "
        f"load {os.getloadavg()[0]:.2f}; thread CPU time medians, shared machine)"
    )
    print(head, file=buf)
    print(head, flush=True)
    for k in args.sections:
        text = SECTIONS[k]()
        print(text, flush=True)
        print(text, file=buf)
    print(f"\nload at end {os.getloadavg()[0]:.2f}", file=buf)
    if args.out:
        with open(args.out, "w") as f:
            f.write(buf.getvalue())


if __name__ == "__main__":
    sys.exit(main())
