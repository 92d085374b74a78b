r"""Probe: what would a fused (compiled) kernel buy the small per-element calls? (issue 10)

The few-element algorithm the default method had until issue 19 (Van Loan's block on the
sub-step, its Taylor polynomial by Paterson–Stockmeyer, PSD doubling with the decayed-A
switch) written as ONE C++ loop over the elements
(``at::parallel_for``; the block kept as its three n × n blocks, n ∈ {2, 4, 8} unrolled by
templates), forward only, built at run time with
``torch.utils.cpp_extension.load_inline`` (needs a C++ compiler; not part of the package).
Printed side by side with the package's default and naive ``torch.matrix_exp`` Van Loan on
the per-element workload of ``bench_per_element.py``, and its largest deviation from the
default (relative to max |·|). The question it answers: is the small-call gap (B = 1, 100)
arithmetic or per-op dispatch, and how far would shipping compiled kernels close it.

    python experiments/probe_fused_kernel.py [--threads 1]
"""

from __future__ import annotations

import argparse
import os
import time

import torch
from bench_per_element import make_problem, naive_van_loan
from thresholds import cpu_us as median_us

import torchsde_lti as tl


def _ps_table(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(J, 4) Paterson–Stockmeyer coefficients of expm(C) − I = Σ_{k=1}^m C^k/k! for ‖C‖_F ≤ 1
    (m = 18 in float64, 11 in float32: the remainder below eps/8), in powers C⁰ … C³ of C⁴."""
    import math

    eps = torch.finfo(dtype).eps
    m = 1
    while 1.0 / math.factorial(m + 1) >= eps / 8.0:
        m += 1
    a = torch.zeros(m // 4 + 1, 4, dtype=torch.float64)
    for k in range(1, m + 1):
        a[k // 4, k % 4] = 1.0 / math.factorial(k)
    return a.to(dtype=dtype, device=device)


CPP = r"""
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <cmath>
#include <limits>
#include <vector>

// n x n row-major products, n a compile-time constant (unrolled by the compiler)
template <typename T, int n> static inline void mm(const T* a, const T* b, T* c) {  // c = a b
  for (int i = 0; i < n; ++i) {
    T row[n] = {};
    for (int k = 0; k < n; ++k) { const T aik = a[i * n + k]; for (int j = 0; j < n; ++j) row[j] += aik * b[k * n + j]; }
    for (int j = 0; j < n; ++j) c[i * n + j] = row[j];
  }
}
template <typename T, int n> static inline void mm_add(const T* a, const T* b, T* c) {  // c += a b
  for (int i = 0; i < n; ++i)
    for (int k = 0; k < n; ++k) { const T aik = a[i * n + k]; for (int j = 0; j < n; ++j) c[i * n + j] += aik * b[k * n + j]; }
}
template <typename T, int n> static inline void mm_bt_add(const T* a, const T* b, T* c) {  // c += a b^T
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) { T acc = 0; for (int k = 0; k < n; ++k) acc += a[i * n + k] * b[j * n + k]; c[i * n + j] += acc; }
}

// Van Loan's block C = [[P, S], [0, D]] (P = F h, S = sigma W h, D = -P^T h) kept as its three
// n x n blocks: block-triangular products take 3-4 n x n products instead of 8.
template <typename T, int n> struct Blk { T p[n * n], s[n * n], d[n * n]; };

template <typename T, int n>
static void one_element(const T* F, const T* W, T dt, T* Aout, T* Qout, const T* coef, int J) {
  constexpr int nn = n * n;
  constexpr int q = 4;
  T fn = 0, wn = 0;
  for (int i = 0; i < nn; ++i) { fn += F[i] * F[i]; wn += W[i] * W[i]; }
  fn = std::sqrt(fn); wn = std::sqrt(wn);
  const T bound = std::max(fn, T(0.25) / std::max(dt, std::numeric_limits<T>::min()));
  int k = 0;
  if (wn > 0) { std::frexp(wn / bound, &k); k = std::min(std::max(k, 0), 60); }
  const T sigma = std::ldexp(T(1), -k);
  const T c = std::sqrt(2 * fn * fn + sigma * sigma * wn * wn) * dt;
  const int s = (c > 1 && std::isfinite(c)) ? (int)std::ceil(std::log2(c)) : 0;
  const T h = std::ldexp(dt, -s);
  Blk<T, n> pw[q + 1];  // C^0 ... C^q
  for (int i = 0; i < nn; ++i) {
    const T e = (i % (n + 1)) == 0 ? T(1) : T(0);
    pw[0].p[i] = e; pw[0].s[i] = 0; pw[0].d[i] = e;
    pw[1].p[i] = F[i] * h; pw[1].s[i] = sigma * W[i] * h;
  }
  for (int i = 0; i < n; ++i) for (int j = 0; j < n; ++j) pw[1].d[i * n + j] = -F[j * n + i] * h;
  for (int m = 2; m <= q; ++m) {  // C^m = C C^{m-1}; its D block is (-1)^m (P^m)^T
    mm<T, n>(pw[1].p, pw[m - 1].p, pw[m].p);
    mm<T, n>(pw[1].p, pw[m - 1].s, pw[m].s);
    mm_add<T, n>(pw[1].s, pw[m - 1].d, pw[m].s);
    const T sign = (m % 2) ? T(-1) : T(1);
    for (int i = 0; i < n; ++i) for (int j = 0; j < n; ++j) pw[m].d[i * n + j] = sign * pw[m].p[j * n + i];
  }
  // Paterson-Stockmeyer: expm(C) - I = sum_j B_j (C^q)^j, B_j = sum_i coef[j][i] C^i
  Blk<T, n> R, tmp;
  auto combine = [&](int j, Blk<T, n>& out) {
    for (int x = 0; x < nn; ++x) {
      T a = 0, b = 0, e = 0;
      for (int i = 0; i < q; ++i) { const T w = coef[j * q + i]; a += w * pw[i].p[x]; b += w * pw[i].s[x]; e += w * pw[i].d[x]; }
      out.p[x] = a; out.s[x] = b; out.d[x] = e;
    }
  };
  combine(J - 1, R);
  for (int j = J - 2; j >= 0; --j) {  // R <- B_j + R C^q
    combine(j, tmp);
    mm_add<T, n>(R.p, pw[q].p, tmp.p);
    mm_add<T, n>(R.p, pw[q].s, tmp.s);
    mm_add<T, n>(R.s, pw[q].d, tmp.s);
    mm_add<T, n>(R.d, pw[q].d, tmp.d);
    R = tmp;
  }
  T X[nn], A[nn], Q[nn], t1[nn], t2[nn];
  for (int i = 0; i < nn; ++i) { X[i] = R.p[i]; A[i] = X[i] + ((i % (n + 1)) == 0 ? T(1) : T(0)); Q[i] = R.s[i]; }
  mm_bt_add<T, n>(R.s, X, Q);  // Q_h = M A_h^T = M + M X^T (sigma-scaled)
  bool near = true;
  for (int step = 0; step < s; ++step) {
    if (step > 0 && near) {
      T a2 = 0;
      for (int i = 0; i < nn; ++i) a2 += A[i] * A[i];
      if (a2 < T(0.25)) { near = false; for (int i = 0; i < nn; ++i) X[i] = A[i]; }
    }
    mm<T, n>(A, Q, t1);
    mm_bt_add<T, n>(t1, A, Q);  // Q <- A Q A^T + Q
    mm<T, n>(X, A, t2);
    if (near) {  // E <- E + E A
      for (int i = 0; i < nn; ++i) { X[i] += t2[i]; A[i] = X[i] + ((i % (n + 1)) == 0 ? T(1) : T(0)); }
    } else {
      for (int i = 0; i < nn; ++i) { X[i] = t2[i]; A[i] = t2[i]; }
    }
  }
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) {
      Aout[i * n + j] = A[i * n + j];
      Qout[i * n + j] = (Q[i * n + j] + Q[j * n + i]) / (2 * sigma);
    }
}

template <typename T, int n>
static void run(const T* f, const T* w, const T* t, T* a, T* qo, const T* coef, int J, int64_t N) {
  at::parallel_for(0, N, 16, [&](int64_t lo, int64_t hi) {
    for (int64_t i = lo; i < hi; ++i)
      one_element<T, n>(f + i * n * n, w + i * n * n, t[i], a + i * n * n, qo + i * n * n, coef, J);
  });
}

std::vector<torch::Tensor> fused(torch::Tensor F, torch::Tensor W, torch::Tensor dt, torch::Tensor coef) {
  F = F.contiguous(); W = W.contiguous(); dt = dt.contiguous(); coef = coef.contiguous();
  const int64_t N = F.size(0), n = F.size(1);
  const int J = (int)coef.size(0);
  auto A = torch::empty_like(F), Q = torch::empty_like(F);
  AT_DISPATCH_FLOATING_TYPES(F.scalar_type(), "fused", [&] {
    const scalar_t* f = F.data_ptr<scalar_t>(); const scalar_t* w = W.data_ptr<scalar_t>();
    const scalar_t* t = dt.data_ptr<scalar_t>(); const scalar_t* c = coef.data_ptr<scalar_t>();
    scalar_t* a = A.data_ptr<scalar_t>(); scalar_t* q = Q.data_ptr<scalar_t>();
    switch (n) {
      case 2: run<scalar_t, 2>(f, w, t, a, q, c, J, N); break;
      case 4: run<scalar_t, 4>(f, w, t, a, q, c, J, N); break;
      case 8: run<scalar_t, 8>(f, w, t, a, q, c, J, N); break;
      default: TORCH_CHECK(false, "probe built for n in {2, 4, 8}");
    }
  });
  return {A, Q};
}
"""


def build():
    from torch.utils.cpp_extension import load_inline

    return load_inline(
        "probe_fused_discretize_omp",
        cpp_sources=CPP,
        functions=["fused"],
        extra_cflags=["-O3", "-fopenmp"],
        extra_ldflags=["-fopenmp"],
        verbose=False,
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    ext = build()
    print(
        f"# fused-kernel probe (torch {torch.__version__}, {args.threads} thread(s), load "
        f"{os.getloadavg()[0]:.2f}; build {time.perf_counter() - t0:.0f} s; shared machine, noisy: medians)\n"
    )
    print("Forward only; the fused kernel's arguments W = L Qc Lᵀ precomputed, no value checks.\n")
    print(
        "| dtype | n | B | fused (µs) | default (µs) | naive (µs) | naive / fused | naive / default | max rel. dev. fused vs default |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for dtype in (torch.float64, torch.float32):
        coef = _ps_table(dtype, torch.device("cpu"))
        for n in (2, 4, 8):
            for B in (1, 100, 10_000):
                F, L, Qc, dt = make_problem(n, B, dtype)
                W = L @ Qc @ L.mT
                r = 200 if B <= 100 else 10
                fused = median_us(lambda: ext.fused(F, W, dt, coef), r)
                default = median_us(lambda: tl.discretize(F, L, Qc, dt), r)
                naive = median_us(lambda: naive_van_loan(F, L, Qc, dt), r)
                A, Q = ext.fused(F, W, dt, coef)
                ref = tl.discretize(F, L, Qc, dt)
                dev = max(
                    float((A - ref.A).abs().max() / ref.A.abs().max()),
                    float((Q - ref.Q).abs().max() / ref.Q.abs().max()),
                )
                print(
                    f"| {str(dtype)[6:]} | {n} | {B} | {fused:.0f} | {default:.0f} | {naive:.0f} | "
                    f"{naive / fused:.2f}× | {naive / default:.2f}× | {dev:.1e} |",
                    flush=True,
                )
    print(f"\nload at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
