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
``Hurwitz``            ``F = (J − R) S``, J skew, R, S ⪰ δ I       (..., 3, n, n)
``IntegratorChain``    ``[[0, I], [0, F_v]]`` per axis, F_v free   (..., d, d) or
                       or Hurwitz                                  (..., 3, d, d)
``Generator``          Markov generator Λ: ``softplus(x) + floor``  (..., M, M); diagonal
                       off the diagonal, rows summing to 0         unused
``ModeProbabilities``  ``softmax(x)`` (probability vectors)        (..., M)
=====================  ==========================================  =======================

No forward map inverts, solves with, or exponentiates an unbounded quantity: values are
polynomial in the raw entries and ``softplus`` (whose ``exp`` only sees ``−|x|``), and the
polynomial maps (``PositiveDefinite``, ``Hurwitz``) take raw entries beyond a bound
(``finfo.max`` to the power 1/4 or 1/8) logarithmically, so values are finite for every
finite raw tensor.

The floor δ of ``Positive``/``PositiveDefinite``/``Generator`` only keeps values strictly
positive when ``softplus`` underflows to zero; ``right_inverse`` subtracts it again, so
set-then-get round-trips to rounding. δ is part of the map raw -> value, so it does not follow
the dtype: by default (``floor=None``) δ = ``torch.finfo(dtype).eps`` of the first tensor the
parametrisation sees (the value ``register_parametrization`` passes to ``right_inverse``, or the
raw tensor of a first ``forward``), fixed from then on, so ``module.double()`` / ``.float()``
keep every value to the rounding of the new dtype. δ is saved in the module's ``state_dict``
(the parametrisation's ``_extra_state``, a 0-dim float64 tensor: :func:`floor_state_keys`) and
restored by ``load_state_dict``, so a checkpoint saved in one dtype gives its values in a model
of another. A state dict without it (saved before δ was saved) loads, also with
``strict=True``, with δ the eps of the model's dtype, the floor it was read with before. An
explicit ``floor`` is used as given. A module built in float32 keeps float32's δ (values
>= 1.2e-7) in float64; :func:`reset_default_floors` gives it float64's. :class:`Hurwitz` uses
a relative floor instead (see there).
Parametrisation modules carry a zero-size, non-persistent buffer that follows
``module.to(...)`` so that ``right_inverse`` can cast assigned values (Python floats,
arrays, tensors of another dtype) to the dtype and device of the raw tensor.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from torchsde_lti.core.linalg import sym
from torchsde_lti.core.validation import check_finite, check_matrix, shape_str
from torchsde_lti.nn._parametrization_base import (
    FlooredParametrization,
    Parametrization,
    default_floor,
    floor_state_keys,
    reset_default_floors,
    softplus,
    softplus_inverse,
)

__all__ = [
    "Generator",
    "Hurwitz",
    "IntegratorChain",
    "ModeProbabilities",
    "Positive",
    "PositiveDefinite",
    "default_floor",
    "floor_state_keys",
    "generator_from_rates",
    "hurwitz_floor",
    "integrator_chain",
    "reset_default_floors",
    "softplus",
    "softplus_inverse",
]


class Positive(FlooredParametrization):
    """Elementwise positive values: ``value = softplus(raw) + floor`` (any shape).

    ``floor`` δ > 0: by default the eps of the dtype of the first tensor the parametrisation
    sees, then fixed whatever the dtype and saved in ``state_dict`` (module docstring).
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
            raise ValueError(f"{self.name} must be positive, got min {float(v.min()):.3g} (shape {shape_str(v)})")
        floor = self._floor(v.dtype)
        return softplus_inverse((v - floor).clamp_min(torch.finfo(v.dtype).tiny))


def _saturation_bound(dtype: torch.dtype, degree: int) -> float:
    """``finfo(dtype).max ** (1 / (2 degree))``: raw entries beyond it enter a map of that
    polynomial degree logarithmically (:func:`_saturated`), so its values stay finite."""
    return float(torch.finfo(dtype).max) ** (1.0 / (2 * degree))


def _saturated(x: Tensor, bound: float) -> Tensor:
    """x where ``|x| <= bound``, else ``sign(x) bound (1 + log(|x| / bound))`` (continuous with its
    first derivative; at most ``bound (1 + log(max / bound))``)."""
    big = x.abs() > bound
    tail = torch.sign(x) * bound * (1.0 + torch.log(torch.where(big, x.abs(), bound) / bound))
    return torch.where(big, tail, x)


def _unsaturated(v: Tensor, bound: float, name: str) -> Tensor:
    """The preimage of :func:`_saturated` (for ``right_inverse``); ValueError where ``v`` is
    beyond its range."""
    big = v.abs() > bound
    x = torch.where(big, torch.sign(v) * bound * torch.exp(torch.where(big, v.abs(), bound) / bound - 1.0), v)
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} is too large for the parametrisation in {v.dtype} (shape {shape_str(v)})")
    return x


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
    chol, info = torch.linalg.cholesky_ex(sym(value))
    if bool((info != 0).any()):
        raise ValueError(f"{name} must be symmetric positive definite (Cholesky failed; shape {shape_str(value)})")
    diag = torch.diagonal(chol, dim1=-2, dim2=-1)
    raw_diag = softplus_inverse((diag - floor).clamp_min(torch.finfo(value.dtype).tiny))
    return torch.tril(chol, -1) + torch.diag_embed(raw_diag)


class PositiveDefinite(FlooredParametrization):
    """Symmetric positive-definite matrices ``value = C Cᵀ`` (..., n, n).

    ``C = tril(x, -1) + diag(softplus(diag x) + floor)``, x the raw entries (beyond
    ``finfo(dtype).max ** (1/4)`` entering logarithmically, so the value is finite for
    every finite raw tensor), is a Cholesky factor with a strictly positive diagonal, so
    ``value`` is symmetric positive definite for every real ``raw`` (the upper triangle of
    ``raw`` is unused). Formed in floating point it is numerically singular where its
    condition number passes ~1/eps (pivots of C far below their rows' entries); a filter then
    says so (R nearly singular). The result is symmetrised. The floor is fixed and saved as
    :class:`Positive`'s. ``right_inverse`` takes the Cholesky factor of the value (ValueError
    if the value is not symmetric positive definite, or not (..., size, size) when ``size`` is
    given).
    """

    def __init__(self, floor: float | None = None, name: str = "value", size: int | None = None) -> None:
        super().__init__(floor, size)
        self.name = name

    def factor(self, raw: Tensor) -> Tensor:
        """The lower Cholesky factor C (..., n, n) of the value."""
        return _cholesky_factor(_saturated(raw, _saturation_bound(raw.dtype, 2)), self._floor(raw.dtype))

    def forward(self, raw: Tensor) -> Tensor:
        c = self.factor(raw)
        return sym(c @ c.mT)

    def right_inverse(self, value: object) -> Tensor:
        v = self._as_raw_tensor(value, self.name)
        self._check_size(v, self.name)
        raw = _cholesky_raw(v, self._floor(v.dtype), self.name)
        return _unsaturated(raw, _saturation_bound(v.dtype, 2), self.name)


def _lyapunov_identity(F: Tensor) -> Tensor:
    """P ≻ 0 solving F P + P Fᵀ + 2 I = 0 (ValueError if F is not Hurwitz)."""
    from torchsde_lti.core.stationary import stationary_covariance

    n = F.shape[-1]
    eye = torch.eye(n, dtype=F.dtype, device=F.device)
    return stationary_covariance(F, eye, 2.0 * eye)


HURWITZ_FLOOR = 1e-3


def hurwitz_floor(dtype: torch.dtype) -> float:
    """Default relative floor δ of :class:`Hurwitz`: ``HURWITZ_FLOOR`` (1e-3) for every dtype.

    The floor is a property of the map raw -> F, so it must not change with the raw dtype:
    ``module.to(torch.float32)`` keeps F (to rounding). 1e-3 guarantees a relative stability
    margin ``δ² = 1e-6`` (≈ 8 float32 eps, so rounding F to float32 cannot cross the
    imaginary axis at moderate eigenvector conditioning) and reaches every F whose time
    scales lie within ~1e3 of each other. ``dtype`` must be a floating dtype.
    """
    torch.finfo(dtype)  # TypeError for non-floating dtypes
    return HURWITZ_FLOOR


def _frobenius_sq(x: Tensor) -> Tensor:
    """``‖X‖_F²`` over the last two dims, kept as (..., 1, 1) to scale an identity."""
    return (x * x).sum(dim=(-2, -1), keepdim=True)


class Hurwitz(Parametrization):
    """Hurwitz-stable matrices (every eigenvalue strictly in the open left half-plane).

    ``F = (J − R) S`` with J skew-symmetric and R, S symmetric positive definite, all three
    from one raw tensor (..., 3, n, n):

    - ``raw[..., 0, :, :]``: its strict upper triangle U gives ``J = U − Uᵀ``;
    - ``raw[..., 1, :, :]``: ``R = C_R C_Rᵀ + δ (‖C_R‖_F² + sqrt(1 + ‖J‖_F²)) I``;
    - ``raw[..., 2, :, :]``: ``S = C_S C_Sᵀ + δ (‖C_S‖_F² + 1) I``;

    where ``C = tril(raw, −1) + diag(softplus(diag raw))`` is a Cholesky-type factor and δ
    the floor (default :func:`hurwitz_floor`, 1e-3 whatever the dtype). The forward
    map is polynomial in ``U``, ``C_R``, ``C_S`` (up to the smooth ``sqrt(1 + ·)``; softplus is
    bounded by ``|x| + log 2``): no inverse, no solve, no exponential of an unbounded
    quantity, so F is finite for any finite raw tensor.

    The floors are relative (``‖C C ᵀ‖₂ ≤ ‖C‖_F²``): ``λ_min(R) ≥ δ (‖C_R C_Rᵀ‖ + ‖J‖)``
    and ``λ_min(S) ≥ δ ‖C_S C_Sᵀ‖``, so the conditioning of R and S and the size of J
    relative to R stay bounded whatever an optimiser writes into the raw tensor, and the
    stability margin scales with F: ``Re λ ≤ −λ_min(R) λ_min(S) ≈ −δ² ‖J − R‖ ‖S‖``. An
    absolute floor would not do: one large SGD step can leave R and S with λ_min/λ_max
    ~ 1e-10, a Hurwitz F that is indistinguishable from an unstable one after rounding.

    Why every such F is Hurwitz: ``F S⁻¹ + S⁻¹ Fᵀ = (J − R) + (J − R)ᵀ = −2R ≺ 0`` with
    ``S⁻¹ ≻ 0``. For an eigenpair ``Fᵀ v = λ v``: ``2 Re(λ) vᴴ S⁻¹ v = −2 vᴴ R v``, so
    ``Re λ = −vᴴRv / vᴴS⁻¹v ≤ −λ_min(R) λ_min(S) < 0``.

    Which F are reached: for Hurwitz F the Lyapunov equation ``F P + P Fᵀ = −2I`` has
    ``P = 2∫₀^∞ e^{Ft} e^{Fᵀt} dt ≻ 0``. With ``M = F P``, ``M + Mᵀ = −2I``, so
    ``(J, R, S) = (r (M − Mᵀ)/2, r I, P⁻¹ / r)`` gives ``(J − R) S = F`` for any ``r > 0``.
    ``right_inverse`` computes this preimage (P by ``tl.stationary_covariance(F, I, 2I)``,
    ``P⁻¹`` by a Cholesky inverse — the only inverse, and it is not in ``forward``) with
    r the geometric mean of the interval where both floors hold (closed form: the floors
    are ``c = δ (tr S + 1) / (1 + n δ)`` for S, likewise for R), so R, S and J start at
    comparable sizes (a well-scaled start). It
    raises ``ValueError`` for non-Hurwitz F and for F this preimage cannot reach:
    roughly, ``cond(P) ≳ 1/δ`` or ``‖(M − Mᵀ)/2‖ ≳ 1/δ`` (time scales more than ~1/δ apart,
    or rotation much faster than damping), or eigenvalues below ``δ²`` in magnitude; pass a
    smaller ``floor`` to reach those. With ``size`` given, ``right_inverse`` also rejects
    values that are not (..., size, size).
    """

    def __init__(self, floor: float | None = None, name: str = "F", size: int | None = None) -> None:
        super().__init__(floor, size)
        self.name = name

    def _floor(self, dtype: torch.dtype) -> float:
        return hurwitz_floor(dtype) if self.floor is None else float(self.floor)

    def components(self, raw: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(J, R, S)`` (each (..., n, n)) from the raw (..., 3, n, n) tensor."""
        if raw.dim() < 3 or raw.shape[-3] != 3:
            raise ValueError(f"Hurwitz raw tensor must have shape (..., 3, n, n), got {shape_str(raw)}")
        delta = self._floor(raw.dtype)
        raw = _saturated(raw, _saturation_bound(raw.dtype, 4))
        eye = torch.eye(raw.shape[-1], dtype=raw.dtype, device=raw.device)
        upper = torch.triu(raw[..., 0, :, :], 1)
        skew = upper - upper.mT
        c_r = _cholesky_factor(raw[..., 1, :, :], 0.0)
        c_s = _cholesky_factor(raw[..., 2, :, :], 0.0)
        shift_r = delta * (_frobenius_sq(c_r) + torch.sqrt(1.0 + _frobenius_sq(skew)))
        shift_s = delta * (_frobenius_sq(c_s) + 1.0)
        return skew, sym(c_r @ c_r.mT) + shift_r * eye, sym(c_s @ c_s.mT) + shift_s * eye

    def forward(self, raw: Tensor) -> Tensor:
        skew, r, s = self.components(raw)
        return (skew - r) @ s

    def right_inverse(self, value: object) -> Tensor:
        f = self._as_raw_tensor(value, self.name)
        self._check_size(f, self.name)
        check_finite(f, self.name)
        n = f.shape[-1]
        eye = torch.eye(n, dtype=f.dtype, device=f.device)
        p = sym(_lyapunov_identity(f))
        m = f @ p
        chol_p, info = torch.linalg.cholesky_ex(p)
        if bool((info != 0).any()):
            raise ValueError(f"{self.name}: Lyapunov solution P is not positive definite (shape {shape_str(f)})")
        s1 = sym(torch.cholesky_inverse(chol_p))  # right_inverse only: P⁻¹ of a bounded, PD P
        delta = self._floor(f.dtype)
        # (J, R, S) = (r K, r I, S1 / r): the floors hold for r in (r_lo, r_hi); take their
        # geometric mean (the largest relative slack on both sides), else the F is out of reach.
        k_sq = _frobenius_sq(0.5 * (m - m.mT))
        trace = lambda x: torch.diagonal(x, dim1=-2, dim2=-1).sum(-1)[..., None, None]  # noqa: E731
        lam_min = torch.linalg.eigvalsh(s1)[..., :1].unsqueeze(-1)
        r_lo = delta / (1.0 - delta**2 * k_sq).clamp_min(torch.finfo(f.dtype).tiny).sqrt()
        r_hi = (lam_min * (1.0 + n * delta) - delta * trace(s1)) / delta
        if bool(((delta**2 * k_sq >= 1.0) | (r_hi <= r_lo)).any()):
            raise ValueError(
                f"{self.name} is Hurwitz but out of reach of the floor {delta:.3g}: its Lyapunov solution P "
                "is too ill-conditioned or its rotation too fast for its damping; pass a smaller floor "
                f"(shape {shape_str(f)})"
            )
        r = (r_lo * r_hi).sqrt()
        skew = r * 0.5 * (m - m.mT)
        s = s1 / r
        c_r = delta * (n * r + torch.sqrt(1.0 + _frobenius_sq(skew))) / (1.0 + n * delta)
        c_s = delta * (trace(s) + 1.0) / (1.0 + n * delta)
        what = f"{self.name} (floor {delta:.3g})"
        raw_r = _cholesky_raw((r - c_r) * eye, 0.0, f"{what}; R − floor")
        raw_s = _cholesky_raw(s - c_s * eye, 0.0, f"{what}; S − floor")
        raw = torch.stack((torch.triu(skew, 1), raw_r, raw_s), dim=-3)
        return _unsaturated(raw, _saturation_bound(raw.dtype, 4), self.name)


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


class IntegratorChain(Parametrization):
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


class Unconstrained(Parametrization):
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


def generator_from_rates(rates: Tensor) -> Tensor:
    """Markov-chain generator (..., M, M) from its off-diagonal rates (the diagonal of ``rates``
    is ignored): ``Λ_ij = rates_ij`` (i ≠ j), ``Λ_ii = −Σ_{j≠i} rates_ij``."""
    off = rates * (1.0 - torch.eye(rates.shape[-1], dtype=rates.dtype, device=rates.device))
    return off - torch.diag_embed(off.sum(-1))


class Generator(FlooredParametrization):
    r"""Markov-chain generators Λ (..., M, M): ``Λ_ij = softplus(raw_ij) + floor`` for i ≠ j,
    ``Λ_ii = −Σ_{j≠i} Λ_ij`` (the diagonal of raw is unused).

    Off-diagonal rates are finite and > 0 for every finite raw tensor (no exponential of an
    unbounded parameter; raw entries beyond ``finfo.max ** (1/2)`` enter logarithmically, so
    the diagonal's sums stay finite too), so ``expm(Λ dt)`` is a stochastic matrix for every dt ≥ 0.
    ``right_inverse`` accepts a generator or a matrix of off-diagonal rates (its diagonal is
    ignored); rates must be finite and > 0 (ValueError otherwise; use a fixed buffer for
    exactly zero rates). The floor is fixed and saved as :class:`Positive`'s.
    """

    def __init__(self, name: str = "rates", floor: float | None = None) -> None:
        super().__init__(floor)
        self.name = name

    def forward(self, raw: Tensor) -> Tensor:
        return generator_from_rates(softplus(_saturated(raw, _saturation_bound(raw.dtype, 1))) + self._floor(raw.dtype))

    def right_inverse(self, value: object) -> Tensor:
        v = self._as_raw_tensor(value, self.name)
        check_matrix(v, self.name, square=True)
        check_finite(v, self.name)
        off = ~torch.eye(v.shape[-1], dtype=torch.bool, device=v.device)
        if bool((v[..., off] <= 0).any()):
            raise ValueError(
                f"{self.name}: learnable off-diagonal rates must be > 0, got min "
                f"{float(v[..., off].min()):.3g} (shape {shape_str(v)})"
            )
        raw = softplus_inverse((v - self._floor(v.dtype)).clamp_min(torch.finfo(v.dtype).tiny))
        raw = _unsaturated(torch.where(off, raw, torch.zeros_like(raw)), _saturation_bound(v.dtype, 1), self.name)
        return raw


class ModeProbabilities(Parametrization):
    """Probability vectors (..., M) = ``softmax(raw)``; ``right_inverse`` = log of the
    normalised value (entries must be finite and > 0)."""

    def __init__(self, name: str = "mode_prob0") -> None:
        super().__init__()
        self.name = name

    def forward(self, raw: Tensor) -> Tensor:
        return torch.softmax(raw, dim=-1)

    def right_inverse(self, value: object) -> Tensor:
        v = self._as_raw_tensor(value, self.name)
        check_finite(v, self.name)
        if bool((v <= 0).any()):
            raise ValueError(f"{self.name}: learnable probabilities must be > 0, got {v.tolist()}")
        return torch.log(v / v.sum(-1, keepdim=True))
