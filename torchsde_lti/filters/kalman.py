r"""The public Kalman filter function: one signature, one ``algorithm=`` argument.

:func:`kalman_filter` checks, masks and whitens its arguments once
(:mod:`~torchsde_lti.filters.inputs`) and runs one of :data:`ALGORITHMS`:

- ``"sequential"``: the Joseph-form loop (:mod:`~torchsde_lti.filters.sequential`), O(T) depth;
  under ``torch.compile`` and ``torch.export`` it runs as torch's structured scan (one step
  traced, T not unrolled: an exported program takes a dynamic T);
- ``"square_root"``: the Cholesky-factor loop (:mod:`~torchsde_lti.filters.square_root`);
- ``"scan"``: the associative scan (:mod:`~torchsde_lti.filters.scan`), O(log T) depth, in
  memory-bounded time chunks;
- ``"auto"`` (default): :func:`choose_algorithm`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from torchsde_lti.core.validation import common_float_dtype
from torchsde_lti.filters.inputs import FilterInputs, PreparedInputs, complete_from_filtered, prepare_inputs
from torchsde_lti.filters.results import FilterResult
from torchsde_lti.filters.runtime import eager_runtime_tracing
from torchsde_lti.filters.scan import _scan_suits, chunked_scan, prefers_scan, scan_filtered
from torchsde_lti.filters.sequential import sequential_filter, structured_filtered
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
    algorithm: str, batch_size: int, T: int, device: torch.device, dtype: torch.dtype = torch.float64
) -> str:
    """The algorithm a call runs: ``algorithm`` itself unless it is ``"auto"``.

    ``"auto"``: under ``torch.compile`` and ``torch.export`` the sequential loop, which
    then runs as torch's structured scan (one step compiled: seconds to compile, and an
    exported program takes any T; the associative scan traced whole takes minutes and fixes
    T); exported for a program run op by op
    (:func:`~torchsde_lti.filters.runtime.traced_for_eager_runtime`) ``"auto"`` stays, and
    the program picks the scan or the loop by its batch size as eager calls do; otherwise the
    associative scan where :func:`~torchsde_lti.filters.prefers_scan` says so (few tracks on
    CPU, any batch on other devices; float64 only), else the sequential loop. ``batch_size``:
    tracks in the call; ``dtype``: the call's floating dtype.
    """
    check_algorithm(algorithm)
    if algorithm != "auto":
        return algorithm
    if torch.compiler.is_compiling():
        # traced for torch's compilers: the loop as one structured scan step; for a program
        # run op by op ("auto" kept): chosen inside the program by the batch size
        return "auto" if eager_runtime_tracing() else "sequential"
    return "scan" if prefers_scan(batch_size, T, device, dtype) else "sequential"


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
    algorithm: str = "auto",
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
        D: optional (..., [T,] m, p) feedthrough, ``y_k = H_k x_k + D u_k + r_k``: the update
            uses ``y_k − D u_k`` (so innovations are ``y_k − D u_k − H_k m⁻_k``); needs u.
        algorithm: one of :data:`ALGORITHMS`, same results up to rounding:
            ``"sequential"`` (Joseph-form loop, O(T) depth), ``"square_root"`` (propagates
            factors ``P = S Sᵀ``: QR predict, Givens update, covariances PSD by construction
            and accurate in float32 when predicted and measurement variances differ by more
            than 1/eps; slower), ``"scan"`` (associative scan, Särkkä & García-Fernández
            2021: O(log T) depth, wins when per-step overhead dominates: few tracks, long
            series) or ``"auto"`` (:func:`choose_algorithm`).
        chunk: with the scan, time steps per scan chunk, a positive int (None: the largest
            chunk with batch · chunk ≤ :data:`~torchsde_lti.filters.scan.SCAN_MAX_ELEMENTS`).
        validate_args: check the values (y without Inf; finite A, H, m0, u, D; Q, P0
            symmetric PSD; R positive definite), then use the checked Q, R, P0 as their
            symmetric parts ``(X + Xᵀ) / 2``, so every algorithm computes the same function
            of them and returns the same, symmetric gradient (a gradient step keeps a learned
            Q symmetric); shapes are always checked. Modules that assemble already valid
            (exactly symmetric) matrices pass False: the matrices are then used as given.

    Returns:
        :class:`FilterResult`; every output broadcasts to the full batch ``...``.
    """
    args = FilterInputs(y, A, Q, H, R, m0, P0, G, u, mask, D)
    if algorithm == "auto":
        y_t, A_t = torch.as_tensor(y), torch.as_tensor(A)
        batch = max(math.prod(y_t.shape[:-2]), math.prod(A_t.shape[:-3]))
        T = y_t.shape[-2] if y_t.dim() >= 2 else 1
        algorithm = choose_algorithm(algorithm, batch, T, y_t.device, common_float_dtype(y_t, A_t))
    return run_filter(args, algorithm, chunk=chunk, validate_args=validate_args)


def run_filter(
    args: FilterInputs,
    algorithm: str,
    *,
    chunk: int | None = None,
    validate_args: bool = True,
    compiled_loop: bool = False,
) -> FilterResult:
    """:func:`kalman_filter` on an argument bundle with a chosen algorithm (not ``"auto"``).

    ``compiled_loop``: run the sequential loop as torch's structured scan compiled on its own
    also outside a ``torch.compile`` trace (what :class:`~torchsde_lti.KalmanFilter` runs under
    ``torch.compile``, with its discretisation eager); inside a trace it always does.
    """
    check_algorithm(algorithm, ALGORITHMS if eager_runtime_tracing() else ALGORITHMS[1:])
    return _run_algorithm(args, algorithm, chunk, validate_args, compiled_loop)


def _run_algorithm(
    args: FilterInputs, algorithm: str, chunk: int | None, validate_args: bool, compiled_loop: bool
) -> FilterResult:
    """:func:`run_filter`'s body."""
    if algorithm == "auto":  # traced for a program run op by op
        return _chosen_in_program(prepare_inputs(args, validate_args))
    if algorithm == "scan":
        return chunked_scan(args, chunk, validate_args)
    prep = prepare_inputs(args, validate_args)
    if algorithm == "square_root":
        return square_root_filter(prep)
    # traced (torch.compile, torch.export): the loop as torch's structured scan, one step's
    # graph for any T (an exported program then takes any T: a dynamic time axis)
    return sequential_filter(prep, compiled_loop or torch.compiler.is_compiling())


def _chosen_in_program(prep: PreparedInputs) -> FilterResult:
    """The filter of a program traced to run op by op, with :func:`choose_algorithm`'s choice
    between the associative scan (over any T: its levels one ``while_loop``) and the loop
    (torch's structured scan) made inside the program (``torch.cond``) where the batch size is
    dynamic."""
    scan = _scan_suits(math.prod(prep.mean_batch), prep.m0.device, prep.A.dtype)  # (T: the scan takes any)
    if isinstance(scan, bool):
        filtered = scan_filtered(prep) if scan else structured_filtered(prep)
    else:  # (the branches take the tensors as operands and read every size from them)
        slots = [i for i, x in enumerate(prep) if isinstance(x, Tensor)]
        rest = [None if isinstance(x, Tensor) else x for x in prep]  # (no tensor reaches a branch but by operand)

        def branch(run: Callable[[PreparedInputs], tuple[Tensor, Tensor]]) -> Callable[..., tuple[Tensor, Tensor]]:
            def from_operands(*tensors: Tensor) -> tuple[Tensor, Tensor]:
                fields: list[object] = list(rest)
                for i, t in zip(slots, tensors):
                    fields[i] = t
                m0 = tensors[slots.index(PreparedInputs._fields.index("m0"))]  # (*mb, n)
                y0 = tensors[slots.index(PreparedInputs._fields.index("y0"))]  # (..., T, m)
                fields[-2:] = [m0.shape[:-1], y0.shape[-2]]  # mean_batch, T
                mean, cov = run(PreparedInputs(*fields))
                return mean.contiguous(), cov.contiguous()  # (both branches' outputs: one layout)

            return from_operands

        # (operands are copied: a view among them can fail torch's transfer of its base's symbolic
        # sizes into the branches' trace, and operands that share memory are refused)
        operands = tuple(prep[i].clone() for i in slots)
        filtered = torch.cond(scan, branch(scan_filtered), branch(structured_filtered), operands)
    return complete_from_filtered(prep, *filtered)
