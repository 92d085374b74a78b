"""The base of the constraint parametrisations (private to :mod:`torchsde_lti.nn`): the raw
tensor's dtype and device, and the absolute floor δ after ``softplus`` fixed once and saved
in ``state_dict`` (the public classes and the rules: :mod:`torchsde_lti.nn.parametrizations`).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn.modules.module import _EXTRA_STATE_KEY_SUFFIX

from torchsde_lti.core.validation import as_float_tensor, check_matrix, tracing
from torchsde_lti.nn._online import drop_evaluated

__all__ = [
    "FlooredParametrization",
    "Parametrization",
    "default_floor",
    "floor_state_keys",
    "reset_default_floors",
    "softplus",
    "softplus_inverse",
]


def default_floor(dtype: torch.dtype) -> float:
    """Dtype-aware lower bound added after ``softplus``: machine epsilon of ``dtype``."""
    return float(torch.finfo(dtype).eps)


def softplus(x: Tensor) -> Tensor:
    """``log(1 + exp(x))`` evaluated without overflow and without a linear threshold.

    Unlike ``torch.nn.functional.softplus`` (which returns ``x`` above ``threshold=20``)
    this is the exact function everywhere, so :func:`softplus_inverse` round-trips.
    """
    return x.clamp_min(0) + torch.log1p(torch.exp(-x.abs()))


def softplus_inverse(y: Tensor) -> Tensor:
    """Inverse of :func:`softplus` for ``y > 0``: ``y + log(-expm1(-y))`` (stable for all y > 0)."""
    return y + torch.log(-torch.expm1(-y))


class Parametrization(nn.Module):
    """Base: remembers dtype/device of the raw tensor through a zero-size buffer."""

    _ref: Tensor

    def __init__(self, floor: float | None = None, size: int | None = None) -> None:
        super().__init__()
        if floor is not None and not floor > 0:
            raise ValueError(f"floor must be positive or None, got {floor!r}")
        if size is not None and (isinstance(size, bool) or not isinstance(size, int) or size < 1):
            raise ValueError(f"size must be a positive integer or None, got {size!r}")
        self.floor = floor
        self.size = size
        self.register_buffer("_ref", torch.empty(0), persistent=False)

    def _check_size(self, value: Tensor, name: str) -> None:
        """A square (..., k, k) value, with k = ``size`` when given.

        :mod:`torch.nn.utils.parametrize` stores whatever ``right_inverse`` returns, even
        with a new shape, so a wrong-sized assignment must fail here or it corrupts the module.
        """
        check_matrix(value, name, rows=self.size, cols=self.size, square=True)

    def _as_raw_tensor(self, value: object, name: str) -> Tensor:
        """Cast an assigned value to the raw tensor's dtype and device."""
        if isinstance(value, torch.Tensor):
            x = as_float_tensor(value, name).detach()
        else:  # convert Python numbers / arrays straight to the raw dtype (no float32 detour)
            x = as_float_tensor(value, name, self._ref.dtype)
        return x.to(dtype=self._ref.dtype, device=self._ref.device)

    def extra_repr(self) -> str:
        parts = [] if self.size is None else [f"size={self.size}"]
        if self.floor is not None:
            parts.append(f"floor={self.floor}")
        return ", ".join(parts)


class FlooredParametrization(Parametrization):
    """Base of the parametrisations that add an absolute floor δ > 0 after ``softplus``.

    δ is ``floor`` when given. Otherwise it is fixed once, at ``default_floor(dtype)`` of the
    first tensor the parametrisation sees (``right_inverse``'s value or ``forward``'s raw
    tensor), and then kept whatever the dtype of later tensors. The δ in use is the module's
    extra state (``<prefix>._extra_state`` in ``state_dict``: a 0-dim float64 tensor, 0 while
    not fixed yet); ``load_state_dict`` restores it (an explicit ``floor`` stays as given), and
    a state dict without it loads, strict or not, with δ = ``default_floor`` of the module's
    dtype.
    """

    def __init__(self, floor: float | None = None, size: int | None = None) -> None:
        super().__init__(floor, size)
        self._default_floor: float | None = None

    def _floor(self, dtype: torch.dtype) -> float:
        """δ for a tensor of ``dtype``: the explicit floor, else the default fixed at the first call."""
        if self.floor is not None:
            return float(self.floor)
        if self._default_floor is not None:
            return self._default_floor
        value = default_floor(dtype)
        if not tracing():  # a traced call leaves the module as it is (the next eager call fixes δ)
            self._default_floor = value
        return value

    def get_extra_state(self) -> Tensor:
        """δ in use as a 0-dim float64 tensor (0 while the default floor is not fixed yet)."""
        value = self._default_floor if self.floor is None else float(self.floor)
        return torch.tensor(0.0 if value is None else value, dtype=torch.float64)

    def set_extra_state(self, state: Any) -> None:
        """Restore δ from :meth:`get_extra_state` (kept as the default floor; an explicit
        ``floor`` is used as given). ValueError unless ``state`` is one finite number >= 0."""
        value = float(state.item()) if isinstance(state, Tensor) and state.numel() == 1 else state
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise ValueError(
                f"{self._label()}: the saved floor ({_EXTRA_STATE_KEY_SUFFIX} in the state dict) must be one "
                f"finite number >= 0, got {state!r}"
            )
        if self.floor is None:
            self._default_floor = float(value) if value > 0 else None

    def _label(self) -> str:
        return f"{type(self).__name__}({getattr(self, 'name', '')!r})"

    def _load_from_state_dict(
        self,
        state_dict: dict[str, Any],
        prefix: str,
        local_metadata: dict[str, Any],
        strict: bool,
        missing_keys: list[str],
        unexpected_keys: list[str],
        error_msgs: list[str],
    ) -> None:
        key = prefix + _EXTRA_STATE_KEY_SUFFIX
        saved = key in state_dict
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        if not saved:  # saved before floors were saved: δ as such a state was read before
            if key in missing_keys:
                missing_keys.remove(key)
            if self.floor is None:
                self._default_floor = default_floor(self._ref.dtype)


def floor_state_keys(module: nn.Module) -> frozenset[str]:
    """The ``module.state_dict()`` keys holding the floors of its :class:`~torchsde_lti.nn.parametrizations.Positive`,
    :class:`~torchsde_lti.nn.parametrizations.PositiveDefinite` and :class:`~torchsde_lti.nn.parametrizations.Generator` parametrisations.

    ``load_state_dict`` accepts a state dict without them, with ``strict=True`` too (one saved
    before the floors were saved: each floor is then the eps of the module's dtype).
    """
    return frozenset(
        f"{name}.{_EXTRA_STATE_KEY_SUFFIX}" if name else _EXTRA_STATE_KEY_SUFFIX
        for name, mod in module.named_modules(remove_duplicate=False)
        if isinstance(mod, FlooredParametrization)
    )


def reset_default_floors(module: nn.Module, dtype: torch.dtype) -> None:
    """Fix the default floor (``floor=None``) of every :class:`~torchsde_lti.nn.parametrizations.Positive`, :class:`~torchsde_lti.nn.parametrizations.PositiveDefinite`
    and :class:`~torchsde_lti.nn.parametrizations.Generator` of ``module`` at ``default_floor(dtype)``, as if it had been built in
    ``dtype``; explicit floors are kept.

    The raw tensors are not changed, so each value moves by the change of its floor (at most
    float32's eps, 1.2e-7). Use it where a module built in one dtype is meant to be trained in
    another: a float32 floor keeps a float64 model's values above 1.2e-7. ``dtype`` must be a
    floating dtype (TypeError otherwise).
    """
    value = default_floor(dtype)
    for mod in module.modules():
        if isinstance(mod, FlooredParametrization) and mod.floor is None:
            mod._default_floor = value
        drop_evaluated(mod)  # the online calls' evaluated model: it is kept per parameter version
