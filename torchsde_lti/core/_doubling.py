r"""Scaling and doubling: the default, PSD-preserving discretisation method (private).

Few elements, eager: module ``_power_series`` (the same method on a schedule of fewer torch
calls). Element i takes ``s_i = ceil(log2(‖F_i‖ dt_i / θ))`` halvings (none when ``‖F_i‖ dt_i ≤ θ``),
sums Taylor series on the sub-step ``h_i = dt_i / 2^{s_i}`` (``M = F h``, ``𝓛(X) = F X + X Fᵀ``)::

    E_h = A_h − I = M φ₁(M),   φ₁(M) = Σ_k M^k/(k+1)!,   G_h = h φ₁(M) B,   Q_h = h Σ_k h^k 𝓛^k(W)/(k+1)!,

and doubles ``s_i`` times: ``Q ← A Q Aᵀ + Q``, ``G ← A G + G``, ``A ← A A``. Every doubling adds
PSD terms. While A is near the identity the recursion carries ``E = A − I`` (``E ← 2E + E²``,
no slow mode rounded away) and switches to A once ``‖A‖_F < 1/2``.

:func:`per_element_doubling` is the one algorithm (each element its own F, W, B, dt; eager
doubling on the elements sorted by ``s``, masked while torch.compile / torch.export trace);
:func:`shared_doubling` its one specialisation for ONE parameter set (series terms once on
n × n matrices, one product per quantity for the batch; a nilpotent F takes its terminating
series at the full step).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core._power_series import _flat, eye_matrix, few_elements_series, frobenius_norm
from torchsde_lti.core.linalg import bl_matmul, nilpotency_index
from torchsde_lti.core.series import TerminatingSeries, derivative_order, series_matrices, terminating_series
from torchsde_lti.core.thresholds import (
    BATCH_LAST_MAX_DIM,
    BATCH_LAST_MIN_ELEMENTS,
    CHUNK_BYTES,
    CHUNKED_MIN_BYTES,
    FEW_ENTRIES,
    ROWS_BY_PRODUCTS_MIN,
    SHARED_MIN_ELEMENTS,
    THETA_SHARED,
    THETA_SORTED,
    TRACED_MAX_HALVINGS,
)
from torchsde_lti.core.validation import SDEInputs, tracing

__all__ = [
    "SharedSeries",
    "discretization_series",
    "doubling",
    "per_element_doubling",
    "shared_doubling",
    "shared_series",
]

_TERMS: dict[tuple[torch.dtype, float, int, int], int] = {}


def series_terms(dtype: torch.dtype, theta: float, n: int, order: int = 0) -> int:
    """Taylor terms K for a sub-step with ‖F‖ h ≤ θ and n states: the first omitted term of the
    Q series, (2θ)^K / (K+1)!, is below eps/8 of its leading term (‖𝓛‖_F ≤ 2‖F‖_F), and
    K ≥ (order + 2) n − 1: the series of a nilpotent F (index m ≤ n) keeps every term whose
    derivatives of order ≤ ``order`` with respect to F are not zero (E: powers j ≤ K, of which
    (order+1) n − 1 are needed; φ₁ and G: j < K, (order+1) n; Q: 𝓛^k, k < K, (order+2) n − 1,
    module :mod:`~torchsde_lti.core.series`) — with order 0 every entry (an integrator chain's
    q h^{2n−1}/… too) keeps its leading term."""
    key = (dtype, theta, n, order)
    K = _TERMS.get(key)
    if K is None:
        eps = torch.finfo(dtype).eps
        K = max(1, (order + 2) * n - 1)
        while (2.0 * theta) ** K / math.factorial(K + 1) >= eps / 8.0:
            K += 1
        if not tracing():
            _TERMS[key] = K
    return K


def halvings_for(norm: Tensor, dt: Tensor, theta: float) -> Tensor:
    """s = ceil(log2(‖F‖ dt / θ)), at least 0 (float, broadcast shape). ‖F‖ dt beyond the float
    range takes the most halvings (A → 0, Q → P∞ for a stable F); NaN takes none."""
    x = torch.nan_to_num(norm * dt, nan=0.0, posinf=torch.finfo(dt.dtype).max)
    return torch.ceil(torch.log2(x.clamp_min(theta)) - math.log2(theta))


def traced_schedule(
    halvings: Tensor, dt: Tensor, nu: Tensor, theta: float, differentiable: bool
) -> tuple[Tensor, Tensor]:
    """(halvings, sub-step h) of the traced (masked) schedule from ``halvings_for(nu, dt, theta)``:
    every halving for the ``while_loop`` (not ``differentiable``); for the static differentiable
    schedule at most :data:`TRACED_MAX_HALVINGS`, the sub-step capped at θ/ν — beyond
    ‖F‖ dt = θ 2^TRACED_MAX_HALVINGS the result is that of that step (A and Q converged for a
    stable F). halvings, dt, nu: broadcast shapes."""
    if not differentiable:
        return halvings, dt * torch.exp2(-halvings)
    halvings = halvings.clamp_max(TRACED_MAX_HALVINGS)
    return halvings, torch.minimum(dt * torch.exp2(-halvings), theta / nu)


class _Layout:
    """Batch layout of the series and the doubling: batch-last (r, c, N) (fused multiply-adds
    over the contiguous batch) or batch-first (N, r, c) (one ``bmm`` a product)."""

    def __init__(self, batch_first: bool) -> None:
        self.batch_first = batch_first

    def mm(self, a: Tensor, b: Tensor, c: Tensor | None = None, alpha: float = 1.0) -> Tensor:
        """c + α a b."""
        if not self.batch_first:
            return bl_matmul(a, b, c, alpha)
        if c is None:
            return a @ b if alpha == 1.0 else (a @ b) * alpha
        return torch.baddbmm(c.expand(a.shape[0], *c.shape[-2:]), a, b, alpha=alpha)

    def t(self, x: Tensor) -> Tensor:
        return x.mT if self.batch_first else x.transpose(0, 1)

    def col(self, v: Tensor) -> Tensor:
        """A per-element scalar (N,) shaped to broadcast against matrices."""
        return v[:, None, None] if self.batch_first else v

    def split(self, x: Tensor | None, c: int) -> tuple[Any, Any]:
        """The first c elements and the rest."""
        if x is None:
            return None, None
        return (x[:c], x[c:]) if self.batch_first else (x[..., :c], x[..., c:])

    def eye(self, n: int, like: Tensor) -> Tensor:
        e = eye_matrix(n, like)
        return e if self.batch_first else e[..., None]

    def norm(self, A: Tensor) -> Tensor:
        """Frobenius norm per element, shaped as :meth:`col`."""
        if self.batch_first:
            return torch.linalg.vector_norm(A, dim=(-2, -1), keepdim=True)
        return torch.linalg.vector_norm(A, dim=(0, 1))

    def put(self, x: Tensor) -> Tensor:
        """(N, r, c) -> this layout (contiguous)."""
        return x.contiguous() if self.batch_first else x.permute(1, 2, 0).contiguous()

    def take(
        self, parts: list[Tensor | None], order: Tensor | None, batch: torch.Size, batch_last: bool, sym: bool = False
    ) -> Tensor | None:
        """Consecutive groups ``parts`` of elements in sorted ``order`` (or None), in this
        layout -> (*batch, r, c) in the elements' order, or contiguous (r, c, *batch) with
        ``batch_last``; with ``sym`` made exactly symmetric ((X + Xᵀ)/2). ``order``: for
        batch-first output its inverse (``x[inverse]`` restores the elements' order)."""
        present = [t for t in parts if t is not None]
        if not present:
            return None
        x = present[0] if len(present) == 1 else torch.cat(present, 0 if self.batch_first else -1)
        if sym:
            x = 0.5 * (x + self.t(x))  # (x + xᵀ is exactly symmetric; torch.lerp is not)
        if not self.batch_first and batch_last:
            if order is not None:  # out[..., order[i]] = x[..., i]
                x = torch.empty_like(x).index_copy_(-1, order, x)
            return x.reshape(*x.shape[:2], *batch)
        xb = (x if self.batch_first else x.permute(2, 0, 1)).contiguous()
        if order is not None:  # (a gather of contiguous rows: the fastest way back)
            xb = xb.index_select(0, order)
        if xb.shape[:1] != batch:
            xb = xb.reshape(*batch, *xb.shape[1:])
        return xb.movedim((-2, -1), (0, 1)).contiguous() if batch_last else xb


def _double(
    A: Tensor, X: Tensor, Q: Tensor | None, G: Tensor | None, near: Tensor | None, eye: Tensor, lo: _Layout
) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
    """One doubling: Q ← A Q Aᵀ + Q, G ← A G + G and A ← A A, where X holds E = A − I
    (E ← E + A E) for the elements with ``near`` = 1 and A for those with 0 (None: all E).
    Batch-first: one product A [X, Q, G] for the three. Returns (A, X, Q, G)."""
    if lo.batch_first:
        n = X.shape[-1]
        parts = [X, *(t for t in (Q, G) if t is not None)]
        R = torch.bmm(A, torch.cat(parts, -1) if len(parts) > 1 else X)
        Q = None if Q is None else torch.baddbmm(Q, R[..., n : 2 * n], A.mT)
        G = None if G is None else R[..., R.shape[-1] - G.shape[-1] :] + G
        X = R[..., :n] + X if near is None else torch.addcmul(R[..., :n], near, X)
    else:
        Q = None if Q is None else lo.mm(lo.mm(A, Q), lo.t(A), Q)
        G = None if G is None else lo.mm(A, G, G)
        X = lo.mm(X, A, X if near is None else X * near)
    return (X + eye if near is None else torch.addcmul(X, near, eye)), X, Q, G


def _decayed(A: Tensor, lo: _Layout) -> Tensor:
    """Per element (bool, shaped as :meth:`_Layout.col`): ‖A‖_F < 1/2 — A has decayed and
    E = A − I no longer resolves it."""
    with torch.no_grad():
        return lo.norm(A) < 0.5


def _double_sorted(
    A: Tensor, X: Tensor, Q: Tensor | None, G: Tensor | None, counts: list[int], lo: _Layout
) -> list[tuple[Tensor, Tensor | None, Tensor | None]]:
    """Doubling of elements sorted by halvings (descending): step j doubles the first counts[j]
    (those with more than j halvings) and leaves the others final. Returns the (A, Q, G) of
    consecutive groups of the sorted elements (assembled by :func:`_finish`)."""
    eye = lo.eye(X.shape[1], X)
    near: Tensor | None = None  # None: every element holds E; else a per-element 1/0 mask
    size = A.shape[0] if lo.batch_first else A.shape[-1]
    done: list[tuple[Tensor, Tensor | None, Tensor | None]] = []
    for j, c in enumerate(counts):
        if c < size:
            (A, a), (Q, q), (G, g), (X, _), (near, _) = (lo.split(t, c) for t in (A, Q, G, X, near))
            done.append((a, q, g))
            size = c
        if j:  # after a doubling: elements whose A has decayed carry A from now on
            switch = _decayed(A, lo)
            if near is not None:
                switch = switch & (near > 0)
            if bool(switch.any()):
                sw = switch.to(X.dtype)
                X = torch.addcmul(X, sw, eye)  # A where switched
                near = 1.0 - sw if near is None else near * (1.0 - sw)
        A, X, Q, G = _double(A, X, Q, G, near, eye, lo)
    return [(A, Q, G), *done[::-1]]


def _double_masked(
    A: Tensor, X: Tensor, Q: Tensor | None, G: Tensor | None, halvings: Tensor, lo: _Layout, differentiable: bool
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Doubling of unsorted elements without data-dependent control flow (tracing): every step
    runs on all elements and keeps the result of those with more halvings than the step
    (``torch.where``). ``max s`` steps of torch's structured while_loop, or with
    ``differentiable`` (which while_loop is not) :data:`TRACED_MAX_HALVINGS` static steps."""
    eye = lo.eye(X.shape[1], X)
    keep = lambda mask, new, old: None if old is None else torch.where(mask, new, old)

    def step(j: Tensor | int, A: Tensor, X: Tensor, near: Tensor, Q: Tensor | None, G: Tensor | None):
        active = lo.col(halvings > j)
        first = j == 0 if isinstance(j, int) else (j == 0).reshape(())
        switch = near & _decayed(A, lo) & ~torch.as_tensor(first)
        X = torch.where(switch, A, X)
        near = near & ~switch
        A2, X2, Q2, G2 = _double(A, X, Q, G, near.to(X.dtype), eye, lo)
        return keep(active, A2, A), keep(active, X2, X), near, keep(active, Q2, Q), keep(active, G2, G)

    near = lo.col(torch.ones(halvings.shape, dtype=torch.bool, device=halvings.device))
    if differentiable:
        for j in range(TRACED_MAX_HALVINGS):
            A, X, near, Q, G = step(j, A, X, near, Q, G)
        return A, Q, G
    from torch._higher_order_ops import while_loop

    has_q, has_g = Q is not None, G is not None
    # at least one iteration (one with no element active changes nothing): an AOTInductor
    # package returned wrong values after a while_loop of no iteration (torch 2.13)
    # (a zero-size call, which a traced program may get: the max of one more 0, not of none)
    steps = torch.cat([halvings.reshape(-1), halvings.new_zeros(1)]).max().clamp_min(1).to(torch.int64)

    def body(j: Tensor, A: Tensor, X: Tensor, near: Tensor, *qg: Tensor):
        A, X, near, q, g = step(j, A, X, near, qg[0] if has_q else None, qg[-1] if has_g else None)
        return (j + 1, A, X, near, *(t for t in (q, g) if t is not None))

    init = (
        torch.zeros((), dtype=torch.int64, device=halvings.device),
        A,
        X,
        near,
        *(t for t in (Q, G) if t is not None),
    )
    out = while_loop(lambda j, *rest: j < steps, body, init)
    return out[1], (out[4] if has_q else None), (out[-1] if has_g else None)


def per_element_doubling(
    x: SDEInputs, batch_last: bool = False, masked: bool | None = None
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """(A, Q, G) when every element has its own F, W, B and dt (the general algorithm).

    F: (..., n, n); W: (..., n, n) or None; B: (..., n, p) or None; dt: (...), broadcast to
    ``x.batch``. Returns (*batch, n, n), (*batch, n, n) or None, (*batch, n, p) or None
    (with ``batch_last`` contiguous (n, n, *batch), …). ``masked``: the schedule without
    data-dependent control flow (default: while torch.compile / torch.export trace). Eager
    calls of at most :data:`FEW_ENTRIES` entries N n² take
    :func:`~torchsde_lti.core._power_series.few_elements_series` (fewest torch calls); eager
    calls of many elements run chunk by chunk (:func:`chunk_elements`).
    """
    F, W, B, dt, batch = x.F, x.W, x.B, x.dt, x.batch
    assert dt is not None
    n, N = F.shape[-1], math.prod(batch)  # (a symbolic size while tracing: no guard on it)
    p = 0 if B is None else B.shape[-1]
    traced = tracing() if masked is None else masked
    if not traced and N * n * n <= FEW_ENTRIES:  # one number of halvings s for all, no sort
        E, Q, G, s = few_elements_series(x)
        lo = _Layout(batch_first=True)
        return _finish(_double_sorted(E + lo.eye(n, E), E, Q, G, [N] * s, lo), lo, None, batch, batch_last)
    Fb, Wb, Bb = _flat(F, batch, n), _flat(W, batch, n), _flat(B, batch, p)
    assert Fb is not None
    dtf = dt.expand(batch).reshape(N)
    if not traced and (chunk := chunk_elements(N, n, p, Fb)) < N:  # (traced: no guard on the symbolic N)
        cut = lambda t, i: None if t is None else t[i : i + chunk]  # noqa: E731
        parts = [
            _per_element_flat(Fb[i : i + chunk], cut(Wb, i), cut(Bb, i), dtf[i : i + chunk], False, batch_last)
            for i in range(0, N, chunk)
        ]
        return joined(parts, batch, batch_last)
    return _per_element_flat(Fb, Wb, Bb, dtf, traced, batch_last, batch)


def _per_element_flat(
    Fb: Tensor,
    Wb: Tensor | None,
    Bb: Tensor | None,
    dtf: Tensor,
    traced: bool,
    batch_last: bool,
    batch: torch.Size | None = None,
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """:func:`per_element_doubling` of N flat elements: Fb (N, n, n), Wb (N, n, n) or None,
    Bb (N, n, p) or None, dtf (N,) -> (*batch, n, n), … (``batch`` of N elements; default
    (N,)), with ``batch_last`` contiguous (n, n, *batch), …."""
    n, N = Fb.shape[-1], Fb.shape[0]
    batch = torch.Size([N]) if batch is None else batch
    with torch.no_grad():
        nu = frobenius_norm(Fb)
        halvings = halvings_for(nu, dtf, THETA_SORTED)
    order: Tensor | None = None
    counts: list[int] = []
    grad_order = derivative_order(Fb)
    K = series_terms(Fb.dtype, THETA_SORTED, n, grad_order)
    differentiable = traced and torch.is_grad_enabled() and not torch.compiler.is_exporting()
    differentiable = differentiable and any(t is not None and t.requires_grad for t in (Fb, Wb, Bb, dtf))
    if traced:
        halvings, h = traced_schedule(halvings, dtf, nu, THETA_SORTED, differentiable)
    elif N:
        with torch.no_grad():  # one synchronisation: the most halvings and the largest ‖F‖ dt
            top_f, x_max = torch.stack([halvings.max(), (nu * dtf).max()]).tolist()
            if not top_f:  # no element halves: the series for the largest ‖F‖ dt (a power of 2) suffices
                K = series_terms(Fb.dtype, 2.0 ** math.ceil(math.log2(x_max)) if x_max > 0 else 0.0, n, grad_order)
            order, counts = _schedule(halvings.to(torch.int64), int(top_f))
    if order is not None:
        Fb, dtf, halvings = Fb[order], dtf[order], halvings[order]
        Wb, Bb = (None if t is None else t[order] for t in (Wb, Bb))

    lo = _Layout(batch_first=n > BATCH_LAST_MAX_DIM or tracing() or N <= BATCH_LAST_MIN_ELEMENTS)
    hc = lo.col(h if traced else dtf * torch.exp2(-halvings))
    M = lo.put(Fb) * hc
    eye = lo.eye(n, M)
    Y = eye.expand_as(M)  # φ₁(M) by Horner: Y ← I + M Y / (k+1)
    Z = None if Wb is None else lo.put(Wb)  # Q/h by Horner: Z ← W + (M Z + Z Mᵀ)/(k+1) = T + Tᵀ
    W_half = None if Z is None else 0.5 * Z  # with T = W/2 + M Z/(k+1)
    for k in range(K - 1, 0, -1):
        Y = lo.mm(M, Y, eye, 1.0 / (k + 1))
        if Z is not None and W_half is not None:
            T = lo.mm(M, Z, W_half, 1.0 / (k + 1))
            Z = T + lo.t(T)
    X = lo.mm(M, Y)  # E = A − I
    Q = None if Z is None else Z * hc
    G = None if Bb is None else lo.mm(Y, lo.put(Bb)) * hc
    if traced:
        parts = [_double_masked(X + eye, X, Q, G, halvings, lo, differentiable)]
    else:
        parts = _double_sorted(X + eye, X, Q, G, counts, lo)
    return _finish(parts, lo, order, batch, batch_last)


def _schedule(steps: Tensor, top: int) -> tuple[Tensor | None, list[int]]:
    """The order that sorts the elements by halvings ``steps`` (N,) (descending; None for
    fewer than two elements or no halving) and ``counts[j]``: how many have more than j, j < top."""
    if not top:
        return None, []
    order = None
    if steps.numel() > 1:  # (a stable sort of small integer keys: torch's fastest)
        order = torch.argsort((top - steps).to(torch.uint8 if top < 256 else torch.int32), stable=True)
    tally = torch.bincount(steps, minlength=top + 1)
    return order, (steps.numel() - torch.cumsum(tally, 0))[:top].tolist()


def _finish(
    parts: list[tuple[Tensor, Tensor | None, Tensor | None]],
    lo: _Layout,
    order: Tensor | None,
    batch: torch.Size,
    batch_last: bool,
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """(A, Q, G) from the groups ``parts`` of the sorted elements: in the elements' order and
    the output layout (one copy that concatenates, one gather), Q made exactly symmetric."""
    if order is not None and (lo.batch_first or not batch_last):
        inverse = torch.empty_like(order)
        inverse[order] = torch.arange(order.numel(), device=order.device)
        order = inverse
    A, Q, G = (lo.take([p[i] for p in parts], order, batch, batch_last, sym=i == 1) for i in range(3))
    assert A is not None
    return A, Q, G


def chunk_elements(N: int, n: int, p: int, like: Tensor) -> int:
    """Elements per chunk of an eager call of N elements on ``like``'s dtype and device: all N
    off the CPU (no page faults behind a caching allocator; a chunk costs synchronisations) or
    while their (n, max(n, p)) matrices take at most :data:`CHUNKED_MIN_BYTES`, else
    :data:`CHUNK_BYTES` of them."""
    size = n * max(n, p) * like.element_size()
    if like.device.type != "cpu" or N * size <= CHUNKED_MIN_BYTES:
        return N
    return max(1, CHUNK_BYTES // size)


def joined(
    parts: list[tuple[Tensor, Tensor | None, Tensor | None]], batch: torch.Size, batch_last: bool
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """(A, Q, G) of consecutive chunks of flat elements, each (C, r, c) (with ``batch_last``
    (r, c, C)), joined into (*batch, r, c) (with ``batch_last`` contiguous (r, c, *batch))."""
    out: list[Tensor | None] = []
    for group in zip(*parts):
        if group[0] is None:
            out.append(None)
            continue
        x = torch.cat(group, -1 if batch_last else 0) if len(group) > 1 else group[0]
        out.append(x.reshape(*x.shape[:2], *batch) if batch_last else x.reshape(*batch, *x.shape[1:]))
    A, Q, G = out
    assert A is not None
    return A, Q, G


class SharedSeries(NamedTuple):
    r"""The dt-independent part of :func:`shared_doubling` for ONE parameter set that is not
    nilpotent: with F = ν F̃, the series terms as the coefficients of the rows ``r_k = (ν h)^k / k!``
    of a sub-step h (``E_h = Σ_k r_k F̃^k``, ``Q_h / h = Σ_k r_k 𝓛̃^k(W) / (k+1)``,
    ``G_h / h = Σ_k r_k F̃^k B / (k+1)``, k < K). Formed once (:func:`shared_series`); a call
    over dt (...) costs the halvings, the rows, one product for the batch and the doubling, so
    a module may keep it per parameter version (a live tracker's online step).

    coeff: (K, E) with the E entries [E's n² | Q's n² | G's n p] (absent blocks left out);
    nu: () the scale ν (a tensor: also while traced); inv_k: (K − 1,) 1/k, k = 1 … K − 1.
    """

    coeff: Tensor
    nu: Tensor
    inv_k: Tensor
    has_q: bool
    n: int
    p: int

    def __call__(self, dt: Tensor, batch_last: bool = False) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """(A, Q, G) over dt (...): (..., n, n), (..., n, n) or None, (..., n, p) or None (with
        ``batch_last`` contiguous (n, n, ...), …). Eager: each element its own halvings, the
        doubling on the elements sorted by them (a call of at most :data:`FEW_ENTRIES` entries
        N n²: every element the most halvings, read on the host, no sort); traced
        (torch.compile / torch.export): the masked doubling (every element every step, a
        ``while_loop`` over the most halvings), no data-dependent control flow. Eager calls of
        many elements run chunk by chunk (:func:`chunk_elements`)."""
        batch, n, p, dtype = dt.shape, self.n, self.p, self.coeff.dtype
        N = math.prod(batch)  # (a symbolic size while tracing: no guard on it)
        dtf = dt.reshape(N).to(dtype)
        traced = tracing()
        if not traced and (chunk := chunk_elements(N, n, p, dtf)) < N:  # (traced: no guard on the symbolic N)
            return joined([self(d, batch_last) for d in dtf.split(chunk)], batch, batch_last)
        order: Tensor | None = None
        counts: list[int] = []
        if traced:
            differentiable = torch.is_grad_enabled() and (dt.requires_grad or self.coeff.requires_grad)
            differentiable = differentiable and not torch.compiler.is_exporting()
            with torch.no_grad():
                steps = halvings_for(self.nu, dtf, THETA_SHARED)
            steps, h = traced_schedule(steps, dtf, self.nu, THETA_SHARED, differentiable)
        elif N * n * n <= FEW_ENTRIES:  # few elements: one number of halvings for all
            with torch.no_grad():  # (a NaN step takes no halving, as in halvings_for)
                top = float(torch.nan_to_num(self.nu * dtf, nan=0.0).max()) if N else 0.0
            s = _host_halvings(top, THETA_SHARED, dtype)
            counts = [N] * s
            h = dtf * 2.0**-s if s else dtf
        else:
            with torch.no_grad():
                steps = halvings_for(self.nu, dtf, THETA_SHARED)
                order, counts = _schedule(steps.to(torch.int64), int(steps.max()) if N else 0)
            h = dtf
            if counts:
                h = dtf * torch.exp2(-steps)
                h = h if order is None else h[order]
        rows = _rows(self.nu * h, self.inv_k, traced)  # (K, N)
        sizes = [n * n, *([n * n] if self.has_q else []), *([n * p] if p else [])]
        # one product for the batch; batch-last eagerly, batch-first while traced (as the
        # per-element schedule: AOTInductor's while_loop gave wrong results for batch-last
        # carries of one or two elements)
        lo = _Layout(batch_first=traced)
        if traced:
            parts = iter((rows.mT @ self.coeff).split(sizes, -1))
            hb = h[:, None, None]
            X = next(parts).reshape(N, n, n).contiguous()  # (a loop carry: strides must match)
            Q = next(parts).reshape(N, n, n) * hb if self.has_q else None
            G = next(parts).reshape(N, n, p) * hb if p else None
        else:
            parts = iter((self.coeff.mT @ rows).split(sizes))
            X = next(parts).reshape(n, n, N)
            Q = next(parts).reshape(n, n, N) * h if self.has_q else None
            G = next(parts).reshape(n, p, N) * h if p else None
        A = X + lo.eye(n, X)
        if traced:
            return _finish([_double_masked(A, X, Q, G, steps, lo, differentiable)], lo, None, batch, batch_last)
        return _finish(_double_sorted(A, X, Q, G, counts, lo), lo, order, batch, batch_last)


def _rows(x: Tensor, inv_k: Tensor, traced: bool) -> Tensor:
    """``r_k = x^k / k!``, k < K = len(inv_k) + 1: (K, N) from x (N,). Traced or fewer than
    :data:`ROWS_BY_PRODUCTS_MIN` elements: one cumulative product; else one product a row (on
    the CPU torch's cumulative product over the leading dimension slows down sharply with N)."""
    if traced or x.shape[0] < ROWS_BY_PRODUCTS_MIN:
        return torch.cat([torch.ones_like(x)[None], torch.cumprod(x * inv_k[:, None], 0)])
    rows = [torch.ones_like(x)]
    for c in inv_k.tolist():
        rows.append(torch.mul(rows[-1], x).mul_(c))
    return torch.stack(rows)


def _host_halvings(x: float, theta: float, dtype: torch.dtype) -> int:
    """:func:`halvings_for` of one Python float ‖F‖ dt: ceil(log2(x / θ)), at least 0; beyond the
    float range of ``dtype`` that of its largest number (A → 0, Q → P∞ for a stable F)."""
    if not x > theta:  # (NaN too)
        return 0
    x = min(x, torch.finfo(dtype).max)
    return max(0, math.ceil(math.log2(x) - math.log2(theta)))


def shared_series(F: Tensor, W: Tensor | None, B: Tensor | None) -> SharedSeries:
    """:class:`SharedSeries` of F (n, n), W = L Qc Lᵀ (n, n) or None, B (n, p) or None
    (ν = max(‖F‖₁, ‖F‖∞), which bounds ‖F‖ and ‖𝓛‖/2 in the induced 1-norm)."""
    n, p, dtype = F.shape[-1], 0 if B is None else B.shape[-1], F.dtype
    with torch.no_grad():
        absF = F.abs()
        nu = torch.maximum(absF.sum(-2).amax(-1), absF.sum(-1).amax(-1))
        nu = torch.where(nu > 0, nu, torch.ones_like(nu))
    K = series_terms(dtype, THETA_SHARED, n, derivative_order(F))
    Ft = F / nu
    k1 = torch.arange(1, K + 1, dtype=dtype, device=F.device)[:, None, None]
    eye = torch.eye(n, dtype=dtype, device=F.device)
    stacks = [  # (K, n, c) terms whose coefficients are r_k (Q and G: times h)
        torch.cat([torch.zeros_like(eye)[None], series_matrices(Ft, eye, K)[1:]]),
        None if W is None else series_matrices(Ft, W, K, lyapunov=True) / k1,
        None if B is None else series_matrices(Ft, B, K) / k1,
    ]
    coeff = torch.cat([t.reshape(K, -1) for t in stacks if t is not None], -1)
    inv_k = torch.arange(1, K, dtype=dtype, device=F.device).reciprocal()
    return SharedSeries(coeff, nu, inv_k, W is not None, n, p)


def discretization_series(
    F: Tensor, W: Tensor | None, B: Tensor | None, index: int | None = None, read_values: bool = True
) -> TerminatingSeries | SharedSeries:
    """The dt-independent part of the doubling discretisation of ONE parameter set, to form
    once and call on many steps: ``series(dt)`` -> (A, Q, G) over dt (...) (with
    ``batch_last=True`` contiguous (n, n, ...), …), the values of
    :func:`~torchsde_lti.core.discretize`'s default method to rounding. Arguments are taken as
    checked (no validation).

    F: (n, n); W = L Qc Lᵀ: (n, n) or None; B: (n, p) or None. A nilpotent F (F^index = 0)
    gives its :class:`~torchsde_lti.core.series.TerminatingSeries` (exact polynomial in dt; when
    F records a graph, with the terms whose value is zero but whose first or second derivative
    with respect to F is not), any
    other F a :class:`SharedSeries` (series terms of a sub-step, then the doubling).
    ``index``: F's nilpotency index when the model's structure fixes it; with ``read_values``
    and ``index`` None it is found from F's values (one synchronisation), without
    ``read_values`` None means not nilpotent (no value read: traceable).
    """
    if index is None and read_values:
        index = nilpotency_index(F)
    if index is None:
        return shared_series(F, W, B)
    return terminating_series(F, W, B, index, derivative_order(F))


def shared_doubling(
    F: Tensor, W: Tensor | None, B: Tensor | None, dt: Tensor, batch_last: bool = False
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    r"""(A, Q, G) for ONE parameter set, F (n, n), W (n, n) or None, B (n, p) or None, over
    dt (*batch); shapes as :func:`per_element_doubling`: :func:`discretization_series` called
    on dt (the series terms F̃^k, 𝓛̃^k(W), F̃^k B computed once, every element combining them
    with its rows ``r_k = (ν h)^k / k!`` in one matrix product for the whole batch, then the
    doubling; a nilpotent F's terminating series at the full step).
    """
    return discretization_series(F, W, B)(dt, batch_last)


def doubling(x: SDEInputs, batch_last: bool = False) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Scaling and doubling: (A, Q, G) of shapes (*batch, n, n), (*batch, n, n) or None,
    (*batch, n, p) or None (with ``batch_last`` contiguous (n, n, *batch), …).

    F: (..., n, n); W = L Qc Lᵀ: (..., n, n) or None; B: (..., n, p) or None; dt: (...).
    ONE parameter set for at least :data:`SHARED_MIN_ELEMENTS` elements takes
    :func:`shared_doubling` (not while tracing); everything else :func:`per_element_doubling`.
    """
    F, W, B, dt, batch = x.F, x.W, x.B, x.dt, x.batch
    assert dt is not None
    if tracing():  # (no guard on a symbolic batch size: a dynamic per-element batch exports)
        return per_element_doubling(x, batch_last)
    one_set = all(t is None or t.shape[:-2].numel() == 1 for t in (F, W, B))
    if one_set and batch.numel() >= SHARED_MIN_ELEMENTS:
        F1, W1, B1 = (None if t is None else t.reshape(t.shape[-2:]) for t in (F, W, B))
        return shared_doubling(F1, W1, B1, dt.expand(batch), batch_last)  # type: ignore[arg-type]
    return per_element_doubling(x, batch_last)
