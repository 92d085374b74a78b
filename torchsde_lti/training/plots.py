"""Plots of a run: loss curves, parameter trajectories against the truth, one filtered (and, where the
filter has a smoother, smoothed) track."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch

from torchsde_lti.training.metrics import flat_values, learned_values, same_model
from torchsde_lti.training.module import KalmanFilterModule

__all__ = ["plot_run"]


def _first_val_batch(datamodule: Any) -> Any:
    loader = datamodule.val_dataloader()
    return next(iter(loader))


def plot_run(
    out_dir: Path, module: KalmanFilterModule, datamodule: Any, history: list[dict[str, float]], truth: Any
) -> list[Path]:
    """Write loss.png, params.png and track.png into ``out_dir``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths: list[Path] = []
    if history:
        epochs = [r["epoch"] for r in history]
        fig, ax = plt.subplots(figsize=(6, 4))
        for key in ("train/nll", "val/nll"):
            ax.plot(epochs, [r.get(key, math.nan) for r in history], label=key)
        ax.set_xlabel("epoch")
        ax.set_ylabel("NLL per observed scalar")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out_dir / "loss.png", dpi=100)
        plt.close(fig)
        paths.append(out_dir / "loss.png")

        skip = {"epoch", "train/nll", "val/nll", "val/param_error"}
        names = [k for k in history[-1] if k not in skip]
        true = {}
        modes = module.kf.modes()
        if truth and len(modes) == 1:  # a truth is one model: it pairs with a single-model filter only
            paired = same_model(modes[0].sde, truth["sde"])
            true = flat_values(learned_values(truth["sde"], truth.get("R"), module.param_names if paired else []))
        if names:
            cols = min(len(names), 4)
            rows = math.ceil(len(names) / cols)
            fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
            for ax, name in zip(axes.flat, names):
                ax.plot(epochs, [r.get(name, math.nan) for r in history], label="learned")
                if name in true:
                    ax.axhline(true[name], color="k", ls="--", label="true")
                ax.set_title(name)
                ax.set_xlabel("epoch")
            for ax in list(axes.flat)[len(names) :]:
                ax.axis("off")
            axes.flat[0].legend()
            fig.tight_layout()
            fig.savefig(out_dir / "params.png", dpi=100)
            plt.close(fig)
            paths.append(out_dir / "params.png")

    batch = _first_val_batch(datamodule)
    y, dt, mask, u, x = module.unpack(batch)
    y, dt = y[:1], dt[:1]
    u = u[:1] if u is not None else None
    x = x[:1] if x is not None else None
    T = int(mask[0].sum()) if mask is not None else y.shape[-2]
    y, dt = y[:, :T], dt[:, :T]
    u = u[:, :T] if u is not None else None
    smooth = getattr(module.kf, "smooth", None)  # the IMMFilter has no smoother: filtered only
    with torch.no_grad():
        out = module.kf(y, dt, u=u)
        sm = smooth(out) if smooth is not None else None
    H = module.kf.modes()[0].H.detach().to(y.dtype)  # the combined mean through the first mode's H
    t = torch.cumsum(dt[0], 0)
    m = y.shape[-1]
    fig, axes = plt.subplots(m, 1, figsize=(8, 2.4 * m), sharex=True, squeeze=False)
    for i, ax in enumerate(axes[:, 0]):
        h = H[i]
        curves = [("filtered", out.mean[0], out.cov[0], "C0")]
        if sm is not None:
            curves.append(("smoothed", sm.mean[0], sm.cov[0], "C1"))
        for label, mean, cov, color in curves:
            mu = mean @ h
            sd = torch.einsum("i,tij,j->t", h, cov, h).clamp_min(0).sqrt()
            ax.plot(t, mu, color=color, label=f"{label} mean")
            ax.fill_between(t, mu - 2 * sd, mu + 2 * sd, color=color, alpha=0.2, label=f"{label} ±2σ")
        if x is not None:
            ax.plot(t, x[0, :T] @ h, "k--", lw=1, label="true state")
        ax.plot(t, y[0, :, i], "k.", ms=4, label="observations")
        ax.set_ylabel(f"y[{i}]")
    axes[-1, 0].set_xlabel("time")
    axes[0, 0].legend(fontsize=7, ncol=3)
    fig.tight_layout()
    fig.savefig(out_dir / "track.png", dpi=100)
    plt.close(fig)
    paths.append(out_dir / "track.png")
    return paths
