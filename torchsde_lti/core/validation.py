"""Argument checking shared by every public function.

Every check raises ``ValueError`` (or ``TypeError`` for non-numeric input) naming the
argument and the shapes it saw, so that a wrong call fails at the boundary and not deep
inside a matrix exponential. Checks that need the values (finiteness, signs, PSD) cost a
device synchronisation; they run once, at the public boundary: public functions take
``validate_args`` (default True) and inner calls pass already-checked arguments with
``validate_args=False``. While torch.compile / torch.export trace a call the values are
symbolic and only shape checks run.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core.linalg import sym


def tracing() -> bool:
    """Whether torch.compile / torch.export is tracing the call (values are symbolic then:
    no data-dependent branch may run)."""
    return torch.compiler.is_compiling() or torch.compiler.is_exporting()


def checks_values(validate_args: bool) -> bool:
    """Whether value checks (finite, non-negative, PSD) run: ``validate_args`` and not
    :func:`tracing`. Shape checks always run."""
    return validate_args and not tracing()


def shape_str(x: Tensor) -> str:
    return "(" + ", ".join(str(d) for d in x.shape) + ")"


def as_float_tensor(
    x: object, name: str, dtype: torch.dtype | None = None, device: torch.device | None = None
) -> Tensor:
    """Convert ``x`` to a floating tensor (keeping autograd history when it already is one)."""
    if isinstance(x, Tensor):
        if x.is_complex() or not (x.is_floating_point() or dtype is not None):
            raise TypeError(f"{name} must be a real floating tensor, got dtype {x.dtype}")
        if dtype is not None and x.dtype != dtype:
            x = x.to(dtype)
        if device is not None and x.device != device:
            x = x.to(device)
        return x
    try:
        t = torch.as_tensor(x, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"{name} must be a tensor or array-like of numbers, got {type(x).__name__}") from err
    if not t.is_floating_point():
        t = t.to(torch.get_default_dtype())
    return t


def common_float_dtype(*tensors: Tensor | None) -> torch.dtype:
    """The promoted floating dtype of the given tensors (float32 at least)."""
    dtype: torch.dtype | None = None
    for t in tensors:
        if t is None:
            continue
        if not t.is_floating_point():
            continue
        dtype = t.dtype if dtype is None else torch.promote_types(dtype, t.dtype)
    return dtype if dtype is not None else torch.get_default_dtype()



def as_float_tensors(**named: object) -> dict[str, Tensor | None]:
    """Every non-None argument as a floating tensor of their common dtype
    (:func:`common_float_dtype`), on the device of the first tensor given; None stays None.
    The keyword names are the argument names used in error messages."""
    tensors = [v for v in named.values() if isinstance(v, Tensor)]
    dtype = common_float_dtype(*tensors)
    device = tensors[0].device if tensors else None
    return {k: None if v is None else as_float_tensor(v, k, dtype, device) for k, v in named.items()}


def check_matrix(
    x: Tensor, name: str, rows: int | None = None, cols: int | None = None, square: bool = False
) -> None:
    """Check ``x`` is (..., rows, cols); ``square`` requires rows == cols."""
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
    """Check ``x`` is (..., size)."""
    if x.dim() < 1 or x.shape[-1] != size:
        raise ValueError(f"{name} must have shape (..., {size}), got shape {shape_str(x)}")


def check_finite(x: Tensor, name: str) -> None:
    """ValueError if ``x`` holds NaN or ±Inf. Tested on the sum first (non-finite if any entry
    is; one reduction), elementwise only where the sum is not finite (or overflowed)."""
    if not tracing() and not bool(x.sum().isfinite()) and not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains NaN or Inf (shape {shape_str(x)})")


def check_nonnegative(x: Tensor, name: str) -> None:
    check_finite(x, name)
    if not tracing() and bool((x < 0).any()):
        raise ValueError(f"{name} must be non-negative, got min {float(x.min()):.3g} (shape {shape_str(x)})")


def psd_tolerance(x: Tensor) -> float:
    """Relative tolerance for symmetry/PSD checks: a few hundred ulps per dimension."""
    return 100.0 * x.shape[-1] * torch.finfo(x.dtype).eps


#: Up to this many entries in all, the finiteness test sums their concatenation.
_CONCAT_MAX_ENTRIES = 16384
#: Batch size from which 2×2 matrices take the closed-form PSD test (``profile_small_calls.py``
#: section 8, 1 thread: 41 vs 34 µs at 16 matrices, 41 vs 41 at 64, 41 vs 48 at 100, 45 vs 65
#: at 256; 1×1 matrices always take it).
_CLOSED_FORM_MIN_2X2 = 128


def _lapack_dtype(x: Tensor) -> Tensor:
    """x in float32 if it is a half-precision float (LAPACK has no float16/bfloat16 kernels)."""
    return x if x.dtype in (torch.float32, torch.float64) else x.to(torch.float32)


def _psd_test(x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(passes, asym, scale) without synchronising: ``passes`` (0-dim bool) says x is
    symmetric within tol and x + tol·scale·I has a Cholesky factor (⇒ λ_min > −tol·scale up
    to rounding far below tol); asym: relative asymmetry (...); scale: max |x| (...)."""
    scale = x.abs().amax(dim=(-2, -1)).clamp_min(torch.finfo(x.dtype).tiny)
    tol = psd_tolerance(x)
    k = x.shape[-1]
    if k == 1 or (k == 2 and x.numel() >= 4 * _CLOSED_FORM_MIN_2X2):
        # the same test in closed form: the pivots of the shifted Cholesky factor (LAPACK's
        # per-matrix call and the strided x − xᵀ cost 1.11 ms at 1e4 2×2 matrices, the closed
        # form 0.20 ms, 1 thread; its dozen small ops lose below ≈ 100 matrices: section 8)
        shift = tol * scale
        a = x[..., 0, 0] + shift
        if k == 1:
            return (a > 0).all(), torch.zeros_like(scale), scale
        b, c = x[..., 1, 0], x[..., 1, 1] + shift
        asym = (x[..., 0, 1] - b).abs() / scale
        pivot = c - b * (b / a)  # second pivot squared (PSD x: b²/a ≤ c, no overflow)
        return ~((asym > tol) | ~(a > 0) | ~(pivot > 0)).any(), asym, scale
    asym = (x - x.mT).abs().amax(dim=(-2, -1)) / scale
    shifted = x + (tol * scale)[..., None, None] * torch.eye(k, dtype=x.dtype, device=x.device)
    passes = ~((asym > tol) | (torch.linalg.cholesky_ex(_lapack_dtype(shifted)).info != 0)).any()
    return passes, asym, scale


def check_symmetric_psd(x: Tensor, name: str) -> None:
    """Check ``x`` (..., k, k) is symmetric positive semi-definite up to rounding."""
    check_matrix(x, name, square=True)
    check_finite(x, name)
    if tracing() or x.numel() == 0:
        return
    with torch.no_grad():
        passes, asym, scale = _psd_test(x)
        if bool(passes):  # the one synchronisation on the valid path
            return
        if bool((asym > psd_tolerance(x)).any()):
            raise ValueError(
                f"{name} must be symmetric, got relative asymmetry {float(asym.max()):.3g} (shape {shape_str(x)})"
            )
        eig_min = torch.linalg.eigvalsh(_lapack_dtype(sym(x))).amin(dim=-1) / scale
        if bool((eig_min < -psd_tolerance(x)).any()):
            raise ValueError(
                f"{name} must be positive semi-definite, got smallest eigenvalue "
                f"{float(eig_min.min()):.3g} relative to its largest entry (shape {shape_str(x)})"
            )


def broadcast_batch(named: Sequence[tuple[str, Sequence[int]]]) -> torch.Size:
    """Broadcast named batch shapes (numpy rules), naming them all when they do not broadcast."""
    out: list[int] = []
    for _, shape in named:
        shape = tuple(shape)
        if len(shape) > len(out):
            out = [1] * (len(shape) - len(out)) + out
        offset = len(out) - len(shape)
        for i, size in enumerate(shape):
            cur = out[offset + i]
            if size == cur or size == 1:
                continue
            if cur == 1:
                out[offset + i] = size
                continue
            seen = ", ".join(f"{n}: ({', '.join(map(str, s))})" for n, s in named)
            raise ValueError(f"batch shapes do not broadcast: {seen}")
    return torch.Size(out)


def parse_learn(learn: Iterable[str] | str, allowed: Sequence[str]) -> tuple[str, ...]:
    """The names in ``learn`` (one name or several), each checked to be among ``allowed``."""
    names = (learn,) if isinstance(learn, str) else tuple(learn)
    if any(name not in allowed for name in names):
        raise ValueError(f"learn must name some of {tuple(allowed)}, got {names!r}")
    return names


class SDEInputs(NamedTuple):
    """Validated SDE arguments: F (..., n, n), W = L Qc Lᵀ (..., n, n) or None, B (..., n, p)
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
    """Validate and convert SDE arguments (common float dtype, F's device); W = L Qc Lᵀ.

    Raises ValueError naming the argument and the shapes for non-square F, mismatched L,
    Qc, B, and (with ``validate_args``) for non-PSD Qc, NaN/Inf values and negative dt.
    """
    F = as_float_tensor(F, "F")
    dtype = common_float_dtype(
        F,
        L if isinstance(L, Tensor) else None,
        Qc if isinstance(Qc, Tensor) else None,
        B if isinstance(B, Tensor) else None,
    )
    device = F.device
    F = as_float_tensor(F, "F", dtype, device)
    check_matrix(F, "F", square=True)
    n = F.shape[-1]
    if n == 0:
        raise ValueError(f"F must have a state dimension n >= 1, got shape {shape_str(F)}")
    named: list[tuple[str, torch.Size]] = [("F", F.shape[:-2])]
    checked: list[tuple[str, Tensor]] = [("F", F)]  # finiteness, checked together below
    if L is not None or Qc is not None:
        if L is None or Qc is None:
            raise ValueError("L and Qc must be given together")
        L = as_float_tensor(L, "L", dtype, device)
        Qc = as_float_tensor(Qc, "Qc", dtype, device)
        check_matrix(L, "L", rows=n)
        s = L.shape[-1]
        if Qc.dim() < 2 or Qc.shape[-2:] != (s, s):
            raise ValueError(
                f"Qc must have shape (..., {s}, {s}) to match L {shape_str(L)}, got shape {shape_str(Qc)}"
            )
        checked += [("L", L), ("Qc", Qc)]
        named += [("L", L.shape[:-2]), ("Qc", Qc.shape[:-2])]
    if B is not None:
        B = as_float_tensor(B, "B", dtype, device)
        check_matrix(B, "B", rows=n)
        checked.append(("B", B))
        named.append(("B", B.shape[:-2]))
    dt_t = None
    if dt is not None:
        dt_t = as_float_tensor(dt, "dt", dtype, device)
        checked.append(("dt", dt_t))
        named.append(("dt", dt_t.shape))
    batch = broadcast_batch(named)
    if checks_values(validate_args):
        # one synchronisation when everything is valid; otherwise the detailed checks name
        # the culprit (finiteness first, then dt ≥ 0, then Qc symmetric PSD)
        with torch.no_grad():
            # a sum is non-finite if any entry is (NaN propagates, inf − inf = NaN); a finite
            # sum that overflows only sends the check to the detailed path, which passes it.
            # One reduction per tensor: measured 7–20× faster than isfinite(cat(...)).all() at
            # N = 1e4 elements, n = 2 … 8 (profile_small_calls.py section 6); for a few
            # entries one sum of the concatenation saves the per-tensor ops
            if sum(t.numel() for _, t in checked) <= _CONCAT_MAX_ENTRIES:
                ok = torch.cat([t.reshape(-1) for _, t in checked]).sum().isfinite()
            else:
                ok = torch.stack([t.sum() for _, t in checked]).isfinite().all()
            if dt_t is not None and dt_t.numel():
                ok = ok & (dt_t.amin() >= 0)
            if Qc is not None and Qc.numel():
                ok = ok & _psd_test(Qc)[0]
            valid = bool(ok)
        if not valid:
            for name, t in checked:
                check_finite(t, name)
            if dt_t is not None:
                check_nonnegative(dt_t, "dt")
            if Qc is not None:
                check_symmetric_psd(Qc, "Qc")
    W = None
    if L is not None and Qc is not None:
        W = sym(L @ Qc @ L.mT)
    return SDEInputs(F, W, B, dt_t, batch)

