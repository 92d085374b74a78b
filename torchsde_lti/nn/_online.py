"""The evaluated model of a module's online calls (private to nn/): its parametrisations run
once per parameter version while no gradient is recorded, and what the exact discretisation
of a step needs that does not depend on dt (:func:`model_series`: a nilpotent F's terminating
series, any other F's doubling series terms) is formed with them."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, TypeVar

import torch
from torch import Tensor, nn

from torchsde_lti.core.discretization import Discrete, SharedSeries, discretization_series, discretize
from torchsde_lti.core.linalg import noise_covariance
from torchsde_lti.core.validation import as_float_tensor, broadcast_batch, shape_str, tracing
from torchsde_lti.filters.online import KalmanState

if TYPE_CHECKING:  # (nn.sde imports the parametrisations, which import this module)
    from torchsde_lti.nn.sde import SDEMatrices

T = TypeVar("T")

#: The dt-independent part of one parameter set's discretisation (:func:`model_series`).
Series = SharedSeries

_CACHE = "_online_model_cache"


def model_version(module: nn.Module) -> tuple[int, ...]:
    """(id, storage address, version counter) of every parameter and buffer of ``module`` and
    its submodules, flattened: changes with an optimiser step (in-place), ``.to()``, a
    load_state_dict or an assignment. (A plain walk over the module tree: ``named_modules``
    costs 5× more; it runs on every online call.)"""
    key: list[int] = []
    add = key.extend
    stack = [module]
    while stack:
        mod = stack.pop()
        for t in mod._parameters.values():
            if t is not None:
                add((id(t), t.data_ptr(), t._version))
        for b in mod._buffers.values():
            if b is not None:
                add((id(b), b.data_ptr(), b._version))
        stack.extend([m for m in mod._modules.values() if m is not None])
    return tuple(key)


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


def drop_evaluated(module: nn.Module) -> None:
    """Forget ``module``'s cached :func:`evaluated` model (a change its parameter version does
    not show, such as a parametrisation's floor)."""
    module.__dict__.pop(_CACHE, None)


def tracks_shape(batch_shape: object) -> tuple[int, ...]:
    """``batch_shape`` of :meth:`initial_state` (an int or a sequence of ints ≥ 0) as a tuple;
    ValueError naming it otherwise."""
    shape = (batch_shape,) if isinstance(batch_shape, int) else batch_shape
    out: tuple[object, ...] | None = tuple(shape) if isinstance(shape, Iterable) else None
    if out is None or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in out):
        raise ValueError(f"batch_shape must be an int or a sequence of ints >= 0, got {batch_shape!r}")
    return out  # type: ignore[return-value]


def check_batches(named: Sequence[tuple[str, Sequence[int]]]) -> None:
    """ValueError naming the batch shapes ``named`` when they do not broadcast (an empty batch
    broadcasts with any and is left out; nothing to check when the others are equal)."""
    shaped = [(name, shape) for name, shape in named if len(shape)]
    if any(tuple(shape) != tuple(shaped[0][1]) for _, shape in shaped[1:]):
        broadcast_batch(shaped)


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


def model_series(F: Tensor, L: Tensor, Qc: Tensor, B: Tensor | None) -> Series | None:
    """Core's :func:`~torchsde_lti.core.discretization.discretization_series` of a model's
    matrices (F (n, n), L (n, s), Qc (s, s), B (n, p) or None, no batch dims): the
    dt-independent part of its exact discretisation (a nilpotent F's terminating series, else
    the series terms of the doubling); None for a batch of parameters (those take core's
    :func:`~torchsde_lti.core.discretize`). A nilpotent F is found on the device: no value is
    read (no synchronisation; the same series eager, compiled and exported)."""
    if any(t is not None and t.dim() != 2 for t in (F, L, Qc, B)):
        return None
    return discretization_series(F, noise_covariance(L, Qc), B)


def discretize_steps(
    mats: SDEMatrices,
    dt: Tensor,
    method: str,
    series: Series | None,
    batch_last: bool = True,
    unique: bool = False,
    time_axis: bool = True,
) -> Discrete:
    """(A, Q, G) of every step dt (..., T) of a model: THE discretisation of the modules'
    calls (sequence, online step, prediction, forecast, each mode of an IMM), so they agree.

    With ``method="doubling"`` and one parameter set (``series``, :func:`model_series`, not
    None) the series over dt, as batch-first views (..., T, r, c) of batch-last storage
    (r, c, T, ...) with ``batch_last`` (the sequence loop's layout: its per-step moves are row
    copies), else plain batch-first; otherwise core's
    :func:`~torchsde_lti.core.discretize` of the matrices with a length-1 time axis (a
    parameter batch (..., 1, n, n) lines up with dt (..., T)), no value checks (the caller
    checked). ``unique``: discretise the distinct values of dt only and gather them (one
    parameter set and a dt that does not require grad; same values). Without ``time_axis``,
    dt (...) is one step of each track and the results are (..., r, c) (views of (r, c, ...)
    storage with ``batch_last``; an online step)."""
    if method == "doubling" and series is not None:
        if not time_axis:
            one = series(dt, batch_last=batch_last)
            if batch_last and dt.dim():  # (r, c, ...) -> (..., r, c)
                one = tuple(None if x is None else x.movedim((0, 1), (-2, -1)) for x in one)  # type: ignore[assignment]
            assert one[1] is not None
            return Discrete(one[0], one[1], one[2])
        # storage (r, c, T, ...): each step's matrices of all tracks contiguous (the loop's moves
        # to (r, c, tracks) are then row copies)
        dt_tm = dt.movedim(-1, 0) if dt.dim() else dt
        inverse = None
        if unique and not dt.requires_grad and dt.numel() > 0:
            values, inverse = torch.unique(dt_tm, return_inverse=True)
            out = series(values, batch_last=True)
        else:
            out = series(dt_tm, batch_last=True)
        picked: list[Tensor | None] = []
        for x in out:
            if x is not None and inverse is not None:  # (r, c, U) -> (r, c, T, ...)
                x = x.index_select(-1, inverse.reshape(-1)).reshape(*x.shape[:2], *dt_tm.shape)
            if x is not None:  # (r, c, T, ...) -> (..., T, r, c)
                x = x.permute(*range(3, x.dim()), 2, 0, 1) if dt.dim() else x.movedim((0, 1), (-2, -1))
                x = x if batch_last else x.contiguous()
            picked.append(x)
        A, Q, G = picked
        assert A is not None and Q is not None
        return Discrete(A, Q, G)
    F, L, Qc, B = (None if x is None else x.unsqueeze(-3) for x in mats) if time_axis else mats
    assert F is not None and L is not None and Qc is not None
    return discretize(F, L, Qc, dt, B=B, method=method, validate_args=False)
