"""Callbacks: Lightning's :class:`ParameterHistory` (per-epoch values) and :class:`RunLog` (the
run's log), and Hydra's :class:`BestRun`."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback as HydraCallback
from lightning.pytorch import Callback, LightningModule
from omegaconf import DictConfig, OmegaConf

from torchsde_lti.training.metrics import filter_values, flat_values
from torchsde_lti.training.module import KalmanFilterModule
from torchsde_lti.training.outputs import data_summary, write_json

__all__ = ["BestRun", "ParameterHistory", "RunLog"]

log = logging.getLogger("torchsde_lti.training")


class ParameterHistory(Callback):
    """Records, after every training epoch, the epoch-mean losses and the learned values.

    ``history`` is a list of {"epoch", "train/nll", "val/nll", <param>: value} (the
    learned values of :func:`~torchsde_lti.training.metrics.filter_values`, so every mode
    of an IMM and its switching rates) of plain
    floats (so it round-trips through ``state_dict`` and ``torch.load(weights_only=True)``).
    """

    def __init__(self) -> None:
        self.history: list[dict[str, float]] = []

    def on_train_epoch_end(self, trainer: Any, pl_module: LightningModule) -> None:
        if trainer.sanity_checking:
            return
        row: dict[str, float] = {"epoch": float(trainer.current_epoch)}
        for key in ("train/nll", "val/nll", "val/param_error"):
            if key in trainer.callback_metrics:
                row[key] = float(trainer.callback_metrics[key])
        if isinstance(pl_module, KalmanFilterModule):
            row.update(flat_values(filter_values(pl_module.kf, pl_module.param_names)))
        self.history.append(row)

    def state_dict(self) -> dict[str, Any]:
        return {"history": [dict(r) for r in self.history]}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.history = [dict(r) for r in state_dict.get("history", [])]


class RunLog(Callback):
    """Writes the run's story to the ``torchsde_lti.training`` logger (Hydra's job logging puts
    it in ``<run>/train.log`` and on the console): the data summary when the data are set up
    (``datamodule.summary``, when the datamodule offers one) and one line per epoch with every
    epoch-level metric (``train/nll``, ``val/nll``, ``val/param_error``, ...)."""

    def setup(self, trainer: Any, pl_module: LightningModule, stage: str) -> None:
        summary = data_summary(trainer.datamodule) if trainer.datamodule is not None else None
        if summary is not None and trainer.is_global_zero:
            text = summary if isinstance(summary, str) else json.dumps(summary, indent=1)
            log.info("data summary (%s):\n%s", type(trainer.datamodule).__name__, text)

    def on_train_epoch_end(self, trainer: Any, pl_module: LightningModule) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero:
            return
        values = {
            k: float(v)
            for k, v in trainer.callback_metrics.items()
            if "/" in k and v.numel() == 1 and k != "train/skipped_steps"
        }  # logged after this hook
        if isinstance(pl_module, KalmanFilterModule):
            values["skipped_steps"] = float(pl_module.skipped_steps)
        text = "  ".join(f"{k}={v:.6g}" for k, v in sorted(values.items()))
        log.info("epoch %d/%s: %s", trainer.current_epoch, trainer.max_epochs, text)


class BestRun(HydraCallback):
    """Hydra callback: after a multirun, pick the run with the best ``metric`` and report it.

    Reads every completed job's ``metrics.json`` under the sweep directory, writes ``best_run.json``
    (the winner's directory, overrides, metric value, and all runs' values) there, and
    prints it. With ``experiment=restarts`` (a sweep over ``restart``) this keeps the best
    of K random restarts; the jobs themselves run through whatever Hydra launcher is
    configured (``hydra/launcher=parallel`` for joblib).
    """

    def __init__(self, metric: str = "val/nll", mode: str = "min") -> None:
        if mode not in ("min", "max"):
            raise ValueError(f"mode must be 'min' or 'max', got {mode!r}")
        self.metric, self.mode = metric, mode

    def best(self, sweep_dir: Path) -> dict[str, Any]:
        """{"best_dir", "overrides", "value", "runs": [{"dir", "overrides", "value"}]} for ``sweep_dir``."""
        runs = []
        for path in sorted(Path(sweep_dir).glob("*/metrics.json")):
            summary = json.loads(path.read_text())
            if summary.get("status", "completed") != "completed":  # interrupted / failed runs do not compete
                continue
            value = summary.get("metrics", {}).get(self.metric)
            if value is None or not math.isfinite(float(value)):
                continue
            overrides_file = path.parent / ".hydra" / "overrides.yaml"
            overrides = OmegaConf.to_container(OmegaConf.load(overrides_file)) if overrides_file.exists() else []
            runs.append({"dir": str(path.parent), "overrides": overrides, "value": float(value)})
        if not runs:
            raise ValueError(f"no run under {sweep_dir} logged a finite {self.metric}")
        pick = min if self.mode == "min" else max
        winner = pick(runs, key=lambda r: r["value"])
        return {
            "metric": self.metric,
            "best_dir": winner["dir"],
            "overrides": winner["overrides"],
            "value": winner["value"],
            "runs": runs,
        }

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        result = self.best(sweep_dir)
        write_json(sweep_dir / "best_run.json", result)
        print(
            f"best of {len(result['runs'])} runs by {self.metric}: {result['value']:.6g} in {result['best_dir']} "
            f"({' '.join(map(str, result['overrides']))})"
        )
