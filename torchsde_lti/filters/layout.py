r"""The one memory layout of every filter and smoother: batch-last, time leading.

A state is ``(r, c, *batch)`` (a matrix) or ``(r, *batch)`` (a vector); a sequence of them
``(T, r, c, *batch)`` / ``(T, r, *batch)``, contiguous. The batch is the contiguous inner
dimension, so every elementwise operation, and every small product written as ``k``
multiply-adds over the batch (:func:`mm`), runs at vector speed; batched BLAS / LAPACK calls on
4 × 4 matrices cost several times more per matrix at these sizes. ``at`` is the position of the
event dimensions: 0 for a state, 1 for a sequence (the steps are then one more batch dimension).
Results are returned batch-first, as views (:func:`batch_first`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["batch_first", "batch_last", "lower_solve", "mm", "mv", "psd_cholesky", "psd_solve", "solve", "sym", "tr"]


def batch_last(x: Tensor, event_ndim: int, batch_ndim: int, time: bool = True) -> Tensor:
    """``(*b, [T,] *event) -> ([T,] *event, *b)`` contiguous, ``b`` left-padded with size-1
    dims to ``batch_ndim`` dims (broadcast dims stay size 1)."""
    lead = batch_ndim + (1 if time else 0) + event_ndim - x.dim()
    if lead > 0:
        x = x.reshape((1,) * lead + tuple(x.shape))
    front = [batch_ndim] if time else []
    first = batch_ndim + len(front)
    return x.permute(*front, *range(first, first + event_ndim), *range(batch_ndim)).contiguous()


def batch_first(x: Tensor, event_ndim: int, batch_ndim: int) -> Tensor:
    """``(T, *event, *b) -> (*b, T, *event)`` (a view)."""
    return x.permute(*range(1 + event_ndim, 1 + event_ndim + batch_ndim), *range(1 + event_ndim))


def mm(a: Tensor, b: Tensor, at: int = 0) -> Tensor:
    """``a b``: a (*L, r, k, *B), b (*L, k, s, *B) -> (*L, r, s, *B), ``len(L) == at``: k
    multiply-adds of (r, 1, *B) by (1, s, *B) (batch dims broadcast)."""
    cols, rows = a.split(1, at + 1), b.split(1, at)
    out = cols[0] * rows[0]
    if torch.is_grad_enabled() and (a.requires_grad or b.requires_grad):
        for col, row in zip(cols[1:], rows[1:]):
            out = torch.addcmul(out, col, row)
    else:  # (no graph to record: accumulate in place, one buffer)
        for col, row in zip(cols[1:], rows[1:]):
            out.addcmul_(col, row)
    return out


def mv(a: Tensor, v: Tensor, at: int = 0) -> Tensor:
    """``a v``: a (*L, r, k, *B), v (*L, k, *B) -> (*L, r, *B)."""
    return torch.linalg.vecdot(a, v.unsqueeze(at), dim=at + 1)


def tr(a: Tensor, at: int = 0) -> Tensor:
    """``aᵀ`` (a view): (*L, r, c, *B) -> (*L, c, r, *B)."""
    return a.transpose(at, at + 1)


def sym(a: Tensor, at: int = 0) -> Tensor:
    """``(a + aᵀ) / 2``: (*L, k, k, *B)."""
    return 0.5 * (a + a.transpose(at, at + 1))


def solve(X: Tensor, B: Tensor, at: int = 1) -> Tensor:
    """``X⁻¹ B`` for X (*L, k, k, *b), B (*L, k, r, *b) batch-last (``len(L) == at``): Gaussian
    elimination with partial pivoting, unrolled over k (the row swaps as ``where``), so it runs
    elementwise over the contiguous batch; X non-singular."""
    k = X.shape[at]
    rows = list(_augmented(X, B, at).unbind(at))  # k rows [X_i | B_i], each (*L, k + r, *b)
    col = lambda row, j: row.narrow(at, j, 1)  # noqa: E731  (one column of a row: (*L, 1, *b))
    for j in range(k):
        for i in range(j + 1, k):  # the largest |entry| of column j among rows j … k−1 to row j
            swap = col(rows[i], j).abs() > col(rows[j], j).abs()
            rows[j], rows[i] = torch.where(swap, rows[i], rows[j]), torch.where(swap, rows[j], rows[i])
        for i in range(j + 1, k):
            rows[i] = rows[i] - (col(rows[i], j) / col(rows[j], j)) * rows[j]
    x: list[Tensor] = []
    for i in reversed(range(k)):
        v = rows[i].narrow(at, k, rows[i].shape[at] - k)
        for j, xj in zip(range(i + 1, k), reversed(x)):
            v = v - col(rows[i], j) * xj
        x.append(v / col(rows[i], i))
    return torch.stack(x[::-1], at)


def _augmented(X: Tensor, B: Tensor, at: int) -> Tensor:
    """``[X | B]`` (*L, k, k + r, *b), both broadcast to one batch."""
    batch = torch.broadcast_shapes(X.shape[at + 2 :], B.shape[at + 2 :])
    return torch.cat([X.expand(*X.shape[: at + 2], *batch), B.expand(*B.shape[: at + 2], *batch)], at + 1)


def _factor(P: Tensor, at: int, diagonal: bool = True) -> tuple[list[list[Tensor]], list[Tensor]]:
    """The entries ``L_ij`` (j ≤ i; j < i without ``diagonal``) of :func:`psd_cholesky`'s factor
    and its inverted pivots, each (*L, *b)."""
    k = P.shape[at]
    rel = k * torch.finfo(P.dtype).eps
    entries = [row.unbind(at) for row in P.unbind(at)]  # P_ij (*L, *b): views
    low: list[list[Tensor]] = [[] for _ in range(k)]
    inv: list[Tensor] = []
    for j in range(k):
        d = entries[j][j]
        for t in range(j):
            d = d - low[j][t] * low[j][t]
        keep = d > rel * entries[j][j]  # (a comparison: no gradient flows through it)
        inv.append(torch.where(keep, d, math.inf).rsqrt())  # (1 / ∞ = 0: a dropped pivot, gradient 0)
        if diagonal:
            low[j].append(d * inv[j])
        for i in range(j + 1, k):
            v = entries[i][j]
            for t in range(j):
                v = v - low[i][t] * low[j][t]
            low[i].append(v * inv[j])
    return low, inv


def psd_cholesky(P: Tensor, at: int = 1) -> tuple[Tensor, Tensor]:
    """(L, d) for symmetric PSD P (*L, k, k, *b): the lower Cholesky factor, unrolled over k and
    elementwise over the batch, and its inverted pivots ``d_j = 1 / L_jj`` (*L, k, *b). A pivot
    ``L_jj² ≤ k · eps · P_jj`` (zero to the rounding of its own diagonal entry, so badly scaled
    matrices keep their small pivots) gives a zero column of L and ``d_j = 0``, with gradient 0;
    no jitter."""
    low, inv = _factor(P, at)
    k, zero = len(inv), torch.zeros_like(low[0][0])
    rows = [torch.stack(torch.broadcast_tensors(*row, *[zero] * (k - len(row))), at) for row in low]
    return torch.stack(rows, at), torch.stack(torch.broadcast_tensors(*inv), at)


def lower_solve(L: Tensor, d: Tensor, B: Tensor, tail: int) -> Tensor:
    """``L⁻¹ B`` for L (…, k, k, *b) lower triangular with inverted pivots d (…, k, *b)
    (:func:`psd_cholesky`; a zero pivot gives a zero row) and B (…, k, r, *b), ``tail`` = len(b)
    (leading dims broadcast, right-aligned)."""
    at, at_b = L.dim() - tail - 2, B.dim() - tail - 2
    z: list[Tensor] = []
    for j, row in enumerate(B.unbind(at_b)):  # (…, r, *b)
        for t in range(j):
            row = row - L.select(at, j).narrow(at, t, 1) * z[t]
        z.append(row * d.narrow(at, j, 1))
    return torch.stack(z, at_b)


def psd_solve(P: Tensor, B: Tensor, at: int = 1) -> Tensor:
    """``P⁻ B`` for symmetric PSD P (*L, k, k, *b) and B (*L, k, r, *b) by the factor of
    :func:`psd_cholesky`: a dropped pivot gives a zero component of the solution, so a singular
    P gives a generalised inverse (``P P⁻ P = P``; the solution where B lies in P's range)."""
    low, inv = _factor(P, at)
    k = len(inv)
    entry = [[x.unsqueeze(at) for x in row] for row in low]  # (*L, 1, *b) against a row of B
    pivot = [x.unsqueeze(at) for x in inv]
    z: list[Tensor] = []
    for j, row in enumerate(B.unbind(at)):  # L z = B, row by row (*L, r, *b)
        for t in range(j):
            row = row - entry[j][t] * z[t]
        z.append(row * pivot[j])
    x: list[Tensor] = [z[-1] * pivot[-1]]
    for j in reversed(range(k - 1)):  # Lᵀ x = z
        v = z[j]
        for t, xt in zip(range(k - 1, j, -1), x):
            v = v - entry[t][j] * xt
        x.append(v * pivot[j])
    return torch.stack(x[::-1], at)
