r"""Online Kalman filtering: one report per track at a time, each track with its own step.

A live tracker holds a :class:`KalmanState` (mean (..., n), cov (..., n, n), one entry per
live track) and, when reports arrive, calls :func:`kalman_step` with every track's own
discrete model (A, Q) over its own gap. The step is the SAME predict/update as the
sequence filter's loop (the loop's step in :mod:`~torchsde_lti.filters.sequential`: predict
``m⁻ = A m + c``, ``P⁻ = A P Aᵀ + Q``, then whitened scalar Joseph updates with the observed
components of y), so running :func:`kalman_step` over a series reproduces
:func:`~torchsde_lti.kalman_filter` to rounding. Missing reports (NaN in y, or mask False)
are pure predictions and contribute 0 to the log-likelihood.

:func:`~torchsde_lti.filters.imm_online.imm_step` is the same for the interacting multiple
model filter, with the mode probabilities in the state.

Tracks join and leave by indexing or concatenating the state (every field has the batch
leading)::

    state = state.select(keep)                      # drop tracks (bool mask or indices)
    state = KalmanState.cat([state, new_tracks])   # add tracks

:class:`KalmanStep` carries what gating and data association need: the innovation
``e = y − H m⁻``, its covariance ``S = H P⁻ Hᵀ + R`` and the step log-likelihood
``log N(e; 0, S)`` over the observed components.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core.linalg import matvec, sym, to_batch_last
from torchsde_lti.core.validation import broadcast_shapes
from torchsde_lti.filters.inputs import LOG_2PI, mask_observation_model, whiten
from torchsde_lti.filters.noise import GAUSSIAN, NoiseModel
from torchsde_lti.filters.results import serializable
from torchsde_lti.filters.sequential import _joseph_step

__all__ = ["KalmanState", "KalmanStep", "kalman_predict", "kalman_step"]


@serializable
class KalmanState(NamedTuple):
    """The filter's belief about live tracks, batch leading.

    mean: (..., n) state means. cov: (..., n, n) state covariances.
    """

    mean: Tensor
    cov: Tensor

    def select(self, idx: Tensor | slice | int | Sequence[int]) -> KalmanState:
        """The tracks ``idx`` of the (first) batch dimension: a bool mask, indices or a slice."""
        return type(self)(*(t[idx] for t in self))

    @classmethod
    def cat(cls, states: Sequence[KalmanState]) -> KalmanState:
        """The tracks of several states (each with one batch dimension) in one state."""
        return cls(*(torch.cat(fields) for fields in zip(*states)))


@serializable
class KalmanStep(NamedTuple):
    """What one update saw, per track.

    pred_mean: (..., n) m⁻. pred_cov: (..., n, n) P⁻.
    innovation: (..., m) ``y − H m⁻`` (0 in unobserved components).
    innovation_cov: (..., m, m) ``S = H P⁻ Hᵀ + R`` (all components; gate with
        ``eᵀ S⁻¹ e`` on the observed ones).
    log_likelihood: (...) ``log N(y^obs; H^obs m⁻, S^obs)`` (0 for a fully missing report).
    observed: (..., m) bool, the components that entered the update.
    """

    pred_mean: Tensor
    pred_cov: Tensor
    innovation: Tensor
    innovation_cov: Tensor
    log_likelihood: Tensor
    observed: Tensor


def kalman_predict(state: KalmanState, A: Tensor, Q: Tensor, c: Tensor | None = None) -> KalmanState:
    """Prediction only: ``m⁻ = A m + c``, ``P⁻ = A P Aᵀ + Q``.

    Args:
        state: mean (..., n), cov (..., n, n).
        A: (..., n, n) transitions. Q: (..., n, n) process noise. c: optional (..., n) input term G u.

    Returns:
        :class:`KalmanState` of the predictions (batch dims broadcast).
    """
    pm = (A @ state.mean.unsqueeze(-1)).squeeze(-1)
    if c is not None:
        pm = pm + c
    pc = sym(A @ state.cov @ A.mT + Q)
    batch = broadcast_shapes(pm.shape[:-1], pc.shape[:-2])
    n = pm.shape[-1]
    return KalmanState(pm.expand(*batch, n), pc.expand(*batch, n, n))


def kalman_step(
    state: KalmanState,
    y: Tensor,
    A: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    c: Tensor | None = None,
    mask: Tensor | None = None,
    noise: NoiseModel = GAUSSIAN,
) -> tuple[KalmanState, KalmanStep]:
    r"""One predict + update of every track: the step of the sequence filter's loop.

    Predict ``m⁻ = A m + c``, ``P⁻ = A P Aᵀ + Q``; mask (a NaN in y or mask False: a zero row
    of H and a decoupled unit variance in R), whiten with the Cholesky factor L of the masked
    R (``H' = L⁻¹ H``, ``y' = L⁻¹ y``) and take one scalar Joseph update per component
    (:func:`~torchsde_lti.filters.sequential._joseph_step`, batch-last: the loop's own step);
    ``log N(y^obs; H^obs m⁻, S^obs) = −½ Σ_j (log s_j + e_j² / s_j) − ½ n_obs log 2π − log|L|``.
    One path for every batch size, dtype and device, eager or traced; arguments are taken as
    checked (the modules check them once at their boundary).

    Args:
        state: mean (..., n), cov (..., n, n) before the step.
        y: (..., m) reports; NaN = missing component.
        A: (..., n, n) transitions over each track's gap. Q: (..., n, n) process noise.
        H: (..., m, n) observation matrix. R: (..., m, m) noise covariance (symmetric PD).
        c: optional (..., n) input term ``G u`` of the prediction (the feedthrough ``D u``,
            if any, is subtracted from y by the caller).
        mask: optional bool (...) (whole report) or (..., m); False = not observed.
        noise: the observation-noise model (:mod:`~torchsde_lti.filters.noise`), as in the
            sequence filter: a Student-t's update rescales the filtered scale matrix and its
            log-likelihood is the Student-t predictive density.

    Returns:
        (:class:`KalmanState` after the update, :class:`KalmanStep`); batch dims broadcast.
        The covariances are batch-first views of batch-last storage (the layout the next
        step reads without a copy).
    """
    if mask is not None:
        y = torch.where(mask.unsqueeze(-1) if mask.dim() < y.dim() else mask, y, torch.nan)
    obs = ~torch.isnan(y)
    y0 = torch.where(obs, y, torch.zeros((), dtype=y.dtype, device=y.device))
    Hm, Rm = mask_observation_model(H, R, obs)
    Hw, yw, log_det = whiten(Hm, Rm, y0)
    n, m = A.shape[-1], y.shape[-1]
    shapes = [state.mean.shape[:-1], state.cov.shape[:-2], A.shape[:-2], Q.shape[:-2], Hw.shape[:-2], y.shape[:-1]]
    mb = broadcast_shapes(*shapes, *(() if c is None else (c.shape[:-1],)))
    # the sequence loop's batch-last layout (event dims first, the batch contiguous)
    Ab, Qb, Pb = (to_batch_last(x.expand(*mb, n, n), 2) for x in (A, Q, state.cov))
    mean_b = to_batch_last(state.mean.expand(*mb, n), 1)
    c_b = None if c is None else to_batch_last(c.expand(*mb, n), 1)
    h_rows = to_batch_last(Hw.expand(*mb, m, n), 2).unbind(0)
    y_vals = to_batch_last(yw.expand(*mb, m), 1).unbind(0)
    pm, pc, mean, P, es, ss = _joseph_step(Ab, Qb, mean_b, Pb, c_b, h_rows, y_vals, None, None)
    d = obs.to(y.dtype).sum(-1)
    P = noise.update(P, es, ss, d)  # (the Gaussian's: P itself)
    e_t, s_t = torch.stack(es), torch.stack(ss)  # (m, *mb)
    core = noise.log_likelihood_core(torch.log(s_t).sum(0), (e_t * e_t / s_t).sum(0), d)
    ll = core - 0.5 * LOG_2PI * d - log_det
    pred_mean, filt_mean = pm.movedim(0, -1), mean.movedim(0, -1)
    pred_cov, filt_cov = pc.movedim((0, 1), (-2, -1)), P.movedim((0, 1), (-2, -1))
    innovation = (y0 - matvec(H, pred_mean)) * obs
    innovation_cov = sym(H @ pred_cov @ H.mT + R)
    return KalmanState(filt_mean, filt_cov), KalmanStep(
        pred_mean,
        pred_cov,
        innovation.expand(*mb, m),
        innovation_cov.expand(*mb, m, m),
        ll.expand(mb),
        obs.expand(*mb, m),
    )
