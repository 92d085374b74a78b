r"""Exact discretisation of LTI SDEs ``dx = F x dt + B u dt + L dβ`` (spectral density Qc).

Over a step dt with u held constant (zero-order hold), ``x' = A x + G u + q``, ``q ~ N(0, Q)``::

    A = expm(F dt),   G = ∫_0^dt expm(F s) ds B,   Q = ∫_0^dt expm(F s) W expm(F s)ᵀ ds,   W = L Qc Lᵀ.

Methods: ``"doubling"`` (default; scaling and doubling, PSD and accurate for stiff F and
large dt in float32 too: the recurrence of module ``_doubling``, its one-parameter-set
specialisation in :mod:`~torchsde_lti.core.series`) and ``"matrix_exp"`` (the design card's
layer: :func:`torch.matrix_exp` of Van Loan's block; its ``−Fᵀ`` block grows like
``e^{|λ| dt}``; where a gradient is asked for, it is the doubling's: torch.matrix_exp's own
backward of the block goes wrong long before its values do). The route is chosen from the
shapes and ``method`` alone.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor
from torch.fx.experimental.symbolic_shapes import statically_known_true

from torchsde_lti.core._doubling import Results, per_element_doubling
from torchsde_lti.core.linalg import sym
from torchsde_lti.core.series import SharedSeries, shared_series
from torchsde_lti.core.validation import (
    SDEInputs,
    _psd_test,
    _value_check,
    check_matrix,
    checks_values,
    sde_inputs,
    shape_str,
)

__all__ = [
    "METHODS",
    "Discrete",
    "SharedSeries",
    "check_matrix_exp_noise",
    "discretization_series",
    "discretize",
    "discretize_series",
    "doubling",
    "process_noise",
    "resolve_method",
    "transition_matrix",
    "zero_order_hold",
]

#: Discretisation methods.
METHODS = ("doubling", "matrix_exp")


class Discrete(NamedTuple):
    """Exact discrete-time model over a step: ``x' = A x + G u + q``, ``q ~ N(0, Q)``.

    A: (..., n, n) transition matrix expm(F dt).
    Q: (..., n, n) process-noise covariance (symmetric PSD).
    G: (..., n, p) zero-order-hold input matrix, or None when the SDE has no input.
    """

    A: Tensor
    Q: Tensor
    G: Tensor | None


def resolve_method(method: str) -> str:
    """``method`` if it is one of :data:`METHODS`; ValueError naming it otherwise."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    return method


def _one_set(x: SDEInputs) -> bool:
    """Whether F, W and B hold ONE parameter set (no batch elements, or one): from the shapes, and
    while traced only where that is known without a guard (a dynamic batch of F is many sets)."""
    return all(t is None or statically_known_true(math.prod(t.shape[:-2]) == 1) for t in (x.F, x.W, x.B))


def doubling(x: SDEInputs, batch_last: bool = False) -> Results:
    """The doubling method: (A, Q, G) of shapes (*batch, n, n), (*batch, n, n) or None,
    (*batch, n, p) or None (with ``batch_last`` contiguous (n, n, *batch), …). ONE parameter set
    (F, W, B without batch elements) takes :class:`SharedSeries`; everything else
    :func:`~torchsde_lti.core._doubling.per_element_doubling`."""
    assert x.dt is not None
    if _one_set(x):
        F, W, B = (None if t is None else t.reshape(t.shape[-2:]) for t in (x.F, x.W, x.B))
        assert F is not None
        return shared_series(F, W, B)(x.dt.expand(x.batch), batch_last)
    return per_element_doubling(x, batch_last)


def _matrix_exp(x: SDEInputs) -> Results:
    """The ``"matrix_exp"`` method: one :func:`torch.matrix_exp` of the smallest block that holds
    what is asked for: ``expm(F dt)`` for A alone, ``expm([[F, B], [0, 0]] dt) = [[A, G], [0, I]]``
    with B, and with noise Van Loan's ``expm([[F, W, B], [0, −Fᵀ, 0], [0, 0, 0]] dt) =
    [[A, X, G], [0, A⁻ᵀ, 0], [0, 0, I]]``, ``Q = X Aᵀ`` (symmetrised)."""
    F, W, B, dt, batch = x.F, x.W, x.B, x.dt, x.batch
    assert dt is not None
    n, p = F.shape[-1], 0 if B is None else B.shape[-1]
    d = dt[..., None, None]
    zero = F.new_zeros(())
    top = [
        t.expand(*batch, n, t.shape[-1])
        for t in (F * d, None if W is None else W * d, None if B is None else B * d)
        if t is not None
    ]
    rows = [torch.cat(top, -1)]
    if W is not None:  # [0, −Fᵀ dt, 0]
        rows.append(torch.cat([zero.expand(*batch, n, n), -top[0].mT, zero.expand(*batch, n, p)], -1))
    if B is not None:  # [0, 0, 0]
        rows.append(zero.expand(*batch, p, rows[0].shape[-1]))
    E = torch.matrix_exp(torch.cat(rows, -2))
    A = E[..., :n, :n]
    Q = None if W is None else sym(E[..., :n, n : 2 * n] @ A.mT)
    return A, Q, None if B is None else E[..., :n, E.shape[-1] - p :]


def _check_result(inputs: SDEInputs, results: Results, method: str) -> None:
    """ValueError when a result is not finite although the (checked) arguments are: the exact
    values exceed the dtype's range (an unstable F over a long step, a huge noise or input), or
    ``"matrix_exp"``'s −Fᵀ block overflows. One synchronisation."""
    parts = [t for t in results if t is not None and t.numel()]
    with torch.no_grad():
        if not parts or bool(torch.stack([t.sum() for t in parts]).isfinite().all()):
            return
        bad = [name for name, t in zip("AQG", results) if t is not None and not bool(torch.isfinite(t).all())]
        if not bad:  # a finite result whose sum overflowed
            return
        real = torch.linalg.eigvals(inputs.F.double()).real
        rightmost, leftmost = float(real.max()), float(real.min())
        dt_max = float(inputs.dt.max()) if inputs.dt is not None and inputs.dt.numel() else 0.0
    if method == "matrix_exp" and leftmost < 0 and -leftmost >= rightmost:
        cause = (
            f"method='matrix_exp' overflows for this F (leftmost eigenvalue real part {leftmost:.3g}): the −Fᵀ block of "
            "Van Loan's exponential grows like e^(|Re λ| dt) for its stable modes, faster than the result itself; "
            "the default method='doubling' does not"
        )
    else:
        wider = "" if inputs.F.dtype == torch.float64 else ", or use float64"
        cause = (
            f"F's rightmost eigenvalue has real part {rightmost:.3g}; an unstable F grows like e^(Re λ dt); "
            f"shorten dt or rescale the state{wider}"
        )
    raise ValueError(
        f"the discretisation overflows {inputs.F.dtype}: {', '.join(bad)} not finite for dt up to {dt_max:.3g} ({cause})"
    )


@_value_check
def check_matrix_exp_noise(Q: Tensor) -> None:
    """ValueError where ``method="matrix_exp"``'s Q (..., n, n) is not finite, or not PSD beyond
    √eps of its largest entry: the cancellation ``Q = X Aᵀ`` of Van Loan's block (growing like
    ``‖e^{F dt}‖ ‖e^{−F dt}‖``) has lost it. A zero Q (dt = 0) passes. One synchronisation;
    nothing while tracing."""
    if Q.numel() == 0:
        return
    with torch.no_grad():
        passes, _, scale = _psd_test(Q, math.sqrt(torch.finfo(Q.dtype).eps))
        if bool(passes):
            return
        if not bool(torch.isfinite(Q).all()):
            raise ValueError(
                f"method='matrix_exp' gave a process noise Q that is not finite (shape {shape_str(Q)}): Van Loan's "
                "block exponential overflows for a large ‖F‖ dt (its −Fᵀ block grows like e^(|Re λ| dt)); the "
                "default method='doubling' does not"
            )
        lowest = float((torch.linalg.eigvalsh(Q).amin(dim=-1) / scale.clamp_min(torch.finfo(Q.dtype).tiny)).min())
    raise ValueError(
        f"method='matrix_exp' gave a process noise Q that is not positive semi-definite (smallest eigenvalue "
        f"{lowest:.3g} relative to its largest entry, shape {shape_str(Q)}): Van Loan's Q = X Aᵀ cancels for a "
        "large ‖F‖ dt; the default method='doubling' stays PSD"
    )


def _required(dt: Tensor | float | None, B: Tensor | None = None, needs_B: bool = False) -> None:
    """ValueError for a missing dt (every function of dt), or a missing B where G is asked for."""
    if dt is None:
        raise ValueError("dt is required: (...) non-negative step lengths, or a Python float")
    if needs_B and B is None:
        raise ValueError(
            "B is required: the (..., n, p) input matrix whose zero-order hold G = ∫ expm(F s) ds B is asked for"
        )


def _run(inputs: SDEInputs, method: str, validate_args: bool, batch_last: bool = False) -> Results:
    """(A, Q, G) of checked arguments by ``method`` and, with ``validate_args``, the result
    checks. ``"matrix_exp"`` recording a graph: its values forward, the doubling's gradient
    backward (``e + (v − e).detach()``): torch.matrix_exp's backward differentiates the whole
    Van Loan block, whose ``−Fᵀ`` part grows like ``e^{|λ| dt}`` (a Matérn-5/2 filter over gaps
    of 20 lengthscales: 1e21 against the exact −31)."""
    if resolve_method(method) == "matrix_exp":
        results = _matrix_exp(inputs)
        if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in inputs[:4]):
            exact = doubling(inputs)
            results = tuple(None if v is None or e is None else e + (v - e).detach() for v, e in zip(results, exact))  # type: ignore[assignment]
        if batch_last:
            results = tuple(None if t is None else t.movedim((-2, -1), (0, 1)).contiguous() for t in results)  # type: ignore[assignment]
    else:
        results = doubling(inputs, batch_last)
    if checks_values(validate_args):
        _check_result(inputs, results, method)
        if method == "matrix_exp" and results[1] is not None:
            check_matrix_exp_noise(results[1])
    return results


def discretize(
    F: Tensor,
    L: Tensor,
    Qc: Tensor,
    dt: Tensor | float,
    B: Tensor | None = None,
    method: str = "doubling",
    *,
    validate_args: bool = True,
) -> Discrete:
    r"""Exact discretisation (A, Q, G) of ``dx = F x dt + B u dt + L dβ`` over steps dt.

    All leading dimensions broadcast (numpy rules, right-aligned): F (n, n) with dt (B, T)
    gives (B, T, n, n); F (B, 1, n, n) with dt (B, T) gives (B, T, n, n).

    Args:
        F: (..., n, n) drift matrix.
        L: (..., n, s) noise-input matrix.
        Qc: (..., s, s) spectral density of β (symmetric PSD).
        dt: (...) non-negative step lengths; a Python float is a scalar.
        B: optional (..., n, p) input matrix; u is held constant over each step.
        method: ``"doubling"`` (default; accurate and PSD for stiff F and large dt) or
            ``"matrix_exp"`` (torch.matrix_exp of Van Loan's block; gradients, where asked for, the
            doubling's).
        validate_args: check the values (finite, dt ≥ 0, Qc symmetric PSD) and that the result is
            finite; shapes are always checked. False reads nothing to the host.

    Returns:
        :class:`Discrete` with A (..., n, n), Q (..., n, n) symmetric PSD and
        G (..., n, p) or None. Differentiable with respect to F, L, Qc, B and dt.

    Raises:
        ValueError: a bad shape or value (naming the argument), or a result that overflows the dtype.
    """
    _required(dt)
    A, Q, G = _run(sde_inputs(F, L, Qc, dt, B, validate_args=validate_args), method, validate_args)
    assert Q is not None
    return Discrete(A, Q, G)


def discretize_series(
    F: Tensor,
    L: Tensor,
    Qc: Tensor,
    dt: Tensor,
    B: Tensor | None = None,
    method: str = "doubling",
    unique: bool = False,
    *,
    validate_args: bool = True,
) -> Discrete:
    """:func:`discretize` of a time series dt (..., T), laid out for a filter's time loop.

    Same values as ``discretize(F, L, Qc, dt, B, method)``. With the doubling method and ONE
    parameter set (all batch dims of F, L, Qc, B of size 1) the results are batch-first
    VIEWS (..., T, n, n) of batch-last storage (n, n, T, ...), the layout of the filter
    loop; otherwise the plain batch-first result.

    Args:
        F, L, Qc, B, method, validate_args: as in :func:`discretize`.
        dt: (..., T) step lengths.
        unique: discretise the distinct values of dt only and gather them (same values and
            gradients w.r.t. the parameters); applies to one parameter set and a dt that
            does not require grad.

    Returns:
        :class:`Discrete` with A, Q (..., T, n, n) and G (..., T, n, p) or None.
    """
    _required(dt)
    inputs = sde_inputs(F, L, Qc, dt, B, validate_args=validate_args)
    if resolve_method(method) != "doubling" or len(inputs.batch) == 0 or not _one_set(inputs):
        return Discrete(*_run(inputs, method, validate_args))  # type: ignore[arg-type]
    assert inputs.dt is not None
    lead = inputs.batch[:-1]
    steps = inputs.dt.expand(inputs.batch).movedim(-1, 0)  # (T, *lead)
    inverse = None
    if unique and not steps.requires_grad:
        steps, inverse = torch.unique(steps, return_inverse=True)
    results = _run(inputs._replace(dt=steps, batch=steps.shape), method, validate_args, batch_last=True)
    perm = [*range(3, 3 + len(lead)), 2, 0, 1]  # (r, c, T, *lead) -> (*lead, T, r, c)

    def layout(x: Tensor) -> Tensor:
        if inverse is not None:  # (r, c, U) -> (r, c, T, *lead)
            x = x.index_select(-1, inverse.reshape(-1)).reshape(*x.shape[:2], *inverse.shape)
        return x.permute(perm)

    A, Q, G = (None if x is None else layout(x) for x in results)
    return Discrete(A, Q, G)  # type: ignore[arg-type]


def transition_matrix(F: Tensor, dt: Tensor | float, method: str = "doubling", *, validate_args: bool = True) -> Tensor:
    """A = expm(F dt).

    Args:
        F: (..., n, n) drift matrix.
        dt: (...) non-negative step lengths.
        method: ``"doubling"`` or ``"matrix_exp"`` (:func:`torch.matrix_exp` of F dt).
        validate_args: as in :func:`discretize`.

    Returns:
        (..., n, n), batch broadcast from F and dt.
    """
    _required(dt)
    return _run(sde_inputs(F, None, None, dt, validate_args=validate_args), method, validate_args)[0]


def zero_order_hold(
    F: Tensor, B: Tensor, dt: Tensor | float, method: str = "doubling", *, validate_args: bool = True
) -> tuple[Tensor, Tensor]:
    """(A, G) with A = expm(F dt) and G = ∫_0^dt expm(F s) ds B: the blocks of
    expm([[F, B], [0, 0]] dt) = [[A, G], [0, I]] (what ``method="matrix_exp"`` evaluates).

    Args:
        F: (..., n, n); B: (..., n, p); dt: (...).
        method, validate_args: as in :func:`discretize`.

    Returns:
        A (..., n, n), G (..., n, p).
    """
    _required(dt, B, needs_B=True)
    A, _, G = _run(sde_inputs(F, None, None, dt, B, validate_args=validate_args), method, validate_args)
    assert G is not None
    return A, G


def process_noise(
    F: Tensor,
    L: Tensor,
    Qc: Tensor,
    dt: Tensor | float,
    method: str = "doubling",
    *,
    validate_args: bool = True,
) -> Tensor:
    """Q = ∫_0^dt expm(F s) L Qc Lᵀ expm(F s)ᵀ ds, the discrete process-noise covariance.

    Args:
        F: (..., n, n); L: (..., n, s); Qc: (..., s, s) symmetric PSD; dt: (...).
        method, validate_args: as in :func:`discretize`.

    Returns:
        (..., n, n) symmetric PSD.
    """
    return discretize(F, L, Qc, dt, method=method, validate_args=validate_args).Q


def discretization_series(F: Tensor, W: Tensor | None, B: Tensor | None = None) -> SharedSeries:
    """The dt-independent part of the doubling discretisation of ONE parameter set, to form
    once and call on many steps: ``series(dt)`` -> (A, Q, G) over dt (...) (with
    ``batch_last=True`` contiguous (n, n, ...), …), the values of :func:`discretize`'s default
    method to rounding.

    F: (n, n), n ≥ 1; W = L Qc Lᵀ: (n, n) or None (symmetric PSD); B: (n, p) or None; all of
    F's dtype and device. A nilpotent F (an integrator chain) is found on the device: its series
    terminates and takes no halving (:mod:`~torchsde_lti.core.series`). No value is read to the
    host (traceable).

    Shapes are checked, ValueError naming the argument; values are not (form
    the series from checked matrices, e.g. an SDE's ``matrices()``).
    """
    if not isinstance(F, Tensor) or not F.is_floating_point():
        raise TypeError(f"F must be a real floating tensor, got {type(F).__name__}")
    if F.dim() != 2:
        raise ValueError(f"F must be one (n, n) matrix (no batch dims), got shape {shape_str(F)}")
    check_matrix(F, "F", square=True)
    n = F.shape[-1]
    if n == 0:
        raise ValueError("F must have at least one state, got shape (0, 0)")
    for name, x, cols in (("W", W, n), ("B", B, None)):
        if x is None:
            continue
        if x.dim() != 2:
            raise ValueError(f"{name} must be one matrix with {n} rows (no batch dims), got shape {shape_str(x)}")
        check_matrix(x, name, rows=n, cols=cols)
        if x.dtype != F.dtype or x.device != F.device:
            raise ValueError(
                f"{name} must have F's dtype and device ({F.dtype}, {F.device}), got {x.dtype}, {x.device}"
            )
    return shared_series(F, W, B)
