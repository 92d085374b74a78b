r"""Motion-model library: each factory returns an :class:`~torchsde_lti.LTISDE` with exact (F, L, Qc[, B]).

The models are :class:`StructuredSDE` subclasses: their matrices are functions of a few
named scalars (``q``, ``alpha``, ``k``, ``theta``, ``lengthscale``, ``variance``, ``m``,
``c`` …) that are learnable ``nn.Parameter``\ s, positive by construction
(:class:`~torchsde_lti.nn.parametrizations.Positive`, ``softplus + floor``). Read and set them
by name: ``model.q`` is the current positive value, ``model.q = 2.0`` stores it (in place);
the raw tensor is ``model.parametrizations.q.original``. Scalars may carry a batch shape
(``q`` of shape (16,) gives 16 models in one module, matrices (16, n, n)); Python floats
become tensors of ``dtype`` (default: torch's default dtype).

``model.F`` etc. are read-only (they are derived); use :meth:`LTISDE.to_free` to continue
from a model with free matrices.

Multi-axis models use per-axis state ordering ``[x, vx, y, vy]`` (``[x, vx, ax, y, vy, ay]``),
one independent Brownian motion per axis (``Qc = q I_dim``), and ``position_indices`` lists the
position components (``position_observation`` builds the matching H).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchsde_lti.core.stationary import stationary_covariance
from torchsde_lti.core.validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_matrix,
    common_float_dtype,
    shape_str,
)
from torchsde_lti.nn.parametrizations import integrator_chain
from torchsde_lti.nn.sde import LTISDE, SDEMatrices, StructuredSDE

__all__ = [
    "BlockDiagSDE",
    "Companion",
    "IntegratedOU",
    "IntegratedWiener",
    "MassSpringDamper",
    "Matern",
    "OrnsteinUhlenbeck",
    "Singer",
    "StructuredSDE",
    "block_diag",
    "companion",
    "constant_acceleration",
    "constant_velocity",
    "integrated_ou",
    "integrated_wiener",
    "mass_spring_damper",
    "matern",
    "ornstein_uhlenbeck",
    "position_observation",
    "ShapedSDE",
    "TransferFunction",
    "from_transfer_function",
    "shaped",
    "singer",
]

Scalar = float | Tensor


# ---------------------------------------------------------------------------- helpers
def _check_int(value: object, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return value


def _scalar_dtype(values: Sequence[object], dtype: torch.dtype | None) -> torch.dtype:
    if dtype is not None:
        return dtype
    tensors = [v for v in values if isinstance(v, Tensor)]
    return common_float_dtype(*tensors) if tensors else torch.get_default_dtype()


def _scalar_device(values: Sequence[object], device: torch.device | str | None) -> torch.device | None:
    if device is not None:
        return torch.device(device)
    for v in values:
        if isinstance(v, Tensor):
            return v.device
    return None


def _block_diag(blocks: Sequence[Tensor]) -> Tensor:
    """Batched block-diagonal matrix of (..., r_i, c_i) blocks (batch dims broadcast)."""
    batch = torch.broadcast_shapes(*(b.shape[:-2] for b in blocks))
    total_c = sum(b.shape[-1] for b in blocks)
    rows = []
    offset = 0
    for b in blocks:
        c = b.shape[-1]
        b = b.expand(*batch, *b.shape[-2:])
        rows.append(nn.functional.pad(b, (offset, total_c - offset - c)))
        offset += c
    return torch.cat(rows, dim=-2)


def _eye_blocks(like: Tensor, dim: int, scale: Tensor) -> Tensor:
    """``scale[..., None, None] · I_dim`` (..., dim, dim)."""
    eye = torch.eye(dim, dtype=like.dtype, device=like.device)
    return scale[..., None, None] * eye


class _ChainSDE(StructuredSDE):
    """Shared layout: ``dim`` axes of ``order`` derivatives each, noise on the highest one."""

    def _init_chain(self, order: int, dim: int, dtype: torch.dtype, device: torch.device | None) -> None:
        self.order = order
        self.dim = dim
        chain, top = integrator_chain(order, dim, dtype, device)
        self.register_buffer("_chain", chain, persistent=False)
        self.register_buffer("_top", top, persistent=False)  # L: noise drives the highest derivative
        self.position_indices = tuple(axis * order for axis in range(dim))

    def _drag(self, rate: Tensor) -> Tensor:
        """``_chain − rate · (highest-derivative selector)``: (..., n, n)."""
        sel = self._top @ self._top.mT
        return self._chain - rate[..., None, None] * sel

    def _init_drag_model(self, order: int, rate_name: str, rate: Scalar, q: Scalar, dim: int,
                         dtype: torch.dtype | None, device: torch.device | str | None) -> None:
        """Positive scalars ``rate_name`` and ``q`` and the chain layout of a drag model."""
        _check_int(dim, "dim", 1)
        dt_ = _scalar_dtype([rate, q], dtype)
        dev = _scalar_device([rate, q], device)
        self._add_positive(rate_name, rate, dt_, dev)
        self._add_positive("q", q, dt_, dev)
        self._check_scalars((rate_name, "q"))
        self._init_chain(order, dim, dt_, dev)

    def _drag_matrices(self, rate: Tensor, q: Tensor) -> SDEMatrices:
        """F with drag ``rate`` on the highest derivative, ``L = _top``, ``Qc = q I_dim``.

        rate, q: (...) scalars whose batch shapes broadcast (either may be unbatched).
        """
        batch = torch.broadcast_shapes(rate.shape, q.shape)
        F = self._drag(rate.expand(batch))
        Qc = _eye_blocks(F, self.dim, q.expand(batch))
        return SDEMatrices(F, self._top.expand(*batch, *self._top.shape), Qc, None)


# ---------------------------------------------------------------------------- integrator chains
class _DragSDE(_ChainSDE):
    """A chain of ``_order`` derivatives per axis whose highest one has a positive drag rate,
    the scalar named ``_rate_name``; constructed as ``Model(rate, q, dim, dtype=, device=)``."""

    _order: int
    _rate_name: str

    def __init__(self, rate: Scalar, q: Scalar, dim: int = 1, *, dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None) -> None:
        super().__init__()
        self._init_drag_model(self._order, self._rate_name, rate, q, dim, dtype, device)

    def _build(self) -> SDEMatrices:
        return self._drag_matrices(getattr(self, self._rate_name), self.q)

    def extra_repr(self) -> str:
        return f"dim={self.dim}, " + self._scalar_repr([self._rate_name, "q"])


class IntegratedWiener(_ChainSDE):
    r"""Integrator chain per axis: ``d x^(order−1) = dβ``, ``E[dβ dβᵀ] = q I dt``.

    Per axis the state is ``[x, x', …, x^(order−1)]``; F has ones on the per-axis
    superdiagonal, L selects the highest derivative, ``Qc = q I_dim``. Closed form
    (0-based i, j within an axis, a = order−1−i, b = order−1−j):
    ``A_ij = dt^(j−i)/(j−i)!`` (j ≥ i), ``Q_ij = q dt^(a+b+1) / (a! b! (a+b+1))``.
    """

    def __init__(self, order: int, dim: int, q: Scalar, *, dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None) -> None:
        super().__init__()
        _check_int(order, "order", 1)
        _check_int(dim, "dim", 1)
        dt_ = _scalar_dtype([q], dtype)
        dev = _scalar_device([q], device)
        self._add_positive("q", q, dt_, dev)
        self._init_chain(order, dim, dt_, dev)

    def _build(self) -> SDEMatrices:
        q = self.q
        F = self._chain.expand(*q.shape, *self._chain.shape)
        return SDEMatrices(F, self._top.expand(*q.shape, *self._top.shape), _eye_blocks(q, self.dim, q), None)

    def extra_repr(self) -> str:
        return f"order={self.order}, dim={self.dim}, " + self._scalar_repr(["q"])


def integrated_wiener(order: int, dim: int = 1, q: Scalar = 1.0, **kw: object) -> IntegratedWiener:
    r"""Integrator chain of ``order`` states per axis driven by white noise of spectral density q.

    SDE per axis: ``dx^(k) = x^(k+1) dt`` (k < order−1), ``dx^(order−1) = dβ``, ``E[dβ²] = q dt``.
    ``order=1``: Brownian motion; 2: constant velocity; 3: constant acceleration.
    """
    return IntegratedWiener(order, dim, q, **kw)  # type: ignore[arg-type]


def constant_velocity(dim: int = 2, q: Scalar = 1.0, **kw: object) -> IntegratedWiener:
    r"""Constant velocity (white-noise acceleration), state ``[x, vx, y, vy, …]``.

    Per axis ``dx = v dt``, ``dv = dβ``, ``E[dβ²] = q dt``:
    ``A = [[1, dt], [0, 1]]``, ``Q = q [[dt³/3, dt²/2], [dt²/2, dt]]``.
    """
    return IntegratedWiener(2, dim, q, **kw)  # type: ignore[arg-type]


def constant_acceleration(dim: int = 2, q: Scalar = 1.0, **kw: object) -> IntegratedWiener:
    r"""Constant acceleration (white-noise jerk), state ``[x, vx, ax, y, vy, ay, …]``.

    Per axis ``dx = v dt``, ``dv = a dt``, ``da = dβ``, ``E[dβ²] = q dt``:
    ``Q = q [[dt⁵/20, dt⁴/8, dt³/6], [dt⁴/8, dt³/3, dt²/2], [dt³/6, dt²/2, dt]]``.
    """
    return IntegratedWiener(3, dim, q, **kw)  # type: ignore[arg-type]


class Singer(_DragSDE):
    r"""Singer model per axis: ``dx = v dt``, ``dv = a dt``, ``da = −α a dt + dβ``, ``E[dβ²] = q dt``.

    Same parametrisation as Stone Soup's ``Singer(damping_coeff=α, noise_diff_coeff=q)``.
    """

    _order, _rate_name = 3, "alpha"


def singer(alpha: Scalar, q: Scalar, dim: int = 1, **kw: object) -> Singer:
    r"""Singer acceleration model: ``da = −α a dt + dβ`` (spectral density q), state ``[x, v, a]`` per axis."""
    return Singer(alpha, q, dim, **kw)  # type: ignore[arg-type]


class IntegratedOU(_DragSDE):
    r"""Integrated Ornstein–Uhlenbeck per axis: ``dx = v dt``, ``dv = −k v dt + dβ``, ``E[dβ²] = q dt``.

    Stone Soup calls this ``OrnsteinUhlenbeck(damping_coeff=k, noise_diff_coeff=q)``.
    """

    _order, _rate_name = 2, "k"


def integrated_ou(k: Scalar, q: Scalar, dim: int = 1, **kw: object) -> IntegratedOU:
    r"""Velocity with drag k integrated to position: ``dx = v dt``, ``dv = −k v dt + dβ`` (density q)."""
    return IntegratedOU(k, q, dim, **kw)  # type: ignore[arg-type]


class OrnsteinUhlenbeck(StructuredSDE):
    r"""Scalar OU per axis: ``dx = −θ x dt + dβ``, ``E[dβ dβᵀ] = q I dt``.

    ``A = e^{−θ dt} I``, ``Q = q (1 − e^{−2θ dt}) / (2θ) I``, ``P∞ = q / (2θ) I``.
    """

    def __init__(self, theta: Scalar, q: Scalar, dim: int = 1, *, dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None) -> None:
        super().__init__()
        _check_int(dim, "dim", 1)
        dt_ = _scalar_dtype([theta, q], dtype)
        dev = _scalar_device([theta, q], device)
        self._add_positive("theta", theta, dt_, dev)
        self._add_positive("q", q, dt_, dev)
        self._check_scalars(("theta", "q"))
        self.dim = dim
        self.position_indices = tuple(range(dim))

    def _build(self) -> SDEMatrices:
        theta, q = self.theta, self.q
        batch = torch.broadcast_shapes(theta.shape, q.shape)
        F = _eye_blocks(theta, self.dim, -theta.expand(batch))
        L = torch.eye(self.dim, dtype=F.dtype, device=F.device).expand(*batch, self.dim, self.dim)
        return SDEMatrices(F, L, _eye_blocks(q, self.dim, q.expand(batch)), None)

    def extra_repr(self) -> str:
        return f"dim={self.dim}, " + self._scalar_repr(["theta", "q"])


def ornstein_uhlenbeck(theta: Scalar, q: Scalar, dim: int = 1, **kw: object) -> OrnsteinUhlenbeck:
    r"""Mean-reverting position: ``dx = −θ x dt + dβ`` per axis (spectral density q)."""
    return OrnsteinUhlenbeck(theta, q, dim, **kw)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------- Matérn
_MATERN_NU = (0.5, 1.5, 2.5)


class Matern(StructuredSDE):
    r"""State-space Matérn-ν Gaussian process (ν ∈ {1/2, 3/2, 5/2}), state ``[f, f', …]``.

    With ``λ = √(2ν)/ℓ`` and ``m = ν + 1/2`` states, F is the companion matrix of
    ``(d/dt + λ)^m`` (last row ``−C(m, j) λ^{m−j}``, j = 0…m−1), ``L = e_m`` and
    ``Qc = 2σ² √π λ^{2ν} Γ(ν+½)/Γ(ν)`` (2σ²λ, 4σ²λ³, 16σ²λ⁵/3). Its stationary covariance
    P∞ gives exactly the Matérn kernel: ``k(τ) = H expm(F τ) P∞ Hᵀ`` with ``H = e_1ᵀ``, e.g.
    ``σ² (1 + λτ) e^{−λτ}`` for ν = 3/2.
    """

    def __init__(self, nu: float, lengthscale: Scalar, variance: Scalar, *, dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None) -> None:
        super().__init__()
        try:
            nu_f = float(nu)
        except (TypeError, ValueError):
            raise ValueError(f"nu must be one of 1/2, 3/2, 5/2, got {nu!r}") from None
        match = [v for v in _MATERN_NU if abs(nu_f - v) < 1e-12]
        if not match:
            raise ValueError(f"nu must be one of 1/2, 3/2, 5/2, got {nu!r}")
        self.nu = match[0]
        self.order = int(self.nu + 0.5)
        dt_ = _scalar_dtype([lengthscale, variance], dtype)
        dev = _scalar_device([lengthscale, variance], device)
        self._add_positive("lengthscale", lengthscale, dt_, dev)
        self._add_positive("variance", variance, dt_, dev)
        self._check_scalars(("lengthscale", "variance"))
        m = self.order
        kw = {"dtype": dt_, "device": dev}
        chain, top = integrator_chain(m, 1, dt_, dev)  # one axis: [f, f', …], top = e_m
        self.register_buffer("_chain", chain, persistent=False)
        self.register_buffer("_top", top, persistent=False)
        self.register_buffer(
            "_binom", torch.tensor([float(math.comb(m, j)) for j in range(m)], **kw), persistent=False
        )
        self.register_buffer("_powers", torch.arange(m, 0, -1, **kw), persistent=False)  # m−j
        self.position_indices = (0,)
        self._qc_const = 2.0 * math.sqrt(math.pi) * math.gamma(self.nu + 0.5) / math.gamma(self.nu)

    @property
    def rate(self) -> Tensor:
        """λ = √(2ν)/ℓ, shape (...)."""
        return math.sqrt(2.0 * self.nu) / self.lengthscale

    def _build(self) -> SDEMatrices:
        lam = self.rate
        var = self.variance
        batch = torch.broadcast_shapes(lam.shape, var.shape)
        lam = lam.expand(batch)
        m = self.order
        last = -self._binom * lam[..., None] ** self._powers  # (..., m)
        sel = self._top[:, 0]  # e_m
        F = self._chain + sel[:, None] * last[..., None, :]
        qc = self._qc_const * var.expand(batch) * lam ** (2 * self.nu)
        L = self._top.expand(*batch, m, 1)
        return SDEMatrices(F, L, qc[..., None, None], None)

    def kernel(self, tau: Tensor) -> Tensor:
        """Closed-form Matérn covariance ``k(τ)``; ``tau`` broadcasts against the batch."""
        lam, var = self.rate, self.variance
        r = lam * tau.abs()
        poly = {0.5: 1.0, 1.5: 1.0 + r, 2.5: 1.0 + r + r**2 / 3.0}[self.nu]
        return var * poly * torch.exp(-r)

    def extra_repr(self) -> str:
        return f"nu={self.nu}, " + self._scalar_repr(["lengthscale", "variance"])


def matern(nu: float, lengthscale: Scalar = 1.0, variance: Scalar = 1.0, **kw: object) -> Matern:
    r"""Matérn-ν GP as an SDE (ν ∈ {1/2, 3/2, 5/2}); ``k(τ) = σ² · poly(λτ) · e^{−λτ}``, λ = √(2ν)/ℓ."""
    return Matern(nu, lengthscale, variance, **kw)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------- ODE systems
class _OutputEquation:
    """Models with an output equation ``y = C x + D u``: ``C`` is the registered buffer
    ``output_matrix`` (1, n) (pass it as the filter's H), ``D`` the (1, p) zero feedthrough
    unless a subclass says otherwise (pass it as the filter's D)."""

    output_matrix: Tensor

    @property
    def C(self) -> Tensor:
        return self.output_matrix

    @property
    def D(self) -> Tensor:
        return self.output_matrix.new_zeros(1, 1)


class MassSpringDamper(_OutputEquation, StructuredSDE):
    r"""``m p'' = u − c p' − k p + w``: state ``[p, p']``, force input u, random force w.

    ``F = [[0, 1], [−k/m, −c/m]]``, ``B = L = [0, 1/m]ᵀ``, ``Qc = q`` (spectral density of
    the random force), output ``C = [[1, 0]]`` (``output_matrix``).
    """

    def __init__(self, m: Scalar, k: Scalar, c: Scalar, q: Scalar = 1.0, *, dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None) -> None:
        super().__init__()
        dt_ = _scalar_dtype([m, k, c, q], dtype)
        dev = _scalar_device([m, k, c, q], device)
        for name, value in (("m", m), ("k", k), ("c", c), ("q", q)):
            self._add_positive(name, value, dt_, dev)
        self._check_scalars(("m", "k", "c", "q"))
        self.register_buffer("output_matrix", torch.tensor([[1.0, 0.0]], dtype=dt_, device=dev), persistent=False)
        self.position_indices = (0,)

    def _build(self) -> SDEMatrices:
        m, k, c, q = self.m, self.k, self.c, self.q
        batch = torch.broadcast_shapes(m.shape, k.shape, c.shape, q.shape)
        zero = m.new_zeros(batch)
        one = zero + 1.0
        F = torch.stack(
            (torch.stack((zero, one), -1), torch.stack(((-k / m).expand(batch), (-c / m).expand(batch)), -1)), -2
        )
        Bm = torch.stack((zero, (1.0 / m).expand(batch)), -1)[..., None]
        return SDEMatrices(F, Bm, q.expand(batch)[..., None, None], Bm)

    def extra_repr(self) -> str:
        return self._scalar_repr(["m", "k", "c", "q"])


def mass_spring_damper(m: Scalar, k: Scalar, c: Scalar, q: Scalar = 1.0, **kw: object) -> MassSpringDamper:
    r"""Mass–spring–damper ``m p'' = u − c p' − k p + w`` with force input (B) and random force (q)."""
    return MassSpringDamper(m, k, c, q, **kw)  # type: ignore[arg-type]


class Companion(_OutputEquation, StructuredSDE):
    r"""Order-n ODE ``a_n y⁽ⁿ⁾ + … + a_1 y' + a_0 y = u + w`` in companion form, state ``[y, y', …, y⁽ⁿ⁻¹⁾]``.

    F has ones on the superdiagonal and last row ``−a_0/a_n … −a_{n−1}/a_n``;
    ``B = L = [0, …, 0, 1/a_n]ᵀ``; ``Qc = q`` (spectral density of w); output
    ``C = [[1, 0, …, 0]]``. The coefficients ``a`` (..., n+1) are free (unconstrained)
    parameters — an ODE may be unstable or undamped — and a_n must stay non-zero; ``q`` is
    positive.
    """

    def __init__(self, a: Sequence[float] | Tensor, q: Scalar = 1.0, *, dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None) -> None:
        super().__init__()
        dt_ = _scalar_dtype([a, q], dtype)
        dev = _scalar_device([a, q], device)
        coeffs = as_float_tensor(a, "a", dt_, dev).detach().clone()
        if coeffs.dim() < 1 or coeffs.shape[-1] < 2:
            raise ValueError(f"a must hold coefficients a_0..a_n with n >= 1, shape (..., n+1); got shape {shape_str(coeffs)}")
        check_finite(coeffs, "a")
        if bool((coeffs[..., -1] == 0).any()):
            raise ValueError(f"a: the leading coefficient a_n must be non-zero (shape {shape_str(coeffs)})")
        self.a = nn.Parameter(coeffs)
        self._add_positive("q", q, dt_, dev)
        broadcast_batch([("a", coeffs.shape[:-1]), ("q", self.q.shape)])
        n = coeffs.shape[-1] - 1
        self.order = n
        kw = {"dtype": dt_, "device": dev}
        chain, e_n = integrator_chain(n, 1, dt_, dev)  # one axis: [y, y', …], e_n (n, 1)
        self.register_buffer("_chain", chain, persistent=False)
        self.register_buffer("_e_n", e_n[:, 0], persistent=False)
        out = torch.zeros(1, n, **kw)
        out[0, 0] = 1.0
        self.register_buffer("output_matrix", out, persistent=False)
        self.position_indices = (0,)

    def _build(self) -> SDEMatrices:
        a, q = self.a, self.q
        lead = a[..., -1:]
        last = -a[..., :-1] / lead  # (..., n)
        F = self._chain + self._e_n[:, None] * last[..., None, :]
        batch = torch.broadcast_shapes(F.shape[:-2], q.shape)
        F = F.expand(*batch, *F.shape[-2:])
        Bm = (self._e_n / lead)[..., None].expand(*batch, self.order, 1)
        return SDEMatrices(F, Bm, q.expand(batch)[..., None, None], Bm)

    def extra_repr(self) -> str:
        return f"order={self.order}, a: {shape_str(self.a)}, " + self._scalar_repr(["q"])


def companion(a: Sequence[float] | Tensor, q: Scalar = 1.0, **kw: object) -> Companion:
    r"""Companion form of ``a_n y⁽ⁿ⁾ + … + a_0 y = u + w`` from coefficients ``a = [a_0, …, a_n]``."""
    return Companion(a, q, **kw)  # type: ignore[arg-type]


class TransferFunction(Companion):
    r"""A proper transfer function ``G(s) = num(s) / den(s)`` in controllable canonical form.

    With ``den(s) = a_n sⁿ + … + a_0`` and ``num(s) = b_n sⁿ + … + b_0`` (``b_n = 0`` unless
    deg num = deg den), write ``num = d · den + r`` with ``d = b_n / a_n`` and deg r < n.
    The state ``x = [z, z', …, z⁽ⁿ⁻¹⁾]`` of ``den(d/dt) z = u + w`` (the :class:`Companion`
    matrices: F with ones on the superdiagonal and last row ``−a_0/a_n … −a_{n−1}/a_n``,
    ``B = L = e_n / a_n``, ``Qc = q``) gives ``y = num(d/dt) z = C x + D u`` with

        C = [r_0, r_1, …, r_{n−1}]  (1, n),      D = [[d]]  (1, 1).

    State ordering: ascending derivatives. scipy's ``tf2ss`` uses the reversed order and a
    monic denominator: its state is ``a_n J x`` with J the exchange matrix (ones on the
    anti-diagonal), so ``A_scipy = J F J``, ``B_scipy = a_n J B`` (= e_1),
    ``C_scipy = C J / a_n``, ``D_scipy = D``; transfer function and responses are identical.

    The denominator coefficients ``a`` are free parameters (as in :class:`Companion`);
    the numerator is a constant buffer ``numerator`` (..., n+1) in ascending powers; C and
    D are recomputed from the current ``a``.
    """

    def __init__(self, num: Sequence[float] | Tensor, den: Sequence[float] | Tensor, q: Scalar = 1.0, *,
                 dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> None:
        dt_ = _scalar_dtype([num, den, q], dtype)
        dev = _scalar_device([num, den, q], device)
        b = as_float_tensor(num, "num", dt_, dev).detach().clone()
        a = as_float_tensor(den, "den", dt_, dev).detach().clone()
        if b.dim() < 1 or a.dim() < 1:
            raise ValueError(
                f"num and den must hold polynomial coefficients (..., k), highest power first; got shapes "
                f"num {shape_str(b)}, den {shape_str(a)}"
            )
        check_finite(b, "num")
        check_finite(a, "den")
        a = _strip_leading_zeros(a)
        b = _strip_leading_zeros(b)
        if a.shape[-1] < 2:
            raise ValueError(
                f"den must have degree >= 1 (a transfer function with a state), got den of shape {shape_str(a)} "
                "after removing leading zeros"
            )
        if b.shape[-1] > a.shape[-1]:
            raise ValueError(
                f"improper transfer function: deg num = {b.shape[-1] - 1} > deg den = {a.shape[-1] - 1} "
                f"(num shape {shape_str(b)}, den shape {shape_str(a)}); a state-space model y = C x + D u needs "
                "deg num <= deg den"
            )
        n1 = a.shape[-1]
        b = nn.functional.pad(b, (n1 - b.shape[-1], 0))  # same length as den
        super().__init__(torch.flip(a, (-1,)), q, dtype=dt_, device=dev)
        broadcast_batch([("num", b.shape[:-1]), ("den", a.shape[:-1])])
        self.register_buffer("numerator", torch.flip(b, (-1,)), persistent=False)  # ascending b_0..b_n
        self.position_indices = None  # the output is C x + D u, not a state component: use model.C as H

    def _output(self) -> tuple[Tensor, Tensor]:
        a, b = self.a, self.numerator
        d = b[..., -1:] / a[..., -1:]  # (..., 1)
        r = b[..., :-1] - d * a[..., :-1]  # (..., n) remainder of num − d·den (ascending)
        return r[..., None, :], d[..., None]

    @property
    def C(self) -> Tensor:
        """Output matrix ``[r_0 … r_{n−1}]`` (..., 1, n): pass it as the filter's H."""
        return self._output()[0]

    @property
    def D(self) -> Tensor:
        """Feedthrough ``[[b_n / a_n]]`` (..., 1, 1): pass it as the filter's D."""
        return self._output()[1]

    def extra_repr(self) -> str:
        return f"order={self.order}, num: {shape_str(self.numerator)}, a: {shape_str(self.a)}, " + self._scalar_repr(["q"])


def _strip_leading_zeros(coeffs: Tensor) -> Tensor:
    """Drop leading (highest-power) coefficients that are zero across the whole batch."""
    while coeffs.shape[-1] > 1 and bool((coeffs[..., 0] == 0).all()):
        coeffs = coeffs[..., 1:]
    return coeffs


def from_transfer_function(num: Sequence[float] | Tensor, den: Sequence[float] | Tensor, q: Scalar = 1.0,
                           **kw: object) -> TransferFunction:
    r"""State-space model of ``G(s) = num(s) / den(s)`` (coefficients highest power first, as in scipy).

    Controllable canonical (companion) form, state ``[z, z', …]``: ``ẋ = F x + B u + L w``,
    ``y = C x + D u`` with ``model.C`` (1, n) and ``model.D`` (1, 1); white noise w of
    spectral density q enters where u does (``L = B``). D ≠ 0 exactly when
    deg num = deg den; ValueError for an improper G (deg num > deg den).

    Example: ``from_transfer_function([1.0], [1.0, 3.0, 2.0])`` is ``1 / (s² + 3s + 2)``.
    """
    return TransferFunction(num, den, q, **kw)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------- shaping filters
class ShapedSDE(StructuredSDE):
    r"""A system driven by coloured noise: the system plus a shaping filter driven by white noise.

    The system ``dx_s = F_s x_s dt + B_s u dt + L_s ν dt`` has its white noise ν replaced by
    the output ``ν = C_f x_f`` of the shaping filter ``dx_f = F_f x_f dt + B_f u_f dt + L_f dβ``
    (spectral density Qc_f). The augmented state ``[x_s, x_f]`` (n_s + n_f) has

        F = [[F_s, L_s C_f], [0, F_f]],   L = [[0], [L_f]],   Qc = Qc_f,
        B = diag(B_s, B_f)   (deterministic inputs of either part; None when neither has one).

    The system's own Qc is not used (its noise *is* the shaping filter's output). The parts
    stay submodules (``model.system``, ``model.shaping``), learned jointly; a C taken
    from the shaping model (its ``C`` property) is re-read at every evaluation.

    :meth:`start_covariance` is the steady-state start of seed 003 (lecture 23): every
    covariance entry that involves a system state is 0, the shaping-filter block is the
    shaping filter's own P∞ (white noise applied for all past time); with it the
    shaping-filter block stays at P∞ for all t. ``KalmanFilter`` uses it as the default
    prior of a shaped model (``prior_mode == "shaping"``).
    """

    def __init__(self, system: LTISDE, shaping: LTISDE, C: Tensor | None = None) -> None:
        super().__init__()
        for name, value in (("system", system), ("shaping", shaping)):
            if not isinstance(value, LTISDE):
                raise TypeError(f"{name} must be an LTISDE, got {type(value).__name__}")
        feedthrough = getattr(shaping, "D", None)
        if isinstance(feedthrough, Tensor) and bool((feedthrough != 0).any()):
            raise ValueError(
                f"the shaping filter must be strictly proper (D = 0): its D (shape {shape_str(feedthrough)}) "
                "would pass white noise straight into the system"
            )
        self.system = system
        self.shaping = shaping
        n_s, s, n_f = system.state_dim, system.noise_dim, shaping.state_dim
        dtype, device = system.dtype, system.device
        self._c_from_shaping = C is None and isinstance(getattr(shaping, "C", None), Tensor)
        if C is None:
            C = getattr(shaping, "C", None)
            if C is None:
                if n_f != s:
                    raise ValueError(
                        f"C is needed: the shaping filter has {n_f} states but the system's noise has "
                        f"{s} components (L_s shape (…, {n_s}, {s})); give C of shape ({s}, {n_f})"
                    )
                C = torch.eye(s, dtype=dtype, device=device)
            else:
                C = C.detach().clone()
        C = as_float_tensor(C, "C", dtype, device).detach().clone()
        check_matrix(C, "C", rows=s, cols=n_f)
        check_finite(C, "C")
        self.register_buffer("shaping_output", C, persistent=False)
        self.system_dim = n_s
        if system.position_indices is not None:
            self.position_indices = tuple(system.position_indices)

    def _build(self) -> SDEMatrices:
        ms, mf = self.system.matrices(), self.shaping.matrices()
        n_s, n_f = ms.F.shape[-1], mf.F.shape[-1]
        C_f = self.shaping.C if self._c_from_shaping else self.shaping_output  # follows a learned shaping C
        coupling = ms.L @ C_f  # L_s C_f (..., n_s, n_f)
        batch = torch.broadcast_shapes(ms.F.shape[:-2], coupling.shape[:-2], mf.F.shape[:-2])
        top = torch.cat([ms.F.expand(*batch, n_s, n_s), coupling.expand(*batch, n_s, n_f)], dim=-1)
        bottom = nn.functional.pad(mf.F.expand(*batch, n_f, n_f), (n_s, 0))
        F = torch.cat([top, bottom], dim=-2)
        L = nn.functional.pad(mf.L, (0, 0, n_s, 0))  # [0; L_f]
        if ms.B is None and mf.B is None:
            B = None
        else:
            B = _block_diag([m.B if m.B is not None else m.F.new_zeros(*m.F.shape[:-1], 0) for m in (ms, mf)])
        return SDEMatrices(F, L, mf.Qc, B)

    def start_covariance(self, mats: SDEMatrices | None = None) -> Tensor:
        r"""Seed 003's steady-state start ``P0 = [[0, 0], [0, P∞_f]]`` (..., n, n).

        ``P∞_f`` solves ``F_f P + P F_fᵀ + L_f Qc_f L_fᵀ = 0`` at the current parameters
        (read from the augmented ``mats`` when given, so a filter evaluates each
        parametrisation once). ValueError when F_f is not Hurwitz.
        """
        if mats is None:
            mats = self.matrices()
        n_s = self.system_dim
        P_f = stationary_covariance(mats.F[..., n_s:, n_s:], mats.L[..., n_s:, :], mats.Qc)
        return nn.functional.pad(P_f, (n_s, 0, n_s, 0))

    def extra_repr(self) -> str:
        return f"system_dim={self.system_dim}, shaping_dim={int(self.shaping_output.shape[-1])}"


def shaped(system: LTISDE, shaping: LTISDE, C: Tensor | None = None) -> ShapedSDE:
    r"""System driven by the coloured noise ``C x_f`` of a shaping filter (seed 003), see :class:`ShapedSDE`.

    ``F = [[F_s, L_s C], [0, F_f]]``, ``L = [0; L_f]``, ``Qc = Qc_f``; the steady-state start
    is ``model.start_covariance()``. C defaults to the shaping filter's ``C`` (companion,
    mass–spring–damper, transfer-function models) or the identity when dimensions match.

    Example (first-order system with a Gauss–Markov input, ``ẋ = −a x + f``,
    ``ḟ = −b f + w``): ``shaped(ornstein_uhlenbeck(a, 1.0), ornstein_uhlenbeck(b, q))``.
    """
    return ShapedSDE(system, shaping, C)


# ---------------------------------------------------------------------------- composition
class BlockDiagSDE(StructuredSDE):
    r"""Independent SDEs side by side: every matrix is the block diagonal of the parts'.

    ``B`` is block diagonal over the parts that have an input (parts without one get a
    zero-width block); it is None when no part has an input. The parts stay submodules
    (``model.parts[i].q``), so their parameters are learned jointly.
    """

    def __init__(self, *sdes: LTISDE) -> None:
        super().__init__()
        if len(sdes) == 0:
            raise ValueError("sdes must contain at least one LTISDE, got none")
        for i, s in enumerate(sdes):
            if not isinstance(s, LTISDE):
                raise ValueError(f"sdes[{i}] must be an LTISDE, got {type(s).__name__}")
        self.parts = nn.ModuleList(sdes)
        dims = [s.state_dim for s in sdes]
        if all(s.position_indices is not None for s in sdes):
            idx: list[int] = []
            offset = 0
            for s, n in zip(sdes, dims):
                idx.extend(offset + i for i in s.position_indices)  # type: ignore[union-attr]
                offset += n
            self.position_indices = tuple(idx)

    def _build(self) -> SDEMatrices:
        mats = [s.matrices() for s in self.parts]
        F = _block_diag([m.F for m in mats])
        L = _block_diag([m.L for m in mats])
        Qc = _block_diag([m.Qc for m in mats])
        if all(m.B is None for m in mats):
            B = None
        else:
            B = _block_diag([m.B if m.B is not None else m.F.new_zeros(*m.F.shape[:-1], 0) for m in mats])
        return SDEMatrices(F, L, Qc, B)

    def extra_repr(self) -> str:
        return f"{len(self.parts)} parts"


def block_diag(*sdes: LTISDE) -> BlockDiagSDE:
    r"""Compose independent SDEs: ``F = diag(F_1, F_2, …)`` and likewise L, Qc, B."""
    return BlockDiagSDE(*sdes)


def position_observation(model: LTISDE) -> Tensor:
    """H (k, n) with a one at each position component: ``y = H x`` observes positions.

    Uses ``model.position_indices`` (set by every model of this module and by
    :func:`block_diag` of such models); dtype/device follow the model.
    """
    idx = getattr(model, "position_indices", None)
    if idx is None:
        raise ValueError(
            f"model ({type(model).__name__}) does not declare position_indices; build H by hand"
        )
    with torch.no_grad():
        F = model.matrices().F
    n = F.shape[-1]
    H = F.new_zeros(len(idx), n)
    for row, col in enumerate(idx):
        H[row, col] = 1.0
    return H


# ---------------------------------------------------------------------------- moored / stationary mode
class Moored(_DragSDE):
    r"""A vessel at rest: per axis ``dx = v dt + dβ_x``, ``dv = −k v dt`` (state ``[x, vx, y, vy]``).

    The velocity state decays with a strong rate k (any velocity inherited from another
    mode of an IMM bank dies out within a few 1/k), and the position wanders as a slow
    random walk of spectral density q (m²/s: drift at the mooring). Same state layout as
    :func:`constant_velocity` / :func:`integrated_ou`, so it can share an IMM bank with them.
    ``L`` selects the positions, ``Qc = q I_dim``.
    """

    _order, _rate_name = 2, "k"

    def __init__(self, k: Scalar, q: Scalar, dim: int = 2, *, dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None) -> None:
        super().__init__(k, q, dim, dtype=dtype, device=device)
        pos = torch.zeros_like(self._top)
        for axis, idx in enumerate(self.position_indices):
            pos[idx, axis] = 1.0
        self.register_buffer("_pos", pos, persistent=False)

    def _build(self) -> SDEMatrices:
        k, q = self.k, self.q
        batch = torch.broadcast_shapes(k.shape, q.shape)
        F = self._drag(k.expand(batch))
        Qc = _eye_blocks(F, self.dim, q.expand(batch))
        return SDEMatrices(F, self._pos.expand(*batch, *self._pos.shape), Qc, None)


def moored(k: Scalar = 0.1, q: Scalar = 1e-3, dim: int = 2, **kw: object) -> Moored:
    r"""Stationary-vessel mode: position random walk (density q), velocity damped at rate k."""
    return Moored(k, q, dim, **kw)  # type: ignore[arg-type]
