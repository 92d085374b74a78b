r"""The Student-t predictive of a filter with ``noise=tl.StudentT(ν)``: density, HPD level, draws.

    mixture_t_log_prob(x, w, mu, S, dof)   # log Σ_j w_j St(x; mu_j, S_j, ν)
    t_hpd_level(maha, m, dof)              # P(D² <= maha) for D² the Mahalanobis² of a t draw
    t_draws(mu, Lz, dof, generator, comp)  # mu + L z sqrt(ν / g), g ~ χ²_ν

Such a filter's one-step predictive is ``St(y; H m⁻, S, ν)`` (one mode) or a mixture of them
with one ν or a ν per mode (an IMM; ``dof`` (M,)): :mod:`torchsde_lti.filters.noise`, where S
is the t's scale matrix.

HPD region: the density of ``St(mu, S, ν)`` in m dimensions falls with ``D² = (y − mu)ᵀ S⁻¹
(y − mu)``, and ``D² / m`` follows the F distribution F(m, ν), so the level of y (the mass
denser than at y) is the F CDF at ``D²/m``: ``I_z(m/2, ν/2)`` with ``z = D² / (D² + ν)``, the
regularised incomplete beta function (:func:`betainc`; for m = 2 in closed form,
``1 − (1 + D²/ν)^(−ν/2)``). The "2σ" level stays 1 − e⁻² = 86.5 %; its region for a t is the
ellipse ``D² ≤ m · F⁻¹(0.865; m, ν)``, wider than the Gaussian's ``D² ≤ 4`` (m = 2).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchsde_lti.filters.noise import log_gamma_ratio

__all__ = ["betainc", "mixture_t_log_prob", "t_draws", "t_hpd_level"]

#: The continued fraction's stopping test and its most iterations (it converges in
#: O(sqrt(max(a, b))) terms on the side of the symmetry split it is evaluated on).
_CF_TOL = 1e-15
_CF_MAX = 2000


def _log_beta(a: Tensor, b: Tensor) -> Tensor:
    """``log B(a, b)`` with b possibly large: ``lgamma(a) − (log Γ(b + a) − log Γ(b))``."""
    return torch.lgamma(a) - log_gamma_ratio(b, a) - a * torch.log(b)


def _beta_cf(a: Tensor, b: Tensor, x: Tensor) -> Tensor:
    """The continued fraction of ``I_x(a, b)`` (modified Lentz), for x < (a + 1)/(a + b + 2)."""
    tiny = torch.finfo(x.dtype).tiny * 1e10
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c = torch.ones_like(x)
    d = 1.0 - qab * x / qap
    d = 1.0 / torch.where(d.abs() < tiny, torch.full_like(d, tiny), d)
    h = d
    for i in range(1, _CF_MAX + 1):
        m2 = 2.0 * i
        for aa in (i * (b - i) * x / ((qam + m2) * (a + m2)), -(a + i) * (qab + i) * x / ((a + m2) * (qap + m2))):
            d = 1.0 + aa * d
            d = 1.0 / torch.where(d.abs() < tiny, torch.full_like(d, tiny), d)
            c = 1.0 + aa / c
            c = torch.where(c.abs() < tiny, torch.full_like(c, tiny), c)
            step = d * c
            h = h * step
        if i % 8 == 0 and bool(((step - 1.0).abs() <= _CF_TOL).all()):
            break
    return h


def betainc(a: Tensor, b: Tensor, x: Tensor) -> Tensor:
    """The regularised incomplete beta function ``I_x(a, b)`` elementwise (a, b > 0, x in [0, 1]).

    The continued fraction of Numerical Recipes §6.4 on the side of ``I_x(a, b) = 1 − I_{1−x}(b, a)``
    where it converges fast, its prefactor ``x^a (1 − x)^b / (a B(a, b))`` with a B(a, b) exact
    also for large b (:func:`~torchsde_lti.filters.noise.log_gamma_ratio`). Float64 to ~1e-14.
    """
    a, b, x = torch.broadcast_tensors(*(torch.as_tensor(v, dtype=torch.float64) for v in (a, b, x)))
    swap = x > (a + 1.0) / (a + b + 2.0)
    a2, b2 = torch.where(swap, b, a), torch.where(swap, a, b)
    x2 = torch.where(swap, 1.0 - x, x)
    inner = (x2 > 0) & (x2 < 1)
    xs = torch.where(inner, x2, torch.full_like(x2, 0.5))
    front = torch.exp(a2 * torch.log(xs) + b2 * torch.log1p(-xs) - _log_beta(a2, b2)) / a2
    r = torch.where(inner, front * _beta_cf(a2, b2, xs), torch.where(x2 >= 1, 1.0, 0.0).to(x2))
    return torch.where(swap, 1.0 - r, r)


def t_hpd_level(maha: Tensor, m: int, dof: Tensor | float) -> Tensor:
    """The HPD level of points with Mahalanobis² ``maha`` (N,) under an m-variate t with ν = ``dof``:
    ``P(D² ≤ maha) = I_z(m/2, ν/2)``, ``z = maha / (maha + ν)`` (module docstring); m = 2 in
    closed form."""
    nu = torch.as_tensor(dof, dtype=maha.dtype)
    if m == 2:
        return -torch.expm1(-0.5 * nu * torch.log1p(maha / nu))
    return betainc(torch.full_like(maha, m / 2.0), (0.5 * nu).expand_as(maha), maha / (maha + nu)).to(maha.dtype)


def mixture_t_log_prob(x: Tensor, w: Tensor, mu: Tensor, S: Tensor, dof: Tensor | float) -> Tensor:
    """``log Σ_j w_j St(x; mu_j, S_j, ν_j)`` of points x (N, m) or (N, D, m), shapes as
    :func:`~torchsde_lti.evaluation.mixture_log_prob`, S_j the t's scale matrices, ν one number
    or one per component (M,); elementwise over the m × m entries of the inverse."""
    squeeze = x.dim() == 2
    if squeeze:
        x = x.unsqueeze(1)
    m = x.shape[-1]
    nu = torch.as_tensor(dof, dtype=x.dtype)
    L = torch.linalg.cholesky(S)
    Sinv = torch.cholesky_inverse(L).unsqueeze(1)  # (N, 1, M, m, m)
    logdet = 2.0 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1).unsqueeze(1)  # (N, 1, M)
    d = x.unsqueeze(-2) - mu.unsqueeze(1)  # (N, D, M, m)
    quad = sum(d[..., i] * Sinv[..., i, j] * d[..., j] for i in range(m) for j in range(m))
    const = log_gamma_ratio(0.5 * nu, torch.tensor(0.5 * m, dtype=x.dtype)) - 0.5 * m * math.log(2 * math.pi)
    comp = const - 0.5 * logdet - 0.5 * (nu + m) * torch.log1p(quad / nu)
    out = torch.logsumexp(comp + torch.log(w.clamp_min(1e-300)).unsqueeze(1), -1)
    return out.squeeze(1) if squeeze else out


def t_draws(
    mu: Tensor, Lz: Tensor, dof: Tensor | float, generator: torch.Generator, comp: Tensor | None = None
) -> Tensor:
    """Draws ``mu + (L z) sqrt(ν / g)`` of a t from Gaussian draws ``L z`` (..., m) about 0:
    g ~ χ²_ν = 2 Gamma(ν/2) from ``generator`` (torch's gamma sampler, the one
    ``torch.distributions.Gamma`` uses, with a generator: seeded common random numbers).
    ν: one number, or one per mixture component (M,) with ``comp`` (...) the component of each
    draw (ν_comp)."""
    nu = torch.as_tensor(dof, dtype=Lz.dtype)
    if nu.dim():
        if comp is None:
            raise ValueError(f"t_draws: dof of shape {tuple(nu.shape)} is per component: pass comp")
        nu = nu[comp]
    alpha = (0.5 * nu).expand(Lz.shape[:-1]).contiguous()
    g = 2.0 * torch._standard_gamma(alpha, generator=generator)
    return mu + Lz * torch.sqrt(nu / g).unsqueeze(-1)
