r"""The square-root (Cholesky-factor) sequential Kalman filter: P = S Sᵀ is never formed.

QR predict, Givens scalar updates: PSD by construction and accurate in float32 beyond the
Joseph form's range (predicted/measured variance ratios > 1/eps), at a higher cost than the
Joseph-form loop.
Reached through ``kalman_filter(..., algorithm="square_root")``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsde_lti.core.linalg import cholesky, matvec, sym
from torchsde_lti.filters.inputs import PreparedInputs, assemble_result
from torchsde_lti.filters.results import FilterResult

__all__ = ["square_root_filter"]


def square_root_filter(prep: PreparedInputs) -> FilterResult:
    r"""Square-root Kalman filter: propagates ``S_k`` with ``P_k = S_k S_kᵀ`` (no P is formed).

    Predict (QR of a (2n, n) array; ``L_Q L_Qᵀ = Q_k`` by ``cholesky(Q_k, semidefinite=True)``)::

        [ (A_k S)ᵀ ; L_Qᵀ ] = Θ [ S⁻ᵀ ; 0 ]   ⇒   S⁻ S⁻ᵀ = A_k S Sᵀ A_kᵀ + Q_k.

    Update on the whitened model (R' = I; unobserved components are zero rows of H' with
    unit variance, exactly as in the standard path), one scalar row h of H' at a time: with
    ``f = Sᵀ h`` the array ``[[1, fᵀ], [0, S]]`` is rotated by n Givens rotations of its
    columns (column 0 against column j, zeroing f_j) into ``[[x, 0], [k̄, S⁺]]``, so that
    ``x² = 1 + fᵀ f`` (innovation variance), ``m⁺ = m + k̄ e`` with ``e = (y' − hᵀ m) / x``,
    ``S⁺ S⁺ᵀ = P − P h hᵀ P / x²`` (S⁺ is square, not necessarily triangular) and the
    whitened log-likelihood core is ``−½ Σ (2 log x + e²)``.

    Givens rather than Householder in the update: a rotation with ``c = a / hypot(a, f_j)``
    multiplies, it does not subtract, so a posterior much smaller than the prior (predicted
    / measured variance ratio beyond 1/eps, e.g. q = 10 over a 5000 s gap with R = 1e-4 in
    float32) keeps its value when h is aligned with the factor (position observations of a
    kinematic model), where a Householder reflection cancels it to 0. Covariances are
    returned as ``S Sᵀ``, PSD by construction. The QR's R and the rotations are
    differentiable (:func:`_compressed_factor`), also where the predicted covariance is
    singular. One exception: where Q_k or P0 is singular (a step with
    dt = 0 has Q_k = 0) the factor's zero pivots carry no gradient, so the gradient with
    respect to that Q_k (to dt at a zero step) is not the log-likelihood's; the
    ``"sequential"`` and ``"scan"`` algorithms give it.
    """
    A_steps = prep.A.unbind(-3)  # (*cb, n, n) each
    LQ_steps = cholesky(prep.Q, semidefinite=True).unbind(-3)
    Hw = prep.Hw  # (..., T or 1, m, n)
    h_single = Hw.shape[-3] == 1
    yw_steps = prep.yw.unbind(-2)  # (*mb, m) each
    c = prep.c
    m_dim, n = Hw.shape[-2], prep.A.shape[-1]
    mean, S = prep.m0, cholesky(prep.P0, semidefinite=True)
    means, facs, pmeans, pfacs, cores = [], [], [], [], []
    for k in range(prep.T):
        Ak = A_steps[k]
        mean = matvec(Ak, mean)
        if c is not None:
            mean = mean + c[..., 0 if c.shape[-2] == 1 else k, :]
        AS = Ak @ S
        LQ = LQ_steps[k]
        lead = torch.broadcast_shapes(AS.shape[:-2], LQ.shape[:-2])
        pre_p = torch.cat([AS.mT.expand(*lead, n, n), LQ.mT.expand(*lead, n, n)], dim=-2)  # (2n, n)
        S = _compressed_factor(pre_p)
        pmeans.append(mean)
        pfacs.append(S)
        Hk = Hw[..., 0 if h_single else k, :, :]  # (.., m, n)
        F_ = Hk @ S  # rows f_iᵀ = h_iᵀ S  (*cb, m, n)
        cols = list(S.unbind(-1))  # columns S[:, j] (*cb, n)
        core = None
        for i in range(m_dim):
            f = F_[..., i, :].unbind(-1) if i == 0 else [torch.linalg.vecdot(Hk[..., i, :], col) for col in cols]
            x = torch.ones_like(f[0])
            kbar = torch.zeros_like(cols[0])
            for j in range(n):
                r = torch.hypot(x, f[j])
                cj, sj = x / r, f[j] / r
                kbar, cols[j] = (
                    cj[..., None] * kbar + sj[..., None] * cols[j],
                    cj[..., None] * cols[j] - sj[..., None] * kbar,
                )
                x = r
            e = (yw_steps[k][..., i] - torch.linalg.vecdot(Hk[..., i, :], mean)) / x
            mean = mean + kbar * e[..., None]
            term = -0.5 * (2.0 * torch.log(x) + e * e)
            core = term if core is None else core + term
        S = torch.stack(cols, dim=-1)
        assert core is not None
        cores.append(core)
        means.append(mean)
        facs.append(S)
    mb = prep.mean_batch

    def covs(fs: list[Tensor]) -> Tensor:
        F_ = torch.stack(torch.broadcast_tensors(*fs), dim=-3)
        return sym(F_ @ F_.mT)

    mean_t = torch.stack(torch.broadcast_tensors(*means), dim=-2)
    pmean_t = torch.stack(torch.broadcast_tensors(*pmeans), dim=-2)
    core = torch.stack(torch.broadcast_tensors(*cores), dim=-1)
    core = core.expand(*torch.broadcast_shapes(core.shape[:-1], mb), prep.T)
    return assemble_result(prep, (mean_t, covs(facs)), (pmean_t, covs(pfacs)), core)


def _compressed_factor(pre: Tensor) -> Tensor:
    """S⁻ (..., n, n) with ``S⁻ S⁻ᵀ = preᵀ pre`` from pre (..., 2n, n): the transposed R of
    pre's reduced QR, ``pre = Θ R``, so ``S⁻ = Rᵀ = preᵀ Θ``. When autograd records, Θ is taken
    as a constant and the gradient flows through ``preᵀ Θ``: exact for every result that
    depends on the factor through ``S⁻ S⁻ᵀ`` only (all of this filter's: Θ Θᵀ pre = pre, as Θ
    spans pre's columns), and finite where pre is rank-deficient (a singular prior followed by
    a zero step), where the backward of QR divides by R's zero pivots."""
    if not (torch.is_grad_enabled() and pre.requires_grad):
        return torch.linalg.qr(pre, mode="reduced").R.mT  # lower triangular
    with torch.no_grad():
        theta = torch.linalg.qr(pre, mode="reduced").Q  # (..., 2n, n)
    return pre.mT @ theta
