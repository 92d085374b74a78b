r"""The Rauch–Tung–Striebel smoother over a filter result: sequential loop or associative scan."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsde_lti.core.linalg import cho_solve, cholesky, matvec, sym
from torchsde_lti.core.validation import broadcast_shapes, check_matrix, shape_str
from torchsde_lti.filters.inputs import check_time_axis
from torchsde_lti.filters.kalman import check_algorithm
from torchsde_lti.filters.results import FilterResult, SmootherResult
from torchsde_lti.filters.scan import Elems, associative_scan, prefers_scan

__all__ = ["SMOOTHER_ALGORITHMS", "rts_smoother"]

#: The algorithms of :func:`rts_smoother` ("auto" chooses per call).
SMOOTHER_ALGORITHMS = ("auto", "sequential", "scan")


def _check_model(x: Tensor, name: str, result: FilterResult) -> Tensor:
    """x, an explicitly passed A or Q (..., [T,] n, n) of the filter that gave ``result``
    (mean (*batch, T, n)): ValueError naming ``name`` and the shapes unless it is n × n, has
    no time axis or one of length 1 or T, and its batch broadcasts to the result's."""
    mean = result.mean
    n, T, batch = mean.shape[-1], mean.shape[-2], tuple(mean.shape[:-2])
    x = torch.as_tensor(x)
    check_matrix(x, name, rows=n, cols=n)
    check_time_axis(x, name, T, f"the filter result has T={T} (mean shape {shape_str(mean)})")
    own = tuple(x.shape[:-3])
    try:
        fits = tuple(broadcast_shapes(batch, own)) == batch
    except ValueError:
        fits = False
    if not fits:
        raise ValueError(
            f"{name} of shape {shape_str(x)} has batch shape ({', '.join(map(str, own))}), which does not "
            f"broadcast to the filter result's batch ({', '.join(map(str, batch))}) (mean shape {shape_str(mean)})"
        )
    return x


def _smoother_elements(result: FilterResult, A: Tensor | None, Q: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """Per-step (E_k, g_k, C_k) with ``x_k | x_{k+1}, y ~ N(g_k + E_k x_{k+1}, C_k)``.

    E_k = P_k A_{k+1}ᵀ (P⁻_{k+1})⁻¹ (a Cholesky solve; a generalised inverse where P⁻_{k+1}
    is singular), g_k = m_k − E_k m⁻_{k+1},
    C_k = (I − E_k A_{k+1}) P_k (I − E_k A_{k+1})ᵀ + E_k Q_{k+1} E_kᵀ (Joseph form of
    P_k − E_k P⁻_{k+1} E_kᵀ: a sum of PSD terms). The last step has E = 0, g = m, C = P.
    """
    A = result.transition if A is None else _check_model(A, "A", result)
    Q = result.process_noise if Q is None else _check_model(Q, "Q", result)
    mf, Pf, pm, Pp = result.mean, result.cov, result.pred_mean, result.pred_cov
    n, T = mf.shape[-1], mf.shape[-2]
    # Work at the covariance batch (filtered covariances are usually broadcast views).
    A1 = A[..., 1:, :, :] if A.dim() >= 3 and A.shape[-3] == T else A
    Q1 = Q[..., 1:, :, :] if Q.dim() >= 3 and Q.shape[-3] == T else Q
    P_k = Pf[..., :-1, :, :]
    Pp1 = Pp[..., 1:, :, :]
    AP = A1 @ P_k  # A_{k+1} P_k
    # (a singular P⁻_{k+1}, e.g. a prior with zero variances and a step dt = 0: a generalised
    # inverse, under which the smoothed moments are those of the pseudo-inverse)
    L = cholesky(Pp1, semidefinite=True)
    E = cho_solve(L, AP, semidefinite=True).mT  # P_k A_{k+1}ᵀ (P⁻_{k+1})⁻¹
    eye = torch.eye(n, dtype=mf.dtype, device=mf.device)
    IEA = eye - E @ A1
    C = sym(IEA @ P_k @ IEA.mT + E @ Q1 @ E.mT)
    g = mf[..., :-1, :] - matvec(E, pm[..., 1:, :])
    lead = E.shape[:-3]
    E_all = torch.cat([E, torch.zeros((*lead, 1, n, n), dtype=E.dtype, device=E.device)], dim=-3)
    lead_c = torch.broadcast_shapes(C.shape[:-3], Pf.shape[:-3])
    C_all = torch.cat([C.expand(*lead_c, T - 1, n, n), Pf[..., -1:, :, :].expand(*lead_c, 1, n, n)], dim=-3)
    lead_g = torch.broadcast_shapes(g.shape[:-2], mf.shape[:-2])
    g_all = torch.cat([g.expand(*lead_g, T - 1, n), mf[..., -1:, :].expand(*lead_g, 1, n)], dim=-2)
    return E_all, g_all, C_all


def rts_smoother(
    result: FilterResult, A: Tensor | None = None, Q: Tensor | None = None, *, algorithm: str = "auto"
) -> SmootherResult:
    r"""Rauch–Tung–Striebel smoother for time-varying (A_k, Q_k).

    ``m^s_k = m_k + E_k (m^s_{k+1} − m⁻_{k+1})``, ``P^s_k = P_k + E_k (P^s_{k+1} − P⁻_{k+1}) E_kᵀ``,
    evaluated as ``m^s_k = g_k + E_k m^s_{k+1}``, ``P^s_k = C_k + E_k P^s_{k+1} E_kᵀ`` with the
    PSD-preserving (E, g, C) of the smoothing elements computed batched over all steps.

    Args:
        result: a :class:`FilterResult` (mean, cov, pred_mean, pred_cov over T steps).
        A, Q: (..., T, n, n) the transitions/noises the filter used; default: those stored
            in ``result`` (``result.transition``, ``result.process_noise``). As in the
            filter, the time axis may be 1 or absent (a constant (n, n)); the batch must
            broadcast to the result's. ValueError naming A or Q and the shapes otherwise.
        algorithm: one of :data:`SMOOTHER_ALGORITHMS`, same results up to rounding:
            ``"sequential"`` (backward loop), ``"scan"`` (reverse associative scan of
            (E, g, C), Särkkä & García-Fernández 2021, O(log T) depth) or ``"auto"`` (the
            scan where :func:`~torchsde_lti.filters.prefers_scan` says so).

    Returns:
        :class:`SmootherResult` with mean (..., T, n), cov (..., T, n, n), gain (..., T, n, n).
    """
    check_algorithm(algorithm, SMOOTHER_ALGORITHMS, "rts_smoother")
    if not isinstance(result, FilterResult):
        raise TypeError(
            f"result must be a FilterResult (the output of kalman_filter or KalmanFilter), got {type(result).__name__}"
        )
    return _rts(result, A, Q, algorithm)


def _rts(result: FilterResult, A: Tensor | None, Q: Tensor | None, algorithm: str) -> SmootherResult:
    E, g, C = _smoother_elements(result, A, Q)
    if algorithm == "auto":
        T = g.shape[-2]
        algorithm = "scan" if prefers_scan(result.mean.shape[:-2].numel(), T, result.mean.device) else "sequential"
    if algorithm == "scan":
        return _scan_smoother(result, E, g, C)
    T = g.shape[-2]
    Es, gs, Cs = E.unbind(-3), g.unbind(-2), C.unbind(-3)
    ms, Ps = gs[-1], Cs[-1]
    means, covs = [ms], [Ps]
    for k in range(T - 2, -1, -1):
        ms = gs[k] + matvec(Es[k], ms)
        Ps = sym(Cs[k] + Es[k] @ Ps @ Es[k].mT)
        means.append(ms)
        covs.append(Ps)
    mean = torch.stack(means[::-1], dim=-2)
    cov = torch.stack(covs[::-1], dim=-3)
    batch = torch.broadcast_shapes(mean.shape[:-2], cov.shape[:-3], result.mean.shape[:-2])
    n = mean.shape[-1]
    return SmootherResult(mean.expand(*batch, T, n), cov.expand(*batch, T, n, n), E.expand(*batch, T, n, n))


def _smoother_combine(a: Elems, b: Elems) -> Elems:
    """Combine smoothing elements a (earlier) with b (later): x_i | x_{j+1}."""
    Ei, gi, Ci = a
    Ej, gj, Cj = b
    return Ei @ Ej, matvec(Ei, gj) + gi, sym(Ei @ Cj @ Ei.mT + Ci)


def _scan_smoother(result: FilterResult, E: Tensor, g: Tensor, C: Tensor) -> SmootherResult:
    """The smoother by a reverse associative scan of the smoothing elements (E, g, C)."""
    T, n = g.shape[-2], g.shape[-1]
    batch = torch.broadcast_shapes(E.shape[:-3], g.shape[:-2], C.shape[:-3])
    moved = (
        E.expand(*batch, T, n, n).movedim(-3, 0),
        g.expand(*batch, T, n).movedim(-2, 0),
        C.expand(*batch, T, n, n).movedim(-3, 0),
    )
    Es, gs, Cs = associative_scan(_smoother_combine, moved, reverse=True)
    mean = gs.movedim(0, -2)
    cov = Cs.movedim(0, -3)
    full = torch.broadcast_shapes(batch, result.mean.shape[:-2])
    return SmootherResult(mean.expand(*full, T, n), cov.expand(*full, T, n, n), E.expand(*full, T, n, n))
