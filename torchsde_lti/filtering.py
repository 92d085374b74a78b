r"""Functional Kalman filtering and RTS smoothing on per-step discrete matrices.

Inference is kept apart from models (as in dynamax): these are pure functions of the
discrete-time state-space model

    x_k = A_k x_{k-1} + G_k u_k + q_k,    q_k ~ N(0, Q_k),     x_{-1} ~ N(m0, P0)
    y_k = H_k x_k + D u_k + r_k,          r_k ~ N(0, R_k),     k = 0 … T-1

(D, the feedthrough of known inputs, is optional: ``D u`` is subtracted from y during the
input preparation, so every filter variant sees ``y − D u``.)

(the prior sits *before* step 0: step k first predicts with A_k, Q_k, then updates with
y_k; pass A_0 = I, Q_0 = 0 to put the prior at the first observation).
:class:`torchsde_lti.KalmanFilter` builds (A_k, Q_k, G_k) from an SDE and calls them.

Shapes (batch dims ``...`` lead and broadcast, numpy rules, right-aligned)::

    y (..., T, m)   A, Q (..., T, n, n)   H (..., T, m, n)   R (..., T, m, m)
    m0 (..., n)     P0 (..., n, n)        G (..., T, n, p)   u (..., T, p)
    mask (..., T) or (..., T, m) bool (True = observed)

Per-step arrays may omit or size-1 the T axis (a constant ``H (m, n)`` is fine); a
per-batch constant matrix needs its T axis as 1, e.g. ``A (B, 1, n, n)``.

Missing data: a NaN in y, or mask False, means "not observed". y is sanitised first
(``where(observed, y, 0)``) so no NaN reaches any arithmetic or gradient. Unobserved
components get a zero row in H and a decoupled unit variance in R, so every step keeps
static shapes; a fully missing step is a pure prediction, a partially observed one updates
with its observed components only, and the log-likelihood counts observed components only.

Numerics. Each step's noise is whitened with the Cholesky factor L_k of the (masked) R_k:
``y' = L⁻¹ y``, ``H' = L⁻¹ H``, so R' = I, and the m scalar observations are processed one
after the other (Bierman's sequential processing: the result equals the joint update). Each
scalar update uses the Joseph form ``P⁺ = (I − k hᵀ) P (I − k hᵀ)ᵀ + k kᵀ`` and P is
symmetrised once per step. No matrix is inverted; there is no Cholesky in the time loop.
``kalman_filter(..., square_root=True)`` instead propagates factors P = S Sᵀ (QR predict,
Givens scalar updates): PSD by construction and accurate in float32 beyond the Joseph
form's range (predicted/measured variance ratios > 1/eps), at 2–5× the cost.

The work that does not depend on the recursion (whitening, control terms, innovations and
log-likelihood bookkeeping) is done batched over all T outside the loop. The covariance
recursion depends on (A, Q, H, R, mask, P0) only, never on y, so it runs at the batch
shape of those: with a shared dt grid and no missing data it runs once for all tracks.
Inside the loop tensors are laid out batch-last, ``(n, n, *batch)``, so that elementwise
work runs over the contiguous batch; the returned tensors are (possibly non-contiguous)
views in the documented batch-first shapes.

The parallel variants (Särkkä & García-Fernández, 2021, "Temporal parallelization of
Bayesian smoothers") compute the same quantities with an associative scan of O(log T)
depth.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti._validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_matrix,
    check_symmetric_psd,
    common_float_dtype,
    shape_str,
    value_checks_enabled,
)

__all__ = [
    "FilterResult",
    "SmootherResult",
    "kalman_filter",
    "parallel_kalman_filter",
    "parallel_rts_smoother",
    "rts_smoother",
]

_LOG_2PI = math.log(2.0 * math.pi)
_SMALL = 4  # matrices up to this size use unrolled elementwise Cholesky/solves (faster than LAPACK per matrix)


class FilterResult(NamedTuple):
    """Output of :func:`kalman_filter` / :func:`parallel_kalman_filter`.

    mean: (..., T, n) filtered means E[x_k | y_{0:k}].
    cov: (..., T, n, n) filtered covariances.
    pred_mean: (..., T, n) one-step predictions E[x_k | y_{0:k-1}].
    pred_cov: (..., T, n, n) predicted covariances.
    innovation: (..., T, m) ``y_k − H_k pred_mean_k``; 0 in unobserved components.
    innovation_cov: (..., T, m, m) ``H_k pred_cov_k H_kᵀ + R_k`` (all components).
    log_likelihood: (...) Σ_k step_log_likelihood.
    step_log_likelihood: (..., T) log N(y_k^obs; H^obs pred_mean_k, S_k^obs) over the
        observed components of y_k (0 for a fully missing step).
    transition: (..., T, n, n) the A_k used (a broadcast view), kept for smoothing.
    process_noise: (..., T, n, n) the Q_k used (a broadcast view), kept for smoothing.
    observed: (..., T, m) bool, the components that entered the update.
    """

    mean: Tensor
    cov: Tensor
    pred_mean: Tensor
    pred_cov: Tensor
    innovation: Tensor
    innovation_cov: Tensor
    log_likelihood: Tensor
    step_log_likelihood: Tensor
    transition: Tensor
    process_noise: Tensor
    observed: Tensor


class SmootherResult(NamedTuple):
    """Output of :func:`rts_smoother` / :func:`parallel_rts_smoother`.

    mean: (..., T, n) smoothed means E[x_k | y_{0:T-1}].
    cov: (..., T, n, n) smoothed covariances (≤ the filtered ones in the PSD order).
    gain: (..., T, n, n) smoother gains ``E_k = P_k A_{k+1}ᵀ (P⁻_{k+1})⁻¹`` (E_{T-1} = 0).
    """

    mean: Tensor
    cov: Tensor
    gain: Tensor


# ----------------------------------------------------------------------------------------
# Small dense linear algebra, unrolled over the matrix size and vectorised over the batch.
# For the 1–4 dimensional blocks of tracking models this beats one LAPACK call per matrix
# by an order of magnitude and is differentiable by plain autograd.
# ----------------------------------------------------------------------------------------


def _sym(P: Tensor) -> Tensor:
    return 0.5 * (P + P.mT)


def _cholesky(S: Tensor) -> Tensor:
    """Lower Cholesky factor of symmetric positive-definite S (..., k, k)."""
    k = S.shape[-1]
    if k > _SMALL:
        return torch.linalg.cholesky(S)
    rows: list[list[Tensor]] = [[] for _ in range(k)]  # rows[i][j] = L[i, j] for j <= i
    for j in range(k):
        d = S[..., j, j]
        for t in range(j):
            d = d - rows[j][t] * rows[j][t]
        ljj = torch.sqrt(d)
        rows[j].append(ljj)
        for i in range(j + 1, k):
            v = S[..., i, j]
            for t in range(j):
                v = v - rows[i][t] * rows[j][t]
            rows[i].append(v / ljj)
    zero = torch.zeros_like(S[..., 0, 0])
    full = [[rows[i][j] if j <= i else zero for j in range(k)] for i in range(k)]
    return torch.stack([torch.stack(r, dim=-1) for r in full], dim=-2)


def _solve_lower(L: Tensor, B: Tensor) -> Tensor:
    """X with L X = B; L (..., k, k) lower triangular, B (..., k, r)."""
    k = L.shape[-1]
    if k > _SMALL:
        return torch.linalg.solve_triangular(L, B, upper=False)
    xs: list[Tensor] = []
    for i in range(k):
        v = B[..., i, :]
        for j in range(i):
            v = v - L[..., i, j, None] * xs[j]
        xs.append(v / L[..., i, i, None])
    return torch.stack(xs, dim=-2)


def _solve_upper_t(L: Tensor, B: Tensor) -> Tensor:
    """X with Lᵀ X = B; L (..., k, k) lower triangular, B (..., k, r)."""
    k = L.shape[-1]
    if k > _SMALL:
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


def _cho_solve(L: Tensor, B: Tensor) -> Tensor:
    """X with (L Lᵀ) X = B."""
    return _solve_upper_t(L, _solve_lower(L, B))


def _matvec(M: Tensor, v: Tensor) -> Tensor:
    return (M @ v.unsqueeze(-1)).squeeze(-1)


# Batch-last helpers: tensors laid out as (*event, *batch); products broadcast and sum
# over the event index so that the innermost (contiguous) dimension is the batch.


def _to_batch_last(x: Tensor, event_ndim: int, time: bool = False) -> Tensor:
    """(*batch, [T,] *event) -> ([T,] *event, *batch), contiguous."""
    nd = x.dim()
    nb = nd - event_ndim - (1 if time else 0)
    perm = ([nb] if time else []) + list(range(nd - event_ndim, nd)) + list(range(nb))
    return x.permute(perm).contiguous()


def _from_batch_last(x: Tensor, event_ndim: int, batch_ndim: int) -> Tensor:
    """(T, *event, *batch) -> (*batch, T, *event) (a view)."""
    perm = list(range(1 + event_ndim, 1 + event_ndim + batch_ndim)) + list(range(1 + event_ndim))
    return x.permute(perm)


def _bl_matmul(X: Tensor, Y: Tensor) -> Tensor:
    """(a, b, *B) @ (b, c, *B) -> (a, c, *B)."""
    return torch.linalg.vecdot(X.unsqueeze(2), Y.unsqueeze(0), dim=1)


def _bl_matvec(X: Tensor, v: Tensor) -> Tensor:
    """(a, b, *B) @ (b, *B) -> (a, *B)."""
    return torch.linalg.vecdot(X, v.unsqueeze(0), dim=1)


def _bl_sym(P: Tensor) -> Tensor:
    return 0.5 * (P + P.transpose(0, 1))


def _bl_sym_into(P: Tensor, out: Tensor | None) -> Tensor:
    """_bl_sym(P), written into ``out`` when given (no autograd); same values."""
    if out is None:
        return _bl_sym(P)
    torch.add(P, P.transpose(0, 1), out=out)
    return out.mul_(0.5)


# ----------------------------------------------------------------------------------------
# Argument preparation shared by the sequential and parallel filters
# ----------------------------------------------------------------------------------------


class _Prepared(NamedTuple):
    A: Tensor  # (*cb, T, n, n) broadcast view; cb has len(mean batch) dims
    Q: Tensor  # (*cb, T, n, n)
    Hw: Tensor  # (..., T or 1, m, n) whitened, masked observation matrix (broadcastable to cb)
    yw: Tensor  # (*mb, T, m) whitened, sanitised observations
    c: Tensor | None  # (*mb, T, n) control term G u
    m0: Tensor  # (*mb, n)
    P0: Tensor  # (*cb, n, n)
    H: Tensor  # (..., T or 1, m, n) unwhitened (for innovations), broadcastable to (*cb, T, m, n)
    R: Tensor  # (..., T or 1, m, m) unmasked (for innovation covariances)
    y0: Tensor  # (*mb, T, m) sanitised y
    obs: Tensor | None  # (*ob, T, m) bool, None when all observed
    log_det_chol_R: Tensor  # (*cb, T) Σ log diag of the whitening factor (observed part)
    mean_batch: torch.Size
    T: int


def _pad(x: Tensor, ndim: int) -> Tensor:
    """Prepend size-1 dims so that x has ``ndim`` dims."""
    return x.reshape((1,) * (ndim - x.dim()) + tuple(x.shape)) if x.dim() < ndim else x


def _prepare(
    y: Tensor,
    A: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    m0: Tensor,
    P0: Tensor,
    G: Tensor | None,
    u: Tensor | None,
    mask: Tensor | None,
    D: Tensor | None = None,
) -> _Prepared:
    dtype = common_float_dtype(*(t for t in (y, A, Q, H, R, m0, P0, G, u, D) if isinstance(t, Tensor)))
    device = next(t.device for t in (y, A, Q, H, R, m0, P0) if isinstance(t, Tensor))
    y = as_float_tensor(y, "y", dtype, device)
    A = as_float_tensor(A, "A", dtype, device)
    Q = as_float_tensor(Q, "Q", dtype, device)
    H = as_float_tensor(H, "H", dtype, device)
    R = as_float_tensor(R, "R", dtype, device)
    m0 = as_float_tensor(m0, "m0", dtype, device)
    P0 = as_float_tensor(P0, "P0", dtype, device)

    if y.dim() < 2:
        raise ValueError(f"y must have shape (..., T, m), got shape {shape_str(y)}")
    T, m = y.shape[-2], y.shape[-1]
    if T < 1 or m < 1:
        raise ValueError(f"y must have at least one step and one component, got shape {shape_str(y)}")
    check_matrix(A, "A", square=True)
    n = A.shape[-1]
    check_matrix(Q, "Q", rows=n, cols=n)
    check_matrix(H, "H")
    if H.shape[-2] != m:
        raise ValueError(
            f"y has {m} components (shape {shape_str(y)}) but H has {H.shape[-2]} rows (shape {shape_str(H)})"
        )
    if H.shape[-1] != n:
        raise ValueError(f"H must have {n} columns to match A {shape_str(A)}, got shape {shape_str(H)}")
    check_matrix(R, "R", rows=m, cols=m)
    if m0.dim() < 1 or m0.shape[-1] != n:
        raise ValueError(f"m0 must have shape (..., {n}), got shape {shape_str(m0)}")
    check_matrix(P0, "P0", rows=n, cols=n)
    if u is None and (G is not None or D is not None):
        raise ValueError(
            f"G and u (or D and u) must be given together: u is None (G={'None' if G is None else shape_str(G)}, "
            f"D={'None' if D is None else shape_str(torch.as_tensor(D))})"
        )
    if u is not None and G is None and D is None:
        raise ValueError(
            f"G and u (or D and u) must be given together: u was given (shape {shape_str(torch.as_tensor(u))}) "
            "but G and D are None"
        )
    if D is not None and u is not None:
        # Feedthrough y = H x + D u + r: filter y − D u (NaN stays NaN, so missing data keep their meaning).
        D = as_float_tensor(D, "D", dtype, device)
        u = as_float_tensor(u, "u", dtype, device)
        check_matrix(D, "D", rows=m)
        pD = D.shape[-1]
        if u.dim() < 2 or u.shape[-1] != pD or u.shape[-2] not in (1, T):
            raise ValueError(f"u must have shape (..., T={T}, {pD}) to match D {shape_str(D)}, got shape {shape_str(u)}")
        if D.dim() >= 3 and D.shape[-3] not in (1, T):
            raise ValueError(f"D has {D.shape[-3]} steps on its time axis (shape {shape_str(D)}) but y has T={T}")
        check_finite(D, "D")
        check_finite(u, "u")
        y = y - _matvec(D, u)
    c = None
    if G is not None and u is not None:
        G = as_float_tensor(G, "G", dtype, device)
        u = as_float_tensor(u, "u", dtype, device)
        check_matrix(G, "G", rows=n)
        p = G.shape[-1]
        if u.dim() < 2 or u.shape[-1] != p:
            raise ValueError(f"u must have shape (..., T, {p}) to match G {shape_str(G)}, got shape {shape_str(u)}")
        check_finite(u, "u")
        c = _matvec(G, u)  # (..., T, n)
    obs_given = None
    if mask is not None:
        mask = torch.as_tensor(mask, device=device)
        if mask.dtype != torch.bool:
            raise ValueError(f"mask must be a bool tensor, got dtype {mask.dtype}")
        per_component = mask.dim() >= 2 and mask.shape[-2] == T and mask.shape[-1] == m
        if not per_component and mask.dim() >= 1 and mask.shape[-1] == T:
            mask = mask.unsqueeze(-1)  # (..., T) -> (..., T, 1)
        if mask.dim() < 2 or mask.shape[-2] != T or mask.shape[-1] not in (1, m):
            raise ValueError(f"mask must have shape (..., {T}) or (..., {T}, {m}), got shape {shape_str(mask)}")
        obs_given = mask

    # Per-step arrays: check their T axis.
    for name, x, k in (("A", A, 3), ("Q", Q, 3), ("H", H, 3), ("R", R, 3)):
        if x.dim() >= k and x.shape[-k] not in (1, T):
            raise ValueError(
                f"{name} has {x.shape[-k]} steps on its time axis (shape {shape_str(x)}) but y has T={T} "
                f"(shape {shape_str(y)}); give a per-batch constant as (..., 1, r, c)"
            )
    if c is not None and c.shape[-2] not in (1, T):
        raise ValueError(f"u has {c.shape[-2]} steps but y has T={T}")

    if value_checks_enabled():
        check_finite(A, "A")
        check_finite(H, "H")
        check_finite(m0, "m0")
        check_symmetric_psd(Q, "Q")
        check_symmetric_psd(R, "R")
        check_symmetric_psd(P0, "P0")
        if bool((torch.linalg.cholesky_ex(R).info != 0).any()):
            raise ValueError(f"R must be positive definite (Cholesky failed; shape {shape_str(R)})")

    # Observed components: NaN in y or mask False.
    nan = torch.isnan(y)
    obs: Tensor | None = None
    if bool(nan.any()):
        obs = ~nan
    if obs_given is not None:
        obs = obs_given if obs is None else (obs & obs_given)
    y0 = y if obs is None else torch.where(obs, y, torch.zeros((), dtype=dtype, device=device))

    # Batch shapes: the covariance path excludes y (and u) unless data are missing.
    tshape = lambda s: tuple(s)  # noqa: E731
    cov_named = [
        ("A", tshape(A.shape[:-2])),
        ("Q", tshape(Q.shape[:-2])),
        ("H", tshape(H.shape[:-2])),
        ("R", tshape(R.shape[:-2])),
        ("P0", tshape(P0.shape[:-2]) + (1,)),
        ("T", (T,)),
    ]
    if obs is not None:
        cov_named.append(("mask", tshape(obs.shape[:-1])))
    cov_bt = broadcast_batch(cov_named)  # (*cb, T)
    mean_named = cov_named + [("y", tshape(y.shape[:-1])), ("m0", tshape(m0.shape[:-1]) + (1,))]
    if c is not None:
        mean_named.append(("u", tshape(c.shape[:-1])))
    mean_bt = broadcast_batch(mean_named)
    if mean_bt[-1] != T:
        raise ValueError(f"time axes do not broadcast to T={T}: {mean_named}")
    nd = len(mean_bt) - 1
    cov_bt = torch.Size((1,) * (len(mean_bt) - len(cov_bt)) + tuple(cov_bt))
    cb = cov_bt[:-1]

    A = _pad(A, nd + 3).expand(*cov_bt, n, n)
    Q = _pad(Q, nd + 3).expand(*cov_bt, n, n)
    # H, R and everything derived from them keep their own (broadcastable) shapes.
    H = _pad(H, nd + 3)
    R = _pad(R, nd + 3)
    P0 = _pad(P0, nd + 2).expand(*cb, n, n)
    m0 = _pad(m0, nd + 1).expand(*mean_bt[:-1], n)
    y0 = _pad(y0, nd + 2)
    if c is not None:
        c = _pad(c, nd + 2)

    if obs is None:
        Hm, Rm = H, R
    else:
        o = _pad(obs, nd + 2).to(dtype)
        o = o.expand(*o.shape[:-1], m)
        eye_m = torch.eye(m, dtype=dtype, device=device)
        Hm = H * o.unsqueeze(-1)
        Rm = R * (o.unsqueeze(-1) * o.unsqueeze(-2)) + torch.diag_embed(1.0 - o) * eye_m
    # Whitening: L L^T = Rm, H' = L^{-1} Hm, y' = L^{-1} y0 (unobserved rows stay 0).
    LR = _cholesky(Rm)
    Hw = _solve_lower(LR, Hm)
    yw = _solve_lower(LR, y0.unsqueeze(-1)).squeeze(-1)
    log_det = torch.log(torch.diagonal(LR, dim1=-2, dim2=-1)).sum(-1)
    return _Prepared(A, Q, Hw, yw, c, m0, P0, H, R, y0, obs, log_det, mean_bt[:-1], T)


def _finish(
    prep: _Prepared,
    mean: Tensor,
    cov: Tensor,
    pred_mean: Tensor,
    pred_cov: Tensor,
    step_ll_core: Tensor,
    innovation: Tensor | None = None,
    innovation_cov: Tensor | None = None,
) -> FilterResult:
    """Innovations (original space), log-likelihood, broadcast outputs to the full batch."""
    mb, T = prep.mean_batch, prep.T
    n, m = mean.shape[-1], prep.yw.shape[-1]
    if innovation is None or innovation_cov is None:
        innovation = prep.y0 - _matvec(prep.H, pred_mean)
        innovation_cov = _sym(prep.H @ pred_cov @ prep.H.mT + prep.R)
    if prep.obs is None:
        n_obs = torch.full((), float(m), dtype=mean.dtype, device=mean.device)
        observed = torch.ones((*mb, T, m), dtype=torch.bool, device=mean.device)
    else:
        o = _pad(prep.obs, len(mb) + 2).expand(*mb, T, m)
        innovation = innovation * o
        n_obs = o.to(mean.dtype).sum(-1)
        observed = o
    step_ll = step_ll_core - 0.5 * n_obs * _LOG_2PI - prep.log_det_chol_R
    step_ll = step_ll.expand(*mb, T)
    return FilterResult(
        mean=mean.expand(*mb, T, n),
        cov=cov.expand(*mb, T, n, n),
        pred_mean=pred_mean.expand(*mb, T, n),
        pred_cov=pred_cov.expand(*mb, T, n, n),
        innovation=innovation.expand(*mb, T, m),
        innovation_cov=innovation_cov.expand(*mb, T, m, m),
        log_likelihood=step_ll.sum(-1),
        step_log_likelihood=step_ll,
        transition=prep.A,
        process_noise=prep.Q,
        observed=observed,
    )


# ----------------------------------------------------------------------------------------
# Sequential filter
# ----------------------------------------------------------------------------------------


def kalman_filter(
    y: Tensor,
    A: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    m0: Tensor,
    P0: Tensor,
    G: Tensor | None = None,
    u: Tensor | None = None,
    mask: Tensor | None = None,
    square_root: bool = False,
    D: Tensor | None = None,
) -> FilterResult:
    r"""Kalman filter over T steps (sequential loop, O(T) depth).

    Step k: predict ``m⁻ = A_k m + G_k u_k``, ``P⁻ = A_k P A_kᵀ + Q_k``; then update with the
    observed components of y_k (whitened sequential scalar updates in Joseph form, see the
    module docstring). The log-likelihood is the prediction-error decomposition
    ``Σ_k log N(y_k^obs; H_k^obs m⁻_k, H_k^obs P⁻_k H_k^obsᵀ + R_k^obs)``.

    Args:
        y: (..., T, m) observations; NaN = missing component.
        A: (..., T, n, n) transitions. Q: (..., T, n, n) process noise (symmetric PSD).
        H: (..., T, m, n) observation matrices. R: (..., T, m, m) noise (symmetric PD).
        m0: (..., n) prior mean. P0: (..., n, n) prior covariance (before step 0).
        G: optional (..., T, n, p) input matrices; u: (..., T, p) inputs (u needs G or D).
        mask: optional bool (..., T) or (..., T, m); False = not observed.
        square_root: propagate factors ``P = S Sᵀ`` (QR predict, Givens update, see
            :func:`_square_root_filter`) instead of covariances; same results up to
            rounding, covariances PSD by construction and accurate in float32 when predicted
            and measurement variances differ by more than 1/eps. Slower (a batched LAPACK
            QR per step); off by default.
        D: optional (..., [T,] m, p) feedthrough, ``y_k = H_k x_k + D u_k + r_k``: the update
            uses ``y_k − D u_k`` (so innovations are ``y_k − D u_k − H_k m⁻_k``); needs u.

    Returns:
        :class:`FilterResult`; every output broadcasts to the full batch ``...``.
    """
    prep = _prepare(y, A, Q, H, R, m0, P0, G, u, mask, D)
    if square_root:
        return _square_root_filter(prep)
    m_dim = prep.yw.shape[-1]
    # Batch-last layout: per-step tensors (n, n, *batch) keep the batch as the contiguous
    # inner dimension, so every elementwise op and the broadcast-and-sum products below run
    # at full vector speed (batched 4×4 `bmm`/transposes are several times slower).
    # A_k, Q_k are moved to this layout one step at a time (a small, cache-friendly copy).
    # (unbind, not indexing, inside the loop: the backward of T separate index operations
    # would materialise T full-size zero gradients; unbind's backward is one stack.)
    A_bf, Q_bf = prep.A, prep.Q  # (*cb, T, n, n)
    nb = A_bf.dim() - 3
    to_bl = list(range(nb, nb + 2)) + list(range(nb))
    A_steps, Q_steps = A_bf.unbind(-3), Q_bf.unbind(-3)
    H_s = _to_batch_last(prep.Hw, 2, time=True)  # (T or 1, m, n, *cb or broadcastable)
    # Materialise H' over the batch: products with a stride-0 (broadcast) inner dimension
    # take a slow path, same-shape ones do not.
    cb = A_bf.shape[:nb]
    H_s = H_s.expand(*H_s.shape[:3], *torch.broadcast_shapes(H_s.shape[3:], cb)).contiguous()
    h_single = H_s.shape[0] == 1
    h_rows = H_s.reshape(-1, *H_s.shape[2:]).unbind(0)  # (T or 1)·m rows, each (n, *)
    yw_bl = _to_batch_last(prep.yw, 1, time=True)  # (T, m, *mb)
    y_rows = yw_bl.reshape(-1, *yw_bl.shape[2:]).unbind(0)  # T·m entries, each (*mb)
    c_steps = _to_batch_last(prep.c, 1, time=True).unbind(0) if prep.c is not None else None
    c_single = c_steps is not None and len(c_steps) == 1

    mean = _to_batch_last(prep.m0, 1)  # (n, *mb)
    P = _to_batch_last(prep.P0, 2)  # (n, n, *cb)
    means, covs, pmeans, pcovs, es, ss = [], [], [], [], [], []
    # Without autograd the covariances are written straight into (T, n, n, *cb) outputs
    # (no stack of T tensors at the end); with autograd they are stacked.
    buffers = not torch.is_grad_enabled() or not any(
        t.requires_grad for t in (prep.A, prep.Q, prep.Hw, prep.P0) if isinstance(t, Tensor)
    )
    n_state = P.shape[0]
    pc_buf = P.new_empty((prep.T, n_state, n_state, *P.shape[2:])) if buffers else None
    fc_buf = P.new_empty((prep.T, n_state, n_state, *P.shape[2:])) if buffers else None
    for k in range(prep.T):
        Ak = A_steps[k].permute(to_bl)
        Qk = Q_steps[k].permute(to_bl)
        if Ak.stride(-1) != 1 or Ak.dim() == 2:
            Ak, Qk = Ak.contiguous(), Qk.contiguous()
        # Predict.
        mean = _bl_matvec(Ak, mean)
        if c_steps is not None:
            mean = mean + c_steps[0 if c_single else k]
        P = _bl_sym_into(_bl_matmul(_bl_matmul(Ak, P), Ak.transpose(0, 1)) + Qk, None if pc_buf is None else pc_buf[k])
        pmeans.append(mean)
        pcovs.append(P)
        # Update: one whitened scalar observation at a time (Joseph form).
        hk0 = 0 if h_single else k * m_dim
        for j in range(m_dim):
            h = h_rows[hk0 + j]
            ph = _bl_matvec(P, h)
            s = torch.linalg.vecdot(h, ph, dim=0) + 1.0
            gain = ph / s
            e = y_rows[k * m_dim + j] - torch.linalg.vecdot(h, mean, dim=0)
            mean = torch.addcmul(mean, gain, e)
            MP = torch.addcmul(P, gain.unsqueeze(1), ph.unsqueeze(0), value=-1.0)  # (I − k hᵀ) P
            w = _bl_matvec(MP, h)  # (I − k hᵀ) P h
            P = torch.addcmul(MP, (gain - w).unsqueeze(1), gain.unsqueeze(0))  # … (I − h kᵀ) + k kᵀ
            es.append(e)
            ss.append(s)
        P = _bl_sym_into(P, None if fc_buf is None else fc_buf[k])
        means.append(mean)
        covs.append(P)
    nd = len(prep.mean_batch)
    pm_bl = torch.stack(pmeans)  # (T, n, *mb)
    pc_bl = torch.stack(pcovs) if pc_buf is None else pc_buf  # (T, n, n, *cb)
    # Innovations and their covariances, batched over all steps in the same layout.
    H_bl = _to_batch_last(prep.H, 2, time=True)  # (T or 1, m, n, *)
    R_bl = _to_batch_last(prep.R, 2, time=True)
    y0_bl = _to_batch_last(prep.y0, 1, time=True)
    n = pm_bl.shape[1]
    if H_bl.shape[0] == 1 and all(d == 1 for d in H_bl.shape[3:]):
        # One H for every step and track: contract with a single matrix product (BLAS) on
        # the flattened (T, n·n, batch) covariances.
        Hm = H_bl.reshape(H_bl.shape[1:3])  # (m, n)
        bshape = pc_bl.shape[3:]
        innov = y0_bl - (Hm @ pm_bl.reshape(prep.T, n, -1)).reshape(prep.T, -1, *pm_bl.shape[2:])
        HH = (Hm[:, None, :, None] * Hm[None, :, None, :]).reshape(m_dim * m_dim, n * n)  # (m², n²)
        S = (HH @ pc_bl.reshape(prep.T, n * n, -1)).reshape(prep.T, m_dim, m_dim, *bshape) + R_bl
    else:
        # (accumulated over the contracted index: no (T, m, n, n, *batch) intermediate)
        innov = y0_bl
        HP = None
        for j in range(n):
            innov = innov - H_bl[:, :, j] * pm_bl[:, j : j + 1]
            term = H_bl[:, :, j : j + 1] * pc_bl[:, j : j + 1]  # (T, m, n, *)
            HP = term if HP is None else HP + term
        assert HP is not None
        S = R_bl
        for j in range(n):
            S = S + HP[:, :, j : j + 1] * H_bl[:, :, j].unsqueeze(1)  # (T, m, m, *)
    S = 0.5 * (S + S.transpose(1, 2))
    mean_t = _from_batch_last(torch.stack(means), 1, nd)
    cov_t = _from_batch_last(torch.stack(covs) if fc_buf is None else fc_buf, 2, nd)
    pmean_t = _from_batch_last(pm_bl, 1, nd)
    pcov_t = _from_batch_last(pc_bl, 2, nd)
    e_t = torch.stack(torch.broadcast_tensors(*es))  # (T m, *mb)
    s_t = torch.stack(ss)  # (T m, *cb)
    terms = torch.log(s_t) + e_t * e_t / s_t
    core = -0.5 * terms.reshape(prep.T, m_dim, *terms.shape[1:]).sum(1)  # (T, *mb)
    core = core.permute(*range(1, core.dim()), 0)  # (*mb, T)
    innovation = _from_batch_last(innov, 1, nd)
    innovation_cov = _from_batch_last(S, 2, nd)
    return _finish(prep, mean_t, cov_t, pmean_t, pcov_t, core, innovation, innovation_cov)


# ----------------------------------------------------------------------------------------
# Square-root (Cholesky-factor) sequential filter
# ----------------------------------------------------------------------------------------


def _psd_factor(X: Tensor) -> Tensor:
    r"""Lower-triangular L with ``L Lᵀ = X`` for symmetric PSD X (..., n, n), singular allowed.

    Cholesky–Banachiewicz, unrolled over n and vectorised over the batch, with a
    semi-definite pivot rule: a pivot ``d_j ≤ n · eps · X_jj`` (zero up to the rounding of
    its own diagonal entry, e.g. every pivot of Q(dt = 0) = 0 or of a rank-deficient Q)
    gives a zero column instead of a NaN. The threshold is per pivot, so badly scaled
    matrices (a constant-velocity Q over a long gap: diagonal q dt³/3 vs q dt) keep their
    small pivots. No jitter is added, so ``L Lᵀ = X`` up to rounding; the gradient through a dropped
    pivot is taken as 0 (``torch.where`` with safe branches: no NaN in backward).
    """
    n = X.shape[-1]
    rel = n * torch.finfo(X.dtype).eps
    one = torch.ones((), dtype=X.dtype, device=X.device)
    zero = torch.zeros_like(X[..., 0, 0])
    rows: list[list[Tensor]] = [[] for _ in range(n)]
    for j in range(n):
        d = X[..., j, j]
        for t in range(j):
            d = d - rows[j][t] * rows[j][t]
        pos = d > rel * X[..., j, j].detach()
        ljj = torch.where(pos, torch.sqrt(torch.where(pos, d, one)), zero)
        safe = torch.where(pos, ljj, one)
        rows[j].append(ljj)
        for i in range(j + 1, n):
            v = X[..., i, j]
            for t in range(j):
                v = v - rows[i][t] * rows[j][t]
            rows[i].append(torch.where(pos, v / safe, zero))
    full = [[rows[i][j] if j <= i else zero for j in range(n)] for i in range(n)]
    return torch.stack([torch.stack(r, dim=-1) for r in full], dim=-2)


def _square_root_filter(prep: _Prepared) -> FilterResult:
    r"""Square-root Kalman filter: propagates ``S_k`` with ``P_k = S_k S_kᵀ`` (no P is formed).

    Predict (QR of a (2n, n) array; ``L_Q L_Qᵀ = Q_k`` by :func:`_psd_factor`)::

        [ (A_k S)ᵀ ; L_Qᵀ ] = Θ [ S⁻ᵀ ; 0 ]   ⇒   S⁻ S⁻ᵀ = A_k S Sᵀ A_kᵀ + Q_k.

    Update on the whitened model (R' = I; unobserved components are zero rows of H' with
    unit variance, exactly as in the standard path), one scalar row h of H' at a time: with
    ``f = Sᵀ h`` the array ``[[1, fᵀ], [0, S]]`` is rotated by n Givens rotations of its
    columns (column 0 against column j, zeroing f_j) into ``[[x, 0], [k̄, S⁺]]``, so that
    ``x² = 1 + fᵀ f`` (innovation variance), ``m⁺ = m + k̄ e`` with ``e = (y' − hᵀ m) / x``,
    ``S⁺ S⁺ᵀ = P − P h hᵀ P / x²`` (S⁺ is square, not necessarily triangular) and the
    whitened log-likelihood core is ``−½ Σ (2 log x + e²)``.

    Givens rather than Householder in the update: a rotation with ``c = a / hypot(a, f_j)``
    multiplies, it does not subtract, so a posterior much smaller than the prior (predicted
    / measured variance ratio beyond 1/eps, e.g. q = 10 over a 5000 s gap with R = 1e-4 in
    float32) keeps its value when h is aligned with the factor (position observations of a
    kinematic model), where a Householder reflection cancels it to 0. Covariances are
    returned as ``S Sᵀ``, PSD by construction. ``torch.linalg.qr`` (reduced) and the
    rotations are differentiable.
    """
    A_steps = prep.A.unbind(-3)  # (*cb, n, n) each
    LQ_steps = _psd_factor(prep.Q).unbind(-3)
    Hw = prep.Hw  # (..., T or 1, m, n)
    h_single = Hw.shape[-3] == 1
    yw_steps = prep.yw.unbind(-2)  # (*mb, m) each
    c = prep.c
    m_dim, n = Hw.shape[-2], prep.A.shape[-1]
    mean, S = prep.m0, _psd_factor(prep.P0)
    means, facs, pmeans, pfacs, cores = [], [], [], [], []
    for k in range(prep.T):
        Ak = A_steps[k]
        mean = _matvec(Ak, mean)
        if c is not None:
            mean = mean + c[..., 0 if c.shape[-2] == 1 else k, :]
        AS = Ak @ S
        LQ = LQ_steps[k]
        lead = torch.broadcast_shapes(AS.shape[:-2], LQ.shape[:-2])
        pre_p = torch.cat([AS.mT.expand(*lead, n, n), LQ.mT.expand(*lead, n, n)], dim=-2)  # (2n, n)
        S = torch.linalg.qr(pre_p, mode="reduced").R.mT  # lower triangular S⁻
        pmeans.append(mean)
        pfacs.append(S)
        Hk = Hw[..., 0 if h_single else k, :, :]  # (.., m, n)
        F_ = Hk @ S  # rows f_iᵀ = h_iᵀ S  (*cb, m, n)
        cols = list(S.unbind(-1))  # columns S[:, j] (*cb, n)
        core = None
        for i in range(m_dim):
            f = F_[..., i, :].unbind(-1) if i == 0 else [torch.linalg.vecdot(Hk[..., i, :], col) for col in cols]
            x = torch.ones_like(f[0])
            kbar = torch.zeros_like(cols[0])
            for j in range(n):
                r = torch.hypot(x, f[j])
                cj, sj = x / r, f[j] / r
                kbar, cols[j] = cj[..., None] * kbar + sj[..., None] * cols[j], cj[..., None] * cols[j] - sj[..., None] * kbar
                x = r
            e = (yw_steps[k][..., i] - torch.linalg.vecdot(Hk[..., i, :], mean)) / x
            mean = mean + kbar * e[..., None]
            term = -0.5 * (2.0 * torch.log(x) + e * e)
            core = term if core is None else core + term
        S = torch.stack(cols, dim=-1)
        assert core is not None
        cores.append(core)
        means.append(mean)
        facs.append(S)
    mb = prep.mean_batch

    def covs(fs: list[Tensor]) -> Tensor:
        F_ = torch.stack(torch.broadcast_tensors(*fs), dim=-3)
        return _sym(F_ @ F_.mT)

    mean_t = torch.stack(torch.broadcast_tensors(*means), dim=-2)
    pmean_t = torch.stack(torch.broadcast_tensors(*pmeans), dim=-2)
    core = torch.stack(torch.broadcast_tensors(*cores), dim=-1)
    core = core.expand(*torch.broadcast_shapes(core.shape[:-1], mb), prep.T)
    return _finish(prep, mean_t, covs(facs), pmean_t, covs(pfacs), core)


# ----------------------------------------------------------------------------------------
# Associative scan
# ----------------------------------------------------------------------------------------

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


def _bcast_pair(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    return torch.broadcast_tensors(a, b) if a.shape[:-2] != b.shape[:-2] else (a, b)


def _filter_combine(a: Elems, b: Elems) -> Elems:
    """Särkkä & García-Fernández (2021), Lemma 7: combine filtering elements a (earlier), b (later)."""
    Ai, bi, Ci, ei, Ji = a
    Aj, bj, Cj, ej, Jj = b
    n = Ai.shape[-1]
    eye = torch.eye(n, dtype=Ai.dtype, device=Ai.device)
    X = eye + Ci @ Jj  # I + C_i J_j
    bi_col = (bi + _matvec(Ci, ej)).unsqueeze(-1)
    lead = torch.broadcast_shapes(X.shape[:-2], bi_col.shape[:-2])
    rhs = torch.cat([Ai.expand(*lead, n, n), Ci.expand(*lead, n, n), bi_col.expand(*lead, n, 1)], dim=-1)
    sol = torch.linalg.solve(X.expand(*lead, n, n), rhs)  # (I + C_i J_j)^{-1} [A_i, C_i, b_i + C_i η_j]
    A = Aj @ sol[..., :n]
    C = _sym(Aj @ sol[..., n : 2 * n] @ Aj.mT + Cj)
    b = _matvec(Aj, sol[..., 2 * n]) + bj
    ecol = (ej - _matvec(Jj, bi)).unsqueeze(-1)
    lead2 = torch.broadcast_shapes(X.shape[:-2], ecol.shape[:-2])
    rhs2 = torch.cat([(Jj @ Ai).expand(*lead2, n, n), ecol.expand(*lead2, n, 1)], dim=-1)
    sol2 = torch.linalg.solve(X.mT.expand(*lead2, n, n), rhs2)  # (I + J_j C_i)^{-1} [J_j A_i, η_j − J_j b_i]
    J = _sym(Ai.mT @ sol2[..., :n] + Ji)
    e = _matvec(Ai.mT, sol2[..., n]) + ei
    return A, b, C, e, J


def parallel_kalman_filter(
    y: Tensor,
    A: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    m0: Tensor,
    P0: Tensor,
    G: Tensor | None = None,
    u: Tensor | None = None,
    mask: Tensor | None = None,
    D: Tensor | None = None,
) -> FilterResult:
    r"""Kalman filter by associative scan (Särkkä & García-Fernández 2021), O(log T) depth.

    Same arguments and results as :func:`kalman_filter` (up to rounding). Step k's element
    (with whitened H', y' and R' = I, prior moments ``c_k = G_k u_k``, ``Q_k``; for k = 0 the
    prior is folded in: ``c_0 += A_0 m0``, ``Q_0 += A_0 P0 A_0ᵀ``, ``A_0 := 0``)::

        S = H' Q Hᵀ' + I,  K = Q H'ᵀ S⁻¹,  Ā = (I − K H') A,  b = c + K (y' − H' c),
        C = (I − K H') Q (I − K H')ᵀ + K Kᵀ,  η = Aᵀ H'ᵀ S⁻¹ (y' − H' c),  J = Aᵀ H'ᵀ S⁻¹ H' A.

    The scan yields filtered (b, C); predictions and the log-likelihood are then computed
    batched over all steps. Wins over the sequential loop when per-step Python overhead
    dominates (small batch, long T); loses when the batch already fills the cores.
    """
    prep = _prepare(y, A, Q, H, R, m0, P0, G, u, mask, D)
    n = prep.A.shape[-1]
    T = prep.T
    A_ = prep.A
    Qp = prep.Q
    cp = prep.c if prep.c is not None else torch.zeros((), dtype=A_.dtype, device=A_.device)
    A0 = A_[..., 0, :, :]
    P0m = _sym(A0 @ prep.P0 @ A0.mT + Qp[..., 0, :, :])
    m0m = _matvec(A0, prep.m0) + (cp[..., 0, :] if prep.c is not None else 0.0)
    lead = torch.broadcast_shapes(Qp.shape[:-3], P0m.shape[:-2])
    Qe = torch.cat([P0m.expand(*lead, n, n).unsqueeze(-3), Qp[..., 1:, :, :].expand(*lead, T - 1, n, n)], dim=-3)
    Ae = torch.cat([torch.zeros_like(A0).unsqueeze(-3), A_[..., 1:, :, :]], dim=-3)
    mb = prep.mean_batch
    cfull = cp.expand(*mb, T, n) if prep.c is not None else torch.zeros((*mb, T, n), dtype=A_.dtype, device=A_.device)
    ce = torch.cat([m0m.expand(*mb, n).unsqueeze(-2), cfull[..., 1:, :]], dim=-2)

    Hw, yw = prep.Hw, prep.yw
    HQ = Hw @ Qe  # (.., T, m, n)
    S = _sym(HQ @ Hw.mT) + torch.eye(Hw.shape[-2], dtype=Hw.dtype, device=Hw.device)
    LS = _cholesky(S)
    Kt = _cho_solve(LS, HQ)  # Kᵀ = S⁻¹ H' Q  (m, n)
    K = Kt.mT
    IKH = torch.eye(n, dtype=A_.dtype, device=A_.device) - K @ Hw
    v = yw - _matvec(Hw, ce)
    b = ce + _matvec(K, v)
    C = _sym(IKH @ Qe @ IKH.mT + K @ Kt)
    Abar = IKH @ Ae
    HA = Hw @ Ae  # (.., T, m, n)
    Sinv_HA = _cho_solve(LS, HA)
    J = _sym(HA.mT @ Sinv_HA)
    Sinv_v = _cho_solve(LS, v.unsqueeze(-1)).squeeze(-1)
    eta = _matvec(HA.mT, Sinv_v)

    elems = (Abar, b, C, eta, J)
    tm = [-3, -2, -3, -2, -3]
    moved = tuple(x.movedim(d, 0) for x, d in zip(elems, tm))
    scanned = _scan(_filter_combine, moved)
    mean = scanned[1].movedim(0, -2)
    cov = scanned[2].movedim(0, -3)

    # Predictions batched over steps, then the log-likelihood from whitened innovations.
    prev_m = torch.cat([prep.m0.unsqueeze(-2), mean[..., :-1, :]], dim=-2)
    lead_c = torch.broadcast_shapes(prep.P0.shape[:-2], cov.shape[:-3])
    prev_P = torch.cat([prep.P0.expand(*lead_c, n, n).unsqueeze(-3), cov[..., :-1, :, :].expand(*lead_c, T - 1, n, n)], dim=-3)
    pred_mean = _matvec(A_, prev_m)
    if prep.c is not None:
        pred_mean = pred_mean + prep.c
    pred_cov = _sym(A_ @ prev_P @ A_.mT + Qp)
    HP = Hw @ pred_cov
    Sw = _sym(HP @ Hw.mT) + torch.eye(Hw.shape[-2], dtype=Hw.dtype, device=Hw.device)
    Lw = _cholesky(Sw)
    vw = yw - _matvec(Hw, pred_mean)
    z = _solve_lower(Lw, vw.unsqueeze(-1)).squeeze(-1)
    logdet = 2.0 * torch.log(torch.diagonal(Lw, dim1=-2, dim2=-1)).sum(-1)
    core = -0.5 * (logdet + (z * z).sum(-1))
    return _finish(prep, mean, cov, pred_mean, pred_cov, core)


# ----------------------------------------------------------------------------------------
# RTS smoother
# ----------------------------------------------------------------------------------------


def _smoother_elements(result: FilterResult, A: Tensor | None, Q: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """Per-step (E_k, g_k, C_k) with ``x_k | x_{k+1}, y ~ N(g_k + E_k x_{k+1}, C_k)``.

    E_k = P_k A_{k+1}ᵀ (P⁻_{k+1})⁻¹ (a Cholesky solve), g_k = m_k − E_k m⁻_{k+1},
    C_k = (I − E_k A_{k+1}) P_k (I − E_k A_{k+1})ᵀ + E_k Q_{k+1} E_kᵀ (Joseph form of
    P_k − E_k P⁻_{k+1} E_kᵀ: a sum of PSD terms). The last step has E = 0, g = m, C = P.
    """
    A = result.transition if A is None else A
    Q = result.process_noise if Q is None else Q
    mf, Pf, pm, Pp = result.mean, result.cov, result.pred_mean, result.pred_cov
    n, T = mf.shape[-1], mf.shape[-2]
    check_matrix(A, "A", rows=n, cols=n)
    check_matrix(Q, "Q", rows=n, cols=n)
    # Work at the covariance batch (filtered covariances are usually broadcast views).
    A1 = A[..., 1:, :, :] if A.dim() >= 3 and A.shape[-3] == T else A
    Q1 = Q[..., 1:, :, :] if Q.dim() >= 3 and Q.shape[-3] == T else Q
    P_k = Pf[..., :-1, :, :]
    Pp1 = Pp[..., 1:, :, :]
    AP = A1 @ P_k  # A_{k+1} P_k
    L = _cholesky(Pp1) if n <= _SMALL else torch.linalg.cholesky(Pp1)
    E = _cho_solve(L, AP).mT  # P_k A_{k+1}ᵀ (P⁻_{k+1})⁻¹
    eye = torch.eye(n, dtype=mf.dtype, device=mf.device)
    IEA = eye - E @ A1
    C = _sym(IEA @ P_k @ IEA.mT + E @ Q1 @ E.mT)
    g = mf[..., :-1, :] - _matvec(E, pm[..., 1:, :])
    lead = E.shape[:-3]
    E_all = torch.cat([E, torch.zeros((*lead, 1, n, n), dtype=E.dtype, device=E.device)], dim=-3)
    lead_c = torch.broadcast_shapes(C.shape[:-3], Pf.shape[:-3])
    C_all = torch.cat([C.expand(*lead_c, T - 1, n, n), Pf[..., -1:, :, :].expand(*lead_c, 1, n, n)], dim=-3)
    lead_g = torch.broadcast_shapes(g.shape[:-2], mf.shape[:-2])
    g_all = torch.cat([g.expand(*lead_g, T - 1, n), mf[..., -1:, :].expand(*lead_g, 1, n)], dim=-2)
    return E_all, g_all, C_all


def rts_smoother(result: FilterResult, A: Tensor | None = None, Q: Tensor | None = None) -> SmootherResult:
    r"""Rauch–Tung–Striebel smoother for time-varying (A_k, Q_k), sequential backward pass.

    ``m^s_k = m_k + E_k (m^s_{k+1} − m⁻_{k+1})``, ``P^s_k = P_k + E_k (P^s_{k+1} − P⁻_{k+1}) E_kᵀ``,
    evaluated as ``m^s_k = g_k + E_k m^s_{k+1}``, ``P^s_k = C_k + E_k P^s_{k+1} E_kᵀ`` with the
    PSD-preserving (E, g, C) of the smoothing elements computed batched over all steps.

    Args:
        result: a :class:`FilterResult` (mean, cov, pred_mean, pred_cov over T steps).
        A, Q: (..., T, n, n) the transitions/noises the filter used; default: those stored
            in ``result`` (``result.transition``, ``result.process_noise``).

    Returns:
        :class:`SmootherResult` with mean (..., T, n), cov (..., T, n, n), gain (..., T, n, n).
    """
    E, g, C = _smoother_elements(result, A, Q)
    T = g.shape[-2]
    Es, gs, Cs = E.unbind(-3), g.unbind(-2), C.unbind(-3)
    ms, Ps = gs[-1], Cs[-1]
    means, covs = [ms], [Ps]
    for k in range(T - 2, -1, -1):
        ms = gs[k] + _matvec(Es[k], ms)
        Ps = _sym(Cs[k] + Es[k] @ Ps @ Es[k].mT)
        means.append(ms)
        covs.append(Ps)
    mean = torch.stack(means[::-1], dim=-2)
    cov = torch.stack(covs[::-1], dim=-3)
    batch = torch.broadcast_shapes(mean.shape[:-2], cov.shape[:-3], result.mean.shape[:-2])
    n = mean.shape[-1]
    return SmootherResult(mean.expand(*batch, T, n), cov.expand(*batch, T, n, n), E.expand(*batch, T, n, n))


def _smoother_combine(a: Elems, b: Elems) -> Elems:
    """Combine smoothing elements a (earlier) with b (later): x_i | x_{j+1}."""
    Ei, gi, Ci = a
    Ej, gj, Cj = b
    return Ei @ Ej, _matvec(Ei, gj) + gi, _sym(Ei @ Cj @ Ei.mT + Ci)


def parallel_rts_smoother(result: FilterResult, A: Tensor | None = None, Q: Tensor | None = None) -> SmootherResult:
    """RTS smoother by a reverse associative scan of (E, g, C) (Särkkä & García-Fernández 2021).

    Same arguments and results as :func:`rts_smoother` (up to rounding), O(log T) depth.
    """
    E, g, C = _smoother_elements(result, A, Q)
    T, n = g.shape[-2], g.shape[-1]
    batch = torch.broadcast_shapes(E.shape[:-3], g.shape[:-2], C.shape[:-3])
    moved = (E.expand(*batch, T, n, n).movedim(-3, 0), g.expand(*batch, T, n).movedim(-2, 0),
             C.expand(*batch, T, n, n).movedim(-3, 0))
    Es, gs, Cs = associative_scan(_smoother_combine, moved, reverse=True)
    mean = gs.movedim(0, -2)
    cov = Cs.movedim(0, -3)
    full = torch.broadcast_shapes(batch, result.mean.shape[:-2])
    return SmootherResult(mean.expand(*full, T, n), cov.expand(*full, T, n, n), E.expand(*full, T, n, n))
