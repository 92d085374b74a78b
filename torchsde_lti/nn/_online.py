"""The evaluated model of a module's online calls (private to nn/): its parametrisations run
once per parameter version while no gradient is recorded."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import torch
from torch import Tensor, nn

from torchsde_lti.core.validation import as_float_tensor, shape_str, tracing
from torchsde_lti.filters.online import KalmanState

T = TypeVar("T")

_CACHE = "_online_model_cache"


def model_version(module: nn.Module) -> tuple[tuple[int, int, int], ...]:
    """(id, storage address, version counter) of every parameter and buffer of ``module`` and
    its submodules: changes with an optimiser step (in-place), ``.to()``, a load_state_dict or
    an assignment. (A plain walk over the module tree: ``named_modules`` costs 5× more.)"""
    out: list[tuple[int, int, int]] = []
    stack = [module]
    while stack:
        mod = stack.pop()
        for t in (*mod._parameters.values(), *mod._buffers.values()):
            if t is not None:
                out.append((id(t), t.data_ptr(), t._version))
        stack.extend(m for m in mod._modules.values() if m is not None)
    return tuple(out)


def evaluated(module: nn.Module, build: Callable[[], T]) -> T:
    """``build()`` (the module's matrices from its parametrisations), cached on ``module``
    for its current parameter version when no gradient is recorded (a tracker's hot loop);
    evaluated afresh while recording gradients and while traced."""
    if torch.is_grad_enabled() or tracing():
        return build()
    key = model_version(module)
    hit = module.__dict__.get(_CACHE)
    if hit is not None and hit[0] == key:
        return hit[1]
    value = build()
    module.__dict__[_CACHE] = (key, value)
    return value


def online_state(state: object, dt: Tensor | float, F: Tensor) -> tuple[KalmanState, Tensor]:
    """(state, dt) of a KalmanFilter's online call as tensors of F's dtype and device, shapes
    checked: state a (mean (..., n), cov (..., n, n)) pair, n = F's; TypeError or ValueError."""
    dtype, device, n = F.dtype, F.device, F.shape[-1]
    if not isinstance(state, tuple) or len(state) != 2:
        raise TypeError(f"state must be a KalmanState (mean, cov), got {type(state).__name__}")
    mean = as_float_tensor(state[0], "state.mean", dtype, device)
    cov = as_float_tensor(state[1], "state.cov", dtype, device)
    if mean.dim() < 1 or mean.shape[-1] != n or cov.dim() < 2 or cov.shape[-2:] != (n, n):
        raise ValueError(
            f"state must be (mean (..., {n}), cov (..., {n}, {n})), got mean {shape_str(mean)}, cov {shape_str(cov)}"
        )
    return KalmanState(mean, cov), as_float_tensor(dt, "dt", dtype, device)
