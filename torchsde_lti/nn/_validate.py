"""Value checks of the modules (private to nn/): a per-instance ``validate_args`` with a class
default, as in torch.distributions, and one fused check of a call's arguments."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import Tensor

from torchsde_lti.core.validation import check_finite, check_nonnegative, shape_str, tracing

Named = Sequence[tuple[str, Tensor | None]]


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
    finite = [(k, v) for k, v in finite if v is not None]
    nonnegative = [(k, v) for k, v in nonnegative if v is not None and v.numel()]
    no_inf = [(k, v) for k, v in no_inf if v is not None]
    with torch.no_grad():
        flags = [torch.stack([v.sum() for _, v in (*finite, *nonnegative)]).isfinite().all()] if finite or nonnegative else []
        flags += [v.amin() >= 0 for _, v in nonnegative]
        flags += [~torch.isinf(v).any() for _, v in no_inf]
        if not flags or bool(torch.stack(flags).all()):
            return
    for name, value in finite:  # a finite sum that overflowed passes these
        check_finite(value, name)
    for name, value in nonnegative:
        check_nonnegative(value, name)
    for name, value in no_inf:
        if bool(torch.isinf(value).any()):
            raise ValueError(f"{name} contains Inf (shape {shape_str(value)}); mark missing values with NaN or mask")
