r"""Where the time of small calls goes, and the measurements behind the doubling dispatch.

Sections (medians of repeats; shared machine, noisy):

1. One ``discretize`` call (per-element workload of ``bench_per_element.py``, B = 1): total,
   argument checks with and without value checks, the computation alone, naive Van Loan.
2. Per-element parameters: the few-element block path (``_block``) vs the per-term Horner
   (``_doubling_per_element``) vs naive, over N — the ``_BLOCK_MAX_BATCH`` threshold.
3. One shared non-nilpotent parameter set (Matérn-3/2, Singer) over small N: block vs
   per-term vs shared-series path — the ``_BLOCK_MAX_SHARED`` threshold.
4. The Horner at 1 and 2 threads, and the batch split over two Python threads (B = 1e4).
5. The sequential filter loop: time inside the step function per step (2-D constant
   velocity, T = 200, B = 1 and 1000).
6. Kernel choices of the per-element path at N = 1e4, 1 and 2 threads: the finiteness test
   (isfinite of the concatenation vs one sum per tensor), the scale (max(‖F‖₁, ‖F‖∞) vs
   ‖F‖_F), the unsort to batch-first (index_copy_ vs the gather).
8. The batch-size thresholds of two kernel choices (1 thread, float64): the closed-form 2×2
   PSD test vs LAPACK's (``validation._CLOSED_FORM_MIN_2X2``), and the sort + unsort through
   ``_steps._Gather`` vs builtin indexing, forward + backward (``_steps._GATHER_MIN_BATCH``),
   each path forced by setting the threshold.
7. Would compiled kernels close the small-call gap? ``torch.compile`` (inductor, C++) of
   ``discretize`` (the traced path: masked doubling steps) and of the naive block
   exponential, per-element problem, B = 1 and 100, warm calls; first-call compile time.

    python experiments/profile_small_calls.py [--threads 1] [--sections 1 2 3 4 5 6 7 8]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from concurrent.futures import ThreadPoolExecutor

import torch
from bench_filter_choice import cv_data, cv_filter
from bench_per_element import make_problem, naive_van_loan

import torchsde_lti as tl
import torchsde_lti.filters.sequential as sequential
from torchsde_lti.core._block import block_doubling
from torchsde_lti.core._doubling import _doubling_per_element, _doubling_shared
from torchsde_lti.core._steps import _frobenius_norm, _operator_norm_bound
from torchsde_lti.core.validation import sde_inputs


def median_us(fn, repeats: int = 50) -> float:
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts) * 1e6


def one_call() -> None:
    print("\n### 1. One discretize call, B = 1, float64 (µs)\n")
    print("| n | discretize | sde_inputs | sde_inputs, value checks off | discretize, value checks off | naive |")
    print("|---|---|---|---|---|---|")
    for n in (2, 4, 8):
        F, L, Qc, dt = make_problem(n, 1, torch.float64)
        total = median_us(lambda: tl.discretize(F, L, Qc, dt))
        inputs = median_us(lambda: sde_inputs(F, L, Qc, dt))
        inputs_off = median_us(lambda: sde_inputs(F, L, Qc, dt, validate_args=False))
        total_off = median_us(lambda: tl.discretize(F, L, Qc, dt, validate_args=False))
        naive = median_us(lambda: naive_van_loan(F, L, Qc, dt))
        print(f"| {n} | {total:.0f} | {inputs:.0f} | {inputs_off:.0f} | {total_off:.0f} | {naive:.0f} |", flush=True)


def per_element_paths(dtypes: tuple[torch.dtype, ...]) -> None:
    print("\n### 2. Per-element parameters: block path vs per-term Horner vs naive (µs, value checks off)\n")
    print("| dtype | n | N | block | Horner | naive | Horner / block |")
    print("|---|---|---|---|---|---|---|")
    for dtype in dtypes:
        for n in (2, 4, 8):
            for N in (1, 10, 100, 300, 1000, 3000):
                F, L, Qc, dt = make_problem(n, N, dtype)
                x = sde_inputs(F, L, Qc, dt, validate_args=False)
                r = 30 if N <= 300 else 7
                b = median_us(lambda: block_doubling(x), r)
                h = median_us(lambda: _doubling_per_element(x, False), r)
                v = median_us(lambda: naive_van_loan(F, L, Qc, dt), r)
                print(f"| {str(dtype)[6:]} | {n} | {N} | {b:.0f} | {h:.0f} | {v:.0f} | {h / b:.2f} |", flush=True)


def shared_small() -> None:
    print("\n### 3. One shared parameter set, small N: block vs per-term vs shared series (µs, value checks off)\n")
    print("| model | N | block | per-term | shared |")
    print("|---|---|---|---|---|")
    f64 = torch.float64
    models = {
        "matern32": tl.models.matern(1.5, lengthscale=0.7, variance=2.0, dtype=f64),
        "singer": tl.models.singer(alpha=0.5, q=1.0, dtype=f64),
    }
    g = torch.Generator().manual_seed(0)
    for name, sde in models.items():
        F, L, Qc = sde.F.detach(), sde.L.detach(), sde.Qc.detach()
        for N in (1, 4, 16, 64, 256):
            x = sde_inputs(F, L, Qc, torch.rand(N, generator=g, dtype=f64) * 2 + 0.05, validate_args=False)
            b = median_us(lambda: block_doubling(x))
            p = median_us(lambda: _doubling_per_element(x, False))
            s = median_us(lambda: _doubling_shared(x.F, x.W, x.B, x.dt, x.batch, torch.Size(), False))
            print(f"| {name} | {N} | {b:.0f} | {p:.0f} | {s:.0f} |", flush=True)


def threads_and_split() -> None:
    print("\n### 4. Per-term Horner at 1 and 2 threads; the batch split over two Python threads (ms, B = 1e4, float64)\n")
    print("| n | threads | Horner | two Python threads × half | naive |")
    print("|---|---|---|---|---|")
    pool = ThreadPoolExecutor(2)
    for n in (2, 4):
        F, L, Qc, dt = make_problem(n, 10_000, torch.float64)
        half = F.shape[0] // 2
        parts = [(F[:half], Qc[:half], dt[:half]), (F[half:], Qc[half:], dt[half:])]

        def split() -> None:
            futures = [pool.submit(lambda p: _doubling_per_element(sde_inputs(p[0], L, p[1], p[2], validate_args=False), False), p)
                       for p in parts]
            for f in futures:
                f.result()

        for threads in (1, 2):
            torch.set_num_threads(threads)
            one = median_us(lambda: _doubling_per_element(sde_inputs(F, L, Qc, dt, validate_args=False), False), 9) / 1e3
            two = median_us(split, 9) / 1e3 if threads == 2 else float("nan")
            naive = median_us(lambda: naive_van_loan(F, L, Qc, dt), 9) / 1e3
            print(f"| {n} | {threads} | {one:.1f} | {two:.1f} | {naive:.1f} |", flush=True)
    pool.shutdown()


def loop_steps(threads: int) -> None:
    torch.set_num_threads(threads)
    print("\n### 5. Sequential loop: time in the step function (2-D CV, T = 200, float64)\n")
    print("| B | call (ms) | in steps (ms) | per step (µs) |")
    print("|---|---|---|---|")
    original = sequential._joseph_step
    for B in (1, 1000):
        y, dt = cv_data(B, 200)
        kf = cv_filter(False)
        with torch.no_grad():
            total = median_us(lambda: kf(y, dt), 7) / 1e3
            spent = [0.0, 0]

            def timed(*args, **kwargs):
                t0 = time.perf_counter()
                out = original(*args, **kwargs)
                spent[0] += time.perf_counter() - t0
                spent[1] += 1
                return out

            sequential._joseph_step = timed
            try:
                kf(y, dt)
            finally:
                sequential._joseph_step = original
        print(f"| {B} | {total:.1f} | {spent[0] * 1e3:.1f} | {spent[0] / spent[1] * 1e6:.0f} |", flush=True)


def kernel_choices() -> None:
    print("\n### 6. Per-element kernel choices, N = 1e4, float64 (µs)\n")
    print("| threads | n | isfinite(cat).all | sums | max(‖F‖₁, ‖F‖∞) | ‖F‖_F | unsort index_copy_ | unsort gather |")
    print("|---|---|---|---|---|---|---|---|")
    N = 10_000
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for n in (2, 4, 8):
            F, L, Qc, dt = make_problem(n, N, torch.float64)
            args = (F, L, Qc, dt)
            cat = median_us(lambda: torch.isfinite(torch.cat([t.reshape(-1) for t in args])).all(), 30)
            sums = median_us(lambda: torch.stack([t.sum() for t in args]).isfinite().all(), 30)
            induced = median_us(lambda: _operator_norm_bound(F), 30)
            frob = median_us(lambda: _frobenius_norm(F), 30)
            order = torch.randperm(N)
            inverse = torch.empty_like(order).index_copy_(0, order, torch.arange(N))
            x = torch.randn(n, n, N, dtype=torch.float64)  # batch-last, sorted
            copy = median_us(lambda: torch.empty(N, n, n, dtype=x.dtype).index_copy_(0, order, x.permute(2, 0, 1)), 30)
            gather = median_us(lambda: x.permute(2, 0, 1)[inverse], 30)
            print(f"| {threads} | {n} | {cat:.0f} | {sums:.0f} | {induced:.0f} | {frob:.0f} | {copy:.0f} | {gather:.0f} |",
                  flush=True)


def compiled_small_calls() -> None:
    print("\n### 7. torch.compile'd discretize vs naive, per-element problem, float64 (µs per call, warm)\n")
    print("| n | B | compile (s) | eager default | compiled default | eager naive | compiled naive |")
    print("|---|---|---|---|---|---|---|")
    import torch._dynamo

    for n in (2, 4, 8):
        for B in (1, 100):
            torch._dynamo.reset()
            F, L, Qc, dt = make_problem(n, B, torch.float64)
            default = torch.compile(lambda F, L, Qc, dt: tl.discretize(F, L, Qc, dt).Q)
            naive = torch.compile(lambda F, L, Qc, dt: naive_van_loan(F, L, Qc, dt)[1])
            t0 = time.perf_counter()
            default(F, L, Qc, dt)
            compile_s = time.perf_counter() - t0
            naive(F, L, Qc, dt)
            row = [median_us(lambda f=f: f(F, L, Qc, dt)) for f in (
                lambda *a: tl.discretize(*a), default, naive_van_loan, naive)]
            print(f"| {n} | {B} | {compile_s:.1f} | " + " | ".join(f"{v:.0f}" for v in row) + " |", flush=True)


def thresholds() -> None:
    import torchsde_lti.core._steps as steps
    import torchsde_lti.core.validation as checks

    torch.set_num_threads(1)
    print("\n### 8. Kernel-choice thresholds, float64, 1 thread (µs)\n")
    print("| N | PSD test 2×2: closed form | LAPACK | sort, batch-last, unsort (4×4), fwd+bwd: gathers | builtin |")
    print("|---|---|---|---|---|")
    saved = checks._CLOSED_FORM_MIN_2X2, steps._GATHER_MIN_BATCH
    g = torch.Generator().manual_seed(0)
    try:
        for N in (16, 64, 100, 256, 1000, 10_000):
            C = torch.randn(N, 2, 2, generator=g, dtype=torch.float64)
            x = C @ C.mT
            timings = []
            for bound in (0, 10**9):  # closed form always / never
                checks._CLOSED_FORM_MIN_2X2 = bound
                timings.append(median_us(lambda: checks._psd_test(x), 200))
            y = torch.randn(N, 4, 4, generator=g, dtype=torch.float64, requires_grad=True)
            perm = steps._Permutation(torch.randperm(N, generator=g))
            for bound in (0, 10**9):  # gathers always / never
                steps._GATHER_MIN_BATCH = bound
                # the per-element path's pattern: sort batch-first, work batch-last, unsort
                timings.append(median_us(lambda: perm.unsort(
                    (perm.sort(y).permute(1, 2, 0).contiguous() * 2.0).permute(2, 0, 1)).sum().backward(), 200))
            print(f"| {N} | " + " | ".join(f"{t:.0f}" for t in timings) + " |", flush=True)
    finally:
        checks._CLOSED_FORM_MIN_2X2, steps._GATHER_MIN_BATCH = saved


SECTIONS = {1: one_call, 2: lambda: per_element_paths((torch.float64, torch.float32)), 3: shared_small,
            4: threads_and_split, 6: kernel_choices, 7: compiled_small_calls, 8: thresholds}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=1, help="threads for sections 1–3 and 5 (4 and 6 run 1 and 2)")
    ap.add_argument("--sections", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6, 7, 8])
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"# small-call profile (torch {torch.__version__}, {args.threads} thread(s), load "
          f"{os.getloadavg()[0]:.2f}; shared machine, noisy: medians)")
    for k in args.sections:
        torch.set_num_threads(args.threads)
        loop_steps(args.threads) if k == 5 else SECTIONS[k]()
    print(f"\nload at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
