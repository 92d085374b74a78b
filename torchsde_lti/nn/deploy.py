"""Deployment entry points of a trained :class:`~torchsde_lti.KalmanFilter`: modules with
plain tensor inputs and outputs whose ``forward`` is what a service calls, ready for
``torch.export`` (with dynamic shapes) and AOTInductor packaging.

- :class:`DeployedFilter`: the sequence filter, ``(y, dt) -> (log_likelihood, mean)``;
- :class:`OnlineStep`: one online step of live tracks (:meth:`~torchsde_lti.KalmanFilter.step`).
"""

from __future__ import annotations

from torch import Tensor, nn

from torchsde_lti.filters.online import KalmanState
from torchsde_lti.nn.kalman import KalmanFilter

__all__ = ["DeployedFilter", "OnlineStep"]


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


class OnlineStep(nn.Module):
    """:meth:`KalmanFilter.step` as a module's ``forward``, to export and package (torch.export,
    AOTInductor) for a live tracker: plain tensors in and out.

    ``forward(mean, cov, y, dt)``: mean (B, n), cov (B, n, n), y (B, m) (NaN = missing), dt (B,)
    -> ``(mean, cov, innovation (B, m), innovation_cov (B, m, m), log_likelihood (B,))``.
    Value checks are off inside (check reports where they enter the tracker).
    """

    def __init__(self, kf: KalmanFilter) -> None:
        super().__init__()
        if not isinstance(kf, KalmanFilter):
            raise TypeError(f"kf must be a KalmanFilter, got {type(kf).__name__}")
        self.kf = kf

    def forward(self, mean: Tensor, cov: Tensor, y: Tensor, dt: Tensor) -> tuple[Tensor, ...]:
        state, out = self.kf.step(KalmanState(mean, cov), y, dt)
        return state.mean, state.cov, out.innovation, out.innovation_cov, out.log_likelihood
