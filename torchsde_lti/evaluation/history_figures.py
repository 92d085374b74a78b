"""Figures of a training history (matplotlib, Agg), drawn by :func:`history_figures`:

- ``loss.png``: train/val NLL per epoch;
- ``params.png``: each learned value per epoch, beside the true one where the filter and the
  simulated truth are the same kind of model (parameter recovery at a glance).

The history is one dict of values per epoch (``train/nll``, ``val/nll``, ``param/<name>``): the
training job reads it from its CSV logger (:func:`torchsde_lti.training.plots.epoch_rows`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from torchsde_lti.evaluation.figures import pyplot, save_figure
from torchsde_lti.evaluation.recovery import flat_values, learned_values, same_model
from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import KalmanFilter

__all__ = ["history_figures"]


def history_figures(
    out_dir: Path,
    kf: KalmanFilter | IMMFilter,
    history: Sequence[Mapping[str, float]],
    truth: Mapping[str, Any] | None = None,
    param_names: Sequence[str] | None = None,
) -> list[Path]:
    """Draw ``loss.png`` and (where the history holds ``param/*`` values) ``params.png``.

    Args:
        out_dir: where the figures go.
        kf: the trained filter (a single-model filter pairs its values with the truth's).
        history: one dict per epoch, in order: ``epoch``, ``train/nll``, ``val/nll``, ``param/<name>``.
        truth: the simulated truth ({"sde", "R", ...}) or None.
        param_names: the learned scalars the run tracks (None: the model's own).

    Returns:
        The paths written.
    """
    plt = pyplot()
    epochs = [r["epoch"] for r in history]
    fig, ax = plt.subplots(figsize=(6, 4))
    for key in ("train/nll", "val/nll"):
        ax.plot(epochs, [r.get(key, math.nan) for r in history], label=key)
    ax.set_xlabel("epoch")
    ax.set_ylabel("NLL per observed scalar")
    ax.legend()
    paths = [save_figure(fig, Path(out_dir) / "loss.png")]
    names = sorted({k.removeprefix("param/") for r in history for k in r if k.startswith("param/")})
    if not names:
        return paths
    true: dict[str, float] = {}
    modes = kf.modes()
    if truth and len(modes) == 1:  # a truth is one model: it pairs with a single-model filter only
        paired = same_model(modes[0].sde, truth["sde"])
        true = flat_values(learned_values(truth["sde"], truth.get("R"), param_names if paired else []))
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
    return [*paths, save_figure(fig, Path(out_dir) / "params.png")]
