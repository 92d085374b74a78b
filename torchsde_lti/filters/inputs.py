r"""Input preparation shared by the sequential, square-root and scan filters.

Conventions of every filter in :mod:`torchsde_lti.filters` (batch dims ``...`` lead and
broadcast, numpy rules, right-aligned)::

    y (..., T, m)   A, Q (..., T, n, n)   H (..., T, m, n)   R (..., T, m, m)
    m0 (..., n)     P0 (..., n, n)        G (..., T, n, p)   u (..., T, p)
    mask (..., T) or (..., T, m) bool (True = observed; with T == m a (..., T, T) mask with
         fewer dims than y is refused as ambiguous: write (..., T, 1) or y's dims)

Per-step arrays may omit or size-1 the T axis (a constant ``H (m, n)`` is fine); a
per-batch constant matrix needs its T axis as 1, e.g. ``A (B, 1, n, n)``.

Three stages: argument checks (shapes always; values while value checks are on, and then
Q, R, P0 taken as their symmetric parts: one function, one symmetric gradient), masking
(a NaN in y or mask False = not observed: y is sanitised with ``where(observed, y, 0)``,
unobserved components get a zero row in H and a decoupled unit variance in R, so every
step keeps static shapes and the log-likelihood counts observed components only), and
whitening with the Cholesky factor of the masked R (R' = I).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import torch
from torch import Tensor

from torchsde_lti.core.linalg import cholesky, matvec, solve_lower, sym
from torchsde_lti.core.validation import (
    as_float_tensors,
    broadcast_batch,
    check_finite,
    check_matrix,
    check_no_inf,
    check_symmetric_psd,
    checks_values,
    shape_str,
    tracing,
)
from torchsde_lti.filters.results import FilterResult

__all__ = [
    "LOG_2PI",
    "FilterInputs",
    "PreparedInputs",
    "assemble_result",
    "check_mask",
    "check_time_axis",
    "complete_from_filtered",
    "mask_observation_model",
    "observed_components",
    "own_extent",
    "pad_dims",
    "prepare_inputs",
    "symmetric_part",
    "whiten",
]

LOG_2PI = math.log(2.0 * math.pi)


_REQUIRED, _OPTIONAL = ("y", "A", "Q", "H", "R", "m0", "P0"), ("G", "u", "mask", "D")
#: The arguments of every filter, as given: y, A, Q, H, R, m0, P0 and the optional G, u,
#: mask, D (default None); shapes in the module docstring.
FilterInputs = NamedTuple(  # type: ignore[misc]
    "FilterInputs", [(k, Tensor) for k in _REQUIRED] + [(k, Optional[Tensor]) for k in _OPTIONAL]
)
FilterInputs.__new__.__defaults__ = (None,) * len(_OPTIONAL)


class PreparedInputs(NamedTuple):
    """Checked, masked, whitened and broadcast filter inputs (cb: covariance batch, mb: mean batch)."""

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


class _Checked(NamedTuple):
    args: FilterInputs  # converted to the common float dtype and device, y − D u applied, mask (..., T, 1 or m)
    c: Tensor | None  # (..., T, n) control term G u
    T: int
    n: int


def pad_dims(x: Tensor, ndim: int) -> Tensor:
    """Prepend size-1 dims so that x has ``ndim`` dims."""
    return x.reshape((1,) * (ndim - x.dim()) + tuple(x.shape)) if x.dim() < ndim else x


def check_mask(mask: Tensor | None, T: int, m: int, device: torch.device, y_ndim: int) -> Tensor | None:
    """A bool mask (..., T) or (..., T, m) (True = observed) as (..., T, 1 or m) on ``device``;
    ValueError naming its shape or dtype otherwise. None stays None. ``y_ndim``: the number of
    dimensions of y (..., T, m). When T == m a mask (..., T, T) fits both forms: it is read per
    component if it has y's number of dimensions (or more), and refused otherwise (write a
    per-step mask as (..., T, 1), a per-component one with y's leading dimensions); a mask
    (..., T, 1) with y's number of dimensions is read as such also when T = 1."""
    if mask is None:
        return None
    mask = torch.as_tensor(mask, device=device)
    if mask.dtype != torch.bool:
        raise ValueError(f"mask must be a bool tensor, got dtype {mask.dtype}")
    # (..., T, 1) with y's dims is already in form (with T = 1 it also reads as (..., T))
    in_form = mask.dim() >= max(2, y_ndim) and mask.shape[-2] == T and mask.shape[-1] == 1
    per_component = mask.dim() >= 2 and mask.shape[-2] == T and (mask.shape[-1] == m or in_form)
    per_step = mask.dim() >= 1 and mask.shape[-1] == T
    if per_component and per_step and mask.dim() < y_ndim:
        raise ValueError(
            f"mask of shape {shape_str(mask)} is ambiguous with T = m = {T}: write a per-step mask as "
            f"(..., {T}, 1), a per-component mask with y's {y_ndim} dimensions (..., {T}, {m})"
        )
    if not per_component and per_step:
        mask = mask.unsqueeze(-1)  # (..., T) -> (..., T, 1)
    if mask.dim() < 2 or mask.shape[-2] != T or mask.shape[-1] not in (1, m):
        raise ValueError(f"mask must have shape (..., {T}) or (..., {T}, {m}), got shape {shape_str(mask)}")
    return mask


def check_time_axis(x: Tensor, name: str, T: int, source: str) -> None:
    """ValueError naming ``name`` unless the per-step matrix x (..., [T,] r, c) has no time
    axis (2 dims) or one of length 1 or T; ``source`` says where T comes from ("y has T=5 …")."""
    if x.dim() >= 3 and x.shape[-3] not in (1, T):
        raise ValueError(
            f"{name} has {x.shape[-3]} steps on its time axis (shape {shape_str(x)}) but {source}; "
            "give a per-batch constant as (..., 1, r, c)"
        )


def own_extent(x: Tensor) -> Tensor:
    """x (..., r, c) without its broadcast (stride-0) leading dims: each of size 1 (a view of the
    same values; it broadcasts back to x's shape). A shared matrix passed expanded, e.g. one
    time grid's A (T, n, n) as (B, T, n, n), is then worked on once, not B times."""
    if x.dim() <= 2 or all(st != 0 or sz == 1 for sz, st in zip(x.shape[:-2], x.stride())):
        return x
    return x[tuple(slice(0, 1) if st == 0 and sz > 1 else slice(None) for sz, st in zip(x.shape[:-2], x.stride()))]


def symmetric_part(x: Tensor) -> Tensor:
    """``(X + Xᵀ) / 2`` of x (..., k, k), formed at x's own extent (:func:`own_extent`) and
    expanded again: a shared matrix passed as a broadcast view (B, T, k, k) costs one k × k
    matrix, not B·T. Its gradient is the symmetric part of the incoming one, whatever an
    algorithm does with the upper and lower triangles."""
    return x if x.dim() < 2 else sym(own_extent(x)).expand(x.shape)


def _batched(x: Tensor | None) -> bool:
    """Whether the per-step matrix x (..., [T,] r, c) has batch dims (ahead of its time axis)."""
    return x is not None and x.dim() > 3


def _check_arguments(args: FilterInputs, validate_args: bool = True) -> _Checked:
    """Shapes (and, with ``validate_args``, values) of every argument; c = G u."""
    values = checks_values(validate_args)
    t = as_float_tensors(**{k: v for k, v in args._asdict().items() if k != "mask"})
    mask = args.mask
    y, A, Q, H, R, m0, P0, G, u, D = (t[k] for k in ("y", "A", "Q", "H", "R", "m0", "P0", "G", "u", "D"))
    device = y.device

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
        # Feedthrough y = H x + D u + r: filter y − D u (formed below, once the batches are checked).
        check_matrix(D, "D", rows=m)
        pD = D.shape[-1]
        if u.dim() < 2 or u.shape[-1] != pD or u.shape[-2] not in (1, T):
            raise ValueError(
                f"u must have shape (..., T={T}, {pD}) to match D {shape_str(D)}, got shape {shape_str(u)}"
            )
        check_time_axis(D, "D", T, f"y has T={T} (shape {shape_str(y)})")
        if values:
            check_finite(D, "D")
    if G is not None and u is not None:
        check_matrix(G, "G", rows=n)
        p = G.shape[-1]
        if u.dim() < 2 or u.shape[-1] != p:
            raise ValueError(f"u must have shape (..., T, {p}) to match G {shape_str(G)}, got shape {shape_str(u)}")
        if u.shape[-2] not in (1, T):
            raise ValueError(f"u has {u.shape[-2]} steps (shape {shape_str(u)}) but y has T={T}")
        check_time_axis(G, "G", T, f"y has T={T} (shape {shape_str(y)})")
    if values and u is not None:
        check_finite(u, "u")
    mask = check_mask(mask, T, m, device, y.dim())

    # Per-step arrays: check their T axis; then every batch, before any arithmetic combines them.
    for name, x in (("A", A), ("Q", Q), ("H", H), ("R", R)):
        check_time_axis(x, name, T, f"y has T={T} (shape {shape_str(y)})")
    per_step = [
        (k, x.shape[:-3]) for k, x in (("A", A), ("Q", Q), ("H", H), ("R", R), ("G", G), ("D", D)) if _batched(x)
    ]
    other = [("m0", m0.shape[:-1]), ("P0", P0.shape[:-2]), *([] if mask is None else [("mask", mask.shape[:-2])])]
    broadcast_batch([("y", y.shape[:-2]), *per_step, *other, *([] if u is None else [("u", u.shape[:-2])])])
    c = None
    if u is not None:
        if D is not None:
            y = y - matvec(D, u)  # (NaN stays NaN, so missing data keep their meaning)
        if G is not None:
            c = matvec(G, u)  # (..., T, n)

    # the model's matrices at their own extent (their shapes checked above): values are checked
    # and the covariance recursion runs at their batch (once for a shared grid passed expanded
    # over the tracks); every output broadcasts back to the full batch
    A, Q, H, R, P0 = (own_extent(x) for x in (A, Q, H, R, P0))
    if values:
        check_no_inf(y, "y")
        check_finite(A, "A")
        check_finite(H, "H")
        check_finite(m0, "m0")
        check_symmetric_psd(Q, "Q")
        check_symmetric_psd(R, "R")
        check_symmetric_psd(P0, "P0")
        if bool((torch.linalg.cholesky_ex(R).info != 0).any()):
            raise ValueError(f"R must be positive definite (Cholesky failed; shape {shape_str(R)})")
    if validate_args:  # (also while traced: no value is read)
        Q, R, P0 = symmetric_part(Q), symmetric_part(R), symmetric_part(P0)
    return _Checked(FilterInputs(y, A, Q, H, R, m0, P0, G, u, mask, D), c, T, n)


def observed_components(y: Tensor, mask: Tensor | None) -> tuple[Tensor | None, Tensor]:
    """(obs, y0): the observed components (NaN in y or mask False = missing; None when all
    are observed) and y with every missing entry replaced by 0, so no NaN reaches any
    arithmetic or gradient. y (..., T, m); mask (..., T, 1 or m) bool or None."""
    # Observed components: NaN in y or mask False.
    nan = torch.isnan(y)
    obs: Tensor | None = None
    if tracing() or bool(nan.any()):  # traced: always the masked path (same values)
        obs = ~nan
    if mask is not None:
        obs = mask if obs is None else (obs & mask)
    y0 = y if obs is None else torch.where(obs, y, torch.zeros((), dtype=y.dtype, device=y.device))
    return obs, y0


def mask_observation_model(H: Tensor, R: Tensor, obs: Tensor | None) -> tuple[Tensor, Tensor]:
    """(Hm, Rm): unobserved components get a zero row in H and a decoupled unit variance in R,
    so every step keeps static shapes. H (..., T or 1, m, n), R (..., T or 1, m, m), obs
    (..., T, m) bool padded to H's number of dims, or None."""
    if obs is None:
        return H, R
    m = R.shape[-1]
    o = obs.to(H.dtype)
    o = o.expand(*o.shape[:-1], m)
    eye_m = torch.eye(m, dtype=H.dtype, device=H.device)
    Hm = H * o.unsqueeze(-1)
    Rm = R * (o.unsqueeze(-1) * o.unsqueeze(-2)) + torch.diag_embed(1.0 - o) * eye_m
    return Hm, Rm


def whiten(H: Tensor, R: Tensor, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(H', y', Σ log diag L) with L Lᵀ = R, H' = L⁻¹ H, y' = L⁻¹ y: the whitened model has
    R' = I. H (..., m, n), R (..., m, m) symmetric PD, y (..., m)."""
    LR = cholesky(R)
    Hw = solve_lower(LR, H)
    yw = solve_lower(LR, y.unsqueeze(-1)).squeeze(-1)
    return Hw, yw, torch.log(torch.diagonal(LR, dim1=-2, dim2=-1)).sum(-1)


def prepare_inputs(args: FilterInputs, validate_args: bool = True) -> PreparedInputs:
    """Check, mask, broadcast and whiten the filter arguments (shapes: :mod:`torchsde_lti.filters`).

    With a feedthrough D (..., [T,] m, p) and inputs u, the observations become ``y − D u``.

    The covariance path's batch excludes y (and u) unless data are missing, so with a shared
    dt grid and no missing data the covariance recursion runs once for all tracks.
    """
    checked = _check_arguments(args, validate_args)
    y, A, Q, H, R, m0, P0 = checked.args[:7]
    c = checked.c
    T, n = checked.T, checked.n
    obs, y0 = observed_components(y, checked.args.mask)

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

    A = pad_dims(A, nd + 3).expand(*cov_bt, n, n)
    Q = pad_dims(Q, nd + 3).expand(*cov_bt, n, n)
    # H, R and everything derived from them keep their own (broadcastable) shapes.
    H = pad_dims(H, nd + 3)
    R = pad_dims(R, nd + 3)
    P0 = pad_dims(P0, nd + 2).expand(*cb, n, n)
    m0 = pad_dims(m0, nd + 1).expand(*mean_bt[:-1], n)
    y0 = pad_dims(y0, nd + 2)
    if c is not None:
        c = pad_dims(c, nd + 2)

    o = None if obs is None else pad_dims(obs, nd + 2)
    Hw, yw, log_det = whiten(*mask_observation_model(H, R, o), y0)
    return PreparedInputs(A, Q, Hw, yw, c, m0, P0, H, R, y0, obs, log_det, mean_bt[:-1], T)


def assemble_result(
    prep: PreparedInputs,
    filtered: tuple[Tensor, Tensor],
    predicted: tuple[Tensor, Tensor],
    step_ll_core: Tensor,
    innovations: tuple[Tensor, Tensor] | None = None,
) -> FilterResult:
    """The :class:`FilterResult` of an algorithm's moments: filtered and predicted (mean
    (..., T, n), cov (..., T, n, n)) pairs, the whitened per-step log-likelihood core
    (..., T), and optionally the innovations and their covariances (else computed here, in
    the original space); log-likelihood constants added, outputs broadcast to the full batch."""
    (mean, cov), (pred_mean, pred_cov) = filtered, predicted
    innovation, innovation_cov = (None, None) if innovations is None else innovations
    mb, T = prep.mean_batch, prep.T
    n, m = mean.shape[-1], prep.yw.shape[-1]
    if innovation is None or innovation_cov is None:
        innovation = prep.y0 - matvec(prep.H, pred_mean)
        innovation_cov = sym(prep.H @ pred_cov @ prep.H.mT + prep.R)
    if prep.obs is None:
        n_obs = torch.full((), float(m), dtype=mean.dtype, device=mean.device)
        observed = torch.ones((*mb, T, m), dtype=torch.bool, device=mean.device)
    else:
        o = pad_dims(prep.obs, len(mb) + 2).expand(*mb, T, m)
        innovation = innovation * o
        n_obs = o.to(mean.dtype).sum(-1)
        observed = o
    step_ll = step_ll_core - 0.5 * n_obs * LOG_2PI - prep.log_det_chol_R
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
        control=(mean.new_zeros(()) if prep.c is None else prep.c).expand(*mb, T, n),
    )


def complete_from_filtered(prep: PreparedInputs, mean: Tensor, cov: Tensor) -> FilterResult:
    """The :class:`FilterResult` of an algorithm that yields the filtered moments alone, mean
    (..., T, n) and cov (..., T, n, n): the predictions ``m⁻_k = A_k m_{k−1} + c_k``,
    ``P⁻_k = A_k P_{k−1} A_kᵀ + Q_k`` (step 0 from the prior) and the log-likelihood from the
    whitened innovations ``z_k = L_k⁻¹ (y'_k − H'_k m⁻_k)``, ``L_k L_kᵀ = H'_k P⁻_k H'_kᵀ + I``,
    all batched over the steps (an unobserved component has a zero row of H' and y': it adds 0)."""
    n = mean.shape[-1]
    # (the prior put in front, the last step dropped: no size-(T − 1) tensor, which a traced
    # program with a dynamic T would have to guard against being 1)
    prev_m = torch.cat([prep.m0.unsqueeze(-2), mean], dim=-2)[..., :-1, :]
    lead = torch.broadcast_shapes(prep.P0.shape[:-2], cov.shape[:-3])
    prev_P = torch.cat([prep.P0.expand(*lead, n, n).unsqueeze(-3), cov.expand(*lead, -1, n, n)], dim=-3)[..., :-1, :, :]
    pred_mean = matvec(prep.A, prev_m)
    if prep.c is not None:
        pred_mean = pred_mean + prep.c
    pred_cov = sym(prep.A @ prev_P @ prep.A.mT + prep.Q)
    Hw = prep.Hw
    S = sym(Hw @ pred_cov @ Hw.mT) + torch.eye(Hw.shape[-2], dtype=Hw.dtype, device=Hw.device)
    L = cholesky(S)
    z = solve_lower(L, (prep.yw - matvec(Hw, pred_mean)).unsqueeze(-1)).squeeze(-1)
    logdet = 2.0 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    return assemble_result(prep, (mean, cov), (pred_mean, pred_cov), -0.5 * (logdet + (z * z).sum(-1)))
