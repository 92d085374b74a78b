r"""Exact forecast moments of the switching SDE an IMM filters (no observation in between).

Between reports the IMM's model is a Markov jump linear SDE: ``dx = F_{r_t} x dt + L_{r_t} dβ``
with the mode r_t a continuous-time Markov chain of generator Λ (Λ_ij the rate of jumping from
i to j). From the filtered mixture (μ_j, m_j, P_j) its mode-weighted moments
``p_j = P(r_t = j)``, ``q_j = E[x_t 1{r_t = j}]``, ``S_j = E[x_t x_tᵀ 1{r_t = j}]`` solve the
linear ODEs (Costa, Fragoso & Todorov 2013, *Continuous-Time Markov Jump Linear Systems*, §3)::

    ṗ_j = Σ_i Λ_ij p_i,   q̇_j = F_j q_j + Σ_i Λ_ij q_i,   Ṡ_j = F_j S_j + S_j F_jᵀ + p_j W_j + Σ_i Λ_ij S_i,

W_j = L_j Qc_j L_jᵀ, so over a horizon h they are ``expm(𝒢 h)`` of their initial values
(:func:`~torchsde_lti.core.transition_apply`: no matrix per forecast). Mode j's forecast is
then ``c_j = p_j``, ``m_j = q_j / p_j``, ``P_j = S_j / p_j − m_j m_jᵀ``: the exact first and
second moments of the state given the mode at the horizon (the mixture's too), where the
IMM's own prediction (:func:`~torchsde_lti.filters.imm_predict`) mixes once at the start and
lets the mode at the horizon govern the whole of it — exact only when no switch occurs, and
increasingly wrong for horizons beyond the modes' sojourn times. With one mode, or no
switching, the two agree.

Student-t modes (:mod:`~torchsde_lti.filters.noise`) carry scale matrices: the moments are
propagated as covariances ``r_j P_j`` with the process noise ``r_j W_j`` (the limit of the
t-IMM's prediction, which adds Q to the scale, over vanishing steps) and returned as scales.
Computed in float64 and returned in the state's dtype: ``S_j / p_j − m_j m_jᵀ`` loses about
``|x|² · 1e-16`` to cancellation (1e-6 m² at coordinates of 100 km; centre coordinates of
the size of the Earth's radius first, as the data loaders do).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchsde_lti.core import transition_apply
from torchsde_lti.core.linalg import sym
from torchsde_lti.core.validation import checks_values
from torchsde_lti.filters.imm import IMMPrediction, combine
from torchsde_lti.filters.noise import GAUSSIAN, NoiseModel

__all__ = ["imm_forecast"]


def _per_mode_factor(noise: NoiseModel, M: int, like: Tensor) -> Tensor:
    """r (..., M): each mode's covariance per unit scale matrix (1 for Gaussian modes)."""
    r = noise.covariance_factor()
    if r is None:
        w = noise.spread()
        r = None if w is None else 1.0 / w.unsqueeze(-1)
    return (
        torch.ones(M, dtype=like.dtype, device=like.device) if r is None else r.to(like.dtype).expand(*r.shape[:-1], M)
    )


def _packing(n: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """(upper, full) of symmetric n × n matrices: ``upper`` (n(n+1)/2,) the row-major positions of
    the upper triangle (``vech S = vec(S)[upper]``), ``full`` (n²,) the vech position of every entry
    (``vec S = vech(S)[full]``)."""
    rows, cols = torch.triu_indices(n, n, device=device)
    index = torch.zeros(n, n, dtype=torch.long, device=device)
    index[rows, cols] = torch.arange(rows.numel(), device=device)
    return rows * n + cols, torch.maximum(index, index.mT).reshape(-1)


def _generator(F: Tensor, W: Tensor, rates: Tensor, upper: Tensor, full: Tensor) -> Tensor:
    """𝒢 (..., D, D) of the moment vector ``z = [p (M) | q (M n) | vech S (M n(n+1)/2)]``
    (vech: the upper triangle, row-major, :func:`_packing`'s upper and full), D = M (1 + n +
    n(n+1)/2): F (..., M, n, n), W (..., M, n, n) (covariance units), rates (..., M, M)."""
    M, n = F.shape[-3], F.shape[-1]
    t = upper.numel()
    eye_m = torch.eye(M, dtype=F.dtype, device=F.device)
    eye_n = torch.eye(n, dtype=F.dtype, device=F.device)
    batch = torch.broadcast_shapes(F.shape[:-3], W.shape[:-3], rates.shape[:-2])

    def blocks(diag: Tensor, k: int) -> Tensor:  # blockdiag_j(diag_j) + Λᵀ ⊗ I_k: (..., M k, M k)
        out = torch.einsum("ij,...iab->...iajb", eye_m, diag) + torch.einsum(
            "...ji,ab->...iajb", rates, torch.eye(k, dtype=F.dtype, device=F.device)
        )
        return out.reshape(*out.shape[:-4], M * k, M * k)

    # vec(F S + S Fᵀ) = (F ⊗ I + I ⊗ F) vec S (row-major vec), on vech: its upper rows, the
    # columns of an entry and its mirror summed
    kron_sum = torch.einsum("...ac,bd->...abcd", F, eye_n) + torch.einsum("ac,...bd->...abcd", eye_n, F)
    kron_sum = kron_sum.reshape(*F.shape[:-2], n * n, n * n)[..., upper, :]
    duplicate = torch.zeros(n * n, t, dtype=F.dtype, device=F.device)
    duplicate[torch.arange(n * n, device=F.device), full] = 1.0
    Gq, Gs = blocks(F, n), blocks(kron_sum @ duplicate, t)
    source = torch.einsum("ij,...ia->...iaj", eye_m, W.flatten(-2)[..., upper]).reshape(*W.shape[:-3], M * t, M)
    D = M * (1 + n + t)
    rows = [
        torch.cat([rates.mT.expand(*batch, M, M), rates.new_zeros(*batch, M, D - M)], -1),
        torch.cat(
            [F.new_zeros(*batch, M * n, M), Gq.expand(*batch, M * n, M * n), F.new_zeros(*batch, M * n, M * t)], -1
        ),
        torch.cat(
            [source.expand(*batch, M * t, M), F.new_zeros(*batch, M * t, M * n), Gs.expand(*batch, M * t, M * t)], -1
        ),
    ]
    return torch.cat(rows, -2)


def imm_forecast(
    prob: Tensor,
    mean: Tensor,
    cov: Tensor,
    F: Tensor,
    W: Tensor,
    rates: Tensor,
    horizons: Tensor,
    noise: NoiseModel = GAUSSIAN,
    validate_args: bool = False,
) -> IMMPrediction:
    """The exact mode-conditional moments of the switching SDE at each horizon (module docstring).

    Args:
        prob: (..., M) mode probabilities; mean: (..., M, n); cov: (..., M, n, n) (scale
            matrices for Student-t modes).
        F: (M, n, n) the modes' drifts; W: (M, n, n) their L Qc Lᵀ; rates: (M, M) the generator Λ
            (rows summing to 0); each may lead with batch dims of its own (parameters per
            element: one generator each).
        horizons: (..., K) non-negative, each measured from the state's time.
        noise: the modes' noise model (:class:`~torchsde_lti.filters.GaussianNoise` or a
            :class:`~torchsde_lti.filters.StudentTNoise` of the model, without the K axis).

    Arguments are taken as checked (:meth:`~torchsde_lti.IMMFilter.forecast` checks them);
    ``validate_args``: a moment that overflows float64 (a horizon too long for an unstable or
    fast-growing mode), or mode probabilities whose total (conserved exactly) drifts by more
    than √eps (the ~2^digits eps of as many squarings: horizons beyond about 10⁷ of the model's
    fastest time scale) raise ValueError.

    Returns:
        :class:`~torchsde_lti.filters.IMMPrediction` with a K axis after the batch: c (..., K, M),
        the modes' means and covariances (scales) and their moment-matched mixture. A mode whose
        probability is ≤ √tiny of the dtype gets weight 0 and moments 0, as in the IMM's mixing.
    """
    out_dtype, work = cov.dtype, torch.float64
    prob, mean, cov, F, W, rates, horizons = (t.to(work) for t in (prob, mean, cov, F, W, rates, horizons))
    M, n = F.shape[-3], F.shape[-1]
    r = _per_mode_factor(noise, M, cov)  # (..., M)
    second = prob[..., None, None] * (cov * r[..., None, None] + mean.unsqueeze(-1) * mean.unsqueeze(-2))
    upper, full = _packing(n, F.device)
    z0 = torch.cat([prob, (prob.unsqueeze(-1) * mean).flatten(-2), second.flatten(-2)[..., upper].flatten(-2)], -1)
    G = _generator(F, W * r[..., None, None], rates, upper, full)  # (..., D, D)
    # (the arguments are checked; the moments are checked below)
    z = transition_apply(G.unsqueeze(-3) if G.dim() > 2 else G, horizons, z0.unsqueeze(-2), validate_args=False)
    p, q, S = z.split([M, M * n, M * upper.numel()], -1)  # (..., K, ·)
    if checks_values(validate_args) and z.numel():  # one synchronisation
        with torch.no_grad():  # Σ p is conserved exactly: its drift measures what the squarings lost
            total_drift = (p.sum(-1) - prob.sum(-1, keepdim=True)).abs().amax()
            finite, drift = torch.stack([torch.isfinite(z).all().to(work), total_drift]).tolist()
        if not finite:
            raise ValueError(
                f"the forecast overflows float64 for horizons up to {float(horizons.detach().max()):.3g} (an unstable "
                "or fast-growing mode): shorten them"
            )
        if not drift <= math.sqrt(torch.finfo(work).eps):
            raise ValueError(
                f"the forecast over horizons up to {float(horizons.detach().max()):.3g} loses accuracy: the mode "
                f"probabilities' total drifts by {drift:.2g} after squaring the moment system that often in float64; "
                "forecast over shorter horizons"
            )
    q, S = q.unflatten(-1, (M, n)), S.unflatten(-1, (M, upper.numel()))[..., full].unflatten(-1, (n, n))
    pos = p > math.sqrt(torch.finfo(p.dtype).tiny)
    safe = torch.where(pos, p, torch.ones_like(p))
    m = q / safe.unsqueeze(-1)
    P = (S / safe[..., None, None] - m.unsqueeze(-1) * m.unsqueeze(-2)) / r.unsqueeze(-2)[..., None, None]
    m = torch.where(pos.unsqueeze(-1), m, torch.zeros_like(m))
    P = torch.where(pos[..., None, None], sym(P), torch.zeros_like(P))
    c = torch.where(pos, p, torch.zeros_like(p))
    c = c / c.sum(-1, keepdim=True)
    x, P_mix = combine(c, m, P, noise.with_axis())
    return IMMPrediction(*(t.to(out_dtype) for t in (c, m, P, x, P_mix)))
