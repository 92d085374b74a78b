r"""Observation-noise options of the filter modules: ``noise=Gaussian()`` (default) or ``noise=StudentT(dof)``.

    kf = tl.KalmanFilter(sde, H, R, noise=tl.StudentT(dof=4.0, learn=True))   # ν learned with the rest
    imm = tl.IMMFilter(models, H, R, rates, noise=tl.StudentT(4.0))            # one ν for every mode
    imm = tl.IMMFilter(models, H, R, rates, noise=tl.StudentT([4.0] * M))      # a ν per mode (M,)
    kf.noise.dof                                                                # current ν (> 2), assignable

An option is a small module the filter owns (its ν is trained and saved with the filter);
:meth:`Gaussian.model` / :meth:`StudentT.model` give the pure noise model the filter functions
read (:mod:`torchsde_lti.filters.noise`: the Student-t filter of Roth, Özkan & Gustafsson 2013,
its exact Student-t one-step predictive, and what "covariance" means there: the t's scale
matrix; the covariance is ``ν / (ν − 2)`` times it).

ν is parametrised ``ν = 2 + softplus(raw) + δ`` (:class:`DegreesOfFreedom`, δ = 4 eps of the dtype):
finite and > 2 for every finite raw value; ``noise.dof = value`` stores its preimage. A
Gaussian filter is the limit ν → ∞ (``StudentT(1e12)`` agrees with it to ~4e-8 on residuals of
Δ² ~ 100, ``StudentT(1e8)`` to ~4e-4).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from torchsde_lti.core.validation import as_float_tensor, check_finite, shape_str
from torchsde_lti.filters.noise import GAUSSIAN, GaussianNoise, StudentTNoise
from torchsde_lti.nn._parametrization_base import Parametrization, softplus, softplus_inverse
from torchsde_lti.nn._register import register_tensor

__all__ = ["DegreesOfFreedom", "Gaussian", "NoiseOption", "StudentT", "noise_option"]


def _excess_floor(dtype: torch.dtype) -> float:
    """The least ν − 2 of :class:`DegreesOfFreedom`: 4 eps of ``dtype`` (2 + it is > 2 in the dtype)."""
    return 4.0 * float(torch.finfo(dtype).eps)


class DegreesOfFreedom(Parametrization):
    """Degrees of freedom ν > 2: ``value = 2 + softplus(raw) + 4 eps`` (any shape; eps of the
    raw tensor's dtype, so that the value is > 2 in that dtype for every finite raw value).

    ``right_inverse`` raises ValueError for values that are not finite or not > 2."""

    def __init__(self, name: str = "dof") -> None:
        super().__init__()
        self.name = name

    def forward(self, raw: Tensor) -> Tensor:
        return 2.0 + softplus(raw) + _excess_floor(raw.dtype)

    def right_inverse(self, value: object) -> Tensor:
        v = self._as_raw_tensor(value, self.name)
        check_finite(v, self.name)
        if bool((v <= 2.0).any()):
            raise ValueError(f"{self.name} must be > 2 (the t's covariance exists), got min {float(v.min()):.6g}")
        excess = (v - 2.0 - _excess_floor(v.dtype)).clamp_min(torch.finfo(v.dtype).tiny)
        return softplus_inverse(excess)


class Gaussian(nn.Module):
    """Gaussian observation and process noise: the Kalman filter (the filters' default)."""

    def model(self) -> GaussianNoise:
        """The filters' noise model: :class:`~torchsde_lti.filters.GaussianNoise`."""
        return GAUSSIAN


class StudentT(nn.Module):
    r"""Student-t noise with ν degrees of freedom, shared by the state, process and measurement
    noise (Roth, Özkan & Gustafsson 2013; :mod:`torchsde_lti.filters.noise`).

    Args:
        dof: the initial ν > 2: one number (the filter's, shared by the modes of an IMM) or, for
            an :class:`~torchsde_lti.IMMFilter` of M modes, M numbers (M,), each mode's own ν.
        learn: ν is an ``nn.Parameter`` (trained through the filter's log-likelihood) or a
            fixed buffer.
    """

    dof: Tensor

    def __init__(self, dof: float | Tensor = 4.0, learn: bool = True) -> None:
        super().__init__()
        value = as_float_tensor(dof, "dof", torch.float64).detach().clone()
        if value.dim() > 1 or value.numel() == 0:
            raise ValueError(f"dof must be one number or one per IMM mode (M,), got shape {shape_str(value)}")
        check_finite(value, "dof")
        if not bool((value > 2.0).all()):
            raise ValueError(f"dof must be > 2 (the t's covariance exists), got {value.tolist()}")
        self.learn = bool(learn)
        register_tensor(self, "dof", value, self.learn)
        parametrize.register_parametrization(self, "dof", DegreesOfFreedom().to(dtype=torch.float64))

    def model(self) -> StudentTNoise:
        """The filters' noise model with the current ν: :class:`~torchsde_lti.filters.StudentTNoise`
        (``per_mode`` for a ν per mode)."""
        dof = self.dof
        return StudentTNoise(dof, per_mode=True) if dof.dim() else StudentTNoise(dof)

    def extra_repr(self) -> str:
        dof = self.dof.detach()
        shown = f"{float(dof):.4g}" if dof.dim() == 0 else "[" + ", ".join(f"{v:.4g}" for v in dof.tolist()) + "]"
        return f"dof={shown}, learn={self.learn}"


#: A filter module's noise option.
NoiseOption = Gaussian | StudentT


def noise_option(noise: object, dtype: torch.dtype, device: torch.device, modes: int | None = None) -> NoiseOption:
    """A filter's ``noise=`` argument as its option module in the filter's dtype and device:
    None is :class:`Gaussian`; TypeError naming ``noise`` for anything but an option, ValueError
    for a ν per mode (dof (k,)) unless the filter is an IMM of ``modes`` = k modes."""
    if noise is None:
        return Gaussian()
    if not isinstance(noise, (Gaussian, StudentT)):
        raise TypeError(f"noise must be tl.Gaussian() or tl.StudentT(dof), got {type(noise).__name__}")
    if isinstance(noise, StudentT) and noise.dof.dim() and noise.dof.shape[0] != modes:
        where = "a KalmanFilter takes one ν" if modes is None else f"one ν or one per mode, ({modes},)"
        raise ValueError(f"noise=StudentT(dof) has dof of shape {shape_str(noise.dof)}: {where}")
    return noise.to(dtype=dtype, device=device)
