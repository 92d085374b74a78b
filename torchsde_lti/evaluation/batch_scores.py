r"""Scores of a filter's output on one padded batch, differentiable where they are losses.

    kalman_k_step_nll(kf, out, y, observed, k, u)   # Σ_t -log p(y_{t+k} | y_0:t), exact steps
    imm_k_step_nll(imm, out, y, dt, observed, k)    # ... under the IMM's forecast mixture
    coverage_counts(y, w, mu, S, observed, dof)     # (inside, scored) of the 2σ coverage

The k-step-ahead predictive NLL scores y_{t+k} from the filtered state at t, pushed k reports
ahead: a KalmanFilter through the exact discrete model each step used (A_j, Q_j, G_j u_j), an
IMMFilter through its forecast mixture over the lead τ = t_{t+k} − t_t. At k = 1 both are the
filter's own prediction-error decomposition (the tests check it). The training module adds
them to its loss (``module.k_step``) and logs the coverage counts per epoch.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from torchsde_lti.evaluation.predictive import masked_gaussian_nll, mixture_log_prob
from torchsde_lti.evaluation.scores import hpd_inside
from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import KalmanFilter

__all__ = ["coverage_counts", "imm_k_step_nll", "kalman_k_step_nll"]


def kalman_k_step_nll(
    kf: KalmanFilter, out: Any, y: Tensor, observed: Tensor, k: int, u: Tensor | None = None
) -> Tensor:
    """Σ over origins t of -log p(y_{t+k} | y_0:t) of a Kalman filter.

    Each step's exact (A_j, Q_j) and input term G_j u_j, as the filter used them
    (``out.transition``, ``out.process_noise``, ``out.control``): m ← A m + G u,
    P ← A P Aᵀ + Q for j = t+1 .. t+k (zero-dt padding steps are identities); the target is
    scored in its observed coordinates against ``N(H m + D u, H P Hᵀ + R)`` (D u where the filter
    has a feedthrough D and ``u`` is given).

    Args:
        kf: the filter; out: its KalmanResult on (y, dt, u).
        y: (B, T, m) observations; observed: (B, T, m) bool.
        k: horizon in reports (>= 1); u: (B, T, p) inputs or None.

    Returns:
        A scalar (0 when T <= k).
    """
    T = y.shape[-2]
    if k < 1 or T <= k:
        return y.new_zeros(())
    A, Q, c = out.transition, out.process_noise, out.control  # (B, T, n, n), (B, T, n)
    m, P = out.mean[..., : T - k, :], out.cov[..., : T - k, :, :]
    for j in range(1, k + 1):
        Aj, Qj = A[..., j : T - k + j, :, :], Q[..., j : T - k + j, :, :]
        m = (Aj @ m.unsqueeze(-1)).squeeze(-1) + c[..., j : T - k + j, :]
        P = Aj @ P @ Aj.mT + Qj
    H, R = kf.H, kf.R
    obs_k = observed[..., k:, :]
    Du = kf.feedthrough(u)
    target = y[..., k:, :] if Du is None else y[..., k:, :] - Du[..., k:, :]
    target = torch.where(obs_k, target, torch.zeros_like(target))
    return masked_gaussian_nll(target - m @ H.mT, H @ P @ H.mT + R, obs_k).sum()


def imm_k_step_nll(imm: IMMFilter, out: Any, y: Tensor, dt: Tensor, observed: Tensor, k: int) -> Tensor:
    """Σ over origins t of -log p(y_{t+k} | y_0:t) under the IMM's forecast mixture.

    From the filtered (mode probabilities, mode means, mode covariances) at t, the mixture
    at lead τ = Σ dt_{t+1..t+k} (``imm.forecast``: ``c = μ expm(Λ τ)`` and each mode's exact
    moments at τ, switches within τ included) is ``Σ_j c_j N(ŷ_j, H_j P_j H_jᵀ + R_j)``; only targets with every
    component observed count (padding has dt = 0 and is unobserved).

    Args:
        imm: the filter; out: its IMMResult on (y, dt); y: (B, T, m); dt: (B, T);
        observed: (B, T, m) bool; k: horizon in reports (>= 1).

    Returns:
        A scalar (0 when T <= k).
    """
    T = y.shape[-2]
    if k < 1 or T <= k:
        return y.new_zeros(())
    cs = torch.cumsum(dt, dim=-1)
    lead = (cs[..., k:] - cs[..., : T - k]).detach()  # (B, T - k)
    state = (
        out.mode_probabilities[..., : T - k, :],
        out.mode_mean[..., : T - k, :, :],
        out.mode_cov[..., : T - k, :, :, :],
    )
    fc = imm.forecast(state, lead.unsqueeze(-1))
    w, mu, S = fc.mode_probabilities[..., 0, :], fc.mode_obs_mean[..., 0, :, :], fc.mode_obs_cov[..., 0, :, :, :]
    ok = observed[..., k:, :].all(-1)  # (B, T - k)
    target = torch.where(ok.unsqueeze(-1), y[..., k:, :], mu[..., 0, :].detach())
    origins = ok.dim()  # (mixture_log_prob takes one batch dim: the origins flattened)
    flat = [x.expand(*ok.shape, *x.shape[origins:]).flatten(0, origins - 1) for x in (target, w, mu, S)]
    ll = mixture_log_prob(*flat).reshape(ok.shape)  # log Σ_j w_j N(y; ŷ_j, S_j) per origin
    return -(ll * ok).sum()


def coverage_counts(
    y: Tensor, w: Tensor, mu: Tensor, S: Tensor, observed: Tensor, dof: Tensor | None
) -> tuple[Tensor, Tensor]:
    """(reports inside, reports scored) of the 2σ coverage of one batch.

    Every report after its window's first (which holds the prior) with a coordinate observed,
    tested in its observed coordinates against the predictive mixture (w, mu, S) by
    :func:`~torchsde_lti.evaluation.hpd_inside`, one pattern of observed coordinates at a time.

    Args:
        y: (..., T, m); w, mu, S: the predictive (:func:`batch_predictive`);
        observed: (..., T, m) bool; dof: ν of a Student-t filter's predictive, or None.

    Returns:
        Two 0-dim tensors: the count inside (float64) and the count scored.
    """
    scored = observed.any(-1)
    scored[..., 0] = False
    m = y.shape[-1]
    pattern = (observed.long() << torch.arange(m, device=y.device)).sum(-1)
    inside = torch.zeros((), dtype=torch.float64, device=y.device)
    for code in torch.unique(pattern[scored]).tolist():
        rows = scored & (pattern == code)
        idx = torch.tensor([i for i in range(m) if code >> i & 1], device=y.device)
        sel = hpd_inside(y[rows][:, idx], w[rows], mu[rows][..., idx], S[rows][..., idx, :][..., idx], dof=dof)
        inside = inside + sel.sum()
    return inside, scored.sum()
