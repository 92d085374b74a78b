r"""Calibration of a frozen filter's predictive: HPD levels and a scalar covariance inflation.

    levels = hpd_level(y, w, mu, S)                     # (N,) mass of the predictive denser than y
    c = fit_cov_scale(y, w, mu, S)                      # S -> c S: share of y in the 86.5 % region = 86.5 %
    c = calibrate_filter(model, val_tracks)             # the same, on a filter's one-step predictive: [c]
    cs = fit_mode_scales(y, w, mu, S)                   # one scale per mode, by the mode the filter predicts
    before, after = online_scales(OnlineScale(), y, w, mu, S, scored)   # (B, T) per-track scales, online

The one-step predictive of a report is a Gaussian mixture ``Σ_j w_j N(mu_j, S_j)`` (one
component for a Kalman filter), or a mixture of Student-t's with one ν (``dof``) for a filter
with ``noise=tl.StudentT`` (:mod:`~torchsde_lti.evaluation.student_t`). Its *HPD level* at y is the probability mass of the
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
:func:`fit_mode_scales` fits one scale per mode instead (``S_j -> c_j S_j``).

:class:`OnlineScale` fits nothing in advance: each track carries its own scale, adapted after
every report from that track's past reports alone (adaptive conformal inference on the log
scale), so that a filter trained on one coast keeps its nominal coverage on another.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsde_lti.data.loaded_tracks import Tracks
from torchsde_lti.evaluation.predictive import Model, mixture_log_prob, one_step_predictive, predictive_dof
from torchsde_lti.evaluation.student_t import t_draws, t_hpd_level

__all__ = [
    "NOMINAL_2SIGMA",
    "OnlineScale",
    "calibrate_filter",
    "fit_cov_scale",
    "fit_mode_scales",
    "hpd_level",
    "online_scales",
    "scale_vector",
]

#: P(chi²_2 <= 4) = 1 - e^-2: the probability of the 2σ region in 2-D.
NOMINAL_2SIGMA = 1.0 - math.exp(-2.0)


def scale_vector(scale: float | Sequence[float] | Tensor, M: int, dtype: torch.dtype = torch.float64) -> Tensor:
    """The per-component covariance scales (M,) of ``scale``: one number for every component, or M.

    Raises:
        ValueError: for a length other than 1 or M, or a scale that is not finite and > 0.
    """
    c = torch.as_tensor(scale, dtype=dtype).reshape(-1)
    if c.numel() not in (1, M) or not bool(torch.all(torch.isfinite(c) & (c > 0))):
        raise ValueError(f"scale must be one finite number > 0 or {M} of them (one per component), got {c.tolist()}")
    return c.expand(M)


def _check(y: Tensor, w: Tensor, mu: Tensor, S: Tensor) -> None:
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


def hpd_level(
    y: Tensor,
    w: Tensor,
    mu: Tensor,
    S: Tensor,
    scale: float | Sequence[float] | Tensor = 1.0,
    samples: int = 500,
    seed: int = 0,
    chunk: int = 2000,
    dof: Tensor | float | None = None,
) -> Tensor:
    """HPD level of each y under its predictive mixture with covariances ``c_j S_j``: (N,).

    Args:
        y: (N, m) observations; w: (N, M) weights; mu: (N, M, m) means; S: (N, M, m, m)
            covariances (SPD).
        scale: the covariance inflation c > 0: one number, or one per component (M,).
        samples, seed, chunk: Monte Carlo of a mixture (M > 1): draws per row, the seed,
            rows per chunk. One component: closed form (no draws).
        dof: None (Gaussian components) or ν (Student-t components, S their scale matrices:
            one component's level is the F(m, ν) CDF of Mahalanobis² / m,
            :func:`~torchsde_lti.evaluation.student_t.t_hpd_level`; a mixture's draws are t draws).

    Returns:
        (N,) in [0, 1]: the mass of the predictive with a higher density than at y
        (y is inside the level-α HPD region iff this is <= α).

    Raises:
        ValueError: for shapes that do not agree, or a scale that is not > 0.
    """
    _check(y, w, mu, S)
    m = y.shape[-1]
    c = scale_vector(scale, w.shape[-1], y.dtype)
    if w.shape[-1] == 1:
        d = (y - mu[:, 0]).unsqueeze(-1)
        maha = (d.mT @ torch.linalg.solve(S[:, 0], d)).reshape(-1) / c[0]
        if dof is not None:
            return t_hpd_level(maha, m, dof)
        return torch.special.gammainc(torch.full_like(maha, m / 2.0), 0.5 * maha)
    g = torch.Generator().manual_seed(seed)
    out = []
    for lo in range(0, y.shape[0], chunk):
        ww, mm, SS = w[lo : lo + chunk], mu[lo : lo + chunk], c[:, None, None] * S[lo : lo + chunk]
        comp = torch.multinomial(ww.clamp_min(0), samples, replacement=True, generator=g)  # (n, D)
        L = torch.linalg.cholesky(SS)
        z = torch.randn(*comp.shape, m, generator=g, dtype=y.dtype)
        Lg = torch.gather(L.flatten(-2), 1, comp[..., None].expand(-1, -1, m * m)).unflatten(-1, (m, m))
        xs = torch.gather(mm, 1, comp[..., None].expand(-1, -1, m))
        Lz = sum(Lg[..., :, j] * z[..., j : j + 1] for j in range(m))
        assert isinstance(Lz, Tensor)
        xs = xs + Lz if dof is None else t_draws(xs, Lz, dof, g, comp)
        ly = mixture_log_prob(y[lo : lo + chunk], ww, mm, SS, dof)  # (n,)
        lx = mixture_log_prob(xs, ww, mm, SS, dof)  # (n, D)
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
    dof: Tensor | float | None = None,
) -> float:
    """The scalar c with share(hpd_level(y, w, mu, S, c) <= target) = target (a quantile match).

    Bisection of log c, from the bracket [1/2, 2] widened within ``bounds`` (the coverage
    grows with c); one component has closed-form levels, a mixture the same Monte Carlo
    draws at every c.

    Args:
        y, w, mu, S: the predictive of N reports, as in :func:`hpd_level`.
        target: the HPD probability whose coverage is matched (default 86.5 %: 2σ in 2-D).
        samples, seed: Monte Carlo of a mixture; bounds: the search interval of c; tol: the
            width of the final bracket in log c; dof: ν of Student-t components (None: Gaussian).

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
        return float((hpd_level(y, w, mu, S, c, samples=samples, seed=seed, dof=dof) <= target).to(y.dtype).mean())

    return _bisect(coverage, target, 1.0, bounds, tol)


def _bisect(
    coverage: Callable[[float], float], target: float, start: float, bounds: tuple[float, float], tol: float
) -> float:
    """The c with coverage(c) = target (coverage grows with c): bisection of log c from the
    bracket [start / 2, 2 start], widened by x4 within ``bounds``; the upper end of the final bracket."""
    lo_b, hi_b = math.log(bounds[0]), math.log(bounds[1])
    s0 = math.log(start)
    lo, hi = min(max(s0 - math.log(2.0), lo_b), hi_b), min(max(s0 + math.log(2.0), lo_b), hi_b)
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


def fit_mode_scales(
    y: Tensor,
    w: Tensor,
    mu: Tensor,
    S: Tensor,
    target: float = NOMINAL_2SIGMA,
    samples: int = 500,
    seed: int = 0,
    min_reports: int = 200,
    sweeps: int = 2,
    bounds: tuple[float, float] = (1.0 / 64.0, 64.0),
    tol: float = 0.01,
    dof: Tensor | float | None = None,
) -> list[float]:
    """One covariance scale per mixture component (mode), ``S_j -> c_j S_j``: coverage by the model's own modes.

    Each report belongs to the component with the largest predictive weight (the mode the
    filter predicts: known before the report, unlike any label of the evaluation). Starting
    from the single scale of :func:`fit_cov_scale` for all components, each c_j is fitted by
    bisection so that ``target`` of the reports of its group lie in the ``target`` HPD region
    of the whole mixture (the others held), for ``sweeps`` rounds. A component predicting
    fewer than ``min_reports`` reports keeps the common scale. With one component this is
    :func:`fit_cov_scale`.

    Args:
        y, w, mu, S: the predictive of N reports, as in :func:`hpd_level`.
        target, samples, seed, bounds: as in :func:`fit_cov_scale`; tol: the final bracket in log c_j.
        min_reports: the smallest group with its own scale; sweeps: rounds over the components.
        dof: ν of Student-t components (None: Gaussian).

    Returns:
        [c_1, ..., c_M].
    """
    c0 = fit_cov_scale(y, w, mu, S, target, samples=samples, seed=seed, bounds=bounds, tol=tol, dof=dof)
    M = w.shape[-1]
    c = [c0] * M
    group = w.argmax(-1)
    for _ in range(sweeps if M > 1 else 0):
        for j in range(M):
            rows = group == j
            if int(rows.sum()) < min_reports:
                continue
            yj, wj, mj, Sj = y[rows], w[rows], mu[rows], S[rows]

            def coverage(x: float, j: int = j) -> float:
                cj = c[:j] + [x] + c[j + 1 :]
                lev = hpd_level(yj, wj, mj, Sj, cj, samples=samples, seed=seed, dof=dof)
                return float((lev <= target).to(y.dtype).mean())

            c[j] = _bisect(coverage, target, c[j], bounds, tol)
    return [float(x) for x in c]


def calibrate_filter(
    model: Model,
    tracks: Tracks,
    target: float = NOMINAL_2SIGMA,
    samples: int = 500,
    seed: int = 0,
    max_reports: int | None = 20_000,
    per_mode: bool = False,
) -> list[float]:
    """The covariance inflation of a frozen filter's one-step predictive, fitted on ``tracks``.

    Use validation tracks (never the data the result is judged on). Pass the result as
    ``cov_scale`` to :func:`~torchsde_lti.evaluation.evaluate_filter`.

    Args:
        model: a position-observing KalmanFilter or IMMFilter.
        tracks: the validation tracks.
        target, samples, seed: as in :func:`fit_cov_scale`.
        max_reports: fit on at most this many reports (a seeded subsample), None = all.
        per_mode: one scale per mode (:func:`fit_mode_scales`) or one for all (:func:`fit_cov_scale`,
            the default).

    Returns:
        [c_1, ..., c_M] (M = 1 for a Kalman filter; M equal values when ``per_mode`` is False).
    """
    pred = one_step_predictive(model, tracks)
    n = pred["y"].shape[0]
    if max_reports is not None and n > max_reports:
        keep = torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:max_reports]
        pred = {k: v[keep] for k, v in pred.items()}
    args = (pred["y"], pred["w"], pred["mu"], pred["S"], target)
    dof = predictive_dof(model)
    if per_mode:
        return fit_mode_scales(*args, samples=samples, seed=seed, dof=dof)
    return [fit_cov_scale(*args, samples=samples, seed=seed, dof=dof)] * pred["w"].shape[-1]


@dataclass(frozen=True)
class OnlineScale:
    r"""A covariance scale per track, adapted online to the nominal coverage of the predictive.

    Before report k of a track the predictive's covariances are multiplied by ``s_k = e^{ℓ_k}``;
    after it, with ``miss_k`` = 1 when y_k lies outside the ``level`` HPD region of that scaled
    predictive (0 otherwise)::

        ℓ_1 = 0,    ℓ_{k+1} = ℓ_k + rate · (miss_k − (1 − level)).

    This is adaptive conformal inference (Gibbs & Candès, "Adaptive conformal inference under
    distribution shift", NeurIPS 2021) with the scale of the predictive as the adapted
    quantity: a miss widens by ``e^{rate · level}``, a hit narrows by ``e^{−rate (1 − level)}``,
    and over the first K reports of a track the share of misses is exactly
    ``1 − level + ℓ_{K+1} / (rate K)`` whatever the data (nominal as K grows while the scale
    stays bounded). Causal: s_k depends on the reports before k only, so the
    scaled predictive is a forecast. The means and mode weights are unchanged; the scale
    multiplies a fixed calibration (``cov_scale``) where there is one.

    Attributes:
        rate: γ > 0, the step on ℓ (larger: faster adaptation, noisier scale).
        level: the HPD probability whose coverage is tracked (default 86.5 %, 2σ in 2-D).
    """

    rate: float = 0.4
    level: float = NOMINAL_2SIGMA

    def __post_init__(self) -> None:
        for name in ("rate", "level"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TypeError(f"{name} must be a number, got {type(value).__name__}")
        if not (math.isfinite(self.rate) and self.rate > 0):
            raise ValueError(f"rate must be a finite number > 0, got {self.rate}")
        if not 0.0 < self.level < 1.0:
            raise ValueError(f"level must be in (0, 1), got {self.level}")

    def update(self, log_scale: Tensor, miss: Tensor) -> Tensor:
        """ℓ after one report: ``log_scale + rate (miss − (1 − level))``; log_scale (...), miss (...)
        bool or 0/1 (the report outside the ``level`` region of the predictive scaled by
        ``e^log_scale``). A live tracker keeps ℓ per track and calls this after each report."""
        return log_scale + self.rate * (miss.to(log_scale.dtype) - (1.0 - self.level))


def online_scales(
    rule: OnlineScale,
    y: Tensor,
    w: Tensor,
    mu: Tensor,
    S: Tensor,
    scored: Tensor,
    samples: int = 500,
    seed: int = 0,
    dof: Tensor | float | None = None,
) -> tuple[Tensor, Tensor]:
    """The per-track scales of :class:`OnlineScale` over a padded batch of tracks.

    Args:
        rule: the adaptation.
        y: (B, T, m) reports; w: (B, T, M); mu: (B, T, M, m); S: (B, T, M, m, m): the one-step
            predictive of each report (:func:`~torchsde_lti.evaluation.batch_predictive`).
        scored: (B, T) bool, the reports that are tested and update the scale (observed, not a
            track's first); the others keep it.
        samples, seed, dof: the HPD test, as in :func:`hpd_level`.

    Returns:
        ``before`` (B, T): the scale s_k of report k's predictive; ``after`` (B, T): the scale
        once report k is seen (that of a forecast from the filtered state at k).
    """
    if y.dim() != 3 or scored.shape != y.shape[:2]:
        raise ValueError(f"y must be (B, T, m) and scored (B, T), got {tuple(y.shape)} and {tuple(scored.shape)}")
    B, T = scored.shape
    log_s = y.new_zeros(B)
    before, after = y.new_empty(B, T), y.new_empty(B, T)
    for k in range(T):
        before[:, k] = log_s.exp()
        rows = scored[:, k].nonzero().squeeze(-1)
        if len(rows):
            Sk = before[rows, k, None, None, None] * S[rows, k]
            level = hpd_level(y[rows, k], w[rows, k], mu[rows, k], Sk, samples=samples, seed=seed, dof=dof)
            log_s = log_s.index_copy(0, rows, rule.update(log_s[rows], level > rule.level))
        after[:, k] = log_s.exp()
    return before, after
