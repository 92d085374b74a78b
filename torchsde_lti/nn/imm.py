r"""``IMMFilter``: an interacting multiple model filter over learned continuous-time motion models.

    imm = tl.IMMFilter([sde_1, …, sde_M], H, R, rates)   # LTISDEs in ONE common state (n)
    out = imm(y, dt, mask=None)                          # y (..., T, m), dt (..., T)
    out.log_likelihood                                   # (...)  -> loss = -out.log_likelihood.mean()
    out.mode_probabilities, out.mean, out.cov            # (..., T, M), (..., T, n), (..., T, n, n)
    fc = imm.forecast(out, horizons)                     # the mixture at t_last + horizons (..., K)
    sm = imm.smooth(out)                                 # IMM smoother (Kim 1994): sm.mean, sm.mode_probabilities

Modes switch by a continuous-time Markov chain with generator Λ (``imm.rates``, (M, M):
off-diagonal rates Λ_ij ≥ 0 of jumping from mode i to j, rows summing to 0), so over a gap
dt the mode transition matrix is ``Pi = expm(Λ dt)``, exact for any irregular gap. Each
mode's (A_j, Q_j) is the exact discretisation of its SDE (its noise enters as
``L_j Qc_j L_jᵀ``, so the noise dimensions of the modes may differ).

The IMM shares the Kalman filter's plumbing: each mode is discretised exactly as a
:class:`~torchsde_lti.KalmanFilter` of that mode discretises it (its series, formed once per
call, :func:`~torchsde_lti.nn._online.discretize_steps`), the chain by its own series in
float64; each mode's predict and update in the cycle (:func:`torchsde_lti.filters.imm.imm_filter`)
is the Kalman filter's step; the sequence call (:meth:`IMMFilter.forward`), the online
:meth:`IMMFilter.step` and the exported program take the same route and the same checks
(arguments once; with value checks on, a non-finite outcome raises
:class:`~torchsde_lti.NonFiniteLikelihoodError`).

The models must share the state space: same n, and the same meaning of each component
(e.g. [x, vx, y, vy] for :func:`~torchsde_lti.models.constant_velocity`,
:func:`~torchsde_lti.models.integrated_ou` and :func:`~torchsde_lti.models.moored`).
Inputs u (B matrices) are not used.

Learnable (``learn``): ``"H"``, ``"R"`` (per mode when R is (M, m, m)), ``"rates"``,
``"mode_prob0"``, ``"m0"``, ``"P0"``; the models' own ``learn`` controls F, Qc. R and a
learnable P0 are symmetric positive definite by
:class:`~torchsde_lti.nn.parametrizations.PositiveDefinite`; the rates by
:class:`~torchsde_lti.nn.parametrizations.Generator`
(``softplus(raw) + floor`` off the diagonal: finite and ≥ 0 for every finite raw value, no
exponential of an unbounded parameter); the initial mode probabilities by
:class:`~torchsde_lti.nn.parametrizations.ModeProbabilities` (a softmax).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from torchsde_lti.core.discretization import Discrete, check_matrix_exp_noise, discretization_series
from torchsde_lti.core.linalg import sym
from torchsde_lti.core.validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_matrix,
    parse_learn,
    shape_str,
)
from torchsde_lti.filters.imm import (
    IMMResult,
    combine,
    imm_filter,
)
from torchsde_lti.filters.imm_forecast import imm_forecast
from torchsde_lti.filters.imm_online import IMMState, IMMStep, imm_predict_state, imm_step
from torchsde_lti.filters.imm_smoother import IMMSmootherResult, imm_smoother
from torchsde_lti.filters.kalman import check_algorithm
from torchsde_lti.filters.results import serializable
from torchsde_lti.nn._imm_model import IMMModel, bank_of, check_model_values, imm_state, state_batches
from torchsde_lti.nn._online import check_batches, discretize_steps, evaluated, model_series, tracks_shape
from torchsde_lti.nn._register import register_tensor
from torchsde_lti.nn._validate import ValidateArgs, check_outcome, check_values, online_report
from torchsde_lti.nn.kalman import FilterMode
from torchsde_lti.nn.noise import NoiseOption, StudentT, noise_option
from torchsde_lti.nn.parametrizations import (
    Generator,
    ModeProbabilities,
    PositiveDefinite,
    generator_from_rates,
)
from torchsde_lti.nn.sde import LTISDE

__all__ = ["IMMFilter", "IMMForecast"]

_LEARNABLE = ("H", "R", "rates", "mode_prob0", "m0", "P0")
#: The algorithms of :class:`IMMFilter`: the IMM cycle is a sequential loop.
IMM_ALGORITHMS = ("auto", "sequential")


@serializable
class IMMForecast(NamedTuple):
    """Predictive mixture at future times (K horizons).

    mode_probabilities: (..., K, M); mode_mean: (..., K, M, n); mode_cov: (..., K, M, n, n);
    mean: (..., K, n), cov: (..., K, n, n) moment-matched state; obs_mean: (..., K, m),
    obs_cov: (..., K, m, m) moment-matched observation; mode_obs_mean: (..., K, M, m) and
    mode_obs_cov: (..., K, M, m, m) = H_j P_j H_jᵀ + R_j, the components of the
    observation mixture.
    """

    mode_probabilities: Tensor
    mode_mean: Tensor
    mode_cov: Tensor
    mean: Tensor
    cov: Tensor
    obs_mean: Tensor
    obs_cov: Tensor
    mode_obs_mean: Tensor
    mode_obs_cov: Tensor


class IMMFilter(ValidateArgs, nn.Module):
    r"""IMM filter over M continuous-time motion models with a learned switching generator.

    Args:
        models: M :class:`~torchsde_lti.LTISDE` s with the same state dimension n (and
            without a parameter batch): the modes.
        H: (m, n) shared or (M, m, n) per-mode observation matrix.
        R: (m, m) shared or (M, m, m) per-mode observation-noise covariance (SPD).
        rates: (M, M) generator Λ or off-diagonal switching rates (1/time; diagonal
            ignored). Learnable rates must be > 0; fixed ones (``"rates"`` not in learn)
            may be 0 (no switching).
        m0: optional (n,) or (M, n) prior mean (default zeros).
        P0: optional (n, n) or (M, n, n) prior covariance (default ``diffuse_variance · I``).
        mode_prob0: optional (M,) prior mode probabilities (default uniform).
        learn: which of ``"H", "R", "rates", "mode_prob0", "m0", "P0"`` are learned
            (default ``("R", "rates")``).
        diffuse_variance: variance of the default prior.
        unique_dt: discretise only the distinct values of dt and gather (same values and
            gradients; used when dt does not require grad). Pays off for quantised gaps.
        method: discretisation method passed to :func:`torchsde_lti.discretize`.
        algorithm: ``"auto"`` or ``"sequential"`` (the IMM cycle is a loop over steps; the
            algorithms of :class:`~torchsde_lti.KalmanFilter` that it does not have raise a
            ValueError).
        validate_args: check the values of every call's arguments and the current
            parameters (one fused test; shapes are always checked); None: the class default
            :attr:`default_validate_args` (True).
        mode_names: optional M distinct names of the modes (default ``"mode0"``, ``"mode1"``, …),
            used by :meth:`modes` and in reports (``"moored/k"``, ``"rate[moored->underway]"``).
        noise: :class:`~torchsde_lti.Gaussian` (None, default) or :class:`~torchsde_lti.StudentT`: every
            mode Roth et al.'s Student-t filter, one shared ν or dof (M,) a ν per mode (covariances
            are then scale matrices; per mode, the combined ``cov`` is the mixture's covariance).
    """

    if TYPE_CHECKING:  # the modes' ModuleList, registered tensors and parametrised attributes
        models: Sequence[LTISDE]
        H: Tensor
        R: Tensor
        rates: Tensor
        m0: Tensor
        P0: Tensor
        mode_prob0: Tensor

    def __init__(
        self,
        models: Sequence[LTISDE],
        H: Tensor,
        R: Tensor,
        rates: Tensor,
        *,
        learn: Iterable[str] | str = ("R", "rates"),
        m0: Tensor | None = None,
        P0: Tensor | None = None,
        mode_prob0: Tensor | None = None,
        diffuse_variance: float = 1e4,
        unique_dt: bool = False,
        method: str = "doubling",
        mode_names: Sequence[str] | None = None,
        algorithm: str = "auto",
        validate_args: bool | None = None,
        noise: NoiseOption | None = None,
    ) -> None:
        super().__init__()
        self.algorithm = check_algorithm(algorithm, IMM_ALGORITHMS, "IMMFilter")
        self.validate_args = validate_args
        models = list(models)
        if len(models) < 1:
            raise ValueError("models must contain at least one LTISDE, got 0")
        names_m = [f"mode{j}" for j in range(len(models))] if mode_names is None else [str(s) for s in mode_names]
        if len(names_m) != len(models) or len(set(names_m)) != len(names_m) or not all(names_m):
            raise ValueError(
                f"mode_names must be {len(models)} distinct non-empty names (one per model), got {list(names_m)}"
            )
        self.mode_names = tuple(names_m)
        for i, sde in enumerate(models):
            if not isinstance(sde, LTISDE):
                raise TypeError(f"models[{i}] must be an LTISDE, got {type(sde).__name__}")
        names = parse_learn(learn, _LEARNABLE)
        self.add_module("models", nn.ModuleList(models))
        self.unique_dt = bool(unique_dt)
        self.method = method
        M = len(models)
        dtype, device = models[0].dtype, models[0].device
        n = models[0].state_dim
        self.noise = noise_option(noise, dtype, device, modes=M)
        for i, sde in enumerate(models):
            with torch.no_grad():
                F = sde.matrices().F
            if F.shape != (n, n):
                raise ValueError(
                    f"models[{i}] has F of shape {shape_str(F)}; every mode needs an unbatched "
                    f"({n}, {n}) F (the common state of models[0])"
                )
            if F.dtype != dtype:
                raise ValueError(f"models[{i}] has dtype {F.dtype}, models[0] has {dtype}")

        H = as_float_tensor(H, "H", dtype, device).detach().clone()
        check_matrix(H, "H", cols=n)
        check_finite(H, "H")
        if H.dim() not in (2, 3) or (H.dim() == 3 and H.shape[0] != M):
            raise ValueError(f"H must have shape (m, {n}) or (M={M}, m, {n}), got shape {shape_str(H)}")
        m = H.shape[-2]
        R = as_float_tensor(R, "R", dtype, device).detach().clone()
        if R.dim() not in (2, 3) or R.shape[-2:] != (m, m) or (R.dim() == 3 and R.shape[0] != M):
            raise ValueError(
                f"R must have shape ({m}, {m}) or (M={M}, {m}, {m}) to match H {shape_str(H)}, got shape {shape_str(R)}"
            )
        register_tensor(self, "H", H, "H" in names)
        register_tensor(self, "R", R, "R" in names)
        parametrize.register_parametrization(
            self, "R", PositiveDefinite(name="R", size=m).to(dtype=dtype, device=device)
        )

        rates_t = as_float_tensor(rates, "rates", dtype, device).detach().clone()
        if rates_t.shape != (M, M):
            raise ValueError(f"rates must have shape (M={M}, {M}) for {M} models, got shape {shape_str(rates_t)}")
        check_finite(rates_t, "rates")
        off = ~torch.eye(M, dtype=torch.bool, device=device)
        if bool((rates_t[off] < 0).any()):
            raise ValueError(f"rates must be >= 0 off the diagonal, got min {float(rates_t[off].min()):.3g}")
        if "rates" in names:
            self.register_parameter("rates", nn.Parameter(rates_t))
            parametrize.register_parametrization(self, "rates", Generator(name="rates").to(dtype=dtype, device=device))
        else:
            self.register_buffer("rates", generator_from_rates(rates_t))

        p0 = (
            torch.full((M,), 1.0 / M, dtype=dtype, device=device)
            if mode_prob0 is None
            else as_float_tensor(mode_prob0, "mode_prob0", dtype, device).detach().clone()
        )
        if p0.shape != (M,) or not bool((p0 >= 0).all()) or not abs(float(p0.sum()) - 1.0) <= 1e-6:  # (NaN fails)
            raise ValueError(f"mode_prob0 must be a probability vector of shape ({M},), got {p0.tolist()}")
        p0 = p0 / p0.sum()
        register_tensor(self, "mode_prob0", p0, "mode_prob0" in names)
        if "mode_prob0" in names:
            parametrize.register_parametrization(self, "mode_prob0", ModeProbabilities().to(dtype=dtype, device=device))

        m0_t = torch.zeros(n, dtype=dtype, device=device) if m0 is None else as_float_tensor(m0, "m0", dtype, device)
        if m0_t.shape not in ((n,), (M, n)):
            raise ValueError(f"m0 must have shape ({n},) or (M={M}, {n}), got shape {shape_str(m0_t)}")
        check_finite(m0_t, "m0")
        register_tensor(self, "m0", m0_t.detach().clone(), "m0" in names)
        P0_t = (
            diffuse_variance * torch.eye(n, dtype=dtype, device=device)
            if P0 is None
            else as_float_tensor(P0, "P0", dtype, device).detach().clone()
        )
        if P0_t.shape not in ((n, n), (M, n, n)):
            raise ValueError(f"P0 must have shape ({n}, {n}) or (M={M}, {n}, {n}), got shape {shape_str(P0_t)}")
        register_tensor(self, "P0", P0_t, "P0" in names)
        parametrize.register_parametrization(
            self, "P0", PositiveDefinite(name="P0", size=n).to(dtype=dtype, device=device)
        )

    # ------------------------------------------------------------------ helpers
    @property
    def num_modes(self) -> int:
        return len(self.models)

    @property
    def state_dim(self) -> int:
        return self.models[0].state_dim

    @property
    def obs_dim(self) -> int:
        return int(self.H.shape[-2])

    def modes(self) -> list[FilterMode]:
        """Each mode's motion model and observation: ``FilterMode(name, sde, H_j, R_j)`` (H_j (m, n), R_j (m, m))."""
        H, R = self._obs_model()
        return [
            FilterMode(name, sde, H[min(j, H.shape[0] - 1)], R[min(j, R.shape[0] - 1)])
            for j, (name, sde) in enumerate(zip(self.mode_names, self.models))
        ]

    def bank(self) -> tuple[Tensor, Tensor]:
        """Stacked mode matrices: F (M, n, n) and noise intensity ``L Qc Lᵀ`` (M, n, n)."""
        return bank_of(self.imm_model().modes)

    def imm_model(self) -> IMMModel:
        """:class:`IMMModel`: what a call reads of the filter, each parametrisation evaluated
        once; each mode's discretisation series as a :class:`~torchsde_lti.KalmanFilter` of
        that mode forms it (a nilpotent F is found on the device: no value read)."""
        modes = tuple(sde.matrices() for sde in self.models)
        series = tuple(model_series(*mats) for mats in modes)
        H, R = self._obs_model()
        rates = self.rates
        chain = discretization_series(rates.double(), None, None)
        return IMMModel(modes, series, H, R, rates, chain, self.noise.model())

    def discretize(self, dt: Tensor, validate_args: bool | None = None) -> tuple[Discrete, Tensor]:
        """Every mode over every gap and the chain's transitions.

        dt: (...) gaps (``validate_args``: check them, default :attr:`validate_args`). Returns
        ``Discrete`` with A, Q (..., M, n, n) and Pi (..., M, M) = ``expm(Λ dt)``.
        """
        model = self.imm_model()
        dt = as_float_tensor(dt, "dt", model.rates.dtype, model.rates.device)
        if self._validates(validate_args):
            check_values(nonnegative=[("dt", dt)])
        d, Pi = self._discretizebank_of(model, dt.unsqueeze(-1))
        return Discrete(d.A.select(-4, 0), d.Q.select(-4, 0), None), Pi.select(-3, 0)

    def _discretizebank_of(self, model: IMMModel, dt: Tensor) -> tuple[Discrete, Tensor]:
        """Every mode over every step dt (..., T): A, Q (..., T, M, n, n), each mode as a
        :class:`~torchsde_lti.KalmanFilter` of it discretises
        (:func:`~torchsde_lti.nn._online.discretize_steps`), and the chain's transitions
        Pi (..., T, M, M) = expm(Λ dt) from its series in float64 (a float32 exponential of
        Λ dt for dt ≫ 1/rate loses the row sums), rows renormalised. Eager, online, compiled
        and exported calls alike."""
        steps = [
            discretize_steps(mats, dt, self.method, series, batch_last=False, unique=self.unique_dt)
            for mats, series in zip(model.modes, model.series)
        ]
        d = Discrete(torch.stack([s.A for s in steps], -3), torch.stack([s.Q for s in steps], -3), None)
        if self.method == "matrix_exp" and self.validate_args:  # (Van Loan's Q is not PSD by construction)
            check_matrix_exp_noise(d.Q)
        Pi = model.chain(dt.double())[0].clamp_min(0.0)
        Pi = (Pi / Pi.sum(-1, keepdim=True)).to(model.rates.dtype)
        return d, Pi

    def _obs_model(self) -> tuple[Tensor, Tensor]:
        """H (M or 1, m, n), R (M or 1, m, m)."""
        H, R = self.H, self.R
        return (H if H.dim() == 3 else H.unsqueeze(0)), (R if R.dim() == 3 else R.unsqueeze(0))

    # ------------------------------------------------------------------ API
    def forward(self, y: Tensor, dt: Tensor, u: Tensor | None = None, mask: Tensor | None = None) -> IMMResult:
        """Filter observations y (..., T, m) taken after steps dt (..., T).

        ``u`` exists for the call shape of :class:`~torchsde_lti.KalmanFilter` only: the IMM
        has no inputs, a non-None u raises ValueError.

        Returns :class:`~torchsde_lti.filters.imm.IMMResult` (log_likelihood (...),
        step_log_likelihood (..., T), mode_probabilities (..., T, M), mean, cov, …). With
        value checks on, a non-finite log-likelihood or final state raises
        :class:`~torchsde_lti.NonFiniteLikelihoodError`, as :meth:`step` does.
        """
        if u is not None:
            raise ValueError(f"u was given (shape {shape_str(torch.as_tensor(u))}) but IMMFilter has no inputs")
        model = self.imm_model()
        dtype, device = model.rates.dtype, model.rates.device
        y = as_float_tensor(y, "y", dtype, device)
        if y.dim() < 2 or y.shape[-1] != self.obs_dim:
            raise ValueError(
                f"y must have shape (..., T, m={self.obs_dim}) to match H {shape_str(self.H)}, got shape {shape_str(y)}"
            )
        dt = as_float_tensor(dt, "dt", dtype, device)
        if dt.dim() < 1 or dt.shape[-1] != y.shape[-2]:
            raise ValueError(
                f"dt must have shape (..., T={y.shape[-2]}) to match y {shape_str(y)}, got shape {shape_str(dt)}"
            )
        m0, P0, p0 = self.m0, self.P0, self.mode_prob0
        validate = self.validate_args
        if validate:
            check_model_values(model, dt, y=y, finite=[("m0", m0), ("P0", P0), ("mode_prob0", p0)])
        d, Pi = self._discretizebank_of(model, dt)
        out = imm_filter(y, d.A, d.Q, model.H, model.R, Pi, m0, P0, p0.expand(self.num_modes), mask, False, model.noise)
        if validate:  # (the state it ends in: a NaN or Inf there persists into every later step)
            final = (out.log_likelihood, out.mode_probabilities[..., -1, :], out.mode_mean[..., -1, :, :])
            update = model.noise.update_bound((model.H, out.observed.unsqueeze(-2), out.mode_cov))
            check_outcome(final, (out.mode_cov,), d, y, dt, bank_of(model.modes)[0], model.R, update)
        return out

    def smooth(self, out: IMMResult) -> IMMSmootherResult:
        """Fixed-interval IMM smoother over the filter output (Kim 1994, with the A_j, Q_j and
        Pi of each step stored in ``out``): :func:`~torchsde_lti.filters.imm_smoother.imm_smoother`.
        Returns mean (..., T, n), cov, mode_probabilities (..., T, M), mode_mean, mode_cov (not for a t)."""
        if isinstance(self.noise, StudentT):
            raise ValueError("IMMFilter.smooth: Kim's IMM smoother is Gaussian; not for noise=StudentT")
        return imm_smoother(out)

    # ------------------------------------------------------------------ online
    def initial_state(self, batch_shape: torch.Size | tuple[int, ...] | int = ()) -> IMMState:
        """The prior (mode_prob0, m0, P0) for ``batch_shape`` new tracks, for :meth:`step`:
        :class:`~torchsde_lti.IMMState` with mode_prob (*batch, M), mode_mean (*batch, M, n),
        mode_cov (*batch, M, n, n) (expanded views), batch = ``batch_shape`` broadcast with the
        prior's batch; ValueError naming ``batch_shape`` when it is not a shape or does not
        broadcast with it."""
        shape = tracks_shape(batch_shape)
        M, n = self.num_modes, self.state_dim
        p0, m0, P0 = self.mode_prob0, self.m0, self.P0
        named = [("batch_shape", shape), ("mode_prob0", p0.shape[:-1]), ("m0", m0.shape[:-2]), ("P0", P0.shape[:-3])]
        batch = broadcast_batch(named)
        return IMMState(p0.expand(*batch, M), m0.expand(*batch, M, n), P0.expand(*batch, M, n, n))

    def step(
        self, state: IMMState, y: Tensor, dt: Tensor | float, u: Tensor | None = None, mask: Tensor | None = None
    ) -> tuple[IMMState, IMMStep]:
        """One report per live track: one IMM cycle of each track over its own dt (...).

        The cycle of :meth:`forward`'s loop with its discretisation and checks: iterating it
        over a series gives the same mode probabilities, moments and step log-likelihoods, and
        raises where :meth:`forward` raises.

        Args:
            state: :class:`~torchsde_lti.IMMState` from :meth:`initial_state` or a previous
                step (mode_prob probability vectors, mode_cov symmetric PSD).
            y: (..., m) reports; NaN = missing component.
            dt: (...) non-negative time since each track's state.
            u: must be None (the IMM has no inputs).
            mask: optional bool (...) or (..., m); False = not observed.

        Returns:
            (new :class:`~torchsde_lti.IMMState`, :class:`~torchsde_lti.IMMStep` with the
            combined mean, cov, pred_mode_prob, mode_innovation (..., M, m),
            mode_innovation_cov (..., M, m, m), log_likelihood (...), observed).
        """
        if u is not None:
            raise ValueError(f"u was given (shape {shape_str(torch.as_tensor(u))}) but IMMFilter has no inputs")
        model, state, dt = self._online_args(state, dt)
        H, R = model.H, model.R
        y, mask = online_report(y, mask, H, H.dtype, H.device)
        check_batches([*state_batches(state), ("y", y.shape[:-1]), ("dt", dt.shape)])
        validate = self.validate_args
        if validate:
            check_model_values(model, dt, state, y=y)
        d, Pi = self._discretizebank_of(model, dt.unsqueeze(-1))
        A, Q, Pi = d.A.select(-4, 0), d.Q.select(-4, 0), Pi.select(-3, 0)
        new, out = imm_step(state, y, A, Q, Pi, H, R, mask, model.noise)
        if validate:
            final, update = (
                (out.log_likelihood, new.mode_prob, new.mode_mean),
                model.noise.update_bound((H, out.observed.unsqueeze(-2), new.mode_cov)),
            )
            check_outcome(final, (new.mode_cov,), (A, Q), y, dt, bank_of(model.modes)[0], R, update)
        return new, out

    def predict(self, state: IMMState, dt: Tensor | float) -> IMMState:
        """Prediction only, each track over its own dt (...): mixing with ``expm(Λ dt)``, then
        each mode's exact A_j, Q_j (the predicted :class:`~torchsde_lti.IMMState`; the filter's own
        step, not :meth:`forecast`'s exact moments)."""
        model, state, dt = self._online_args(state, dt)
        check_batches([*state_batches(state), ("dt", dt.shape)])
        if self.validate_args:
            check_model_values(model, dt, state)
        d, Pi = self._discretizebank_of(model, dt.unsqueeze(-1))
        return imm_predict_state(state, d.A.select(-4, 0), d.Q.select(-4, 0), Pi.select(-3, 0), model.noise)

    def _online_args(self, state: IMMState, dt: Tensor | float) -> tuple[IMMModel, IMMState, Tensor]:
        """The evaluated model (:meth:`imm_model`; without gradients once per parameter
        version, :func:`~torchsde_lti.nn._online.evaluated`), the state and dt of an online
        call, converted and shape-checked."""
        model = evaluated(self, self.imm_model)
        F = model.modes[0].F
        M, n = self.num_modes, F.shape[-1]
        return model, imm_state(state, M, n, F.dtype, F.device), as_float_tensor(dt, "dt", F.dtype, F.device)

    def forecast(
        self,
        state: IMMResult | tuple[Tensor, Tensor, Tensor],
        dt: Tensor | float,
    ) -> IMMForecast:
        """The mixture at horizons dt after the state's time (each measured from it).

        The switching SDE's exact moments at each horizon given the mode there, switches within
        it included (:func:`~torchsde_lti.filters.imm_forecast`); observation moments per mode
        and moment-matched.

        Args:
            state: a filter result (its last step is used) or (mode_prob (..., M),
                mode_mean (..., M, n), mode_cov (..., M, n, n)).
            dt: (..., K) non-negative horizons (a float or (K,) is shared by the batch).
        """
        if isinstance(state, IMMResult):
            state = (
                state.mode_probabilities[..., -1, :],
                state.mode_mean[..., -1, :, :],
                state.mode_cov[..., -1, :, :, :],
            )
        model = self.imm_model()
        F = model.modes[0].F
        prob, mean, cov = imm_state(state, self.num_modes, F.shape[-1], F.dtype, F.device)
        dt = as_float_tensor(dt, "dt", F.dtype, F.device)
        if dt.dim() == 0:
            dt = dt.reshape(1)
        check_batches([*state_batches(IMMState(prob, mean, cov)), ("dt", dt.shape[:-1])])
        H, R = model.H, model.R
        if self.validate_args:
            check_model_values(model, dt, IMMState(prob, mean, cov))
        p = imm_forecast(prob, mean, cov, *bank_of(model.modes), model.rates, dt, model.noise, self.validate_args)
        ym = (H @ p.mode_mean.unsqueeze(-1)).squeeze(-1)  # (..., K, M, m)
        S = sym(H @ p.mode_cov @ H.mT + R)
        obs_mean, obs_cov = combine(p.mode_probabilities, ym, S, model.noise.with_axis())
        return IMMForecast(p.mode_probabilities, p.mode_mean, p.mode_cov, p.mean, p.cov, obs_mean, obs_cov, ym, S)

    def extra_repr(self) -> str:
        return f"modes={list(self.mode_names)}, obs_dim={self.obs_dim}, unique_dt={self.unique_dt}"
