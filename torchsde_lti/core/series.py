r"""The terminating series of a nilpotent F: the exact discretisation as a polynomial in dt.

When F^m = 0 (an integrator chain: constant velocity, constant acceleration, Wiener velocity)
the series of expm(F s) terminate. With ν = max(‖F‖₁, ‖F‖∞) (1 for F = 0), F̃ = F/ν,
𝓛̃(X) = F̃ X + X F̃ᵀ, x = ν dt and r_k = x^k / k!::

    A = Σ_{k<m} r_k F̃^k,   Q = dt Σ_{k<2m−1} r_k 𝓛̃^k(W) / (k+1),   G = dt Σ_{k<m} r_k F̃^k B / (k+1)

(exact: every omitted term is zero). The matrices F̃^k, 𝓛̃^k(W), F̃^k B do not depend on dt:
:func:`terminating_series` forms them once, and a batch of steps costs the rows r_k and one
product for all three results (:class:`TerminatingSeries`).

Derivatives with respect to F need more terms than the values: the d-th derivative of F^k in
directions Δ_1 … Δ_d is a sum of products of k factors, d of them Δs and k − d of them F, in
d + 1 runs of consecutive Fs; for k ≥ (d+1) m one run has m or more Fs and the product
vanishes. So the derivatives of order ≤ d at a nilpotent F are exact with the terms
k < (d+1) m of A and G and k < (d+2) m − 1 of Q (𝓛^k(W) = Σ_j C(k, j) F^j W (F^{k−j})ᵀ:
j < (d₁+1) m, k − j < (d₂+1) m, d₁ + d₂ = d). :func:`terminating_series` keeps those of
``order`` d (:func:`derivative_order`: 2 where F records a graph — the second derivatives
are exact, the third are not).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor
from torch.autograd import forward_ad

__all__ = ["TerminatingSeries", "derivative_order", "terminating_series"]


def derivative_order(F: Tensor) -> int:
    """The order of the derivatives with respect to F that a truncated series must keep exact
    at a nilpotent F: 2 where a graph is recorded for F (a second derivative may follow: a
    Hessian, a gradient penalty) or F carries a forward-mode tangent (torch.func.jvp,
    ``forward_ad``), else 0 (values only). Derivatives with respect to dt, W and B need no more
    terms than the values (polynomial in dt, linear in W and B)."""
    if torch.is_grad_enabled() and F.requires_grad:
        return 2
    if not torch.compiler.is_compiling() and forward_ad.unpack_dual(F).tangent is not None:
        return 2
    return 0


def series_matrices(F: Tensor, X: Tensor, count: int, lyapunov: bool = False) -> Tensor:
    """F^k X, or with ``lyapunov`` 𝓛^k(X) (𝓛(X) = F X + X Fᵀ, exactly symmetric), for
    k < count: (count, n, c)."""
    terms = [X]
    for _ in range(1, count):
        FX = F @ terms[-1]
        terms.append(FX + FX.mT if lyapunov else FX)
    return torch.stack(terms)


class TerminatingSeries(NamedTuple):
    """The dt-independent matrices of a nilpotent F's exact discretisation (module docstring),
    as the coefficients of r_k = x^k / k!: A = Σ_k r_k F̃^k, Q = Σ_{k≥1} r_k 𝓛̃^{k−1}(W)/ν,
    G = Σ_{k≥1} r_k F̃^{k−1} B/ν (h r_k/(k+1) = r_{k+1}/ν), all results in one product.

    bias: (E,) the coefficients of r_0 = 1; rest: (K, E) those of r_1 … r_K, with the E
    entries [A's n² row-major | Q's upper triangle n(n+1)/2 | G's n p] (None blocks absent:
    ``has_q``, ``p`` = 0). scale: (K,) ν / k, so that r_k = Π_{j≤k} (dt ν / j). mirror: (n²,)
    the upper-triangle entry of each (i, j) (Q exactly symmetric). The coefficients are kept
    in float64 for float32 parameters, so that r_k of a gap whose exact results fit in float32
    does not overflow (a coefficient of a zero term would then give inf · 0).
    """

    bias: Tensor
    rest: Tensor
    scale: Tensor
    mirror: Tensor
    has_q: bool
    n: int
    p: int

    def __call__(self, dt: Tensor, batch_last: bool = False) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """(A, Q, G) over steps dt (...): A (..., n, n), Q (..., n, n) exactly symmetric or
        None, G (..., n, p) or None; with ``batch_last`` contiguous (n, n, ...), (n, n, ...),
        (n, p, ...). Differentiable with respect to dt and to the parameters the terms came
        from. Entries whose exact value exceeds dt's float range are inf (float64 parameters:
        gaps with ν dt up to ~1e61)."""
        batch, N, n, p = dt.shape, dt.numel(), self.n, self.p
        h = dt.reshape(N, 1).to(self.scale.dtype)
        r = torch.cumprod(h * self.scale, -1)  # (N, K): r_k = x^k / k!
        if batch_last:
            out = torch.addmm(self.bias[:, None], self.rest.mT, r.mT).to(dt.dtype)  # (E, N)
            A = out[: n * n].reshape(n, n, *batch)
            Q = out[n * n :].index_select(0, self.mirror).reshape(n, n, *batch) if self.has_q else None
            G = out[out.shape[0] - n * p :].reshape(n, p, *batch) if p else None
        else:
            out = torch.addmm(self.bias, r, self.rest).to(dt.dtype)  # (N, E)
            A = out[:, : n * n].reshape(*batch, n, n)
            Q = out[:, n * n :].index_select(1, self.mirror).reshape(*batch, n, n) if self.has_q else None
            G = out[:, out.shape[1] - n * p :].reshape(*batch, n, p) if p else None
        return A, Q, G


def terminating_series(F: Tensor, W: Tensor | None, B: Tensor | None, index: int, order: int = 0) -> TerminatingSeries:
    """:class:`TerminatingSeries` of ONE parameter set: F (n, n) with F^index = 0 (m = index),
    W = L Qc Lᵀ (n, n) symmetric or None, B (n, p) or None. ``order`` d: also the terms whose
    value is zero but whose derivatives of order ≤ d with respect to F are not (module
    docstring): F̃^k for k < (d+1) m (A, G), 𝓛̃^k(W) for k < (d+2) m − 1 (Q)."""
    n, p = F.shape[-1], 0 if B is None else B.shape[-1]
    work = torch.float64 if F.dtype == torch.float32 else F.dtype
    F = F.to(work)
    W = None if W is None else W.to(work)
    B = None if B is None else B.to(work)
    with torch.no_grad():  # (a scale: any positive ν gives the same exact series)
        absF = F.abs()
        nu = torch.maximum(absF.sum(-2).amax(-1), absF.sum(-1).amax(-1))
        nu = torch.where(nu > 0, nu, torch.ones_like(nu))
    m = (order + 1) * index  # terms of A (of G: r_1 … r_m)
    mq = (order + 2) * index - 1  # of Q: r_1 … r_mq
    K = max(m - 1, mq if W is not None else 0, m if B is not None else 0)
    Ft = F / nu
    eye = torch.eye(n, dtype=work, device=F.device)
    powers = series_matrices(Ft, eye, m)  # F̃^k, k < m
    zero = F.new_zeros(())
    blocks = [torch.cat([powers, zero.expand(K + 1 - m, n, n)]).reshape(K + 1, n * n)]
    upper = [(i, j) for i in range(n) for j in range(i, n)]
    if W is not None:
        rows, cols = (torch.tensor(c, dtype=torch.int64, device=F.device) for c in zip(*upper))
        lyap = series_matrices(Ft, W, mq, lyapunov=True)[:, rows, cols] / nu  # 𝓛̃^{k−1}(W)/ν for r_k, k = 1 … mq
        blocks.append(torch.cat([zero.expand(1, len(upper)), lyap, zero.expand(K - mq, len(upper))]))
    if B is not None:
        inputs = (powers @ B).reshape(m, n * p) / nu  # F̃^{k−1} B/ν for r_k, k = 1 … m
        blocks.append(torch.cat([zero.expand(1, n * p), inputs, zero.expand(K - m, n * p)]))
    coeff = torch.cat(blocks, -1)  # (K + 1, E)
    scale = nu / torch.arange(1, K + 1, dtype=work, device=F.device)
    upper_index = {ij: e for e, ij in enumerate(upper)}
    mirror = torch.tensor([upper_index[min(i, j), max(i, j)] for i in range(n) for j in range(n)], device=F.device)
    return TerminatingSeries(coeff[0], coeff[1:], scale, mirror, W is not None, n, p)
