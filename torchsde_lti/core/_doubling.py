r"""Scaling and doubling: the default, PSD-preserving discretisation method (private).

Each element picks its own number of halvings ``s ≥ 0`` so that ``‖F‖ h ≤ θ`` for the
sub-step ``h = dt / 2^s``. On the sub-step the Taylor series are summed
(``𝓛(X) = F X + X Fᵀ``)::

    A_h = Σ_k (F h)^k / k!,   Q_h = Σ_k h^{k+1}/(k+1)! 𝓛^k(W),   G_h = Σ_k h^{k+1}/(k+1)! F^k B

and then doubled ``s`` times: ``Q ← A Q Aᵀ + Q``, ``G ← A G + G``, ``A ← A A``. Every
doubling adds positive semi-definite terms, so Q stays PSD, and nothing grows like
``e^{|λ| dt}`` for stable F. The series terms ``F^k``, ``𝓛^k(W)``, ``F^k B`` depend on the
parameters only: when F, L, Qc, B are shared by a batch of dt (the training case), they are
computed once on n×n matrices and all elements are combined by one matrix product.
Nilpotent F (integrator chains) is detected and its terminating series is used at the
full step, with no doubling at all.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch
from torch import Tensor

from torchsde_lti.core._block import block_doubling
from torchsde_lti.core._steps import (
    _doubling_order,
    _doubling_steps,
    _finite_or_max,
    _frobenius_norm,
    _halvings_for,
    _Layout,
    _operator_norm_bound,
    _Permutation,
    _prefix_counts,
    _truncation_order,
    _unsort_batch_first,
    _unsort_batch_last,
    _unsort_from_batch_first,
    _unsort_from_batch_first_last,
)
from torchsde_lti.core.validation import SDEInputs, broadcast_batch, tracing

__all__ = ["doubling"]

# Sub-step bound ‖F‖ h ≤ _THETA. With it, ‖𝓛‖ ≤ 2 ‖F‖ and the truncated Q series has
# relative error below (2θ)^K / (K+1)!, which _series_length makes smaller than eps/8.
_THETA = 1.0


def _series_length(dtype: torch.dtype) -> int:
    """Number of Taylor terms K of the shared path: one past the truncation order for 2θ."""
    return _truncation_order(dtype, 2.0 * _THETA) + 1



def _nilpotency_index(F: Tensor) -> int | None:
    """Smallest k ≤ n with F^k = 0 exactly for every batch element, else None (also None for a
    non-zero trace, even where a power underflows to 0, e.g. F = 1e-200 I)."""
    n = F.shape[-1]
    with torch.no_grad():
        # a nilpotent F has trace 0: one test settles the common case (any stable F) without
        # the matrix powers (a power can underflow to 0 with a non-zero trace, F = 1e-200 I:
        # then either path is exact to rounding)
        if bool(torch.diagonal(F, dim1=-2, dim2=-1).sum(-1).ne(0).any()):
            return None
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


def _taylor_rows(x: Tensor, count: int) -> Tensor:
    """Rows x^k / k! for k < count: (count, N) for x (N,)."""
    rows = [torch.ones_like(x)]
    for k in range(1, count):
        rows.append(rows[-1] * x * (1.0 / k))
    return torch.stack(rows)


def _symmetric_index(n: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """Upper-triangle rows/cols (2, n(n+1)/2) and the (n·n,) map from (i, j) to its entry."""
    iu = torch.triu_indices(n, n, device=device)
    pos = torch.arange(iu.shape[1], device=device)
    idx = torch.empty(n, n, dtype=torch.int64, device=device)
    idx[iu[0], iu[1]] = pos
    idx[iu[1], iu[0]] = pos
    return iu, idx.reshape(-1)


def _series_full_step(
    powers: Tensor,
    lyap: Tensor | None,
    inputs: Tensor | None,
    x: Tensor,
    h: Tensor,
    batch: torch.Size,
    batch_last: bool,
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Full-step series for ONE parameter set (no doubling).

    powers: (K, n, n) F̃^k; lyap: (K, n, n) 𝓛̃^k(W) or None; inputs: (K, n, p) F̃^k B or None;
    x = ν h, h: (N,) with N = prod(batch). With rows r_k = x^k / k! (K, N)::

        A = Σ_k r_k F̃^k,   Q = h Σ_k r_k 𝓛̃^k(W) / (k+1),   G = h Σ_k r_k F̃^k B / (k+1)

    each one GEMM whose output is the contiguous result: (*batch, n, n) batch-first, or
    (n, n, *batch) with ``batch_last``. Q is formed on its n(n+1)/2 distinct entries and
    mirrored (a copy of whole rows in the batch-last layout), so it is exactly symmetric.
    """
    count, n = powers.shape[0], powers.shape[-1]
    rows = _taylor_rows(x, count)  # (K, N)

    def combine(r: Tensor, terms: Tensor, shape: tuple[int, int]) -> Tensor:
        if batch_last:
            return (terms.mT @ r).reshape(*shape, *batch)
        return (r.mT @ terms).reshape(*batch, *shape)

    A = combine(rows, powers.reshape(count, n * n), (n, n))
    Q = G = None
    if lyap is None and inputs is None:
        return A, Q, G
    k1 = torch.arange(1, count + 1, dtype=powers.dtype, device=powers.device)
    rows_h = rows * (h / k1[:, None])  # (K, N): h x^k / (k+1)!
    if lyap is not None:
        iu, idx = _symmetric_index(n, powers.device)
        tri = lyap[:, iu[0], iu[1]]  # (K, n(n+1)/2)
        if batch_last:
            Q = (tri.mT @ rows_h).index_select(0, idx).reshape(n, n, *batch)
        else:
            Q = (rows_h.mT @ tri).index_select(1, idx).reshape(*batch, n, n)
    if inputs is not None:
        p = inputs.shape[-1]
        G = combine(rows_h, inputs.reshape(count, n * p), (n, p))
    return A, Q, G


def _halvings(F: Tensor, dt: Tensor) -> tuple[Tensor, int, Tensor | None]:
    """Scale ν = max(‖F‖₁, ‖F‖∞) (> 0), series length K and halvings s per element.

    s = ceil(log2(ν dt / θ)) (int64, broadcast shape of F's batch and dt), or None for a
    nilpotent F, whose terminating series is exact at the full step (3·index terms also
    make its gradient exact). ν is a constant (no gradient), so ``F / ν`` keeps F's.
    """
    with torch.no_grad():
        nu = _operator_norm_bound(F)
        nu = torch.where(nu > 0, nu, torch.ones_like(nu))
    nil = _nilpotency_index(F)
    if nil is not None:
        return nu, 3 * nil, None
    with torch.no_grad():
        # NaN (only reachable with value checks off) takes no halvings and gives NaN output;
        # ν dt beyond the float range takes the most halvings (non-finite dt: non-finite output)
        halvings = _halvings_for(_finite_or_max(nu * dt), _THETA).to(torch.int64)
    return nu, _series_length(F.dtype), halvings


def _stacked_terms(powers: Tensor, lyap: Tensor | None, inputs: Tensor | None) -> Tensor:
    """One stack (..., K, n² [+ n²] [+ n p]) of series terms whose coefficients are all
    (νh)^k / k!: F̃^k (k ≥ 1) for E = A − I, 𝓛̃^k(W) / (k+1) for Q / h, F̃^k B / (k+1) for G / h."""
    count = powers.shape[-3]
    k1 = torch.arange(1, count + 1, dtype=powers.dtype, device=powers.device)[:, None, None]
    terms = [torch.cat([torch.zeros_like(powers[..., :1, :, :]), powers[..., 1:, :, :]], -3).flatten(-2)]
    if lyap is not None:
        terms.append((lyap / k1).flatten(-2))
    if inputs is not None:
        terms.append((inputs / k1).flatten(-2))
    return torch.cat(terms, -1)



# ----------------------------------------------------------------------------------------
# Per-element parameters: every batch element has its own F (and W, B)
# ----------------------------------------------------------------------------------------

# Sub-step bound of the per-element path (measured: 0.5 beats 1.0, where the longer series
# costs more than the extra doubling it saves).
_THETA_ELEMENT = 0.5
# Layout of the per-element loops: batch-last multiply-adds for n ≤ 4 and more than 256
# elements, batch-first bmm otherwise (measured on CPU, float64, n = 2 … 8).
_BATCH_LAST_MAX_N = 4
_BATCH_LAST_MIN_BATCH = 256
# Per-element parameters and N · max(n, 4) up to this: ``_block.block_doubling`` (a fixed,
# small number of batched ops) beats the per-term Horner below; beyond it flops and the 2n
# blocks' memory count and the Horner on n × n matrices wins. Measured by
# ``python experiments/profile_small_calls.py`` (section 2, CPU, 1 thread): Horner / block
# time 1.1–2.4 (n = 2, N ≤ 1000), 1.2–1.9 (n = 4, N ≤ 1000), 1.1 (n = 8, N = 300–600), and
# 0.64–0.88 at n = 2, N = 2000–3000 and 0.54–1.0 at n = 8, N = 1000 (float64).
_BLOCK_MAX_ROWS = 4096
# One parameter set (not nilpotent) and at most this many elements: the block path beats
# computing all K shared series terms (same script, section 3: N = 1 … 64, block 247–454 vs
# shared 468–604 µs for a Matérn-3/2, 202–512 vs 360–497 µs for a Singer model; the shared
# path wins at N = 256).
_BLOCK_MAX_SHARED = 64


@lru_cache(maxsize=None)
def _element_thresholds(dtype: torch.dtype, theta: float) -> tuple[float, ...]:
    """x_K, K = 0 … K_max − 1: the Horner series of length K (terms 0 … K) is accurate for
    ν h < x_K, i.e. its first omitted term (2x)^{K+1}/(K+2)! < eps/8; K_max covers x ≤ θ."""
    eps = torch.finfo(dtype).eps
    out: list[float] = []
    K = 0
    while True:
        x_K = 0.5 * (eps / 8.0 * math.factorial(K + 2)) ** (1.0 / (K + 1))
        if x_K > theta:
            return tuple(out)
        out.append(x_K)
        K += 1


def _doubling_per_element(x: SDEInputs, batch_last: bool) -> tuple[Tensor, Tensor | None, Tensor | None]:
    r"""Scaling and doubling when every element has its own parameters (or a small batch).

    Per element i: ν_i = ‖F_i‖_F, s_i = ceil(log2(ν_i dt_i / θ)) halvings,
    h_i = dt_i / 2^{s_i}, M_i = F_i h_i and a series length K_i (the full K_max when
    s_i > 0, fewer terms for a small ν_i dt_i). On the sub-step, by Horner's rule on the
    batch-last layout (n, n, N) (one batched product per term over all elements)::

        φ₁(M) = Σ_k M^k/(k+1)!,   E = A − I = M φ₁(M),   G = h φ₁(M) B,
        Q = h Σ_k h^k 𝓛^k(W)/(k+1)!,   𝓛(X) = F X + X Fᵀ,

    then :func:`_doubling_steps`. The elements are sorted by (halvings, terms) (descending),
    so the elements that need term k and doubling j are prefixes and no work is spent on the
    others.
    """
    F, W, B, dt, batch = x
    n = F.shape[-1]
    p = 0 if B is None else B.shape[-1]
    N = batch.numel()
    dtype, device = F.dtype, F.device
    Fb = F.expand(*batch, n, n).reshape(N, n, n)
    dtf = dt.expand(batch).reshape(N)
    thresholds = _element_thresholds(dtype, _THETA_ELEMENT)
    K_max = len(thresholds)
    with torch.no_grad():
        nu = _frobenius_norm(Fb)
        x_full = _finite_or_max(nu * dtf)
        halvings = _halvings_for(x_full, _THETA_ELEMENT).to(torch.int64)
        x_sub = x_full * torch.exp2(-halvings.to(dtype))
        terms = torch.bucketize(x_sub, torch.tensor(thresholds, dtype=dtype, device=device), right=True)
        terms = torch.where(halvings > 0, K_max, terms)
        perm: _Permutation | None = None
        if N > 1:  # descending (halvings, terms): an int key sorts faster than ν dt
            perm = _Permutation(torch.argsort(halvings * (K_max + 1) + terms, descending=True))
            halvings, terms = perm.sort(halvings), perm.sort(terms)
        top_s = int(halvings[0]) if N else 0
        top_k = int(terms[0]) if N else 0
        counts = _prefix_counts(halvings, top_s) if top_s else []
        term_counts = _prefix_counts(terms, top_k) if top_k else []  # [j]: elements with K > j

    # batch-first bmm beats the batch-last multiply-adds for n > 4 or a small batch (measured)
    lo = _Layout(batch_first=n > _BATCH_LAST_MAX_N or N <= _BATCH_LAST_MIN_BATCH)

    def sort(x: Tensor, cols: int) -> Tensor:  # (..., n, c) -> sorted (N, n, c) or (n, c, N)
        x = x.expand(*batch, n, cols).reshape(N, n, cols)
        x = x if perm is None else perm.sort(x)
        return x.contiguous() if lo.batch_first else x.permute(1, 2, 0).contiguous()

    h = (dtf if perm is None else perm.sort(dtf)) * torch.exp2(-halvings.to(dtype))
    hc = lo.col(h)
    M = sort(F, n) * hc
    W_s = None if W is None else sort(W, n)
    W_half = None if W_s is None else 0.5 * W_s  # Z ← W + F Z + Z Fᵀ as T + Tᵀ, T = W/2 + F Z
    eye = lo.eye(n, M)
    Y: Tensor | None = None  # φ₁ Horner state of the first `active` elements
    Z = None  # Q / h Horner state
    active = 0
    for k in range(top_k, 0, -1):  # term k enters: elements with K ≥ k
        c = term_counts[k - 1]
        if c > active:
            grow = lo.expand_eye(eye, c - active)
            Y = grow if Y is None else lo.cat([Y, grow])
            if W_s is not None:
                Z = lo.head(W_s, c) if Z is None else lo.cat([Z, lo.part(W_s, active, c)])
            active = c
        assert Y is not None
        Mc = lo.head(M, c) if c < N else M
        Y = lo.mm(Mc, Y, eye, 1.0 / (k + 1))  # I + M Y / (k+1)
        if Z is not None and W_half is not None:
            T = lo.mm(Mc, Z, lo.head(W_half, c) if c < N else W_half, 1.0 / (k + 1))
            Z = T + lo.t(T)  # W + (M Z + Z Mᵀ) / (k+1)
    if active < N:  # elements with K = 0 (dt = 0 or tiny): φ₁ = I, Q/h = W
        grow = lo.expand_eye(eye, N - active)
        Y = grow if Y is None else lo.cat([Y, grow])
        if W_s is not None:
            Z = W_s if Z is None else lo.cat([Z, lo.part(W_s, active, N)])
    assert Y is not None
    X = lo.mm(M, Y)  # E = A − I
    Q = None if Z is None else Z * hc
    G = None if B is None else lo.mm(Y, sort(B, p)) * hc
    if counts:
        A, Q, G = _doubling_steps(X, Q, G, counts, lo)
    else:
        A = X + eye
    if Q is not None:
        Q = torch.lerp(Q, lo.t(Q), 0.5)  # symmetrise
    if lo.batch_first:
        convert = _unsort_from_batch_first_last if batch_last else _unsort_from_batch_first
    else:
        convert = _unsort_batch_last if batch_last else _unsort_batch_first
    return (
        convert(A, perm, batch),
        None if Q is None else convert(Q, perm, batch),
        None if G is None else convert(G, perm, batch),
    )


# ----------------------------------------------------------------------------------------
# Traced (torch.compile / torch.export): no data-dependent control flow
# ----------------------------------------------------------------------------------------

#: Halvings the traced path can take: covers ν dt ≤ θ · 2^32 (beyond it the result is that
#: of dt = θ 2^32 / ν; far outside any physical model, where A and Q have long converged).
_TRACED_MAX_HALVINGS = 32


#: K_max of the per-element series by dtype, looked up while tracing (dynamo warns about, and
#: traces through, the ``lru_cache`` of :func:`_element_thresholds`).
_TRACED_SERIES_LENGTH = {
    dtype: len(_element_thresholds(dtype, _THETA_ELEMENT))
    for dtype in (torch.float16, torch.bfloat16, torch.float32, torch.float64)
}


def _doubling_traced(x: SDEInputs, batch_last: bool) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """:func:`_doubling_per_element` without value-dependent control flow, for tracing.

    Same sub-step series (all K_max terms) and the same doubling recursion, but the doubling
    steps are masked (``torch.where`` keeps the elements whose own s_i halvings are done) and
    the E → A switch is a mask too: ``max_i s_i`` steps of torch's structured while_loop
    without a gradient (export, inference under torch.compile), :data:`_TRACED_MAX_HALVINGS`
    static steps with one. The values equal the eager path's up to rounding.
    """
    F, W, B, dt, batch = x
    n = F.shape[-1]
    p = 0 if B is None else B.shape[-1]
    N = batch.numel()
    dtype, device = F.dtype, F.device
    lo = _Layout(batch_first=n > _BATCH_LAST_MAX_N or N <= _BATCH_LAST_MIN_BATCH)
    Fb = F.expand(*batch, n, n).reshape(N, n, n)
    dtf = dt.expand(batch).reshape(N)
    theta = _THETA_ELEMENT
    K_max = _TRACED_SERIES_LENGTH[dtype]
    with torch.no_grad():
        x_full = _finite_or_max(_frobenius_norm(Fb) * dtf)
        halvings = _halvings_for(x_full, theta).clamp_max(_TRACED_MAX_HALVINGS)

    def layout(x: Tensor, cols: int) -> Tensor:  # (..., n, c) -> (N, n, c) or (n, c, N)
        x = x.expand(*batch, n, cols).reshape(N, n, cols)
        return x if lo.batch_first else x.permute(1, 2, 0).contiguous()

    h = dtf * torch.exp2(-halvings)
    hc = lo.col(h)
    M = layout(F, n) * hc
    eye = lo.eye(n, M)
    Y = lo.expand_eye(eye, N)
    W_l = None if W is None else layout(W, n)
    W_half = None if W_l is None else 0.5 * W_l
    Z = W_l
    for k in range(K_max, 0, -1):  # the scale as a tensor op: a Python float α would be a
        # guard per term for dynamo (recompiles of ``mm`` under torch.compile with gradients)
        Y = lo.mm(M, Y * (1.0 / (k + 1)), eye)
        if Z is not None and W_half is not None:
            T = lo.mm(M, Z * (1.0 / (k + 1)), W_half)
            Z = T + lo.t(T)
    X = lo.mm(M, Y)  # E = A − I
    Q = None if Z is None else Z * hc
    G = None if B is None else lo.mm(Y, layout(B, p)) * hc
    near = lo.col(torch.ones(N, dtype=torch.bool, device=device))
    A = X + eye

    def double(j: Tensor | int, A: Tensor, X: Tensor, Q: Tensor | None, G: Tensor | None, near: Tensor):
        """Doubling step j (masked to the elements with s_i > j)."""
        active = lo.col(halvings > j)
        switch = near & lo.col(lo.norm_sq(A) < 0.25) & (j > 0 if isinstance(j, int) else (j > 0).reshape(()))
        X = torch.where(switch, A, X)
        near = near & ~switch
        if Q is not None:
            Q = torch.where(active, lo.mm(lo.mm(A, Q), lo.t(A), Q), Q)
        if G is not None:
            G = torch.where(active, lo.mm(A, G, G), G)
        X_new = torch.where(near, lo.mm(X, A, X), lo.mm(A, A))
        X = torch.where(active, X_new, X)
        A = torch.where(near, X + eye, X)
        return A, X, Q, G, near

    needs_grad = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (F, W, B, dt))
    if torch.compiler.is_exporting() or not needs_grad:
        # loop max_i s_i times (torch's structured while_loop), not _TRACED_MAX_HALVINGS
        # times; the static loop below where a gradient is traced (torch.compile of a
        # training step), which while_loop does not differentiate
        from torch._higher_order_ops import while_loop

        has_q, has_g = Q is not None, G is not None
        steps = halvings.max().to(torch.int64).reshape(())

        def cond(j: Tensor, *rest: Tensor) -> Tensor:
            return j < steps

        def body(j: Tensor, A: Tensor, X: Tensor, near: Tensor, *qg: Tensor):
            q = qg[0] if has_q else None
            g = qg[-1] if has_g else None
            A, X, q, g, near = double(j, A, X, q, g, near)
            return (j + 1, A, X, near, *(t for t in (q, g) if t is not None))

        init = (torch.zeros((), dtype=torch.int64, device=device), A, X, near,
                *(t for t in (Q, G) if t is not None))
        out = while_loop(cond, body, init)
        A, X = out[1], out[2]
        Q = out[4] if has_q else None
        G = out[-1] if has_g else None
    else:
        for j in range(_TRACED_MAX_HALVINGS):
            A, X, Q, G, near = double(j, A, X, Q, G, near)
    if Q is not None:
        Q = torch.lerp(Q, lo.t(Q), 0.5)

    def convert(x: Tensor) -> Tensor:
        if not lo.batch_first:
            return x.reshape(*x.shape[:2], *batch) if batch_last else x.permute(2, 0, 1).reshape(*batch, *x.shape[:2])
        x = x.reshape(*batch, *x.shape[1:])
        return x.movedim((-2, -1), (0, 1)) if batch_last else x

    return convert(A), None if Q is None else convert(Q), None if G is None else convert(G)


def _doubling_shared(
    F: Tensor, W: Tensor | None, B: Tensor | None, dt: Tensor, batch: torch.Size, param_batch: torch.Size, batch_last: bool
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Shared (or few) parameter sets: the series terms are computed once per parameter set
    and all elements are combined by one matrix product, then doubled in sorted order."""
    dtype = F.dtype
    n = F.shape[-1]
    p = 0 if B is None else B.shape[-1]
    if param_batch.numel() == 1:
        # One set of parameters (size-1 batch dims, e.g. an LTISDE aligned to a series):
        # drop the dims so the series terms are combined by a single GEMM (K, T) x (K, N)
        # instead of N tiny batched products.
        param_batch = torch.Size()
    F = F.expand(*param_batch, n, n) if param_batch else F.reshape(n, n)
    if W is not None:
        W = W.expand(*param_batch, n, n) if param_batch else W.reshape(n, n)
    if B is not None:
        B = B.expand(*param_batch, n, p) if param_batch else B.reshape(n, p)

    nu, count, halvings = _halvings(F, dt)  # F = ν F̃ with ‖F̃‖ = 1
    powers, lyap, inputs = _series_terms(F / nu[..., None, None], W, B, count)
    h = dt if halvings is None else dt * torch.exp2(-halvings.to(dtype))
    N = batch.numel()
    hf = h.expand(batch).reshape(-1)
    xf = (h * nu).expand(batch).reshape(-1)  # ‖F‖ h ≤ θ
    perm, counts = _doubling_order(halvings, batch)
    if not counts and powers.dim() == 3:  # one parameter set, no doubling (e.g. nilpotent F)
        return _series_full_step(powers, lyap, inputs, xf, hf, batch, batch_last)
    if perm is not None:
        xf, hf = perm.sort(xf), perm.sort(hf)

    # Series on the sub-step, batch-last (T, N). Shared parameters (the training case): one
    # GEMM (T, K) x (K, N) for the whole batch, already in doubling order.
    terms_all = _stacked_terms(powers, lyap, inputs)  # (*param_batch, K, T)
    rows = _taylor_rows(xf, count)  # (K, N)
    if terms_all.dim() == 2:
        out = terms_all.mT @ rows
    else:
        coeff = rows.mT if perm is None else perm.unsort(rows.mT)  # original order
        out = torch.einsum("...k,...kt->...t", coeff.reshape(*batch, count), terms_all).reshape(N, -1)
        out = (out if perm is None else perm.sort(out)).mT
    X = out[: n * n].reshape(n, n, N)
    Q = None if lyap is None else hf * out[n * n : 2 * n * n].reshape(n, n, N)
    G = None if inputs is None else hf * out[out.shape[0] - n * p :].reshape(n, p, N)

    if counts:
        A, Q, G = _doubling_steps(X, Q, G, counts)
    else:
        A = X + torch.eye(n, dtype=dtype, device=F.device)[..., None]
    if Q is not None:
        Q = torch.lerp(Q, Q.transpose(0, 1), 0.5)  # symmetrise
    convert = _unsort_batch_last if batch_last else _unsort_batch_first
    return (
        convert(A, perm, batch),
        None if Q is None else convert(Q, perm, batch),
        None if G is None else convert(G, perm, batch),
    )


def doubling(x: SDEInputs, batch_last: bool = False) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Scaling and doubling: (A, Q, G) of shapes (*batch, n, n), (*batch, n, n), (*batch, n, p)
    (contiguous (n, n, *batch), … with ``batch_last``).

    F: (..., n, n); W = L Qc Lᵀ: (..., n, n) or None; B: (..., n, p) or None; dt: (...).
    Each element takes s = ceil(log2(‖F‖ dt / θ)) halvings (none for nilpotent F), sums the
    Taylor series on h = dt / 2^s and doubles s times. Internally the batch is flattened to
    N = prod(batch), laid out last ("batch-last" (n, n, N): elementwise work on contiguous
    rows of N) and sorted by s, so doubling step j only touches the elements with s > j.

    Paths (same values up to rounding): few elements — per-element parameters with
    N · max(n, 4) ≤ 4096, or one non-nilpotent parameter set with N ≤ 64 — go through Van Loan's block
    (``_block``: a fixed, small number of batched ops); more per-element elements through
    the per-term Horner (``_doubling_per_element``); one shared parameter set through
    ``_doubling_shared`` (series terms once, one GEMM for the whole batch).
    """
    F, W, B, dt, batch = x
    if tracing():
        return _doubling_traced(x, batch_last)
    param_batch = broadcast_batch(
        [("F", F.shape[:-2])]
        + ([("W", W.shape[:-2])] if W is not None else [])
        + ([("B", B.shape[:-2])] if B is not None else [])
    )
    N, n = batch.numel(), F.shape[-1]
    if param_batch.numel() > 1 and 4 * param_batch.numel() >= N:
        # (nearly) every element its own parameters: per-element sub-steps
        if N * max(n, _BATCH_LAST_MAX_N) <= _BLOCK_MAX_ROWS:
            return block_doubling(x, batch_last)
        return _doubling_per_element(x, batch_last)
    if N == 0:  # an empty batch: nothing to compute, shapes only
        return block_doubling(x, batch_last)
    if N <= _BLOCK_MAX_SHARED and _nilpotency_index(F) is None:
        # a few elements (one call, an online step): few batched ops beat the shared terms
        return block_doubling(x, batch_last)
    return _doubling_shared(F, W, B, dt, batch, param_batch, batch_last)
