r"""Small dense kernels: batch-first (``(..., k, k)``: :func:`sym`, :func:`noise_covariance`,
:func:`matvec`, and for the filters' information forms :func:`cholesky`, :func:`solve_lower`,
:func:`solve_upper_t`, :func:`cho_solve`, unrolled over k ≤ :data:`UNROLLED_MAX_DIM`, LAPACK
beyond) and batch-last (``(r, c, *batch)``, the batch the contiguous inner dimension:
:func:`to_batch_last`, :func:`bl_matmul`)."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd import forward_ad

__all__ = [
    "bl_matmul",
    "cho_solve",
    "cholesky",
    "matvec",
    "noise_covariance",
    "solve_lower",
    "solve_upper_t",
    "sym",
    "to_batch_last",
]

#: Matrices up to this size take the unrolled Cholesky factor and triangular solves.
UNROLLED_MAX_DIM = 4


def sym(P: Tensor) -> Tensor:
    """``(P + Pᵀ) / 2`` over the last two dimensions: P (..., k, k) -> (..., k, k)."""
    return 0.5 * (P + P.mT)


def noise_covariance(L: Tensor, Qc: Tensor) -> Tensor:
    """W = L Qc Lᵀ, exactly symmetric: L (..., n, s), Qc (..., s, s) -> (..., n, n)."""
    return sym(L @ Qc @ L.mT)


def cholesky(S: Tensor, semidefinite: bool = False) -> Tensor:
    r"""Lower Cholesky factor L (L Lᵀ = S) of symmetric S (..., k, k): positive-definite S, or
    with ``semidefinite`` any PSD S, singular allowed.

    Cholesky–Banachiewicz unrolled over k, vectorised over the batch (torch.linalg.cholesky
    for k > :data:`UNROLLED_MAX_DIM` when not ``semidefinite``). Semi-definite: a pivot
    ``d_j ≤ k · eps · S_jj`` (zero to the rounding of its own diagonal entry, so badly scaled
    matrices keep their small pivots) gives a zero column, with gradient 0; no jitter.
    """
    k = S.shape[-1]
    if k > UNROLLED_MAX_DIM and not semidefinite:
        return torch.linalg.cholesky(S)
    zero = torch.zeros_like(S[..., 0, 0])
    if semidefinite:
        rel = k * torch.finfo(S.dtype).eps
        one = torch.ones((), dtype=S.dtype, device=S.device)
    rows: list[list[Tensor]] = [[] for _ in range(k)]  # rows[i][j] = L[i, j] for j <= i
    for j in range(k):
        d = S[..., j, j]
        for t in range(j):
            d = d - rows[j][t] * rows[j][t]
        if semidefinite:
            pos = d > rel * S[..., j, j].detach()
            ljj = torch.where(pos, torch.sqrt(torch.where(pos, d, one)), zero)
            div = torch.where(pos, ljj, one)
        else:
            ljj = div = torch.sqrt(d)
        rows[j].append(ljj)
        for i in range(j + 1, k):
            v = S[..., i, j]
            for t in range(j):
                v = v - rows[i][t] * rows[j][t]
            rows[i].append(torch.where(pos, v / div, zero) if semidefinite else v / div)
    full = [[rows[i][j] if j <= i else zero for j in range(k)] for i in range(k)]
    return torch.stack([torch.stack(r, dim=-1) for r in full], dim=-2)


def solve_lower(L: Tensor, B: Tensor) -> Tensor:
    """X with ``L X = B``; L (..., k, k) lower triangular, B (..., k, r) -> X (..., k, r)."""
    k = L.shape[-1]
    if k > UNROLLED_MAX_DIM:
        return torch.linalg.solve_triangular(L, B, upper=False)
    xs: list[Tensor] = []
    for i in range(k):
        v = B[..., i, :]
        for j in range(i):
            v = v - L[..., i, j, None] * xs[j]
        xs.append(v / L[..., i, i, None])
    return torch.stack(xs, dim=-2)


def solve_upper_t(L: Tensor, B: Tensor) -> Tensor:
    """X with ``Lᵀ X = B``; L (..., k, k) lower triangular, B (..., k, r) -> X (..., k, r)."""
    k = L.shape[-1]
    if k > UNROLLED_MAX_DIM:
        return torch.linalg.solve_triangular(L.mT, B, upper=True)
    xs: list[Tensor | None] = [None] * k
    for i in reversed(range(k)):
        v = B[..., i, :]
        for j in range(i + 1, k):
            x = xs[j]
            assert x is not None
            v = v - L[..., j, i, None] * x
        xs[i] = v / L[..., i, i, None]
    return torch.stack([x for x in xs if x is not None], dim=-2)


def cho_solve(L: Tensor, B: Tensor, semidefinite: bool = False) -> Tensor:
    """X with ``(L Lᵀ) X = B`` from the Cholesky factor L (..., k, k); B (..., k, r).

    ``semidefinite``: L from :func:`cholesky` ``(S, semidefinite=True)`` of a singular S: a
    zero pivot's component of X is 0 (X = S⁻ B for a generalised inverse S⁻, S S⁻ S = S;
    the solution where B lies in the range of S)."""
    if not semidefinite:
        return solve_upper_t(L, solve_lower(L, B))
    kept = (torch.diagonal(L, dim1=-2, dim2=-1) > 0).to(L.dtype)
    L = L + torch.diag_embed(1.0 - kept)  # a zero column of L: unit pivot, then its component zeroed
    return solve_upper_t(L, solve_lower(L, B) * kept[..., None]) * kept[..., None]


def matvec(M: Tensor, v: Tensor) -> Tensor:
    """``M v``: M (..., r, c), v (..., c) -> (..., r) (batch dims broadcast)."""
    return (M @ v.unsqueeze(-1)).squeeze(-1)


def to_batch_last(x: Tensor, event_ndim: int) -> Tensor:
    """``(*batch, *event) -> (*event, *batch)``, contiguous."""
    nb = x.dim() - event_ndim
    return x.permute(*range(nb, x.dim()), *range(nb)).contiguous()


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
