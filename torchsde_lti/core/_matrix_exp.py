r"""The ``"matrix_exp"`` discretisation method: :func:`torch.matrix_exp` of block matrices (private).

- transition only: ``A = expm(F dt)``;
- with B (zero-order hold): ``expm([[F, B], [0, 0]] dt) = [[A, G], [0, I]]``;
- with noise (Van Loan 1978): ``expm([[F, W, B], [0, −Fᵀ, 0], [0, 0, 0]] dt)`` has blocks
  ``[[A, X, G], [0, A⁻ᵀ, 0], [0, 0, I]]`` and ``Q = X Aᵀ`` (W = L Qc Lᵀ).

Exact in exact arithmetic and one fused call, the cheapest for a few elements. In floating
point the ``−Fᵀ`` block holds ``e^{−Fᵀ dt}`` and Q is recovered by cancellation: its relative
error grows like ``κ = ‖e^{F dt}‖ ‖e^{−F dt}‖ ≤ e^{(μ(F) − μ̌(F)) dt}`` (μ, μ̌ the largest and
smallest eigenvalue of the symmetric part of F), and torch's own squarings (their number set
by the block's norm) round away the slow modes of A. :func:`accurate` is the a-priori bound
under which the default doubling method routes a call here.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchsde_lti.core.linalg import sym
from torchsde_lti.core.validation import SDEInputs

__all__ = ["ROUTE_MAX_ELEMENTS", "accurate", "matrix_exp"]

#: The default method routes calls of at most this many elements here when :func:`accurate`
#: holds (beyond, the doubling's batched series are cheaper than torch's per-matrix kernel).
ROUTE_MAX_ELEMENTS = 512
#: Bounds of :func:`accurate` per dtype: ``(growth, steps)`` — the spread of the symmetric
#: part of F times dt, ln κ, and ‖C‖_F dt of the whole block (torch's squarings).
ROUTE_BOUNDS = {torch.float64: (3.0, 4.0), torch.float32: (1.0, 2.0)}


def matrix_exp(x: SDEInputs) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """(A, Q, G) of shapes (*batch, n, n), (*batch, n, n) or None, (*batch, n, p) or None.

    F: (..., n, n); W = L Qc Lᵀ: (..., n, n) or None; B: (..., n, p) or None; dt: (...),
    all broadcast to ``batch`` (the fields of ``x``). One :func:`torch.matrix_exp` of the
    smallest block that holds what is asked for: (n, n) for A alone, (n+p) with B, (2n+p) with W.
    """
    F, W, B, dt, batch = x
    assert dt is not None
    n = F.shape[-1]
    p = 0 if B is None else B.shape[-1]
    dt_mat = dt[..., None, None]
    if W is None and B is None:
        return torch.matrix_exp((F * dt_mat).expand(*batch, n, n)), None, None
    w = 0 if W is None else n
    size = n + w + p
    block = F.new_zeros(*batch, size, size)
    Fd = F * dt_mat
    block[..., :n, :n] = Fd
    if W is not None:
        block[..., :n, n : 2 * n] = W * dt_mat
        block[..., n : 2 * n, n : 2 * n] = -Fd.mT
    if B is not None:
        block[..., :n, n + w :] = B * dt_mat
    E = torch.matrix_exp(block)
    A = E[..., :n, :n]
    Q = None if W is None else sym(E[..., :n, n : 2 * n] @ A.mT)
    G = None if B is None else E[..., :n, n + w :]
    return A, Q, G


def accurate(x: SDEInputs) -> bool:
    """Whether :func:`matrix_exp` is accurate for every element (an a-priori bound; one
    synchronisation): the relative error of Q is of order eps · κ with
    ``ln κ ≤ (μ(F) − μ̌(F)) dt ≤ √2 ‖S − tr(S)/n I‖_F dt`` (S = (F + Fᵀ)/2: the eigenvalues of
    the traceless part sum to 0, so their spread is at most √2 times their 2-norm), and the
    slow modes of A lose about ``2^s`` eps to torch's ``s ≈ log2 ‖C‖ dt`` squarings, where
    ``‖C‖_F² = 2‖F‖_F² + ‖W‖_F² + ‖B‖_F²`` bounds the block. Both must stay below
    :data:`ROUTE_BOUNDS` (float32 / float64; other dtypes are never routed)."""
    F, W, B, dt, batch = x
    bounds = ROUTE_BOUNDS.get(F.dtype)
    if bounds is None or dt is None or batch.numel() == 0:
        return False
    growth, steps = bounds
    n = F.shape[-1]
    with torch.no_grad():
        S = F + F.mT  # 2 S
        dev = S - torch.diagonal(S, dim1=-2, dim2=-1).mean(-1)[..., None, None] * torch.eye(n, dtype=F.dtype, device=F.device)
        spread = (math.sqrt(2.0) / 2.0) * torch.linalg.matrix_norm(dev)
        block_sq = 2.0 * torch.linalg.matrix_norm(F).square()
        for t in (W, B):
            if t is not None:
                block_sq = block_sq + torch.linalg.matrix_norm(t).square()
        worst = torch.stack([(spread * dt).amax() / growth, (block_sq.sqrt() * dt).amax() / steps])
        return bool(worst.amax() <= 1.0)
