r"""The one specialisation of the doubling: ONE parameter set shared by the batch.

With ``F = ν F̃`` (ν = max(‖F‖₁, ‖F‖∞) rounded up to a power of two: F̃ and its powers are
exact), Van Loan's block ``C̃ = [[F̃, W̃, B̃], [0, −F̃ᵀ, 0], [0, 0, 0]]`` (W̃ = W/ν, B̃ = B/ν) and a
step h, ``x = ν h``, the top rows of ``expm(C̃ x) − [I, 0, 0]`` are::

    [E_h | X_h | G_h] = Σ_{1≤k≤K} x^k/k! T_k,   T_k: the top rows of C̃^k;   A_h = I + E_h,   Q_h = X_h A_hᵀ.

The T_k do not depend on h: :func:`shared_series` forms them once (by doubling,
``T_{j+k} = T_j C̃^k``). A step ``dt = m h₀ + r`` (the base step ``h₀ = θ/ν``, a power of two:
m and ``0 ≤ r < h₀`` are exact) starts from the series at r (the powers of x against the T_k:
ONE matrix product for the whole batch, which also gives the base step's state; ``ν r ≤ θ``, so
X Aᵀ does not cancel) and composes, for each binary digit j of m, the state of the step
``2^j h₀`` where the digit is set (the semigroup law of module ``_doubling``:
``Q ← A_j Q A_jᵀ + Q_j``, …). The states of ``2^j h₀`` are the doublings of the base step's, ONE
state each, so a composition is a plain matrix product over the whole batch (Q's as
``vec(A Q Aᵀ) = (A ⊗ A) vec Q``); as many as the digits of the largest m.

**A nilpotent F** (``F̃^m = 0``: an integrator chain — constant velocity, constant
acceleration — or F = 0): the series terminate and are exact at the full step, which takes no
composition. The index m is found on the device from the exact powers (no value is read).
Derivatives with respect to F need more terms than the values: the d-th derivative of F^k in
directions Δ_1 … Δ_d is a sum of products of k factors, d of them Δs and k − d of them F, in
d + 1 runs of consecutive Fs; for k ≥ (d+1) m one run has m or more Fs and the product
vanishes. X_k = Σ_j F^j W (−Fᵀ)^{k−1−j} has two such products, so its derivatives of order
≤ d vanish for k ≥ (d+2) m: the terms k < 4m give the values and the first and second
derivatives exactly (third derivatives are not claimed). The powers of x are taken in float64
(a float32 ``x^k`` of a long step overflows where the result does not).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core._doubling import (
    THETA_SHARED,
    Results,
    carried,
    layout,
    results,
    run_steps,
    scale,
    schedule,
    series_degree,
    transition,
)
from torchsde_lti.core.linalg import bl_matmul
from torchsde_lti.core.validation import (
    SDE_CONSTRAINTS,
    as_float_tensor,
    broadcast_batch,
    check_constraints,
    check_finite,
    check_matrix,
    check_vector,
    checks_values,
)

__all__ = ["SharedSeries", "shared_series", "transition_apply"]


class SharedSeries(NamedTuple):
    """The dt-independent part of the doubling for ONE parameter set (module docstring), formed
    once (:func:`shared_series`); ``series(dt)`` costs one product for the batch and the
    compositions, so a module may keep it per parameter version.

    coeff: (n c, K + 1) float64, column k the top rows of ``C̃^k/k!`` laid out ``[E | A | G | X]``
    (A's block E's again), column 0 the identity of A's block (the term k = 0); nu: () ν;
    nilpotent: () bool; terms: (K + 1,) bool, the terms kept (k < 4m for a nilpotent F of index
    m, all otherwise); n, p: F's and B's columns; dtype: the results' (the parameters')."""

    coeff: Tensor
    nu: Tensor
    nilpotent: Tensor
    terms: Tensor
    n: int
    p: int
    dtype: torch.dtype

    def __call__(self, dt: Tensor, batch_last: bool = False) -> Results:
        """(A, Q, G) over dt (...): (..., n, n), (..., n, n) or None, (..., n, p) or None (with
        ``batch_last`` contiguous (n, n, ...), …). Differentiable with respect to dt and to the
        parameters the terms came from."""
        n, p, work = self.n, self.p, self.coeff.dtype
        dtw = dt.reshape(-1).to(work)
        h0 = THETA_SHARED / self.nu  # dt = m h0 + r, 0 ≤ r < h0, exactly
        m = torch.floor(torch.nan_to_num(dtw / h0, nan=0.0, posinf=torch.finfo(work).max))
        m = torch.where(self.nilpotent, 0.0, m)
        count = torch.frexp(m).exponent  # the binary digits of m (int32: inductor's AVX-512
        # code for frexp's exponent converted to int64 does not compile)
        order, ends = schedule(count)
        if order is not None:
            dtw, m, count = dtw.index_select(0, order), m.index_select(0, order), count.index_select(0, order)
        r = torch.where(self.nilpotent, dtw, torch.minimum(dtw - m * h0, h0))  # (h0 where dt/h0 overflows)
        x = torch.cat([r, h0.reshape(1)]) * self.nu  # the remainders' steps and the base step
        powers = torch.cat([torch.ones_like(x)[:, None], x[:, None].expand(-1, self.coeff.shape[1] - 1).cumprod(1)], 1)
        powers = torch.where(self.terms, powers, 0.0)  # (not inf · 0: a long nilpotent step's x^k overflow)
        N, c = dtw.shape[0], 2 * n + p
        out = (self.coeff @ powers.mT).reshape(n, self.coeff.shape[0] // n, N + 1)  # [E | A | G | X]
        XQ = bl_matmul(out[:, c:], out[:, n : 2 * n].transpose(0, 1)) if out.shape[1] > c else None  # Q = X Aᵀ
        X, P = (t.contiguous() for t in out[:, :c].to(self.dtype).split([N, 1], -1))  # the remainders', h0's
        q, Qj = [], []
        if XQ is not None:
            q, Qj = ([t.contiguous().reshape(n * n, -1)] for t in XQ.to(self.dtype).split([N, 1], -1))
        P = P[..., 0]
        mask = carried(n, c, P)

        def step(j: Any, elems: list[Tensor], shared: list[Tensor]) -> tuple[list[Tensor], list[Tensor]]:
            """Composes the state of 2^j h₀ (P = [E | A | G], vec Q_j) where digit j of m is set
            (``[E, A, G] ← A [E, A, G] + [E_j, 0, G_j]``, ``vec Q ← (A ⊗ A) vec Q + vec Q_j``) and
            doubles it."""
            (X, m, *q), (P, *qj) = elems, shared
            half = torch.floor(m * 0.5)
            bit = m > 2.0 * half  # digit j of m
            A, C = transition(P), P * mask
            X = torch.where(bit, (A @ X.reshape(n, -1)).reshape(X.shape).add_(C[..., None]), X)
            if q:
                AA = torch.kron(A, A)
                q, qj = [torch.where(bit, torch.addmm(qj[0], AA, q[0]), q[0])], [torch.addmm(qj[0], AA, qj[0])]
            return [X, half, *q], [torch.addmm(C, A, P), *qj]

        X, _, *q = run_steps(step, count, ends, [X, m, *q], [P, *Qj])
        return layout(results(X, q[0].reshape(n, n, -1) if q else None), dt.shape, batch_last, order)


def shared_series(F: Tensor, W: Tensor | None, B: Tensor | None) -> SharedSeries:
    """:class:`SharedSeries` of F (n, n), W = L Qc Lᵀ (n, n) or None, B (n, p) or None (taken
    as checked), with K = max(:func:`~torchsde_lti.core._doubling.series_degree` at θ_shared,
    4n) terms, the top rows T_k of the powers of Van Loan's block ``C̃`` by doubling
    (``T_{j+k} = T_j C̃^k``: ⌈log₂ K⌉ products)."""
    n, p, work = F.shape[-1], 0 if B is None else B.shape[-1], torch.float64
    K = max(series_degree(F.dtype, n, THETA_SHARED), 4 * n)
    mantissa, exponent = torch.frexp(scale(F).to(work))
    nu = torch.where(mantissa > 0, torch.ldexp(torch.ones((), dtype=work), exponent), 1.0)
    Ft = F.to(work) / nu
    top = [Ft, *([] if B is None else [B.to(work) / nu]), *([] if W is None else [W.to(work) / nu])]
    C = torch.cat(top, 1)  # [F̃ | B̃ | W̃]: the top rows of C̃ (block order of the state, X last)
    lower = [C.new_zeros(p, C.shape[1])] + ([] if W is None else [torch.cat([C.new_zeros(n, n + p), -Ft.mT], 1)])
    C = torch.cat([C, *lower])  # the rows of B's (zero) and of X's (-F̃ᵀ) blocks
    T, power = C[:n], C  # T_1, C̃; T_k stacked as (k n, c)
    while T.shape[0] < K * n:
        T, power = torch.cat([T, T @ power]), power @ power
    T = T[: K * n].reshape(K, n, -1)
    with torch.no_grad():  # F̃^k ≠ 0 exactly for k < m (m ≤ n: nilpotent, index m)
        index = T[:n, :, :n].flatten(1).ne(0).any(1).sum() + 1
        nilpotent = index <= n
        kept = (torch.arange(K + 1, device=F.device) < 4 * index) | ~nilpotent
    inv_factorial = torch.exp(-torch.lgamma(torch.arange(2, K + 2, dtype=work, device=F.device)))  # 1/k!
    T = T * inv_factorial[:, None, None]
    T = torch.cat([T[..., :n], T], -1)  # [E | A | G | X]: A's terms are E's
    eye = torch.eye(n, dtype=work, device=F.device)
    first = torch.cat([torch.zeros_like(eye), eye, T.new_zeros(n, T.shape[-1] - 2 * n)], -1)  # k = 0: A = I
    coeff = torch.cat([first[None], T]).reshape(K + 1, -1).mT
    return SharedSeries(coeff, nu, nilpotent, kept, n, p, F.dtype)


def transition_apply(F: Tensor, dt: Tensor | float, x: Tensor, *, validate_args: bool = True) -> Tensor:
    r"""``expm(F dt) x`` without forming a matrix per element: F (..., n, n) (one parameter set,
    or a few broadcast), dt (...) ≥ 0, x (..., n) -> (..., n), all batch dims broadcast.

    The scheme of :class:`SharedSeries` applied to vectors: ν = max(‖F‖₁, ‖F‖∞) over every set,
    rounded up to a power of two, the base step ``h₀ = θ/ν`` and ``dt = m h₀ + r`` (exact);
    ``expm(F r) x`` by Horner on the vectors (``y ← x + (r/k) F y``, k = K … 1, with
    ``‖F r‖ ≤ θ``), then, for each binary digit j of m that is set, ``y ← expm(F 2^j h₀) y``
    (those matrices formed once for the batch: the series at h₀, then squarings). Memory is
    that of x, so n may be large (the moment systems of a switching model). Computed in float64
    and returned in x's dtype; differentiable with respect to F, dt and x. Eager: the number of
    digits of the largest m is read to the host (one synchronisation).

    Shapes are always checked (ValueError naming the argument); with ``validate_args`` the values
    too (F and x finite, dt ≥ 0) and a result that overflows float64 raises ValueError.
    """
    F = as_float_tensor(F, "F")
    check_matrix(F, "F", square=True)
    dt, x = as_float_tensor(dt, "dt", F.dtype, F.device), as_float_tensor(x, "x", device=F.device)
    check_vector(x, "x", F.shape[-1])
    broadcast_batch([("F", F.shape[:-2]), ("dt", dt.shape), ("x", x.shape[:-1])])
    if checks_values(validate_args):
        check_constraints([("F", F), ("dt", dt)], SDE_CONSTRAINTS)
        check_finite(x, "x")
    y = _apply(F, dt, x)
    if checks_values(validate_args) and not bool(torch.isfinite(y).all()):
        raise ValueError(
            f"expm(F dt) x overflows float64 for dt up to {float(dt.max()):.3g} (F's norm {float(scale(F.double()).max()):.3g}): "
            "shorten dt or rescale the state"
        )
    return y


def _apply(F: Tensor, dt: Tensor, x: Tensor) -> Tensor:
    """:func:`transition_apply` of checked arguments."""
    work = torch.float64
    Fw, dtw, xw = F.to(work), dt.to(work), x.to(work)
    n = F.shape[-1]
    with torch.no_grad():
        mantissa, exponent = torch.frexp(scale(Fw).amax() if Fw.numel() else Fw.new_zeros(()))
        nu = torch.where(mantissa > 0, torch.ldexp(torch.ones((), dtype=work, device=F.device), exponent), 1.0)
        h0 = THETA_SHARED / nu
        m = torch.floor(torch.nan_to_num(dtw / h0, nan=0.0, posinf=torch.finfo(work).max))
    r = torch.minimum(dtw - m * h0, h0).unsqueeze(-1)  # (h0 where dt/h0 overflows)
    # K: series_degree's bound is for the Lyapunov operator (norm 2ν); the exponential alone has
    # norm ν, so its omitted terms e^θ θ^K/(K+1)! are that bound at θ/2
    K = series_degree(work, 1, THETA_SHARED / 2)
    shared = Fw.dim() == 2

    def apply(M: Tensor, y: Tensor) -> Tensor:
        return y @ M.mT if shared else (M @ y.unsqueeze(-1)).squeeze(-1)

    y = xw
    for k in range(K, 0, -1):  # expm(F r) x by Horner
        y = xw + (r / k) * apply(Fw, y)
    eye = torch.eye(n, dtype=work, device=F.device)
    Fh = Fw * h0
    P = eye
    for k in range(K, 0, -1):  # expm(F h0)
        P = eye + (Fh @ P) / k
    digits = int(m.max().item()).bit_length() if m.numel() else 0
    for _ in range(digits):
        half = torch.floor(m * 0.5)
        y = torch.where((m > 2.0 * half).unsqueeze(-1), apply(P, y), y)
        m, P = half, P @ P
    return y.to(x.dtype)
