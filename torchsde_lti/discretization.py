r"""Exact discretisation of LTI SDEs ``dx = F x dt + B u dt + L dβ`` (spectral density Qc).

Over a step dt with u held constant (zero-order hold)::

    x_{k+1} = A x_k + G u_k + q_k,        q_k ~ N(0, Q)
    A = expm(F dt),   G = ∫_0^dt expm(F s) ds B,   Q = ∫_0^dt expm(F s) W expm(F s)ᵀ ds,
    W = L Qc Lᵀ.

Two methods are offered.

``"doubling"`` (default): scaling and doubling. Each element picks its own number of
halvings ``s ≥ 0`` so that ``‖F‖ h ≤ 1`` for the sub-step ``h = dt / 2^s``. On the sub-step
the Taylor series are summed (``𝓛(X) = F X + X Fᵀ``)::

    A_h = Σ_k (F h)^k / k!,   Q_h = Σ_k h^{k+1}/(k+1)! 𝓛^k(W),   G_h = Σ_k h^{k+1}/(k+1)! F^k B

and then doubled ``s`` times: ``Q ← A Q Aᵀ + Q``, ``G ← A G + G``, ``A ← A A``. Every
doubling adds positive semi-definite terms, so Q stays PSD, and nothing grows like
``e^{|λ| dt}`` for stable F. The series terms ``F^k``, ``𝓛^k(W)``, ``F^k B`` depend on the
parameters only: when F, L, Qc, B are shared by a batch of dt (the training case), they are
computed once on n×n matrices and all elements are combined by one matrix product.
Nilpotent F (integrator chains) is detected and its terminating series is used at the
full step, with no doubling at all.

``"van_loan"``: Van Loan's block exponential via :func:`torch.matrix_exp` of
``[[F, W, B], [0, -Fᵀ, 0], [0, 0, 0]] dt`` (blocks ``[[A, X, G], [0, A^{-T}, 0], [0, 0, I]]``,
``Q = X Aᵀ``). Exact in exact arithmetic; in floating point the ``-Fᵀ`` block holds
``e^{|λ| dt}`` and Q is recovered by cancellation, so it fails for stiff F or large dt.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti._validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_matrix,
    check_nonnegative,
    check_symmetric_psd,
    check_vector,
    common_float_dtype,
    shape_str,
)

METHODS = ("doubling", "van_loan")

# Sub-step bound ‖F‖ h ≤ _THETA. With it, ‖𝓛‖ ≤ 2 ‖F‖ and the truncated Q series has
# relative error below (2θ)^K / (K+1)!, which _series_length makes smaller than eps/8.
_THETA = 1.0


class Discrete(NamedTuple):
    """Exact discrete-time model over a step: ``x' = A x + G u + q``, ``q ~ N(0, Q)``.

    A: (..., n, n) transition matrix expm(F dt).
    Q: (..., n, n) process-noise covariance (symmetric PSD).
    G: (..., n, p) zero-order-hold input matrix, or None when the SDE has no input.
    """

    A: Tensor
    Q: Tensor
    G: Tensor | None


@lru_cache(maxsize=None)
def _series_length(dtype: torch.dtype) -> int:
    """Number of Taylor terms K with (2θ)^K / (K+1)! < eps / 8."""
    eps = torch.finfo(dtype).eps
    k = 1
    while (2.0 * _THETA) ** k / math.factorial(k + 1) > eps / 8.0:
        k += 1
    return k + 1


class _Inputs(NamedTuple):
    F: Tensor
    W: Tensor | None
    B: Tensor | None
    dt: Tensor
    batch: torch.Size


def _prepare(
    F: Tensor, L: Tensor | None, Qc: Tensor | None, dt: Tensor | float, B: Tensor | None
) -> _Inputs:
    """Validate and convert arguments; return W = L Qc Lᵀ and the broadcast batch shape."""
    F = as_float_tensor(F, "F")
    dtype = common_float_dtype(
        F,
        L if isinstance(L, Tensor) else None,
        Qc if isinstance(Qc, Tensor) else None,
        B if isinstance(B, Tensor) else None,
    )
    device = F.device
    F = as_float_tensor(F, "F", dtype, device)
    check_matrix(F, "F", square=True)
    n = F.shape[-1]
    check_finite(F, "F")
    named: list[tuple[str, torch.Size]] = [("F", F.shape[:-2])]
    W = None
    if L is not None or Qc is not None:
        if L is None or Qc is None:
            raise ValueError("L and Qc must be given together")
        L = as_float_tensor(L, "L", dtype, device)
        Qc = as_float_tensor(Qc, "Qc", dtype, device)
        check_matrix(L, "L", rows=n)
        s = L.shape[-1]
        if Qc.dim() < 2 or Qc.shape[-2:] != (s, s):
            raise ValueError(
                f"Qc must have shape (..., {s}, {s}) to match L {shape_str(L)}, got shape {shape_str(Qc)}"
            )
        check_finite(L, "L")
        check_symmetric_psd(Qc, "Qc")
        named += [("L", L.shape[:-2]), ("Qc", Qc.shape[:-2])]
        W = L @ Qc @ L.mT
        W = 0.5 * (W + W.mT)
    if B is not None:
        B = as_float_tensor(B, "B", dtype, device)
        check_matrix(B, "B", rows=n)
        check_finite(B, "B")
        named.append(("B", B.shape[:-2]))
    dt = as_float_tensor(dt, "dt", dtype, device)
    check_nonnegative(dt, "dt")
    named.append(("dt", dt.shape))
    batch = broadcast_batch(named)
    return _Inputs(F, W, B, dt, batch)


def discretize(
    F: Tensor,
    L: Tensor,
    Qc: Tensor,
    dt: Tensor | float,
    B: Tensor | None = None,
    method: str = "doubling",
) -> Discrete:
    r"""Exact discretisation (A, Q, G) of ``dx = F x dt + B u dt + L dβ`` over steps dt.

    Args:
        F: (..., n, n) drift matrix.
        L: (..., n, s) noise-input matrix.
        Qc: (..., s, s) spectral density of β (symmetric PSD).
        dt: (...) non-negative step lengths; a Python float is a scalar.
        B: optional (..., n, p) input matrix; u is held constant over each step.
        method: ``"doubling"`` (default; accurate and PSD for stiff F and large dt) or
            ``"van_loan"`` (the plain block exponential).

    All leading dimensions broadcast (numpy rules, right-aligned): F (n, n) with dt (B, T)
    gives (B, T, n, n); F (B, 1, n, n) with dt (B, T) gives (B, T, n, n).

    Returns:
        :class:`Discrete` with A (..., n, n), Q (..., n, n) symmetric PSD and
        G (..., n, p) or None. Differentiable with respect to F, L, Qc, B and dt.
    """
    inputs = _prepare(F, L, Qc, dt, B)
    if method == "doubling":
        A, Q, G = _doubling(inputs.F, inputs.W, inputs.B, inputs.dt, inputs.batch)
    elif method == "van_loan":
        A, Q, G = _van_loan(inputs.F, inputs.W, inputs.B, inputs.dt, inputs.batch)
    else:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    assert Q is not None
    return Discrete(A, Q, G)


def transition_matrix(F: Tensor, dt: Tensor | float) -> Tensor:
    """A = expm(F dt).

    Args:
        F: (..., n, n) drift matrix.
        dt: (...) non-negative step lengths.

    Returns:
        (..., n, n), batch broadcast from F and dt.
    """
    inputs = _prepare(F, None, None, dt, None)
    A, _, _ = _doubling(inputs.F, None, None, inputs.dt, inputs.batch)
    return A


def zero_order_hold(F: Tensor, B: Tensor, dt: Tensor | float) -> tuple[Tensor, Tensor]:
    """(A, G) with A = expm(F dt) and G = ∫_0^dt expm(F s) ds B.

    Equivalent to the blocks of expm([[F, B], [0, 0]] dt) = [[A, G], [0, I]].

    Args:
        F: (..., n, n); B: (..., n, p); dt: (...).

    Returns:
        A (..., n, n), G (..., n, p).
    """
    inputs = _prepare(F, None, None, dt, B)
    A, _, G = _doubling(inputs.F, None, inputs.B, inputs.dt, inputs.batch)
    assert G is not None
    return A, G


def process_noise(
    F: Tensor, L: Tensor, Qc: Tensor, dt: Tensor | float, method: str = "doubling"
) -> Tensor:
    """Q = ∫_0^dt expm(F s) L Qc Lᵀ expm(F s)ᵀ ds, the discrete process-noise covariance.

    Args:
        F: (..., n, n); L: (..., n, s); Qc: (..., s, s) symmetric PSD; dt: (...).
        method: as in :func:`discretize`.

    Returns:
        (..., n, n) symmetric PSD.
    """
    return discretize(F, L, Qc, dt, method=method).Q


def propagate(
    m0: Tensor,
    P0: Tensor,
    F: Tensor,
    L: Tensor,
    Qc: Tensor,
    dt: Tensor | float,
    B: Tensor | None = None,
    u: Tensor | None = None,
    method: str = "doubling",
) -> tuple[Tensor, Tensor]:
    """Moments after a horizon dt: ``m = A m0 + G u``, ``P = A P0 Aᵀ + Q``.

    They solve dm/dt = F m + B u and the Lyapunov ODE dP/dt = F P + P Fᵀ + L Qc Lᵀ.

    Args:
        m0: (..., n) mean at the start. P0: (..., n, n) covariance at the start.
        F, L, Qc, dt, B: as in :func:`discretize`.
        u: (..., p) input held constant over the horizon; requires B.

    Returns:
        m (..., n), P (..., n, n) symmetric.
    """
    if u is not None and B is None:
        raise ValueError(f"u was given (shape {shape_str(torch.as_tensor(u))}) but the SDE has no input matrix B")
    d = discretize(F, L, Qc, dt, B=B, method=method)
    n = d.A.shape[-1]
    m0 = as_float_tensor(m0, "m0", d.A.dtype, d.A.device)
    P0 = as_float_tensor(P0, "P0", d.A.dtype, d.A.device)
    check_vector(m0, "m0", n)
    check_matrix(P0, "P0", rows=n, cols=n)
    check_finite(m0, "m0")
    check_symmetric_psd(P0, "P0")
    m = (d.A @ m0.unsqueeze(-1)).squeeze(-1)
    if u is not None:
        assert d.G is not None
        u = as_float_tensor(u, "u", d.A.dtype, d.A.device)
        check_vector(u, "u", d.G.shape[-1])
        check_finite(u, "u")
        m = m + (d.G @ u.unsqueeze(-1)).squeeze(-1)
    P = d.A @ P0 @ d.A.mT + d.Q
    return m, 0.5 * (P + P.mT)


# ----------------------------------------------------------------------------------------
# Scaling and doubling
# ----------------------------------------------------------------------------------------


def _operator_norm_bound(F: Tensor) -> Tensor:
    """max(‖F‖₁, ‖F‖∞): bounds ‖F‖ and ‖𝓛‖/2 in the induced 1-norm. Shape (...)."""
    absF = F.abs()
    return torch.maximum(absF.sum(-2).amax(-1), absF.sum(-1).amax(-1))


def _nilpotency_index(F: Tensor) -> int | None:
    """Smallest k ≤ n with F^k = 0 exactly for every batch element, else None."""
    n = F.shape[-1]
    with torch.no_grad():
        power = F
        for k in range(1, n + 1):
            if not bool(power.any()):
                return k
            if k < n:
                power = F @ power
    return None


def _series_terms(
    F: Tensor, W: Tensor | None, B: Tensor | None, count: int
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Stacked terms F^k, 𝓛^k(W), F^k B for k < count: (..., count, n, n|p)."""
    eye = torch.eye(F.shape[-1], dtype=F.dtype, device=F.device).expand_as(F)
    powers = [eye]
    lyap = [W] if W is not None else None
    inputs = [B] if B is not None else None
    for _ in range(1, count):
        powers.append(F @ powers[-1])
        if lyap is not None:
            prev = lyap[-1]
            FX = F @ prev
            lyap.append(FX + FX.mT)  # 𝓛(X) = F X + X Fᵀ, X symmetric
        if inputs is not None:
            inputs.append(F @ inputs[-1])
    return (
        torch.stack(powers, dim=-3),
        torch.stack(lyap, dim=-3) if lyap is not None else None,
        torch.stack(inputs, dim=-3) if inputs is not None else None,
    )


def _combine(coeffs: Tensor, terms: Tensor, batch: torch.Size) -> Tensor:
    """Σ_k coeffs[..., k] terms[..., k, :, :] broadcast to ``batch``.

    coeffs: (*batch_c, K); terms: (*batch_t, K, r, c) -> (*batch, r, c).
    """
    K, r, c = terms.shape[-3:]
    if terms.dim() == 3:  # shared parameters: one matrix product for the whole batch
        out = coeffs.reshape(-1, K) @ terms.reshape(K, r * c)
        return out.reshape(*coeffs.shape[:-1], r, c).expand(*batch, r, c)
    return torch.einsum("...k,...kij->...ij", coeffs, terms).expand(*batch, r, c)


def _doubling(
    F: Tensor, W: Tensor | None, B: Tensor | None, dt: Tensor, batch: torch.Size
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    dtype = F.dtype
    param_batch = broadcast_batch(
        [("F", F.shape[:-2])]
        + ([("W", W.shape[:-2])] if W is not None else [])
        + ([("B", B.shape[:-2])] if B is not None else [])
    )
    n = F.shape[-1]
    F = F.expand(*param_batch, n, n)
    if W is not None:
        W = W.expand(*param_batch, n, n)
    if B is not None:
        B = B.expand(*param_batch, n, B.shape[-1])

    # Scale F to unit norm (a constant, so gradients are untouched): F = ν F̃.
    with torch.no_grad():
        nu = _operator_norm_bound(F)
        nu = torch.where(nu > 0, nu, torch.ones_like(nu))
    F_unit = F / nu[..., None, None]

    nil = _nilpotency_index(F)
    if nil is not None:
        # Terminating series: exact at the full step (3ν terms also make the gradient exact).
        count = 3 * nil
        halvings = None
    else:
        count = _series_length(dtype)
        with torch.no_grad():
            ratio = nu * dt / _THETA  # (batch)
            halvings = torch.ceil(torch.log2(ratio.clamp_min(1.0))).to(torch.int64)
    powers, lyap, inputs = _series_terms(F_unit, W, B, count)

    h = dt if halvings is None else dt / torch.exp2(halvings.to(dtype))
    x = (h * nu).unsqueeze(-1)  # (batch, 1): ‖F‖ h ≤ θ
    k = torch.arange(count, dtype=dtype, device=F.device)
    log_fact = torch.lgamma(k + 1.0)
    x_pow = x.expand(*x.shape[:-1], count).pow(k)
    coeff_A = x_pow / torch.exp(log_fact)  # (νh)^k / k!
    coeff_QG = x_pow / torch.exp(log_fact + torch.log(k + 1.0))  # (νh)^k / (k+1)!
    h_mat = h.expand(batch)[..., None, None]

    # X holds E = A - I while A is near the identity (small ‖F‖ h): there A itself would lose
    # the digits of E to rounding, and 2^s squarings amplify that loss. Once ‖A‖₁ falls below
    # 1/2 (a decaying A), X switches to A itself, whose small entries E cannot resolve.
    eye = torch.eye(n, dtype=dtype, device=F.device)
    X = _combine(coeff_A[..., 1:], powers[..., 1:, :, :], batch)
    Q = None if lyap is None else h_mat * _combine(coeff_QG, lyap, batch)
    G = None if inputs is None else h_mat * _combine(coeff_QG, inputs, batch)
    if Q is not None:
        Q = 0.5 * (Q + Q.mT)
    direct = torch.zeros(batch, dtype=torch.bool, device=F.device)[..., None, None]

    if halvings is not None:
        halvings = halvings.expand(batch)
        steps = int(halvings.max()) if halvings.numel() else 0
        for j in range(steps):
            active = (halvings > j)[..., None, None]
            A = torch.where(direct, X, X + eye)
            if Q is not None:
                AQ = A @ Q
                Q_next = AQ @ A.mT + Q  # Q <- A Q Aᵀ + Q
                Q = torch.where(active, 0.5 * (Q_next + Q_next.mT), Q)
            if G is not None:
                G = torch.where(active, A @ G + G, G)  # G <- A G + G
            XX = X @ X
            X_next = torch.where(direct, XX, 2.0 * X + XX)  # A <- A A, or E <- 2E + E E
            with torch.no_grad():
                switch = active & ~direct & (_operator_norm_bound(X_next + eye) < 0.5)[..., None, None]
            X = torch.where(active, torch.where(switch, X_next + eye, X_next), X)
            direct = direct | switch
    A = torch.where(direct, X, X + eye)
    return A, Q, G


# ----------------------------------------------------------------------------------------
# Van Loan's block exponential
# ----------------------------------------------------------------------------------------


def _van_loan(
    F: Tensor, W: Tensor | None, B: Tensor | None, dt: Tensor, batch: torch.Size
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    n = F.shape[-1]
    p = 0 if B is None else B.shape[-1]
    size = 2 * n + p
    dt_mat = dt[..., None, None]
    block = F.new_zeros(*batch, size, size)
    block[..., :n, :n] = F * dt_mat
    if W is not None:
        block[..., :n, n : 2 * n] = W * dt_mat
    block[..., n : 2 * n, n : 2 * n] = -F.mT * dt_mat
    if B is not None:
        block[..., :n, 2 * n :] = B * dt_mat
    E = torch.matrix_exp(block)
    A = E[..., :n, :n]
    Q = None
    if W is not None:
        Q = E[..., :n, n : 2 * n] @ A.mT
        Q = 0.5 * (Q + Q.mT)
    G = E[..., :n, 2 * n :] if B is not None else None
    return A, Q, G
