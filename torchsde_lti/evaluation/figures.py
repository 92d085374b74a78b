"""Figures of a filter on a batch of tracks (matplotlib, Agg), drawn by :func:`track_figures`:

- ``map.png`` (2-D or 3-D observations): a few tracks in their own east/north frame (metres for
  real tracks), the reports, the filtered and smoothed paths and the filtered 2σ ellipses of the
  position (the true path, where the data carry true states); the tracks shown are those that move
  furthest from their first report (a moored ship is a dot: not one to look at);
- ``track.png`` (1-D observations): the same track against time, means ±2σ;
- ``modes.png`` (an IMM): the filtered mode probabilities of those tracks over time;
- ``forecast.png``: the forecast error ‖y(t + τ) − ŷ(t + τ | t)‖ against the lead time τ, from
  every state past its second report to the next reports (binned root mean square), beside the
  RMS spread √tr S the filter predicts for it.

The training job draws them from its first validation batch
(:func:`torchsde_lti.training.plots.plot_run`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import KalmanFilter

__all__ = ["pyplot", "save_figure", "track_figures"]

#: Tracks drawn on the map (and in the mode plot).
MAP_TRACKS = 4
#: Ellipses drawn along each track on the map.
ELLIPSES = 8
#: Forecast origins x horizons per forecast call (keeps the forecast figure's memory bounded).
FORECAST_BUDGET = 200_000
#: Reports ahead that the forecast figure looks at.
FORECAST_STEPS = 12


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (files, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: Path) -> Path:
    """Write ``fig`` to ``path`` (100 dpi) and close it; returns ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    pyplot().close(fig)
    return path


def _moving_tracks(y: Tensor, mask: Tensor, k: int) -> list[int]:
    """The ``k`` tracks whose reports get furthest from their first one (moored ones last)."""
    first = y[:, :1, :]
    reach = torch.linalg.vector_norm(torch.nan_to_num(y - first), dim=-1).masked_fill(~mask, 0).amax(-1)
    return torch.argsort(reach, descending=True, stable=True)[:k].tolist()


def _true_observation(x: Tensor | None, H_true: Tensor) -> Tensor | None:
    """H_true x of the true states x (B, T, n_true), when the data carry them and H_true's
    state is theirs (the truth's own observation matrix may differ from the learner's:
    ``model=cv truth=singer``)."""
    if x is None:
        return None
    H_true = H_true.detach().to(x.dtype)
    return x @ H_true.mT if H_true.shape[-1] == x.shape[-1] else None


def _ellipse(ax: Any, center: Tensor, cov: Tensor, color: str) -> None:
    """The 2σ ellipse {p: (p - c)ᵀ cov⁻¹ (p - c) <= 4} of a 2 x 2 covariance."""
    from matplotlib.patches import Ellipse

    values, vectors = torch.linalg.eigh(0.5 * (cov + cov.mT))
    width, height = (4.0 * values.clamp_min(0).sqrt()).tolist()[::-1]
    angle = math.degrees(math.atan2(float(vectors[1, 1]), float(vectors[0, 1])))
    x, y = center.tolist()
    ax.add_patch(Ellipse((x, y), width, height, angle=angle, fill=False, color=color, lw=0.8, alpha=0.7))


def _frame(ax: Any, paths: list[Tensor]) -> None:
    """Equal axes around the paths (10 % margin): an ellipse larger than the track is cut."""
    points = torch.cat([p[~torch.isnan(p).any(-1)] for p in paths])
    low, high = points.amin(0), points.amax(0)
    half = max(float((high - low).max()) * 0.55, 1e-9)
    center = 0.5 * (low + high)
    ax.set_xlim(float(center[0]) - half, float(center[0]) + half)
    ax.set_ylim(float(center[1]) - half, float(center[1]) + half)
    ax.set_aspect("equal", adjustable="box")


def _map_plot(out_dir: Path, batch: dict[str, Any], tracks: list[int], metres: bool) -> Path:
    """map.png: one panel per track, east/north (the first two observed components)."""
    plt = pyplot()
    H, out, sm = batch["H"], batch["out"], batch["smoothed"]
    true = batch["true"]
    cols = min(len(tracks), 2)
    rows = math.ceil(len(tracks) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.6 * rows), squeeze=False)
    for ax, b in zip(axes.flat, tracks):
        T = int(batch["mask"][b].sum())
        obs = batch["y"][b, :T, :2]
        filtered = (out.mean[b, :T] @ H.mT)[:, :2]
        ax.plot(obs[:, 0], obs[:, 1], "k.", ms=4, label="reports")
        if true is not None:
            ax.plot(true[b, :T, 0], true[b, :T, 1], "k--", lw=1, label="true path")
        ax.plot(filtered[:, 0], filtered[:, 1], color="C0", lw=1.2, label="filtered")
        drawn = [obs, filtered] + ([true[b, :T, :2]] if true is not None else [])
        if sm is not None:
            smoothed = (sm.mean[b, :T] @ H.mT)[:, :2]
            ax.plot(smoothed[:, 0], smoothed[:, 1], color="C1", lw=1.2, label="smoothed")
            drawn.append(smoothed)
        P = (H @ out.cov[b, :T] @ H.mT)[:, :2, :2]
        seen = torch.nonzero(~torch.isnan(obs).any(-1)).flatten().tolist()  # (a missing report's is the prior's)
        for t in sorted(
            {seen[round(i * (len(seen) - 1) / max(ELLIPSES - 1, 1))] for i in range(ELLIPSES)} if seen else ()
        ):
            _ellipse(ax, filtered[t], P[t], "C0")
        _frame(ax, drawn)
        ax.set_xlabel("east (m)" if metres else "y[0]")
        ax.set_ylabel("north (m)" if metres else "y[1]")
        ax.set_title(f"validation track {b} ({T} reports)")
    for ax in list(axes.flat)[len(tracks) :]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7, title="ellipses: filtered 2σ", title_fontsize=7)
    return save_figure(fig, out_dir / "map.png")


def _time_plot(out_dir: Path, batch: dict[str, Any], b: int) -> Path:
    """track.png: one track's observation against time, filtered and smoothed means ±2σ."""
    plt = pyplot()
    H, out, sm = batch["H"], batch["out"], batch["smoothed"]
    T = int(batch["mask"][b].sum())
    t = torch.cumsum(batch["dt"][b, :T], 0)
    true = batch["true"]
    m = batch["y"].shape[-1]
    fig, axes = plt.subplots(m, 1, figsize=(8, 2.4 * m), sharex=True, squeeze=False)
    for i, ax in enumerate(axes[:, 0]):
        h = H[i]
        curves = [("filtered", out.mean[b, :T], out.cov[b, :T], "C0")]
        if sm is not None:
            curves.append(("smoothed", sm.mean[b, :T], sm.cov[b, :T], "C1"))
        for label, mean, cov, color in curves:
            mu = mean @ h
            sd = torch.einsum("i,tij,j->t", h, cov, h).clamp_min(0).sqrt()
            ax.plot(t, mu, color=color, label=f"{label} mean")
            ax.fill_between(t, mu - 2 * sd, mu + 2 * sd, color=color, alpha=0.2, label=f"{label} ±2σ")
        if true is not None:
            ax.plot(t, true[b, :T, i], "k--", lw=1, label="true")
        ax.plot(t, batch["y"][b, :T, i], "k.", ms=4, label="reports")
        ax.set_ylabel(f"y[{i}]")
    axes[-1, 0].set_xlabel("time")
    axes[0, 0].legend(fontsize=7, ncol=3)
    return save_figure(fig, out_dir / "track.png")


def _modes_plot(out_dir: Path, batch: dict[str, Any], tracks: list[int], names: list[str], seconds: bool) -> Path:
    """modes.png: each shown track's filtered mode probabilities against time."""
    plt = pyplot()
    probs = batch["out"].mode_probabilities
    fig, axes = plt.subplots(len(tracks), 1, figsize=(8, 1.9 * len(tracks)), sharey=True, squeeze=False)
    for ax, b in zip(axes[:, 0], tracks):
        T = int(batch["mask"][b].sum())
        t = torch.cumsum(batch["dt"][b, :T], 0)
        ax.stackplot(t, probs[b, :T].mT, labels=names, alpha=0.8)
        ax.set_ylim(0, 1)
        ax.set_ylabel(f"track {b}")
    axes[-1, 0].set_xlabel("time since the first report (s)" if seconds else "time")
    axes[0, 0].legend(fontsize=7, ncol=len(names), loc="upper right")
    fig.suptitle("filtered mode probabilities")
    return save_figure(fig, out_dir / "modes.png")


def _forecast_errors(kf: Any, batch: dict[str, Any]) -> tuple[Tensor, Tensor, Tensor]:
    """(lead, error, spread) of every forecast from a validation state to one of the next
    :data:`FORECAST_STEPS` reports of its track, fully observed: ``lead`` τ, ``error``
    ‖y − ŷ‖ and ``spread`` √tr S (S the predicted observation covariance)."""
    y, mask, out = batch["y"], batch["mask"], batch["out"]
    B, T = mask.shape
    K = min(FORECAST_STEPS, T - 1)
    if K < 1:
        return (y.new_zeros(0),) * 3
    B = max(1, min(B, FORECAST_BUDGET // (T * K)))
    y, mask = y[:B], mask[:B]
    cs = torch.cumsum(batch["dt"][:B], -1)
    steps = torch.arange(T).unsqueeze(-1) + torch.arange(1, K + 1)  # (T, K): the target report
    inside = steps < T
    target = steps.clamp_max(T - 1)
    lead = torch.where(inside, cs[:, target] - cs[:, :T].unsqueeze(-1), torch.zeros(()))  # (B, T, K)
    if isinstance(kf, IMMFilter):
        state: Any = (out.mode_probabilities[:B], out.mode_mean[:B], out.mode_cov[:B])
    else:
        state = (out.mean[:B], out.cov[:B])
    with torch.no_grad():
        fc = kf.forecast(state, lead)
    truth = y[:, target]  # (B, T, K, m)
    seen = torch.cumsum((mask & ~torch.isnan(y).any(-1)).to(torch.int64), -1) >= 2  # (origins past the prior)
    valid = inside & mask[:, target] & seen.unsqueeze(-1) & ~torch.isnan(truth).any(-1)
    error = torch.linalg.vector_norm(torch.nan_to_num(truth - fc.obs_mean), dim=-1)
    spread = torch.diagonal(fc.obs_cov, dim1=-2, dim2=-1).sum(-1).clamp_min(0).sqrt()
    return lead[valid], error[valid], spread[valid]


def _forecast_plot(out_dir: Path, kf: Any, batch: dict[str, Any], metres: bool) -> Path | None:
    """forecast.png: RMS forecast error per lead-time bin, beside the predicted RMS spread
    (origins with two reports seen or more: not the prior's spread)."""
    lead, error, spread = _forecast_errors(kf, batch)
    if lead.numel() < 10:
        return None
    plt = pyplot()
    edges = torch.quantile(lead, torch.linspace(0, 1, 13, dtype=lead.dtype))
    which = torch.bucketize(lead, edges[1:-1])
    rows = []
    for k in range(len(edges) - 1):
        sel = which == k
        if sel.any():
            rows.append(
                (
                    float(lead[sel].median()),
                    float(error[sel].square().mean().sqrt()),
                    float(spread[sel].square().mean().sqrt()),
                )
            )
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot([r[0] for r in rows], [r[1] for r in rows], "o-", color="C0", label="RMS error ‖y − ŷ‖")
    ax.plot([r[0] for r in rows], [r[2] for r in rows], "s--", color="C1", label="predicted RMS spread √tr S")
    ax.set_xlabel("lead time (s)" if metres else "lead time")
    ax.set_ylabel("forecast error (m)" if metres else "forecast error")
    ax.set_title(f"forecasts 1-{FORECAST_STEPS} reports ahead, {lead.numel()} pairs")
    ax.legend()
    return save_figure(fig, out_dir / "forecast.png")


def track_figures(
    out_dir: Path,
    kf: KalmanFilter | IMMFilter,
    y: Tensor,
    dt: Tensor,
    mask: Tensor | None = None,
    u: Tensor | None = None,
    x: Tensor | None = None,
    H_true: Tensor | None = None,
    metres: bool = True,
) -> list[Path]:
    """Run ``kf`` (and its smoother) over the tracks and draw the figures of the module docstring
    into ``out_dir``; returns their paths.

    Args:
        out_dir: the folder the figures are written to.
        kf: the filter drawn.
        y: (B, T, m) observations, NaN where missing; dt: (B, T) steps.
        mask: (B, T) True where a step is real (None: all); padded steps are made "no report,
            no motion".
        u: (B, T, p) inputs or None (with inputs there is no forecast figure: a forecast needs
            them over the horizon).
        x: (B, T, n_true) true states or None (simulated data: the true path is drawn).
        H_true: the true states' observation matrix (None: the filter's own H).
        metres: label the axes in metres and seconds (real tracks).

    Raises:
        TypeError: ``kf`` is neither a KalmanFilter nor an IMMFilter.
    """
    if not isinstance(kf, (KalmanFilter, IMMFilter)):
        raise TypeError(f"track_figures draws a KalmanFilter or an IMMFilter, got a {type(kf).__name__}")
    if mask is None:
        mask = torch.ones(y.shape[:-1], dtype=torch.bool)
    y = torch.where(mask.unsqueeze(-1), y, torch.full_like(y, math.nan))
    dt = torch.where(mask, dt, torch.zeros_like(dt))
    with torch.no_grad():
        out = kf(y, dt, u=u)
        smooth = getattr(kf, "smooth", None)
        sm = smooth(out) if smooth is not None else None
    H = kf.modes()[0].H.detach().to(y.dtype)  # the combined mean through the first mode's H
    true = _true_observation(x, H if H_true is None else H_true)
    batch = {"y": y, "dt": dt, "mask": mask, "out": out, "smoothed": sm, "H": H, "true": true}
    tracks = _moving_tracks(y, mask, MAP_TRACKS)
    if y.shape[-1] >= 2:
        paths = [_map_plot(out_dir, batch, tracks, metres)]
    else:
        paths = [_time_plot(out_dir, batch, tracks[0])]
    if isinstance(kf, IMMFilter):
        paths.append(_modes_plot(out_dir, batch, tracks, list(kf.mode_names), metres))
    if u is None:
        forecast = _forecast_plot(out_dir, kf, batch, metres)
        paths += [forecast] if forecast is not None else []
    return paths
