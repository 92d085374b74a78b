"""Callbacks: Lightning's :class:`RunLog` (the run's log) and :class:`FollowMovedRun` (resume of
a moved run), and Hydra's :class:`BestRun` (the best job of a sweep)."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback as HydraCallback
from lightning.pytorch import Callback, LightningModule, Trainer
from omegaconf import DictConfig, OmegaConf

from torchsde_lti.training.outputs import data_summary, write_json

__all__ = ["BestRun", "FollowMovedRun", "RunLog"]

#: the run's details: train.log only, not the console (conf/hydra/job_logging/run.yaml)
details = logging.getLogger("torchsde_lti.training.details")


class RunLog(Callback):
    """Writes the run's story to the ``torchsde_lti.training.details`` logger (Hydra's job logging
    puts it in ``<run>/train.log``, not on the console, where the progress bar is): the data
    summary when the data are set up (``datamodule.summary``, where it has one) and one line per
    epoch with its scores (``train/nll``, ``val/nll``, ...; not the learned ``param/*``),
    numbered as the progress bar numbers it (``epoch 3/39``)."""

    def setup(self, trainer: Trainer, pl_module: LightningModule, stage: str) -> None:
        datamodule = getattr(trainer, "datamodule", None)
        summary = data_summary(datamodule)
        if summary is not None and trainer.is_global_zero:
            text = summary if isinstance(summary, str) else json.dumps(summary, indent=1)
            details.info("data summary (%s):\n%s", type(datamodule).__name__, text)

    def on_train_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero:
            return
        values = {k: float(v) for k, v in trainer.callback_metrics.items() if "/" in k and not k.startswith("param/")}
        values["skipped_steps"] = float(getattr(pl_module, "skipped_steps", 0))
        values.pop("train/skipped_steps", None)
        text = "  ".join(f"{k}={v:.6g}" for k, v in sorted(values.items()))
        last = trainer.max_epochs - 1 if trainer.max_epochs is not None and trainer.max_epochs >= 0 else "?"
        details.info("epoch %d/%s: %s", trainer.current_epoch, last, text)


class FollowMovedRun(Callback):
    """For a run resumed in its own directory after that directory was moved or copied: Lightning
    restores a ModelCheckpoint's best score and files only when its directory is the one saved (so
    the next epoch would overwrite ``best.ckpt`` whatever its score). Before Lightning loads their
    states, this points them at the files of the same names here, where those exist."""

    def on_load_checkpoint(self, trainer: Trainer, pl_module: LightningModule, checkpoint: dict[str, Any]) -> None:
        states = checkpoint.get("callbacks") or {}
        for cb in trainer.checkpoint_callbacks:
            state, dirpath = states.get(getattr(cb, "state_key", None)), getattr(cb, "dirpath", None)
            if not state or dirpath is None or state.get("dirpath") in (None, dirpath):
                continue
            if not (Path(dirpath) / Path(state.get("best_model_path") or "").name).is_file():
                continue  # its file is not here (deleted): Lightning's fresh start is right

            def here(path: str | None, dirpath: str = dirpath) -> str | None:
                return str(Path(dirpath) / Path(path).name) if path else path

            state.update({k: here(state.get(k)) for k in ("best_model_path", "kth_best_model_path", "last_model_path")})
            state.update(
                dirpath=dirpath, best_k_models={here(k): v for k, v in (state.get("best_k_models") or {}).items()}
            )


class BestRun(HydraCallback):
    """Hydra callback: after a multirun, pick the completed run with the best ``metric``.

    Reads every job's ``metrics.json`` under the sweep directory, writes ``best_run.json`` (the
    winner's directory, overrides and value, and every run's value) there and prints it. With
    ``experiment=restarts`` (a sweep over ``restart``) this keeps the best of K random restarts.
    """

    def __init__(self, metric: str = "val/nll", mode: str = "min") -> None:
        if mode not in ("min", "max"):
            raise ValueError(f"mode must be 'min' or 'max', got {mode!r}")
        self.metric, self.mode = metric, mode

    def best(self, sweep_dir: Path) -> dict[str, Any]:
        """{"metric", "best_dir", "overrides", "value", "runs": [{"dir", "overrides", "value"}]}."""
        runs: list[dict[str, Any]] = []
        for path in sorted(Path(sweep_dir).glob("*/metrics.json")):
            card = json.loads(path.read_text())
            value = card.get("metrics", {}).get(self.metric)
            if card.get("status", "completed") != "completed" or value is None or not math.isfinite(float(value)):
                continue  # interrupted / failed runs and runs without the metric do not compete
            overrides = path.parent / ".hydra" / "overrides.yaml"
            listed = OmegaConf.to_container(OmegaConf.load(overrides)) if overrides.exists() else []
            runs.append({"dir": str(path.parent), "overrides": listed, "value": float(value)})
        if not runs:
            raise ValueError(f"no run under {sweep_dir} logged a finite {self.metric}")
        winner = (min if self.mode == "min" else max)(runs, key=lambda r: r["value"])
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
        overrides = " ".join(map(str, result["overrides"]))
        print(
            f"best of {len(result['runs'])} runs by {self.metric}: {result['value']:.6g} in {result['best_dir']} ({overrides})"
        )
