r"""Integrator chains and drag models: constant velocity / acceleration, Singer, integrated OU,
Ornstein–Uhlenbeck and the moored-vessel mode (state ``[x, x', …]`` per axis)."""

from __future__ import annotations

import torch
from torch import Tensor
from typing_extensions import Unpack

from torchsde_lti.models._common import ModelOptions, Scalar, check_int, eye_blocks, scalar_dtype_device
from torchsde_lti.nn.parametrizations import integrator_chain
from torchsde_lti.nn.sde import SDEMatrices, StructuredSDE

__all__ = [
    "constant_acceleration",
    "constant_velocity",
    "integrated_ou",
    "integrated_wiener",
    "moored",
    "ornstein_uhlenbeck",
    "singer",
]


class ChainSDE(StructuredSDE):
    """Shared layout: ``dim`` axes of ``order`` derivatives each, noise on the highest one."""

    q: Tensor
    _chain: Tensor
    _top: Tensor

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


class DragSDE(ChainSDE):
    """A chain of ``_order`` derivatives per axis whose highest one has a positive drag rate,
    the scalar named ``_rate_name``; F with that drag, ``L = _top``, ``Qc = q I_dim``."""

    _order: int
    _rate_name: str

    def __init__(self, rate: Scalar, q: Scalar, dim: int = 1, **options: Unpack[ModelOptions]) -> None:
        super().__init__(options.get("validate_args"))
        check_int(dim, "dim", 1)
        dtype, device = scalar_dtype_device([rate, q], options)
        self._add_positive(self._rate_name, rate, dtype, device)
        self._add_positive("q", q, dtype, device)
        self._check_scalars((self._rate_name, "q"))
        self._init_chain(self._order, dim, dtype, device)

    def _noise_gain(self) -> Tensor:
        """L (n, dim): the highest derivative of each axis."""
        return self._top

    def _build(self) -> SDEMatrices:
        rate, q = getattr(self, self._rate_name), self.q
        batch = torch.broadcast_shapes(rate.shape, q.shape)
        F = self._drag(rate.expand(batch))
        Qc = eye_blocks(F, self.dim, q.expand(batch))
        L = self._noise_gain()
        return SDEMatrices(F, L.expand(*batch, *L.shape), Qc, None)

    def extra_repr(self) -> str:
        return f"dim={self.dim}, " + self._scalar_repr([self._rate_name, "q"])


class IntegratedWiener(ChainSDE):
    """Integrator chain per axis driven by white noise of spectral density q (see :func:`integrated_wiener`)."""

    def __init__(self, order: int, dim: int, q: Scalar, **options: Unpack[ModelOptions]) -> None:
        super().__init__(options.get("validate_args"))
        check_int(order, "order", 1)
        check_int(dim, "dim", 1)
        dtype, device = scalar_dtype_device([q], options)
        self._add_positive("q", q, dtype, device)
        self._init_chain(order, dim, dtype, device)

    def structural_nilpotency(self) -> int:
        """``order``: F holds ones on each axis's superdiagonal (a fixed buffer), F^order = 0."""
        return self.order

    def _build(self) -> SDEMatrices:
        q = self.q
        F = self._chain.expand(*q.shape, *self._chain.shape)
        return SDEMatrices(F, self._top.expand(*q.shape, *self._top.shape), eye_blocks(q, self.dim, q), None)

    def extra_repr(self) -> str:
        return f"order={self.order}, dim={self.dim}, " + self._scalar_repr(["q"])


def integrated_wiener(order: int, dim: int = 1, q: Scalar = 1.0, **options: Unpack[ModelOptions]) -> IntegratedWiener:
    r"""Integrator chain of ``order`` states per axis driven by white noise of spectral density q.

    SDE per axis: ``dx^(k) = x^(k+1) dt`` (k < order−1), ``dx^(order−1) = dβ``, ``E[dβ²] = q dt``.
    ``order=1``: Brownian motion; 2: constant velocity; 3: constant acceleration. Per axis the
    state is ``[x, x', …, x^(order−1)]``; F has ones on the per-axis superdiagonal, L selects
    the highest derivative, ``Qc = q I_dim``. Closed form (0-based i, j within an axis,
    a = order−1−i, b = order−1−j): ``A_ij = dt^(j−i)/(j−i)!`` (j ≥ i),
    ``Q_ij = q dt^(a+b+1) / (a! b! (a+b+1))``.

    Args:
        order: states per axis (>= 1): 1 Brownian motion, 2 constant velocity, 3 constant acceleration.
        dim: number of spatial axes (>= 1).
        q: spectral density of the driving white noise, positive; a float or a tensor whose shape is
            the parameter batch (...).
        **options: ``dtype``, ``device`` (of the parameters) and ``validate_args`` (see
            :class:`~torchsde_lti.LTISDE`).

    Returns:
        IntegratedWiener: an LTISDE with F (dim·order, dim·order), L (dim·order, dim), Qc (dim, dim); learns q.
    """
    return IntegratedWiener(order, dim, q, **options)


def constant_velocity(dim: int = 2, q: Scalar = 1.0, **options: Unpack[ModelOptions]) -> IntegratedWiener:
    r"""Constant velocity (white-noise acceleration), state ``[x, vx, y, vy, …]``.

    Per axis ``dx = v dt``, ``dv = dβ``, ``E[dβ²] = q dt``:
    ``A = [[1, dt], [0, 1]]``, ``Q = q [[dt³/3, dt²/2], [dt²/2, dt]]``.

    Args:
        dim: number of spatial axes (>= 1).
        q: spectral density of the driving white noise, positive; a float or a tensor whose shape is
            the parameter batch (...).
        **options: ``dtype``, ``device`` (of the parameters) and ``validate_args`` (see
            :class:`~torchsde_lti.LTISDE`).

    Returns:
        IntegratedWiener: F (2·dim, 2·dim), L (2·dim, dim), Qc (dim, dim); learns q.
    """
    return IntegratedWiener(2, dim, q, **options)


def constant_acceleration(dim: int = 2, q: Scalar = 1.0, **options: Unpack[ModelOptions]) -> IntegratedWiener:
    r"""Constant acceleration (white-noise jerk), state ``[x, vx, ax, y, vy, ay, …]``.

    Per axis ``dx = v dt``, ``dv = a dt``, ``da = dβ``, ``E[dβ²] = q dt``:
    ``Q = q [[dt⁵/20, dt⁴/8, dt³/6], [dt⁴/8, dt³/3, dt²/2], [dt³/6, dt²/2, dt]]``.

    Args:
        dim: number of spatial axes (>= 1).
        q: spectral density of the driving white noise, positive; a float or a tensor whose shape is
            the parameter batch (...).
        **options: ``dtype``, ``device`` (of the parameters) and ``validate_args`` (see
            :class:`~torchsde_lti.LTISDE`).

    Returns:
        IntegratedWiener: F (3·dim, 3·dim), L (3·dim, dim), Qc (dim, dim); learns q.
    """
    return IntegratedWiener(3, dim, q, **options)


class Singer(DragSDE):
    """Singer acceleration model (see :func:`singer`)."""

    _order, _rate_name = 3, "alpha"


def singer(alpha: Scalar, q: Scalar, dim: int = 1, **options: Unpack[ModelOptions]) -> Singer:
    r"""Singer acceleration model per axis, state ``[x, v, a]``.

    ``dx = v dt``, ``dv = a dt``, ``da = −α a dt + dβ``, ``E[dβ²] = q dt``.

    Same parametrisation as Stone Soup's ``Singer(damping_coeff=α, noise_diff_coeff=q)``.

    Args:
        alpha: acceleration decay rate α (1/s), positive.
        q: spectral density of the driving white noise, positive; a float or a tensor whose shape is
            the parameter batch (...).
        dim: number of spatial axes (>= 1).
        **options: ``dtype``, ``device`` (of the parameters) and ``validate_args`` (see
            :class:`~torchsde_lti.LTISDE`).

    Returns:
        Singer: F (3·dim, 3·dim), state ``[x, v, a]`` per axis; learns alpha and q.
    """
    return Singer(alpha, q, dim, **options)


class IntegratedOU(DragSDE):
    """Velocity with drag integrated to position (see :func:`integrated_ou`)."""

    _order, _rate_name = 2, "k"


def integrated_ou(k: Scalar, q: Scalar, dim: int = 1, **options: Unpack[ModelOptions]) -> IntegratedOU:
    r"""Integrated Ornstein–Uhlenbeck per axis: ``dx = v dt``, ``dv = −k v dt + dβ``, ``E[dβ²] = q dt``.

    Stone Soup calls this ``OrnsteinUhlenbeck(damping_coeff=k, noise_diff_coeff=q)``.

    Args:
        k: velocity drag rate (1/s), positive.
        q: spectral density of the driving white noise, positive; a float or a tensor whose shape is
            the parameter batch (...).
        dim: number of spatial axes (>= 1).
        **options: ``dtype``, ``device`` (of the parameters) and ``validate_args`` (see
            :class:`~torchsde_lti.LTISDE`).

    Returns:
        IntegratedOU: F (2·dim, 2·dim), state ``[x, vx, y, vy, …]``; learns k and q.
    """
    return IntegratedOU(k, q, dim, **options)


class Moored(DragSDE):
    """A vessel at rest (see :func:`moored`): the drag chain with the noise on the positions."""

    _order, _rate_name = 2, "k"
    _pos: Tensor

    def __init__(self, k: Scalar, q: Scalar, dim: int = 2, **options: Unpack[ModelOptions]) -> None:
        super().__init__(k, q, dim, **options)
        pos = torch.zeros_like(self._top)
        for axis in range(dim):
            pos[axis * self._order, axis] = 1.0  # the axis's position (its first state)
        self.register_buffer("_pos", pos, persistent=False)

    def _noise_gain(self) -> Tensor:
        return self._pos


def moored(k: Scalar = 0.1, q: Scalar = 1e-3, dim: int = 2, **options: Unpack[ModelOptions]) -> Moored:
    r"""A vessel at rest: per axis ``dx = v dt + dβ_x``, ``dv = −k v dt`` (state ``[x, vx, y, vy]``).

    The velocity state decays with a strong rate k (any velocity inherited from another
    mode of an IMM bank dies out within a few 1/k), and the position wanders as a slow
    random walk of spectral density q (m²/s: drift at the mooring). Same state layout as
    :func:`constant_velocity` / :func:`integrated_ou`, so it can share an IMM bank with them.
    ``L`` selects the positions, ``Qc = q I_dim``.

    Args:
        k: velocity decay rate (1/s), positive.
        q: spectral density of the position random walk (m²/s), positive.
        dim: number of spatial axes (>= 1).
        **options: ``dtype``, ``device`` (of the parameters) and ``validate_args`` (see
            :class:`~torchsde_lti.LTISDE`).

    Returns:
        Moored: F (2·dim, 2·dim), state ``[x, vx, y, vy, …]``; learns k and q.
    """
    return Moored(k, q, dim, **options)


class OrnsteinUhlenbeck(StructuredSDE):
    """Mean-reverting position per axis (see :func:`ornstein_uhlenbeck`)."""

    theta: Tensor
    q: Tensor

    def __init__(self, theta: Scalar, q: Scalar, dim: int = 1, **options: Unpack[ModelOptions]) -> None:
        super().__init__(options.get("validate_args"))
        check_int(dim, "dim", 1)
        dtype, device = scalar_dtype_device([theta, q], options)
        self._add_positive("theta", theta, dtype, device)
        self._add_positive("q", q, dtype, device)
        self._check_scalars(("theta", "q"))
        self.dim = dim
        self.position_indices = tuple(range(dim))

    def _build(self) -> SDEMatrices:
        theta, q = self.theta, self.q
        batch = torch.broadcast_shapes(theta.shape, q.shape)
        F = eye_blocks(theta, self.dim, -theta.expand(batch))
        L = torch.eye(self.dim, dtype=F.dtype, device=F.device).expand(*batch, self.dim, self.dim)
        return SDEMatrices(F, L, eye_blocks(q, self.dim, q.expand(batch)), None)

    def extra_repr(self) -> str:
        return f"dim={self.dim}, " + self._scalar_repr(["theta", "q"])


def ornstein_uhlenbeck(theta: Scalar, q: Scalar, dim: int = 1, **options: Unpack[ModelOptions]) -> OrnsteinUhlenbeck:
    r"""Mean-reverting position per axis: ``dx = −θ x dt + dβ``, ``E[dβ dβᵀ] = q I dt``.

    ``A = e^{−θ dt} I``, ``Q = q (1 − e^{−2θ dt}) / (2θ) I``, ``P∞ = q / (2θ) I``.

    Args:
        theta: mean-reversion rate θ (1/s), positive.
        q: spectral density of the driving white noise, positive; a float or a tensor whose shape is
            the parameter batch (...).
        dim: number of spatial axes (>= 1).
        **options: ``dtype``, ``device`` (of the parameters) and ``validate_args`` (see
            :class:`~torchsde_lti.LTISDE`).

    Returns:
        OrnsteinUhlenbeck: F (dim, dim) = −θ I; learns theta and q.
    """
    return OrnsteinUhlenbeck(theta, q, dim, **options)
