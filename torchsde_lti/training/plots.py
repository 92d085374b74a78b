"""The figures of a run, drawn by :func:`plot_run` after training (matplotlib, Agg):

- ``loss.png``: train/val NLL per epoch; ``params.png``: each learned value per epoch (and the
  true one, when the learner and the truth are the same kind of model), both read from the CSV
  logger's ``metrics.csv`` (``train/nll``, ``val/nll``, ``param/<name>``: no CSV logger, no figure);
- ``map.png`` (2-D or 3-D observations): a few validation tracks in their own east/north frame
  (metres for real tracks), the reports, the filtered and smoothed paths and the filtered 2σ
  ellipses of the position (the true path, for simulated data); the tracks shown are those that
  move furthest from their first report (a moored ship is a dot: not one to look at);
- ``track.png`` (1-D observations): the same track against time, means ±2σ;
- ``modes.png`` (an IMM): the filtered mode probabilities of those tracks over time;
- ``forecast.png``: the forecast error ‖y(t + τ) − ŷ(t + τ | t)‖ against the lead time τ, from
  every validation state past its second report to the next reports (binned root mean square), beside the RMS spread
  √tr S the filter predicts for it.

All figures come from the first validation batch: the filter's own validation data.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchsde_lti.evaluation import flat_values, learned_values, same_model
from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import KalmanFilter
from torchsde_lti.training.module import KalmanFilterModule

__all__ = ["epoch_rows", "plot_run"]

#: Tracks drawn on the map (and in the mode plot).
MAP_TRACKS = 4
#: Ellipses drawn along each track on the map.
ELLIPSES = 8
#: Forecast origins x horizons per forecast call (keeps the forecast figure's memory bounded).
FORECAST_BUDGET = 200_000
#: Reports ahead that the forecast figure looks at.
FORECAST_STEPS = 12


def _filter(module: KalmanFilterModule) -> KalmanFilter | IMMFilter:
    kf = module.kf
    if not isinstance(kf, (KalmanFilter, IMMFilter)):
        raise TypeError(f"plot_run draws a KalmanFilter's or an IMMFilter's run, got a {type(kf).__name__}")
    return kf


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    _pyplot().close(fig)
    return path


def epoch_rows(metrics_csv: Path) -> list[dict[str, float]]:
    """The epoch-level values of a CSV logger's ``metrics.csv``, one dict per epoch (Lightning
    writes an epoch's training and validation values in rows of their own), in epoch order."""
    epochs: dict[int, dict[str, float]] = {}
    with Path(metrics_csv).open(newline="") as f:
        for row in csv.DictReader(f):
            if row.get("epoch"):
                values = {k: float(v) for k, v in row.items() if v and k not in ("epoch", "step")}
                epochs.setdefault(int(float(row["epoch"])), {}).update(values)
    return [{"epoch": float(e), **epochs[e]} for e in sorted(epochs)]


def _history_plots(
    out_dir: Path, module: KalmanFilterModule, history: list[dict[str, float]], truth: Any
) -> list[Path]:
    """loss.png and params.png from the per-epoch values (:func:`epoch_rows`)."""
    plt = _pyplot()
    epochs = [r["epoch"] for r in history]
    fig, ax = plt.subplots(figsize=(6, 4))
    for key in ("train/nll", "val/nll"):
        ax.plot(epochs, [r.get(key, math.nan) for r in history], label=key)
    ax.set_xlabel("epoch")
    ax.set_ylabel("NLL per observed scalar")
    ax.legend()
    paths = [_save(fig, out_dir / "loss.png")]
    names = sorted({k.removeprefix("param/") for r in history for k in r if k.startswith("param/")})
    if not names:
        return paths
    true: dict[str, float] = {}
    modes = _filter(module).modes()
    if truth and len(modes) == 1:  # a truth is one model: it pairs with a single-model filter only
        paired = same_model(modes[0].sde, truth["sde"])
        true = flat_values(learned_values(truth["sde"], truth.get("R"), module.param_names if paired else []))
    cols = min(len(names), 4)
    rows = math.ceil(len(names) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    for ax, name in zip(axes.flat, names):
        ax.plot(epochs, [r.get(f"param/{name}", math.nan) for r in history], label="learned")
        if name in true:
            ax.axhline(true[name], color="k", ls="--", label="true")
        ax.set_title(name)
        ax.set_xlabel("epoch")
    for ax in list(axes.flat)[len(names) :]:
        ax.axis("off")
    axes.flat[0].legend()
    return [*paths, _save(fig, out_dir / "params.png")]


def _validation_batch(module: KalmanFilterModule, datamodule: Any) -> dict[str, Any]:
    """The first validation batch, padded steps made "no report, no motion" (as in training),
    run through the filter (and its smoother, where it has one)."""
    y, dt, mask, u, x = module.unpack(next(iter(datamodule.val_dataloader())))
    if mask is None:
        mask = torch.ones(y.shape[:-1], dtype=torch.bool)
    y = torch.where(mask.unsqueeze(-1), y, torch.full_like(y, math.nan))
    dt = torch.where(mask, dt, torch.zeros_like(dt))
    kf = _filter(module)
    with torch.no_grad():
        out = kf(y, dt, u=u)
        smooth = getattr(kf, "smooth", None)
        sm = smooth(out) if smooth is not None else None
    H = kf.modes()[0].H.detach().to(y.dtype)  # the combined mean through the first mode's H
    return {"y": y, "dt": dt, "mask": mask, "u": u, "x": x, "out": out, "smoothed": sm, "H": H}


def _moving_tracks(y: Tensor, mask: Tensor, k: int) -> list[int]:
    """The ``k`` tracks whose reports get furthest from their first one (moored ones last)."""
    first = y[:, :1, :]
    reach = torch.linalg.vector_norm(torch.nan_to_num(y - first), dim=-1).masked_fill(~mask, 0).amax(-1)
    return torch.argsort(reach, descending=True, stable=True)[:k].tolist()


def _true_observation(batch: dict[str, Any], truth: Any) -> Tensor | None:
    """H_true x of the true states, when the data carry them: the truth's own observation
    matrix, whose state may differ from the learner's (``model=cv truth=singer``)."""
    x = batch["x"]
    if x is None:
        return None
    H_true = truth.get("H") if truth else None
    if H_true is None:
        H_true = batch["H"]
    H_true = H_true.detach().to(x.dtype)
    if H_true.shape[-1] != x.shape[-1]:
        return None
    return x @ H_true.mT


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


def _map_plot(out_dir: Path, batch: dict[str, Any], tracks: list[int], truth: Any, metres: bool) -> Path:
    """map.png: one panel per track, east/north (the first two observed components)."""
    plt = _pyplot()
    H, out, sm = batch["H"], batch["out"], batch["smoothed"]
    true = _true_observation(batch, truth)
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
    return _save(fig, out_dir / "map.png")


def _time_plot(out_dir: Path, batch: dict[str, Any], b: int, truth: Any) -> Path:
    """track.png: one track's observation against time, filtered and smoothed means ±2σ."""
    plt = _pyplot()
    H, out, sm = batch["H"], batch["out"], batch["smoothed"]
    T = int(batch["mask"][b].sum())
    t = torch.cumsum(batch["dt"][b, :T], 0)
    true = _true_observation(batch, truth)
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
    return _save(fig, out_dir / "track.png")


def _modes_plot(out_dir: Path, batch: dict[str, Any], tracks: list[int], names: list[str], seconds: bool) -> Path:
    """modes.png: each shown track's filtered mode probabilities against time."""
    plt = _pyplot()
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
    return _save(fig, out_dir / "modes.png")


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
    plt = _pyplot()
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
    return _save(fig, out_dir / "forecast.png")


def plot_run(
    out_dir: Path, module: KalmanFilterModule, datamodule: Any, truth: Any, metrics_csv: Path | None = None
) -> list[Path]:
    """Draw the run's figures (module docstring) into ``out_dir``; returns their paths.

    Args:
        out_dir: the run directory.
        module: the trained module (its filter ``module.kf``).
        datamodule: the run's data (its first validation batch is drawn).
        truth: the simulated truth ({"sde", "R", "H"}) or None.
        metrics_csv: the CSV logger's ``metrics.csv`` (None or missing: no loss / parameter figure).
    """
    history = epoch_rows(metrics_csv) if metrics_csv is not None and Path(metrics_csv).is_file() else []
    paths = _history_plots(out_dir, module, history, truth) if history else []
    batch = _validation_batch(module, datamodule)
    metres = not truth  # real tracks (no simulated truth) are in metres and seconds
    tracks = _moving_tracks(batch["y"], batch["mask"], MAP_TRACKS)
    if batch["y"].shape[-1] >= 2:
        paths.append(_map_plot(out_dir, batch, tracks, truth, metres))
    else:
        paths.append(_time_plot(out_dir, batch, tracks[0], truth))
    if isinstance(module.kf, IMMFilter):
        paths.append(_modes_plot(out_dir, batch, tracks, list(module.kf.mode_names), metres))
    if batch["u"] is None:  # (with inputs, a forecast needs them over the horizon)
        forecast = _forecast_plot(out_dir, module.kf, batch, metres)
        paths += [forecast] if forecast is not None else []
    return paths
