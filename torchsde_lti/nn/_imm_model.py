"""The evaluated model of an :class:`~torchsde_lti.IMMFilter` call and its checks (private to
nn/): what a call reads of the filter (:class:`IMMModel`), the state of its online calls
converted and shape-checked (:func:`imm_state`), and the one fused value check of a call
(:func:`check_model_values`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core.linalg import noise_covariance
from torchsde_lti.core.validation import as_float_tensor, shape_str
from torchsde_lti.filters.imm_online import IMMState
from torchsde_lti.filters.noise import GAUSSIAN, NoiseModel
from torchsde_lti.nn._online import Series
from torchsde_lti.nn._validate import check_values
from torchsde_lti.nn.sde import SDEMatrices

__all__ = ["IMMModel", "bank_of", "check_model_values", "imm_state", "state_batches"]


class IMMModel(NamedTuple):
    """The evaluated model of an :class:`IMMFilter` call (:meth:`IMMFilter.imm_model`), each
    parametrisation read once: modes: each mode's SDE matrices; series: each mode's
    discretisation series (:func:`~torchsde_lti.nn._online.model_series`); H (M or 1, m, n),
    R (M or 1, m, m); rates (M, M) the generator Λ; chain: the mode chain's series
    (``expm(Λ dt)``, float64); noise: the modes' observation-noise model."""

    modes: tuple[SDEMatrices, ...]
    series: tuple[Series | None, ...]
    H: Tensor
    R: Tensor
    rates: Tensor
    chain: Series
    noise: NoiseModel = GAUSSIAN


#: The names of an IMM state's fields in error messages.
_STATE_NAMES = ("state.mode_prob", "state.mode_mean", "state.mode_cov")


def imm_state(state: object, M: int, n: int, dtype: torch.dtype, device: torch.device) -> IMMState:
    """An online call's state as an :class:`~torchsde_lti.IMMState` of the filter's dtype and
    device, shapes checked against M modes and n states; TypeError or ValueError naming it."""
    if not isinstance(state, tuple) or len(state) != 3:
        raise TypeError(f"state must be an IMMState (mode_prob, mode_mean, mode_cov), got {type(state).__name__}")
    prob, mean, cov = (as_float_tensor(t, name, dtype, device) for name, t in zip(_STATE_NAMES, state))
    if prob.dim() < 1 or prob.shape[-1] != M or mean.shape[-2:] != (M, n) or cov.shape[-3:] != (M, n, n):
        raise ValueError(
            f"state must be (mode_prob (..., {M}), mode_mean (..., {M}, {n}), mode_cov "
            f"(..., {M}, {n}, {n})), got {shape_str(prob)}, {shape_str(mean)}, {shape_str(cov)}"
        )
    return IMMState(prob, mean, cov)


def bank_of(modes: Sequence[SDEMatrices]) -> tuple[Tensor, Tensor]:
    """Stacked F (M, n, n) and noise intensities ``L Qc Lᵀ`` (M, n, n) of the modes' matrices."""
    return torch.stack([m.F for m in modes]), torch.stack([noise_covariance(m.L, m.Qc) for m in modes])


def check_model_values(
    model: IMMModel,
    dt: Tensor,
    state: IMMState | None = None,
    y: Tensor | None = None,
    finite: Sequence[tuple[str, Tensor]] = (),
) -> None:
    """The value checks of a call (one synchronisation): every mode's matrices, H, R, the
    rates and ``finite`` finite; dt ≥ 0; y without ±Inf; the state's mode probabilities
    probability vectors, its means finite and covariances symmetric PSD."""
    F, W = bank_of(model.modes)
    check_values(
        finite=[("F", F), ("W", W), ("H", model.H), ("R", model.R), ("rates", model.rates), *finite,
                *([] if state is None else [("state.mode_mean", state.mode_mean)])],
        nonnegative=[("dt", dt)],
        no_inf=[("y", y)],
        psd=[] if state is None else [("state.mode_cov", state.mode_cov)],
        probabilities=[] if state is None else [("state.mode_prob", state.mode_prob)],
    )  # fmt: skip


def state_batches(state: IMMState) -> list[tuple[str, tuple[int, ...]]]:
    """The named batch shapes of an IMM state's fields."""
    return [(name, tuple(t.shape[: t.dim() - k])) for name, t, k in zip(_STATE_NAMES, state, (1, 2, 3))]
