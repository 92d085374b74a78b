r"""Small dense kernels: batch-first (``(..., k, k)``: :func:`sym`, :func:`noise_covariance`,
:func:`matvec`) and batch-last (``(r, c, *batch)``, the batch the contiguous inner dimension:
:func:`bl_matmul`; the filters' factorisations and solves are in
:mod:`torchsde_lti.filters.layout`)."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd import forward_ad

__all__ = [
    "bl_matmul",
    "matvec",
    "noise_covariance",
    "sym",
]


def sym(P: Tensor) -> Tensor:
    """``(P + Pᵀ) / 2`` over the last two dimensions: P (..., k, k) -> (..., k, k)."""
    return 0.5 * (P + P.mT)


def noise_covariance(L: Tensor, Qc: Tensor) -> Tensor:
    """W = L Qc Lᵀ, exactly symmetric: L (..., n, s), Qc (..., s, s) -> (..., n, n)."""
    return sym(L @ Qc @ L.mT)


def matvec(M: Tensor, v: Tensor) -> Tensor:
    """``M v``: M (..., r, c), v (..., c) -> (..., r) (batch dims broadcast)."""
    return (M @ v.unsqueeze(-1)).squeeze(-1)


def _fma(a: Tensor, b: Tensor, c: Tensor | None, alpha: float) -> Tensor:
    """c + α a b for a (r, k, N), b (k, s, N), c (r, s, N) or None: k fused multiply-adds."""
    cols, rows = a.split(1, 1), b.split(1, 0)
    if c is None:
        out = cols[0] * rows[0] if alpha == 1.0 else torch.mul(cols[0], rows[0]).mul_(alpha)
    else:
        out = torch.addcmul(c, cols[0], rows[0], value=alpha)
    for col, row in zip(cols[1:], rows[1:]):
        out.addcmul_(col, row, value=alpha)
    return out


class _Fma(torch.autograd.Function):
    """:func:`_fma` whose backward is two such products (not k graph nodes of addcmul)."""

    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor, c: Tensor | None, alpha: float) -> Tensor:
        ctx.save_for_backward(a, b)
        ctx.c_shape, ctx.alpha = None if c is None else c.shape, alpha
        return _fma(a, b, c, alpha)

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor | None, ...]:
        a, b = ctx.saved_tensors
        ga = bl_matmul(g, b.transpose(0, 1), alpha=ctx.alpha) if ctx.needs_input_grad[0] else None
        gb = bl_matmul(a.transpose(0, 1), g, alpha=ctx.alpha) if ctx.needs_input_grad[1] else None
        gc = g.sum_to_size(ctx.c_shape) if ctx.c_shape is not None and ctx.needs_input_grad[2] else None
        return ga, gb, gc, None


def _plain_ops_required() -> bool:
    """Whether a custom autograd Function must step aside for plain ops: under forward-mode AD or
    a ``torch.func`` transform (True if torch's internals move)."""
    try:
        return forward_ad._current_level >= 0 or torch._C._functorch.peek_interpreter_stack() is not None
    except AttributeError:  # pragma: no cover - a torch release without these internals
        return True


def bl_matmul(a: Tensor, b: Tensor, c: Tensor | None = None, alpha: float = 1.0) -> Tensor:
    """``c + α a b`` on batch-last matrices: a (r, k, *B), b (k, s, *B), c broadcastable to
    (r, s, *B) -> (r, s, *B).

    Eagerly with one flat, equal batch dimension: k fused multiply-adds over the contiguous batch
    (their backward two such products where autograd records); otherwise (a broadcast batch, or
    traced: one op for the compiler to fuse, and no ``prims.fma`` in an exported program) a
    ``vecdot`` that keeps the batch innermost."""
    if a.dim() == 3 and b.dim() == 3 and a.shape[-1] == b.shape[-1] and not torch.compiler.is_compiling():
        recording = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (a, b, c))
        if recording and not _plain_ops_required():
            return _Fma.apply(a, b, c, alpha)
        return _fma(a, b, c, alpha)
    out = torch.linalg.vecdot(a.unsqueeze(2), b.unsqueeze(0), dim=1)
    out = out if alpha == 1.0 else out * alpha
    return out if c is None else c + out
