r"""Input preparation shared by the sequential, square-root and scan filters.

Conventions of every filter in :mod:`torchsde_lti.filters` (batch dims ``...`` lead and
broadcast, numpy rules, right-aligned)::

    y (..., T, m)   A, Q (..., T, n, n)   H (..., T, m, n)   R (..., T, m, m)
    m0 (..., n)     P0 (..., n, n)        G (..., T, n, p)   u (..., T, p)
    mask (..., T) or (..., T, m) bool (True = observed; with T == m a (..., T, T) mask with
         fewer dims than y is refused as ambiguous: write (..., T, 1) or y's dims)

Per-step arrays may omit or size-1 the T axis (a constant ``H (m, n)`` is fine); a
per-batch constant matrix needs its T axis as 1, e.g. ``A (B, 1, n, n)``.

Three stages, the same for every algorithm: argument checks (shapes always; values with
``validate_args``, which only raises), masking (a NaN in y or mask False = not observed: y is
sanitised with ``where(observed, y, 0)``, unobserved components get a zero row in H and a
decoupled unit variance in R, so every step keeps static shapes and the log-likelihood counts
observed components only; always, so the route never depends on y's values), and whitening
with the Cholesky factor of the masked R (R' = I). Every algorithm reads Q, R and P0 through
their symmetric parts ``(X + Xᵀ) / 2`` (formed here, once): the function computed, and its
gradient (a symmetric matrix), are the same under every ``algorithm=`` and ``validate_args``.
The prepared inputs are laid out batch-last (:mod:`~torchsde_lti.filters.layout`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core.linalg import matvec
from torchsde_lti.core.validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_matrix,
    check_no_inf,
    check_symmetric_psd,
    checks_values,
    common_float_dtype,
    shape_str,
)
from torchsde_lti.filters.layout import _factor, batch_first, batch_last, lower_solve, mm, mv, psd_cholesky, sym, tr
from torchsde_lti.filters.noise import GAUSSIAN, NoiseModel
from torchsde_lti.filters.results import FilterResult

__all__ = [
    "LOG_2PI",
    "FilterInputs",
    "PreparedInputs",
    "as_float_tensors",
    "assemble_result",
    "check_mask",
    "check_time_axis",
    "complete_from_filtered",
    "mask_observation_model",
    "observed_components",
    "observed_count",
    "own_extent",
    "pad_dims",
    "prepare_inputs",
    "whiten",
]

LOG_2PI = math.log(2.0 * math.pi)


def as_float_tensors(**named: object) -> dict[str, Tensor | None]:
    """Every non-None argument as a floating tensor of their common dtype, on the device of the
    first tensor given (the keyword names are the names in error messages); None stays None."""
    tensors = [v for v in named.values() if isinstance(v, Tensor)]
    dtype = common_float_dtype(*tensors)
    device = tensors[0].device if tensors else None
    return {k: None if v is None else as_float_tensor(v, k, dtype, device) for k, v in named.items()}


class FilterInputs(NamedTuple):
    """The arguments of every filter, as given (shapes in the module docstring)."""

    y: Tensor  # (..., T, m)
    A: Tensor  # (..., T, n, n)
    Q: Tensor  # (..., T, n, n)
    H: Tensor  # (..., T, m, n)
    R: Tensor  # (..., T, m, m)
    m0: Tensor  # (..., n)
    P0: Tensor  # (..., n, n)
    G: Tensor | None = None  # (..., T, n, p)
    u: Tensor | None = None  # (..., T, p)
    mask: Tensor | None = None  # (..., T) or (..., T, m) bool
    D: Tensor | None = None  # (..., [T,] m, p)


class PreparedInputs(NamedTuple):
    """Checked, symmetrised, masked and whitened filter inputs, batch-last: every tensor's batch
    dims (``*b``) are its own, left-padded to ``len(mean_batch)`` dims (size 1 where shared), so
    they broadcast to the call's batch ``mean_batch``."""

    A: Tensor  # (T, n, n, *b) (a broadcast view where one matrix serves every step)
    Q: Tensor  # (T, n, n, *b) symmetric part (idem)
    Hw: Tensor  # (T, m, n, *b) whitened, masked observation matrix
    yw: Tensor  # (T, m, *b) whitened, sanitised observations
    c: Tensor | None  # (T, n, *b) control term G u (idem)
    m0: Tensor  # (n, *b)
    P0: Tensor  # (n, n, *b) symmetric part
    H: Tensor  # (T or 1, m, n, *b) as given (for innovations)
    R: Tensor  # (T or 1, m, m, *b) symmetric part, unmasked (for innovation covariances)
    y0: Tensor  # (T, m, *b) sanitised y
    obs: Tensor  # (T, m, *b) bool, the observed components
    log_det_chol_R: Tensor  # (T, *b) Σ log diag of the whitening factor (observed part)
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


def _given(converted: dict[str, Tensor | None], name: str) -> Tensor:
    """A required argument after conversion (never None)."""
    x = converted[name]
    if x is None:
        raise TypeError(f"{name} is required, got None")
    return x


def _check_arguments(args: FilterInputs, validate_args: bool = True) -> _Checked:
    """Shapes (and, with ``validate_args``, values) of every argument; c = G u."""
    values = checks_values(validate_args)
    t = as_float_tensors(**{k: v for k, v in args._asdict().items() if k != "mask"})
    mask = args.mask
    y, A, Q, H, R, m0, P0 = (_given(t, k) for k in ("y", "A", "Q", "H", "R", "m0", "P0"))
    G, u, D = t["G"], t["u"], t["D"]
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
        (k, x.shape[:-3])
        for k, x in (("A", A), ("Q", Q), ("H", H), ("R", R), ("G", G), ("D", D))
        if x is not None and x.dim() > 3
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
    return _Checked(FilterInputs(y, A, Q, H, R, m0, P0, G, u, mask, D), c, T, n)


def observed_components(y: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """(obs, y0): the observed components (NaN in y or mask False = missing), (..., T, m) bool,
    and y with every missing entry replaced by 0, so no NaN reaches any arithmetic or gradient.
    y (..., T, m); mask (..., T, 1 or m) bool or None. Nothing is read to the host."""
    obs = ~torch.isnan(y)
    if mask is not None:
        obs = obs & mask
    return obs, torch.where(obs, y, torch.zeros((), dtype=y.dtype, device=y.device))


def mask_observation_model(H: Tensor, R: Tensor, obs: Tensor, at: int = 0) -> tuple[Tensor, Tensor]:
    """(Hm, Rm): unobserved components get a zero row in H and a decoupled unit variance in R,
    so every step keeps static shapes. Batch-last: H (…, m, n, *b), R (…, m, m, *b), obs
    (…, m, *b) bool; ``at``: the position of the (m, ·) dims (0 for one step, 1 for a sequence,
    whose leading dim is the steps'). An observed component's entries are kept as they are."""
    row, col = obs.unsqueeze(at + 1), obs.unsqueeze(at)  # (…, m, 1, *b), (…, 1, m, *b)
    m = R.shape[at]
    eye = torch.eye(m, dtype=R.dtype, device=R.device).reshape(m, m, *[1] * (R.dim() - at - 2))
    return torch.where(row, H, 0.0), torch.where(row & col, R, eye)


def whiten(H: Tensor, R: Tensor, y: Tensor, at: int = 0) -> tuple[list[Tensor], list[Tensor], Tensor]:
    """(rows of H', values of y', Σ log L_jj) with L Lᵀ = R (the factor of
    :func:`~torchsde_lti.filters.layout.psd_cholesky`), H' = L⁻¹ H, y' = L⁻¹ y by forward
    substitution: the whitened model has R' = I. Batch-last: H (…, m, n, *b), R (…, m, m, *b)
    symmetric PD, y (…, m, *b) -> m rows (…, n, *b), m values (…, *b) and (…, *b); ``at``: the
    position of the (m, ·) dims (0 for one step, 1 for a sequence). Elementwise over the batch,
    on the factor's entries (no factor is assembled)."""
    low, inv = _factor(R, at, diagonal=False)  # L_jt (t < j) and 1 / L_jj, each (…, *b)
    against_h = (lambda x: x.unsqueeze(at)) if at else (lambda x: x)  # noqa: E731  ((…, 1, *b) against a row)
    hw: list[Tensor] = []
    yw: list[Tensor] = []
    for j, (h, v) in enumerate(zip(H.unbind(at), y.unbind(at))):
        for t in range(j):
            h = h - against_h(low[j][t]) * hw[t]
            v = v - low[j][t] * yw[t]
        hw.append(h * against_h(inv[j]))
        yw.append(v * inv[j])
    return hw, yw, -torch.log(torch.stack(inv)).sum(0)


def prepare_inputs(args: FilterInputs, validate_args: bool = True) -> PreparedInputs:
    """Check, symmetrise, mask and whiten the filter arguments (shapes: :mod:`torchsde_lti.filters`)
    and lay them out batch-last. With a feedthrough D (..., [T,] m, p) and inputs u, the
    observations become ``y − D u``."""
    checked = _check_arguments(args, validate_args)
    y, A, Q, H, R, m0, P0 = checked.args[:7]
    c, T = checked.c, checked.T
    obs, y0 = observed_components(y, checked.args.mask)
    named: list[tuple[str, tuple[int, ...]]] = [("A", A.shape[:-2]), ("Q", Q.shape[:-2]), ("H", H.shape[:-2])]
    named += [("R", R.shape[:-2]), ("P0", (*P0.shape[:-2], 1)), ("T", (T,)), ("y", y.shape[:-1])]
    named += [("mask", obs.shape[:-1]), ("m0", (*m0.shape[:-1], 1))] + ([] if c is None else [("u", c.shape[:-1])])
    batch_t = broadcast_batch(named)  # (*mean batch, T)
    if batch_t[-1] != T:
        raise ValueError(f"time axes do not broadcast to T={T}: {named}")
    nd = len(batch_t) - 1
    H, R = batch_last(H, 2, nd), sym(batch_last(R, 2, nd), 1)  # (T or 1, m, ·, *b)
    obs, y0 = batch_last(obs, 1, nd), batch_last(y0, 1, nd)  # (T, m, *b)
    h_rows, y_rows, log_det = whiten(*mask_observation_model(H, R, obs, 1), y0, 1)
    Hw, yw = torch.stack(h_rows, 1), torch.stack(y_rows, 1)
    steps = lambda x: x.expand(T, *x.shape[1:])  # noqa: E731  (a shared matrix: a view over the steps)
    return PreparedInputs(
        steps(batch_last(A, 2, nd)),
        steps(sym(batch_last(Q, 2, nd), 1)),
        Hw,
        yw,
        None if c is None else steps(batch_last(c, 1, nd)),
        batch_last(m0, 1, nd, time=False),
        sym(batch_last(P0, 2, nd, time=False)),
        H,
        R,
        y0,
        obs,
        log_det,
        batch_t[:-1],
        T,
    )


def assemble_result(
    prep: PreparedInputs, filtered: tuple[Tensor, Tensor], predicted: tuple[Tensor, Tensor], step_ll_core: Tensor
) -> FilterResult:
    """The :class:`FilterResult` of an algorithm's batch-last moments: filtered and predicted
    (mean (T, n, *b), cov (T, n, n, *b)) pairs and the whitened per-step log-likelihood core
    (T, *b); the innovations and their covariances formed here in the original space, the
    log-likelihood constants added, every output a batch-first view of the full batch."""
    (mean, cov), (pred_mean, pred_cov) = filtered, predicted
    mb, T, nd = prep.mean_batch, prep.T, len(prep.mean_batch)
    n, m = mean.shape[1], prep.yw.shape[1]
    obs = prep.obs.to(mean.dtype)
    innovation = (prep.y0 - mv(prep.H, pred_mean, 1)) * obs
    innovation_cov = sym(mm(mm(prep.H, pred_cov, 1), tr(prep.H, 1), 1), 1) + prep.R
    step_ll = step_ll_core - 0.5 * LOG_2PI * obs.sum(1) - prep.log_det_chol_R
    c = prep.c if prep.c is not None else mean.new_zeros((1, n, *(1,) * nd))

    def out(x: Tensor, event: tuple[int, ...]) -> Tensor:
        return batch_first(x, len(event), nd).expand(*mb, T, *event)

    step_ll = out(step_ll.unsqueeze(1), (1,)).squeeze(-1)
    return FilterResult(
        mean=out(mean, (n,)),
        cov=out(cov, (n, n)),
        pred_mean=out(pred_mean, (n,)),
        pred_cov=out(pred_cov, (n, n)),
        innovation=out(innovation, (m,)),
        innovation_cov=out(innovation_cov, (m, m)),
        log_likelihood=step_ll.sum(-1),
        step_log_likelihood=step_ll,
        transition=out(prep.A, (n, n)),
        process_noise=out(prep.Q, (n, n)),
        observed=out(prep.obs, (m,)),
        control=out(c, (n,)),
    )


def predictions(prep: PreparedInputs, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
    """The predictions ``m⁻_k = A_k m_{k−1} + c_k``, ``P⁻_k = A_k P_{k−1} A_kᵀ + Q_k`` (step 0
    from the prior) of the filtered moments mean (T, n, *b), cov (T, n, n, *b), batched over
    the steps."""
    # (the prior put in front, the last step dropped: no size-(T − 1) tensor, which a traced
    # program with a dynamic T would have to guard against being 1)
    prev_m = torch.cat([prep.m0.expand(mean.shape[1:]).unsqueeze(0), mean])[:-1]
    prev_P = torch.cat([prep.P0.expand(cov.shape[1:]).unsqueeze(0), cov])[:-1]
    pred_mean = mv(prep.A, prev_m, 1)
    if prep.c is not None:
        pred_mean = pred_mean + prep.c
    return pred_mean, sym(mm(mm(prep.A, prev_P, 1), tr(prep.A, 1), 1), 1) + prep.Q


def observed_count(prep: PreparedInputs) -> Tensor:
    """The number of observed components of each step, (T, *b) in the filter's dtype."""
    return prep.obs.sum(1).to(prep.yw.dtype)


def complete_from_filtered(
    prep: PreparedInputs, mean: Tensor, cov: Tensor, noise: NoiseModel = GAUSSIAN
) -> FilterResult:
    """The :class:`FilterResult` of an algorithm that yields the filtered moments alone, mean
    (T, n, *b) and cov (T, n, n, *b): the predictions (:func:`predictions`) and the
    log-likelihood from the whitened innovations ``z_k = L_k⁻¹ (y'_k − H'_k m⁻_k)``,
    ``L_k L_kᵀ = H'_k P⁻_k H'_kᵀ + I``, all batched over the steps (an unobserved component has
    a zero row of H' and y': it adds 0), its core the ``noise`` model's."""
    pred_mean, pred_cov = predictions(prep, mean, cov)
    Hw, m = prep.Hw, prep.Hw.shape[1]
    eye = torch.eye(m, dtype=Hw.dtype, device=Hw.device).reshape(1, m, m, *[1] * len(prep.mean_batch))
    L, d = psd_cholesky(sym(mm(mm(Hw, pred_cov, 1), tr(Hw, 1), 1), 1) + eye, 1)  # (T, m, m, *b)
    v = (prep.yw - mv(Hw, pred_mean, 1)).unsqueeze(2)
    z = lower_solve(L, d, v, len(prep.mean_batch)).squeeze(2)  # (T, m, *b)
    # log det S = −2 Σ log d_j (det S = Π 1 / d_j²), Δ² = zᵀ z
    core = noise.log_likelihood_core(-2.0 * torch.log(d).sum(1), (z * z).sum(1), observed_count(prep))
    return assemble_result(prep, (mean, cov), (pred_mean, pred_cov), core)
