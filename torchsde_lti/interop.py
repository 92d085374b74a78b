r"""Hand an :class:`~torchsde_lti.LTISDE` (learned or built) to the trackers people already run.

- Stone Soup: :func:`stonesoup_transition_model` (class :data:`LTISDETransitionModel`, a
  ``stonesoup.models.transition.linear.LinearGaussianTransitionModel``) whose
  ``matrix(time_interval=…)`` and ``covar(time_interval=…)`` are the exact discretisation
  ``A = expm(F dt)``, ``Q = ∫₀^dt e^{Fs} L Qc Lᵀ e^{Fsᵀ} ds`` of the SDE for the gap, so the
  model runs inside Stone Soup's predictors, updaters, smoothers and trackers.
- filterpy: :func:`set_filterpy_step` sets a ``filterpy.kalman.KalmanFilter``'s ``F`` (= A),
  ``Q`` and, when the SDE has an input matrix, ``B`` (= the zero-order-hold G) for a gap dt;
  call it before each ``predict`` on an irregular grid.

Neither library is a dependency (``pip install torchsde_lti[interop]``): Stone Soup is
imported on first use of the Stone Soup model, filterpy is never imported (the helper only
sets attributes). Note the notation clash: Stone Soup and filterpy call the *discrete*
transition matrix F; here F is the continuous drift and A = expm(F dt).

The matrices are evaluated without autograd at the SDE's current parameters (each call
reads them again, so a model trained further is picked up) and returned as float64
numpy arrays.
"""

from __future__ import annotations

import datetime
import functools
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from torchsde_lti.core.discretization import discretization_series, discretize, resolve_method
from torchsde_lti.core.linalg import noise_covariance
from torchsde_lti.nn import model_version
from torchsde_lti.nn.sde import LTISDE

__all__ = ["LTISDETransitionModel", "discrete_step", "set_filterpy_step", "stonesoup_transition_model"]


def _seconds(time_interval: object, name: str) -> float:
    if isinstance(time_interval, datetime.timedelta):
        seconds = time_interval.total_seconds()
    elif isinstance(time_interval, (int, float, np.floating, np.integer)) and not isinstance(time_interval, bool):
        seconds = float(time_interval)
    else:
        raise TypeError(
            f"{name} must be a datetime.timedelta or a number of seconds, got {type(time_interval).__name__}"
        )
    if not np.isfinite(seconds) or seconds < 0:
        raise ValueError(f"{name} must be finite and non-negative, got {seconds!r} s")
    return seconds


def _discretizer(sde: LTISDE, method: str) -> Callable[[float], tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
    """The exact discretisation of ``sde``'s current parameters as a function of one gap (seconds)
    -> float64 numpy ``(A, Q, G)``. The matrices are read now, once; with ``"doubling"`` the
    dt-independent part (:func:`~torchsde_lti.core.discretization.discretization_series`, what
    :func:`~torchsde_lti.core.discretize` forms for one parameter set on every call) too, so a
    call costs the series at that gap alone."""
    with torch.no_grad():
        m = sde.matrices()  # each parametrisation evaluated once
        batch = [x.shape[:-2] for x in m if x is not None]
        if any(len(b) for b in batch):
            raise ValueError(
                f"sde must be a single model (batch_shape ()), got batch_shape {tuple(torch.broadcast_shapes(*batch))}"
            )
        resolve_method(method)
        series = discretization_series(m.F, noise_covariance(m.L, m.Qc), m.B) if method == "doubling" else None

    def step(seconds: float) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        with torch.no_grad():
            h = torch.tensor(seconds, dtype=m.F.dtype, device=m.F.device)
            # the gap is checked by the caller; the parameters' values on the result (numpy, no torch check)
            A, Q, G = (
                series(h) if series is not None else discretize(m.F, m.L, m.Qc, h, m.B, method, validate_args=False)
            )
        to_np = lambda x: x.detach().cpu().to(torch.float64).numpy()  # noqa: E731
        A, Q, G = to_np(A), to_np(Q), None if G is None else to_np(G)
        if not (np.isfinite(A).all() and np.isfinite(Q).all() and (G is None or np.isfinite(G).all())):
            raise ValueError(
                f"the discretisation of the SDE over dt = {seconds!r} s is not finite: its parameters are not "
                "finite or the step overflows float64 (an unstable F over a long gap)"
            )
        return A, 0.5 * (Q + Q.T), G

    return step


def discrete_step(
    sde: LTISDE, dt: object, method: str = "doubling"
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(A, Q, G)`` of ``sde`` over one gap ``dt`` as float64 numpy arrays (G None without B).

    Args:
        sde: an unbatched :class:`~torchsde_lti.LTISDE` (``batch_shape == ()``).
        dt: seconds (float) or a ``datetime.timedelta``; non-negative.
        method: ``"doubling"`` or ``"matrix_exp"`` (see :func:`torchsde_lti.discretize`).

    Returns:
        A (n, n), Q (n, n) symmetric PSD, G (n, p) or None.
    """
    if not isinstance(sde, LTISDE):
        raise TypeError(f"sde must be an LTISDE, got {type(sde).__name__}")
    seconds = _seconds(dt, "dt")
    return _discretizer(sde, method)(seconds)


# ---------------------------------------------------------------------------- Stone Soup
#: Gaps whose (A, Q) a Stone Soup model keeps (a tracker's scans share a few gaps).
_GAPS_KEPT = 16


@functools.cache
def _stonesoup_class() -> type:
    try:
        from stonesoup.base import Property
        from stonesoup.models.base import TimeVariantModel
        from stonesoup.models.transition.linear import LinearGaussianTransitionModel
        from stonesoup.types.array import CovarianceMatrix
    except ImportError as err:  # pragma: no cover - exercised only without stonesoup
        raise ImportError(
            "the Stone Soup transition model needs stonesoup (pip install stonesoup, or torchsde_lti[interop])"
        ) from err

    class LTISDETransitionModel(LinearGaussianTransitionModel, TimeVariantModel):
        r"""Stone Soup linear-Gaussian transition model backed by an :class:`~torchsde_lti.LTISDE`.

        ``matrix(time_interval=Δ)`` = expm(F Δ) and ``covar(time_interval=Δ)`` = the exact
        process noise over Δ (seconds of the ``timedelta``), computed by
        :func:`torchsde_lti.discretize` at the SDE's current parameters. Δ must be
        non-negative. The state layout is the SDE's (e.g. ``[x, vx, y, vy]``). The (A, Q)
        of the last 16 gaps, and the dt-independent part of the discretisation, are reused
        while every parameter/buffer version counter and ``method`` are unchanged (in-place
        optimiser steps and ``sde.q = …`` bump them; writes through ``tensor.data`` do not).
        """

        sde: Any = Property(doc="The torchsde_lti.LTISDE (unbatched) that defines the dynamics.")
        method: str = Property(default="doubling", doc="Discretisation method: 'doubling' or 'matrix_exp'.")

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            if not isinstance(self.sde, LTISDE):
                raise TypeError(f"sde must be an LTISDE, got {type(self.sde).__name__}")
            if len(self.sde.batch_shape) != 0:
                raise ValueError(
                    f"sde must be a single model (batch_shape ()), got batch_shape {tuple(self.sde.batch_shape)}"
                )

            self._version: tuple = ()
            self._gaps: dict[float, tuple[np.ndarray, np.ndarray]] = {}
            self._discretize: Callable[[float], tuple[np.ndarray, np.ndarray, np.ndarray | None]] | None = None

        @property
        def ndim_state(self) -> int:
            return self.sde.state_dim

        def _step(self, time_interval: datetime.timedelta) -> tuple[np.ndarray, np.ndarray]:
            # A scan asks for matrix() and covar() of the same few gaps for every track and
            # hypothesis: keep the (A, Q) of the last gaps seen, and the discretisation of the
            # current parameters (their dt-independent part formed once), valid while the version
            # counters of every parameter and buffer are unchanged (an optimiser step or an
            # assignment ``sde.q = …`` changes them).
            seconds = _seconds(time_interval, "time_interval")
            version = (model_version(self.sde), self.method)
            if version != self._version or self._discretize is None:
                self._version, self._gaps = version, {}
                self._discretize = _discretizer(self.sde, self.method)
            hit = self._gaps.get(seconds)
            if hit is None:
                A, Q, _ = self._discretize(seconds)
                if len(self._gaps) >= _GAPS_KEPT:
                    self._gaps.pop(next(iter(self._gaps)))  # the oldest gap
                hit = self._gaps[seconds] = (A, Q)
            return hit[0].copy(), hit[1].copy()

        def matrix(self, time_interval: datetime.timedelta, **kwargs: Any) -> np.ndarray:
            """A = expm(F Δ) (n, n) for the gap ``time_interval``."""
            return self._step(time_interval)[0]

        def covar(self, time_interval: datetime.timedelta, **kwargs: Any) -> Any:
            """Exact process-noise covariance Q(Δ) (n, n) as a Stone Soup ``CovarianceMatrix``."""
            return CovarianceMatrix(self._step(time_interval)[1])

    return LTISDETransitionModel


def stonesoup_transition_model(sde: LTISDE, method: str = "doubling") -> Any:
    """A Stone Soup ``LinearGaussianTransitionModel`` whose matrices come from ``sde`` per gap.

    Example::

        from stonesoup.predictor.kalman import KalmanPredictor
        predictor = KalmanPredictor(stonesoup_transition_model(tl.models.singer(0.5, 2.0, dim=2)))
    """
    return _stonesoup_class()(sde=sde, method=method)


def __getattr__(name: str) -> Any:
    if name == "LTISDETransitionModel":
        return _stonesoup_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ---------------------------------------------------------------------------- filterpy
def set_filterpy_step(kf: Any, sde: LTISDE, dt: object, method: str = "doubling") -> Any:
    """Set a filterpy ``KalmanFilter``'s ``F``, ``Q`` (and ``B``) to ``sde``'s exact step over ``dt``.

    ``kf.F = expm(F_c dt)`` (filterpy's F is the discrete transition), ``kf.Q`` = the exact
    process noise, and ``kf.B`` = the zero-order-hold input matrix G when the SDE has an
    input matrix (then ``kf.predict(u=u)`` applies ``G u``). Returns ``kf``.

    Args:
        kf: a ``filterpy.kalman.KalmanFilter`` with ``dim_x == sde.state_dim``.
        sde: an unbatched :class:`~torchsde_lti.LTISDE`.
        dt: the gap to the next observation, seconds or a ``datetime.timedelta``.
    """
    if not isinstance(sde, LTISDE):
        raise TypeError(f"sde must be an LTISDE, got {type(sde).__name__}")
    n = sde.state_dim
    dim_x = getattr(kf, "dim_x", None)
    if dim_x is None or not hasattr(kf, "F") or not hasattr(kf, "Q"):
        raise TypeError(f"kf must be a filterpy KalmanFilter (attributes dim_x, F, Q), got {type(kf).__name__}")
    if dim_x != n:
        raise ValueError(f"kf.dim_x = {dim_x} does not match the SDE's state dimension {n}")
    A, Q, G = discrete_step(sde, dt, method)
    kf.F = A
    kf.Q = Q
    if G is not None:
        kf.B = G
    return kf
