"""Value checks of the modules (private to nn/): a per-instance ``validate_args`` with a class
default, as in torch.distributions, and one fused check of a call's arguments."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import Tensor

from torchsde_lti.core.validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_no_inf,
    check_nonnegative,
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


def check_values(finite: Named = (), nonnegative: Named = (), no_inf: Named = ()) -> None:
    """ValueError naming the first bad tensor: NaN/Inf in ``finite`` and ``nonnegative``,
    a negative entry in ``nonnegative``, ±Inf in ``no_inf`` (NaN allowed: missing data).
    One synchronisation when everything is valid (no-op while tracing)."""
    if tracing():
        return
    fin: Present = [(k, v) for k, v in finite if v is not None]
    nonneg: Present = [(k, v) for k, v in nonnegative if v is not None and v.numel()]
    noinf: Present = [(k, v) for k, v in no_inf if v is not None]
    if not (fin or nonneg or noinf):
        return
    with torch.no_grad():
        flags = [torch.stack([v.sum() for _, v in (*fin, *nonneg)]).isfinite().all()] if fin or nonneg else []
        flags += [v.amin() >= 0 for _, v in nonneg]
        flags += [~torch.isinf(v).any() for _, v in noinf]
        if bool(torch.stack(flags).all()):
            return
    for name, value in fin:  # a finite sum that overflowed passes these
        check_finite(value, name)
    for name, value in nonneg:
        check_nonnegative(value, name)
    for name, value in noinf:
        check_no_inf(value, name)


class NonFiniteLikelihoodError(ValueError):
    """A checked filter call whose arguments were valid gave a non-finite log-likelihood
    (the discretisation or the squared residuals overflow the dtype). A ``ValueError``, so
    callers that catch bad input catch it too; a training loop that skips such batches
    catches this class alone."""


def check_outcome(
    log_likelihood: Tensor, steps: Sequence[Tensor | None], y: Tensor, dt: Tensor, F: Tensor, R: Tensor | None = None
) -> None:
    """:class:`NonFiniteLikelihoodError` when a checked call's log-likelihood is not finite although its arguments
    were valid, saying why: the discretisation over-/underflows the dtype (an unstable F over
    a long step), the observation noise R is nearly singular in the dtype, or the observations
    are too large for it (the squared residuals overflow). One synchronisation (no-op while
    tracing). ``steps``: the discrete matrices the filter used; R: (..., m, m) or None."""
    if tracing():
        return
    with torch.no_grad():
        if bool(torch.isfinite(log_likelihood).all()):
            return
        bad = [t for t in steps if t is not None and not bool(torch.isfinite(t).all())]
        dtype = y.dtype
        if bad:
            rightmost = float(torch.linalg.eigvals(torch.nan_to_num(F.detach().double())).real.max())
            raise NonFiniteLikelihoodError(
                f"the discretisation overflows {dtype} for dt up to {float(dt.max()):.3g} (F's rightmost eigenvalue "
                f"has real part {rightmost:.3g}; an unstable F grows like e^(Re λ dt)): shorten dt, constrain F "
                "(F_constraint='hurwitz') or use float64"
            )
        top = float(torch.nan_to_num(y.detach(), nan=0.0).abs().max())
        info = torch.finfo(dtype)
        ratio = None
        if R is not None and R.numel():
            lam = torch.linalg.eigvalsh(torch.nan_to_num(R.detach().double()))
            ratio = float((lam[..., 0] / lam[..., -1].clamp_min(torch.finfo(torch.float64).tiny)).min())
    wider = " or use float64" if dtype != torch.float64 else ""
    if ratio is not None and ratio < 1e3 * info.eps:
        why = (
            f"the observation noise R is nearly singular in {dtype} (smallest / largest eigenvalue {ratio:.3g}): "
            f"the updates lose the covariances' positive definiteness; keep R's eigenvalues apart{wider}"
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
    raise NonFiniteLikelihoodError(f"the log-likelihood is not finite in {dtype}: {why}")


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
