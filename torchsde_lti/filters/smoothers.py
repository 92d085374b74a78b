r"""The Rauch–Tung–Striebel smoother over a filter result: sequential loop or associative scan,
on the filters' batch-last layout (:mod:`~torchsde_lti.filters.layout`)."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsde_lti.core.validation import broadcast_shapes, check_matrix, shape_str
from torchsde_lti.filters.inputs import check_time_axis, own_extent
from torchsde_lti.filters.kalman import check_algorithm, choose_algorithm
from torchsde_lti.filters.layout import batch_first, batch_last, mm, mv, psd_solve, sym, tr
from torchsde_lti.filters.results import FilterResult, SmootherResult
from torchsde_lti.filters.scan import Elems, associative_scan

__all__ = ["SMOOTHER_ALGORITHMS", "rts_smoother"]

#: The algorithms of :func:`rts_smoother` ("auto": the default, "sequential").
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


def rts_smoother(
    result: FilterResult, A: Tensor | None = None, Q: Tensor | None = None, *, algorithm: str = "sequential"
) -> SmootherResult:
    r"""Rauch–Tung–Striebel smoother for time-varying (A_k, Q_k).

    With the gains ``E_k = P_k A_{k+1}ᵀ (P⁻_{k+1})⁻¹`` (computed batched over all steps; a
    generalised inverse where P⁻_{k+1} is singular, :func:`psd_solve`; E_{T-1} = 0):
    ``m^s_k = m_k + E_k (m^s_{k+1} − m⁻_{k+1})``, ``P^s_k = P_k + E_k (P^s_{k+1} − P⁻_{k+1}) E_kᵀ``.

    Args:
        result: a :class:`FilterResult` (mean, cov, pred_mean, pred_cov over T steps).
        A, Q: (..., T, n, n) the transitions/noises the filter used; default: those stored
            in ``result`` (``result.transition``, ``result.process_noise``). As in the
            filter, the time axis may be 1 or absent (a constant (n, n)); the batch must
            broadcast to the result's. ValueError naming A or Q and the shapes otherwise.
        algorithm: one of :data:`SMOOTHER_ALGORITHMS`, same results up to rounding:
            ``"sequential"`` (backward loop), ``"scan"`` (reverse associative scan of the
            elements ``x_k | x_{k+1} ~ N(g_k + E_k x_{k+1}, C_k)``, ``g_k = m_k − E_k m⁻_{k+1}``,
            ``C_k = P_k − E_k A_{k+1} P_k``; Särkkä & García-Fernández 2021, O(log T) depth) or
            ``"auto"`` (the default's name, as in :func:`~torchsde_lti.filters.choose_algorithm`).

    Returns:
        :class:`SmootherResult` with mean (..., T, n), cov (..., T, n, n), gain (..., T, n, n).
    """
    check_algorithm(algorithm, SMOOTHER_ALGORITHMS, "rts_smoother")
    if not isinstance(result, FilterResult):
        raise TypeError(
            f"result must be a FilterResult (the output of kalman_filter or KalmanFilter), got {type(result).__name__}"
        )
    A = result.transition if A is None else _check_model(A, "A", result)
    Q = result.process_noise if Q is None else _check_model(Q, "Q", result)
    batch, T = result.mean.shape[:-2], result.mean.shape[-2]
    nd = len(batch)
    mf, pm = (batch_last(x, 1, nd) for x in (result.mean, result.pred_mean))  # (T, n, *b)
    Pf, Pp = (batch_last(x, 2, nd) for x in (result.cov, result.pred_cov))  # (T, n, n, *b)
    A = batch_last(own_extent(A), 2, nd)  # (T or 1, n, n, *b)
    A1 = A[1:] if A.shape[0] > 1 else A  # A_{k+1}, k = 0 … T − 2
    run = _scan_smoother if choose_algorithm(algorithm) == "scan" else _loop_smoother
    ms, Ps, gain = run(mf, Pf, pm, Pp, A1)  # (gains with E_{T−1} = 0)
    return SmootherResult(
        *(batch_first(x, x.dim() - 1 - nd, nd).expand(*batch, T, *x.shape[1 : x.dim() - nd]) for x in (ms, Ps, gain))
    )


def _gain(P: Tensor, P_next: Tensor, A_next: Tensor, at: int) -> tuple[Tensor, Tensor]:
    """(E, A_{k+1} P_k): the smoother gain ``E_k = P_k A_{k+1}ᵀ (P⁻_{k+1})⁻¹`` (:func:`psd_solve`)."""
    AP = mm(A_next, P, at)
    return tr(psd_solve(P_next, AP, at), at), AP


def _loop_smoother(mf: Tensor, Pf: Tensor, pm: Tensor, Pp: Tensor, A1: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The backward loop, each step's gain formed in the loop (on one step's tensors, which stay
    in the caches): smoothed means (T, n, *b), covariances (T, n, n, *b), gains (T, n, n, *b)."""
    ms, Ps = mf[-1], Pf[-1]
    means, covs, gains = [ms], [Ps], []
    m_k, P_k, pm_k, Pp_k, A_k = mf.unbind(0), Pf.unbind(0), pm.unbind(0), Pp.unbind(0), A1.unbind(0)
    for k in range(mf.shape[0] - 2, -1, -1):
        E, _ = _gain(P_k[k], Pp_k[k + 1], A_k[k if len(A_k) > 1 else 0], 0)
        ms = m_k[k] + mv(E, ms - pm_k[k + 1])
        Ps = sym(P_k[k] + mm(mm(E, Ps - Pp_k[k + 1]), tr(E)))
        means.append(ms)
        covs.append(Ps)
        gains.append(E)
    gains = [*gains[::-1], torch.zeros_like(Pf[-1]).expand_as(gains[0] if gains else Pf[-1])]
    return torch.stack(means[::-1]), torch.stack(covs[::-1]), torch.stack(torch.broadcast_tensors(*gains))


def _smoother_combine(a: Elems, b: Elems) -> Elems:
    """Combine smoothing elements a (earlier) with b (later), (T', ·, *b) each: x_i | x_{j+1}."""
    Ei, gi, Ci = a
    Ej, gj, Cj = b
    return mm(Ei, Ej, 1), mv(Ei, gj, 1) + gi, sym(mm(mm(Ei, Cj, 1), tr(Ei, 1), 1), 1) + Ci


def _scan_smoother(mf: Tensor, Pf: Tensor, pm: Tensor, Pp: Tensor, A1: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The smoother by a reverse associative scan of the elements (E, g, C) (the last step's
    E = 0, g = m, C = P), the gains batched over the steps: smoothed means, covariances, gains."""
    E, AP = _gain(Pf[:-1], Pp[1:], A1, 1)
    g = torch.cat([mf[:-1] - mv(E, pm[1:], 1), mf[-1:]])
    C = torch.cat([sym(Pf[:-1] - mm(E, AP, 1), 1), Pf[-1:]])
    E_all = torch.cat([E.expand(E.shape[0], *Pf.shape[1:]), torch.zeros_like(Pf[:1])])
    _, ms, Ps = associative_scan(
        _smoother_combine, (E_all, g.expand(*E_all.shape[:2], *E_all.shape[3:]), C), reverse=True
    )
    return ms, Ps, E_all
