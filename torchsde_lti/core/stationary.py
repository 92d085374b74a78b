"""Stationary covariance of a stable LTI SDE: the continuous Lyapunov equation."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsde_lti.core.linalg import sym
from torchsde_lti.core.validation import check_hurwitz, checks_values, sde_inputs

__all__ = ["stationary_covariance"]


def stationary_covariance(F: Tensor, L: Tensor, Qc: Tensor, *, validate_args: bool = True) -> Tensor:
    r"""P∞ solving ``F P∞ + P∞ Fᵀ + L Qc Lᵀ = 0`` for Hurwitz-stable F.

    Solved as the linear system ``(F ⊗ I + I ⊗ F) vec(P∞) = -vec(L Qc Lᵀ)`` (row-major vec),
    batched and differentiable; the result is symmetrised. P∞ is the limit of the
    discrete Q as dt → ∞ and the covariance a "shaping filter" starts from.

    Args:
        F: (..., n, n) drift; every eigenvalue must have a negative real part.
        L: (..., n, s); Qc: (..., s, s) symmetric PSD.
        validate_args: check the values (finite, Qc PSD, F Hurwitz); shapes are always checked.

    Returns:
        (..., n, n) symmetric PSD, batch broadcast from F, L, Qc.

    Raises:
        ValueError: (with ``validate_args``) when F is not Hurwitz (naming its rightmost eigenvalue).
    """
    inputs = sde_inputs(F, L, Qc, validate_args=validate_args)
    F, W = inputs.F, inputs.W
    assert W is not None
    n = F.shape[-1]
    if checks_values(validate_args):
        check_hurwitz(F)
    batch = torch.broadcast_shapes(F.shape[:-2], W.shape[:-2])
    F = F.expand(*batch, n, n)
    eye = torch.eye(n, dtype=F.dtype, device=F.device)
    # (F ⊗ I)[(i,k),(j,l)] = F[i,j] δ[k,l];  (I ⊗ F)[(i,k),(j,l)] = δ[i,j] F[k,l]
    system = torch.einsum("...ij,kl->...ikjl", F, eye) + torch.einsum("ij,...kl->...ikjl", eye, F)
    system = system.reshape(*batch, n * n, n * n)
    rhs = -W.expand(*batch, n, n).reshape(*batch, n * n, 1)
    P = torch.linalg.solve(system, rhs).reshape(*batch, n, n)
    return sym(P)
