r"""Exact discretisation of LTI SDEs ``dx = F x dt + B u dt + L dβ`` (spectral density Qc).

Over a step dt with u held constant (zero-order hold), ``x' = A x + G u + q``, ``q ~ N(0, Q)``::

    A = expm(F dt),   G = ∫_0^dt expm(F s) ds B,   Q = ∫_0^dt expm(F s) W expm(F s)ᵀ ds,   W = L Qc Lᵀ.

Methods: ``"doubling"`` (default; scaling and doubling, PSD and accurate for stiff F and
large dt in float32 too, module ``_doubling``) and ``"matrix_exp"`` (:func:`torch.matrix_exp`
of Van Loan's block, module ``_matrix_exp``; its ``−Fᵀ`` block grows like ``e^{|λ| dt}``; where
a gradient is asked for, it is the doubling's: torch.matrix_exp's own backward of the block
goes wrong long before its values do).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core._doubling import SharedSeries, doubling
from torchsde_lti.core._doubling import discretization_series as _discretization_series
from torchsde_lti.core._matrix_exp import matrix_exp
from torchsde_lti.core.series import TerminatingSeries
from torchsde_lti.core.threads import intra_op_threads
from torchsde_lti.core.validation import (
    SDEInputs,
    _psd_test,
    check_matrix,
    checks_values,
    sde_inputs,
    shape_str,
    tracing,
)

__all__ = [
    "METHODS",
    "Discrete",
    "SharedSeries",
    "check_matrix_exp_noise",
    "discretization_series",
    "discretize",
    "discretize_series",
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


def _overflow_impossible(x: SDEInputs) -> bool:
    """Whether the host values (:attr:`SDEInputs.host`) bound the results and every intermediate
    of either method below the dtype's maximum: ‖A‖ ≤ e^{‖F‖ dt}, ‖Q‖ ≤ ‖W‖ dt e^{2‖F‖ dt},
    ‖G‖ ≤ ‖B‖ dt e^{‖F‖ dt} (Frobenius norms bounded by the largest entries), with a margin."""
    host = x.host
    if host is None or not host.get("dt"):
        return False
    top = {name: max(max(v), -min(v)) if v else 0.0 for name, v in host.items()}
    n = x.F.shape[-1]
    # ‖L Qc Lᵀ‖_F ≤ ‖L‖_F² ‖Qc‖_F ≤ n s² max|L|² max|Qc| (s² ≤ the number of Qc values)
    w = n * len(host.get("Qc", ())) * top.get("L", 0.0) ** 2 * top.get("Qc", 0.0)
    b = n * len(host.get("B", ())) * top.get("B", 0.0)
    with_margin = 2.0 * n * top["F"] * top["dt"] + math.log(max(1.0, (w + b) * top["dt"], float(n))) + 4.0
    return with_margin < math.log(torch.finfo(x.F.dtype).max)


def _check_result(inputs: SDEInputs, A: Tensor, Q: Tensor | None, G: Tensor | None, method: str) -> None:
    """ValueError when a result is not finite although the (checked) arguments are: the exact
    values exceed the dtype's range (an unstable F over a long step, a huge noise or input)."""
    with torch.no_grad():
        parts = [t for t in (A, Q, G) if t is not None and t.numel()]
        if not parts or bool(torch.stack([t.sum() for t in parts]).isfinite().all()):
            return
        bad = [name for name, t in zip("AQG", (A, Q, G)) if t is not None and not bool(torch.isfinite(t).all())]
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


def check_matrix_exp_noise(Q: Tensor) -> None:
    """ValueError where ``method="matrix_exp"``'s Q (..., n, n) is not finite, or not PSD beyond
    √eps of its largest entry: the cancellation ``Q = X Aᵀ`` of Van Loan's block (growing like
    ``‖e^{F dt}‖ ‖e^{−F dt}‖``) has lost it. The PSD test of the argument checks
    (``_psd_test``) at tolerance √eps and one synchronisation; nothing while tracing."""
    if tracing() or Q.numel() == 0:
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
        lowest = float((torch.linalg.eigvalsh(Q).amin(dim=-1) / scale).min())
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


def _with_doubling_gradient(values: tuple[Tensor | None, ...], exact: tuple[Tensor | None, ...]) -> tuple:
    """``values`` forward, ``exact``'s gradient backward: ``e + (v − e).detach()``. torch.matrix_exp's
    backward differentiates the whole Van Loan block, whose ``−Fᵀ`` part grows like
    ``e^{|λ| dt}``: its gradient goes wrong long before its values do (a Matérn-5/2 filter over
    gaps of 20 lengthscales: 1e21 against the exact −31)."""
    return tuple(None if v is None or e is None else e + (v - e).detach() for v, e in zip(values, exact))


def _run(inputs: SDEInputs, method: str, validate_args: bool) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """(A, Q, G) of checked arguments by ``method`` and, with ``validate_args``, the result
    check, run with :func:`intra_op_threads` (the backward too: ``inputs.finish``)."""
    with intra_op_threads(inputs.work):
        if resolve_method(method) == "matrix_exp":
            A, Q, G = matrix_exp(inputs)
            if torch.is_grad_enabled() and any(
                t is not None and t.requires_grad for t in (inputs.F, inputs.W, inputs.B, inputs.dt)
            ):
                A, Q, G = _with_doubling_gradient((A, Q, G), doubling(inputs))
        else:
            A, Q, G = doubling(inputs)
        if checks_values(validate_args) and not _overflow_impossible(inputs):
            _check_result(inputs, A, Q, G, method)
        if checks_values(validate_args) and method == "matrix_exp" and Q is not None:
            check_matrix_exp_noise(Q)
    return inputs.finish(A, Q, G)  # type: ignore[return-value]


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
        validate_args: check the values (finite, dt ≥ 0, Qc symmetric PSD); shapes are
            always checked. Inner calls on already-checked arguments pass False.

    Returns:
        :class:`Discrete` with A (..., n, n), Q (..., n, n) symmetric PSD and
        G (..., n, p) or None. Differentiable with respect to F, L, Qc, B and dt.
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
    params = [inputs.F.shape[:-2]] + [x.shape[:-2] for x in (inputs.W, inputs.B) if x is not None]
    single = all(torch.Size(s).numel() == 1 for s in params)
    if resolve_method(method) != "doubling" or len(inputs.batch) == 0 or not single:
        return Discrete(*_run(inputs, method, validate_args))  # type: ignore[arg-type]
    assert inputs.dt is not None
    lead = inputs.batch[:-1]
    dt_tm = inputs.dt.expand(inputs.batch).movedim(-1, 0)  # (T, *lead)
    inverse = None
    if unique and not dt_tm.requires_grad:
        dt_tm, inverse = torch.unique(dt_tm, return_inverse=True)
    with intra_op_threads(inputs.work):
        # (the one parameter set without its size-1 batch dims, which dt_tm's layout does not have)
        W, B_in = (None if x is None else x.reshape(x.shape[-2:]) for x in (inputs.W, inputs.B))
        one = inputs._replace(
            F=inputs.F.reshape(inputs.F.shape[-2:]), W=W, B=B_in, dt=dt_tm, batch=dt_tm.shape, host=None
        )
        A, Q, G = inputs.finish(*doubling(one, batch_last=True))
        assert A is not None
        if checks_values(validate_args):
            _check_result(inputs, A, Q, G, method)
    perm = [*range(3, 3 + len(lead)), 2, 0, 1]  # (r, c, T, *lead) -> (*lead, T, r, c)

    def layout(x: Tensor) -> Tensor:
        if inverse is not None:  # (r, c, U) -> (r, c, T, *lead)
            x = x.index_select(-1, inverse.reshape(-1)).reshape(*x.shape[:2], *inverse.shape)
        return x.permute(perm)

    A, Q, G = (None if x is None else layout(x) for x in (A, Q, G))
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


def discretization_series(
    F: Tensor, W: Tensor | None, B: Tensor | None = None, index: int | None = None, read_values: bool = True
) -> TerminatingSeries | SharedSeries:
    """The dt-independent part of the doubling discretisation of ONE parameter set, to form
    once and call on many steps: ``series(dt)`` -> (A, Q, G) over dt (...) (with
    ``batch_last=True`` contiguous (n, n, ...), …), the values of :func:`discretize`'s default
    method to rounding.

    F: (n, n), n ≥ 1; W = L Qc Lᵀ: (n, n) or None (symmetric PSD); B: (n, p) or None; all of
    F's dtype and device. A nilpotent F (F^index = 0) gives its
    :class:`~torchsde_lti.core.series.TerminatingSeries` (exact polynomial in dt), any other F
    a :class:`SharedSeries` (series terms of a sub-step, then the doubling). ``index``: F's
    nilpotency index when the model's structure fixes it; with ``read_values`` and ``index``
    None it is found from F's values (one synchronisation), without ``read_values`` None means
    not nilpotent (no value read: traceable).

    Shapes (and ``index``) are checked, ValueError naming the argument; values are not (form
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
    if index is not None and (isinstance(index, bool) or not isinstance(index, int) or not 1 <= index <= n):
        raise ValueError(f"index must be None or an int in [1, n={n}], got {index!r}")
    return _discretization_series(F, W, B, index, read_values)
