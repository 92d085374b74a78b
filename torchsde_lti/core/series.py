r"""The one specialisation of the doubling: ONE parameter set shared by the batch.

With ``F = ν F̃`` (ν = max(‖F‖₁, ‖F‖∞) rounded up to a power of two: F̃ and its powers are
exact), Van Loan's block ``C̃ = [[F̃, W̃, B̃], [0, −F̃ᵀ, 0], [0, 0, 0]]`` (W̃ = W/ν, B̃ = B/ν) and a
step h, ``x = ν h`` and the rows ``r_k = x^k/k!``, the top rows of ``expm(C̃ x) − [I, 0, 0]`` are::

    [E_h | X_h | G_h] = Σ_{1≤k≤K} r_k T_k,   T_k: the top rows of C̃^k;   A_h = I + E_h,   Q_h = X_h A_hᵀ.

The T_k do not depend on h: :func:`shared_series` forms them once (by doubling,
``T_{j+k} = T_j C̃^k``). A step ``dt = m h₀ + r`` (the base step ``h₀ = θ/ν``, a power of two:
m and ``0 ≤ r < h₀`` are exact) starts from the series at r (its rows against the T_k: ONE
matrix product for the whole batch; ``ν r ≤ θ``, so X Aᵀ does not cancel) and composes, for
each binary digit j of m that is set, the state of the step ``2^j h₀`` (the semigroup law of
module ``_doubling``: ``Q ← A_j Q A_jᵀ + Q_j``, …). The states of ``2^j h₀`` are the doublings
of the base step's, ONE state each, so a composition is a plain matrix product over the whole
batch (Q's as ``vec(A Q Aᵀ) = (A ⊗ A) vec Q``). As many compositions as the digits of the
largest m (those of an element's digits that are 0 hold it): the number of doublings.

**A nilpotent F** (``F̃^m = 0``: an integrator chain — constant velocity, constant
acceleration, Wiener velocity — or F = 0): the series terminate and are exact at the full step,
which takes no composition. The index m is found on the device from the exact powers (no value
is read to the host). Derivatives with respect to F need more terms than the values: the d-th
derivative of F^k in directions Δ_1 … Δ_d is a sum of products of k factors, d of them Δs and
k − d of them F, in d + 1 runs of consecutive Fs; for k ≥ (d+1) m one run has m or more Fs
and the product vanishes. X_k = Σ_j F^j W (−Fᵀ)^{k−1−j} has two such products, so its
derivatives of order ≤ d vanish for k ≥ (d+2) m: the rows k < 4m give the values and the first
and second derivatives exactly (third derivatives are not claimed). The rows are computed in
float64 (a float32 ``x^k/k!`` of a long step overflows where the result does not).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core._doubling import (
    THETA_SHARED,
    Results,
    carried,
    grouping,
    layout,
    results,
    run_steps,
    scale,
    series_degree,
    state,
    transition,
)
from torchsde_lti.core.linalg import bl_matmul

__all__ = ["SharedSeries", "TerminatingSeries", "shared_series"]


class SharedSeries(NamedTuple):
    """The dt-independent part of the doubling for ONE parameter set (module docstring), formed
    once (:func:`shared_series`); ``series(dt)`` costs the rows, one product for the batch and
    the compositions, so a module may keep it per parameter version.

    coeff: (K, n c) float64, the top rows T_k of C̃^k, k = 1 … K (the coefficients of r_k);
    inv_factorial: (K,) 1/k!; nu: () ν; nilpotent: () bool; rows: (K,) bool, the
    rows kept (k < 4m for a nilpotent F, all otherwise); base: the base step h₀ = θ/ν's state
    ``[E | A | G]`` (n, 2n + p) and Q (n, n) or None; dtype: the results' (the parameters') dtype.
    """

    coeff: Tensor
    inv_factorial: Tensor
    nu: Tensor
    nilpotent: Tensor
    rows: Tensor
    base: tuple[Tensor, Tensor | None]
    n: int
    p: int
    dtype: torch.dtype

    def __call__(self, dt: Tensor, batch_last: bool = False) -> Results:
        """(A, Q, G) over dt (...): (..., n, n), (..., n, n) or None, (..., n, p) or None (with
        ``batch_last`` contiguous (n, n, ...), …). Differentiable with respect to dt and to the
        parameters the terms came from."""
        n, work = self.n, self.coeff.dtype
        dtw = dt.reshape(-1).to(work)
        h0 = THETA_SHARED / self.nu  # the base step (a power of two): dt = m h0 + r, 0 ≤ r < h0, exactly
        m = torch.floor(torch.nan_to_num(dtw / h0, nan=0.0, posinf=torch.finfo(work).max))
        m = torch.where(self.nilpotent, 0.0, m)
        count = torch.frexp(m).exponent  # the binary digits of m (int32)
        order = grouping(count)
        if order is not None:
            dtw, m, count = dtw.index_select(0, order), m.index_select(0, order), count.index_select(0, order)
        r = torch.minimum(dtw - m * h0, h0)  # (exact; h₀ where dt/h₀ overflows, m then the largest float)
        X, Q = _state(self, torch.where(self.nilpotent, dtw, r))  # the remainder's

        def step(j: Any, elems: list[Tensor], shared: list[Tensor]) -> tuple[list[Tensor], list[Tensor], Tensor]:
            """Composes the state of 2^j h₀ (A, C = [E | 0 | G]; A ⊗ A, vec Q_j) where bit j of m
            is set, and doubles it: ``[E, A, G] ← A [E, A, G] + C``, ``vec Q ← (A ⊗ A) vec Q + vec Q_j``."""
            (X, m, *q), (P, *qj) = elems, shared
            j = -torch.as_tensor(j)
            bit = torch.floor(torch.ldexp(m, j)) > 2.0 * torch.floor(torch.ldexp(m, j - 1))  # digit j of m
            A = transition(P[..., None])[..., 0]
            X = (A @ X.reshape(n, -1)).reshape(X.shape).add_((P * mask[..., 0])[..., None])
            if q:  # vec(A Q Aᵀ) = (A ⊗ A) vec(Q): ONE product
                AA = kron(A, A)
                q, qj = [torch.addmm(qj[0], AA, q[0])], [torch.addmm(qj[0], AA, qj[0])]
            return [X, m, *q], [torch.addcmul(A @ P, P, mask[..., 0]), *qj], bit

        P, Qj = self.base
        mask = carried(n, X.shape[1], X)
        q, shared = [], [P]
        if Q is not None and Qj is not None:
            q, shared = [Q.reshape(n * n, -1)], [P, Qj.reshape(-1, 1)]
        X, _, *q = run_steps(step, count, [X, m, *q], shared)
        return layout(results(X, q[0].reshape(n, n, -1) if q else None), dt.shape, batch_last, order)


def _state(series: SharedSeries, h: Tensor) -> tuple[Tensor, Tensor | None]:
    """The state ``[E | A | G]`` (n, 2n + p, N) and Q (n, n, N) or None of the steps h (N,),
    ν h ≤ θ (any h for a nilpotent F): the rows ``(ν h)^k/k!`` against the terms give
    ``[E | X | G]`` of Van Loan's block in one product for the batch (batch-last), and
    ``Q = X Aᵀ``."""
    n, p, K = series.n, series.p, series.coeff.shape[0]
    powers = (series.nu * h)[:, None]  # x^1 … x^k by doubling (one cumulative product is slower)
    while powers.shape[1] < K:
        powers = torch.cat([powers, powers * powers[:, -1:]], 1)
    rows = torch.where(series.rows, powers[:, :K] * series.inv_factorial, 0.0)  # (N, K): r_k = x^k / k!
    out = (series.coeff.mT @ rows.mT).reshape(n, series.coeff.shape[1] // n, h.shape[0])  # (n, c, N), float64
    E, G = out[:, :n], out[:, out.shape[1] - p :] if p else None
    X = state(E, G)  # (Q = X Aᵀ in float64 too: a long step of a nilpotent F cancels a little)
    Q = None if out.shape[1] == n + p else bl_matmul(out[:, n : 2 * n], X[:, n : 2 * n].transpose(0, 1))
    return X.to(series.dtype), None if Q is None else Q.to(series.dtype)


def kron(a: Tensor, b: Tensor) -> Tensor:
    """The Kronecker product of a (r, c) and b (s, d): (r s, c d), ``[(i, k), (j, l)] = a_ij b_kl``."""
    (r, c), (q, d) = a.shape, b.shape
    return (a.reshape(r, 1, c, 1) * b.reshape(1, q, 1, d)).reshape(r * q, c * d)


#: A nilpotent F's series is a :class:`SharedSeries` (it takes no halving).
TerminatingSeries = SharedSeries


def shared_series(F: Tensor, W: Tensor | None, B: Tensor | None) -> SharedSeries:
    """:class:`SharedSeries` of F (n, n), W = L Qc Lᵀ (n, n) or None, B (n, p) or None (taken
    as checked), with K = max(:func:`~torchsde_lti.core._doubling.series_degree` at θ_shared,
    4n) terms: the top rows T_k of the powers of Van Loan's block ``C̃ = [[F̃, W̃, B̃], [0, −F̃ᵀ, 0],
    [0, 0, 0]]`` (W̃ = W/ν, B̃ = B/ν), by doubling (``T_{j+k} = T_j C̃^k``: ⌈log₂ K⌉ products)."""
    n, p, work = F.shape[-1], 0 if B is None else B.shape[-1], torch.float64
    K = max(series_degree(F.dtype, n, THETA_SHARED), 4 * n)
    mantissa, exponent = torch.frexp(scale(F).to(work))
    nu = torch.where(mantissa > 0, torch.ldexp(torch.ones((), dtype=work), exponent), 1.0)
    q = 0 if W is None else n
    C = F.new_zeros(n + q + p, n + q + p, dtype=work)
    C[:n, :n] = F.to(work) / nu
    if W is not None:
        C[:n, n : 2 * n] = W.to(work) / nu
        C[n : 2 * n, n : 2 * n] = -C[:n, :n].mT
    if B is not None:
        C[:n, n + q :] = B.to(work) / nu
    T, power = C[:n], C  # T_1 (the top rows of C̃), C̃; T_k stacked as (k n, c)
    while T.shape[0] < K * n:
        T, power = torch.cat([T, T @ power]), power @ power
    T = T[: K * n].reshape(K, n, -1)
    with torch.no_grad():  # F̃^k ≠ 0 exactly for k < m (m ≤ n: nilpotent, index m)
        m = T[:n, :, :n].flatten(1).ne(0).any(1).sum() + 1
        nilpotent = m <= n
        rows = (torch.arange(1, K + 1, device=F.device) < 4 * m) | ~nilpotent
    inv_factorial = torch.exp(-torch.lgamma(torch.arange(2, K + 2, dtype=work, device=F.device)))
    series = SharedSeries(T.reshape(K, -1), inv_factorial, nu, nilpotent, rows, (F, None), n, p, F.dtype)
    X, Q = _state(series, THETA_SHARED / nu.reshape(1))
    return series._replace(base=(X[..., 0], None if Q is None else Q[..., 0]))
