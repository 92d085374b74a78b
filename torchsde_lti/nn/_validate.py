"""Value checks of the modules (private to nn/): a per-instance ``validate_args`` with a class
default, as in torch.distributions, and one fused check of a call's arguments."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import Tensor

from torchsde_lti.core.validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_no_inf,
    check_symmetric_psd,
    shape_str,
    tracing,
)

Named = Sequence[tuple[str, Tensor | None]]
Present = list[tuple[str, Tensor]]


class ValidateArgs:
    """Mixin: ``validate_args`` per instance, falling back to the class default.

    ``validate_args=True`` checks the values of every call's arguments and parameters
    (finite, dt ≥ 0, …: a device synchronisation); shapes are always checked, and so are the
    constructor's arguments. Inner calls on already-checked tensors pass ``validate_args=False``
    to the core and filter functions. ``None`` (the default) follows the class attribute
    :attr:`default_validate_args` (True), which may be set per class, e.g.
    ``tl.KalmanFilter.default_validate_args = False`` once the inputs are trusted.
    """

    #: The value of :attr:`validate_args` for instances created with ``validate_args=None``.
    default_validate_args: ClassVar[bool] = True

    @property
    def validate_args(self) -> bool:
        """Whether calls check the values of their arguments (shapes are always checked)."""
        value = self.__dict__.get("_validate_args")
        return type(self).default_validate_args if value is None else value

    @validate_args.setter
    def validate_args(self, value: bool | None) -> None:
        self.__dict__["_validate_args"] = None if value is None else bool(value)

    def _validates(self, validate_args: bool | None) -> bool:
        """``validate_args`` of one call: the given value, else this instance's."""
        return self.validate_args if validate_args is None else bool(validate_args)


def check_values(
    finite: Named = (), nonnegative: Named = (), no_inf: Named = (), psd: Named = (), probabilities: Named = ()
) -> None:
    """ValueError naming the first bad tensor: NaN/Inf in ``finite``, ``nonnegative``, ``psd``
    and ``probabilities``; a negative entry in ``nonnegative``; ±Inf in ``no_inf`` (NaN allowed:
    missing data); a ``psd`` matrix (..., k, k) that is not symmetric positive semi-definite up
    to rounding (a covariance); a ``probabilities`` vector (..., M) with a negative entry or not
    summing to 1 (within 1e3 · eps · M).

    All tests run as tensor ops and are read in ONE synchronisation (no-op while tracing): the
    values are never copied to the host or changed. Only when one fails do the per-argument
    checks run, to name it."""
    if tracing():
        return
    fin: Present = [(k, v) for k, v in finite if v is not None]
    nonneg: Present = [(k, v) for k, v in nonnegative if v is not None and v.numel()]
    noinf: Present = [(k, v) for k, v in no_inf if v is not None]
    cov: Present = [(k, v) for k, v in psd if v is not None and v.numel()]
    prob: Present = [(k, v) for k, v in probabilities if v is not None and v.numel()]
    if not (fin or nonneg or noinf or cov or prob):
        return
    with torch.no_grad():
        flags = [v.isfinite().all() for _, v in (*fin, *nonneg, *cov, *prob)]
        flags += [v.amin() >= 0 for _, v in nonneg]
        flags += [~torch.isinf(v).any() for _, v in noinf]
        flags += [f for _, v in cov for f in _psd_flags(v)]
        flags += [_probabilities_pass(v) for _, v in prob]
        if bool(torch.stack(flags).all()):
            return
    for name, value in (*fin, *nonneg, *cov, *prob):
        check_finite(value, name)
    for name, value in nonneg:
        if bool((value < 0).any()):
            raise ValueError(
                f"{name} must be non-negative, got min {float(value.min()):.3g} (shape {shape_str(value)})"
            )
    for name, value in noinf:
        check_no_inf(value, name)
    for name, value in cov:
        check_symmetric_psd(value, name)
    for name, value in prob:
        if not bool(_probabilities_pass(value)):
            sums = value.sum(-1)
            raise ValueError(
                f"{name} must be probability vectors (entries >= 0, summing to 1 over the last axis), got shape "
                f"{shape_str(value)}, min {float(value.min()):.3g}, sums in [{float(sums.min()):.6g}, "
                f"{float(sums.max()):.6g}]"
            )
    named = ", ".join(name for name, _ in (*fin, *nonneg, *noinf, *cov, *prob))
    raise ValueError(f"invalid values among {named} (a covariance not PSD within rounding?)")


def _psd_flags(x: Tensor, symmetric: bool = False) -> list[Tensor]:
    """0-dim bool tests that x (..., k, k) is finite, symmetric and PSD up to rounding, as
    :func:`~torchsde_lti.core.validation.check_symmetric_psd` tests it (100 k eps relative to
    its largest entry): a Cholesky factor exists of x shifted by that tolerance. ``symmetric``:
    x is symmetric by construction (a filter's output), the asymmetry is not tested. No
    synchronisation."""
    scale = x.abs().amax(dim=(-2, -1), keepdim=True)  # (NaN or Inf wherever an entry is)
    info = torch.finfo(x.dtype)
    shift = (100.0 * x.shape[-1] * info.eps) * scale.clamp_min(info.tiny)
    eye = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device)
    flags = [(torch.linalg.cholesky_ex(torch.addcmul(x, shift, eye)).info == 0).all(), (scale < math.inf).all()]
    return flags if symmetric else [*flags, ((x - x.mT).abs() <= shift).all()]


def _measurement_kept(H: Tensor, observed: Tensor, P: Tensor, R: Tensor) -> Tensor:
    """0-dim bool: every observed component's filtered variance ``(H P Hᵀ)_jj`` is at most
    ``2 R_jj`` (exactly it is below R_jj; :func:`check_outcome`). No synchronisation."""
    variance = torch.where(observed, ((H @ P) * H).sum(-1), 0.0)  # (H P Hᵀ)_jj
    return (variance <= 2.0 * R.diagonal(0, -2, -1)).all()


def _finite(tensors: Sequence[Tensor]) -> Tensor:
    """0-dim bool: every entry of ``tensors`` finite (``x · 0 = 0``). No synchronisation."""
    flat = torch.cat([t.reshape(-1) for t in tensors]) if len(tensors) > 1 else tensors[0]
    return (flat * 0 == 0).all()


def _probabilities_pass(p: Tensor) -> Tensor:
    """0-dim bool: p (..., M) has entries ≥ 0 summing to 1 within 1e3 · eps · M. No synchronisation."""
    tol = 1e3 * torch.finfo(p.dtype).eps * p.shape[-1]
    return (p >= 0).all() & ((p.sum(-1) - 1).abs() <= tol).all()


class NonFiniteLikelihoodError(ValueError):
    """A checked filter call whose arguments were valid gave a non-finite log-likelihood
    (the discretisation or the squared residuals overflow the dtype). A ``ValueError``, so
    callers that catch bad input catch it too; a training loop that skips such batches
    catches this class alone."""


def check_outcome(
    outputs: Sequence[Tensor],
    covariances: Sequence[Tensor],
    steps: Sequence[Tensor | None],
    y: Tensor,
    dt: Tensor,
    F: Tensor,
    R: Tensor | None = None,
    update: tuple[Tensor, Tensor, Tensor] | None = None,
) -> None:
    """:class:`NonFiniteLikelihoodError` when a checked call's ``outputs`` (its log-likelihood,
    the mean it ends in: a NaN or Inf there persists into every later step) are not finite or
    its filtered ``covariances`` (..., k, k) are not symmetric PSD up to rounding (the test of
    :func:`check_values`) although its arguments were valid, saying why: the discretisation
    over-/underflows the dtype (an unstable F, or an integrator chain's noise, over a long
    step), the observation noise R is nearly singular in the dtype, the observations are too
    large for it (the squared residuals overflow), or the update cancelled (a prior that dwarfs
    R by more than 1/eps). One synchronisation (no-op while tracing). ``steps``: the discrete
    matrices the call used; F: the drift matrix (or the bank's); R: (..., m, m) or None.

    ``update``: (H (..., m, n), observed (..., m) bool, P (..., n, n)) of the updates, P the
    filtered covariances (broadcasting with H, R): an update that lost the measurement to
    rounding (a prior that dwarfs R by more than 1/eps: the Joseph form then returns a finite,
    even PSD, covariance unrelated to the data) is an error too. Exactly, the posterior
    covariance of the observed components is below R (``R − R S⁻¹ R``), so an observed
    component whose filtered variance ``(H P Hᵀ)_jj`` exceeds ``2 R_jj`` is that loss.

    The Kalman sequence filter checks the state it ends in (and the log-likelihood of every
    step), the online step its new state, so a series of online steps raises exactly where the
    sequence filter of the reports seen so far raises; the IMM's sequence filter checks every
    step's mode covariances. The filtered covariances are symmetric by construction: their
    asymmetry is not tested."""
    if tracing():
        return
    with torch.no_grad():
        if all_pass(outcome_flags(outputs, covariances, R, update)):
            return
        bad = [t for t in steps if t is not None and not bool(torch.isfinite(t).all())]
        dtype = y.dtype
        if bad:
            rightmost = float(torch.linalg.eigvals(torch.nan_to_num(F.detach().double())).real.max())
            raise NonFiniteLikelihoodError(
                f"the discretisation overflows {dtype} for dt up to {float(dt.max()):.3g} (F's rightmost eigenvalue "
                f"has real part {rightmost:.3g}; an unstable F grows like e^(Re λ dt), an integrator chain's noise "
                "like a power of dt): shorten dt, constrain F "
                "(F_constraint='hurwitz') or use float64"
            )
        top = float(torch.nan_to_num(y.detach(), nan=0.0).abs().max())
        info = torch.finfo(dtype)
        ratio = None
        if R is not None and R.numel():
            lam = torch.linalg.eigvalsh(torch.nan_to_num(R.detach().double()))
            ratio = float((lam[..., 0] / lam[..., -1].clamp_min(torch.finfo(torch.float64).tiny)).min())
    wider = " or use float64" if dtype != torch.float64 else ""
    lost = update is not None and R is not None and not bool(_measurement_kept(*update, R))
    if ratio is not None and ratio < 1e3 * info.eps:
        why = (
            f"the observation noise R is nearly singular in {dtype} (smallest / largest eigenvalue {ratio:.3g}): "
            f"the updates lose the covariances' positive definiteness; keep R's eigenvalues apart{wider}"
        )
    elif lost:
        why = (
            f"an update lost the measurement to rounding: an observed component's filtered variance exceeds twice "
            f"its noise variance R (exactly it is below R), which happens where the predicted variance dwarfs R by "
            f"more than 1/eps of {dtype} (a gap too long for the model's noise, or a prior too broad); shorten the "
            f"gaps or start new tracks after them{wider}"
        )
    elif top * top > info.max**0.5:
        why = (
            f"observations y up to |y| = {top:.3g} make the squared residuals overflow; centre and scale the "
            f"observations (e.g. positions relative to each track's start, in km){wider}"
        )
    else:
        why = (
            f"the covariances lost their positive definiteness or overflowed (observations up to |y| = {top:.3g}); "
            f"check the scales of Q, R and P0 against the data's{wider}"
            + (", or algorithm='square_root' (PSD by construction)" if dtype != torch.float64 else "")
        )
    raise NonFiniteLikelihoodError(f"the log-likelihood or the filtered state is not finite in {dtype}: {why}")


def outcome_flags(
    outputs: Sequence[Tensor],
    covariances: Sequence[Tensor],
    R: Tensor | None = None,
    update: tuple[Tensor, Tensor, Tensor] | None = None,
) -> list[Tensor]:
    """The tests of :func:`check_outcome` as 0-dim bool tensors (no synchronisation): the
    ``outputs`` finite, the filtered ``covariances`` finite and PSD up to rounding (symmetric by
    construction), and with ``update`` and R the measurements kept."""
    flags = [_finite(outputs)] if outputs else []
    flags += [f for c in covariances if c.numel() for f in _psd_flags(c, symmetric=True)]
    if update is not None and R is not None:
        flags.append(_measurement_kept(*update, R))
    return flags


def all_pass(flags: Sequence[Tensor]) -> bool:
    """Whether every 0-dim bool test in ``flags`` passed: ONE synchronisation (True for none)."""
    return not flags or bool(torch.stack(list(flags)).all())


def online_report(
    y: Tensor, mask: Tensor | None, H: Tensor, dtype: torch.dtype, device: torch.device
) -> tuple[Tensor, Tensor | None]:
    """(y, mask) of an online step converted and their shapes checked against H (..., m, n).

    Args:
        y: (..., m) one report per live track; NaN = missing component.
        mask: optional bool (...) or (..., m); False = not observed.
        H: the filter's observation matrix, whose m the reports must have.
        dtype: the filter's float dtype. device: its device.

    Returns:
        y as a tensor of ``dtype`` on ``device`` and mask as a bool tensor (or None).
    """
    y = as_float_tensor(y, "y", dtype, device)
    m = H.shape[-2]
    if y.dim() < 1 or y.shape[-1] != m:
        raise ValueError(f"y must have shape (..., m={m}) to match H {shape_str(H)}, got shape {shape_str(y)}")
    if mask is not None:
        mask = torch.as_tensor(mask, device=y.device)
        if mask.dtype != torch.bool:
            raise ValueError(f"mask must be a bool tensor, got dtype {mask.dtype}")
        per_component = mask.dim() == y.dim() and mask.shape[-1] in (1, m)
        if mask.dim() > y.dim() or (mask.dim() == y.dim() and not per_component):
            raise ValueError(
                f"mask must have shape (...) or (..., {m}) to match y {shape_str(y)}, got {shape_str(mask)}"
            )
        broadcast_batch([("y", y.shape[:-1]), ("mask", mask.shape[:-1] if per_component else mask.shape)])
    return y, mask
