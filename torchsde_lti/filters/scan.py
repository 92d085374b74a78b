r"""The Kalman filter by associative scan (Särkkä & García-Fernández 2021), O(log T) depth.

Same quantities as the sequential filter, computed with a parallel prefix scan over per-step
filtering elements, on the batch-last layout of :mod:`~torchsde_lti.filters.layout` (the steps
are one more batch dimension of every product). Its 2 log₂ T levels replace the loop's T steps:
it wins where per-operation overhead, not arithmetic, sets the loop's time (few tracks, long
series), and does a few times the loop's arithmetic where the batch fills the cores.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from torchsde_lti.filters.inputs import PreparedInputs, complete_from_filtered
from torchsde_lti.filters.layout import mm, mv, solve, sym, tr
from torchsde_lti.filters.results import FilterResult

__all__ = ["associative_scan", "scan_filter", "scan_filtered"]


Elems = tuple[Tensor, ...]


def associative_scan(fn: Callable[[Elems, Elems], Elems], elems: Sequence[Tensor], reverse: bool = False) -> Elems:
    """Inclusive scan of an associative ``fn`` along dim 0 with O(log T) depth.

    ``fn(a, b)`` combines earlier elements ``a`` with later ``b`` (each a tuple of tensors
    with the same leading length). With ``reverse=True`` the scan runs from the end:
    result k is ``e_k ⊗ e_{k+1} ⊗ … ⊗ e_{T-1}``. Odd/even recursion as in
    ``jax.lax.associative_scan``: O(T) work, 2 log2 T sequential levels; while torch.export
    traces, recursive doubling (:func:`_shift_scan`: any T).
    """
    el = tuple(elems)
    if reverse:
        el = tuple(torch.flip(x, (0,)) for x in el)
        out = associative_scan(lambda a, b: fn(b, a), el)
        return tuple(torch.flip(x, (0,)) for x in out)
    return _shift_scan(fn, el) if torch.compiler.is_exporting() else _scan(fn, el)


def _scan(fn: Callable[[Elems, Elems], Elems], el: Elems) -> Elems:
    T = el[0].shape[0]
    if T < 2:
        return el
    reduced = fn(tuple(x[0:-1:2] for x in el), tuple(x[1::2] for x in el))
    odd = _scan(fn, reduced)
    if T % 2 == 0:
        even = fn(tuple(x[:-1] for x in odd), tuple(x[2::2] for x in el))
    else:
        even = fn(odd, tuple(x[2::2] for x in el))
    out = []
    for e0, ev, od in zip(el, even, odd):
        ev = torch.cat([e0[:1].expand(1, *ev.shape[1:]), ev], dim=0)
        od = od.expand(od.shape[0], *ev.shape[1:])
        inter = torch.stack([ev[: od.shape[0]], od], dim=1).reshape(2 * od.shape[0], *ev.shape[1:])
        if ev.shape[0] > od.shape[0]:
            inter = torch.cat([inter, ev[-1:]], dim=0)
        out.append(inter)
    return tuple(out)


def _shift_scan(fn: Callable[[Elems, Elems], Elems], el: Elems) -> Elems:
    """The inclusive scan of :func:`_scan` by recursive doubling (Hillis & Steele 1986): at
    level k every element e_t with t ≥ 2^k becomes ``fn(e_{t−2^k}, e_t)``; after ⌈log2 T⌉
    levels e_t = e_0 ⊗ … ⊗ e_t. Each level keeps every shape (the elements must have their full
    shapes), so the levels run as one ``while_loop`` for any T: what an exported program with a
    dynamic time axis runs. O(T log T) work in ⌈log2 T⌉ combines."""
    from torch._higher_order_ops import while_loop

    T = el[0].shape[0]
    full = tuple(x.clone(memory_format=torch.contiguous_format) for x in el)  # (each level's strides)
    steps = torch.arange(T, device=el[0].device)

    def more(offset: Tensor, *xs: Tensor) -> Tensor:
        return offset < T

    def level(offset: Tensor, *xs: Tensor) -> tuple[Tensor, ...]:
        earlier = (steps - offset).clamp_min(0)
        combined = fn(tuple(x.index_select(0, earlier) for x in xs), xs)
        kept = steps < offset
        return (offset * 2, *(torch.where(kept.view(-1, *[1] * (x.dim() - 1)), x, c) for c, x in zip(combined, xs)))

    return tuple(while_loop(more, level, (torch.ones((), dtype=torch.int64, device=steps.device), *full))[1:])


def _filter_combine(a: Elems, b: Elems) -> Elems:
    """Särkkä & García-Fernández (2021), Lemma 7: combine filtering elements a (earlier), b
    (later), each (A, b, C, η, J) of shapes (T', n, n, *B), (T', n, *B), …, with one solve:
    ``[Ā | Φ | β] = (I + C_i J_j)⁻¹ [A_i | C_i | b_i + C_i η_j]`` (I + C J has eigenvalues ≥ 1),
    then ``(I + J_j C_i)⁻¹ = I − J_j Φ``::

        A = A_j Ā,  b = A_j β + b_j,  C = A_j Φ A_jᵀ + C_j,
        η = A_iᵀ (I − J_j Φ) (η_j − J_j b_i) + η_i,  J = A_iᵀ (J_j − J_j Φ J_j) A_i + J_i.
    """
    Ai, bi, Ci, ei, Ji = a
    Aj, bj, Cj, ej, Jj = b
    n = Ai.shape[1]
    eye = torch.eye(n, dtype=Ai.dtype, device=Ai.device).reshape(1, n, n, *[1] * (Ai.dim() - 3))
    rhs = torch.cat([Ai, Ci, (bi + mv(Ci, ej, 1)).unsqueeze(2)], 2)
    sol = solve(eye + mm(Ci, Jj, 1), rhs)
    Phi = sol[:, :, n : 2 * n]
    JPhi = mm(Jj, Phi, 1)
    u = ej - mv(Jj, bi, 1)
    A = mm(Aj, sol[:, :, :n], 1)
    C = sym(mm(mm(Aj, Phi, 1), tr(Aj, 1), 1), 1) + Cj
    bb = mv(Aj, sol[:, :, 2 * n], 1) + bj
    e = mv(tr(Ai, 1), u - mv(JPhi, u, 1), 1) + ei
    J = sym(mm(mm(tr(Ai, 1), Jj - mm(JPhi, Jj, 1), 1), Ai, 1), 1) + Ji
    return A, bb, C, e, J


def scan_filter(prep: PreparedInputs) -> FilterResult:
    """Kalman filter by associative scan on prepared inputs (:func:`scan_filtered`), every
    output of :class:`~torchsde_lti.filters.FilterResult` then formed batched over the steps."""
    return complete_from_filtered(prep, *scan_filtered(prep))


def scan_filtered(prep: PreparedInputs) -> tuple[Tensor, Tensor]:
    r"""Filtered means (T, n, *b) and covariances (T, n, n, *b) by associative scan
    (Särkkä & García-Fernández 2021), O(log T) depth.

    On prepared inputs; same results as the sequential loop (up to rounding). Step k's element
    (with whitened H', y' and R' = I, prior moments ``c_k = G_k u_k``, ``Q_k``; for k = 0 the
    prior is folded in: ``c_0 += A_0 m0``, ``Q_0 += A_0 P0 A_0ᵀ``, ``A_0 := 0``)::

        S = H' Q Hᵀ' + I,  K = Q H'ᵀ S⁻¹,  Ā = (I − K H') A,  b = c + K (y' − H' c),
        C = (I − K H') Q (I − K H')ᵀ + K Kᵀ,  η = Aᵀ H'ᵀ S⁻¹ (y' − H' c),  J = Aᵀ H'ᵀ S⁻¹ H' A.

    The scan (:func:`associative_scan`, :func:`_filter_combine`) yields the filtered (b, C).
    """
    A, Q, Hw, yw, T = prep.A, prep.Q, prep.Hw, prep.yw, prep.T
    n, m = A.shape[1], Hw.shape[1]
    c = prep.c if prep.c is not None else A.new_zeros((1, n, *[1] * (A.dim() - 3)))
    batch = torch.broadcast_shapes(A.shape[3:], Q.shape[3:], Hw.shape[3:], yw.shape[2:], c.shape[2:])
    batch = torch.broadcast_shapes(batch, prep.m0.shape[1:], prep.P0.shape[2:])
    A0, ones = A[0], [1] * len(batch)
    # step 0 takes the prior (selected by a mask over the steps: no size-(T − 1) slice, which a
    # traced program with a dynamic T would have to guard against being 1)
    first = (torch.arange(T, device=A.device) == 0).reshape(T, 1, 1, *ones)
    Qe = torch.where(first, (sym(mm(mm(A0, prep.P0), tr(A0))) + Q[0]).unsqueeze(0), Q)
    ce = torch.where(first[:, 0], (mv(A0, prep.m0) + c[0]).unsqueeze(0), c)
    Ae = torch.where(first, 0.0, A)
    HQ, HA = mm(Hw, Qe, 1), mm(Hw, Ae, 1)  # (T, m, n, *b)
    v = yw - mv(Hw, ce, 1)  # (T, m, *b)
    eye_m = torch.eye(m, dtype=A.dtype, device=A.device).reshape(1, m, m, *ones)
    sol = solve(sym(mm(HQ, tr(Hw, 1), 1), 1) + eye_m, torch.cat([HQ, HA, v.unsqueeze(2)], 2))
    Kt = sol[:, :, :n]  # Kᵀ = S⁻¹ H' Q (T, m, n, *b)
    IKH = torch.eye(n, dtype=A.dtype, device=A.device).reshape(1, n, n, *ones) - mm(tr(Kt, 1), Hw, 1)
    elems = (
        mm(IKH, Ae, 1),
        ce + mv(tr(Kt, 1), v, 1),
        sym(mm(mm(IKH, Qe, 1), tr(IKH, 1), 1) + mm(tr(Kt, 1), Kt, 1), 1),
        mv(tr(HA, 1), sol[:, :, 2 * n], 1),
        sym(mm(tr(HA, 1), sol[:, :, n : 2 * n], 1), 1),
    )
    full = tuple(x.expand(*x.shape[: x.dim() - len(batch)], *batch).contiguous() for x in elems)
    _, b, C, _, _ = associative_scan(_filter_combine, full)
    return b, C
