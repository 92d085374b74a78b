r"""The Kalman filter by associative scan (Särkkä & García-Fernández 2021), O(log T) depth.

Same quantities as the sequential filter, computed with a parallel prefix scan over
per-step filtering elements; wins when per-step Python overhead dominates the loop (few
tracks, long series).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from torchsde_lti.core.linalg import cho_solve, cholesky, matvec, sym
from torchsde_lti.core.validation import broadcast_batch
from torchsde_lti.filters.inputs import (
    FilterInputs,
    PreparedInputs,
    check_mask,
    complete_from_filtered,
    pad_dims,
    prepare_inputs,
)
from torchsde_lti.filters.results import FilterResult

__all__ = [
    "SCAN_MAX_BATCH_CPU",
    "SCAN_MAX_ELEMENTS",
    "associative_scan",
    "chunked_scan",
    "prefers_scan",
    "scan_filter",
    "scan_filtered",
]


Elems = tuple[Tensor, ...]


def associative_scan(fn: Callable[[Elems, Elems], Elems], elems: Sequence[Tensor], reverse: bool = False) -> Elems:
    """Inclusive scan of an associative ``fn`` along dim 0 with O(log T) depth.

    ``fn(a, b)`` combines earlier elements ``a`` with later ``b`` (each a tuple of tensors
    with the same leading length). With ``reverse=True`` the scan runs from the end:
    result k is ``e_k ⊗ e_{k+1} ⊗ … ⊗ e_{T-1}``. Odd/even recursion as in
    ``jax.lax.associative_scan``: O(T) work, 2 log2 T sequential levels.
    """
    el = tuple(elems)
    if reverse:
        el = tuple(torch.flip(x, (0,)) for x in el)
        out = _scan(lambda a, b: fn(b, a), el)
        return tuple(torch.flip(x, (0,)) for x in out)
    return _scan(fn, el)


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


def _shift_scan(fn: Callable[[Elems, Elems], Elems], el: Elems, event_ndims: Sequence[int]) -> Elems:
    """The inclusive scan of :func:`_scan` by recursive doubling (Hillis & Steele 1986): at
    level k every element e_t with t ≥ 2^k becomes ``fn(e_{t−2^k}, e_t)``; after ⌈log2 T⌉
    levels e_t = e_0 ⊗ … ⊗ e_t. Each level keeps every shape (the elements, (T, *batch, *event)
    with ``event_ndims`` event dims each, are broadcast to one batch first), so the levels run
    as one ``while_loop`` for any T: what an exported program with a dynamic time axis runs.
    O(T log T) work in ⌈log2 T⌉ combines."""
    from torch._higher_order_ops import while_loop

    T = el[0].shape[0]
    lead = torch.broadcast_shapes(*(x.shape[1 : x.dim() - e] for x, e in zip(el, event_ndims)))
    # (fresh row-major copies: each level's results have those strides, zero-size ones too)
    full = tuple(
        x.expand(T, *lead, *x.shape[x.dim() - e :]).clone(memory_format=torch.contiguous_format)
        for x, e in zip(el, event_ndims)
    )
    steps = torch.arange(T, device=el[0].device)

    def more(offset: Tensor, *xs: Tensor) -> Tensor:
        return offset < T

    def level(offset: Tensor, *xs: Tensor) -> tuple[Tensor, ...]:
        earlier = (steps - offset).clamp_min(0)
        combined = fn(tuple(x.index_select(0, earlier) for x in xs), xs)
        kept = steps < offset
        out = tuple(
            torch.where(kept.view(-1, *[1] * (x.dim() - 1)), x, c.expand(x.shape)) for c, x in zip(combined, xs)
        )
        return (offset * 2, *out)

    return tuple(while_loop(more, level, (torch.ones((), dtype=torch.int64, device=steps.device), *full))[1:])


def _filter_combine(a: Elems, b: Elems) -> Elems:
    """Särkkä & García-Fernández (2021), Lemma 7: combine filtering elements a (earlier), b (later)."""
    Ai, bi, Ci, ei, Ji = a
    Aj, bj, Cj, ej, Jj = b
    n = Ai.shape[-1]
    eye = torch.eye(n, dtype=Ai.dtype, device=Ai.device)
    X = eye + Ci @ Jj  # I + C_i J_j (eigenvalues ≥ 1: C, J PSD)
    bi_col = (bi + matvec(Ci, ej)).unsqueeze(-1)
    ecol = (ej - matvec(Jj, bi)).unsqueeze(-1)
    lead = torch.broadcast_shapes(X.shape[:-2], bi_col.shape[:-2], ecol.shape[:-2])
    LU, piv, _ = torch.linalg.lu_factor_ex(X.expand(*lead, n, n))  # one factorisation, two solves
    rhs = torch.cat([Ai.expand(*lead, n, n), Ci.expand(*lead, n, n), bi_col.expand(*lead, n, 1)], dim=-1)
    sol = torch.linalg.lu_solve(LU, piv, rhs)  # (I + C_i J_j)^{-1} [A_i, C_i, b_i + C_i η_j]
    A = Aj @ sol[..., :n]
    C = sym(Aj @ sol[..., n : 2 * n] @ Aj.mT + Cj)
    b = matvec(Aj, sol[..., 2 * n]) + bj
    rhs2 = torch.cat([(Jj @ Ai).expand(*lead, n, n), ecol.expand(*lead, n, 1)], dim=-1)
    sol2 = torch.linalg.lu_solve(LU, piv, rhs2, adjoint=True)  # (I + J_j C_i)^{-1} [J_j A_i, η_j − J_j b_i]
    J = sym(Ai.mT @ sol2[..., :n] + Ji)
    e = matvec(Ai.mT, sol2[..., n]) + ei
    return A, b, C, e, J


def scan_filter(prep: PreparedInputs) -> FilterResult:
    """Kalman filter by associative scan on prepared inputs (:func:`scan_filtered`), every
    output of :class:`~torchsde_lti.filters.FilterResult` then formed batched over the steps."""
    return complete_from_filtered(prep, *scan_filtered(prep))


def scan_filtered(prep: PreparedInputs) -> tuple[Tensor, Tensor]:
    r"""Filtered means (..., T, n) and covariances (..., T, n, n) by associative scan
    (Särkkä & García-Fernández 2021), O(log T) depth.

    On prepared inputs; same results as the sequential loop (up to rounding). Step k's element
    (with whitened H', y' and R' = I, prior moments ``c_k = G_k u_k``, ``Q_k``; for k = 0 the
    prior is folded in: ``c_0 += A_0 m0``, ``Q_0 += A_0 P0 A_0ᵀ``, ``A_0 := 0``)::

        S = H' Q Hᵀ' + I,  K = Q H'ᵀ S⁻¹,  Ā = (I − K H') A,  b = c + K (y' − H' c),
        C = (I − K H') Q (I − K H')ᵀ + K Kᵀ,  η = Aᵀ H'ᵀ S⁻¹ (y' − H' c),  J = Aᵀ H'ᵀ S⁻¹ H' A.

    The scan yields filtered (b, C). Wins over the sequential loop when per-step Python
    overhead dominates (small batch, long T); loses when the batch already fills the cores.
    While torch.export traces, the scan is :func:`_shift_scan` (any T).
    """
    n = prep.A.shape[-1]
    T = prep.T
    A_ = prep.A
    Qp = prep.Q
    cp = prep.c if prep.c is not None else torch.zeros((), dtype=A_.dtype, device=A_.device)
    A0 = A_[..., 0, :, :]
    P0m = sym(A0 @ prep.P0 @ A0.mT + Qp[..., 0, :, :])
    m0m = matvec(A0, prep.m0) + (cp[..., 0, :] if prep.c is not None else 0.0)
    # step 0 takes the prior (selected by a mask over the steps: no size-(T − 1) slice, which a
    # traced program with a dynamic T would have to guard against being 1)
    first = torch.arange(T, device=A_.device) == 0  # (T,)
    Qe = torch.where(first[:, None, None], P0m.unsqueeze(-3), Qp)
    Ae = torch.where(first[:, None, None], 0.0, A_)
    mb = prep.mean_batch
    cfull = cp.expand(*mb, T, n) if prep.c is not None else torch.zeros((*mb, T, n), dtype=A_.dtype, device=A_.device)
    ce = torch.where(first[:, None], m0m.unsqueeze(-2), cfull)

    Hw, yw = prep.Hw, prep.yw
    HQ = Hw @ Qe  # (.., T, m, n)
    # (transpose, not .mT: inside torch.cond's trace Hw.mT became an input aliasing Hw)
    S = sym(HQ @ Hw.transpose(-1, -2)) + torch.eye(Hw.shape[-2], dtype=Hw.dtype, device=Hw.device)
    LS = cholesky(S)
    Kt = cho_solve(LS, HQ)  # Kᵀ = S⁻¹ H' Q  (m, n)
    K = Kt.mT
    IKH = torch.eye(n, dtype=A_.dtype, device=A_.device) - K @ Hw
    v = yw - matvec(Hw, ce)
    b = ce + matvec(K, v)
    C = sym(IKH @ Qe @ IKH.mT + K @ Kt)
    Abar = IKH @ Ae
    HA = Hw @ Ae  # (.., T, m, n)
    Sinv_HA = cho_solve(LS, HA)
    J = sym(HA.mT @ Sinv_HA)
    Sinv_v = cho_solve(LS, v.unsqueeze(-1)).squeeze(-1)
    eta = matvec(HA.mT, Sinv_v)

    elems = (Abar, b, C, eta, J)
    tm = [-3, -2, -3, -2, -3]
    moved = tuple(x.movedim(d, 0) for x, d in zip(elems, tm))
    if torch.compiler.is_exporting():  # an exported program takes any T: no recursion on T's value
        scanned = _shift_scan(_filter_combine, moved, [-d - 1 for d in tm])
    else:
        scanned = _scan(_filter_combine, moved)
    return scanned[1].movedim(0, -2), scanned[2].movedim(0, -3)


# ----------------------------------------------------------------------------------------
# Algorithm choice and the chunked scan
# ----------------------------------------------------------------------------------------

#: On CPU the scan wins up to this many tracks (per-step Python overhead dominates the
#: loop there); beyond it the loop's vectorised steps win (the crossover is measured in the
#: documentation's benchmarks, "Kalman filter throughput").
SCAN_MAX_BATCH_CPU = 16
#: One scan holds about 30 n² numbers per track and step; longer series are scanned in
#: chunks of at most this many track·steps (memory bound, no measurable loss at ≥ 2^16).
SCAN_MAX_ELEMENTS = 1 << 18


def prefers_scan(batch_size: int, T: int, device: torch.device, dtype: torch.dtype = torch.float64) -> bool:
    """The automatic algorithm choice: True for the (chunked) associative scan, False for
    the sequential loop. Float64 only (in float32 the scan's combine loses the covariances
    over long gaps: a predicted-to-measured variance ratio of about 1e11 gives NaN, less a
    wrong log-likelihood; the loop's Joseph updates do not). CPU: scan for at most
    :data:`SCAN_MAX_BATCH_CPU` tracks and T > 1. Other devices (where every loop step costs
    kernel launches): always the scan."""
    return T >= 2 and _scan_suits(batch_size, device, dtype)


def _scan_suits(batch_size: int, device: torch.device, dtype: torch.dtype) -> bool:
    """:func:`prefers_scan`'s rule without T (float64; at most :data:`SCAN_MAX_BATCH_CPU`
    tracks on the CPU, any batch elsewhere): a symbolic ``batch_size`` gives a symbolic bool."""
    if dtype != torch.float64:
        return False
    return device.type != "cpu" or batch_size <= SCAN_MAX_BATCH_CPU


def _time_slice(x: Tensor | None, axis: int, T: int, start: int, stop: int) -> Tensor | None:
    """x[..., start:stop, ...] along ``axis`` (counted from the end) when that axis is T."""
    if x is None or x.dim() < -axis or x.shape[axis] != T:
        return x
    return x.narrow(x.dim() + axis, start, stop - start)


def chunked_scan(args: FilterInputs, chunk: int | None = None, validate_args: bool = True) -> FilterResult:
    """:func:`scan_filter` over consecutive time chunks of ``chunk`` steps, each chunk's prior
    the previous chunk's last filtered state (exact: the filter is Markov).

    Memory O(batch · chunk) instead of O(batch · T); depth (T / chunk) · O(log chunk).
    ``chunk``: a positive int, or None for the largest chunk with batch · chunk ≤
    :data:`SCAN_MAX_ELEMENTS`; ValueError otherwise.
    """
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1):
        raise ValueError(f"chunk must be a positive integer or None, got {chunk!r}")
    if torch.compiler.is_exporting():  # one scan over any T, no chunks (no guard on B or T)
        return scan_filter(prepare_inputs(args, validate_args))
    y, A, Q, H, R, m0, P0, G, u, mask, D = args
    T = y.shape[-2]
    batch = broadcast_batch([("y", y.shape[:-2]), ("A", A.shape[:-3] if A.dim() > 3 else ())])
    if chunk is None:
        chunk = max(2, SCAN_MAX_ELEMENTS // max(1, batch.numel()))
    if chunk >= T:
        return scan_filter(prepare_inputs(args, validate_args))
    if mask is not None:
        # as check_mask reads it, made (..., T, m) with at least y's dims: every chunk's slice
        # then reads per component (a (..., T', 1) slice with T' = 1, or a (T', m) one with
        # T' = m, would read as per step or be refused as ambiguous)
        read = check_mask(mask, T, y.shape[-1], y.device, y.dim())
        assert read is not None
        mask = pad_dims(read.expand(*read.shape[:-1], y.shape[-1]), y.dim())
    parts: list[FilterResult] = []
    m, P = m0, P0
    for start in range(0, T, chunk):
        stop = min(T, start + chunk)
        sl = lambda x, axis: _time_slice(x, axis, T, start, stop)  # noqa: E731
        piece = FilterInputs(
            y[..., start:stop, :],
            sl(A, -3),
            sl(Q, -3),
            sl(H, -3),
            sl(R, -3),
            m,
            P,
            sl(G, -3),
            sl(u, -2),
            sl(mask, -2),
            sl(D, -3),
        )
        out = scan_filter(prepare_inputs(piece, validate_args))
        parts.append(out)
        m, P = out.mean[..., -1, :], out.cov[..., -1, :, :]
    axes = FilterResult(-2, -3, -2, -3, -2, -3, 0, -1, -3, -3, -2, -2)
    fields = []
    for name, axis in zip(FilterResult._fields, axes):
        if name == "log_likelihood":
            fields.append(sum(getattr(p, name) for p in parts))
        else:
            xs = [getattr(p, name) for p in parts]
            lead = torch.broadcast_shapes(*(x.shape[: x.dim() + axis] for x in xs))
            xs = [x.expand(*lead, *x.shape[x.dim() + axis :]) for x in xs]
            fields.append(torch.cat(xs, dim=axis))
    return FilterResult(*fields)
