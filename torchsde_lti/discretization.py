r"""Exact discretisation of LTI SDEs ``dx = F x dt + B u dt + L dβ`` (spectral density Qc).

Over a step dt with u held constant (zero-order hold)::

    x_{k+1} = A x_k + G u_k + q_k,        q_k ~ N(0, Q)
    A = expm(F dt),   G = ∫_0^dt expm(F s) ds B,   Q = ∫_0^dt expm(F s) W expm(F s)ᵀ ds,
    W = L Qc Lᵀ.

Two methods are offered.

``"doubling"`` (default): scaling and doubling. Each element picks its own number of
halvings ``s ≥ 0`` so that ``‖F‖ h ≤ 1`` for the sub-step ``h = dt / 2^s``. On the sub-step
the Taylor series are summed (``𝓛(X) = F X + X Fᵀ``)::

    A_h = Σ_k (F h)^k / k!,   Q_h = Σ_k h^{k+1}/(k+1)! 𝓛^k(W),   G_h = Σ_k h^{k+1}/(k+1)! F^k B

and then doubled ``s`` times: ``Q ← A Q Aᵀ + Q``, ``G ← A G + G``, ``A ← A A``. Every
doubling adds positive semi-definite terms, so Q stays PSD, and nothing grows like
``e^{|λ| dt}`` for stable F. The series terms ``F^k``, ``𝓛^k(W)``, ``F^k B`` depend on the
parameters only: when F, L, Qc, B are shared by a batch of dt (the training case), they are
computed once on n×n matrices and all elements are combined by one matrix product.
Nilpotent F (integrator chains) is detected and its terminating series is used at the
full step, with no doubling at all.

``"van_loan"``: Van Loan's block exponential via :func:`torch.matrix_exp` of
``[[F, W, B], [0, -Fᵀ, 0], [0, 0, 0]] dt`` (blocks ``[[A, X, G], [0, A^{-T}, 0], [0, 0, I]]``,
``Q = X Aᵀ``). Exact in exact arithmetic; in floating point the ``-Fᵀ`` block holds
``e^{|λ| dt}`` and Q is recovered by cancellation, so it fails for stiff F or large dt.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti._validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_matrix,
    check_nonnegative,
    check_symmetric_psd,
    check_vector,
    common_float_dtype,
    shape_str,
)

METHODS = ("doubling", "van_loan")

# Sub-step bound ‖F‖ h ≤ _THETA. With it, ‖𝓛‖ ≤ 2 ‖F‖ and the truncated Q series has
# relative error below (2θ)^K / (K+1)!, which _series_length makes smaller than eps/8.
_THETA = 1.0


class Discrete(NamedTuple):
    """Exact discrete-time model over a step: ``x' = A x + G u + q``, ``q ~ N(0, Q)``.

    A: (..., n, n) transition matrix expm(F dt).
    Q: (..., n, n) process-noise covariance (symmetric PSD).
    G: (..., n, p) zero-order-hold input matrix, or None when the SDE has no input.
    """

    A: Tensor
    Q: Tensor
    G: Tensor | None


@lru_cache(maxsize=None)
def _series_length(dtype: torch.dtype) -> int:
    """Number of Taylor terms K with (2θ)^K / (K+1)! < eps / 8."""
    eps = torch.finfo(dtype).eps
    k = 1
    while (2.0 * _THETA) ** k / math.factorial(k + 1) > eps / 8.0:
        k += 1
    return k + 1


class _Inputs(NamedTuple):
    F: Tensor
    W: Tensor | None
    B: Tensor | None
    dt: Tensor
    batch: torch.Size


def _prepare(
    F: Tensor, L: Tensor | None, Qc: Tensor | None, dt: Tensor | float, B: Tensor | None
) -> _Inputs:
    """Validate and convert arguments; return W = L Qc Lᵀ and the broadcast batch shape."""
    F = as_float_tensor(F, "F")
    dtype = common_float_dtype(
        F,
        L if isinstance(L, Tensor) else None,
        Qc if isinstance(Qc, Tensor) else None,
        B if isinstance(B, Tensor) else None,
    )
    device = F.device
    F = as_float_tensor(F, "F", dtype, device)
    check_matrix(F, "F", square=True)
    n = F.shape[-1]
    check_finite(F, "F")
    named: list[tuple[str, torch.Size]] = [("F", F.shape[:-2])]
    W = None
    if L is not None or Qc is not None:
        if L is None or Qc is None:
            raise ValueError("L and Qc must be given together")
        L = as_float_tensor(L, "L", dtype, device)
        Qc = as_float_tensor(Qc, "Qc", dtype, device)
        check_matrix(L, "L", rows=n)
        s = L.shape[-1]
        if Qc.dim() < 2 or Qc.shape[-2:] != (s, s):
            raise ValueError(
                f"Qc must have shape (..., {s}, {s}) to match L {shape_str(L)}, got shape {shape_str(Qc)}"
            )
        check_finite(L, "L")
        check_symmetric_psd(Qc, "Qc")
        named += [("L", L.shape[:-2]), ("Qc", Qc.shape[:-2])]
        W = L @ Qc @ L.mT
        W = 0.5 * (W + W.mT)
    if B is not None:
        B = as_float_tensor(B, "B", dtype, device)
        check_matrix(B, "B", rows=n)
        check_finite(B, "B")
        named.append(("B", B.shape[:-2]))
    dt = as_float_tensor(dt, "dt", dtype, device)
    check_nonnegative(dt, "dt")
    named.append(("dt", dt.shape))
    batch = broadcast_batch(named)
    return _Inputs(F, W, B, dt, batch)


def discretize(
    F: Tensor,
    L: Tensor,
    Qc: Tensor,
    dt: Tensor | float,
    B: Tensor | None = None,
    method: str = "doubling",
) -> Discrete:
    r"""Exact discretisation (A, Q, G) of ``dx = F x dt + B u dt + L dβ`` over steps dt.

    Args:
        F: (..., n, n) drift matrix.
        L: (..., n, s) noise-input matrix.
        Qc: (..., s, s) spectral density of β (symmetric PSD).
        dt: (...) non-negative step lengths; a Python float is a scalar.
        B: optional (..., n, p) input matrix; u is held constant over each step.
        method: ``"doubling"`` (default; accurate and PSD for stiff F and large dt) or
            ``"van_loan"`` (the plain block exponential).

    All leading dimensions broadcast (numpy rules, right-aligned): F (n, n) with dt (B, T)
    gives (B, T, n, n); F (B, 1, n, n) with dt (B, T) gives (B, T, n, n).

    Returns:
        :class:`Discrete` with A (..., n, n), Q (..., n, n) symmetric PSD and
        G (..., n, p) or None. Differentiable with respect to F, L, Qc, B and dt.
    """
    inputs = _prepare(F, L, Qc, dt, B)
    if method == "doubling":
        A, Q, G = _doubling(inputs.F, inputs.W, inputs.B, inputs.dt, inputs.batch)
    elif method == "van_loan":
        A, Q, G = _van_loan(inputs.F, inputs.W, inputs.B, inputs.dt, inputs.batch)
    else:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    assert Q is not None
    return Discrete(A, Q, G)


def _discretize_series(
    F: Tensor, L: Tensor, Qc: Tensor, dt: Tensor, B: Tensor | None = None
) -> Discrete:
    """:func:`discretize` (doubling) of a time series dt (..., T), laid out for a filter loop.

    Same values as ``discretize(F, L, Qc, dt, B)``, but when F, L, Qc, B are one parameter
    set (all batch dims of size 1) the results are batch-first VIEWS (..., T, n, n) of
    batch-last storage (n, n, T, ...): step k's matrices ``A[..., k, :, :]`` permuted to
    (n, n, ...) are rows of contiguous batch, the layout of the filter's loop.
    Otherwise the plain batch-first result is returned.
    """
    inputs = _prepare(F, L, Qc, dt, B)
    params = [inputs.F.shape[:-2]] + [x.shape[:-2] for x in (inputs.W, inputs.B) if x is not None]
    batch, dt_t = inputs.batch, inputs.dt
    if len(batch) == 0 or any(torch.Size(s).numel() != 1 for s in params):
        A, Q, G = _doubling(inputs.F, inputs.W, inputs.B, dt_t, batch)
        assert Q is not None
        return Discrete(A, Q, G)
    lead = batch[:-1]
    dt_tm = dt_t.expand(batch).movedim(-1, 0)  # (T, *lead)
    A, Q, G = _doubling(inputs.F, inputs.W, inputs.B, dt_tm, dt_tm.shape, batch_last=True)
    assert Q is not None
    perm = [*range(3, 3 + len(lead)), 2, 0, 1]  # (r, c, T, *lead) -> (*lead, T, r, c)
    return Discrete(A.permute(perm), Q.permute(perm), None if G is None else G.permute(perm))


def transition_matrix(F: Tensor, dt: Tensor | float) -> Tensor:
    """A = expm(F dt).

    Args:
        F: (..., n, n) drift matrix.
        dt: (...) non-negative step lengths.

    Returns:
        (..., n, n), batch broadcast from F and dt.
    """
    inputs = _prepare(F, None, None, dt, None)
    A, _, _ = _doubling(inputs.F, None, None, inputs.dt, inputs.batch)
    return A


def zero_order_hold(F: Tensor, B: Tensor, dt: Tensor | float) -> tuple[Tensor, Tensor]:
    """(A, G) with A = expm(F dt) and G = ∫_0^dt expm(F s) ds B.

    Equivalent to the blocks of expm([[F, B], [0, 0]] dt) = [[A, G], [0, I]].

    Args:
        F: (..., n, n); B: (..., n, p); dt: (...).

    Returns:
        A (..., n, n), G (..., n, p).
    """
    inputs = _prepare(F, None, None, dt, B)
    A, _, G = _doubling(inputs.F, None, inputs.B, inputs.dt, inputs.batch)
    assert G is not None
    return A, G


def process_noise(
    F: Tensor, L: Tensor, Qc: Tensor, dt: Tensor | float, method: str = "doubling"
) -> Tensor:
    """Q = ∫_0^dt expm(F s) L Qc Lᵀ expm(F s)ᵀ ds, the discrete process-noise covariance.

    Args:
        F: (..., n, n); L: (..., n, s); Qc: (..., s, s) symmetric PSD; dt: (...).
        method: as in :func:`discretize`.

    Returns:
        (..., n, n) symmetric PSD.
    """
    return discretize(F, L, Qc, dt, method=method).Q


def propagate(
    m0: Tensor,
    P0: Tensor,
    F: Tensor,
    L: Tensor,
    Qc: Tensor,
    dt: Tensor | float,
    B: Tensor | None = None,
    u: Tensor | None = None,
    method: str = "doubling",
) -> tuple[Tensor, Tensor]:
    """Moments after a horizon dt: ``m = A m0 + G u``, ``P = A P0 Aᵀ + Q``.

    They solve dm/dt = F m + B u and the Lyapunov ODE dP/dt = F P + P Fᵀ + L Qc Lᵀ.

    Args:
        m0: (..., n) mean at the start. P0: (..., n, n) covariance at the start.
        F, L, Qc, dt, B: as in :func:`discretize`.
        u: (..., p) input held constant over the horizon; requires B.

    Returns:
        m (..., n), P (..., n, n) symmetric.
    """
    if u is not None and B is None:
        raise ValueError(f"u was given (shape {shape_str(torch.as_tensor(u))}) but the SDE has no input matrix B")
    d = discretize(F, L, Qc, dt, B=B, method=method)
    n = d.A.shape[-1]
    m0 = as_float_tensor(m0, "m0", d.A.dtype, d.A.device)
    P0 = as_float_tensor(P0, "P0", d.A.dtype, d.A.device)
    check_vector(m0, "m0", n)
    check_matrix(P0, "P0", rows=n, cols=n)
    check_finite(m0, "m0")
    check_symmetric_psd(P0, "P0")
    m = (d.A @ m0.unsqueeze(-1)).squeeze(-1)
    if u is not None:
        assert d.G is not None
        u = as_float_tensor(u, "u", d.A.dtype, d.A.device)
        check_vector(u, "u", d.G.shape[-1])
        check_finite(u, "u")
        m = m + (d.G @ u.unsqueeze(-1)).squeeze(-1)
    P = d.A @ P0 @ d.A.mT + d.Q
    return m, 0.5 * (P + P.mT)


# ----------------------------------------------------------------------------------------
# Scaling and doubling
# ----------------------------------------------------------------------------------------


def _operator_norm_bound(F: Tensor) -> Tensor:
    """max(‖F‖₁, ‖F‖∞): bounds ‖F‖ and ‖𝓛‖/2 in the induced 1-norm. Shape (...)."""
    absF = F.abs()
    return torch.maximum(absF.sum(-2).amax(-1), absF.sum(-1).amax(-1))


def _nilpotency_index(F: Tensor) -> int | None:
    """Smallest k ≤ n with F^k = 0 exactly for every batch element, else None."""
    n = F.shape[-1]
    with torch.no_grad():
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


# Largest n for which the batch-last doubling products are summed as n fused multiply-adds
# over the contiguous batch (measured on CPU: faster than torch.bmm of 4×4 … 16×16 matrices,
# whose per-matrix overhead dominates); beyond it they go through torch.matmul.
_CHAIN_MAX_N = 16
# For tiny batches the per-call overhead of the autograd.Function outweighs its gain.
_CHAIN_MIN_BATCH = 256


def _chain_matmul(a: Tensor, b: Tensor, c: Tensor | None) -> Tensor:
    """c + a b for batch-last a: (n, m, N), b: (m, r, N), c: (n, r, N) -> (n, r, N)."""
    out = a[:, 0:1] * b[0:1] if c is None else torch.addcmul(c, a[:, 0:1], b[0:1])
    for j in range(1, a.shape[1]):
        out.addcmul_(a[:, j : j + 1], b[j : j + 1])
    return out


class _BatchLastMatmul(torch.autograd.Function):
    """c + a b on batch-last matrices; the backward calls the same product, so it is
    differentiable again (double backward works)."""

    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor, c: Tensor | None) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(a, b)
        ctx.has_c = c is not None
        return _chain_matmul(a, b, c)

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor | None, Tensor | None, Tensor | None]:  # type: ignore[override]
        a, b = ctx.saved_tensors
        ga = _bl_matmul(g, b.transpose(0, 1)) if ctx.needs_input_grad[0] else None
        gb = _bl_matmul(a.transpose(0, 1), g) if ctx.needs_input_grad[1] else None
        return ga, gb, (g if ctx.has_c and ctx.needs_input_grad[2] else None)


def _bl_matmul(a: Tensor, b: Tensor, c: Tensor | None = None) -> Tensor:
    """c + a b for batch-last matrices a: (n, m, N), b: (m, r, N), c: (n, r, N)."""
    if a.shape[1] > _CHAIN_MAX_N or a.shape[-1] <= _CHAIN_MIN_BATCH:
        out = (a.permute(2, 0, 1) @ b.permute(2, 0, 1)).permute(1, 2, 0)
        return out if c is None else out + c
    return _BatchLastMatmul.apply(a, b, c)


def _taylor_rows(x: Tensor, count: int) -> Tensor:
    """Rows x^k / k! for k < count: (count, N) for x (N,)."""
    rows = [torch.ones_like(x)]
    for k in range(1, count):
        rows.append(rows[-1] * x * (1.0 / k))
    return torch.stack(rows)


def _norm_bound_last(A: Tensor) -> Tensor:
    """max(‖A‖₁, ‖A‖∞) of batch-last A (n, n, N): (N,)."""
    absA = A.abs()
    return torch.maximum(absA.sum(0).amax(0), absA.sum(1).amax(0))


def _doubling_steps(
    X: Tensor, Q: Tensor | None, G: Tensor | None, counts: list[int]
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Doubling on batch-last tensors sorted by number of halvings (descending).

    X: (n, n, N) holds E = A − I; Q: (n, n, N); G: (n, p, N). counts[j] is the number of
    elements with more than j halvings: step j doubles the first counts[j] of them
    (A ← A A, Q ← A Q Aᵀ + Q, G ← A G + G) and leaves the others final, so no work is
    spent on elements that are done. While A is near the identity X carries E
    (E ← 2E + E E keeps the digits of E that A = I + E would round away); once a doubling
    leaves max(‖A‖₁, ‖A‖∞) < 1/2 (a decaying A, whose small entries E cannot resolve) it
    carries A itself. Returns A, Q, G batch-last, in the same (sorted) order.
    """
    n = X.shape[0]
    eye = torch.eye(n, dtype=X.dtype, device=X.device)[..., None]
    near = X.new_ones(1, 1, X.shape[-1])  # 1 while X holds E, 0 once it holds A
    n_near = X.shape[-1]
    A = X + eye
    done: list[list[Tensor]] = [[], [], []]
    for j, c in enumerate(counts):
        rest = A.shape[-1] - c
        if rest:
            A, a_done = A.split([c, rest], -1)
            X, near = X[..., :c], near[..., :c]
            done[0].append(a_done)
            if Q is not None:
                Q, q_done = Q.split([c, rest], -1)
                done[1].append(q_done)
            if G is not None:
                G, g_done = G.split([c, rest], -1)
                done[2].append(g_done)
            if n_near:
                n_near = int(near.sum())
        if j and n_near:  # switch E -> A after the previous doubling where A has decayed
            with torch.no_grad():
                switch = (near > 0) & (_norm_bound_last(A) < 0.5)
                n_switch = int(switch.sum())
            if n_switch:
                n_near -= n_switch
                if n_near:
                    X = torch.addcmul(X, switch.to(X.dtype), eye)  # = A in the switched columns
                    near = near * (~switch).to(X.dtype)
                else:
                    X = A
        if Q is not None:
            Q = _bl_matmul(_bl_matmul(A, Q), A.transpose(0, 1), Q)  # Q ← A Q Aᵀ + Q
        if G is not None:
            G = _bl_matmul(A, G, G)  # G ← A G + G
        if n_near == c:
            X = _bl_matmul(X, A, X)  # E ← E + E A = 2E + E E
            A = X + eye
        elif n_near == 0:
            A = X = _bl_matmul(A, A)
        else:
            X = _bl_matmul(X, A, X * near)  # columns holding E: 2E + E E; holding A: A A
            A = torch.addcmul(X, near, eye)
    out: list[Tensor | None] = []
    for t, d in zip((A, Q, G), done):
        out.append(None if t is None else (torch.cat([t] + d[::-1], -1) if d else t))
    return out[0], out[1], out[2]  # type: ignore[return-value]


def _to_batch_first(x: Tensor, order: Tensor | None, batch: torch.Size) -> Tensor:
    """Batch-last (r, c, N) whose column i belongs to element order[i] -> (*batch, r, c)."""
    xb = x.permute(2, 0, 1)
    if order is None:
        out = xb.contiguous()
    else:  # out[order[i]] = xb[i]; its backward is a gather
        out = torch.empty(xb.shape, dtype=x.dtype, device=x.device).index_copy_(0, order, xb)
    return out.reshape(*batch, *x.shape[:2])


def _to_batch_last(x: Tensor, order: Tensor | None, batch: torch.Size) -> Tensor:
    """Batch-last (r, c, N) whose column i belongs to element order[i] -> (r, c, *batch)."""
    if order is not None:  # out[..., order[i]] = x[..., i]
        x = torch.empty(x.shape, dtype=x.dtype, device=x.device).index_copy_(-1, order, x)
    return x.reshape(*x.shape[:2], *batch)


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


def _doubling(
    F: Tensor,
    W: Tensor | None,
    B: Tensor | None,
    dt: Tensor,
    batch: torch.Size,
    batch_last: bool = False,
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Scaling and doubling: (A, Q, G) of shapes (*batch, n, n), (*batch, n, n), (*batch, n, p)
    (contiguous (n, n, *batch), … with ``batch_last``).

    F: (..., n, n); W = L Qc Lᵀ: (..., n, n) or None; B: (..., n, p) or None; dt: (...).
    Each element takes s = ceil(log2(‖F‖ dt / θ)) halvings (none for nilpotent F), sums the
    Taylor series on h = dt / 2^s and doubles s times. Internally the batch is flattened to
    N = prod(batch), laid out last ("batch-last" (n, n, N): elementwise work on contiguous
    rows of N) and sorted by s, so doubling step j only touches the elements with s > j.
    """
    dtype = F.dtype
    param_batch = broadcast_batch(
        [("F", F.shape[:-2])]
        + ([("W", W.shape[:-2])] if W is not None else [])
        + ([("B", B.shape[:-2])] if B is not None else [])
    )
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

    # Scale F to unit norm (a constant, so gradients are untouched): F = ν F̃.
    with torch.no_grad():
        nu = _operator_norm_bound(F)
        nu = torch.where(nu > 0, nu, torch.ones_like(nu))
    F_unit = F / nu[..., None, None]

    nil = _nilpotency_index(F)
    if nil is not None:
        # Terminating series: exact at the full step (3ν terms also make the gradient exact).
        count = 3 * nil
        halvings = None
    else:
        count = _series_length(dtype)
        with torch.no_grad():
            ratio = nu * dt / _THETA  # (batch)
            halvings = torch.ceil(torch.log2(ratio.clamp_min(1.0)))
            # non-finite dt (only reachable with value checks off) gives non-finite output
            halvings = torch.nan_to_num(halvings, nan=0.0, posinf=0.0).to(torch.int64)
    powers, lyap, inputs = _series_terms(F_unit, W, B, count)
    # One stack of terms whose coefficients are all (νh)^k / k!: F̃^k (k ≥ 1) for E = A − I,
    # 𝓛̃^k(W) / (k+1) for Q / h and F̃^k B / (k+1) for G / h.
    k1 = torch.arange(1, count + 1, dtype=dtype, device=F.device)[:, None, None]
    terms = [torch.cat([torch.zeros_like(powers[..., :1, :, :]), powers[..., 1:, :, :]], -3).flatten(-2)]
    if lyap is not None:
        terms.append((lyap / k1).flatten(-2))
    if inputs is not None:
        terms.append((inputs / k1).flatten(-2))
    terms_all = torch.cat(terms, -1)  # (*param_batch, K, T), T = n² [+ n²] [+ n p]

    h = dt if halvings is None else dt * torch.exp2(-halvings.to(dtype))
    N = batch.numel()
    hf = h.expand(batch).reshape(-1)
    xf = (h * nu).expand(batch).reshape(-1)  # ‖F‖ h ≤ θ

    order = None
    counts: list[int] = []
    if halvings is not None and N:
        with torch.no_grad():
            flat = halvings.expand(batch).reshape(-1)
            steps = int(flat.max())
            if steps:
                order = torch.argsort(flat, descending=True)
                tally = torch.bincount(flat, minlength=steps + 1)
                counts = (N - torch.cumsum(tally, 0))[:steps].tolist()
    if not counts and powers.dim() == 3:  # one parameter set, no doubling (e.g. nilpotent F)
        return _series_full_step(powers, lyap, inputs, xf, hf, batch, batch_last)
    if order is not None:
        xf, hf = xf[order], hf[order]

    # Series on the sub-step, batch-last (T, N). Shared parameters (the training case): one
    # GEMM (T, K) x (K, N) for the whole batch, already in doubling order.
    rows = _taylor_rows(xf, count)  # (K, N)
    if terms_all.dim() == 2:
        out = terms_all.mT @ rows
    else:
        coeff = rows.mT if order is None else rows.mT[torch.argsort(order)]  # original order
        out = torch.einsum("...k,...kt->...t", coeff.reshape(*batch, count), terms_all).reshape(N, -1)
        out = (out if order is None else out[order]).mT
    X = out[: n * n].reshape(n, n, N)
    Q = None if lyap is None else hf * out[n * n : 2 * n * n].reshape(n, n, N)
    G = None if inputs is None else hf * out[out.shape[0] - n * p :].reshape(n, p, N)

    if counts:
        A, Q, G = _doubling_steps(X, Q, G, counts)
    else:
        A = X + torch.eye(n, dtype=dtype, device=F.device)[..., None]
    if Q is not None:
        Q = torch.lerp(Q, Q.transpose(0, 1), 0.5)  # symmetrise
    convert = _to_batch_last if batch_last else _to_batch_first
    return (
        convert(A, order, batch),
        None if Q is None else convert(Q, order, batch),
        None if G is None else convert(G, order, batch),
    )


# ----------------------------------------------------------------------------------------
# Van Loan's block exponential
# ----------------------------------------------------------------------------------------


def _van_loan(
    F: Tensor, W: Tensor | None, B: Tensor | None, dt: Tensor, batch: torch.Size
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    n = F.shape[-1]
    p = 0 if B is None else B.shape[-1]
    size = 2 * n + p
    dt_mat = dt[..., None, None]
    block = F.new_zeros(*batch, size, size)
    block[..., :n, :n] = F * dt_mat
    if W is not None:
        block[..., :n, n : 2 * n] = W * dt_mat
    block[..., n : 2 * n, n : 2 * n] = -F.mT * dt_mat
    if B is not None:
        block[..., :n, 2 * n :] = B * dt_mat
    E = torch.matrix_exp(block)
    A = E[..., :n, :n]
    Q = None
    if W is not None:
        Q = E[..., :n, n : 2 * n] @ A.mT
        Q = 0.5 * (Q + Q.mT)
    G = E[..., :n, 2 * n :] if B is not None else None
    return A, Q, G
