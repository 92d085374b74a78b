r"""``IMMFilter``: an interacting multiple model filter over learned continuous-time motion models.

    imm = tl.IMMFilter([sde_1, …, sde_M], H, R, rates)   # LTISDEs in ONE common state (n)
    out = imm(y, dt, mask=None)                          # y (..., T, m), dt (..., T)
    out.log_likelihood                                   # (...)  -> loss = -out.log_likelihood.mean()
    out.mode_probabilities, out.mean, out.cov            # (..., T, M), (..., T, n), (..., T, n, n)
    fc = imm.forecast(out, horizons)                     # the mixture at t_last + horizons (..., K)

Modes switch by a continuous-time Markov chain with generator Λ (``imm.rates``, (M, M):
off-diagonal rates Λ_ij ≥ 0 of jumping from mode i to j, rows summing to 0), so over a gap
dt the mode transition matrix is ``Pi = expm(Λ dt)``, exact for any irregular gap. Each
mode's (A_j, Q_j) is the exact discretisation of its SDE (its noise enters as
``L_j Qc_j L_jᵀ``, so the noise dimensions of the modes may differ). Eagerly each mode and the
chain are discretised by their series, formed once (:func:`~torchsde_lti.core.discretization_series`);
while traced the whole bank is ONE batched :func:`torchsde_lti.discretize` call over (track,
step, mode), the M drift matrices stacked along a batch axis, and Pi is ``torch.matrix_exp``.
The IMM cycle itself is :func:`torchsde_lti.filters.imm.imm_filter`.

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
from typing import NamedTuple

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from torchsde_lti.core.discretization import Discrete, check_matrix_exp_noise, discretization_series, discretize
from torchsde_lti.core.linalg import sym
from torchsde_lti.core.validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_matrix,
    parse_learn,
    shape_str,
    tracing,
)
from torchsde_lti.filters.imm import (
    IMMPrediction,
    IMMResult,
    combine,
    imm_filter,
    imm_predict,
)
from torchsde_lti.filters.imm_online import IMMState, IMMStep, imm_predict_state, imm_step
from torchsde_lti.filters.kalman import check_algorithm
from torchsde_lti.filters.results import serializable
from torchsde_lti.nn._online import Series, check_batches, evaluated, tracks_shape
from torchsde_lti.nn._register import register_tensor
from torchsde_lti.nn._validate import ValidateArgs, check_values, online_report
from torchsde_lti.nn.kalman import FilterMode
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


class OnlineIMM(NamedTuple):
    """The evaluated model of an :class:`IMMFilter`'s online calls: F, W (M, n, n) the bank,
    H (M or 1, m, n), R (M or 1, m, m), rates (M, M) the generator Λ; ``series`` each mode's
    and ``chain`` the mode chain's discretisation series (float64), or None (while recording
    gradients or traced: the calls then discretise from F, W and the rates)."""

    F: Tensor
    W: Tensor
    H: Tensor
    R: Tensor
    rates: Tensor
    series: list[Series] | None
    chain: Series | None


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
    """

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
        self.models = nn.ModuleList(models)
        self.unique_dt = bool(unique_dt)
        self.method = method
        M = len(models)
        dtype, device = models[0].dtype, models[0].device
        n = models[0].state_dim
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
        mats = [sde.matrices() for sde in self.models]
        F = torch.stack([mm.F for mm in mats])
        W = torch.stack([mm.L @ mm.Qc @ mm.L.mT for mm in mats])
        return F, sym(W)

    def discretize(self, dt: Tensor, validate_args: bool | None = None) -> tuple[Discrete, Tensor]:
        """Every mode over every gap, in ONE batched discretisation, and the chain's transitions.

        dt: (...) gaps (``validate_args``: check them, default :attr:`validate_args`; False for
        a dt already checked). Returns ``Discrete`` with A, Q (..., M, n, n) and Pi (..., M, M)
        = ``expm(Λ dt)``.
        """
        return self._discretize_bank(*self.bank(), dt, self._validates(validate_args))

    def _discretize_bank(
        self, F: Tensor, W: Tensor, dt: Tensor, validate_args: bool, online: OnlineIMM | None = None
    ) -> tuple[Discrete, Tensor]:
        """:meth:`discretize` for the stacked bank (F, W) already read; with ``online`` (the
        evaluated model of an online call, :meth:`_online_model`) its rates and, where it holds
        them, each mode's and the chain's discretisation series (the same values to rounding)."""
        eye = torch.eye(F.shape[-1], dtype=F.dtype, device=F.device)
        if self.unique_dt and not dt.requires_grad and dt.numel() > 0:
            values, inverse = torch.unique(dt, return_inverse=True)
            d, Pi = self._discretize_flat(F, W, eye, values, validate_args, online)
            d, Pi = Discrete(d.A[inverse], d.Q[inverse], None), Pi[inverse]
        else:
            d, Pi = self._discretize_flat(F, W, eye, dt, validate_args, online)
        if self.method == "matrix_exp" and self.validate_args:  # (Van Loan's Q is not PSD by construction)
            check_matrix_exp_noise(d.Q)
        return d, Pi

    def _discretize_flat(
        self, F: Tensor, W: Tensor, eye: Tensor, dt: Tensor, validate_args: bool, online: OnlineIMM | None = None
    ) -> tuple[Discrete, Tensor]:
        series = None if online is None else online.series
        if series is None and self.method == "doubling" and not tracing():
            # many gaps: each mode's series once (core's one-parameter-set route), not the bank
            # broadcast to every (gap, mode) element
            series = [discretization_series(F[j], W[j], None) for j in range(F.shape[0])]
        if series is not None and self.method == "doubling":
            As, Qs = [], []
            for mode in series:  # each mode over every gap: (..., n, n)
                A_j, Q_j, _ = mode(dt)
                assert Q_j is not None
                As.append(A_j)
                Qs.append(Q_j)
            d = Discrete(torch.stack(As, -3), torch.stack(Qs, -3), None)
        else:
            d = discretize(
                F, eye, W, dt.unsqueeze(-1), method=self.method, validate_args=validate_args
            )  # F (M,·,·) with dt (..., 1)
        # the chain's transitions in float64 (an M × M exponential), rows renormalised: a
        # float32 exponential of Λ dt for dt ≫ 1/rate loses the row sums (and gives NaN mixing)
        rates = self.rates if online is None else online.rates
        chain = None if online is None else online.chain
        if chain is None and not tracing():
            chain = discretization_series(rates.double(), None, None)
        if chain is not None:
            Pi = chain(dt.double())[0].clamp_min(0.0)
        else:
            Pi = torch.matrix_exp(rates.double() * dt.double()[..., None, None]).clamp_min(0.0)
        Pi = (Pi / Pi.sum(-1, keepdim=True)).to(rates.dtype)
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
        step_log_likelihood (..., T), mode_probabilities (..., T, M), mean, cov, …).
        """
        if u is not None:
            raise ValueError(f"u was given (shape {shape_str(torch.as_tensor(u))}) but IMMFilter has no inputs")
        with parametrize.cached():  # each parametrisation evaluated once per call
            F, W = self.bank()
            y = as_float_tensor(y, "y", F.dtype, F.device)
            if y.dim() < 2 or y.shape[-1] != self.obs_dim:
                raise ValueError(
                    f"y must have shape (..., T, m={self.obs_dim}) to match H {shape_str(self.H)}, "
                    f"got shape {shape_str(y)}"
                )
            dt = as_float_tensor(dt, "dt", F.dtype, F.device)
            if dt.dim() < 1 or dt.shape[-1] != y.shape[-2]:
                raise ValueError(
                    f"dt must have shape (..., T={y.shape[-2]}) to match y {shape_str(y)}, got shape {shape_str(dt)}"
                )
            H, R = self._obs_model()
            rates, m0, P0, p0 = self.rates, self.m0, self.P0, self.mode_prob0
            if self.validate_args:
                check_values(
                    finite=[
                        ("F", F),
                        ("W", W),
                        ("H", H),
                        ("R", R),
                        ("rates", rates),
                        ("m0", m0),
                        ("P0", P0),
                        ("mode_prob0", p0),
                    ],
                    nonnegative=[("dt", dt)],
                    no_inf=[("y", y)],
                )
            # the bank is valid by construction (parametrisations, PSD doubling) and dt checked above
            d, Pi = self._discretize_bank(F, W, dt, validate_args=False)
            return imm_filter(y, d.A, d.Q, H, R, Pi, m0, P0, p0.expand(self.num_modes), mask=mask, validate_args=False)

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

        The cycle of :meth:`forward`'s loop: iterating it over a series gives the same
        mode probabilities, moments and step log-likelihoods (to rounding).

        Args:
            state: :class:`~torchsde_lti.IMMState` from :meth:`initial_state` or a previous step.
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
        with parametrize.cached():
            online, state, dt = self._online_args(state, dt)
            F, W, H, R = online.F, online.W, online.H, online.R
            y, mask = online_report(y, mask, H, F.dtype, F.device)
            check_batches([*_state_batches(state), ("y", y.shape[:-1]), ("dt", dt.shape)])
            if self.validate_args:
                _check_online_values(F, W, online.rates, state, dt, H, R, y)
            d, Pi = self._discretize_bank(F, W, dt, validate_args=False, online=online)
            return imm_step(state, y, d.A, d.Q, Pi, H, R, mask)

    def predict(self, state: IMMState, dt: Tensor | float) -> IMMState:
        """Prediction only, each track over its own dt (...): mixing with ``expm(Λ dt)``, then
        each mode's exact A_j, Q_j (the predicted :class:`~torchsde_lti.IMMState`)."""
        with parametrize.cached():
            online, state, dt = self._online_args(state, dt)
            check_batches([*_state_batches(state), ("dt", dt.shape)])
            if self.validate_args:
                _check_online_values(online.F, online.W, online.rates, state, dt)
            d, Pi = self._discretize_bank(online.F, online.W, dt, validate_args=False, online=online)
            return imm_predict_state(state, d.A, d.Q, Pi)

    def _online_args(self, state: IMMState, dt: Tensor | float) -> tuple[OnlineIMM, IMMState, Tensor]:
        """The evaluated model (:meth:`_online_model`), the state and dt of an online call,
        converted and shape-checked; without gradients the model is evaluated once per
        parameter version."""
        online = evaluated(self, self._online_model)
        F = online.F
        return online, _imm_state(state, F), as_float_tensor(dt, "dt", F.dtype, F.device)

    def _online_model(self) -> OnlineIMM:
        """:class:`OnlineIMM`: :meth:`bank`, the observation model and the rates, each
        parametrisation evaluated once, and, eagerly without gradients (where
        :func:`~torchsde_lti.nn._online.evaluated` caches this per parameter version), the
        discretisation series (:func:`~torchsde_lti.core.discretization.discretization_series`:
        what a step's discretisation needs that does not depend on dt) of each mode and of the
        mode chain (``expm(Λ dt)`` in float64)."""
        with parametrize.cached():
            F, W = self.bank()
            H, R = self._obs_model()
            rates = self.rates
            series = chain = None
            if not torch.is_grad_enabled() and not tracing():
                series = [discretization_series(F[j], W[j], None) for j in range(F.shape[0])]
                chain = discretization_series(rates.double(), None, None)
            return OnlineIMM(F, W, H, R, rates, series, chain)

    def forecast(
        self,
        state: IMMResult | tuple[Tensor, Tensor, Tensor],
        dt: Tensor | float,
    ) -> IMMForecast:
        """The mixture at horizons dt after the state's time (each measured from it).

        One IMM prediction per horizon: ``c = μ expm(Λ h)``, mixing, then each mode's exact
        ``A_j(h)``, ``Q_j(h)``; observation moments per mode and moment-matched.

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
        with parametrize.cached():
            F, W = self.bank()
            prob, mean, cov = _imm_state(state, F)
            dt = as_float_tensor(dt, "dt", F.dtype, F.device)
            if dt.dim() == 0:
                dt = dt.reshape(1)
            check_batches([*_state_batches(IMMState(prob, mean, cov)), ("dt", dt.shape[:-1])])
            H, R = self._obs_model()
            if self.validate_args:
                _check_online_values(F, W, self.rates, (prob, mean, cov), dt, H, R)
            d, Pi = self._discretize_bank(F, W, dt, validate_args=False)  # (..., K, M, n, n), (..., K, M, M)
        p: IMMPrediction = imm_predict(prob, mean, cov, d.A, d.Q, Pi)
        ym = (H @ p.mode_mean.unsqueeze(-1)).squeeze(-1)  # (..., K, M, m)
        S = H @ p.mode_cov @ H.mT + R
        S = sym(S)
        obs_mean, obs_cov = combine(p.mode_probabilities, ym, S)
        return IMMForecast(p.mode_probabilities, p.mode_mean, p.mode_cov, p.mean, p.cov, obs_mean, obs_cov, ym, S)

    def extra_repr(self) -> str:
        return f"modes={list(self.mode_names)}, obs_dim={self.obs_dim}, unique_dt={self.unique_dt}"


#: The names of an IMM state's fields in error messages.
_STATE_NAMES = ("state.mode_prob", "state.mode_mean", "state.mode_cov")


def _imm_state(state: object, F: Tensor) -> IMMState:
    """An online call's state as an :class:`~torchsde_lti.IMMState` of F's dtype and device
    (F: (M, n, n)), shapes checked; TypeError or ValueError naming it."""
    M, n = F.shape[-3], F.shape[-1]
    if not isinstance(state, tuple) or len(state) != 3:
        raise TypeError(f"state must be an IMMState (mode_prob, mode_mean, mode_cov), got {type(state).__name__}")
    prob, mean, cov = (as_float_tensor(t, name, F.dtype, F.device) for name, t in zip(_STATE_NAMES, state))
    if prob.dim() < 1 or prob.shape[-1] != M or mean.shape[-2:] != (M, n) or cov.shape[-3:] != (M, n, n):
        raise ValueError(
            f"state must be (mode_prob (..., {M}), mode_mean (..., {M}, {n}), mode_cov "
            f"(..., {M}, {n}, {n})), got {shape_str(prob)}, {shape_str(mean)}, {shape_str(cov)}"
        )
    return IMMState(prob, mean, cov)


def _check_online_values(
    F: Tensor,
    W: Tensor,
    rates: Tensor,
    state: tuple[Tensor, Tensor, Tensor],
    dt: Tensor,
    H: Tensor | None = None,
    R: Tensor | None = None,
    y: Tensor | None = None,
) -> None:
    """The value checks of an online call (step, predict, forecast): the bank (F, W), H and R
    where the call uses them, the rates and the state finite; dt ≥ 0; y without ±Inf."""
    obs = [] if H is None else [("H", H), ("R", R)]
    check_values(
        finite=[("F", F), ("W", W), *obs, ("rates", rates), *zip(_STATE_NAMES, state)],
        nonnegative=[("dt", dt)],
        no_inf=[] if y is None else [("y", y)],
    )


def _state_batches(state: IMMState) -> list[tuple[str, tuple[int, ...]]]:
    """The named batch shapes of an IMM state's fields."""
    return [(name, tuple(t.shape[: t.dim() - k])) for name, t, k in zip(_STATE_NAMES, state, (1, 2, 3))]
