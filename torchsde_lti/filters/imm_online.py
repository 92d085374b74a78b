"""Online IMM filtering: :func:`imm_step`, one cycle of the interacting multiple model filter
(the cycle of :func:`~torchsde_lti.filters.imm.imm_filter`) for every live track, each with its
own gap, the mode probabilities in the :class:`IMMState`; what
:func:`~torchsde_lti.filters.online.kalman_step` is for one model (the same float32 widening
and chunking)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core.validation import broadcast_shapes
from torchsde_lti.filters.imm import combine, imm_cycle, imm_predict
from torchsde_lti.filters.inputs import mask_observation_model
from torchsde_lti.filters.online import _by_chunks, _narrowed, _online_observed, _rows_per_chunk, _widened, _widens
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
    state: IMMState, y: Tensor, A: Tensor, Q: Tensor, Pi: Tensor, H: Tensor, R: Tensor, mask: Tensor | None = None
) -> tuple[IMMState, IMMStep]:
    """One IMM cycle of every track (the cycle of :func:`~torchsde_lti.filters.imm.imm_filter`;
    float32 in float64, its results rounded once, as :func:`~torchsde_lti.filters.online.kalman_step`); eagerly on the CPU in chunks of tracks along the leading batch dimension beyond
    :data:`~torchsde_lti.filters.online.CHUNKED_STEP_MIN_BYTES` of covariances (one mode's per track).

    Args:
        state: mode_prob (..., M), mode_mean (..., M, n), mode_cov (..., M, n, n).
        y: (..., m) reports; NaN = missing component.
        A, Q: (..., M, n, n) each mode over each track's gap. Pi: (..., M, M) mode transitions.
        H: (..., M or 1, m, n), R: (..., M or 1, m, m) observation model.
        mask: optional bool (...) or (..., m); False = not observed.

    Returns:
        (:class:`IMMState`, :class:`IMMStep`).
    """
    if _widens(state.mode_cov):
        w = _widened((state, y, A, Q, Pi, H, R))
        return _narrowed(imm_step(w[0], w[1], w[2], w[3], w[4], w[5], w[6], mask))
    if mask is not None and mask.dim() < y.dim():
        mask = mask.unsqueeze(-1)
    n = A.shape[-1]
    mb = broadcast_shapes(
        state.mode_prob.shape[:-1], state.mode_mean.shape[:-2], state.mode_cov.shape[:-3], y.shape[:-1],
        A.shape[:-3], Q.shape[:-3], Pi.shape[:-2], H.shape[:-3], R.shape[:-3],
        *(() if mask is None else (mask.shape[:-1],)),
    )  # fmt: skip
    # (the bound and chunk size in ONE mode's covariances: a chunk of the IMM cycle costs about M
    # times the torch calls of a Kalman step, so its best chunks hold about M times the bytes)
    rows = _rows_per_chunk(mb, n * n * A.element_size(), y)
    if rows >= (mb[0] if mb else 1):
        return _imm_step(state, y, A, Q, Pi, H, R, mask)
    args: list[tuple[Tensor | None, int]] = [(state.mode_prob, 1), (state.mode_mean, 2), (state.mode_cov, 3)]
    args += [(y, 1), (A, 3), (Q, 3), (Pi, 2), (H, 3), (R, 3), (mask, 1)]

    def chunk(prob: Tensor, mean: Tensor, cov: Tensor, *rest: Tensor | None) -> tuple[IMMState, IMMStep]:
        yk, Ak, Qk, Pk, Hk, Rk, mk, _ = rest
        assert yk is not None and Ak is not None and Qk is not None and Pk is not None
        assert Hk is not None and Rk is not None
        return _imm_step(IMMState(prob, mean, cov), yk, Ak, Qk, Pk, Hk, Rk, mk)

    new, out = _by_chunks(chunk, args, mb, rows)
    return new, out  # type: ignore[return-value]


def _imm_step(
    state: IMMState, y: Tensor, A: Tensor, Q: Tensor, Pi: Tensor, H: Tensor, R: Tensor, mask: Tensor | None
) -> tuple[IMMState, IMMStep]:
    """:func:`imm_step` in one pass (mask: (..., 1 or m) or None)."""
    m = y.shape[-1]
    obs, y0 = _online_observed(y, mask)
    if obs is None:
        n_obs = torch.full(y0.shape[:-1], float(m), dtype=y0.dtype, device=y0.device)
        observed = torch.ones(y0.shape, dtype=torch.bool, device=y0.device)
    else:
        observed = obs.expand(*obs.shape[:-1], m)
        n_obs = observed.to(y0.dtype).sum(-1)
    Hm, Rm = mask_observation_model(H, R, None if obs is None else observed.unsqueeze(-2))
    cyc = imm_cycle(*state, Pi, A, Q, Hm, Rm, y0, n_obs)
    x, P = combine(cyc.mode_prob, cyc.mode_mean, cyc.mode_cov)
    new = IMMState(cyc.mode_prob, cyc.mode_mean, cyc.mode_cov)
    batch = broadcast_shapes(cyc.log_likelihood.shape, observed.shape[:-1])
    return new, IMMStep(
        x,
        P,
        cyc.pred_mode_prob,
        cyc.mode_innovation,
        cyc.mode_innovation_cov,
        cyc.log_likelihood.expand(batch),
        observed.expand(*batch, m),
    )


def imm_predict_state(state: IMMState, A: Tensor, Q: Tensor, Pi: Tensor) -> IMMState:
    """Prediction only (mixing, then each mode's A_j, Q_j): the IMM's state at the report time.

    A, Q: (..., M, n, n); Pi: (..., M, M). Returns the predicted :class:`IMMState`
    (mode_prob = c = μ Pi).
    """
    p = imm_predict(*state, A.unsqueeze(-4), Q.unsqueeze(-4), Pi.unsqueeze(-3))
    return IMMState(p.mode_probabilities.squeeze(-2), p.mode_mean.squeeze(-3), p.mode_cov.squeeze(-4))
