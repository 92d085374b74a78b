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

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core.linalg import sym
from torchsde_lti.core.validation import broadcast_shapes
from torchsde_lti.filters.inputs import mask_observation_model, whiten
from torchsde_lti.filters.layout import mv, tr
from torchsde_lti.filters.noise import GAUSSIAN, NoiseModel
from torchsde_lti.filters.results import serializable
from torchsde_lti.filters.sequential import _joseph_step, _mm, _mm_t

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
    ``log N(y^obs; H^obs m⁻, S^obs) = −½ Σ_j (log s_j + e_j² / s_j + log 2π [j observed]) − log|L|``.
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
        The moments are batch-first views of batch-last storage (the layout the next step
        reads without a copy).
    """
    if mask is not None:
        y = torch.where(mask.unsqueeze(-1) if mask.dim() < y.dim() else mask, y, torch.nan)
    # the loop's batch-last layout (event dims first, each batch padded to nd dims): views, of
    # the batch-last storage that the discretisation and the previous step return
    nd = max(state.mean.dim() - 1, state.cov.dim() - 2, A.dim() - 2, Q.dim() - 2, H.dim() - 2, R.dim() - 2, y.dim() - 1)
    if c is not None:
        nd = max(nd, c.dim() - 1)
    mean, yb, cb = _batch_last(state.mean, 1, nd), _batch_last(y, 1, nd), None if c is None else _batch_last(c, 1, nd)
    P, Ab, Qb, Hb, Rb = (_batch_last(x, 2, nd) for x in (state.cov, A, Q, H, R))
    obs = yb == yb  # (m, *b): not NaN
    y0 = yb.nan_to_num(0.0, math.inf, -math.inf)
    h_rows, y_rows, log_det = whiten(*mask_observation_model(Hb, Rb, obs), y0)
    pm, pc, mean, P, es, ss = _joseph_step(Ab, Qb, mean, P, cb, h_rows, y_rows)
    P, core = noise.step_update(P, torch.stack(es), torch.stack(ss), obs)  # (m, *b) each; the Gaussian's P stands
    ll = -0.5 * core - log_det
    innovation = (y0 - mv(Hb, pm)) * obs
    # S = H P⁻ Hᵀ + R by multiply-adds over the batch, as the sequence loop forms it (a matmul folds the
    # batch dims into one: torch's export of the IMM's scan failed on it where batch and modes were equal)
    HPH = _mm_t(_mm(Hb, pc), Hb)  # (m, m, *b)
    S = torch.add(Rb, HPH + tr(HPH), alpha=0.5)
    if not nd:  # (no batch: the results are in their shapes)
        return KalmanState(mean, P), KalmanStep(pm, pc, innovation, S, ll, obs)
    # batch-first views of the batch-last results, each expanded to the whole batch
    pm, mean, innovation, obs = (x.movedim(0, -1) for x in (pm, mean, innovation, obs))
    pc, P, S = (x.movedim((0, 1), (-2, -1)) for x in (pc, P, S))
    batch = torch.Size(max(a, b) for a, b in zip(mean.shape[:-1], P.shape[:-2]))  # (every input's batch)
    n, m = mean.shape[-1], obs.shape[-1]
    return KalmanState(_full(mean, batch, n), _full(P, batch, n, n)), KalmanStep(
        _full(pm, batch, n),
        _full(pc, batch, n, n),
        _full(innovation, batch, m),
        _full(S, batch, m, m),
        _full(ll, batch),
        _full(obs, batch, m),
    )


def _batch_last(x: Tensor, event_ndim: int, batch_ndim: int) -> Tensor:
    """``(*b, *event) -> (*event, *b)`` as a view, b left-padded with size-1 dims to
    ``batch_ndim`` dims (the loop's layout; batch-last storage gives a contiguous view)."""
    if not batch_ndim:
        return x
    if x.dim() < event_ndim + batch_ndim:
        x = x.reshape((1,) * (event_ndim + batch_ndim - x.dim()) + tuple(x.shape))
    return x.movedim(tuple(range(batch_ndim, batch_ndim + event_ndim)), tuple(range(event_ndim)))


def _full(x: Tensor, batch: torch.Size, *event: int) -> Tensor:
    """x expanded to the step's whole batch (a view; x itself where it has it)."""
    return x if x.shape[: x.dim() - len(event)] == batch else x.expand(*batch, *event)
