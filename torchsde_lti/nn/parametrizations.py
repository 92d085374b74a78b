"""Constraint parametrisations for :mod:`torch.nn.utils.parametrize`.

Each class is an ``nn.Module`` with ``forward(raw) -> value`` and ``right_inverse(value) -> raw``,
so that after ``parametrize.register_parametrization(module, "Qc", PositiveDefinite())``
reading ``module.Qc`` returns a constrained value and ``module.Qc = X`` stores a raw
preimage of ``X``. Whatever real numbers the optimiser writes into the raw tensor, the
value satisfies the constraint:

=====================  ==========================================  =======================
class                  value                                       raw tensor
=====================  ==========================================  =======================
``Positive``           ``softplus(x) + floor`` (elementwise)       same shape as value
``PositiveDefinite``   ``C Cᵀ``, C lower-triangular,               (..., n, n); strict lower
                       ``diag C = softplus(diag x) + floor``       triangle + diagonal used
``Hurwitz``            ``F = (J − R) P⁻¹``, J skew, R, P ≻ 0       (..., 3, n, n)
``IntegratorChain``    ``[[0, I], [0, F_v]]`` per axis, F_v free   (..., d, d) or
                       or Hurwitz                                  (..., 3, d, d)
=====================  ==========================================  =======================

The floor (default ``torch.finfo(dtype).eps`` of the raw tensor, so float32 and float64
each get their own) only keeps values strictly positive when ``softplus`` underflows to
zero; ``right_inverse`` subtracts it again, so set-then-get round-trips to rounding.
Parametrisation modules carry a zero-size, non-persistent buffer that follows
``module.to(...)`` so that ``right_inverse`` can cast assigned values (Python floats,
arrays, tensors of another dtype) to the dtype and device of the raw tensor.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor, nn

from torchsde_lti.core.validation import as_float_tensor, check_finite, check_matrix, shape_str

__all__ = [
    "Hurwitz",
    "IntegratorChain",
    "Positive",
    "PositiveDefinite",
    "default_floor",
    "integrator_chain",
    "softplus",
    "softplus_inverse",
]


def default_floor(dtype: torch.dtype) -> float:
    """Dtype-aware lower bound added after ``softplus``: machine epsilon of ``dtype``."""
    return float(torch.finfo(dtype).eps)


def softplus(x: Tensor) -> Tensor:
    """``log(1 + exp(x))`` evaluated without overflow and without a linear threshold.

    Unlike ``torch.nn.functional.softplus`` (which returns ``x`` above ``threshold=20``)
    this is the exact function everywhere, so :func:`softplus_inverse` round-trips.
    """
    return x.clamp_min(0) + torch.log1p(torch.exp(-x.abs()))


def softplus_inverse(y: Tensor) -> Tensor:
    """Inverse of :func:`softplus` for ``y > 0``: ``y + log(-expm1(-y))`` (stable for all y > 0)."""
    return y + torch.log(-torch.expm1(-y))


class _Parametrization(nn.Module):
    """Base: remembers dtype/device of the raw tensor through a zero-size buffer."""

    def __init__(self, floor: float | None = None, size: int | None = None) -> None:
        super().__init__()
        if floor is not None and not floor > 0:
            raise ValueError(f"floor must be positive or None, got {floor!r}")
        if size is not None and (isinstance(size, bool) or not isinstance(size, int) or size < 1):
            raise ValueError(f"size must be a positive integer or None, got {size!r}")
        self.floor = floor
        self.size = size
        self.register_buffer("_ref", torch.empty(0), persistent=False)

    def _check_size(self, value: Tensor, name: str) -> None:
        """A square (..., k, k) value, with k = ``size`` when given.

        :mod:`torch.nn.utils.parametrize` stores whatever ``right_inverse`` returns, even
        with a new shape, so a wrong-sized assignment must fail here or it corrupts the module.
        """
        check_matrix(value, name, rows=self.size, cols=self.size, square=True)

    def _floor(self, dtype: torch.dtype) -> float:
        return default_floor(dtype) if self.floor is None else float(self.floor)

    def _as_raw_tensor(self, value: object, name: str) -> Tensor:
        """Cast an assigned value to the raw tensor's dtype and device."""
        if isinstance(value, torch.Tensor):
            x = as_float_tensor(value, name).detach()
        else:  # convert Python numbers / arrays straight to the raw dtype (no float32 detour)
            x = as_float_tensor(value, name, self._ref.dtype)
        return x.to(dtype=self._ref.dtype, device=self._ref.device)

    def extra_repr(self) -> str:
        parts = [] if self.size is None else [f"size={self.size}"]
        if self.floor is not None:
            parts.append(f"floor={self.floor}")
        return ", ".join(parts)


class Positive(_Parametrization):
    """Elementwise positive values: ``value = softplus(raw) + floor`` (any shape).

    ``right_inverse`` raises ``ValueError`` for non-positive or non-finite values; values
    at or below the floor map to the smallest representable value (the floor itself).
    """

    def __init__(self, floor: float | None = None, name: str = "value") -> None:
        super().__init__(floor)
        self.name = name

    def forward(self, raw: Tensor) -> Tensor:
        return softplus(raw) + self._floor(raw.dtype)

    def right_inverse(self, value: object) -> Tensor:
        v = self._as_raw_tensor(value, self.name)
        check_finite(v, self.name)
        if bool((v <= 0).any()):
            raise ValueError(
                f"{self.name} must be positive, got min {float(v.min()):.3g} (shape {shape_str(v)})"
            )
        floor = self._floor(v.dtype)
        return softplus_inverse((v - floor).clamp_min(torch.finfo(v.dtype).tiny))


def _cholesky_factor(raw: Tensor, floor: float) -> Tensor:
    """Lower-triangular factor with strictly positive diagonal from an unconstrained (..., n, n)."""
    diag = softplus(torch.diagonal(raw, dim1=-2, dim2=-1)) + floor
    return torch.tril(raw, -1) + torch.diag_embed(diag)


def _cholesky_raw(value: Tensor, floor: float, name: str) -> Tensor:
    """Raw preimage of a symmetric positive-definite (..., n, n) under :func:`_cholesky_factor` C Cᵀ."""
    check_matrix(value, name, square=True)
    check_finite(value, name)
    scale = value.abs().amax(dim=(-2, -1), keepdim=True).clamp_min(torch.finfo(value.dtype).tiny)
    tol = 100.0 * value.shape[-1] * torch.finfo(value.dtype).eps
    if bool(((value - value.mT).abs() / scale > tol).any()):
        raise ValueError(f"{name} must be symmetric (shape {shape_str(value)})")
    chol, info = torch.linalg.cholesky_ex(0.5 * (value + value.mT))
    if bool((info != 0).any()):
        raise ValueError(
            f"{name} must be symmetric positive definite (Cholesky failed; shape {shape_str(value)})"
        )
    diag = torch.diagonal(chol, dim1=-2, dim2=-1)
    raw_diag = softplus_inverse((diag - floor).clamp_min(torch.finfo(value.dtype).tiny))
    return torch.tril(chol, -1) + torch.diag_embed(raw_diag)


class PositiveDefinite(_Parametrization):
    """Symmetric positive-definite matrices ``value = C Cᵀ`` (..., n, n).

    ``C = tril(raw, -1) + diag(softplus(diag raw) + floor)`` is a Cholesky factor with a
    strictly positive diagonal, so ``value`` is symmetric positive definite for every real
    ``raw`` (the upper triangle of ``raw`` is unused). The result is symmetrised.
    ``right_inverse`` takes the Cholesky factor of the value (ValueError if the value is
    not symmetric positive definite, or not (..., size, size) when ``size`` is given).
    """

    def __init__(self, floor: float | None = None, name: str = "value", size: int | None = None) -> None:
        super().__init__(floor, size)
        self.name = name

    def factor(self, raw: Tensor) -> Tensor:
        """The lower Cholesky factor C (..., n, n) of the value."""
        return _cholesky_factor(raw, self._floor(raw.dtype))

    def forward(self, raw: Tensor) -> Tensor:
        c = self.factor(raw)
        value = c @ c.mT
        return 0.5 * (value + value.mT)

    def right_inverse(self, value: object) -> Tensor:
        v = self._as_raw_tensor(value, self.name)
        self._check_size(v, self.name)
        return _cholesky_raw(v, self._floor(v.dtype), self.name)


def _lyapunov_identity(F: Tensor) -> Tensor:
    """P ≻ 0 solving F P + P Fᵀ + 2 I = 0 (ValueError if F is not Hurwitz)."""
    from torchsde_lti.core.stationary import stationary_covariance

    n = F.shape[-1]
    eye = torch.eye(n, dtype=F.dtype, device=F.device)
    return stationary_covariance(F, eye, 2.0 * eye)


class Hurwitz(_Parametrization):
    """Hurwitz-stable matrices (every eigenvalue strictly in the open left half-plane).

    ``F = (J − R) P⁻¹`` with J skew-symmetric, R and P symmetric positive definite,
    all three built from one raw tensor (..., 3, n, n):

    - ``raw[..., 0, :, :]``: its strict upper triangle U gives ``J = U − Uᵀ``;
    - ``raw[..., 1, :, :]``: Cholesky raw of R (see :class:`PositiveDefinite`);
    - ``raw[..., 2, :, :]``: Cholesky raw of P; ``F`` is formed with ``cholesky_solve``.

    Why every such F is Hurwitz: ``F P + P Fᵀ = (J − R) + (J − R)ᵀ = −2R ≺ 0`` with
    ``P ≻ 0``. For an eigenpair ``Fᵀ v = λ v``,
    ``vᴴ(F P + P Fᵀ)v = 2 Re(λ) vᴴ P v < 0``, hence ``Re λ < 0`` (Lyapunov).

    Why every Hurwitz F is reached (the parametrisation is onto the Hurwitz set): for
    Hurwitz F the Lyapunov equation ``F P + P Fᵀ = −2I`` has the solution
    ``P = 2∫₀^∞ e^{Ft} e^{Fᵀt} dt ≻ 0``. Put ``M = F P``; then ``M + Mᵀ = −2I``, so
    ``R := −(M + Mᵀ)/2 = I ≻ 0`` and ``J := (M − Mᵀ)/2`` is skew, and
    ``(J − R) P⁻¹ = M P⁻¹ = F``. ``right_inverse`` computes exactly this preimage (with
    ``tl.stationary_covariance(F, I, 2I)``), so it raises ``ValueError`` for non-Hurwitz F.
    The only matrices not reached are those whose preimage needs a Cholesky diagonal
    below the floor (condition numbers beyond ~1/eps). With ``size`` given,
    ``right_inverse`` also rejects values that are not (..., size, size).
    """

    def __init__(self, floor: float | None = None, name: str = "F", size: int | None = None) -> None:
        super().__init__(floor, size)
        self.name = name

    def components(self, raw: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(J, R, chol(P))`` from the raw (..., 3, n, n) tensor."""
        if raw.dim() < 3 or raw.shape[-3] != 3:
            raise ValueError(f"Hurwitz raw tensor must have shape (..., 3, n, n), got {shape_str(raw)}")
        floor = self._floor(raw.dtype)
        upper = torch.triu(raw[..., 0, :, :], 1)
        skew = upper - upper.mT
        c_r = _cholesky_factor(raw[..., 1, :, :], floor)
        r = c_r @ c_r.mT
        r = 0.5 * (r + r.mT)
        c_p = _cholesky_factor(raw[..., 2, :, :], floor)
        return skew, r, c_p

    def forward(self, raw: Tensor) -> Tensor:
        skew, r, c_p = self.components(raw)
        m = skew - r
        # F = M P⁻¹  <=>  Fᵀ = P⁻¹ Mᵀ (P symmetric), solved with the Cholesky factor of P.
        return torch.cholesky_solve(m.mT, c_p).mT

    def right_inverse(self, value: object) -> Tensor:
        f = self._as_raw_tensor(value, self.name)
        self._check_size(f, self.name)
        check_finite(f, self.name)
        p = _lyapunov_identity(f)
        p = 0.5 * (p + p.mT)
        m = f @ p
        r = -0.5 * (m + m.mT)
        skew = 0.5 * (m - m.mT)
        floor = self._floor(f.dtype)
        raw_r = _cholesky_raw(r, floor, f"{self.name} (dissipative part R)")
        raw_p = _cholesky_raw(p, floor, f"{self.name} (Lyapunov solution P)")
        return torch.stack((torch.triu(skew, 1), raw_r, raw_p), dim=-3)


DragConstraint = Literal["free", "hurwitz"]


def integrator_chain(
    order: int, dim: int, dtype: torch.dtype | None = None, device: torch.device | str | None = None
) -> tuple[Tensor, Tensor]:
    """Fixed part of ``dim`` integrator chains of ``order`` states each, per-axis ordering.

    Returns ``chain`` (n, n), n = order·dim, with a one from derivative k+1 to derivative k
    of the same axis, and ``selector`` E (n, dim) with a one at each axis' highest
    derivative (so ``E F_v Eᵀ`` places a (dim, dim) drag block, and E is the noise gain L).
    """
    n = order * dim
    chain = torch.zeros(n, n, dtype=dtype, device=device)
    selector = torch.zeros(n, dim, dtype=dtype, device=device)
    for axis in range(dim):
        base = axis * order
        for k in range(order - 1):
            chain[base + k, base + k + 1] = 1.0
        selector[base + order - 1, axis] = 1.0
    return chain, selector


class IntegratorChain(_Parametrization):
    """Integrator chains per axis with a learned drag block on the highest derivative.

    State ordering per axis: ``[x, x', …, x^(order−1), y, y', …]`` (``dim`` axes, n =
    order·dim). The fixed part has ones from derivative k+1 to derivative k of the same
    axis (exact integrator chains); the only learned entries form the (dim, dim) drag block
    ``F_v`` acting on the highest derivatives of all axes:
    ``d/dt x^(order−1) = F_v x^(order−1) (+ noise)``. In block form (derivative-major
    ordering) this is ``[[0, I], [0, F_v]]``.

    ``drag="free"``: ``F_v = raw`` (raw (..., dim, dim)).
    ``drag="hurwitz"``: ``F_v`` through :class:`Hurwitz` (raw (..., 3, dim, dim)), so the
    drag block is stable whatever the optimiser does (the integrators keep their zero
    eigenvalues: the full F is deliberately not Hurwitz).

    ``right_inverse`` raises ``ValueError`` when the value is not of this structure.
    """

    def __init__(self, order: int, dim: int, drag: DragConstraint = "free", floor: float | None = None) -> None:
        super().__init__(floor)
        if not isinstance(order, int) or order < 1:
            raise ValueError(f"order must be an integer >= 1, got {order!r}")
        if not isinstance(dim, int) or dim < 1:
            raise ValueError(f"dim must be an integer >= 1, got {dim!r}")
        if drag not in ("free", "hurwitz"):
            raise ValueError(f"drag must be 'free' or 'hurwitz', got {drag!r}")
        self.order = order
        self.dim = dim
        self.drag = drag
        self.inner = Hurwitz(floor=floor, name="F_v") if drag == "hurwitz" else None

    @property
    def state_dim(self) -> int:
        return self.order * self.dim

    def _chain_and_selector(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """Fixed chain matrix (n, n) and selector E (n, dim) of the highest derivatives."""
        return integrator_chain(self.order, self.dim, like.dtype, like.device)

    def drag_block(self, raw: Tensor) -> Tensor:
        """The drag block F_v (..., dim, dim)."""
        return self.inner(raw) if self.inner is not None else raw

    def forward(self, raw: Tensor) -> Tensor:
        f_v = self.drag_block(raw)
        chain, sel = self._chain_and_selector(f_v)
        return chain + sel @ f_v @ sel.mT

    def right_inverse(self, value: object) -> Tensor:
        f = self._as_raw_tensor(value, "F")
        n = self.state_dim
        check_matrix(f, "F", rows=n, cols=n)
        chain, sel = self._chain_and_selector(f)
        f_v = sel.mT @ f @ sel
        rest = f - sel @ f_v @ sel.mT
        if not torch.equal(rest, chain.expand_as(rest)):
            raise ValueError(
                f"F is not an integrator chain of order {self.order} over {self.dim} axes "
                f"(per-axis ordering) with a drag block on the highest derivative (shape {shape_str(f)})"
            )
        if self.inner is not None:
            return self.inner.right_inverse(f_v)
        return f_v

    def extra_repr(self) -> str:
        return f"order={self.order}, dim={self.dim}, drag={self.drag!r}"


class Unconstrained(_Parametrization):
    """Identity parametrisation: ``value = raw``.

    Registered on unconstrained matrices so that ``sde.L = X`` works for Parameters and
    buffers alike (in place, casting X to the raw dtype/device, checking its shape).
    """

    def __init__(self, name: str = "value", shape_tail: tuple[int, int] | None = None) -> None:
        super().__init__()
        self.name = name
        self.shape_tail = shape_tail

    def forward(self, raw: Tensor) -> Tensor:
        return raw

    def right_inverse(self, value: object) -> Tensor:
        x = self._as_raw_tensor(value, self.name)
        if self.shape_tail is not None:
            check_matrix(x, self.name, rows=self.shape_tail[0], cols=self.shape_tail[1])
        check_finite(x, self.name)
        return x.clone()
