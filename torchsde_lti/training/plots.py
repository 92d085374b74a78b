"""The figures of a run, drawn by :func:`plot_run` after training (matplotlib, Agg):

- ``loss.png``: train/val NLL per epoch; ``params.png``: each learned value per epoch (and the
  true one, when the learner and the truth are the same kind of model), both read from the CSV
  logger's ``metrics.csv`` (``train/nll``, ``val/nll``, ``param/<name>``: no CSV logger, no figure);
- the filter's figures on the first validation batch (the filter's own validation data):
  ``map.png`` or ``track.png``, ``modes.png`` (an IMM) and ``forecast.png``, drawn by
  :func:`torchsde_lti.evaluation.figures.track_figures` (see there).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

from torchsde_lti.evaluation import flat_values, learned_values, same_model
from torchsde_lti.evaluation.figures import pyplot, save_figure, track_figures
from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import KalmanFilter
from torchsde_lti.training.module import KalmanFilterModule

__all__ = ["epoch_rows", "plot_run"]


def _filter(module: KalmanFilterModule) -> KalmanFilter | IMMFilter:
    kf = module.kf
    if not isinstance(kf, (KalmanFilter, IMMFilter)):
        raise TypeError(f"plot_run draws a KalmanFilter's or an IMMFilter's run, got a {type(kf).__name__}")
    return kf


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
    plt = pyplot()
    epochs = [r["epoch"] for r in history]
    fig, ax = plt.subplots(figsize=(6, 4))
    for key in ("train/nll", "val/nll"):
        ax.plot(epochs, [r.get(key, math.nan) for r in history], label=key)
    ax.set_xlabel("epoch")
    ax.set_ylabel("NLL per observed scalar")
    ax.legend()
    paths = [save_figure(fig, out_dir / "loss.png")]
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
    return [*paths, save_figure(fig, out_dir / "params.png")]


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
    y, dt, mask, u, x = module.unpack(next(iter(datamodule.val_dataloader())))
    H_true = truth.get("H") if truth else None
    metres = not truth  # real tracks (no simulated truth) are in metres and seconds
    return [*paths, *track_figures(out_dir, _filter(module), y, dt, mask, u, x, H_true, metres)]
