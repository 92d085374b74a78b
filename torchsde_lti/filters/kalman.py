r"""The public Kalman filter function: one signature, one ``algorithm=`` argument.

:func:`kalman_filter` checks, masks and whitens its arguments once
(:mod:`~torchsde_lti.filters.inputs`) and runs one of :data:`ALGORITHMS`:

- ``"sequential"``: the Joseph-form loop (:mod:`~torchsde_lti.filters.sequential`), O(T) depth;
  under ``torch.compile`` and ``torch.export`` it runs as torch's structured scan (one step
  traced, T not unrolled: an exported program takes a dynamic T);
- ``"square_root"``: the Cholesky-factor loop (:mod:`~torchsde_lti.filters.square_root`);
- ``"scan"``: the associative scan (:mod:`~torchsde_lti.filters.scan`), O(log T) depth;
- ``"auto"``: the default, ``"sequential"`` (:func:`choose_algorithm` says why).

Each runs on the batch-last layout of :mod:`~torchsde_lti.filters.layout`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsde_lti.filters.inputs import FilterInputs, prepare_inputs
from torchsde_lti.filters.noise import GAUSSIAN, NoiseModel
from torchsde_lti.filters.results import FilterResult
from torchsde_lti.filters.scan import scan_filter
from torchsde_lti.filters.sequential import sequential_filter
from torchsde_lti.filters.square_root import square_root_filter

__all__ = ["ALGORITHMS", "check_algorithm", "choose_algorithm", "kalman_filter", "run_filter"]

#: The algorithms of :func:`kalman_filter` (and of :class:`~torchsde_lti.KalmanFilter`).
ALGORITHMS = ("auto", "sequential", "square_root", "scan")


def check_algorithm(algorithm: str, allowed: tuple[str, ...] = ALGORITHMS, owner: str = "kalman_filter") -> str:
    """``algorithm`` if it is among ``allowed``; ValueError naming ``owner`` and the choices otherwise."""
    if algorithm not in allowed:
        raise ValueError(f"{owner} has the algorithms {allowed}, got algorithm={algorithm!r}")
    return algorithm


def choose_algorithm(
    algorithm: str,
    batch_size: int = 1,
    T: int = 1,
    device: torch.device | None = None,
    dtype: torch.dtype | None = None,
) -> str:
    """The algorithm a call runs: ``algorithm`` itself; ``"auto"`` names the documented default,
    the sequential loop, in every dtype, on every device, eager, compiled and exported.

    Why no choice per call: which algorithm is faster depends on the batch. The loop's T steps
    each cost a per-operation overhead; the scan's 2 log₂ T levels replace them at a few times
    the loop's arithmetic. So the scan wins for one or a few long series and loses once the batch
    fills the cores, at a crossover batch set by the ratio of a machine's per-operation overhead
    to its arithmetic speed: a constant tuned to one machine. A choice by batch size would also
    need both algorithms inside one exported program with a dynamic batch. The loop scales to any
    batch and is the default; pass ``algorithm="scan"`` for a few long series (float32 included:
    ``experiments/results/scan_float32.md``); figures in the documentation's benchmarks.
    ``batch_size``, ``T``, ``device``, ``dtype``: the call's (the choice does not depend on them).
    """
    check_algorithm(algorithm)
    return "sequential" if algorithm == "auto" else algorithm


def kalman_filter(
    y: Tensor,
    A: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    m0: Tensor,
    P0: Tensor,
    G: Tensor | None = None,
    u: Tensor | None = None,
    mask: Tensor | None = None,
    D: Tensor | None = None,
    *,
    algorithm: str = "sequential",
    validate_args: bool = True,
    noise: NoiseModel = GAUSSIAN,
) -> FilterResult:
    r"""Kalman filter over T steps of the discrete model of :mod:`torchsde_lti.filters`.

    Step k: predict ``m⁻ = A_k m + G_k u_k``, ``P⁻ = A_k P A_kᵀ + Q_k``; then update with the
    observed components of y_k. The log-likelihood is the prediction-error decomposition
    ``Σ_k log N(y_k^obs; H_k^obs m⁻_k + D u_k, H_k^obs P⁻_k H_k^obsᵀ + R_k^obs)``.

    Args:
        y: (..., T, m) observations; NaN = missing component.
        A: (..., T, n, n) transitions. Q: (..., T, n, n) process noise (symmetric PSD).
        H: (..., T, m, n) observation matrices. R: (..., T, m, m) noise (symmetric PD).
        m0: (..., n) prior mean. P0: (..., n, n) prior covariance (before step 0).
        G: optional (..., T, n, p) input matrices; u: (..., T, p) inputs (u needs G or D).
        mask: optional bool (..., T) or (..., T, m); False = not observed.
        D: optional (..., [T,] m, p) feedthrough, ``y_k = H_k x_k + D u_k + r_k``: the update
            uses ``y_k − D u_k`` (so innovations are ``y_k − D u_k − H_k m⁻_k``); needs u.
        algorithm: one of :data:`ALGORITHMS`, same results up to rounding:
            ``"sequential"`` (default: Joseph-form loop, O(T) depth), ``"square_root"``
            (propagates factors ``P = S Sᵀ`` by Givens rotations: covariances PSD by
            construction and accurate in float32 when predicted and measurement variances
            differ by more than 1/eps; slower), ``"scan"`` (associative scan, Särkkä &
            García-Fernández 2021: O(log T) depth, wins where per-step overhead dominates:
            one or a few long series) or ``"auto"`` (the default's name,
            :func:`choose_algorithm`).
        validate_args: check the values (y without Inf; finite A, H, m0, u, D; Q, P0
            symmetric PSD; R positive definite) and raise a ValueError naming the argument;
            it changes nothing else. Every algorithm reads Q, R and P0 through their
            symmetric parts ``(X + Xᵀ) / 2`` with either flag, so the function, and its
            gradient (symmetric: a gradient step keeps a learned Q symmetric), is the same;
            shapes are always checked. False reads nothing to the host.
        noise: the observation-noise model (:mod:`~torchsde_lti.filters.noise`):
            :class:`~torchsde_lti.filters.GaussianNoise` (default) or
            :class:`~torchsde_lti.filters.StudentTNoise` (Roth et al.'s Student-t filter: Q, R,
            P0 and every covariance of the result are the t's scale matrices; the
            log-likelihood is the exact sum of the one-step Student-t predictive densities;
            ``"sequential"`` and ``"square_root"`` only).

    Returns:
        :class:`FilterResult`; every output broadcasts to the full batch ``...``.
    """
    args = FilterInputs(y, A, Q, H, R, m0, P0, G, u, mask, D)
    return run_filter(args, choose_algorithm(algorithm), validate_args=validate_args, noise=noise)


def run_filter(
    args: FilterInputs,
    algorithm: str,
    *,
    validate_args: bool = True,
    compiled_loop: bool = False,
    noise: NoiseModel = GAUSSIAN,
) -> FilterResult:
    """:func:`kalman_filter` on an argument bundle with a chosen algorithm (not ``"auto"``).

    ``compiled_loop``: run the sequential loop as torch's structured scan compiled on its own
    also outside a ``torch.compile`` trace (what :class:`~torchsde_lti.KalmanFilter` runs under
    ``torch.compile``, with its discretisation eager); inside a trace it always does.
    ``noise``: the observation-noise model (:func:`kalman_filter`).
    """
    check_algorithm(algorithm, ALGORITHMS[1:])
    prep = prepare_inputs(args, validate_args)
    noise = noise.check(prep.mean_batch, algorithm, validate_args)
    if algorithm == "scan":
        return scan_filter(prep)
    if algorithm == "square_root":
        return square_root_filter(prep, noise)
    # traced (torch.compile, torch.export): the loop as torch's structured scan, one step's
    # graph for any T (an exported program then takes any T: a dynamic time axis)
    return sequential_filter(prep, compiled_loop or torch.compiler.is_compiling(), noise)
