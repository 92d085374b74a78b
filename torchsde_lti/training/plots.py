"""The figures of a run, drawn by :func:`plot_run` after training (matplotlib, Agg):

- ``loss.png`` and ``params.png`` from the CSV logger's ``metrics.csv`` (``train/nll``,
  ``val/nll``, ``param/<name>``: no CSV logger, no figure), drawn by
  :func:`torchsde_lti.evaluation.history_figures.history_figures`;
- the filter's figures on the first validation batch (the filter's own validation data):
  ``map.png`` or ``track.png``, ``modes.png`` (an IMM) and ``forecast.png``, drawn by
  :func:`torchsde_lti.evaluation.figures.track_figures` (see there).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

from torchsde_lti.evaluation.figures import track_figures
from torchsde_lti.evaluation.history_figures import history_figures
from torchsde_lti.training.module import KalmanFilterModule

__all__ = ["epoch_rows", "plot_run"]


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

    Raises:
        TypeError: the module's filter is neither a KalmanFilter nor an IMMFilter (from
            :func:`~torchsde_lti.evaluation.track_figures`).
    """
    history = epoch_rows(metrics_csv) if metrics_csv is not None and Path(metrics_csv).is_file() else []
    kf = module.kf
    paths = history_figures(out_dir, kf, history, truth, module.param_names) if history else []
    y, dt, mask, u, x = module.unpack(next(iter(datamodule.val_dataloader())))
    H_true = truth.get("H") if truth else None
    metres = not truth  # real tracks (no simulated truth) are in metres and seconds
    return [*paths, *track_figures(out_dir, kf, y, dt, mask, u, x, H_true, metres)]
