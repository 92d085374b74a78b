r"""The public Kalman filter functions: one signature, three algorithms.

:func:`kalman_filter` checks, masks and whitens its arguments once
(:mod:`~torchsde_lti.filters.inputs`) and runs one of

- the sequential loop (:mod:`~torchsde_lti.filters.sequential`, default): Joseph form, O(T) depth;
- the square-root loop (:mod:`~torchsde_lti.filters.square_root`, ``square_root=True``);
- the associative scan (:mod:`~torchsde_lti.filters.parallel`, ``parallel=True``), O(log T)
  depth, in memory-bounded time chunks.

:func:`parallel_kalman_filter` is ``kalman_filter(..., parallel=True)``.
"""

from __future__ import annotations

from typing import Any

from torch import Tensor

from torchsde_lti.filters.inputs import FilterInputs, prepare_inputs
from torchsde_lti.filters.parallel import chunked_scan
from torchsde_lti.filters.results import FilterResult
from torchsde_lti.filters.sequential import sequential_filter
from torchsde_lti.filters.square_root import square_root_filter

__all__ = ["kalman_filter", "parallel_kalman_filter"]


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
    square_root: bool = False,
    D: Tensor | None = None,
    compile_step: bool = False,
    *,
    parallel: bool = False,
    chunk: int | None = None,
    validate_args: bool = True,
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
        square_root: propagate factors ``P = S Sᵀ`` (QR predict, Givens update, see
            :func:`~torchsde_lti.filters.square_root.square_root_filter`) instead of
            covariances; same results up to rounding, covariances PSD by construction and
            accurate in float32 when predicted and measurement variances differ by more than
            1/eps. Slower (a batched LAPACK QR per step); off by default; loop only.
        D: optional (..., [T,] m, p) feedthrough, ``y_k = H_k x_k + D u_k + r_k``: the update
            uses ``y_k − D u_k`` (so innovations are ``y_k − D u_k − H_k m⁻_k``); needs u.
        compile_step: run the loop as torch's structured scan through ``torch.compile`` (one
            step's graph compiled once, the T steps not unrolled).
        parallel: the associative scan (Särkkä & García-Fernández 2021) instead of the loop:
            O(log T) depth, same results up to rounding; wins when per-step overhead
            dominates (few tracks, long series).
        chunk: with ``parallel``, time steps per scan chunk (None: the largest chunk with
            batch · chunk ≤ :data:`~torchsde_lti.filters.parallel.SCAN_MAX_ELEMENTS`).
        validate_args: check the values (finite A, H, m0, u, D; Q, P0 symmetric PSD; R
            positive definite); shapes are always checked. Modules that assemble already
            valid matrices pass False.

    Returns:
        :class:`FilterResult`; every output broadcasts to the full batch ``...``.
    """
    args = FilterInputs(y, A, Q, H, R, m0, P0, G, u, mask, D)
    if parallel:
        if square_root:
            raise ValueError("square_root=True needs the sequential filter, got parallel=True")
        return chunked_scan(args, chunk, validate_args)
    prep = prepare_inputs(args, validate_args)
    if square_root:
        return square_root_filter(prep)
    return sequential_filter(prep, compile_step)


def parallel_kalman_filter(*args: Any, **kwargs: Any) -> FilterResult:
    r"""``kalman_filter(..., parallel=True)``: the associative-scan Kalman filter, O(log T) depth.

    Same arguments and results as :func:`kalman_filter` (up to rounding); ``chunk=`` bounds
    the memory of long series. Step elements and their combination:
    :func:`~torchsde_lti.filters.parallel.scan_filter`.
    """
    return kalman_filter(*args, parallel=True, **kwargs)
