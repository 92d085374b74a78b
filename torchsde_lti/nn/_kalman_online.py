r"""The online API of :class:`~torchsde_lti.KalmanFilter`: one report per live track at a time.

    state = kf.initial_state(batch_shape)                       # the prior N(m0, P0) per new track
    state, step = kf.step(state, y_k, dt_k, u=None, mask=None)  # predict over each track's own dt, update
    state = kf.predict(state, dt_k, u=None)                     # prediction only

:class:`KalmanOnline` (private to nn/) is the part of ``KalmanFilter`` that serves live
trackers: each track carries its own :class:`~torchsde_lti.KalmanState` and its own gap dt,
and every call predicts each track over its gap and updates it with its report (the same
step as the sequence filter's loop). The model's matrices are evaluated once per parameter
version while no gradient is recorded (:func:`~torchsde_lti.nn._online.evaluated`), with
the dt-independent part of the exact discretisation (:data:`OnlineModel`); the deployed
:class:`~torchsde_lti.OnlineStep` snapshots that model and calls :meth:`KalmanOnline._step`.
The sequence API (forward, smooth, forecast) and the parameters, prior and checks the online
calls read are the filter's own (:mod:`torchsde_lti.nn.kalman`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from torchsde_lti.core.discretization import check_matrix_exp_noise, discretize
from torchsde_lti.core.linalg import matvec
from torchsde_lti.core.validation import as_float_tensor, broadcast_batch, tracing
from torchsde_lti.filters.online import (
    KalmanState,
    KalmanStep,
    kalman_predict,
    kalman_step,
)
from torchsde_lti.nn._online import (
    Series,
    check_batches,
    evaluated,
    model_series,
    online_state,
    series_step,
    tracks_shape,
)
from torchsde_lti.nn._validate import ValidateArgs, online_report
from torchsde_lti.nn.sde import LTISDE, SDEMatrices

__all__ = ["KalmanOnline", "OnlineModel", "model_batches", "state_batches"]

#: The evaluated model of online calls: (SDE matrices, H, R, D, the discretisation series of
#: one parameter set or None), see :meth:`KalmanOnline._online_model`.
OnlineModel = tuple[SDEMatrices, Tensor, Tensor, Tensor | None, Series | None]


class KalmanOnline(ValidateArgs, nn.Module):
    """Base of :class:`~torchsde_lti.KalmanFilter` with its online calls :meth:`initial_state`,
    :meth:`step` and :meth:`predict` (module docstring); the filter provides the rest."""

    if TYPE_CHECKING:  # what the online calls read of their KalmanFilter
        sde: LTISDE
        H: Tensor
        R: Tensor
        D: Tensor | None

        @property
        def state_dim(self) -> int: ...

        @property
        def discretization_method(self) -> str: ...

        def _prior(self, mats: SDEMatrices, validate_args: bool) -> tuple[Tensor, Tensor]: ...

        def _check_u(
            self, u: Tensor, p: int, T: int, axis: str, dtype: torch.dtype, device: torch.device
        ) -> Tensor: ...

        def _check_values(self, mats: SDEMatrices, dt: Tensor, **named: Tensor | None) -> None: ...

    def initial_state(self, batch_shape: torch.Size | tuple[int, ...] | int = ()) -> KalmanState:
        """The prior N(m0, P0) at t₀ for ``batch_shape`` new tracks, for :meth:`step`.

        Returns :class:`~torchsde_lti.KalmanState` with mean (*batch, n) and cov
        (*batch, n, n), batch = ``batch_shape`` broadcast with the batch of m0 and P0 (a model
        with a parameter batch) (expanded views of the current m0, P0; ``()`` and no parameter
        batch: one track, unpacks as ``m0, P0 = kf.initial_state()``). ValueError naming
        ``batch_shape`` when it is not a shape or does not broadcast with the prior's.
        """
        shape = tracks_shape(batch_shape)
        with parametrize.cached():
            m0, P0 = self._prior(self.sde.matrices(), self.validate_args)
        n = self.state_dim
        batch = broadcast_batch([("batch_shape", shape), ("m0", m0.shape[:-1]), ("P0", P0.shape[:-2])])
        return KalmanState(m0.expand(*batch, n), P0.expand(*batch, n, n))

    def step(
        self, state: KalmanState, y: Tensor, dt: Tensor | float, u: Tensor | None = None, mask: Tensor | None = None
    ) -> tuple[KalmanState, KalmanStep]:
        """One report per live track: predict each track over its own dt, then update.

        The same step as the sequence filter's loop: iterating it over a series gives
        :meth:`forward`'s filtered moments and step log-likelihoods (to rounding). Without
        gradients the model's matrices are evaluated once per parameter version (in-place
        updates and assignments are seen; writes through ``tensor.data`` are not).

        Args:
            state: :class:`~torchsde_lti.KalmanState` (mean (..., n), cov (..., n, n)), from
                :meth:`initial_state` or a previous step.
            y: (..., m) one report per track; NaN = missing component.
            dt: (...) non-negative time since each track's state (a float: shared).
            u: optional (..., p) inputs held over the step.
            mask: optional bool (...) or (..., m); False = not observed (a pure prediction).

        Returns:
            (new :class:`~torchsde_lti.KalmanState`, :class:`~torchsde_lti.KalmanStep` with
            pred_mean, pred_cov, innovation (..., m), innovation_cov (..., m, m),
            log_likelihood (...), observed).
        """
        return self._step(evaluated(self, self._online_model), state, y, dt, u, mask)

    def _step(
        self,
        model: OnlineModel,
        state: KalmanState,
        y: Tensor,
        dt: Tensor | float,
        u: Tensor | None = None,
        mask: Tensor | None = None,
    ) -> tuple[KalmanState, KalmanStep]:
        """:meth:`step` with the model's evaluated matrices given (:meth:`_online_model`)."""
        mats, H, R, D, series = model
        state, dt, u = self._check_state(state, dt, u, mats)
        y, mask = online_report(y, mask, H, mats.F.dtype, mats.F.device)
        D = D if u is not None else None
        check_batches(
            [
                *state_batches(state),
                ("y", y.shape[:-1]),
                ("dt", dt.shape),
                *([] if u is None else [("u", u.shape[:-1])]),
                *model_batches(mats, H=H, R=R, D=D),
            ]
        )
        if self.validate_args:
            self._check_values(mats, dt, y=y, u=u, H=H, R=R, D=D, mean=state.mean, cov=state.cov)
        A, Q, c = self._online_step_model(mats, dt, u, series)
        if D is not None and u is not None:  # (D is None without u)
            y = y - matvec(D, u)
        return kalman_step(state, y, A, Q, H, R, c, mask)

    def predict(self, state: KalmanState, dt: Tensor | float, u: Tensor | None = None) -> KalmanState:
        """Prediction only, each track over its own dt (...): ``m⁻ = A m + G u``, ``P⁻ = A P Aᵀ + Q``."""
        mats, _, _, _, series = evaluated(self, self._online_model)
        state, dt, u = self._check_state(state, dt, u, mats)
        check_batches(
            [
                *state_batches(state),
                ("dt", dt.shape),
                *([] if u is None else [("u", u.shape[:-1])]),
                *model_batches(mats),
            ]
        )
        if self.validate_args:
            self._check_values(mats, dt, u=u, mean=state.mean, cov=state.cov)
        return kalman_predict(state, *self._online_step_model(mats, dt, u, series))

    def _online_model(self) -> OnlineModel:
        """(SDE matrices, H, R, D, the model's discretisation series or None), each
        parametrisation evaluated once. The series (:func:`~torchsde_lti.nn._online.model_series`:
        the dt-independent part of the exact discretisation, formed here: a nilpotent F's
        terminating series, any other F's doubling series terms): eagerly without gradients,
        where :func:`~torchsde_lti.nn._online.evaluated` caches this per parameter version (F's
        nilpotency read from its values); while traced (torch.export of
        :class:`~torchsde_lti.OnlineStep`) from the model's structure (the series then inside
        the program); otherwise None (core's discretisation)."""
        with parametrize.cached():
            mats = self.sde.matrices()
            series = None
            if tracing():
                series = self._structural_series(mats)
            elif not torch.is_grad_enabled():
                series = model_series(*mats)
            return mats, self.H, self.R, self.D, series

    def _structural_series(self, mats: SDEMatrices) -> Series | None:
        """The discretisation series of one parameter set with F's nilpotency taken from the
        model's structure (no value of F read: traceable), else None (a parameter batch)."""
        return model_series(*mats, index=self.sde.structural_nilpotency(), read_values=False)

    def _online_step_model(
        self, mats: SDEMatrices, dt: Tensor, u: Tensor | None, series: Series | None = None
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """(A, Q, G u or None) of each track's gap dt (...): one batched exact discretisation,
        with the doubling method from the model's ``series`` (its dt-independent part formed
        once: no value checks, the same values as core's doubling to rounding), else core's
        :func:`~torchsde_lti.core.discretize`."""
        if series is not None and self.discretization_method == "doubling":
            A, Q, G = series_step(series, dt)
        else:
            A, Q, G = discretize(
                mats.F, mats.L, mats.Qc, dt, B=mats.B, method=self.discretization_method, validate_args=False
            )
            self._check_van_loan_noise(Q)
        return A, Q, (matvec(G, u) if (u is not None and G is not None) else None)

    def _check_van_loan_noise(self, Q: Tensor) -> None:
        """With ``method="matrix_exp"`` and value checks on, ValueError where its Q (..., n, n)
        is not finite or not PSD (:func:`~torchsde_lti.core.discretization.check_matrix_exp_noise`):
        the discretisations of checked parameters skip core's result check, and Van Loan's Q,
        unlike the doubling's, is not PSD by construction."""
        if self.discretization_method == "matrix_exp" and self.validate_args:
            check_matrix_exp_noise(Q)

    def _check_state(
        self, state: KalmanState | tuple[Tensor, Tensor], dt: Tensor | float, u: Tensor | None, mats: SDEMatrices
    ) -> tuple[KalmanState, Tensor, Tensor | None]:
        """(state, dt, u) of an online call converted and their shapes checked."""
        state, dt = online_state(state, dt, mats.F)
        if u is not None:  # one step: (..., p) checked as (..., 1, p)
            dtype, device = mats.F.dtype, mats.F.device
            p = mats.B.shape[-1] if mats.B is not None else (self.D.shape[-1] if self.D is not None else 0)
            u = as_float_tensor(u, "u", dtype, device)
            u = self._check_u(u.unsqueeze(-2) if u.dim() else u.reshape(1, 1), p, 1, "1", dtype, device).squeeze(-2)
        return state, dt, u


def state_batches(state: KalmanState) -> list[tuple[str, tuple[int, ...]]]:
    """The named batch shapes of a Kalman state's fields (for :func:`~torchsde_lti.nn._online.check_batches`)."""
    return [("state.mean", tuple(state.mean.shape[:-1])), ("state.cov", tuple(state.cov.shape[:-2]))]


def model_batches(mats: SDEMatrices, **named: Tensor | None) -> list[tuple[str, tuple[int, ...]]]:
    """The named batch shapes of a model's matrices (..., r, c): the SDE's F, L, Qc, B (a
    parameter batch) and ``named`` ones such as H, R, D (None skipped), for
    :func:`~torchsde_lti.nn._online.check_batches`."""
    pairs = [*zip(SDEMatrices._fields, mats), *named.items()]
    return [(f"sde.{k}" if k in SDEMatrices._fields else k, tuple(x.shape[:-2])) for k, x in pairs if x is not None]
