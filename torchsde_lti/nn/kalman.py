r"""``KalmanFilter``: a differentiable Kalman filter whose motion model is an :class:`LTISDE`.

The module assembles parameters and calls the pure functions of
:mod:`torchsde_lti.filters`::

    kf = tl.KalmanFilter(sde, H, R)              # H (m, n), R (m, m) symmetric PD
    out = kf(y, dt, u=None, mask=None)           # y (..., T, m), dt (..., T), u (..., T, p)
    out.mean, out.cov                            # (..., T, n), (..., T, n, n) filtered
    out.log_likelihood                           # (...)  -> loss = -out.log_likelihood.mean()
    sm = kf.smooth(out)                          # RTS: sm.mean, sm.cov
    fc = kf.forecast(out, horizons)              # moments at t_last + horizons (..., K)

Timing convention: the prior N(m0, P0) sits at t₀; step k predicts over dt[..., k] and
then updates with y[..., k]; ``dt[..., 0] = 0`` puts the prior at the first observation.
All steps' (A_k, Q_k, G_k) come from ONE batched ``sde(dt, series=True)`` call (exact
discretisation) before the time loop, so a parameter batch in the SDE (e.g. F (S, n, n))
lines up with the series batch of dt (S, T).

Observation: ``y_k = H x_k + D u_k + v_k``; the feedthrough D (optional, (..., m, p)) acts
on the same known inputs u as the SDE's B (an SDE without B may still have a D).

Prior: ``m0`` defaults to zeros; ``P0`` defaults to the steady-state start of a shaped
model (:func:`torchsde_lti.models.shaped`, prior mode ``"shaping"``: system blocks 0, the
shaping-filter block at its own P∞, recomputed at every call), else to the stationary
covariance P∞ of the SDE when F is Hurwitz at construction (recomputed at every call, so it follows a learned
F — it raises if training makes F unstable, give P0 or use ``F_constraint="hurwitz"``),
otherwise to a broad prior ``diffuse_variance · I`` (default 1e4, in squared state units:
choose it larger than the squared spread of your positions/velocities).

Learnable: any of ``"H"``, ``"D"``, ``"R"``, ``"m0"``, ``"P0"`` (the SDE's own ``learn`` controls
F, L, Qc, B). R and a learnable P0 are parametrised symmetric positive definite by
:class:`~torchsde_lti.nn.parametrizations.PositiveDefinite` (Cholesky factor with a softplus
diagonal), so ``kf.R = value`` works and any optimiser step keeps them valid.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import NamedTuple

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from torchsde_lti.core.discretization import Discrete, discretize, discretize_series, resolve_method
from torchsde_lti.core.linalg import matvec, sym
from torchsde_lti.core.moments import predict_moments
from torchsde_lti.core.stationary import stationary_covariance
from torchsde_lti.core.validation import (
    as_float_tensor,
    check_finite,
    check_matrix,
    check_nonnegative,
    parse_learn,
    shape_str,
    tracing,
)
from torchsde_lti.filters import (
    FilterResult,
    SmootherResult,
    kalman_filter,
    parallel_rts_smoother,
    prefers_scan,
    rts_smoother,
)
from torchsde_lti.nn._register import register_tensor
from torchsde_lti.nn.parametrizations import PositiveDefinite
from torchsde_lti.nn.sde import LTISDE, SDEMatrices

__all__ = ["FilterMode", "Forecast", "KalmanFilter"]

_LEARNABLE = ("H", "D", "R", "m0", "P0")
_PRIOR_MODES = ("stationary", "diffuse", "shaping")


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


class KalmanFilter(nn.Module):
    r"""Kalman filter / RTS smoother for ``dx = F x dt + B u dt + L dβ``, ``y = H x + D u + r``.

    Args:
        sde: the motion model (:class:`~torchsde_lti.LTISDE` or a model of
            :mod:`torchsde_lti.models`); its parameters are trained through the filter.
        H: (..., m, n) observation matrix.
        R: (..., m, m) observation-noise covariance, symmetric positive definite.
        m0: optional (..., n) prior mean (default zeros).
        P0: optional (..., n, n) prior covariance, or a prior mode recomputed from the current
            parameters at every call: ``"shaping"`` (a shaped model's
            ``start_covariance()``, seed 003's steady-state start), ``"stationary"`` (P∞ of
            the whole state) or ``"diffuse"`` (``diffuse_variance · I``). Default: "shaping"
            for a shaped model, else "stationary" if F is Hurwitz, else "diffuse".
        D: optional (..., m, p) feedthrough of the known inputs, ``y = H x + D u + r``
            (p = the SDE's input dimension when it has a B).
        learn: which of ``"H", "D", "R", "m0", "P0"`` are ``nn.Parameter`` (default ``("R",)``).
        parallel: ``None`` (default) chooses per call (:func:`~torchsde_lti.filters.prefers_scan`):
            on CPU the associative scan (O(log T) depth, in memory-bounded time chunks,
            ``kalman_filter(..., parallel=True)``) for at most
            ``SCAN_MAX_BATCH_CPU`` = 16 tracks, where per-step Python overhead dominates the
            loop, else the sequential loop; on other devices the scan. ``True`` / ``False``
            force the scan / the loop (experiments/bench_filter_choice.py).
        diffuse_variance: variance of the broad default prior for non-Hurwitz F.
        unique_dt: discretise only the distinct values of dt (``torch.unique``) and gather
            the per-step matrices; same values and gradients as the plain path. Pays off
            for quantised gaps with a model whose F needs scaling and doubling (Singer,
            OU, a learned Hurwitz F): measured 3.5x faster filtering and 2.8x faster
            forward+backward for a 2-D Singer model with 162 distinct gaps in 1000 x 200
            steps (1 thread). No gain for integrator chains (constant velocity/
            acceleration), whose full-step series is already one GEMM as cheap as the
            gather; and a loss when all gaps are distinct (the sort costs more than the
            discretisation), hence off by default. Used only for one parameter set (no SDE
            batch) and when dt does not require grad; otherwise the plain path runs.
        square_root: propagate Cholesky factors (QR predict, Givens update, see
            ``kalman_filter(..., square_root=True)``): same results up to rounding, and in
            float32 PSD, accurate covariances when predicted and measurement variances
            differ by more than 1/eps (long gaps, precise sensors), where the Joseph form
            can go negative. Slower; sequential filter only (ValueError with ``parallel=True``).
        method: discretisation method of every step, ``"doubling"`` or ``"matrix_exp"``
            (torch.matrix_exp of Van Loan's block); default None = the SDE's own
            :attr:`~torchsde_lti.LTISDE.method` (``"doubling"`` unless set).
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
        parallel: bool | None = None,
        diffuse_variance: float = 1e4,
        unique_dt: bool = False,
        square_root: bool = False,
        method: str | None = None,
    ) -> None:
        super().__init__()
        self.method = None if method is None else resolve_method(method)
        self.unique_dt = bool(unique_dt)
        if square_root and parallel:
            raise ValueError("square_root=True needs the sequential filter, got parallel=True")
        self.square_root = bool(square_root)
        if not isinstance(sde, LTISDE):
            raise TypeError(f"sde must be an LTISDE, got {type(sde).__name__}")
        names = parse_learn(learn, _LEARNABLE)
        self.sde = sde
        self.parallel = None if parallel is None else bool(parallel)
        self.diffuse_variance = float(diffuse_variance)
        dtype, device = sde.dtype, sde.device
        n = sde.state_dim

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
        parametrize.register_parametrization(self, "R", PositiveDefinite(name="R", size=m).to(dtype=dtype, device=device))

        m0_t = torch.zeros(n, dtype=dtype, device=device) if m0 is None else as_float_tensor(m0, "m0", dtype, device)
        if m0_t.dim() < 1 or m0_t.shape[-1] != n:
            raise ValueError(f"m0 must have shape (..., {n}), got shape {shape_str(m0_t)}")
        check_finite(m0_t, "m0")
        register_tensor(self, "m0", m0_t.detach().clone(), "m0" in names)

        # Prior covariance mode: given / shaping / stationary / diffuse.
        self.prior_mode: str
        if isinstance(P0, str):
            if P0 not in _PRIOR_MODES:
                raise ValueError(f"P0 must be a tensor or one of {_PRIOR_MODES}, got {P0!r}")
            if P0 == "shaping" and not callable(getattr(sde, "start_covariance", None)):
                raise ValueError(
                    f"P0='shaping' needs a shaped model (tl.models.shaped), got {type(sde).__name__}"
                )
            self.prior_mode = P0
            with torch.no_grad():
                P0_t = self._prior(sde.matrices())[1].detach().clone()  # raises now if not computable
            if "P0" in names and self.prior_mode != "shaping":
                self.prior_mode = "given"  # learnable, initialised at that mode's value
        elif P0 is not None:
            P0_t = as_float_tensor(P0, "P0", dtype, device).detach().clone()
            check_matrix(P0_t, "P0", rows=n, cols=n)
            self.prior_mode = "given"
        else:
            try:
                with torch.no_grad():
                    if callable(getattr(sde, "start_covariance", None)):
                        P0_t = sde.start_covariance().detach().clone()
                        self.prior_mode = "shaping"
                    else:
                        P0_t = sde.stationary_covariance().detach().clone()
                        self.prior_mode = "stationary"
            except ValueError:
                P0_t = self.diffuse_variance * torch.eye(n, dtype=dtype, device=device)
                self.prior_mode = "diffuse"
            if "P0" in names and self.prior_mode != "shaping":
                self.prior_mode = "given"  # learnable, initialised at the default
        if "P0" in names and self.prior_mode == "shaping":
            raise ValueError(
                "learn contains 'P0', but the shaping start P0 is singular (every entry involving a system "
                "state is 0) and a learnable P0 is parametrised positive definite; pass an initial P0 tensor"
            )
        if self.prior_mode == "given":
            register_tensor(self, "P0", P0_t, "P0" in names)
            parametrize.register_parametrization(self, "P0", PositiveDefinite(name="P0", size=n).to(dtype=dtype, device=device))
        else:
            self.register_buffer("P0", None)

    # ------------------------------------------------------------------ helpers
    @property
    def state_dim(self) -> int:
        return self.sde.state_dim

    @property
    def obs_dim(self) -> int:
        return int(self.H.shape[-2])

    def modes(self) -> list[FilterMode]:
        """The filter's one motion model and observation: ``[FilterMode("", sde, H, R)]``."""
        return [FilterMode("", self.sde, self.H, self.R)]

    def initial_state(self) -> tuple[Tensor, Tensor]:
        """Prior (m0 (..., n), P0 (..., n, n)) at t₀ for the current parameters."""
        return self._prior(self.sde.matrices())

    def _prior(self, mats: SDEMatrices) -> tuple[Tensor, Tensor]:
        """:meth:`initial_state` from already evaluated SDE matrices."""
        if self.prior_mode == "given":
            P0 = self.P0
        elif self.prior_mode == "shaping":
            P0 = self.sde.start_covariance(mats)  # type: ignore[operator]
        elif self.prior_mode == "stationary":
            try:
                P0 = stationary_covariance(mats.F, mats.L, mats.Qc)
            except ValueError as err:
                raise ValueError(
                    "the default prior P0 is the stationary covariance, but F is no longer Hurwitz; "
                    "pass P0 explicitly or constrain F (F_constraint='hurwitz')"
                ) from err
        else:
            n = self.state_dim
            P0 = self.diffuse_variance * torch.eye(n, dtype=self.sde.dtype, device=self.sde.device)
        return self.m0, P0

    def _check_inputs(
        self, y: Tensor, dt: Tensor, u: Tensor | None, mats: SDEMatrices
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        dtype, device = mats.F.dtype, mats.F.device
        p = mats.B.shape[-1] if mats.B is not None else (self.D.shape[-1] if self.D is not None else 0)
        y = as_float_tensor(y, "y", dtype, device)
        if y.dim() < 2:
            raise ValueError(f"y must have shape (..., T, m), got shape {shape_str(y)}")
        m = self.obs_dim
        if y.shape[-1] != m:
            raise ValueError(
                f"y has {y.shape[-1]} components (shape {shape_str(y)}) but H has {m} rows "
                f"(shape {shape_str(self.H)})"
            )
        if not tracing() and bool(torch.isinf(y).any()):
            raise ValueError(f"y contains Inf (shape {shape_str(y)}); mark missing values with NaN or mask")
        T = y.shape[-2]
        dt = as_float_tensor(dt, "dt", dtype, device)
        if dt.dim() < 1 or dt.shape[-1] != T:
            raise ValueError(f"dt must have shape (..., T={T}) to match y {shape_str(y)}, got shape {shape_str(dt)}")
        check_nonnegative(dt, "dt")
        if u is not None:
            if p == 0:
                raise ValueError(
                    f"u was given (shape {shape_str(torch.as_tensor(u))}) but the SDE has no input matrix B "
                    "and the filter no feedthrough D"
                )
            u = as_float_tensor(u, "u", dtype, device)
            if u.dim() < 2 or u.shape[-1] != p or u.shape[-2] not in (1, T):
                raise ValueError(f"u must have shape (..., T={T}, p={p}), got shape {shape_str(u)}")
            check_finite(u, "u")
        return y, dt, u

    @staticmethod
    def _check_parameters(mats: SDEMatrices, **named: Tensor) -> None:
        """NaN/Inf in any model matrix (e.g. after a diverged optimiser step) fails loudly here,
        once per call on n×n matrices, so the unchecked discretisation cannot hide it."""
        for name, value in (*zip(("F", "L", "Qc", "B"), mats), *named.items()):
            if value is not None:
                check_finite(value, name)

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

        Under ``torch.compile(kf)`` the associative scan, where it runs (``parallel=True``,
        or the automatic choice without a gradient, e.g. under ``torch.no_grad()``), is
        traced whole: O(log T) levels, one graph per (batch, T) shape (measured at B = 1:
        17 / 25 s first call at T = 200 / 2000, then 1.6× / 1.3× the eager scan). The
        sequential loop is never traced whole (T unrolled steps take minutes to compile): it
        runs as torch's structured scan with ONE step compiled
        (``kalman_filter(..., compile_step=True)``: 2–4 s first call at T = 200 and 2000,
        then 2.6–2.8× the eager loop at B = 1, any T); the automatic scan with a gradient
        (a compiled training step) runs eagerly. ``torch.export`` traces the call whole
        (value checks off), since an exported program is one graph.
        """
        if torch.compiler.is_compiling() and not torch.compiler.is_exporting():
            scan = self.uses_scan(y.shape[:-2], dt.shape[:-1], y.shape[-2], y.device)
            if not (scan and (self.parallel is True or not torch.is_grad_enabled())):
                return self._forward_compiled_steps(y, dt, u, mask)
        return self._forward(y, dt, u, mask, compile_step=False)

    @torch.compiler.disable
    def _forward_compiled_steps(
        self, y: Tensor, dt: Tensor, u: Tensor | None, mask: Tensor | None
    ) -> FilterResult:
        return self._forward(y, dt, u, mask, compile_step=True)

    def _forward(
        self, y: Tensor, dt: Tensor, u: Tensor | None, mask: Tensor | None, compile_step: bool
    ) -> FilterResult:
        mats = self.sde.matrices()  # each parametrisation evaluated once per call
        y, dt, u = self._check_inputs(y, dt, u, mats)  # dt checked (finite, ≥ 0) once, here
        m0, P0 = self._prior(mats)
        H, R = self.H, self.R
        D = self.D if u is not None else None  # no known input: D u = 0
        self._check_parameters(mats, H=H, R=R, m0=m0, P0=P0, **({} if D is None else {"D": D}))
        # A batch of observation models (..., m, n) is constant over time: insert the T axis.
        H = H.unsqueeze(-3) if H.dim() > 2 else H
        R = R.unsqueeze(-3) if R.dim() > 2 else R
        if D is not None and D.dim() > 2:
            D = D.unsqueeze(-3)
        # Matrices are valid by construction (parametrisations, PSD doubling): no value checks.
        scan = self.uses_scan(y.shape[:-2], dt.shape[:-1], y.shape[-2], y.device)
        d = self._discretize(dt, mats, scan, validate_args=False)  # one batched discretisation: A, Q (..., T, n, n)
        G = d.G if u is not None else None
        return kalman_filter(
            y, d.A, d.Q, H, R, m0, P0, G=G, u=u, mask=mask, D=D,
            square_root=self.square_root, compile_step=compile_step, parallel=scan, validate_args=False,
        )

    def uses_scan(self, *batch_shapes_T_device: object) -> bool:
        """Whether a call with these batch shapes, T and device runs the associative scan:
        ``uses_scan(y_batch, dt_batch, T, device)``; :attr:`parallel` when set, else
        :func:`~torchsde_lti.filters.prefers_scan` (never with ``square_root``)."""
        *shapes, T, device = batch_shapes_T_device
        if self.square_root:
            return False
        if self.parallel is not None:
            return self.parallel
        batch = torch.broadcast_shapes(*(tuple(s) for s in shapes))  # type: ignore[arg-type]
        return prefers_scan(batch.numel(), int(T), device)  # type: ignore[arg-type]

    @property
    def discretization_method(self) -> str:
        """The method used for every step: :attr:`method`, else the SDE's."""
        return self.method or self.sde.method

    def _discretize(
        self, dt: Tensor, mats: SDEMatrices | None = None, scan: bool | None = None, validate_args: bool = True
    ) -> Discrete:
        """All steps' (A, Q, G) in one batched call, laid out for the sequential filter.

        For one parameter set the doubling method returns batch-first views of batch-last
        storage, so the filter loop's per-step moves to (n, n, batch) are cheap row copies
        (:func:`~torchsde_lti.core.discretize_series`). ``validate_args=False`` for a dt
        already checked (the parameters are valid by construction).
        """
        if mats is None:
            mats = self.sde.matrices()
        # a length-1 time axis in the matrices lines a parameter batch up with dt (..., T)
        m = SDEMatrices(*(None if x is None else x.unsqueeze(-3) for x in mats))
        if scan is None:
            scan = bool(self.parallel)
        if scan and not self.unique_dt:  # the scan wants plain batch-first tensors
            return discretize(m.F, m.L, m.Qc, dt, B=m.B, method=self.discretization_method, validate_args=validate_args)
        return discretize_series(
            m.F, m.L, m.Qc, dt, m.B, method=self.discretization_method, unique=self.unique_dt,
            validate_args=validate_args,
        )

    def smooth(self, out: FilterResult) -> SmootherResult:
        """RTS smoother over the filter output (uses the A_k, Q_k stored in ``out``)."""
        scan = self.uses_scan(out.mean.shape[:-2], out.mean.shape[-2], out.mean.device)
        return parallel_rts_smoother(out) if scan else rts_smoother(out)

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
            mean, cov = state.mean[..., -1, :], state.cov[..., -1, :, :]
        else:
            mean, cov = state
        dtype, device = self.sde.dtype, self.sde.device
        dt = as_float_tensor(dt, "dt", dtype, device)
        if dt.dim() == 0:
            dt = dt.reshape(1)
        check_nonnegative(dt, "dt")
        n = self.state_dim
        if mean.shape[-1] != n or cov.shape[-2:] != (n, n):
            raise ValueError(f"state must be (mean (..., {n}), cov (..., {n}, {n})), got "
                             f"{shape_str(mean)}, {shape_str(cov)}")
        d = self.sde(dt, method=self.discretization_method, series=True)
        if u is not None:
            if d.G is None and self.D is None:
                raise ValueError(
                    f"u was given (shape {shape_str(torch.as_tensor(u))}) but the SDE has no input matrix B "
                    "and the filter no feedthrough D"
                )
            u = as_float_tensor(u, "u", dtype, device)
            p = d.G.shape[-1] if d.G is not None else self.D.shape[-1]  # type: ignore[union-attr]
            if u.dim() < 2 or u.shape[-1] != p or u.shape[-2] not in (1, dt.shape[-1]):
                raise ValueError(f"u must have shape (..., K={dt.shape[-1]}, p={p}), got shape {shape_str(u)}")
        m, P = predict_moments(mean.unsqueeze(-2), cov.unsqueeze(-3), d.A, d.Q, d.G, u)
        H, R = self.H, self.R
        Hk = H.unsqueeze(-3) if H.dim() > 2 else H
        Rk = R.unsqueeze(-3) if R.dim() > 2 else R
        obs_mean = matvec(Hk, m)
        if u is not None and self.D is not None:
            obs_mean = obs_mean + matvec(self.D.unsqueeze(-3) if self.D.dim() > 2 else self.D, u)
        return Forecast(m, P, obs_mean, sym(Hk @ P @ Hk.mT + Rk))

    def extra_repr(self) -> str:
        return (
            f"obs_dim={self.obs_dim}, prior={self.prior_mode}, parallel={self.parallel}, unique_dt={self.unique_dt}"
            + (", square_root=True" if getattr(self, "square_root", False) else "")
            + (f", method={self.method!r}" if self.method else "")
        )


class DeployedFilter(nn.Module):
    """The entry point to ship a trained :class:`KalmanFilter` with ``torch.export`` (or
    ``torch.jit``-free serving): plain tensor outputs instead of a :class:`FilterResult`.

    ``forward(y, dt)``: y (..., T, m) with NaN = missing, dt (..., T) ->
    ``(log_likelihood (...), mean (..., T, n))``, the filter's log-likelihood and filtered means.
    """

    def __init__(self, kf: KalmanFilter) -> None:
        super().__init__()
        if not isinstance(kf, KalmanFilter):
            raise TypeError(f"kf must be a KalmanFilter, got {type(kf).__name__}")
        self.kf = kf

    def forward(self, y: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
        out = self.kf(y, dt)
        return out.log_likelihood, out.mean
