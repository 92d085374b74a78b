r"""Calibration of a frozen filter's predictive: HPD levels and a scalar covariance inflation.

    levels = hpd_level(y, w, mu, S)                     # (N,) mass of the predictive denser than y
    c = fit_cov_scale(y, w, mu, S)                      # S -> c S: share of y in the 86.5 % region = 86.5 %
    c = calibrate_filter(model, val_tracks)             # the same, on a filter's one-step predictive

The one-step predictive of a report is a Gaussian mixture ``Σ_j w_j N(mu_j, S_j)`` (one
component for a Kalman filter). Its *HPD level* at y is the probability mass of the
predictive where the density exceeds the density at y; y lies in the level-α highest-density
region iff its level is <= α, and for a calibrated predictive the levels are uniform on
(0, 1). For one Gaussian in m dimensions the level is the chi-square CDF of the Mahalanobis
distance, ``P(m/2, d²/2)`` (regularised lower incomplete gamma), in closed form; for a mixture
it is estimated from seeded draws of the mixture (the same draws for every ``scale``: common
random numbers, so that a bisection over the scale sees a smooth curve).

The inflation is one scalar c > 0 for every component's covariance, ``S_j -> c S_j``, fitted
on *validation* data so that the share of reports inside the ``target`` region equals the
target. For a linear Kalman filter this is exactly the filter with Q, R and the prior
covariance all scaled by c (the gain and the means are unchanged, every covariance scales by
c); for an IMM it widens each mode's predictive and keeps the filtered mode probabilities.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchsde_lti.data.trajectories import Tracks

__all__ = [
    "NOMINAL_2SIGMA",
    "calibrate_filter",
    "fit_cov_scale",
    "hpd_level",
    "mixture_log_prob",
    "one_step_predictive",
]

#: P(chi²_2 <= 4) = 1 - e^-2: the probability of the 2σ region in 2-D.
NOMINAL_2SIGMA = 1.0 - math.exp(-2.0)


def _check(y: Tensor, w: Tensor, mu: Tensor, S: Tensor, scale: float) -> None:
    if y.dim() != 2 or w.dim() != 2 or mu.dim() != 3 or S.dim() != 4:
        raise ValueError(
            f"y must be (N, m), w (N, M), mu (N, M, m), S (N, M, m, m), got y {tuple(y.shape)}, "
            f"w {tuple(w.shape)}, mu {tuple(mu.shape)}, S {tuple(S.shape)}"
        )
    (N, m), M = y.shape, w.shape[1]
    if w.shape[0] != N or mu.shape != (N, M, m) or S.shape != (N, M, m, m):
        raise ValueError(
            f"y (N, m), w (N, M), mu (N, M, m) and S (N, M, m, m) must agree, got y {tuple(y.shape)}, "
            f"w {tuple(w.shape)}, mu {tuple(mu.shape)}, S {tuple(S.shape)}"
        )
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a finite number > 0, got {scale}")


def mixture_log_prob(x: Tensor, w: Tensor, mu: Tensor, S: Tensor) -> Tensor:
    """log Σ_j w_j N(x; mu_j, S_j) of points x (N, S, m) or (N, m).

    Args:
        x: (N, m) or (N, S, m) points (S draws per row).
        w: (N, M) weights; mu: (N, M, m) means; S: (N, M, m, m) covariances (SPD).

    Returns:
        (N,) or (N, S) log densities. Elementwise over the m × m entries of the inverse
        (no batched small solves: those dominate otherwise).
    """
    squeeze = x.dim() == 2
    if squeeze:
        x = x.unsqueeze(1)
    m = x.shape[-1]
    L = torch.linalg.cholesky(S)
    Sinv = torch.cholesky_inverse(L).unsqueeze(1)  # (N, 1, M, m, m)
    logdet = 2.0 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1).unsqueeze(1)  # (N, 1, M)
    d = x.unsqueeze(-2) - mu.unsqueeze(1)  # (N, S, M, m)
    quad = sum(d[..., i] * Sinv[..., i, j] * d[..., j] for i in range(m) for j in range(m))
    comp = -0.5 * (quad + logdet + m * math.log(2 * math.pi))
    out = torch.logsumexp(comp + torch.log(w.clamp_min(1e-300)).unsqueeze(1), -1)
    return out.squeeze(1) if squeeze else out


def hpd_level(
    y: Tensor,
    w: Tensor,
    mu: Tensor,
    S: Tensor,
    scale: float = 1.0,
    samples: int = 500,
    seed: int = 0,
    chunk: int = 2000,
) -> Tensor:
    """HPD level of each y under its predictive mixture with covariances ``scale · S``: (N,).

    Args:
        y: (N, m) observations; w: (N, M) weights; mu: (N, M, m) means; S: (N, M, m, m)
            covariances (SPD).
        scale: the covariance inflation c (> 0).
        samples, seed, chunk: Monte Carlo of a mixture (M > 1): draws per row, the seed,
            rows per chunk. One component: closed form (no draws).

    Returns:
        (N,) in [0, 1]: the mass of the predictive with a higher density than at y
        (y is inside the level-α HPD region iff this is <= α).

    Raises:
        ValueError: for shapes that do not agree, or a scale that is not > 0.
    """
    _check(y, w, mu, S, scale)
    m = y.shape[-1]
    if w.shape[-1] == 1:
        d = (y - mu[:, 0]).unsqueeze(-1)
        maha = (d.mT @ torch.linalg.solve(S[:, 0], d)).reshape(-1) / scale
        return torch.special.gammainc(torch.full_like(maha, m / 2.0), 0.5 * maha)
    g = torch.Generator().manual_seed(seed)
    out = []
    for lo in range(0, y.shape[0], chunk):
        ww, mm, SS = w[lo : lo + chunk], mu[lo : lo + chunk], scale * S[lo : lo + chunk]
        comp = torch.multinomial(ww.clamp_min(0), samples, replacement=True, generator=g)  # (n, D)
        L = torch.linalg.cholesky(SS)
        z = torch.randn(*comp.shape, m, generator=g, dtype=y.dtype)
        Lg = torch.gather(L.flatten(-2), 1, comp[..., None].expand(-1, -1, m * m)).unflatten(-1, (m, m))
        xs = torch.gather(mm, 1, comp[..., None].expand(-1, -1, m))
        xs = xs + sum(Lg[..., :, j] * z[..., j : j + 1] for j in range(m))
        ly = mixture_log_prob(y[lo : lo + chunk], ww, mm, SS)  # (n,)
        lx = mixture_log_prob(xs, ww, mm, SS)  # (n, D)
        out.append((lx > ly[:, None]).to(y.dtype).mean(-1))
    return torch.cat(out) if out else torch.zeros(0, dtype=y.dtype)


def fit_cov_scale(
    y: Tensor,
    w: Tensor,
    mu: Tensor,
    S: Tensor,
    target: float = NOMINAL_2SIGMA,
    samples: int = 500,
    seed: int = 0,
    bounds: tuple[float, float] = (1.0 / 64.0, 64.0),
    tol: float = 0.005,
) -> float:
    """The scalar c with share(hpd_level(y, w, mu, S, c) <= target) = target (a quantile match).

    Bisection of log c, from the bracket [1/2, 2] widened within ``bounds`` (the coverage
    grows with c); one component has closed-form levels, a mixture the same Monte Carlo
    draws at every c.

    Args:
        y, w, mu, S: the predictive of N reports, as in :func:`hpd_level`.
        target: the HPD probability whose coverage is matched (default 86.5 %: 2σ in 2-D).
        samples, seed: Monte Carlo of a mixture; bounds: the search interval of c; tol: the
            width of the final bracket in log c.

    Returns:
        c (the upper end of the final bracket: coverage >= target), clipped to ``bounds``.

    Raises:
        ValueError: for a target outside (0, 1), bounds that are not 0 < lo < hi, or no reports.
    """
    if not 0.0 < target < 1.0:
        raise ValueError(f"target must be in (0, 1), got {target}")
    if not 0.0 < bounds[0] < bounds[1]:
        raise ValueError(f"bounds must be 0 < lo < hi, got {bounds}")
    if y.shape[0] == 0:
        raise ValueError("fit_cov_scale needs at least one report, got y of shape (0, m)")

    def coverage(c: float) -> float:
        return float((hpd_level(y, w, mu, S, c, samples=samples, seed=seed) <= target).to(y.dtype).mean())

    # bracket [lo, hi] in log c around 0, widened by x4 up to ``bounds``, then bisected
    lo_b, hi_b = math.log(bounds[0]), math.log(bounds[1])
    lo, hi = min(max(-math.log(2.0), lo_b), hi_b), min(max(math.log(2.0), lo_b), hi_b)
    while coverage(math.exp(hi)) < target:
        if hi >= hi_b:
            return bounds[1]
        lo, hi = hi, min(hi_b, hi + math.log(4.0))
    while coverage(math.exp(lo)) >= target:
        if lo <= lo_b:
            return bounds[0]
        hi, lo = lo, max(lo_b, lo - math.log(4.0))
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        if coverage(math.exp(mid)) >= target:
            hi = mid
        else:
            lo = mid
    return math.exp(hi)


def one_step_predictive(model: torch.nn.Module, tracks: Tracks, max_steps: int = 50_000) -> dict[str, Tensor]:
    """The one-step predictive of every report k >= 2 of every track (float64, no gradients).

    Args:
        model: a position-observing :class:`~torchsde_lti.KalmanFilter` or :class:`~torchsde_lti.IMMFilter`.
        tracks: whole tracks (:func:`~torchsde_lti.data.load_tracks`).

    Returns:
        {"y": (N, m), "w": (N, M), "mu": (N, M, m), "S": (N, M, m, m), "index": (N,) flat report
        index into ``tracks``}, in the order of :func:`~torchsde_lti.training.evaluation.evaluate_filter`.
    """
    from torchsde_lti.training.evaluation import _batches, _one_step

    model = model.to(torch.float64).eval()
    parts: dict[str, list[Tensor]] = {k: [] for k in ("y", "w", "mu", "S", "index")}
    batches, index = _batches(tracks, max_steps)
    with torch.no_grad():
        for batch, idx in zip(batches, index):
            _, w, ym, S = _one_step(model, batch)
            m = batch.mask.clone()
            m[:, 0] = False
            parts["y"].append(batch.y[m])
            parts["w"].append(w[m])
            parts["mu"].append(ym[m])
            parts["S"].append(S[m])
            parts["index"].append(torch.as_tensor(idx[m.numpy()]))
    return {k: torch.cat(v) for k, v in parts.items()}


def calibrate_filter(
    model: torch.nn.Module,
    tracks: Tracks,
    target: float = NOMINAL_2SIGMA,
    samples: int = 500,
    seed: int = 0,
    max_reports: int | None = 20_000,
) -> float:
    """The covariance inflation c of a frozen filter's one-step predictive, fitted on ``tracks``.

    Use validation tracks (never the data the result is judged on). Pass c as ``cov_scale``
    to :func:`~torchsde_lti.training.evaluation.evaluate_filter`.

    Args:
        model: a position-observing KalmanFilter or IMMFilter.
        tracks: the validation tracks.
        target, samples, seed: as in :func:`fit_cov_scale`.
        max_reports: fit on at most this many reports (a seeded subsample), None = all.

    Returns:
        c > 0.
    """
    pred = one_step_predictive(model, tracks)
    n = pred["y"].shape[0]
    if max_reports is not None and n > max_reports:
        keep = torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:max_reports]
        pred = {k: v[keep] for k, v in pred.items()}
    return fit_cov_scale(pred["y"], pred["w"], pred["mu"], pred["S"], target, samples=samples, seed=seed)
