r"""The series of the doubling for an eager call of few elements (private).

Every element takes the same number of halvings ``s = ⌈log₂(max ‖F‖_F dt / θ)⌉`` (from the host
values of a small call, else one synchronisation) and sums the Taylor series of :func:`_series`
on its sub-step ``h = dt / 2^s``, the powers from ⌈log₂ K⌉ products (few torch calls); module
``_doubling`` doubles the result s times.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchsde_lti.core.series import derivative_order
from torchsde_lti.core.thresholds import THETA_PER_ELEMENT
from torchsde_lti.core.validation import SDEInputs, tracing

__all__ = ["eye_matrix", "few_elements_series", "frobenius_norm"]


def _flat(x: Tensor | None, batch: torch.Size, cols: int) -> Tensor | None:
    """(..., n, c) broadcast to (*batch, n, c), flattened to (N, n, c)."""
    if x is None or (x.dim() == 3 and len(batch) == 1 and x.shape[0] == batch[0]):
        return x
    return x.expand(*batch, x.shape[-2], cols).reshape(-1, x.shape[-2], cols)


_POWER_TERMS: dict[tuple[torch.dtype, float, int, int], int] = {}


def power_terms(dtype: torch.dtype, theta: float, n: int, order: int = 0) -> int:
    """Powers K of :func:`_series` for a sub-step with ‖F‖_F h ≤ θ and n states: the omitted
    terms, at most θ^K/K! e^{2θ} relative, are below eps/8 of the smallest leading term an
    entry can have, θ^{n−1}/(n−1)! (a graded Q's, an integrator chain's: each entry keeps its own
    relative accuracy; a Singer model's Q[0, 0] at dt = 1e-6 had 1.7e-7 with eps/8 alone); and
    K ≥ (order + 1) n, so that a nilpotent F's series (index m ≤ n) and its derivatives of order
    ≤ ``order`` with respect to F are exact (those of M^j vanish for j ≥ (order+1) m, module
    :mod:`~torchsde_lti.core.series`; Q's double sum over j, l < K needs no more)."""
    key = (dtype, theta, n, order)
    K = _POWER_TERMS.get(key)
    if K is None:
        eps, K = torch.finfo(dtype).eps, 1
        while theta**K / math.factorial(K) * math.exp(2.0 * theta) >= eps / 8.0:
            K += 1
        smallest, most = min(1.0, theta ** (n - 1) / math.factorial(n - 1)), K + n - 1
        while K < most and theta**K / math.factorial(K) * math.exp(2.0 * theta) >= eps / 8.0 * smallest:
            K += 1
        K = max(K, (order + 1) * n)
        if not tracing():
            _POWER_TERMS[key] = K
    return K


def frobenius_norm(F: Tensor) -> Tensor:
    """‖F‖_F over the last two dims: (..., r, c) -> (...); rescaled by the largest entry where
    the squares overflow."""
    flat = F.reshape(*F.shape[:-2], F.shape[-2] * F.shape[-1])
    norm = torch.linalg.vector_norm(flat, dim=-1)
    overflow = torch.isinf(norm)
    if tracing() or bool(overflow.any()):
        top = flat.abs().amax(-1).clamp_min(torch.finfo(F.dtype).tiny)
        norm = torch.where(overflow, top * torch.linalg.vector_norm(flat / top[..., None], dim=-1), norm)
    return norm


def _scaled(dt: Tensor, s: int) -> Tensor:
    """dt · 2^−s without underflow of the factor (2^−s is applied in pieces of at most 2^−100)."""
    while s > 0:
        dt, s = dt * 2.0 ** -min(s, 100), s - 100
    return dt


def _weights(K: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """Coefficients over the powers j < K: 1/j! for j ≥ 1 (E), 1/(j+1)! (G) and
    H_jl = 1/(j! l! (j+l+1)) (Q); cached per (K, dtype, device) except while tracing."""
    key = (K, dtype, device)
    found = _WEIGHTS.get(key)
    if found is not None:
        return found
    j = torch.arange(K, dtype=torch.float64, device=device)
    inv_fact = torch.exp(-torch.lgamma(j + 1.0))
    e = torch.cat([inv_fact.new_zeros(1), inv_fact[1:]])
    g = torch.exp(-torch.lgamma(j + 2.0))
    H = inv_fact[:, None] * inv_fact[None, :] / (j[:, None] + j[None, :] + 1.0)
    out = (e.to(dtype), g.to(dtype), H.to(dtype))
    if not tracing() and not torch.is_inference_mode_enabled():  # (an inference tensor cannot enter autograd later)
        _WEIGHTS[key] = out
    return out


_WEIGHTS: dict[tuple[int, torch.dtype, torch.device], tuple[Tensor, Tensor, Tensor]] = {}


def _series(M: Tensor, W: Tensor | None, B: Tensor | None, K: int) -> tuple[Tensor, Tensor | None, Tensor | None]:
    r"""Taylor series on a sub-step, M = F h (N, n, n), W (N, n, n) or None, B (N, n, p) or None::

        E_h = Σ_{1≤j<K} M^j/j!,   Q_h/h = Σ_{j,l<K} (M^j W)(M^l)ᵀ / (j! l! (j+l+1)),   G_h/h = Σ_{j<K} M^j B/(j+1)!

    (the exact integrals of the truncated series of expm(F s)). The powers M^j [I, W, B] for
    j < K come from ⌈log₂ K⌉ rounds of two products (``[S, M^{2^i} S]``, ``M^{2^{i+1}}``); the
    three sums are contractions over the power index j.
    """
    N, n = M.shape[0], M.shape[-1]
    eye = eye_matrix(n, M).expand(N, n, n)
    S = torch.cat([eye, *(t for t in (W, B) if t is not None)], -1)  # power 0: (N, n, c)
    c = S.shape[-1]
    power, k = M, 1
    while k < K:
        take = min(k, K - k)
        S = torch.cat([S, torch.bmm(power, S[..., : take * c])], -1)
        k += take
        if k < K:
            power = torch.bmm(power, power)
    S = S.view(N, n, K, c).transpose(-1, -2)  # [a, r, col, j] = (M^j [I, W, B])[r, col]
    e, g, H = _weights(K, M.dtype, M.device)
    P = S[:, :, :n].reshape(N, n, n * K)  # [a, r, (b, l)] = (M^l)[r, b]
    E = torch.mv(P.view(N * n * n, K), e).view(N, n, n)
    Q = G = None
    if W is not None:  # Σ_{j,l} (M^j W)[i, b] H_jl (M^l)[r, b]
        V = (S[:, :, n : 2 * n].reshape(N * n * n, K) @ H).view(N, n, n * K)
        Q = torch.bmm(V, P.mT)
    if B is not None:
        G = S[:, :, c - B.shape[-1] :] @ g
    return E, Q, G


def eye_matrix(n: int, like: Tensor) -> Tensor:
    """The (n, n) identity of ``like``'s dtype and device (cached except while tracing)."""
    key = (n, like.dtype, like.device)
    eye = _EYES.get(key)
    if eye is None:
        eye = torch.eye(n, dtype=like.dtype, device=like.device)
        if not tracing() and not torch.is_inference_mode_enabled():
            _EYES[key] = eye
    return eye


_EYES: dict[tuple[int, torch.dtype, torch.device], Tensor] = {}


def _largest_reach(x: SDEInputs) -> float:
    """max ‖F‖_F dt over the elements (one synchronisation; none from :attr:`SDEInputs.host`,
    which pairs norms with steps where F's batch shape is dt's, else bounds by max ‖F‖ max dt)."""
    F, dt, host = x.F, x.dt, x.host
    assert dt is not None
    if host is None:
        with torch.no_grad():
            return float((torch.linalg.vector_norm(F, dim=(-2, -1)) * dt).max())
    size, v = F.shape[-1] ** 2, host["F"]
    norms = [math.hypot(*v[i : i + size]) for i in range(0, len(v), size)]
    if F.shape[:-2] == dt.shape:
        return max(a * b for a, b in zip(norms, host["dt"]))
    return max(norms) * max(host["dt"])


def few_elements_series(x: SDEInputs) -> tuple[Tensor, Tensor | None, Tensor | None, int]:
    """The series of an eager call of few elements, each with its own F, W, B and dt: (E_h, Q_h,
    G_h, s) on the sub-step h = dt / 2^s, E_h = A_h − I, flat (N, n, n), (N, n, n) or None,
    (N, n, p) or None for the N elements of ``x.batch``. Every element takes the same number of
    halvings s = ⌈log₂(max ‖F‖_F dt / θ)⌉ (from :attr:`SDEInputs.host`, else one synchronisation).

    F: (..., n, n); W: (..., n, n) or None; B: (..., n, p) or None; dt: (...), broadcast to
    ``x.batch``.
    """
    F, W, B, dt, batch = x.F, x.W, x.B, x.dt, x.batch
    assert dt is not None
    n, N = F.shape[-1], math.prod(batch)
    p = 0 if B is None else B.shape[-1]
    theta = THETA_PER_ELEMENT
    Fb, Wb, Bb = _flat(F, batch, n), _flat(W, batch, n), _flat(B, batch, p)
    assert Fb is not None
    dtf = dt if dt.shape == batch and len(batch) == 1 else dt.expand(batch).reshape(N)
    top = _largest_reach(x) if N else 0.0
    if not math.isfinite(top):  # the squares overflowed (or a NaN passed unchecked)
        with torch.no_grad():
            top = float(torch.nan_to_num(frobenius_norm(Fb).double() * dtf.double(), nan=0.0).max())
    if math.isinf(top):
        s = 2 * 1075  # ‖F‖ dt < 2^2150: enough halvings for any product of two doubles
    else:
        s = math.ceil(math.log2(top) - math.log2(theta)) if top > theta else 0
    bound = theta if s else (2.0 ** math.ceil(math.log2(top)) if top > 0 else 0.0)  # (few cache keys)
    hc = _scaled(dtf, s).view(N, 1, 1)
    E, Q, G = _series(Fb * hc, Wb, Bb, power_terms(F.dtype, bound, n, derivative_order(F)))
    return E, None if Q is None else Q * hc, None if G is None else G * hc, s
