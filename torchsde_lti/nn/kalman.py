r"""``KalmanFilter``: a differentiable Kalman filter whose motion model is an :class:`LTISDE`.

The module assembles parameters and calls the pure functions of
:mod:`torchsde_lti.filters`::

    kf = tl.KalmanFilter(sde, H, R)              # H (m, n), R (m, m) symmetric PD
    out = kf(y, dt, u=None, mask=None)           # y (..., T, m), dt (..., T), u (..., T, p)
    out.mean, out.cov                            # (..., T, n), (..., T, n, n) filtered
    out.log_likelihood                           # (...)  -> loss = -out.log_likelihood.mean()
    sm = kf.smooth(out)                          # RTS: sm.mean, sm.cov
    fc = kf.forecast(out, horizons)              # moments at t_last + horizons (..., K)

This module holds the filter's parameters, its prior and its sequence calls; the online calls
for live trackers (``initial_state``, ``step``, ``predict``: one report per track at a time)
are its base class :class:`~torchsde_lti.nn._kalman_online.KalmanOnline`.

Timing convention: the prior N(m0, P0) sits at t₀; step k predicts over dt[..., k] and
then updates with y[..., k]; ``dt[..., 0] = 0`` puts the prior at the first observation.
All steps' (A_k, Q_k, G_k) come from ONE batched exact discretisation of the SDE before the
time loop, so a parameter batch in the SDE (e.g. F (S, n, n)) lines up with the series batch
of dt (S, T).

Observation: ``y_k = H x_k + D u_k + v_k``; the feedthrough D (optional, (..., m, p)) acts
on the same known inputs u as the SDE's B (an SDE without B may still have a D).

Prior: ``m0`` defaults to zeros; ``P0`` defaults to the motion model's own
:meth:`~torchsde_lti.LTISDE.prior_covariance` (the stationary covariance P∞ for a Hurwitz
F, the steady-state start of a :func:`~torchsde_lti.models.shaped` model), recomputed from the
current parameters at every call (it raises if training makes F unstable: give P0 or use
``F_constraint="hurwitz"``); when the model has none at construction (F not Hurwitz), a
broad prior ``diffuse_variance · I`` (default 1e4, in squared state units: choose it larger
than the squared spread of your positions/velocities).

Validation: the constructor checks its arguments; each call checks the values it is given
(y without Inf, dt finite and ≥ 0, u finite) and the current parameters (finite) once, in one
fused test, when :attr:`validate_args` is True (per instance, class default True); the
discretisation and the filter functions then run on the checked tensors without checking
again. Shapes are always checked.

Learnable: any of ``"H"``, ``"D"``, ``"R"``, ``"m0"``, ``"P0"`` (the SDE's own ``learn`` controls
F, L, Qc, B). R and a learnable P0 are parametrised symmetric positive definite by
:class:`~torchsde_lti.nn.parametrizations.PositiveDefinite` (Cholesky factor with a softplus
diagonal), so ``kf.R = value`` works and any optimiser step keeps them valid.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import NamedTuple

import torch
from torch import Tensor
from torch.nn.utils import parametrize

from torchsde_lti.core.discretization import Discrete, resolve_method
from torchsde_lti.core.linalg import matvec, sym
from torchsde_lti.core.moments import predict_moments
from torchsde_lti.core.validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_matrix,
    checks_values,
    parse_learn,
    shape_str,
)
from torchsde_lti.filters import (
    FilterResult,
    SmootherResult,
    choose_algorithm,
    rts_smoother,
)
from torchsde_lti.filters.inputs import FilterInputs
from torchsde_lti.filters.kalman import ALGORITHMS, check_algorithm, run_filter
from torchsde_lti.filters.results import serializable
from torchsde_lti.nn._kalman_online import KalmanOnline, model_batches, state_batches
from torchsde_lti.nn._online import Series, check_batches, discretize_steps, model_series, online_state
from torchsde_lti.nn._register import register_tensor
from torchsde_lti.nn._validate import check_outcome, check_values
from torchsde_lti.nn.noise import NoiseOption, noise_option
from torchsde_lti.nn.parametrizations import PositiveDefinite
from torchsde_lti.nn.sde import LTISDE, SDEMatrices

__all__ = ["FilterMode", "Forecast", "KalmanFilter"]

_LEARNABLE = ("H", "D", "R", "m0", "P0")


@serializable
class Forecast(NamedTuple):
    """Predictive moments at future times.

    mean: (..., K, n), cov: (..., K, n, n) of the state;
    obs_mean: (..., K, m) = H mean (+ D u when inputs are given), obs_cov: (..., K, m, m) = H cov Hᵀ + R.
    """

    mean: Tensor
    cov: Tensor
    obs_mean: Tensor
    obs_cov: Tensor


class FilterMode(NamedTuple):
    """One motion model of a filter with its observation model: what a filter learns, per mode.

    name: ``""`` for a single-model filter, else the mode's name; sde: its
    :class:`~torchsde_lti.LTISDE`; H: (m, n) its observation matrix; R: (m, m) its
    observation-noise covariance. :meth:`KalmanFilter.modes` returns one,
    :meth:`~torchsde_lti.IMMFilter.modes` one per mode, so reporting and training code treat
    both filters alike.
    """

    name: str
    sde: LTISDE
    H: Tensor
    R: Tensor


class KalmanFilter(KalmanOnline):
    r"""Kalman filter / RTS smoother for ``dx = F x dt + B u dt + L dβ``, ``y = H x + D u + r``.

    Args:
        sde: the motion model (:class:`~torchsde_lti.LTISDE` or a model of
            :mod:`torchsde_lti.models`); its parameters are trained through the filter.
        H: (..., m, n) observation matrix.
        R: (..., m, m) observation-noise covariance, symmetric positive definite.
        m0: optional (..., n) prior mean (default zeros).
        P0: optional (..., n, n) prior covariance, or ``"diffuse"`` (``diffuse_variance · I``).
            Default (None): the model's ``sde.prior_covariance()``, recomputed from the
            current parameters at every call, or diffuse when the model has none (F not
            Hurwitz at construction). :attr:`prior_mode` says which: ``"given"``,
            ``"model"`` or ``"diffuse"``.
        D: optional (..., m, p) feedthrough of the known inputs, ``y = H x + D u + r``
            (p = the SDE's input dimension when it has a B).
        learn: which of ``"H", "D", "R", "m0", "P0"`` are ``nn.Parameter`` (default ``("R",)``).
        algorithm: one of :data:`~torchsde_lti.filters.ALGORITHMS` (see
            :func:`~torchsde_lti.kalman_filter`): ``"auto"`` (default) chooses per call
            (:func:`~torchsde_lti.filters.choose_algorithm`): in float64 on CPU the associative
            scan for at most ``SCAN_MAX_BATCH_CPU`` = 16 tracks, where per-step Python overhead
            dominates the loop, else the sequential loop, and on other devices the scan; in
            float32 the sequential loop (the scan's combine loses long gaps there); under
            ``torch.compile`` the loop as a structured scan. ``"sequential"``, ``"scan"``
            force one; ``"square_root"`` propagates
            Cholesky factors (QR predict, Givens update): same results up to rounding, and in
            float32 PSD, accurate covariances when predicted and measurement variances differ
            by more than 1/eps (long gaps, precise sensors), where the Joseph form can go
            negative; slower.
        diffuse_variance: variance of the broad default prior for non-Hurwitz F.
        unique_dt: discretise only the distinct values of dt (``torch.unique``) and gather
            the per-step matrices; same values and gradients as the plain path. Pays off
            for quantised gaps with a model whose F needs scaling and doubling (Singer,
            OU, a learned Hurwitz F) when gaps repeat many times. No gain for integrator chains (constant velocity/
            acceleration), whose full-step series is already one GEMM as cheap as the
            gather; and a loss when all gaps are distinct (the sort costs more than the
            discretisation), hence off by default. Used only for one parameter set (no SDE
            batch) and when dt does not require grad; otherwise the plain path runs.
        method: discretisation method of every step, ``"doubling"`` or ``"matrix_exp"``
            (torch.matrix_exp of Van Loan's block); default None = the SDE's own
            :attr:`~torchsde_lti.LTISDE.method` (``"doubling"`` unless set).
        validate_args: check the values of every call's arguments and the current
            parameters (one fused test; shapes are always checked); None: the class default
            :attr:`default_validate_args` (True).
        noise: :class:`~torchsde_lti.Gaussian` (None, the default) or
            :class:`~torchsde_lti.StudentT` (Roth et al.'s Student-t filter, ν learned with
            ``learn=True``: R, P0 and every covariance of the results and forecasts are then
            the t's scale matrices, the log-likelihood the exact Student-t predictive; the
            smoother is the RTS smoother of the scale matrices; not with ``algorithm="scan"``).
    """

    def __init__(
        self,
        sde: LTISDE,
        H: Tensor,
        R: Tensor,
        *,
        m0: Tensor | None = None,
        P0: Tensor | str | None = None,
        D: Tensor | None = None,
        learn: Iterable[str] | str = ("R",),
        algorithm: str = "auto",
        diffuse_variance: float = 1e4,
        unique_dt: bool = False,
        method: str | None = None,
        validate_args: bool | None = None,
        noise: NoiseOption | None = None,
    ) -> None:
        super().__init__()
        self.method = None if method is None else resolve_method(method)
        self.algorithm = algorithm
        self.unique_dt = bool(unique_dt)
        self.validate_args = validate_args
        if not isinstance(sde, LTISDE):
            raise TypeError(f"sde must be an LTISDE, got {type(sde).__name__}")
        names = parse_learn(learn, _LEARNABLE)
        self.sde = sde
        self.diffuse_variance = float(diffuse_variance)
        if not (math.isfinite(self.diffuse_variance) and self.diffuse_variance > 0):
            raise ValueError(f"diffuse_variance must be a finite positive variance, got {diffuse_variance!r}")
        dtype, device = sde.dtype, sde.device
        n = sde.state_dim
        self.noise = noise_option(noise, dtype, device)

        H = as_float_tensor(H, "H", dtype, device).detach().clone()
        check_matrix(H, "H", cols=n)
        check_finite(H, "H")
        m = H.shape[-2]
        R = as_float_tensor(R, "R", dtype, device).detach().clone()
        if R.dim() < 2 or R.shape[-2:] != (m, m):
            raise ValueError(f"R must have shape (..., {m}, {m}) to match H {shape_str(H)}, got shape {shape_str(R)}")
        register_tensor(self, "H", H, "H" in names)
        if D is None:
            if "D" in names:
                raise ValueError("learn contains 'D' but D is None")
            self.register_buffer("D", None)
        else:
            D_t = as_float_tensor(D, "D", dtype, device).detach().clone()
            check_matrix(D_t, "D", rows=m)
            check_finite(D_t, "D")
            p = sde.input_dim
            if p and D_t.shape[-1] != p:
                raise ValueError(
                    f"D must have shape (..., {m}, {p}): {p} columns for the SDE's input matrix B, got shape "
                    f"{shape_str(D_t)}"
                )
            register_tensor(self, "D", D_t, "D" in names)
        register_tensor(self, "R", R, "R" in names)
        parametrize.register_parametrization(
            self, "R", PositiveDefinite(name="R", size=m).to(dtype=dtype, device=device)
        )

        m0_t = torch.zeros(n, dtype=dtype, device=device) if m0 is None else as_float_tensor(m0, "m0", dtype, device)
        if m0_t.dim() < 1 or m0_t.shape[-1] != n:
            raise ValueError(f"m0 must have shape (..., {n}), got shape {shape_str(m0_t)}")
        check_finite(m0_t, "m0")
        register_tensor(self, "m0", m0_t.detach().clone(), "m0" in names)
        self._init_prior(P0, "P0" in names, n, dtype, device)

    # ------------------------------------------------------------------ helpers
    @property
    def algorithm(self) -> str:
        """The filter algorithm, one of :data:`~torchsde_lti.filters.ALGORITHMS` (assignable)."""
        return self._algorithm

    @algorithm.setter
    def algorithm(self, value: str) -> None:
        self._algorithm = check_algorithm(value, ALGORITHMS, "KalmanFilter")

    @property
    def state_dim(self) -> int:
        return self.sde.state_dim

    @property
    def obs_dim(self) -> int:
        return int(self.H.shape[-2])

    def modes(self) -> list[FilterMode]:
        """The filter's one motion model and observation: ``[FilterMode("", sde, H, R)]``."""
        return [FilterMode("", self.sde, self.H, self.R)]

    def _check_inputs(
        self, y: Tensor, dt: Tensor, u: Tensor | None, mats: SDEMatrices
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """y, dt, u converted to the model's dtype and device, their shapes checked."""
        dtype, device = mats.F.dtype, mats.F.device
        p = mats.B.shape[-1] if mats.B is not None else (self.D.shape[-1] if self.D is not None else 0)
        y = as_float_tensor(y, "y", dtype, device)
        if y.dim() < 2:
            raise ValueError(f"y must have shape (..., T, m), got shape {shape_str(y)}")
        m = self.obs_dim
        if y.shape[-1] != m:
            raise ValueError(
                f"y has {y.shape[-1]} components (shape {shape_str(y)}) but H has {m} rows (shape {shape_str(self.H)})"
            )
        T = y.shape[-2]
        dt = as_float_tensor(dt, "dt", dtype, device)
        if dt.dim() < 1 or dt.shape[-1] != T:
            raise ValueError(f"dt must have shape (..., T={T}) to match y {shape_str(y)}, got shape {shape_str(dt)}")
        if u is not None:
            u = self._check_u(u, p, T, "T", dtype, device)
        return y, dt, u

    def _check_u(self, u: Tensor, p: int, T: int, axis: str, dtype: torch.dtype, device: torch.device) -> Tensor:
        """Inputs u (..., T or 1, p) converted; ValueError without B and D, or for a wrong shape."""
        if p == 0:
            raise ValueError(
                f"u was given (shape {shape_str(torch.as_tensor(u))}) but the SDE has no input matrix B "
                "and the filter no feedthrough D"
            )
        u = as_float_tensor(u, "u", dtype, device)
        if u.dim() < 2 or u.shape[-1] != p or u.shape[-2] not in (1, T):
            raise ValueError(f"u must have shape (..., {axis}={T}, p={p}), got shape {shape_str(u)}")
        return u

    def _check_values(
        self, mats: SDEMatrices, dt: Tensor, psd: tuple[tuple[str, Tensor], ...] = (), **named: Tensor | None
    ) -> None:
        """One fused value check of a call (one synchronisation): dt finite and ≥ 0, the
        model's matrices and the ``named`` tensors finite (NaN/Inf after a diverged optimiser
        step fails loudly here, so the unchecked discretisation cannot hide it); y (if named)
        without Inf; the ``psd`` (name, covariance) pairs symmetric PSD (an online state)."""
        y = named.pop("y", None)
        finite = [*zip(("F", "L", "Qc", "B"), mats), *named.items()]
        check_values(finite=finite, nonnegative=[("dt", dt)], no_inf=[("y", y)], psd=psd)

    # ------------------------------------------------------------------ API
    def forward(
        self,
        y: Tensor,
        dt: Tensor,
        u: Tensor | None = None,
        mask: Tensor | None = None,
    ) -> FilterResult:
        """Filter observations y (..., T, m) taken after steps dt (..., T).

        Args:
            y: (..., T, m) observations; NaN marks a missing component.
            dt: (..., T) non-negative steps; dt[..., 0] is the time from the prior to y[..., 0].
            u: optional (..., T, p) inputs held constant over each step (needs the SDE's B
                or the filter's D); they enter ``G u`` and ``y = H x + D u + v``.
            mask: optional bool (..., T) or (..., T, m); False = not observed.

        Returns:
            :class:`~torchsde_lti.FilterResult` (mean, cov, pred_mean, pred_cov,
            innovation, innovation_cov, log_likelihood (...), step_log_likelihood (..., T), …).

        Under ``torch.compile(kf)`` the sequential loop (the ``"auto"`` choice there, and
        ``"sequential"``) is never traced whole (T unrolled steps take minutes to compile):
        the discretisation runs eagerly and the loop as torch's structured scan with ONE step
        compiled (any T); ``algorithm="scan"`` traces the associative scan whole (O(log T)
        levels, one graph per (batch, T) shape, minutes to compile); ``"square_root"`` runs
        eagerly. ``torch.export`` traces the call whole (value checks off) with the loop as
        the structured scan, so ``torch.export.export(kf, (y, dt), dynamic_shapes=...)`` with
        ``torch.export.Dim`` for the batch and T gives one program for every (batch, T).
        """
        if torch.compiler.is_compiling() and not torch.compiler.is_exporting() and self.algorithm != "scan":
            return self._forward_compiled_loop(y, dt, u, mask)
        return self._forward(y, dt, u, mask, self.algorithm)

    @torch.compiler.disable
    def _forward_compiled_loop(self, y: Tensor, dt: Tensor, u: Tensor | None, mask: Tensor | None) -> FilterResult:
        algorithm = "square_root" if self.algorithm == "square_root" else "sequential"
        return self._forward(y, dt, u, mask, algorithm, compiled_loop=True)

    def _forward(
        self,
        y: Tensor,
        dt: Tensor,
        u: Tensor | None,
        mask: Tensor | None,
        algorithm: str,
        compiled_loop: bool = False,
    ) -> FilterResult:
        mats = self.sde.matrices()  # (each parametrisation read once a call)
        y, dt, u = self._check_inputs(y, dt, u, mats)
        H, R, m0 = self.H, self.R, self.m0
        H_model, R_model = H, R
        P0_given = self.P0 if self.prior_mode == "given" else None
        D = self.D if u is not None else None  # no known input: D u = 0
        validate = self.validate_args
        if validate:
            self._check_values(mats, dt, y=y, u=u, H=H, R=R, m0=m0, D=D, P0=P0_given)
        _, P0 = self._prior(mats, validate, P0_given)
        # A batch of observation models (..., m, n) is constant over time: insert the T axis.
        H = H.unsqueeze(-3) if H.dim() > 2 else H
        R = R.unsqueeze(-3) if R.dim() > 2 else R
        if D is not None and D.dim() > 2:
            D = D.unsqueeze(-3)
        T = y.shape[-2]
        if algorithm == "auto":
            batch = broadcast_batch([("y", y.shape[:-2]), ("dt", dt.shape[:-1])])
            algorithm = choose_algorithm(algorithm, math.prod(batch), T, y.device, y.dtype)
        # one batched discretisation of every step: A, Q (..., T, n, n), laid out for the algorithm
        d = self._discretize(dt, mats, series_layout=algorithm != "scan")
        G = d.G if u is not None else None
        args = FilterInputs(y, d.A, d.Q, H, R, m0, P0, G, u, mask, D)
        out = run_filter(args, algorithm, validate_args=False, compiled_loop=compiled_loop, noise=self.noise.model())
        if validate:
            # the state it ends in, as the online step checks its new state: a NaN or Inf persists
            # into every later step and the log-likelihood sums every step's, so a series of
            # online steps raises where the sequence filter of the reports seen so far raises
            last = out.cov[..., -1, :, :]
            update = self.noise.model().update_bound((H_model, out.observed[..., -1, :], last))
            check_outcome((out.log_likelihood, out.mean[..., -1, :]), (last,), d, y, dt, mats.F, R_model, update)
        return out

    def algorithm_for(self, batch_size: int, T: int, device: torch.device, dtype: torch.dtype | None = None) -> str:
        """The algorithm a call with ``batch_size`` tracks of T steps on ``device`` runs:
        :attr:`algorithm` unless ``"auto"``, then :func:`~torchsde_lti.filters.choose_algorithm`
        (``dtype``: default the model's)."""
        return choose_algorithm(self.algorithm, batch_size, T, device, dtype or self.sde.dtype)

    @property
    def discretization_method(self) -> str:
        """The method used for every step: :attr:`method`, else the SDE's."""
        return self.method or self.sde.method

    def _discretize(
        self, dt: Tensor, mats: SDEMatrices | None = None, series_layout: bool = True, series: Series | None = None
    ) -> Discrete:
        """All steps' (A, Q, G) over a checked dt (..., T) in one batched call: the modules'
        one discretisation (:func:`~torchsde_lti.nn._online.discretize_steps`, the same in
        :meth:`step`), with the model's series (:func:`~torchsde_lti.nn._online.model_series`)
        formed here unless given; no value checks (the matrices come from the SDE's
        parametrisations, checked by the caller; a ``"matrix_exp"`` Q is checked,
        :meth:`_check_van_loan_noise`). ``series_layout``: batch-first views of batch-last
        storage for the sequential loop (plain batch-first for the scan)."""
        if mats is None:
            mats = self.sde.matrices()
        if series is None:
            series = model_series(*mats)
        d = discretize_steps(mats, dt, self.discretization_method, series, series_layout, self.unique_dt)
        self._check_van_loan_noise(d.Q)
        return d

    def smooth(self, out: FilterResult) -> SmootherResult:
        """RTS smoother over the filter output (uses the A_k, Q_k stored in ``out``): the
        sequential backward pass after ``"sequential"`` and ``"square_root"``, the reverse
        associative scan after ``"scan"``, the automatic choice after ``"auto"``."""
        if not isinstance(out, FilterResult):
            raise TypeError(f"out must be the FilterResult of this filter's forward, got {type(out).__name__}")
        algorithm = {"square_root": "sequential"}.get(self.algorithm, self.algorithm)
        return rts_smoother(out, algorithm=algorithm)

    def forecast(
        self,
        state: FilterResult | SmootherResult | tuple[Tensor, Tensor],
        dt: Tensor | float,
        u: Tensor | None = None,
    ) -> Forecast:
        """Moments at horizons dt after the state's time (each horizon measured from it).

        ``mean = A(dt) m + G(dt) u``, ``cov = A(dt) P A(dt)ᵀ + Q(dt)``, then the observation
        moments ``H mean + D u`` and ``H cov Hᵀ + R`` (G u and D u only where u is given).

        Args:
            state: a filter/smoother result (its last time step is used) or a pair
                (mean (..., n), cov (..., n, n)).
            dt: (..., K) non-negative horizons (a float or (K,) is shared by the batch).
            u: optional (..., K, p) inputs held over each horizon.

        Returns:
            :class:`Forecast` with mean (..., K, n), cov (..., K, n, n), obs_mean, obs_cov.
        """
        if isinstance(state, (FilterResult, SmootherResult)):
            state = (state.mean[..., -1, :], state.cov[..., -1, :, :])
        mats = self.sde.matrices()
        F = mats.F
        checked, dt = online_state(state, dt, F)
        mean, cov = checked
        if dt.dim() == 0:
            dt = dt.reshape(1)
        if u is not None:
            p = mats.B.shape[-1] if mats.B is not None else (self.D.shape[-1] if self.D is not None else 0)
            u = self._check_u(u, p, dt.shape[-1], "K", F.dtype, F.device)
        H, R, D = self.H, self.R, self.D
        check_batches(
            [
                *state_batches(checked),
                ("dt", dt.shape[:-1]),
                *([] if u is None else [("u", u.shape[:-2])]),
                *model_batches(mats, H=H, R=R, D=D if u is not None else None),
            ]
        )
        if self.validate_args:
            self._check_values(mats, dt, psd=(("state.cov", cov),), u=u, H=H, R=R, D=D, mean=mean)
        d = self._discretize(dt, mats, series_layout=False)
        m, P = predict_moments(mean.unsqueeze(-2), cov.unsqueeze(-3), d.A, d.Q, d.G, u)
        if checks_values(self.validate_args) and not bool(torch.isfinite(m).all() & torch.isfinite(P).all()):
            raise ValueError(f"the forecast overflows {F.dtype} for horizons up to {float(dt.max()):.3g}: shorten them")
        Hk = H.unsqueeze(-3) if H.dim() > 2 else H
        Rk = R.unsqueeze(-3) if R.dim() > 2 else R
        obs_mean = matvec(Hk, m)
        Du = self.feedthrough(u)
        if Du is not None:
            obs_mean = obs_mean + Du
        return Forecast(m, P, obs_mean, sym(Hk @ P @ Hk.mT + Rk))

    def feedthrough(self, u: Tensor | None) -> Tensor | None:
        """``D u`` (..., K, m) of inputs u (..., K, p) (a batched D (..., m, p) shared over K),
        or None without a feedthrough D or without inputs."""
        D = self.D
        if D is None or u is None:
            return None
        if u.dim() < 2 or u.shape[-1] != D.shape[-1]:
            raise ValueError(f"u must have shape (..., K, {D.shape[-1]}) to match D {shape_str(D)}, got {shape_str(u)}")
        return matvec(D.unsqueeze(-3) if D.dim() > 2 else D, u)

    def extra_repr(self) -> str:
        return (
            f"obs_dim={self.obs_dim}, prior={self.prior_mode}, algorithm={self.algorithm!r}, unique_dt={self.unique_dt}"
            + (f", method={self.method!r}" if self.method else "")
        )
