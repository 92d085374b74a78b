r"""Scaling and doubling on Van Loan's block: the few-element path of the doubling method (private).

Every element i has its own F, W = L Qc Lᵀ, B and dt (a parameter batch, a bank of models,
one online step). Per element, one block

    C = [[F, σW, βB], [0, −Fᵀ, 0], [0, 0, 0]] · h,       d = n (+ n if W) (+ p if B),

whose exponential on the sub-step ``h = dt / 2^s`` is (Van Loan 1978)

    expm(C) = [[A_h, σ M, β G_h], [0, A_h^{-T}, 0], [0, 0, I]],    Q_h = M A_hᵀ.

σ, β ≤ 1 are powers of two chosen so that ‖σW‖, ‖βB‖ ≤ max(‖F‖, 1/(4 dt)) (a similarity
transform diag(I, σ^{-1}I, β^{-1}I), exact in floating point): a large Qc or B does not
set the number of halvings. ``s = ceil(log2(‖C‖_F dt / θ))`` with θ = 1 makes ‖C‖_F ≤ 1
(Frobenius: submultiplicative, so it bounds the Taylor remainder), so the
−Fᵀ block grows at most e and the Taylor polynomial of degree m (18 in float64, 11 in
float32; remainder below eps/8 relative to ‖C‖) is accurate to rounding. It is evaluated
by Paterson–Stockmeyer: C², C³, C⁴, one product of the coefficient table with the stacked
powers, and ⌈(m+1)/4⌉ − 1 Horner products in C⁴ — 7 batched products in float64 instead of
one per Taylor term. Then ``s`` doublings on the (n, ·) blocks only
(``_steps._doubling_steps``, shared with the per-term path: Q ← A Q Aᵀ + Q, G ← A G + G,
A = I + E with E ← E + E A while A is near the identity), which add PSD terms (Q stays PSD;
nothing grows like e^{|λ| dt} for stable F). Elements are sorted by s (descending), so
doubling step j only touches a prefix.

Compared with :func:`torchsde_lti.core._doubling._doubling_per_element` (per-term Horner on
n × n matrices), this path has a fixed, small number of batched ops: it wins where every
op costs its dispatch (few elements) and loses where flops count (thousands of elements,
whose 2n-blocks cost 8× the flops of n × n products). ``doubling`` picks by measurement.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch
from torch import Tensor

from torchsde_lti.core._steps import (
    _doubling_order,
    _doubling_steps,
    _finite_or_max,
    _frobenius_norm,
    _halvings_for,
    _Layout,
    _truncation_order,
    _unsort_from_batch_first,
    _unsort_from_batch_first_last,
)
from torchsde_lti.core.validation import SDEInputs

__all__ = ["block_doubling"]

#: Bound on the sub-step block's Frobenius norm.
_THETA = 1.0
#: Powers kept by Paterson–Stockmeyer (C⁰ … C³; the Horner variable is C⁴).
_PS_POWERS = 4
_BATCH_FIRST = _Layout(batch_first=True)
#: Largest exponent k of the similarity scales σ, β = 2^-k.
_MAX_SCALE_EXPONENT = 60


@lru_cache(maxsize=None)
def _ps_table(dtype: torch.dtype, device: torch.device) -> Tensor:
    """(J, q) coefficients of expm(C) − I = Σ_{k=1}^m C^k/k! = Σ_j (Σ_i a_ji C^i) (C^q)^j.
    Cached, so built outside inference mode (an inference tensor cannot join a later graph)."""
    m, q = _truncation_order(dtype, _THETA), _PS_POWERS  # remainder relative to ‖C‖ ≤ θ
    J = m // q + 1
    with torch.inference_mode(False):
        a = torch.zeros(J, q, dtype=torch.float64)
        for k in range(1, m + 1):
            a[k // q, k % q] = 1.0 / math.factorial(k)
        return a.to(dtype=dtype, device=device)


def _expm_minus_identity(C: Tensor) -> Tensor:
    """expm(C) − I for C (N, d, d) with ‖C‖_F ≤ θ, by Paterson–Stockmeyer."""
    N, d = C.shape[0], C.shape[-1]
    q = _PS_POWERS
    powers = [torch.eye(d, dtype=C.dtype, device=C.device).expand(N, d, d), C]
    for _ in range(2, q):
        powers.append(powers[-1] @ C)
    Cq = powers[-1] @ C
    a = _ps_table(C.dtype, C.device)
    blocks = (a @ torch.stack(powers).reshape(q, -1)).reshape(a.shape[0], N, d, d)
    R = blocks[-1]
    for j in range(a.shape[0] - 2, -1, -1):
        R = torch.baddbmm(blocks[j], R, Cq)
    return R


def _power_of_two_scale(norm: Tensor, bound: Tensor) -> Tensor:
    """2^-k, k = ceil(log2(norm / bound)) clamped to [0, 60]: norm · 2^-k ≤ bound where reachable
    (scales down only; 1 for norm ≤ bound or norm 0)."""
    _, k = torch.frexp(norm / bound)  # norm / bound = m 2^k, m ∈ [1/2, 1): ≤ 2^k
    return torch.exp2(-k.clamp(0, _MAX_SCALE_EXPONENT).to(norm.dtype))


def block_doubling(x: SDEInputs, batch_last: bool = False) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """(A, Q, G) of every element by scaling and doubling on Van Loan's block (module doc).

    F: (..., n, n); W: (..., n, n) or None; B: (..., n, p) or None; dt: (...), all
    broadcast to ``x.batch``. Returns (*batch, n, n), (*batch, n, n) or None, (*batch, n, p)
    or None; with ``batch_last`` (n, n, *batch), … (contiguous).
    """
    F, W, B, dt, batch = x
    assert dt is not None
    n = F.shape[-1]
    p = 0 if B is None else B.shape[-1]
    w = 0 if W is None else n
    d = n + w + p
    N = batch.numel()
    dtype, device = F.dtype, F.device
    Fb = F.expand(*batch, n, n).reshape(N, n, n)
    dtf = dt.expand(batch).reshape(N)
    Wb = None if W is None else W.expand(*batch, n, n).reshape(N, n, n)
    Bb = None if B is None else B.expand(*batch, n, p).reshape(N, n, p)

    with torch.no_grad():  # Frobenius norms (submultiplicative: bound the Taylor remainder)
        f = _frobenius_norm(Fb)
        norm = f  # ‖C‖_F / h, accumulated by hypot (no overflow of the squares)
        sigma = beta = None
        if d > n:  # similarity scales σ (W block), β (B block): powers of two, ≤ 1
            bound = torch.maximum(f, 0.25 / dtf.clamp_min(torch.finfo(dtype).tiny))
        if Wb is not None:
            w_norm = _frobenius_norm(Wb)
            sigma = _power_of_two_scale(w_norm, bound)
            norm = torch.hypot(math.sqrt(2.0) * f, sigma * w_norm)  # F and −Fᵀ blocks, σW
        if Bb is not None:
            b_norm = _frobenius_norm(Bb)
            beta = _power_of_two_scale(b_norm, bound)
            norm = torch.hypot(norm, beta * b_norm)
        c = _finite_or_max(norm * dtf)  # ‖C‖_F at the full step
        halvings = _halvings_for(c, _THETA)
    h = dtf * torch.exp2(-halvings)
    hc = h[:, None, None]
    Fh = Fb * hc
    pieces = [Fh]
    if Wb is not None:
        assert sigma is not None
        pieces.append(Wb * (sigma * h)[:, None, None])
    if Bb is not None:
        assert beta is not None
        pieces.append(Bb * (beta * h)[:, None, None])
    Ch = torch.cat(pieces, -1) if d > n else Fh
    if d > n:
        below = Fh.new_zeros(N, d - n, d)
        if Wb is not None:
            below[:, :n, n : 2 * n] = -Fh.mT
        Ch = torch.cat([Ch, below], -2)

    perm, counts = _doubling_order(halvings.to(torch.int64), torch.Size([N]))
    if perm is not None:  # descending halvings: doubling step j touches a prefix
        Ch = perm.sort(Ch)
        sigma = None if sigma is None else perm.sort(sigma)
        beta = None if beta is None else perm.sort(beta)

    E = _expm_minus_identity(Ch)
    X = E[:, :n, :n]  # A_h − I
    Q = None if W is None else torch.baddbmm(E[:, :n, n : 2 * n], E[:, :n, n : 2 * n], X.mT)  # M A_hᵀ (σ-scaled)
    G = None if B is None else E[:, :n, n + w :]  # β-scaled
    if counts:
        A, Q, G = _doubling_steps(X, Q, G, counts, _BATCH_FIRST)
    else:
        A = X + torch.eye(n, dtype=dtype, device=device)
    if Q is not None:
        assert sigma is not None
        Q = (Q + Q.mT) * (0.5 / sigma)[:, None, None]  # symmetrise, undo σ
    if G is not None:
        assert beta is not None
        G = G / beta[:, None, None]  # undo β
    convert = _unsort_from_batch_first_last if batch_last else _unsort_from_batch_first
    return (
        convert(A, perm, batch),
        None if Q is None else convert(Q, perm, batch),
        None if G is None else convert(G, perm, batch),
    )
