r"""Evaluation of frozen filters on held-out tracks: the same reports and forecasts for every model.

    recs = evaluate_filter(model, tracks)        # model: KalmanFilter or IMMFilter (eval mode)
    summary(recs)                                # {"nll", "nll_moving", "nll_moored", "cover2s", "fc_rmse_300", ...}
    paired_bootstrap(recs_a, recs_b)             # {metric: {"delta", "lo", "hi"}}: a - b, vessels resampled

Per report k >= 2 of every track (the first report holds the prior): the one-step predictive
NLL ``-log p(y_k | y_<k)`` (nats per 2-D report), whether y_k lies in the 86.5 % highest-density
region of the one-step predictive (the 2σ ellipse of a Gaussian: exactly; of a Student-t
filter's t: exactly, the F distribution's ellipse; for a mixture by seeded Monte Carlo), and whether the report's 1-hour window is *moving*: each track is
cut into windows of ``window`` seconds from its first report, and a window is moving when
the median position-derived speed ``|y_k - y_{k-1}| / dt_k`` of its reports is at least
``moving_speed`` (m/s); else moored.

Forecasts at each horizon h: from every filtered state with at least 2 reports seen, to the
later report of the same track whose lead time is nearest h (within ±``tol`` h), with the
model's exact predictive at that lead (an IMM: the exact moments of its switching SDE given
the mode at the lead, :meth:`~torchsde_lti.IMMFilter.forecast`); the point forecast
is the predictive mean, the error its Euclidean distance to the report.

Every metric is a ratio of per-vessel sums, so that the paired bootstrap resamples
vessels (all tracks of an object together) and recomputes each metric for both models on
the same resample.

Built on :mod:`torchsde_lti.evaluation.predictive` (the predictive distributions) and
:mod:`torchsde_lti.evaluation.calibration` (HPD levels, the covariance inflation ``cov_scale``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchsde_lti.data.loaded_tracks import Tracks
from torchsde_lti.data.tracks import TrackBatch
from torchsde_lti.evaluation.calibration import NOMINAL_2SIGMA, OnlineScale, hpd_level, online_scales, scale_vector
from torchsde_lti.evaluation.predictive import (
    Model,
    _forecast,
    frozen_copy,
    mixture_log_prob,
    predictive_batches,
    predictive_dof,
)
from torchsde_lti.nn.imm import IMMFilter

__all__ = [
    "HORIZONS",
    "EvalRecords",
    "evaluate_filter",
    "evaluate_models",
    "forecast_pairs",
    "hpd_inside",
    "moving_reports",
    "paired_bootstrap",
    "summary",
    "vessel_sums",
]

#: Forecast horizons (s) of :func:`evaluate_filter`: 5, 10, 15 min.
HORIZONS: tuple[float, ...] = (300.0, 600.0, 900.0)


@dataclass
class EvalRecords:
    """Per-report and per-forecast arrays of one model on one data set (numpy, float64).

    vessel: (N,) vessel index of each scored report; nll: (N,) -log p(y_k | y_<k);
    moving: (N,) bool, the report's window is moving; inside: (N,) bool, y_k in the 86.5 %
    HPD region; sq_err: (N,) squared one-step error of the predictive mean;
    fc: horizon (s) -> (vessel (P,), squared forecast error (P,), inside (P,): 1.0 / 0.0, NaN
    when not tested).
    n_vessels: the number of vessels (indices 0 .. n_vessels - 1).
    """

    vessel: np.ndarray
    nll: np.ndarray
    moving: np.ndarray
    inside: np.ndarray
    sq_err: np.ndarray
    fc: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict)
    n_vessels: int = 0


# --------------------------------------------------------------------------- pieces


def hpd_inside(
    y: Tensor,
    w: Tensor,
    mu: Tensor,
    S: Tensor,
    level: float = NOMINAL_2SIGMA,
    samples: int = 500,
    seed: int = 0,
    chunk: int = 2000,
    dof: Tensor | float | None = None,
) -> Tensor:
    """Is y inside the ``level`` highest-density region of the predictive mixture? (N,) bool.

    One component: the ellipse of Mahalanobis² <= the chi-square quantile at ``level`` (the 2σ
    ellipse in 2-D for the default level), in closed form. Otherwise: y is inside when the
    share of ``samples`` seeded draws from the mixture with a higher density than y is at most
    ``level`` (:func:`~torchsde_lti.evaluation.calibration.hpd_level`).

    Args:
        y: (N, m) observations; w: (N, M) weights; mu: (N, M, m); S: (N, M, m, m).
        level: the probability of the region (default 1 - e^-2 = 86.5 %, 2σ in 2-D).
        dof: None (Gaussian components) or ν of Student-t components (a filter with
            ``noise=tl.StudentT``): one component's region is then ``D² ≤ m F⁻¹(level; m, ν)``.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    return hpd_level(y, w, mu, S, samples=samples, seed=seed, chunk=chunk, dof=dof) <= level


def moving_reports(
    t: np.ndarray, pos: np.ndarray, offsets: np.ndarray, window: float = 3600.0, moving_speed: float = 1.0
) -> np.ndarray:
    """Is each report's window moving? (N,) bool over the flat reports of tracks.

    Each track (reports ``offsets[i]:offsets[i+1]``) is cut into windows of ``window`` s from
    its first report; a window is moving when the median of ``|pos_k - pos_{k-1}| / (t_k -
    t_{k-1})`` over its reports k (not a track's first) is >= ``moving_speed``. A track's
    first report takes its window's label (False for a window without a speed).

    Args:
        t: (N,) seconds, increasing within each track; pos: (N, d) metres; offsets: (S + 1,).
    """
    n = len(t)
    lengths = np.diff(offsets)
    owner = np.repeat(np.arange(len(lengths)), lengths)
    first = np.zeros(n, dtype=bool)
    first[offsets[:-1][lengths > 0]] = True
    start_t = np.repeat(t[offsets[:-1]], lengths)
    win = np.floor((t - start_t) / window).astype(np.int64)
    key = owner.astype(np.int64) * (int(win.max(initial=0)) + 1) + win
    speed = np.full(n, np.nan)
    dt = np.diff(t)
    step = np.linalg.norm(np.diff(pos, axis=0), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        speed[1:] = np.where(first[1:], np.nan, step / dt)
    ok = ~np.isnan(speed)
    uniq, inv = np.unique(key, return_inverse=True)
    kk, ss = inv[ok], speed[ok]
    order = np.lexsort((ss, kk))
    kk, ss = kk[order], ss[order]
    starts = np.searchsorted(kk, np.arange(len(uniq)), side="left")
    counts = np.searchsorted(kk, np.arange(len(uniq)), side="right") - starts
    med = np.full(len(uniq), np.nan)
    has = counts > 0
    lo_i = starts[has] + (counts[has] - 1) // 2
    hi_i = starts[has] + counts[has] // 2
    med[has] = 0.5 * (ss[lo_i] + ss[hi_i])
    return np.nan_to_num(med[inv], nan=-np.inf) >= moving_speed


def forecast_pairs(batch: TrackBatch, horizon: float, tol: float = 0.25) -> tuple[Tensor, Tensor, Tensor]:
    """Forecast origins (b, k), k >= 1, and their targets j: the report with lead t_j - t_k nearest ``horizon``.

    Returns index tensors b, k, j (P,) of the pairs with ``|lead - horizon| <= tol · horizon``
    (memory O(B T): the nearest later report is one of the two neighbours ``searchsorted`` finds).
    """
    if batch.t is None:
        raise ValueError("forecast_pairs needs batch.t (report times), got a TrackBatch without t")
    t, mask = batch.t.contiguous(), batch.mask
    B, T = t.shape
    hi = torch.searchsorted(t, (t + horizon).contiguous())
    last = (batch.lengths - 1).clamp_min(0)[:, None, None]
    cand = torch.stack([hi - 1, hi], dim=-1).clamp_min(0).minimum(last)  # (B, T, 2)
    tc = torch.gather(t, 1, cand.reshape(B, -1)).reshape(B, T, 2)
    k_idx = torch.arange(T)
    ok = (cand > k_idx[None, :, None]) & torch.gather(mask, 1, cand.reshape(B, -1)).reshape(B, T, 2)
    gap = torch.where(ok, (tc - t[..., None] - horizon).abs(), torch.full_like(tc, math.inf))
    best, which = gap.min(dim=-1)
    j = cand.gather(-1, which.unsqueeze(-1)).squeeze(-1)
    sel = (best <= tol * horizon) & mask & (k_idx[None, :] >= 1)
    b, k = sel.nonzero(as_tuple=True)
    return b, k, j[b, k]


def evaluate_filter(
    model: Model,
    tracks: Tracks,
    horizons: Sequence[float] = HORIZONS,
    window: float = 3600.0,
    moving_speed: float = 1.0,
    max_steps: int = 50_000,
    samples: int = 500,
    seed: int = 0,
    forecast_coverage: bool = False,
    cov_scale: float | Sequence[float] = 1.0,
    online_scale: OnlineScale | None = None,
) -> EvalRecords:
    """Per-report and per-forecast records of one frozen filter on whole tracks (module docstring).

    Args:
        model: a position-observing :class:`~torchsde_lti.KalmanFilter` or
            :class:`~torchsde_lti.IMMFilter` (run in float64, no gradients).
        tracks: the evaluation tracks (:func:`~torchsde_lti.data.load_tracks`); every track
            of an ``object_id`` is one vessel of the bootstrap.
        horizons: forecast horizons (s); window, moving_speed: the moving-window rule.
        max_steps: B x T of a padded batch; samples, seed: Monte Carlo of the mixture HPD region.
        forecast_coverage: also test the forecasts against their HPD regions (``fc_cover2s_<min>``;
            Monte Carlo for a mixture, so off by default; NaN when off).
        cov_scale: the calibrated predictive: component j's covariance (one-step and forecast)
            times c_j > 0 (one number for all, or one per mode), the means and weights
            unchanged; the NLL and the HPD tests use it
            (:func:`~torchsde_lti.evaluation.calibration.calibrate_filter` fits it on validation
            tracks). 1.0: the filter's own predictive.
        online_scale: a scale per track adapted online from the track's past reports
            (:class:`~torchsde_lti.evaluation.OnlineScale`), on top of ``cov_scale``: report k's
            predictive times the scale before k, a forecast from k times the scale after k.
            None: no adaptation.
    """
    M = len(model.modes()) if isinstance(model, IMMFilter) else 1
    try:
        scale = scale_vector(cov_scale, M)
    except ValueError as e:
        raise ValueError(f"cov_scale: {e}") from None
    unit = bool(torch.all(scale == 1.0))  # the filter's own predictive: its log-likelihood is the NLL
    model = frozen_copy(model)
    dof = predictive_dof(model)
    _, vessel_of_track = np.unique(tracks.object_id, return_inverse=True)
    lengths = np.diff(tracks.offsets)
    vessel_flat = np.repeat(vessel_of_track, lengths)
    moving_flat = moving_reports(tracks.t, tracks.pos[:, :2], tracks.offsets, window, moving_speed)
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("vessel", "nll", "moving", "inside", "sq_err")}
    fc_parts: dict[float, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {h: [] for h in horizons}
    with torch.no_grad():
        for batch, idx, out, w, ym, S, m in predictive_batches(model, tracks, max_steps):
            flat = idx[m.numpy()]
            point = (w.unsqueeze(-1) * ym).sum(-2)
            parts["vessel"].append(vessel_flat[flat])
            parts["moving"].append(moving_flat[flat])
            if not unit:
                S = scale[:, None, None] * S
            after = None
            if online_scale is not None:
                before, after = online_scales(online_scale, batch.y, w, ym, S, m, samples=samples, seed=seed, dof=dof)
                S = before[..., None, None, None] * S
            if unit and online_scale is None:
                parts["nll"].append((-out.step_log_likelihood[m]).numpy())
            else:
                parts["nll"].append((-mixture_log_prob(batch.y[m], w[m], ym[m], S[m], dof)).numpy())
            parts["sq_err"].append((batch.y - point)[m].pow(2).sum(-1).numpy())
            parts["inside"].append(
                hpd_inside(batch.y[m], w[m], ym[m], S[m], samples=samples, seed=seed, dof=dof).numpy()
            )
            for h in horizons:
                b, k, j = forecast_pairs(batch, h)
                if len(b) == 0:
                    continue
                t = batch.t if batch.t is not None else torch.cumsum(batch.dt, dim=-1)
                lead = t[b, j] - t[b, k]
                fw, fm, fS = _forecast(model, out, b, k, lead)
                fS = scale[:, None, None] * fS
                if after is not None:
                    fS = after[b, k, None, None, None] * fS
                yj = batch.y[b, j]
                err = ((fw.unsqueeze(-1) * fm).sum(-2) - yj).pow(2).sum(-1)
                ins = (
                    hpd_inside(yj, fw, fm, fS, samples=samples, seed=seed, dof=dof)
                    if forecast_coverage
                    else torch.full((len(b),), math.nan, dtype=torch.float64)
                )
                fc_parts[h].append((vessel_flat[idx[b.numpy(), k.numpy()]], err.numpy(), ins.numpy()))
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in parts.items()}

    def joined(v: list[tuple[np.ndarray, np.ndarray, np.ndarray]], i: int) -> np.ndarray:
        return np.concatenate([p[i] for p in v]) if v else np.zeros(0, dtype=np.int64 if i == 0 else np.float64)

    fc = {h: (joined(v, 0), joined(v, 1), joined(v, 2)) for h, v in fc_parts.items()}
    return EvalRecords(
        cat["vessel"].astype(np.int64),
        cat["nll"],
        cat["moving"].astype(bool),
        cat["inside"].astype(bool),
        cat["sq_err"],
        fc,
        int(vessel_of_track.max(initial=-1)) + 1,
    )


def evaluate_models(models: Mapping[str, Model], tracks: Tracks, **kwargs: Any) -> dict[str, EvalRecords]:
    """:func:`evaluate_filter` of every model on the same tracks."""
    return {name: evaluate_filter(model, tracks, **kwargs) for name, model in models.items()}


# --------------------------------------------------------------------------- metrics


def _key(h: float) -> str:
    return f"{h / 60:g}"


def vessel_sums(rec: EvalRecords) -> dict[str, tuple[np.ndarray, np.ndarray, str]]:
    """Each metric as per-vessel (numerator (V,), denominator (V,), kind): kind "mean" is
    num/den, "rmse" is sqrt(num/den). Metrics: nll, nll_moving, nll_moored, cover2s,
    cover2s_moving, rmse1, fc_rmse_<min>, fc_cover2s_<min>."""
    V = rec.n_vessels

    def s(x: np.ndarray, sel: np.ndarray | None = None, v: np.ndarray = rec.vessel) -> np.ndarray:
        if sel is not None:
            x, v = x[sel], v[sel]
        return np.bincount(v, weights=x.astype(np.float64), minlength=V)

    one = np.ones_like(rec.nll)
    out: dict[str, tuple[np.ndarray, np.ndarray, str]] = {
        "nll": (s(rec.nll), s(one), "mean"),
        "nll_moving": (s(rec.nll, rec.moving), s(one, rec.moving), "mean"),
        "nll_moored": (s(rec.nll, ~rec.moving), s(one, ~rec.moving), "mean"),
        "cover2s": (s(rec.inside), s(one), "mean"),
        "cover2s_moving": (s(rec.inside, rec.moving), s(one, rec.moving), "mean"),
        "cover2s_moored": (s(rec.inside, ~rec.moving), s(one, ~rec.moving), "mean"),
        "rmse1": (s(rec.sq_err), s(one), "rmse"),
    }
    for h, (v, sq, ins) in rec.fc.items():
        ones = np.ones_like(sq)
        out[f"fc_rmse_{_key(h)}"] = (s(sq, v=v), s(ones, v=v), "rmse")
        out[f"fc_cover2s_{_key(h)}"] = (s(ins, v=v), s(ones, v=v), "mean")
    return out


def _value(num: np.ndarray, den: np.ndarray, kind: str) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        r = num.sum(-1) / den.sum(-1)
    return np.sqrt(r) if kind == "rmse" else r


def summary(rec: EvalRecords) -> dict[str, float]:
    """Every metric of :func:`vessel_sums` over all vessels (NaN where nothing is counted), and
    the counts ``reports``, ``reports_moving``, ``vessels`` and ``fc_n_<min>``."""
    res = {k: float(_value(n, d, kind)) for k, (n, d, kind) in vessel_sums(rec).items()}
    res.update(reports=int(rec.nll.size), reports_moving=int(rec.moving.sum()), vessels=int(rec.n_vessels))
    for h, (v, _, _) in rec.fc.items():
        res[f"fc_n_{_key(h)}"] = int(v.size)
    return res


def paired_bootstrap(
    a: EvalRecords,
    b: EvalRecords,
    metrics: Sequence[str] | None = None,
    n_boot: int = 2000,
    seed: int = 0,
    level: float = 0.95,
) -> dict[str, dict[str, float]]:
    """Metric of a minus metric of b, with a percentile interval from resampling VESSELS (paired).

    Both records must score the same reports (same data, so the same vessels and pairs).
    Returns {metric: {"delta", "lo", "hi", "p_ge_0"}} (delta on all vessels; lo, hi the
    ``level`` percentile interval; p_ge_0 the share of resamples with a - b >= 0).
    """
    if a.n_vessels != b.n_vessels or a.nll.shape != b.nll.shape:
        raise ValueError(
            f"a and b must score the same reports: {a.n_vessels} vs {b.n_vessels} vessels, "
            f"{a.nll.size} vs {b.nll.size} reports"
        )
    sa, sb = vessel_sums(a), vessel_sums(b)
    names = list(sa) if metrics is None else list(metrics)
    V = a.n_vessels
    rng = np.random.default_rng(seed)
    counts = np.stack([np.bincount(rng.integers(0, V, V), minlength=V) for _ in range(n_boot)]).astype(np.float64)
    q = 100 * (1 - level) / 2
    res: dict[str, dict[str, float]] = {}
    for name in names:
        (na, da, kind), (nb, db, _) = sa[name], sb[name]
        est = float(_value(na, da, kind) - _value(nb, db, kind))
        with np.errstate(divide="ignore", invalid="ignore"):
            ra, rb = (counts @ na) / (counts @ da), (counts @ nb) / (counts @ db)
        if kind == "rmse":
            ra, rb = np.sqrt(ra), np.sqrt(rb)
        diff = (ra - rb)[np.isfinite(ra - rb)]
        lo, hi = np.percentile(diff, [q, 100 - q]) if diff.size else (math.nan, math.nan)
        res[name] = {
            "delta": est,
            "lo": float(lo),
            "hi": float(hi),
            "p_ge_0": float((diff >= 0).mean()) if diff.size else math.nan,
        }
    return res
