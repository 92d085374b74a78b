r"""Fixed-interval IMM smoother: a two-filter smoother whose backward filter is an information
filter per mode, over the IMM filter's mode-matched moments, collapsed as in Kim (1994).

The model is the IMM filter's (:mod:`torchsde_lti.filters.imm`): a mode chain with
``P(s_{k+1} = j | s_k = i) = Pi_{k+1}[i, j]`` (``expm(Λ dt_{k+1})`` for a continuous-time chain)
and, given the mode s_{k+1} = j, ``x_{k+1} = A_{k+1,j} x_k + q``, ``q ~ N(0, Q_{k+1,j})``,
``y_{k+1} = H_{k+1,j} x_{k+1} + r``, ``r ~ N(0, R_{k+1,j})``. The exact smoothed posterior is a
mixture over all M^T mode histories; this smoother keeps M Gaussians per step, as the filter does.

Backward over k = T−2 … 0, from the IMM filter's μ_k(i), m_k(i), P_k(i):

1. backward information filter of each mode j (Fraser & Potter 1969; the two-filter IMM
   smoother of Helmick, Blair & Hoffman 1995, IEEE Trans. Inf. Theory 41(5), in information
   form): the information (Λ_j, η_j) that y_{k+1}, y_{k+2}, … carry about x_{k+1} given
   s_{k+1} = j (its report's ``H_jᵀ R_j⁻¹ H_j``, ``H_jᵀ R_j⁻¹ y_{k+1}``, plus the message from
   k+2) is pushed back through mode j's dynamics, ``Λ'_j = A_jᵀ (I + Λ_j Q_j)⁻¹ Λ_j A_j``,
   ``η'_j = A_jᵀ (I + Λ_j Q_j)⁻¹ η_j``, in square-root form (Λ'_j = G_j G_jᵀ, η'_j = G_j z_j;
   no inverse of Λ, singular until the reports fix every component, nor of A or Q);
2. pairs (two-filter formula): x_k given s_k = i, s_{k+1} = j and every report is the filtered
   N(m_k(i), P_k(i)) times ``exp(−½ |G_jᵀ x − z_j|²)``, a Kalman update in Joseph form, so
   ``P_ij ≤ P_k(i)`` by construction; its normaliser Z_ij is the evidence of the later reports
   under the pair;
3. modes: the identity ``P(s_k = i | s_{k+1} = j, y) ∝ P(s_k = i | y_{0:k}) Π_ij
   p(y_{k+1:} | s_k = i, s_{k+1} = j, y_{0:k})`` with these Gaussians: ∝ μ_k(i) Π_ij Z_ij,
   ``q_ij = μ^s_{k+1}(j) P(s_k = i | s_{k+1} = j, y)``, μ^s_k(i) = Σ_j q_ij, w_{j|i} = q_ij / μ^s_k(i)
   (Kim's recursion, ``q_ij ∝ μ_k(i) Π_ij μ^s_{k+1}(j) / c_j``, is the case Z_ij = 1);
4. collapse (Kim 1994, "Dynamic linear models with Markov-switching", J. Econometrics 60):
   m^s_k(i) = Σ_j w_{j|i} m_ij, P^s_k(i) = Σ_j w_{j|i} (P_ij + (m_ij − m^s_k(i))(…)ᵀ), the output
   Σ_i μ^s_k(i) N(m^s_k(i), P^s_k(i)) moment-matched; the message of mode i to step k−1 is the
   w-weighted average of the (Λ'_j, η'_j) (an average of PSD informations).

Why this form, for continuous-time switching with ``expm(Λ dt)`` per gap: it needs only what the
forward filter used, Pi_k and (A, Q, H, R) of each gap (dt = 0 included: Pi = I, A = I, Q = 0).
Helmick et al.'s and Nadarajah et al.'s (2012) backward IMMs mix backward *densities*, which
needs a prior of x at every step (constant velocity and integrated OU have no stationary
covariance) and a time-reversed chain; an information filter needs neither. Kim's own state
step (an RTS step of each pair against the smoothed density of mode j at k+1, a mixture over
all predecessors) inverts a mode's dynamics: where a mode contracts a component without noise
(the shipped ``moored`` mode: velocity decays at rate k, no velocity noise) it maps the other
predecessors' spread back by ``e^{k dt}`` a step; on a recorded AIS track with ``ais-us-imm`` it
reached covariances of 1e101 m² and a mean 1e129 m off. Kim's mode weights (Z_ij = 1) were
measured too: against the exact mixture on the test problems their smoothed mode probabilities
were 0.08–0.26 off where these are 0.007–0.12 off.

Approximations: the filter's (one Gaussian per mode), one Gaussian-shaped message per mode (the
successors' information averaged), the collapse. Exact for one mode (the RTS smoother),
identical modes and a chain that never switches (Λ = 0: each mode's smoother weighted by its
likelihood); ``tests/filters/test_imm_smoother.py`` measures the rest against the mixture over
all mode histories.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core.linalg import matvec, sym
from torchsde_lti.filters.imm import IMMResult, combine
from torchsde_lti.filters.layout import lower_solve, psd_cholesky, psd_solve
from torchsde_lti.filters.results import serializable

__all__ = ["IMMSmootherResult", "imm_smoother"]


@serializable
class IMMSmootherResult(NamedTuple):
    """Output of :func:`imm_smoother` (given every report y_0 … y_{T−1}).

    mean: (..., T, n) smoothed mean E[x_k | y] of the moment-matched mixture.
    cov: (..., T, n, n) its covariance.
    mode_probabilities: (..., T, M) smoothed P(s_k = j | y).
    mode_mean: (..., T, M, n) E[x_k | s_k = j, y]; mode_cov: (..., T, M, n, n) the covariances.
    """

    mean: Tensor
    cov: Tensor
    mode_probabilities: Tensor
    mode_mean: Tensor
    mode_cov: Tensor


def _model(x: Tensor | None, stored: Tensor | None, name: str, event: tuple[int, ...], full: tuple[int, ...]) -> Tensor:
    """A, Q, Pi, H or R as passed (or as stored in the result), broadcast to ``full`` = (*batch,
    T, *event); ValueError naming it and the shapes where it does not broadcast."""
    if x is None:
        if stored is None:
            raise ValueError(
                f"result has no {name} (an IMMResult of an earlier version): pass {name} of shape "
                f"(..., T, {', '.join(map(str, event))})"
            )
        x = stored
    x = torch.as_tensor(x)
    try:
        return x.expand(full)
    except RuntimeError:
        raise ValueError(
            f"{name} of shape ({', '.join(map(str, x.shape))}) does not broadcast to the filter result's "
            f"(..., T, {', '.join(map(str, event))}) = ({', '.join(map(str, full))})"
        ) from None


def _report_information(result: IMMResult, H: Tensor, R: Tensor) -> tuple[Tensor, Tensor]:
    """Each step's and mode's report as information about x_k: ``U = H_oᵀ R_oo⁻¹ H_o`` (..., T,
    M, n, n) and ``u = H_oᵀ R_oo⁻¹ y_o`` (..., T, M, n) over the observed components o (the
    filter's convention: unobserved rows of H zero, decoupled unit variances in R; 0 for a
    missing report). y_o is read back from the filter: ``innovation_j + H_j m⁻_j``."""
    obs = result.observed.unsqueeze(-2)  # (..., T, 1, m)
    H = torch.where(obs.unsqueeze(-1), H, torch.zeros_like(H))
    both = obs.unsqueeze(-1) & obs.unsqueeze(-2)
    eye = torch.eye(R.shape[-1], dtype=R.dtype, device=R.device)
    R = torch.where(both, R, eye)
    y = result.mode_innovation + matvec(H, result.mode_pred_mean)  # (..., T, M, m): 0 where unobserved
    X = psd_solve(R, H, R.dim() - 2)  # R⁻¹ H
    return sym(H.mT @ X), matvec(X.mT, y)


def _message_factor(Lam: Tensor, eta: Tensor, A: Tensor, Q: Tensor) -> tuple[Tensor, Tensor]:
    """The information (Λ, η) about x_{k+1} (given its mode) as information about x_k through that
    mode's x_{k+1} = A x_k + q, q ~ N(0, Q), in square-root form: Lam, A, Q (..., n, n), eta (..., n).

    Returns (G (..., n, n), z (..., n)) with ``Λ' = G Gᵀ = Aᵀ (I + Λ Q)⁻¹ Λ A`` and
    ``η' = G z = Aᵀ (I + Λ Q)⁻¹ η``: with Λ = C Cᵀ (semi-definite Cholesky: Λ is singular until
    the reports fix every component), z₀ = C⁻¹ η (0 in a zero pivot's component), S = I + Cᵀ Q C
    = L_S L_Sᵀ (≥ I): G = Aᵀ C L_S⁻ᵀ and z = L_S⁻¹ z₀. No inverse of Λ, Q or A; Λ' is PSD by
    construction, and ``exp(−½ xᵀ Λ' x + η'ᵀ x) = exp(−½ |Gᵀ x − z|²)`` up to a constant."""
    n, at = Lam.shape[-1], Lam.dim() - 2
    eye = torch.eye(n, dtype=Lam.dtype, device=Lam.device)
    C, d = psd_cholesky(Lam, at)  # (d = 0 at a zero pivot: that component of z₀ is 0)
    z0 = lower_solve(C, d, eta.unsqueeze(-1), 0)
    L_S, d_S = psd_cholesky(sym(eye + C.mT @ Q @ C), at)
    G = A.mT @ lower_solve(L_S, d_S, C.mT, 0).mT  # Aᵀ C L_S⁻ᵀ
    return G, lower_solve(L_S, d_S, z0, 0).squeeze(-1)


def _pair_update(mean: Tensor, cov: Tensor, G: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """N(mean, cov) times ``exp(−½ |Gᵀ x − z|²)``: the Kalman update with the pseudo-report z of
    Gᵀ x with unit noise. mean (..., n), cov, G (..., n, n), z (..., n).

    S = I + Gᵀ P G (≥ I), K = P G S⁻¹, m⁺ = m + K (z − Gᵀ m), P⁺ = (I − K Gᵀ) P (I − K Gᵀ)ᵀ + K Kᵀ
    (Joseph form: PSD and ≤ P). Returns (m⁺, P⁺, log Z) with ``log Z = −½ log det S − ½ rᵀ S⁻¹ r``
    (r = z − Gᵀ m): the log of ∫ N(x; m, P) exp(−½ |Gᵀ x − z|²) dx up to a constant of (G, z)."""
    n, at = cov.shape[-1], cov.dim() - 2
    eye = torch.eye(n, dtype=cov.dtype, device=cov.device)
    PG = cov @ G
    S = sym(eye + G.mT @ PG)
    L, d = psd_cholesky(S, at)  # (d_j = 1 / L_jj)
    K = psd_solve(S, PG.mT, at).mT
    r = z - matvec(G.mT, mean)
    IKG = eye - K @ G.mT
    P = sym(IKG @ cov @ IKG.mT + K @ K.mT)
    white = lower_solve(L, d, r.unsqueeze(-1), 0).squeeze(-1)
    log_z = torch.log(d).sum(-1) - 0.5 * (white * white).sum(-1)
    return mean + matvec(K, r), P, log_z


def _mode_pairs(mu: Tensor, Pi: Tensor, log_z: Tensor, mu_next: Tensor) -> tuple[Tensor, Tensor]:
    """The smoothed mode pairs. mu (..., M) filtered μ_k, Pi (..., M, M) = Pi_{k+1}, log_z
    (..., M_i, M_j) each pair's evidence of the later reports (up to a constant of j), mu_next
    (..., M) smoothed μ^s_{k+1}.

    ``P(s_k = i | s_{k+1} = j, y) ∝ μ_k(i) Π_ij Z_ij`` (a softmax over i; a pair with
    μ_k(i) Π_ij = 0 has probability 0), ``q_ij = μ^s_{k+1}(j) P(s_k = i | s_{k+1} = j, y)``.
    Returns μ^s_k (..., M) = Σ_j q_ij and w (..., M_i, M_j) = q_ij / μ^s_k(i) (rows summing to 1;
    a mode of smoothed probability ≤ sqrt(tiny) gets w_{j|i} = Π_ij: its moments carry no weight,
    and no gradient divides by a number whose square underflows)."""
    joint = mu.unsqueeze(-1) * Pi
    pos = joint > 0
    logits = torch.where(pos, torch.log(torch.where(pos, joint, torch.ones_like(joint))) + log_z, -torch.inf)
    reach = pos.any(-2, keepdim=True)  # (..., 1, M_j): a successor some mode reaches (else μ^s_{k+1}(j) = 0)
    logits = torch.where(reach, logits, torch.zeros_like(logits))
    q = torch.softmax(logits, dim=-2) * mu_next.unsqueeze(-2)
    prob = q.sum(-1)
    tiny = math.sqrt(torch.finfo(mu.dtype).tiny)
    ok = prob > tiny
    w = torch.where(ok.unsqueeze(-1), q / torch.where(ok, prob, torch.ones_like(prob)).unsqueeze(-1), Pi)
    return prob / prob.sum(-1, keepdim=True), w


def imm_smoother(
    result: IMMResult,
    A: Tensor | None = None,
    Q: Tensor | None = None,
    Pi: Tensor | None = None,
    H: Tensor | None = None,
    R: Tensor | None = None,
) -> IMMSmootherResult:
    r"""Fixed-interval IMM smoother (Kim's mode recursion, two-filter pair step; the module
    docstring has the recursion, its references and why).

    Exact for one mode (equal to :func:`~torchsde_lti.filters.rts_smoother`), identical modes
    and a chain without switches; otherwise an approximation of the mixture over all mode
    histories (``tests/filters/test_imm_smoother.py`` measures it against that mixture).
    Missing reports (NaN in the filter's y) carry no information, as in the filter.

    Args:
        result: the :class:`~torchsde_lti.filters.imm.IMMResult` of
            :func:`~torchsde_lti.filters.imm_filter` (or :class:`~torchsde_lti.IMMFilter`):
            mode_probabilities (..., T, M), mode_mean (..., T, M, n), mode_cov (..., T, M, n, n),
            mode_pred_mean, mode_innovation, observed.
        A, Q: (..., T, M, n, n) the per-step, per-mode transitions and process noises the filter
            used; H: (..., T, M, m, n), R: (..., T, M, m, m) its observation model; Pi:
            (..., T, M, M) its row-stochastic mode transitions. Time and mode axes may be 1 and
            the batch broadcasts to the result's; default: those stored in ``result``
            (``transition``, ``process_noise``, ``observation_matrix``, ``observation_noise``,
            ``mode_transition``). Step 0's A, Q, Pi (from the prior) are not used.

    Returns:
        :class:`IMMSmootherResult`: mean (..., T, n), cov (..., T, n, n), mode_probabilities
        (..., T, M), mode_mean (..., T, M, n), mode_cov (..., T, M, n, n).

    Raises:
        TypeError: ``result`` is not an IMMResult. ValueError: A, Q, Pi, H or R that does not
            broadcast to the result's shapes (naming it and the shapes), or missing from an
            IMMResult that does not carry it.
    """
    if not isinstance(result, IMMResult):
        raise TypeError(
            f"result must be an IMMResult (the output of imm_filter or IMMFilter), got {type(result).__name__}"
        )
    mu, mean, cov = result.mode_probabilities, result.mode_mean, result.mode_cov
    *batch, T, M, n = mean.shape
    m = result.observed.shape[-1]
    A = _model(A, result.transition, "A", (M, n, n), (*batch, T, M, n, n))
    Q = _model(Q, result.process_noise, "Q", (M, n, n), (*batch, T, M, n, n))
    Pi = _model(Pi, result.mode_transition, "Pi", (M, M), (*batch, T, M, M))
    H = _model(H, result.observation_matrix, "H", (M, m, n), (*batch, T, M, m, n))
    R = _model(R, result.observation_noise, "R", (M, m, m), (*batch, T, M, m, m))
    U, u = _report_information(result, H, R)
    prob, ms, Ps = mu[..., -1, :], mean[..., -1, :, :], cov[..., -1, :, :, :]
    Lam, eta = torch.zeros_like(Ps), torch.zeros_like(ms)  # what y_{k+2:} say about x_{k+1}, per mode
    probs, means, covs = [prob], [ms], [Ps]
    for k in range(T - 2, -1, -1):
        nxt = k + 1
        G, z = _message_factor(
            Lam + U[..., nxt, :, :, :], eta + u[..., nxt, :, :], A[..., nxt, :, :, :], Q[..., nxt, :, :, :]
        )
        m_pair, P_pair, log_z = _pair_update(
            mean[..., k, :, None, :], cov[..., k, :, None, :, :], G.unsqueeze(-4), z.unsqueeze(-3)
        )  # (..., M_i, M_j, n), (..., M_i, M_j, n, n), (..., M_i, M_j)
        prob, w = _mode_pairs(mu[..., k, :], Pi[..., nxt, :, :], log_z, prob)
        ms, Ps = combine(w, m_pair, P_pair)
        Lam = sym(torch.einsum("...ij,...jab->...iab", w, G @ G.mT))  # the successors' information, pooled
        eta = torch.einsum("...ij,...ja->...ia", w, matvec(G, z))
        probs.append(prob)
        means.append(ms)
        covs.append(Ps)
    prob_s = torch.stack(probs[::-1], dim=-2)
    mean_s = torch.stack(means[::-1], dim=-3)
    cov_s = torch.stack(covs[::-1], dim=-4)
    x, P = combine(prob_s, mean_s, cov_s)
    return IMMSmootherResult(x, P, prob_s, mean_s, cov_s)
