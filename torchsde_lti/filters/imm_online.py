"""Online IMM filtering: :func:`imm_step`, one cycle of the interacting multiple model filter
(the cycle of :func:`~torchsde_lti.filters.imm.imm_filter`) for every live track, each with its
own gap, the mode probabilities in the :class:`IMMState`; what
:func:`~torchsde_lti.filters.online.kalman_step` is for one model."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core.validation import broadcast_shapes
from torchsde_lti.filters.imm import combine, imm_cycle, imm_predict
from torchsde_lti.filters.noise import GAUSSIAN, NoiseModel
from torchsde_lti.filters.results import serializable

__all__ = ["IMMState", "IMMStep", "imm_predict_state", "imm_step"]


@serializable
class IMMState(NamedTuple):
    """The IMM filter's belief about live tracks, batch leading.

    mode_prob: (..., M) mode probabilities. mode_mean: (..., M, n), mode_cov: (..., M, n, n)
    the mode-matched moments.
    """

    mode_prob: Tensor
    mode_mean: Tensor
    mode_cov: Tensor

    def select(self, idx: Tensor | slice | int | Sequence[int]) -> IMMState:
        """The tracks ``idx`` of the (first) batch dimension: a bool mask, indices or a slice."""
        return type(self)(*(t[idx] for t in self))

    @classmethod
    def cat(cls, states: Sequence[IMMState]) -> IMMState:
        """The tracks of several states (each with one batch dimension) in one state."""
        return cls(*(torch.cat(fields) for fields in zip(*states)))


@serializable
class IMMStep(NamedTuple):
    """What one IMM update saw, per track.

    mean: (..., n), cov: (..., n, n) the moment-matched filtered state.
    pred_mode_prob: (..., M) the predicted mode probabilities c.
    mode_innovation: (..., M, m) ``y − H_j m⁻_j`` (0 in unobserved components);
    mode_innovation_cov: (..., M, m, m) ``S_j``.
    log_likelihood: (...) ``log Σ_j c_j N(y; ŷ_j, S_j)`` (0 for a fully missing report).
    observed: (..., m) bool.
    """

    mean: Tensor
    cov: Tensor
    pred_mode_prob: Tensor
    mode_innovation: Tensor
    mode_innovation_cov: Tensor
    log_likelihood: Tensor
    observed: Tensor


def imm_step(
    state: IMMState,
    y: Tensor,
    A: Tensor,
    Q: Tensor,
    Pi: Tensor,
    H: Tensor,
    R: Tensor,
    mask: Tensor | None = None,
    noise: NoiseModel = GAUSSIAN,
) -> tuple[IMMState, IMMStep]:
    """One IMM cycle of every track: the cycle of :func:`~torchsde_lti.filters.imm.imm_filter`'s
    loop (:func:`~torchsde_lti.filters.imm.imm_cycle`), then the moment-matched state.

    Args:
        state: mode_prob (..., M), mode_mean (..., M, n), mode_cov (..., M, n, n).
        y: (..., m) reports; NaN = missing component.
        A, Q: (..., M, n, n) each mode over each track's gap. Pi: (..., M, M) mode transitions.
        H: (..., M or 1, m, n), R: (..., M or 1, m, m) observation model.
        mask: optional bool (...) or (..., m); False = not observed.
        noise: the observation-noise model of every mode (:func:`~torchsde_lti.filters.imm.imm_filter`).

    Returns:
        (:class:`IMMState`, :class:`IMMStep`).
    """
    if mask is not None:  # (a report not observed is a missing one: NaN)
        y = torch.where(mask.unsqueeze(-1) if mask.dim() < y.dim() else mask, y, torch.nan)
    cyc = imm_cycle(*state, Pi, A, Q, H, R, y, noise)
    x, P = combine(cyc.mode_prob, cyc.mode_mean, cyc.mode_cov, noise)
    new = IMMState(cyc.mode_prob, cyc.mode_mean, cyc.mode_cov)
    batch = broadcast_shapes(cyc.log_likelihood.shape, cyc.observed.shape[:-1])
    return new, IMMStep(
        x,
        P,
        cyc.pred_mode_prob,
        cyc.mode_innovation,
        cyc.mode_innovation_cov,
        cyc.log_likelihood.expand(batch),
        cyc.observed.expand(*batch, y.shape[-1]),
    )


def imm_predict_state(state: IMMState, A: Tensor, Q: Tensor, Pi: Tensor, noise: NoiseModel = GAUSSIAN) -> IMMState:
    """Prediction only (mixing, then each mode's A_j, Q_j): the IMM's state at the report time.

    A, Q: (..., M, n, n); Pi: (..., M, M); noise: the modes' noise model (a Student-t's scale
    matrices mix as covariances). Returns the predicted :class:`IMMState` (mode_prob = c = μ Pi).
    """
    p = imm_predict(*state, A.unsqueeze(-4), Q.unsqueeze(-4), Pi.unsqueeze(-3), noise)
    return IMMState(p.mode_probabilities.squeeze(-2), p.mode_mean.squeeze(-3), p.mode_cov.squeeze(-4))
