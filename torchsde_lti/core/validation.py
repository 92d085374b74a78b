"""Argument checks: ``ValueError`` (``TypeError`` for non-numeric input) naming the argument
and the shapes.

Shapes are always checked. Values (finite, signs, PSD) are checked once, at the public
boundary, against the constraints each function declares (torch.distributions' pattern:
:data:`SDE_CONSTRAINTS`), with one read to the host when they hold; ``validate_args=False``
reads nothing, and no check changes a value. While torch.compile / torch.export trace, values
are symbolic and only the shapes are checked.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Sequence
from typing import NamedTuple, TypeVar

import torch
from torch import Tensor

from torchsde_lti.core.linalg import noise_covariance, sym

_C = TypeVar("_C", bound=Callable[..., None])


def tracing() -> bool:
    """Whether torch.compile or torch.export is tracing the call (values are symbolic)."""
    return torch.compiler.is_compiling()


def checks_values(validate_args: bool) -> bool:
    """Whether value checks run: ``validate_args`` and not :func:`tracing`."""
    return validate_args and not tracing()


def _value_check(check: _C) -> _C:
    """A value check (it reads its tensors to the host): skipped while :func:`tracing`."""

    @functools.wraps(check)
    def gated(*args: object, **kwargs: object) -> None:
        if not tracing():
            check(*args, **kwargs)

    return gated  # type: ignore[return-value]


def shape_str(x: Tensor) -> str:
    return "(" + ", ".join(str(d) for d in x.shape) + ")"


def as_float_tensor(
    x: object, name: str, dtype: torch.dtype | None = None, device: torch.device | None = None
) -> Tensor:
    """``x`` as a floating tensor (a tensor keeps its autograd history); TypeError naming it."""
    if isinstance(x, Tensor):
        if x.is_complex() or not (x.is_floating_point() or dtype is not None):
            raise TypeError(f"{name} must be a real floating tensor, got dtype {x.dtype}")
        return x.to(dtype=dtype or x.dtype, device=device or x.device)
    try:
        t = torch.as_tensor(x, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"{name} must be a tensor or array-like of numbers, got {type(x).__name__}") from err
    return t if t.is_floating_point() else t.to(torch.get_default_dtype())


def common_float_dtype(*tensors: Tensor | None) -> torch.dtype:
    """The promoted floating dtype of the given tensors (the default dtype if none is floating)."""
    dtypes = {t.dtype for t in tensors if t is not None and t.is_floating_point()}
    return functools.reduce(torch.promote_types, dtypes) if dtypes else torch.get_default_dtype()


def check_matrix(x: Tensor, name: str, rows: int | None = None, cols: int | None = None, square: bool = False) -> None:
    """ValueError unless ``x`` is (..., rows, cols) (``square``: rows == cols)."""
    if x.dim() < 2:
        raise ValueError(f"{name} must be a matrix of shape (..., r, c), got shape {shape_str(x)}")
    r, c = x.shape[-2], x.shape[-1]
    if square and r != c:
        raise ValueError(f"{name} must be square (..., n, n), got shape {shape_str(x)}")
    if rows is not None and r != rows:
        raise ValueError(f"{name} must have {rows} rows, got shape {shape_str(x)}")
    if cols is not None and c != cols:
        raise ValueError(f"{name} must have {cols} columns, got shape {shape_str(x)}")


def check_vector(x: Tensor, name: str, size: int) -> None:
    """ValueError unless ``x`` is (..., size)."""
    if x.dim() < 1 or x.shape[-1] != size:
        raise ValueError(f"{name} must have shape (..., {size}), got shape {shape_str(x)}")


@_value_check
def check_finite(x: Tensor, name: str) -> None:
    """ValueError if ``x`` holds NaN or ±Inf (the sum first: one reduction)."""
    if not bool(x.sum().isfinite()) and not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains NaN or Inf (shape {shape_str(x)})")


@_value_check
def check_no_inf(x: Tensor, name: str) -> None:
    """ValueError if ``x`` holds ±Inf (NaN allowed: a missing observation)."""
    if bool(torch.isinf(x).any()):
        raise ValueError(f"{name} contains Inf (shape {shape_str(x)}); mark missing values with NaN or mask")


@_value_check
def _check_nonnegative(x: Tensor, name: str) -> None:
    check_finite(x, name)
    if x.numel() and bool((x < 0).any()):
        raise ValueError(f"{name} must be non-negative, got min {float(x.min()):.3g} (shape {shape_str(x)})")


@_value_check
def check_hurwitz(F: Tensor, name: str = "F") -> None:
    """ValueError unless every eigenvalue of ``F`` (..., n, n) has a negative real part (naming
    the rightmost one; NaN/Inf in F named as such). One synchronisation."""
    if F.numel() == 0:
        return
    with torch.no_grad():
        rightmost = torch.linalg.eigvals(torch.nan_to_num(F)).real.amax(dim=-1)  # LAPACK crashes on NaN
        if bool((rightmost < 0).all() & torch.isfinite(F).all()):
            return
    check_finite(F, name)
    raise ValueError(
        f"{name} must be Hurwitz-stable (all eigenvalues with negative real part); got an eigenvalue with "
        f"real part {float(rightmost.max()):.3g} ({name} shape {shape_str(F)})"
    )


def psd_tolerance(x: Tensor) -> float:
    """Relative tolerance for symmetry/PSD checks: a few hundred ulps per dimension."""
    return 100.0 * x.shape[-1] * torch.finfo(x.dtype).eps


def _psd_test(x: Tensor, tol: float | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """(passes, asym, scale) of x (..., k, k), without synchronising, on ``y = x / max|x|``
    (0 for a zero x): ``passes`` (0-dim bool) — y symmetric within ``tol``
    (:func:`psd_tolerance` by default) and ``y + tol I`` has a Cholesky factor; asym (...)
    max |y − yᵀ|; scale (...) max |x|."""
    tol = psd_tolerance(x) if tol is None else tol
    scale = x.abs().amax(dim=(-2, -1))
    y = x / torch.where(scale > 0, scale, 1.0)[..., None, None]
    asym = (y - y.mT).abs().amax(dim=(-2, -1))
    shifted = y + tol * torch.eye(x.shape[-1], dtype=x.dtype, device=x.device)
    lapack = shifted if x.dtype in (torch.float32, torch.float64) else shifted.float()  # (no half LAPACK)
    return ((asym <= tol) & (torch.linalg.cholesky_ex(lapack).info == 0)).all(), asym, scale


@_value_check
def _check_psd_values(x: Tensor, name: str) -> None:
    check_finite(x, name)
    if x.numel() == 0:
        return
    with torch.no_grad():
        passes, asym, scale = _psd_test(x)
        if bool(passes):  # the one synchronisation on the valid path
            return
        if bool((asym > psd_tolerance(x)).any()):
            raise ValueError(
                f"{name} must be symmetric, got relative asymmetry {float(asym.max()):.3g} (shape {shape_str(x)})"
            )
        lapack = x if x.dtype in (torch.float32, torch.float64) else x.float()
        eig_min = torch.linalg.eigvalsh(sym(lapack)).amin(dim=-1) / scale.clamp_min(torch.finfo(x.dtype).tiny)
    raise ValueError(
        f"{name} must be positive semi-definite, got smallest eigenvalue "
        f"{float(eig_min.min()):.3g} relative to its largest entry (shape {shape_str(x)})"
    )


def check_symmetric_psd(x: Tensor, name: str) -> None:
    """Check ``x`` (..., k, k) is square (always) and symmetric positive semi-definite to
    :func:`psd_tolerance` of its largest entry (values)."""
    check_matrix(x, name, square=True)
    _check_psd_values(x, name)


class Constraint(NamedTuple):
    """A declared value constraint: ``holds(x)`` a 0-dim bool tensor (no synchronisation),
    ``check(x, name)`` the detailed check that raises the ValueError naming ``name``."""

    holds: Callable[[Tensor], Tensor]
    check: Callable[[Tensor, str], None]


finite = Constraint(lambda x: x.sum().isfinite(), check_finite)
nonnegative = Constraint(lambda x: x.sum().isfinite() & (x.amin() >= 0 if x.numel() else True), _check_nonnegative)
symmetric_psd = Constraint(lambda x: x.sum().isfinite() & _psd_test(x)[0], _check_psd_values)

#: The value constraints of an SDE's arguments (every core function that takes them).
SDE_CONSTRAINTS: dict[str, Constraint] = {"F": finite, "L": finite, "Qc": symmetric_psd, "B": finite, "dt": nonnegative}


@_value_check
def check_constraints(named: Sequence[tuple[str, Tensor | None]], constraints: dict[str, Constraint]) -> None:
    """ValueError naming the first argument (None skipped) that breaks ``constraints[name]``;
    one synchronisation when all hold."""
    present = [(name, x) for name, x in named if x is not None]
    with torch.no_grad():
        if not present or bool(torch.stack([constraints[name].holds(x) for name, x in present]).all()):
            return
    for name, x in present:  # (a finite sum that overflowed passes these)
        constraints[name].check(x, name)


def broadcast_shapes(*shapes: Sequence[int]) -> torch.Size:
    """Broadcast shapes (numpy rules); ValueError when they do not broadcast. Plain Python on
    ints (``torch.broadcast_shapes`` costs tens of µs a call eagerly), torch's on symbolic sizes."""
    if not all(isinstance(d, int) for shape in shapes for d in shape):
        try:
            return torch.broadcast_shapes(*shapes)
        except RuntimeError:
            raise ValueError(f"shapes {[tuple(s) for s in shapes]} do not broadcast") from None
    out = [1] * max([0, *map(len, shapes)])
    for shape in shapes:
        for i, d in enumerate(shape, len(out) - len(shape)):
            if d != 1 and out[i] != d:
                if out[i] != 1:
                    raise ValueError(f"shapes {[tuple(s) for s in shapes]} do not broadcast")
                out[i] = d
    return torch.Size(out)


def broadcast_batch(named: Sequence[tuple[str, Sequence[int]]]) -> torch.Size:
    """Broadcast named batch shapes (numpy rules), naming them all when they do not broadcast."""
    try:
        return broadcast_shapes(*(s for _, s in named))
    except ValueError:
        seen = ", ".join(f"{n}: ({', '.join(map(str, s))})" for n, s in named)
        raise ValueError(f"batch shapes do not broadcast: {seen}") from None


def parse_learn(learn: Iterable[str] | str, allowed: Sequence[str]) -> tuple[str, ...]:
    """The names in ``learn`` (one name or several), each checked to be among ``allowed``."""
    names = (learn,) if isinstance(learn, str) else tuple(learn)
    if any(name not in allowed for name in names):
        raise ValueError(f"learn must name some of {tuple(allowed)}, got {names!r}")
    return names


class SDEInputs(NamedTuple):
    """Checked SDE arguments: F (..., n, n), W = L Qc Lᵀ (..., n, n) or None, B (..., n, p)
    or None, dt (...) or None, and the broadcast batch shape of all of them."""

    F: Tensor
    W: Tensor | None
    B: Tensor | None
    dt: Tensor | None
    batch: torch.Size


def sde_inputs(
    F: Tensor,
    L: Tensor | None,
    Qc: Tensor | None,
    dt: Tensor | float | None = None,
    B: Tensor | None = None,
    *,
    validate_args: bool = True,
) -> SDEInputs:
    """The SDE's arguments in their common float dtype on F's device, checked: shapes always
    (ValueError naming the argument and the shapes), values against :data:`SDE_CONSTRAINTS`
    with ``validate_args``; W = L Qc Lᵀ."""
    F = as_float_tensor(F, "F")
    dtype = common_float_dtype(*(x if isinstance(x, Tensor) else None for x in (F, L, Qc, B)))
    F, device = F.to(dtype), F.device
    check_matrix(F, "F", square=True)
    n = F.shape[-1]
    if n == 0:
        raise ValueError(f"F must have a state dimension n >= 1, got shape {shape_str(F)}")
    if (L is None) != (Qc is None):
        raise ValueError("L and Qc must be given together")
    if L is not None and Qc is not None:
        L, Qc = as_float_tensor(L, "L", dtype, device), as_float_tensor(Qc, "Qc", dtype, device)
        check_matrix(L, "L", rows=n)
        s = L.shape[-1]
        if Qc.dim() < 2 or Qc.shape[-2:] != (s, s):
            raise ValueError(f"Qc must have shape (..., {s}, {s}) to match L {shape_str(L)}, got shape {shape_str(Qc)}")
    if B is not None:
        B = as_float_tensor(B, "B", dtype, device)
        check_matrix(B, "B", rows=n)
        if B.shape[-1] == 0:
            raise ValueError(f"B must have at least one column (no inputs: pass B=None), got shape {shape_str(B)}")
    dt_t = None if dt is None else as_float_tensor(dt, "dt", dtype, device)
    named = [("F", F), ("L", L), ("Qc", Qc), ("B", B), ("dt", dt_t)]
    batch = broadcast_batch([(k, x.shape if k == "dt" else x.shape[:-2]) for k, x in named if x is not None])
    if checks_values(validate_args):
        check_constraints(named, SDE_CONSTRAINTS)
    W = None if L is None or Qc is None else noise_covariance(L, Qc)
    return SDEInputs(F, W, B, dt_t, batch)
