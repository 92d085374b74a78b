r"""The square-root (Cholesky-factor) sequential Kalman filter: P = S Sᵀ is never formed.

Givens rotations in the predict and in the scalar updates, on the batch-last layout of
:mod:`~torchsde_lti.filters.layout` (a factor is its n columns, each (n, *batch)): PSD by
construction and accurate in float32 beyond the Joseph form's range (predicted/measured
variance ratios > 1/eps), at a higher cost than the Joseph-form loop.
Reached through ``kalman_filter(..., algorithm="square_root")``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsde_lti.filters.inputs import PreparedInputs, assemble_result, observed_count
from torchsde_lti.filters.layout import mm, mv, psd_cholesky, sym, tr
from torchsde_lti.filters.noise import GAUSSIAN, NoiseModel
from torchsde_lti.filters.results import FilterResult

__all__ = ["square_root_filter"]


def square_root_filter(prep: PreparedInputs, noise: NoiseModel = GAUSSIAN) -> FilterResult:
    r"""Square-root Kalman filter: propagates ``S_k`` with ``P_k = S_k S_kᵀ`` (no P is formed).

    Predict: the n × 2n array ``[A_k S | L_Q]`` (``L_Q L_Qᵀ = Q_k``, a semidefinite Cholesky
    factor) is compressed by Givens rotations of its columns into ``[S⁻ | 0]``, so
    ``S⁻ S⁻ᵀ = A_k S Sᵀ A_kᵀ + Q_k`` (:func:`_compress`).

    Update on the whitened model (R' = I; unobserved components are zero rows of H' with
    unit variance, exactly as in the other algorithms), one scalar row h of H' at a time: with
    ``f = Sᵀ h`` the array ``[[1, fᵀ], [0, S]]`` is rotated by n Givens rotations of its
    columns (column 0 against column j, zeroing f_j) into ``[[x, 0], [k̄, S⁺]]``, so that
    ``x² = 1 + fᵀ f`` (innovation variance), ``m⁺ = m + k̄ e`` with ``e = (y' − hᵀ m) / x``,
    ``S⁺ S⁺ᵀ = P − P h hᵀ P / x²`` and the whitened log-likelihood core is ``−½ Σ (2 log x + e²)``.

    Givens rather than Householder: a rotation with ``c = a / hypot(a, f_j)`` multiplies, it
    does not subtract, so a posterior much smaller than the prior (predicted / measured
    variance ratio beyond 1/eps, e.g. q = 10 over a 5000 s gap with R = 1e-4 in float32) keeps
    its value when h is aligned with the factor (position observations of a kinematic model),
    where a Householder reflection cancels it to 0. Covariances are returned as ``S Sᵀ``, PSD by
    construction. Gradients are exact, also where the predicted covariance is singular, with
    one exception: where Q_k or P0 is singular (a step with dt = 0 has Q_k = 0) the factor's
    zero pivots carry no gradient, so the gradient with respect to that Q_k (to dt at a zero
    step) is not the log-likelihood's; the ``"sequential"`` and ``"scan"`` algorithms give it.

    ``noise``: the observation-noise model (:mod:`~torchsde_lti.filters.noise`); a Student-t
    scale ``f P⁺`` is the factor ``√f S⁺``.
    """
    T, n = prep.T, prep.A.shape[1]
    LQ = psd_cholesky(prep.Q, 1)[0].unbind(0)  # (n, n, *b) each
    A, Hw, yw = prep.A.unbind(0), prep.Hw.unbind(0), prep.yw.unbind(0)
    c = None if prep.c is None else prep.c.unbind(0)
    mean, S = prep.m0, psd_cholesky(prep.P0, 0)[0]
    S = noise.full_batch(S, mean)
    d = observed_count(prep)
    means, facs, pmeans, pfacs, cores = [], [], [], [], []
    for k in range(T):
        mean = mv(A[k], mean) if c is None else mv(A[k], mean) + c[k]
        cols = _compress(list(mm(A[k], S).unbind(1)), list(LQ[k].unbind(1)))
        pmeans.append(mean)
        pfacs.append(torch.stack(torch.broadcast_tensors(*cols), 1))
        xs, es = [], []
        for h, yi in zip(Hw[k].unbind(0), yw[k].unbind(0)):  # rows h (n, *b), values (*b)
            x = torch.ones_like(yi)
            kbar = torch.zeros_like(cols[0])
            for j in range(n):
                fj = torch.linalg.vecdot(h, cols[j], dim=0)  # (Sᵀ h)_j, column j not yet rotated
                r = torch.hypot(x, fj)
                cj, sj = x / r, fj / r
                kbar, cols[j] = cj * kbar + sj * cols[j], cj * cols[j] - sj * kbar
                x = r
            e = (yi - torch.linalg.vecdot(h, mean, dim=0)) / x
            mean = mean + kbar * e
            xs.append(x)
            es.append(e)
        # the noise model's update of P = S Sᵀ as √f S (the whitened e_j have variance 1)
        S = torch.stack(torch.broadcast_tensors(*cols), 1)
        maha = (torch.stack(torch.broadcast_tensors(*es)) ** 2).sum(0)
        f = noise.scale(maha, d[k])
        S = S if f is None else S * torch.sqrt(f)
        log_s = 2.0 * torch.log(torch.stack(torch.broadcast_tensors(*xs))).sum(0)
        cores.append(noise.log_likelihood_core(log_s, maha, d[k]))
        means.append(mean)
        facs.append(S)

    def stacked(xs: list[Tensor]) -> Tensor:
        return torch.stack(torch.broadcast_tensors(*xs))

    def covs(fs: list[Tensor]) -> Tensor:
        F = stacked(fs)
        return sym(mm(F, tr(F, 1), 1), 1)

    return assemble_result(prep, (stacked(means), covs(facs)), (stacked(pmeans), covs(pfacs)), stacked(cores))


def _compress(cols: list[Tensor], extra: list[Tensor]) -> list[Tensor]:
    """The n columns (n, *b) of a square factor S⁻ with ``S⁻ S⁻ᵀ = M Mᵀ``, M = [cols | extra]
    (n × 2n, ``extra`` lower triangular), by Givens rotations of M's columns: row i of column
    j > i and of the extra columns j ≤ i zeroed against column i (the extra columns j > i are
    zero in rows ≤ i already). The rotations are taken as constants (computed without autograd,
    ``c = s = 0`` → the identity where both entries are 0): the gradient flows through ``M Θ``
    (Θ the product of rotations), exact for every result that depends on the factor through
    ``S⁻ S⁻ᵀ = M Θ Θᵀ Mᵀ = M Mᵀ`` (all of this filter's), and finite where M is rank-deficient."""
    n = len(cols)
    for i in range(n):
        for j, other in [(j, cols) for j in range(i + 1, n)] + [(j, extra) for j in range(i + 1)]:
            with torch.no_grad():
                a, b = cols[i][i], other[j][i]
                r = torch.hypot(a, b)
                zero = r == 0
                r = torch.where(zero, 1.0, r)
                ci, si = torch.where(zero, 1.0, a / r), b / r
            cols[i], other[j] = ci * cols[i] + si * other[j], ci * other[j] - si * cols[i]
    return cols
