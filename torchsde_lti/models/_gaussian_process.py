r"""Gaussian processes as SDEs: the Matérn family with half-integer smoothness."""

from __future__ import annotations

import math

import torch
from torch import Tensor
from typing_extensions import Unpack

from torchsde_lti.models._common import ModelOptions, Scalar, scalar_dtype_device
from torchsde_lti.nn.parametrizations import integrator_chain
from torchsde_lti.nn.sde import SDEMatrices, StructuredSDE

__all__ = ["matern"]

_MATERN_NU = (0.5, 1.5, 2.5)


class Matern(StructuredSDE):
    """State-space Matérn-ν Gaussian process (see :func:`matern`)."""

    lengthscale: Tensor
    variance: Tensor
    _chain: Tensor
    _top: Tensor
    _binom: Tensor
    _powers: Tensor

    def __init__(self, nu: float, lengthscale: Scalar, variance: Scalar, **options: Unpack[ModelOptions]) -> None:
        super().__init__(options.get("validate_args"))
        try:
            nu_f = float(nu)
        except (TypeError, ValueError):
            raise ValueError(f"nu must be one of 1/2, 3/2, 5/2, got {nu!r}") from None
        match = [v for v in _MATERN_NU if abs(nu_f - v) < 1e-12]
        if not match:
            raise ValueError(f"nu must be one of 1/2, 3/2, 5/2, got {nu!r}")
        self.nu = match[0]
        self.order = int(self.nu + 0.5)
        dt_, dev = scalar_dtype_device([lengthscale, variance], options)
        self._add_positive("lengthscale", lengthscale, dt_, dev)
        self._add_positive("variance", variance, dt_, dev)
        self._check_scalars(("lengthscale", "variance"))
        m = self.order
        chain, top = integrator_chain(m, 1, dt_, dev)  # one axis: [f, f', …], top = e_m
        self.register_buffer("_chain", chain, persistent=False)
        self.register_buffer("_top", top, persistent=False)
        self.register_buffer(
            "_binom", torch.tensor([float(math.comb(m, j)) for j in range(m)], dtype=dt_, device=dev), persistent=False
        )
        self.register_buffer("_powers", torch.arange(m, 0, -1, dtype=dt_, device=dev), persistent=False)  # m−j
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
        # Qc = c σ² λ^{2ν} in logs, capped below the dtype's largest number (/16: room for the
        # discretisation's sums): finite for any finite raw lengthscale and variance
        top = math.log(torch.finfo(lam.dtype).max / 16.0)
        log_qc = math.log(self._qc_const) + torch.log(var.expand(batch)) + 2.0 * self.nu * torch.log(lam)
        qc = torch.exp(log_qc.clamp_max(top))
        L = self._top.expand(*batch, m, 1)
        return SDEMatrices(F, L, qc[..., None, None], None)

    def kernel(self, tau: Tensor) -> Tensor:
        """Closed-form Matérn covariance ``k(τ)``; ``tau`` broadcasts against the batch."""
        lam, var = self.rate, self.variance
        r = lam * tau.abs()
        poly: dict[float, Tensor | float] = {0.5: 1.0, 1.5: 1.0 + r, 2.5: 1.0 + r + r**2 / 3.0}
        return var * poly[self.nu] * torch.exp(-r)

    def extra_repr(self) -> str:
        return f"nu={self.nu}, " + self._scalar_repr(["lengthscale", "variance"])


def matern(nu: float, lengthscale: Scalar = 1.0, variance: Scalar = 1.0, **options: Unpack[ModelOptions]) -> Matern:
    r"""Matérn-ν Gaussian process as an SDE (ν ∈ {1/2, 3/2, 5/2}), state ``[f, f', …]``.

    With ``λ = √(2ν)/ℓ`` and ``m = ν + 1/2`` states, F is the companion matrix of
    ``(d/dt + λ)^m`` (last row ``−C(m, j) λ^{m−j}``, j = 0…m−1), ``L = e_m`` and
    ``Qc = 2σ² √π λ^{2ν} Γ(ν+½)/Γ(ν)`` (2σ²λ, 4σ²λ³, 16σ²λ⁵/3). Its stationary covariance
    P∞ gives exactly the Matérn kernel: ``k(τ) = H expm(F τ) P∞ Hᵀ`` with ``H = e_1ᵀ``, e.g.
    ``σ² (1 + λτ) e^{−λτ}`` for ν = 3/2 (``model.kernel(tau)``).

    Args:
        nu: smoothness ν, one of 0.5, 1.5, 2.5.
        lengthscale: ℓ, positive.
        variance: σ², positive.
        **options: ``dtype``, ``device`` (of the parameters) and ``validate_args`` (see
            :class:`~torchsde_lti.LTISDE`).

    Returns:
        Matern: F (m, m) with m = ν + ½ states; learns lengthscale and variance.
    """
    return Matern(nu, lengthscale, variance, **options)
