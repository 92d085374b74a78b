r"""Interacting multiple model (IMM) filter on per-mode discrete matrices (Blom & Bar-Shalom 1988).

M mode-matched Kalman filters share one state space (dimension n); a Markov chain over the
modes switches between them. Over step k (gap dt_k) the chain moves with the transition
matrix ``Pi_k[i, j] = P(mode j at k | mode i at k−1)`` (for a continuous-time chain with
generator Λ: ``Pi_k = expm(Λ dt_k)``). One IMM cycle, for k = 0 … T−1:

1. mixing:      c_j = Σ_i Pi_ij μ_i,   w_ij = Pi_ij μ_i / c_j,
                m̄_j = Σ_i w_ij m_i,    P̄_j = Σ_i w_ij (P_i + (m_i − m̄_j)(m_i − m̄_j)ᵀ);
2. predict:     m⁻_j = A_j m̄_j,       P⁻_j = A_j P̄_j A_jᵀ + Q_j          (mode j's matrices);
3. update:      ŷ_j = H_j m⁻_j, S_j = H_j P⁻_j H_jᵀ + R_j, the Kalman update,
                ℓ_j = log N(y_k; ŷ_j, S_j) over the observed components of y_k;
4. modes:       log p(y_k | y_<k) = log Σ_j c_j exp(ℓ_j)  (log-sum-exp),  μ_j ∝ c_j exp(ℓ_j);
5. output:      x = Σ_j μ_j m_j,  P = Σ_j μ_j (P_j + (m_j − x)(m_j − x)ᵀ)  (moment matching).

The prior (m_j, P_j, μ) sits before step 0, as in :func:`torchsde_lti.kalman_filter`.

Shape convention (the mode axis M sits right after the time axis; batch dims ``...``
lead and broadcast right-aligned)::

    y (..., T, m)               A, Q (..., T, M, n, n)      Pi (..., T, M, M)
    H (..., T, M, m, n)         R (..., T, M, m, m)
    m0 (..., M, n)              P0 (..., M, n, n)           mode_prob0 (..., M)
    mask (..., T) or (..., T, m) bool (True = observed)

so a mode-dependent, time-constant H is (M, m, n), one H for every mode is (m, n), and a
per-step H without mode dependence is (T, 1, m, n). Missing data (NaN in y or mask False)
are handled as in the Kalman filter: unobserved components get a zero row in H and a
decoupled unit variance in R, so a fully missing step is a pure prediction (ℓ_j = 0, μ = c)
and contributes 0 to the log-likelihood; no NaN reaches any arithmetic or gradient.

Steps 2–3 of every mode are the Kalman filter's own step
(:func:`~torchsde_lti.filters.online.kalman_step`, the sequence loop's whitened scalar Joseph
updates, the modes a batch dimension): no matrix is inverted, and each mode is filtered with
the arithmetic of a Kalman filter of that mode (in float32 too, where a joint Joseph update
over a long gap lost the measurement's variance).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core.linalg import matvec, sym
from torchsde_lti.filters.imm_inputs import check_imm_inputs
from torchsde_lti.filters.noise import GAUSSIAN, NoiseModel, weighted_outer
from torchsde_lti.filters.online import KalmanState, kalman_step
from torchsde_lti.filters.results import serializable

__all__ = ["IMMCycle", "IMMPrediction", "IMMResult", "imm_cycle", "imm_filter", "imm_predict"]


@serializable
class IMMResult(NamedTuple):
    """Output of :func:`imm_filter`.

    log_likelihood: (...) Σ_k step_log_likelihood.
    step_log_likelihood: (..., T) ``log Σ_j c_j N(y_k; ŷ_j, S_j)`` (observed components;
        0 for a fully missing step).
    mode_probabilities: (..., T, M) posterior μ_k = P(mode j at k | y_0:k).
    pred_mode_probabilities: (..., T, M) predicted c_k = P(mode j at k | y_0:k−1).
    mean: (..., T, n) combined filtered mean. cov: (..., T, n, n) combined covariance.
    mode_mean: (..., T, M, n) mode-matched filtered means. mode_cov: (..., T, M, n, n).
    pred_mean: (..., T, n) combined one-step prediction Σ_j c_j m⁻_j;
    pred_cov: (..., T, n, n) its moment-matched covariance.
    mode_pred_mean: (..., T, M, n) m⁻_j. mode_pred_cov: (..., T, M, n, n) P⁻_j.
    mode_innovation: (..., T, M, m) y_k − ŷ_j (0 in unobserved components).
    mode_innovation_cov: (..., T, M, m, m) S_j = H_j P⁻_j H_jᵀ + R_j (all components).
    observed: (..., T, m) bool, the components that entered the update.
    transition: (..., T, M, n, n) the A_j of each step (a broadcast view), kept for smoothing
        (:func:`~torchsde_lti.filters.imm_smoother.imm_smoother`).
    process_noise: (..., T, M, n, n) the Q_j of each step (a broadcast view), kept for smoothing.
    mode_transition: (..., T, M, M) the chain's Pi of each step (a broadcast view), kept for
        smoothing.
    observation_matrix: (..., T, M, m, n) the H_j of each step; observation_noise:
        (..., T, M, m, m) the R_j (broadcast views), kept for smoothing. (These five default to
        None, so that a result built from the first fields alone, e.g. by code or a saved
        program of an earlier version, still constructs.)
    """

    log_likelihood: Tensor
    step_log_likelihood: Tensor
    mode_probabilities: Tensor
    pred_mode_probabilities: Tensor
    mean: Tensor
    cov: Tensor
    mode_mean: Tensor
    mode_cov: Tensor
    pred_mean: Tensor
    pred_cov: Tensor
    mode_pred_mean: Tensor
    mode_pred_cov: Tensor
    mode_innovation: Tensor
    mode_innovation_cov: Tensor
    observed: Tensor
    transition: Tensor | None = None
    process_noise: Tensor | None = None
    mode_transition: Tensor | None = None
    observation_matrix: Tensor | None = None
    observation_noise: Tensor | None = None


class IMMPrediction(NamedTuple):
    """Output of :func:`imm_predict` (one IMM prediction over each horizon, no update).

    mode_probabilities: (..., K, M) c = μ Pi(h). mode_mean: (..., K, M, n), mode_cov:
    (..., K, M, n, n) the mode-matched predictions; mean (..., K, n), cov (..., K, n, n)
    their moment-matched mixture.
    """

    mode_probabilities: Tensor
    mode_mean: Tensor
    mode_cov: Tensor
    mean: Tensor
    cov: Tensor


def _per_unit(factor: Tensor | None) -> Tensor | None:
    """A per-mode factor (..., M) of :meth:`~torchsde_lti.filters.StudentTNoise.covariance_factor`
    as (..., M, 1, 1), to scale matrices (..., M, n, n); None stays None."""
    return None if factor is None else factor[..., None, None]


def combine(prob: Tensor, mean: Tensor, cov: Tensor, noise: NoiseModel = GAUSSIAN) -> tuple[Tensor, Tensor]:
    """Moment-matched Gaussian of a mixture: prob (..., M), mean (..., M, n), cov (..., M, n, n).

    Returns ``x = Σ_j p_j m_j`` (..., n) and ``P = Σ_j p_j (r_j P_j + w (m_j − x)(m_j − x)ᵀ)``
    (..., n, n), w = ``noise.spread()`` (...) (None: 1) and r_j = ``noise.covariance_factor()``
    (None: 1) (:mod:`~torchsde_lti.filters.noise`: a scale matrix of one ν, or the covariance of
    modes with a ν each); ``noise`` has the batch of prob (:meth:`~torchsde_lti.filters.StudentTNoise.with_axis`).
    """
    r = _per_unit(noise.covariance_factor())
    cov = cov if r is None else cov * r
    x = torch.einsum("...j,...jn->...n", prob, mean)
    P = torch.einsum("...j,...jab->...ab", prob, cov + weighted_outer(mean - x.unsqueeze(-2), noise.spread(), 3))
    return x, sym(P)


def _mix(prob: Tensor, Pi: Tensor, mean: Tensor, cov: Tensor, noise: NoiseModel) -> tuple[Tensor, Tensor, Tensor]:
    """IMM mixing step. prob (..., M), Pi (..., M, M), mean (..., M, n), cov (..., M, n, n); noise
    with the batch of prob: the spread's weight (...) and, a ν per mode, the modes' scales mixed as
    covariances ``r_i P_i`` and returned to mode j's scale (÷ r_j; :mod:`~torchsde_lti.filters.noise`).

    Returns c (..., M) = prob Pi, mixed means (..., M, n) and covariances (..., M, n, n).
    A mode with c_j ≤ sqrt(tiny) of the dtype (≈ 1e-154 in float64) gets c_j = 0 and mixed
    moments 0: it carries no weight, and nothing divides by a number whose square
    underflows (the backward of ``joint / c`` is ``joint / c²``: with c subnormal, e.g. after
    a zero-dt padding step of a mode whose probability underflowed, it returned NaN).
    """
    joint = prob.unsqueeze(-1) * Pi  # (..., M_i, M_j) P(i at k−1, j at k)
    c = joint.sum(-2)
    r = _per_unit(noise.covariance_factor())
    pos = c > math.sqrt(torch.finfo(c.dtype).tiny)
    c = torch.where(pos, c, torch.zeros_like(c))
    c_safe = torch.where(pos, c, torch.ones_like(c))
    w = joint / c_safe.unsqueeze(-2)  # w_ij = P(i at k−1 | j at k)
    # Σ_i w_ij m_i as a broadcast sum (a traced einsum's reshapes of symbolic sizes failed
    # torch.export's scan of the cycle in grad mode; mean may broadcast over the modes)
    m_mix = (w.unsqueeze(-1) * mean.unsqueeze(-2)).sum(-3)
    d = mean.unsqueeze(-2) - m_mix.unsqueeze(-3)  # (..., M_i, M_j, n)
    # (..., M_i, M_j, n, n)
    mixed = (cov if r is None else cov * r).unsqueeze(-3) + weighted_outer(d, noise.spread(), 4)
    P_mix = (w[..., None, None] * mixed).sum(-4)  # Σ_i w_ij (r_i P_i + w d_ij d_ijᵀ)
    return c, m_mix, sym(P_mix if r is None else P_mix / r)


class IMMCycle(NamedTuple):
    """One IMM cycle's results (:func:`imm_cycle`), per track.

    mode_prob: (..., M) posterior μ. mode_mean: (..., M, n), mode_cov: (..., M, n, n) the
    mode-matched filtered moments. pred_mode_prob: (..., M) c = μ_prev Pi.
    mode_pred_mean: (..., M, n) m⁻_j; mode_pred_cov: (..., M, n, n) P⁻_j.
    mode_innovation: (..., M, m) y − H_j m⁻_j (0 where unobserved);
    mode_innovation_cov: (..., M, m, m) S_j. log_likelihood: (...) the step's
    ``log Σ_j c_j N(y; ŷ_j, S_j)`` (0 for a fully missing report). observed: (..., m) bool.
    """

    mode_prob: Tensor
    mode_mean: Tensor
    mode_cov: Tensor
    pred_mode_prob: Tensor
    mode_pred_mean: Tensor
    mode_pred_cov: Tensor
    mode_innovation: Tensor
    mode_innovation_cov: Tensor
    log_likelihood: Tensor
    observed: Tensor


def imm_cycle(
    prob: Tensor,
    mean: Tensor,
    cov: Tensor,
    Pi: Tensor,
    A: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    y: Tensor,
    noise: NoiseModel = GAUSSIAN,
) -> IMMCycle:
    r"""One IMM cycle: mixing, each mode's Kalman step, the mode probabilities. The step of
    :func:`imm_filter`'s loop and of the online :func:`~torchsde_lti.filters.imm_online.imm_step`.

    Each mode's predict and update is :func:`~torchsde_lti.filters.online.kalman_step` (the
    sequence Kalman filter's step: whitened scalar Joseph updates) with the mode axis as a
    batch dimension, so every mode is filtered exactly as a Kalman filter of that mode is.

    prob (..., M), mean (..., M, n), cov (..., M, n, n) before the step; Pi (..., M, M);
    A, Q (..., M, n, n); H (..., M or 1, m, n), R (..., M or 1, m, m); y (..., m) the report
    (NaN = missing component); noise: the modes' noise model (a t's scale matrices mix as covariances).
    """
    c, m_mix, P_mix = _mix(prob, Pi, mean, cov, noise)
    state, step = kalman_step(KalmanState(m_mix, P_mix), y.unsqueeze(-2), A, Q, H, R, noise=noise.over_modes())
    log_c = torch.where(c > 0, torch.log(torch.where(c > 0, c, torch.ones_like(c))), torch.full_like(c, -math.inf))
    joint = log_c + step.log_likelihood  # (..., M)
    total = torch.logsumexp(joint, dim=-1)
    prob = torch.softmax(joint, dim=-1)  # (exp(joint − total) sums to 1 only within |joint| eps: 2e-12 at ℓ ~ −1e4)
    observed = step.observed.select(-2, 0)  # (..., m): the same for every mode
    # Σ_j c_j = 1 exactly in theory: a fully missing step contributes exactly 0
    total = torch.where(observed.any(-1), total, torch.zeros_like(total))
    return IMMCycle(
        prob, state.mean, state.cov, c, step.pred_mean, step.pred_cov, step.innovation, step.innovation_cov, total,
        observed,
    )  # fmt: skip


def imm_filter(
    y: Tensor,
    A: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    Pi: Tensor,
    m0: Tensor,
    P0: Tensor,
    mode_prob0: Tensor,
    mask: Tensor | None = None,
    validate_args: bool = True,
    noise: NoiseModel = GAUSSIAN,
) -> IMMResult:
    r"""IMM filter over T steps (see the module docstring for the cycle and the shapes).

    Args:
        y: (..., T, m) observations; NaN = missing component.
        A, Q: (..., T, M, n, n) per-step, per-mode transitions and process noise.
        H: (..., T, M, m, n) observation matrices; R: (..., T, M, m, m) noise (SPD).
        Pi: (..., T, M, M) row-stochastic mode transition matrices of each step
            (``expm(Λ dt_k)`` for a continuous-time chain; identity for dt_k = 0).
        m0: (..., M, n) per-mode prior means; P0: (..., M, n, n) covariances.
        mode_prob0: (..., M) prior mode probabilities (before step 0).
        mask: optional bool (..., T) or (..., T, m); False = not observed.
        validate_args: check the values (y without Inf; finite, PSD covariances, stochastic Pi
            and mode_prob0); shapes are always checked.
        noise: the modes' noise model (:mod:`~torchsde_lti.filters.noise`; a Student-t's ν is
            shared, or one per mode with ``per_mode``: the step log-likelihood is
            ``log Σ_j c_j St(y_k; ŷ_j, S_j, ν_j)``, and with a ν per mode the combined ``cov`` and
            ``pred_cov`` are the mixture's covariances, the mode-matched ones each mode's scale).

    Returns:
        :class:`IMMResult`; every output broadcasts to the full batch ``...``.
    """
    y, A, Q, H, R, Pi, m0, P0, prob, mask = check_imm_inputs(y, A, Q, H, R, Pi, m0, P0, mode_prob0, mask, validate_args)
    noise = noise.check(y.shape[:-2], "sequential", validate_args, modes=prob.shape[-1])
    if mask is not None:  # (a report not observed is a missing one: NaN)
        y = torch.where(mask, y, torch.nan)
    T, m = y.shape[-2], y.shape[-1]
    M, n = prob.shape[-1], A.shape[-1]
    # time-constant arrays get a size-1 time axis; step k then reads index 0 or k
    H4, R4 = (x.reshape((1,) * (4 - x.dim()) + tuple(x.shape)) if x.dim() < 4 else x for x in (H, R))
    A4 = A if A.dim() >= 4 else A.unsqueeze(-4)
    Q4 = Q if Q.dim() >= 4 else Q.unsqueeze(-4)
    Pi3 = Pi if Pi.dim() >= 3 else Pi.unsqueeze(-3)
    mean = m0 if m0.dim() >= 2 else m0.unsqueeze(-2)
    # the T axis goes before each output's event dims (vector over modes: -2, (M, n): -3, ...)
    if torch.compiler.is_exporting():  # one step traced, any T: torch's structured scan
        stk = _imm_scan(H4, R4, A4, Q4, Pi3, y, prob, mean, P0, noise)
    else:

        def at(x: Tensor, k: int, axis: int) -> Tensor:
            return x.select(axis, 0 if x.shape[axis] == 1 else k)

        steps = []
        cov = P0
        for k in range(T):
            cyc = imm_cycle(
                prob,
                mean,
                cov,
                at(Pi3, k, -3),
                at(A4, k, -4),
                at(Q4, k, -4),
                at(H4, k, -4),
                at(R4, k, -4),
                y[..., k, :],
                noise,
            )
            prob, mean, cov = cyc.mode_prob, cyc.mode_mean, cyc.mode_cov
            steps.append(cyc)
        stk = {
            k: torch.stack(torch.broadcast_tensors(*v), dim=-1 - _EVENT_NDIM[k])
            for k, v in zip(IMMCycle._fields, zip(*steps))
        }
    return _imm_result(stk, T, M, n, m, (A4, Q4, Pi3, H4, R4), noise.with_axis())


#: The event dims of each field of :class:`IMMCycle` (the T axis goes before them).
_EVENT_NDIM = dict(zip(IMMCycle._fields, (1, 2, 3, 1, 2, 3, 2, 3, 0, 1)))


def _imm_scan(
    H4: Tensor,
    R4: Tensor,
    A4: Tensor,
    Q4: Tensor,
    Pi3: Tensor,
    y: Tensor,
    prob: Tensor,
    mean: Tensor,
    cov: Tensor,
    noise: NoiseModel = GAUSSIAN,
) -> dict[str, Tensor]:
    """:func:`imm_filter`'s loop as torch's structured scan (``torch._higher_order_ops.scan``):
    one cycle traced, T not unrolled (an exported program takes any T). Per-step arrays
    (..., T or 1, ...) are broadcast to the full batch and T and scanned along a leading T;
    the outputs are the fields of :class:`IMMCycle` with the T axis before their event dims."""
    from torch._higher_order_ops import scan

    T, m, M, n = y.shape[-2], y.shape[-1], prob.shape[-1], A4.shape[-1]
    batch = torch.broadcast_shapes(
        H4.shape[:-4], R4.shape[:-4], A4.shape[:-4], Q4.shape[:-4], Pi3.shape[:-3], y.shape[:-2], prob.shape[:-1],
        mean.shape[:-2], cov.shape[:-3],
    )  # fmt: skip

    def steps(x: Tensor, *event: int) -> Tensor:  # (..., T or 1, *event) -> (T, *batch, *event), a fresh copy
        return x.expand(*batch, T, *event).movedim(len(batch), 0).clone(memory_format=torch.contiguous_format)

    MH, MR = H4.shape[-3], R4.shape[-3]
    xs = (
        steps(H4, MH, m, n),
        steps(R4, MR, m, m),
        steps(A4, M, n, n),
        steps(Q4, M, n, n),
        steps(Pi3, M, M),
        steps(y, m),
    )
    carry = (prob.expand(*batch, M).clone(), mean.expand(*batch, M, n).clone(), cov.expand(*batch, M, n, n).clone())

    def body(
        state: tuple[Tensor, Tensor, Tensor], x: tuple[Tensor, ...]
    ) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]]:
        Hk, Rk, Ak, Qk, Pik, yk = x
        cyc = imm_cycle(*state, Pik, Ak, Qk, Hk, Rk, yk, noise)
        # (outputs must not alias the carry, and have one layout)
        carry = tuple(t.contiguous() for t in (cyc.mode_prob, cyc.mode_mean, cyc.mode_cov))
        return carry, tuple(t.contiguous().clone() for t in cyc[:-1])  # (observed: no tangent, taken from y)

    _, outs = scan(body, carry, xs)
    stk = {k: v.movedim(0, -1 - _EVENT_NDIM[k]) for k, v in zip(IMMCycle._fields[:-1], outs)}
    return {**stk, "observed": ~torch.isnan(y)}


def _imm_result(
    stk: dict[str, Tensor], T: int, M: int, n: int, m: int, model: tuple[Tensor, ...], noise: NoiseModel
) -> IMMResult:
    """The :class:`IMMResult` of the per-step fields of :class:`IMMCycle` ``stk`` (the T axis
    before each one's event dims) and of the model it filtered with, ``model`` = (A, Q
    (..., T or 1, M or 1, n, n), Pi (..., T or 1, M, M), H (..., T or 1, M or 1, m, n),
    R (..., T or 1, M or 1, m, m)); ``noise``: :func:`combine`'s, with the T axis."""
    batch = torch.broadcast_shapes(*(v.shape[: v.dim() - 1 - _EVENT_NDIM[k]] for k, v in stk.items()))
    mu = stk["mode_prob"].expand(*batch, T, M)
    cc = stk["pred_mode_prob"].expand(*batch, T, M)
    mm = stk["mode_mean"].expand(*batch, T, M, n)
    mc = stk["mode_cov"].expand(*batch, T, M, n, n)
    pm = stk["mode_pred_mean"].expand(*batch, T, M, n)
    pc = stk["mode_pred_cov"].expand(*batch, T, M, n, n)
    x, P = combine(mu, mm, mc, noise)
    xp, Pp = combine(cc, pm, pc, noise)
    step_ll = stk["log_likelihood"].expand(*batch, T)
    A, Q, Pi, H, R = model
    return IMMResult(
        log_likelihood=step_ll.sum(-1),
        step_log_likelihood=step_ll,
        mode_probabilities=mu,
        pred_mode_probabilities=cc,
        mean=x,
        cov=P,
        mode_mean=mm,
        mode_cov=mc,
        pred_mean=xp,
        pred_cov=Pp,
        mode_pred_mean=pm,
        mode_pred_cov=pc,
        mode_innovation=stk["mode_innovation"].expand(*batch, T, M, m),
        mode_innovation_cov=stk["mode_innovation_cov"].expand(*batch, T, M, m, m),
        observed=stk["observed"].expand(*batch, T, m),
        transition=A.expand(*batch, T, M, n, n),
        process_noise=Q.expand(*batch, T, M, n, n),
        mode_transition=Pi.expand(*batch, T, M, M),
        observation_matrix=H.expand(*batch, T, M, m, n),
        observation_noise=R.expand(*batch, T, M, m, m),
    )


def imm_predict(
    mode_prob: Tensor, mean: Tensor, cov: Tensor, A: Tensor, Q: Tensor, Pi: Tensor, noise: NoiseModel = GAUSSIAN
) -> IMMPrediction:
    r"""One IMM prediction (mixing + mode-matched prediction) over each of K horizons.

    Each horizon h is measured from the state's time: ``c = μ Pi(h)``, then the mixed
    moments of each mode are pushed through ``A_j(h)``, ``Q_j(h)``. (Exact when no switch
    occurs within the horizon; the IMM's usual one-step approximation otherwise.)

    Args:
        mode_prob: (..., M) mode probabilities; mean: (..., M, n); cov: (..., M, n, n).
        A, Q: (..., K, M, n, n) mode matrices over each horizon; Pi: (..., K, M, M).
        noise: the modes' noise model (batch (...); :func:`combine`: a t's scale matrices mix as
            covariances).

    Returns:
        :class:`IMMPrediction` with a K axis after the batch.
    """
    k_noise = noise.with_axis()  # (over the K horizons)
    c, m_mix, P_mix = _mix(mode_prob.unsqueeze(-2), Pi, mean.unsqueeze(-3), cov.unsqueeze(-4), k_noise)
    m_pred = matvec(A, m_mix)
    P_pred = sym(A @ P_mix @ A.mT + Q)
    x, P = combine(c, m_pred, P_pred, k_noise)
    return IMMPrediction(c, m_pred, P_pred, x, P)
