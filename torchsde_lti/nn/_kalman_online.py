r"""The online API of :class:`~torchsde_lti.KalmanFilter`: one report per live track at a time.

    state = kf.initial_state(batch_shape)                       # the prior N(m0, P0) per new track
    state, step = kf.step(state, y_k, dt_k, u=None, mask=None)  # predict over each track's own dt, update
    state = kf.predict(state, dt_k, u=None)                     # prediction only

:class:`KalmanOnline` (private to nn/) is the part of ``KalmanFilter`` that serves live
trackers: each track carries its own :class:`~torchsde_lti.KalmanState` and its own gap dt,
and every call predicts each track over its gap and updates it with its report. Online =
sequence: the step is the sequence filter's loop step
(:func:`~torchsde_lti.filters.online.kalman_step`), its (A, Q, G) the sequence filter's
discretisation (:func:`~torchsde_lti.nn._online.discretize_steps`), its checks the sequence
filter's (arguments once at the boundary; with value checks on, the outputs too), so a
series of steps gives :meth:`forward`'s values and raises its errors.

The model's matrices are evaluated once per parameter version while no gradient is recorded
(:func:`~torchsde_lti.nn._online.evaluated`), with the dt-independent part of the exact
discretisation (:class:`OnlineModel`, :meth:`KalmanOnline.online_model`); the deployed
:class:`~torchsde_lti.OnlineStep` snapshots that model and passes it to :meth:`KalmanOnline.step`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from torchsde_lti.core.discretization import check_matrix_exp_noise
from torchsde_lti.core.linalg import matvec
from torchsde_lti.core.validation import as_float_tensor, broadcast_batch, check_matrix, tracing
from torchsde_lti.filters.noise import GAUSSIAN, NoiseModel
from torchsde_lti.filters.online import KalmanState, KalmanStep, kalman_predict, kalman_step
from torchsde_lti.nn._online import (
    Series,
    check_batches,
    discretize_steps,
    evaluated,
    model_series,
    online_state,
    tracks_shape,
)
from torchsde_lti.nn._register import register_tensor
from torchsde_lti.nn._validate import (
    ValidateArgs,
    _finite,
    _psd_flags,
    all_pass,
    check_outcome,
    online_report,
    outcome_flags,
)
from torchsde_lti.nn.parametrizations import PositiveDefinite
from torchsde_lti.nn.sde import LTISDE, SDEMatrices

if TYPE_CHECKING:
    from torchsde_lti.nn.noise import NoiseOption

__all__ = ["KalmanOnline", "OnlineModel", "model_batches", "state_batches"]


class OnlineModel(NamedTuple):
    """The evaluated model of a :class:`~torchsde_lti.KalmanFilter`'s online calls
    (:meth:`~torchsde_lti.KalmanFilter.online_model`): what a step reads of the filter.

    mats: the SDE's matrices (F, L, Qc, B); H: (..., m, n); R: (..., m, m); D: (..., m, p) or
    None; series: the dt-independent part of the exact discretisation of one parameter set
    (:func:`~torchsde_lti.core.discretization.discretization_series`), None for a parameter batch;
    noise: the observation-noise model (:mod:`~torchsde_lti.filters.noise`).
    """

    mats: SDEMatrices
    H: Tensor
    R: Tensor
    D: Tensor | None
    series: Series | None
    noise: NoiseModel = GAUSSIAN


class KalmanOnline(ValidateArgs, nn.Module):
    """Base of :class:`~torchsde_lti.KalmanFilter` with its prior and its online calls
    :meth:`initial_state`, :meth:`step` and :meth:`predict` (module docstring); the filter
    provides the rest."""

    if TYPE_CHECKING:  # what the online calls read of their KalmanFilter
        sde: LTISDE
        H: Tensor
        R: Tensor
        D: Tensor | None

        @property
        def state_dim(self) -> int: ...

        @property
        def discretization_method(self) -> str: ...

        m0: Tensor
        P0: Tensor | None
        prior_mode: str
        diffuse_variance: float
        noise: NoiseOption

        def _check_u(
            self, u: Tensor, p: int, T: int, axis: str, dtype: torch.dtype, device: torch.device
        ) -> Tensor: ...

        def _check_values(
            self, mats: SDEMatrices, dt: Tensor, psd: tuple[tuple[str, Tensor], ...] = (), **named: Tensor | None
        ) -> None: ...

    def _init_prior(
        self, P0: Tensor | str | None, learned: bool, n: int, dtype: torch.dtype, device: torch.device
    ) -> None:
        """:attr:`prior_mode` and the P0 parameter/buffer (None unless the mode is "given")."""
        diffuse = self.diffuse_variance * torch.eye(n, dtype=dtype, device=device)
        if isinstance(P0, str):
            if P0 != "diffuse":
                raise ValueError(f"P0 must be a tensor, None (the model's prior_covariance()) or 'diffuse', got {P0!r}")
            self.prior_mode, P0_t = "diffuse", diffuse
        elif P0 is not None:
            P0_t = as_float_tensor(P0, "P0", dtype, device).detach().clone()
            check_matrix(P0_t, "P0", rows=n, cols=n)
            self.prior_mode = "given"
        else:
            try:
                with torch.no_grad():
                    P0_t = self.sde.prior_covariance(validate_args=True, diffuse_variance=self.diffuse_variance)
                    P0_t = P0_t.detach().clone()
                self.prior_mode = "model"
            except ValueError:
                self.prior_mode, P0_t = "diffuse", diffuse
        if learned:
            if bool((torch.linalg.cholesky_ex(P0_t).info != 0).any()):
                raise ValueError(
                    f"learn contains 'P0', but the {self.prior_mode} prior covariance is singular (e.g. a shaped "
                    "model's steady-state start: every entry involving a system state is 0) and a learnable P0 is "
                    "parametrised positive definite; pass an initial P0 tensor"
                )
            self.prior_mode = "given"  # learnable, initialised at that prior's value
        if self.prior_mode == "given":
            register_tensor(self, "P0", P0_t, learned)
            parametrize.register_parametrization(
                self, "P0", PositiveDefinite(name="P0", size=n).to(dtype=dtype, device=device)
            )
        else:
            self.register_buffer("P0", None)

    def _prior(self, mats: SDEMatrices, validate_args: bool, P0: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """(m0, P0) from already evaluated (and checked) SDE matrices; ``P0``: the given prior's
        value when the caller has read it already (each parametrisation is read once a call)."""
        if self.prior_mode == "given":
            P0 = self.P0 if P0 is None else P0
        elif self.prior_mode == "model":
            try:
                P0 = self.sde.prior_covariance(
                    mats, validate_args=validate_args, diffuse_variance=self.diffuse_variance
                )
            except ValueError as err:
                raise ValueError(
                    "the default prior P0 is the model's prior_covariance(), but its F is no longer Hurwitz; "
                    "pass P0 explicitly or constrain F (F_constraint='hurwitz')"
                ) from err
        else:
            F = mats.F
            P0 = self.diffuse_variance * torch.eye(F.shape[-1], dtype=F.dtype, device=F.device)
        assert P0 is not None
        return self.m0, P0

    def initial_state(self, batch_shape: torch.Size | tuple[int, ...] | int = ()) -> KalmanState:
        """The prior N(m0, P0) at t₀ for ``batch_shape`` new tracks, for :meth:`step`.

        Returns :class:`~torchsde_lti.KalmanState` with mean (*batch, n) and cov
        (*batch, n, n), batch = ``batch_shape`` broadcast with the batch of m0 and P0 (a model
        with a parameter batch) (expanded views of the current m0, P0; ``()`` and no parameter
        batch: one track, unpacks as ``m0, P0 = kf.initial_state()``). ValueError naming
        ``batch_shape`` when it is not a shape or does not broadcast with the prior's.
        """
        shape = tracks_shape(batch_shape)
        m0, P0 = self._prior(self.sde.matrices(), self.validate_args)
        n = self.state_dim
        batch = broadcast_batch([("batch_shape", shape), ("m0", m0.shape[:-1]), ("P0", P0.shape[:-2])])
        return KalmanState(m0.expand(*batch, n), P0.expand(*batch, n, n))

    def step(
        self,
        state: KalmanState,
        y: Tensor,
        dt: Tensor | float,
        u: Tensor | None = None,
        mask: Tensor | None = None,
        *,
        model: OnlineModel | None = None,
    ) -> tuple[KalmanState, KalmanStep]:
        """One report per live track: predict each track over its own dt, then update.

        The step of the sequence filter's loop with the sequence filter's discretisation and
        checks: iterating it over a series gives :meth:`forward`'s filtered moments and step
        log-likelihoods, and raises where :meth:`forward` raises (with value checks on, a
        non-finite log-likelihood or state is a
        :class:`~torchsde_lti.NonFiniteLikelihoodError`). Without gradients the model's
        matrices are evaluated once per parameter version (in-place updates and assignments
        are seen; writes through ``tensor.data`` are not).

        Args:
            state: :class:`~torchsde_lti.KalmanState` (mean (..., n), cov (..., n, n)
                symmetric PSD), from :meth:`initial_state` or a previous step.
            y: (..., m) one report per track; NaN = missing component.
            dt: (...) non-negative time since each track's state (a float: shared).
            u: optional (..., p) inputs held over the step.
            mask: optional bool (...) or (..., m); False = not observed (a pure prediction).
            model: the evaluated model to step with (:meth:`online_model`, e.g. a snapshot
                held by :class:`~torchsde_lti.OnlineStep`); default the filter's current one.

        Returns:
            (new :class:`~torchsde_lti.KalmanState`, :class:`~torchsde_lti.KalmanStep` with
            pred_mean, pred_cov, innovation (..., m), innovation_cov (..., m, m),
            log_likelihood (...), observed).
        """
        (mats, H, R, D, series, noise), model_ok = self._model_and_flag(model)
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
        validate = self.validate_args and not tracing()
        if validate and self.discretization_method == "matrix_exp":  # (its Q is checked after the arguments)
            self._check_step_arguments(mats, dt, state, y, u, H, R, D)
        A, Q, c = self._step_model(mats, dt, u, series)
        observed = y if D is None or u is None else y - matvec(D, u)
        new, out = kalman_step(state, observed, A, Q, H, R, c, mask, noise)
        if validate:
            # the arguments' tests and the outcome's in ONE synchronisation; a NaN or Inf in the
            # state's mean, in dt or in the model reaches the new mean (or the log-likelihood)
            n = new.cov.shape[-1]
            covariances = torch.cat([state.cov.reshape(-1, n, n), new.cov.reshape(-1, n, n)])
            flags = [
                *([] if model_ok is None else [model_ok]),
                (dt >= 0).all(),
                *([] if mask is None else [~torch.isinf(y).any()]),  # (else an Inf reaches the log-likelihood)
                *([] if u is None else [_finite([u] if D is None else [u, D])]),
                *_psd_flags(covariances),  # (the state's and the new one: one factorisation)
                *outcome_flags((out.log_likelihood, new.mean), (), R, noise.update_bound((H, out.observed, new.cov))),
            ]
            if not all_pass(flags):
                self._check_step_arguments(mats, dt, state, y, u, H, R, D)  # (raises, naming the argument)
                update = noise.update_bound((H, out.observed, new.cov))
                check_outcome((out.log_likelihood, new.mean), (new.cov,), (A, Q, c), y, dt, mats.F, R, update)
        return new, out

    def _model_and_flag(self, model: OnlineModel | None) -> tuple[OnlineModel, Tensor | None]:
        """The evaluated model of an online call (``model``, else the filter's current one,
        :func:`~torchsde_lti.nn._online.evaluated`) and, with value checks on, the 0-dim bool
        test that its matrices are finite (formed with the model, once per parameter version:
        no synchronisation); None without value checks."""
        flag = None
        if model is None:
            validate = self.validate_args

            def build() -> tuple[OnlineModel, Tensor | None]:
                built = self.online_model()
                return built, self._model_finite(built) if validate else None

            model, flag = evaluated(self, build)
        if flag is None and self.validate_args:  # (value checks turned on since the model was cached)
            flag = self._model_finite(model)
        return model, flag

    @staticmethod
    def _model_finite(model: OnlineModel) -> Tensor:
        """0-dim bool: the SDE's matrices, H and R of ``model`` finite (the feedthrough D is
        tested with the inputs it multiplies)."""
        with torch.no_grad():
            return torch.cat([x.reshape(-1) for x in (*model.mats, model.H, model.R) if x is not None]).isfinite().all()

    def _check_step_arguments(
        self,
        mats: SDEMatrices,
        dt: Tensor,
        state: KalmanState,
        y: Tensor,
        u: Tensor | None,
        H: Tensor,
        R: Tensor,
        D: Tensor | None,
    ) -> None:
        """The argument checks of :meth:`step` (the sequence filter's, and the state's): ValueError naming the first bad one."""
        self._check_values(mats, dt, psd=(("state.cov", state.cov),), y=y, u=u, H=H, R=R, D=D, mean=state.mean)

    def predict(self, state: KalmanState, dt: Tensor | float, u: Tensor | None = None) -> KalmanState:
        """Prediction only, each track over its own dt (...): ``m⁻ = A m + G u``, ``P⁻ = A P Aᵀ + Q``."""
        mats, _, _, _, series, _ = self._model_and_flag(None)[0]
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
            self._check_values(mats, dt, psd=(("state.cov", state.cov),), u=u, mean=state.mean)
        return kalman_predict(state, *self._step_model(mats, dt, u, series))

    def online_model(self) -> OnlineModel:
        """:class:`OnlineModel`: the SDE's matrices, H, R, D, each parametrisation evaluated
        once, and the dt-independent part of the exact discretisation of one parameter set
        (:func:`~torchsde_lti.nn._online.model_series`, F's nilpotency from the model's
        structure: no value read). What :meth:`step` reads; pass it as ``model=`` to step with
        a snapshot (:class:`~torchsde_lti.OnlineStep`)."""
        mats = self.sde.matrices()
        series = model_series(*mats)
        return OnlineModel(mats, self.H, self.R, self.D, series, self.noise.model())

    def _step_model(
        self, mats: SDEMatrices, dt: Tensor, u: Tensor | None, series: Series | None
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """(A, Q, G u or None) of each track's gap dt (...): the sequence filter's
        discretisation (:func:`~torchsde_lti.nn._online.discretize_steps`), one step per track."""
        d = discretize_steps(mats, dt, self.discretization_method, series, time_axis=False)
        self._check_van_loan_noise(d.Q)
        return d.A, d.Q, None if (u is None or d.G is None) else matvec(d.G, u)

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
