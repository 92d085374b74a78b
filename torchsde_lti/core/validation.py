"""Argument checks: ``ValueError`` (``TypeError`` for non-numeric input) naming the argument
and the shapes. Value checks (finite, signs, PSD) run once, at the public boundary
(``validate_args``); while torch.compile / torch.export trace, only shape checks run.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core.linalg import noise_covariance, sym
from torchsde_lti.core.threads import intra_op_threads, one_thread_backward
from torchsde_lti.core.thresholds import PYTHON_CHECK_MAX_VALUES


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
    """The promoted floating dtype of the given tensors (the default dtype if none is floating)."""
    dtypes = {t.dtype for t in tensors if t is not None and t.is_floating_point()}
    if len(dtypes) == 1:
        return dtypes.pop()
    return functools.reduce(torch.promote_types, dtypes) if dtypes else torch.get_default_dtype()


def as_float_tensors(**named: object) -> dict[str, Tensor | None]:
    """Every non-None argument as a floating tensor of their common dtype
    (:func:`common_float_dtype`), on the device of the first tensor given; None stays None.
    The keyword names are the argument names used in error messages."""
    tensors = [v for v in named.values() if isinstance(v, Tensor)]
    dtype = common_float_dtype(*tensors)
    device = tensors[0].device if tensors else None
    return {k: None if v is None else as_float_tensor(v, k, dtype, device) for k, v in named.items()}


def check_matrix(x: Tensor, name: str, rows: int | None = None, cols: int | None = None, square: bool = False) -> None:
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


def check_no_inf(x: Tensor, name: str) -> None:
    """ValueError if ``x`` holds ±Inf (NaN allowed: a missing observation)."""
    if not tracing() and bool(torch.isinf(x).any()):
        raise ValueError(f"{name} contains Inf (shape {shape_str(x)}); mark missing values with NaN or mask")


def check_nonnegative(x: Tensor, name: str) -> None:
    """ValueError if ``x`` holds NaN, ±Inf or a negative value."""
    check_finite(x, name)
    if not tracing() and bool((x < 0).any()):
        raise ValueError(f"{name} must be non-negative, got min {float(x.min()):.3g} (shape {shape_str(x)})")


def check_hurwitz(F: Tensor, name: str = "F") -> None:
    """ValueError unless every eigenvalue of ``F`` (..., n, n) has a negative real part
    (naming the rightmost one; NaN/Inf in F named as such). One synchronisation; no-op
    while tracing."""
    if tracing() or F.numel() == 0:
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


def _lapack_dtype(x: Tensor) -> Tensor:
    """x in float32 if it is a half-precision float (LAPACK has no float16/bfloat16 kernels)."""
    return x if x.dtype in (torch.float32, torch.float64) else x.to(torch.float32)


def _psd_test(x: Tensor, tol: float | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """(passes, asym, scale) without synchronising: ``passes`` (0-dim bool): x is symmetric
    within tol and x + tol·scale·I has a Cholesky factor; asym (...): relative asymmetry;
    scale (...): max |x|. ``tol``: relative tolerance, :func:`psd_tolerance` by default."""
    scale = x.abs().amax(dim=(-2, -1)).clamp_min(torch.finfo(x.dtype).tiny)
    tol = psd_tolerance(x) if tol is None else tol
    k = x.shape[-1]
    if k <= 2:  # the same test in closed form: the pivots of the shifted Cholesky factor
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


def cholesky_succeeds(m: Sequence[float], k: int, shift: float) -> bool:
    """Whether the row-major k × k matrix ``m`` (its lower triangle) plus ``shift`` I has a
    Cholesky factor: every pivot positive (Python floats; for a few small matrices)."""
    low = [0.0] * (k * k)
    for j in range(k):
        jk = j * k
        for t in range(j):
            tk, v = t * k, m[jk + t]
            for u in range(t):
                v -= low[jk + u] * low[tk + u]
            low[jk + t] = v / low[tk + t]
        d = m[jk + j] + shift
        for u in range(j):
            d -= low[jk + u] * low[jk + u]
        if not d > 0:
            return False
        low[jk + j] = math.sqrt(d)
    return True


def _psd_values(values: Sequence[float], k: int, tol: float) -> bool:
    """:func:`_psd_test`'s decision on row-major k × k matrices given as Python floats."""
    size = k * k
    for start in range(0, len(values), size):
        m = values[start : start + size]
        limit = tol * max(max(m), -min(m), 1e-300)
        for i in range(1, k):
            for j in range(i):
                if abs(m[i * k + j] - m[j * k + i]) > limit:
                    return False
        if not cholesky_succeeds(m, k, limit):
            return False
    return True


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


def broadcast_shapes(*shapes: Sequence[int]) -> torch.Size:
    """Broadcast shapes (numpy rules); ValueError when they do not broadcast. Plain Python on
    ints (``torch.broadcast_shapes`` costs tens of µs a call eagerly); torch's own while tracing
    (symbolic sizes)."""
    if tracing():
        try:
            return torch.broadcast_shapes(*shapes)
        except RuntimeError:
            raise ValueError(f"shapes {[tuple(s) for s in shapes]} do not broadcast") from None
    out = [1] * max(map(len, shapes), default=0)
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


def host_values(tensors: Sequence[Tensor]) -> list[list[float]]:
    """The values of ``tensors`` (row-major Python floats, one list per tensor), read to the host
    in one transfer (for the value checks of small calls)."""
    with torch.no_grad():
        parts = [t.reshape(-1) for t in tensors]
        flat: list[float] = (torch.cat(parts) if len(parts) > 1 else parts[0]).tolist() if parts else []
    out, offset = [], 0
    for part in parts:
        out.append(flat[offset : offset + part.numel()])
        offset += part.numel()
    return out


def _values_valid(host: dict[str, list[float]], Qc: Tensor | None) -> bool:
    """The value checks of :func:`sde_inputs` on Python floats: all finite, dt ≥ 0, Qc
    symmetric PSD (the test of :func:`_psd_test`)."""
    if not all(math.isfinite(sum(part)) for part in host.values()):  # (an overflowing sum: the detailed checks)
        return False
    if host.get("dt") and min(host["dt"]) < 0:
        return False
    return Qc is None or not host["Qc"] or _psd_values(host["Qc"], Qc.shape[-1], psd_tolerance(Qc))


def _reductions_valid(checked: Sequence[Tensor], dt: Tensor | None, Qc: Tensor | None) -> bool:
    """A sufficient test for the value checks of :func:`sde_inputs` from a few reductions read in
    one transfer: every sum of ``checked`` finite (a sum is non-finite if any entry is), min dt ≥ 0,
    max |Qc − Qcᵀ| ≤ tol · min_i max |Qc_i| and a Cholesky factor of every Qc (positive definite,
    so :func:`_psd_test` passes). False (NaN/Inf, a negative dt, an asymmetric or semi-definite
    Qc, an overflowing sum) leaves the decision to the detailed checks."""
    parts = [t.sum() for t in checked]
    if dt is not None and dt.numel():
        parts.append(dt.amin())
    if Qc is not None and Qc.numel():
        asym, scale = (Qc - Qc.mT).abs().amax(), Qc.abs().amax((-2, -1)).amin()
        info = torch.linalg.cholesky_ex(_lapack_dtype(Qc)).info.amax().to(Qc.dtype)
        *v, asym_v, scale_v, info_v = torch.stack([*parts, asym, scale, info]).tolist()
        if not (asym_v <= psd_tolerance(Qc) * scale_v and info_v == 0):
            return False
    else:
        v = torch.stack(parts).tolist()
    return all(math.isfinite(x) for x in v) and (dt is None or not dt.numel() or v[-1] >= 0)


class SDEInputs(NamedTuple):
    """Validated SDE arguments: F (..., n, n), W = L Qc Lᵀ (..., n, n) or None, B (..., n, p)
    or None, dt (...) or None, and the broadcast batch shape of all of them.

    ``host``: for a small call (at most :data:`PYTHON_CHECK_MAX_VALUES` values, not traced)
    the values of F, L, Qc, B and dt (row-major Python floats, read in the call's one
    transfer) by name; None otherwise. Replace it (``_replace``) when a field changes.
    ``finish``: to be applied to the call's results (its backward then runs with the
    threads of :func:`~torchsde_lti.core.threads.one_thread_backward`)."""

    F: Tensor
    W: Tensor | None
    B: Tensor | None
    dt: Tensor | None
    batch: torch.Size
    host: dict[str, list[float]] | None = None
    finish: Callable[..., tuple[Tensor | None, ...]] = lambda *results: results

    @property
    def work(self) -> int:
        """Matrix entries the call produces, N n (n + p): the size that sets its threads."""
        return _entries(self.batch, self.F.shape[-1], self.B)


def _entries(batch: Sequence[int], n: int, B: Tensor | None) -> int:
    """N n (n + p) for a batch of N = prod(batch) elements (symbolic-safe)."""
    return math.prod(batch) * n * (n + (0 if B is None else B.shape[-1]))


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
    if F.dtype != dtype:
        F = F.to(dtype)
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
            raise ValueError(f"Qc must have shape (..., {s}, {s}) to match L {shape_str(L)}, got shape {shape_str(Qc)}")
        checked += [("L", L), ("Qc", Qc)]
        named += [("L", L.shape[:-2]), ("Qc", Qc.shape[:-2])]
    if B is not None:
        B = as_float_tensor(B, "B", dtype, device)
        check_matrix(B, "B", rows=n)
        if B.shape[-1] == 0:
            raise ValueError(f"B must have at least one column (no inputs: pass B=None), got shape {shape_str(B)}")
        checked.append(("B", B))
        named.append(("B", B.shape[:-2]))
    dt_t = None
    if dt is not None:
        dt_t = as_float_tensor(dt, "dt", dtype, device)
        checked.append(("dt", dt_t))
        named.append(("dt", dt_t.shape))
    batch = broadcast_batch(named)
    work = _entries(batch, n, B)
    (F_out, L, Qc, B, dt_t), finish = one_thread_backward(work, (F, L, Qc, B, dt_t))  # (the checks: same values)
    assert F_out is not None
    F = F_out
    W = None
    if L is not None and Qc is not None:
        with intra_op_threads(work):
            W = noise_covariance(L, Qc)
    values = checks_values(validate_args)
    total = sum(t.numel() for _, t in checked)
    host: dict[str, list[float]] | None = None
    if not tracing() and total <= PYTHON_CHECK_MAX_VALUES:  # one transfer: checks and decisions on Python floats
        host = dict(zip((name for name, _ in checked), host_values([t for _, t in checked])))
        valid = not values or _values_valid(host, Qc)
    elif values:
        with torch.no_grad(), intra_op_threads(total):
            valid = _reductions_valid([t for _, t in checked], dt_t, Qc)
    else:
        valid = True
    if not valid:  # the detailed checks name the culprit: finiteness, then dt ≥ 0, then Qc PSD
        for name, t in checked:
            check_finite(t, name)
        if dt_t is not None:
            check_nonnegative(dt_t, "dt")
        if Qc is not None:
            check_symmetric_psd(Qc, "Qc")
    return SDEInputs(F, W, B, dt_t, batch, host, finish)
