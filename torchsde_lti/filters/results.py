"""Result types of the filters and smoothers (NamedTuples with batch-first fields)."""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor
from torch.utils import _pytree as pytree

__all__ = ["FilterResult", "SmootherResult", "serializable"]


def serializable(cls: type) -> type:
    """Register the NamedTuple ``cls`` with torch's pytree under its qualified name, so that an
    exported program returning it saves and loads (``torch.export.save``); returns ``cls``."""
    try:
        pytree._register_namedtuple(cls, serialized_type_name=f"{cls.__module__}.{cls.__qualname__}")
    except ValueError:  # registered already (a reloaded module)
        pass
    return cls


@serializable
class FilterResult(NamedTuple):
    """Output of :func:`kalman_filter` (every algorithm).

    mean: (..., T, n) filtered means E[x_k | y_{0:k}].
    cov: (..., T, n, n) filtered covariances.
    pred_mean: (..., T, n) one-step predictions E[x_k | y_{0:k-1}].
    pred_cov: (..., T, n, n) predicted covariances.
    innovation: (..., T, m) ``y_k − H_k pred_mean_k``; 0 in unobserved components.
    innovation_cov: (..., T, m, m) ``H_k pred_cov_k H_kᵀ + R_k`` (all components).
    log_likelihood: (...) Σ_k step_log_likelihood.
    step_log_likelihood: (..., T) log N(y_k^obs; H^obs pred_mean_k, S_k^obs) over the
        observed components of y_k (0 for a fully missing step).
    transition: (..., T, n, n) the A_k used (a broadcast view), kept for smoothing.
    process_noise: (..., T, n, n) the Q_k used (a broadcast view), kept for smoothing.
    observed: (..., T, m) bool, the components that entered the update.
    control: (..., T, n) the input term ``G_k u_k`` of the predictions (zeros without
        inputs), kept with A_k and Q_k for multi-step predictions.
    """

    mean: Tensor
    cov: Tensor
    pred_mean: Tensor
    pred_cov: Tensor
    innovation: Tensor
    innovation_cov: Tensor
    log_likelihood: Tensor
    step_log_likelihood: Tensor
    transition: Tensor
    process_noise: Tensor
    observed: Tensor
    control: Tensor


@serializable
class SmootherResult(NamedTuple):
    """Output of :func:`rts_smoother` (every algorithm).

    mean: (..., T, n) smoothed means E[x_k | y_{0:T-1}].
    cov: (..., T, n, n) smoothed covariances (≤ the filtered ones in the PSD order).
    gain: (..., T, n, n) smoother gains ``E_k = P_k A_{k+1}ᵀ (P⁻_{k+1})⁻¹`` (E_{T-1} = 0).
    """

    mean: Tensor
    cov: Tensor
    gain: Tensor
