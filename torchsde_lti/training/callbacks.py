"""Callbacks: Lightning's :class:`ParameterHistory` (per-epoch values), :class:`RunLog` (the
run's log), :class:`ValidatedAt` and :class:`FollowMovedRun` (resume), and Hydra's :class:`BestRun`."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback as HydraCallback
from lightning.pytorch import Callback, LightningModule, Trainer
from lightning.pytorch.callbacks import ModelCheckpoint
from omegaconf import DictConfig, OmegaConf

from torchsde_lti.training.metrics import filter_values, flat_values
from torchsde_lti.training.module import KalmanFilterModule
from torchsde_lti.training.outputs import data_summary, write_json

__all__ = ["BestRun", "FollowMovedRun", "ParameterHistory", "RunLog", "ValidatedAt"]

#: the run's details: train.log only, not the console (conf/hydra/job_logging/run.yaml)
details = logging.getLogger("torchsde_lti.training.details")


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
    """Writes the run's story to the ``torchsde_lti.training.details`` logger (Hydra's job logging
    puts it in ``<run>/train.log``, not on the console, where the progress bar is): the data
    summary when the data are set up (``datamodule.summary``, when the datamodule offers one) and
    one line per epoch with every epoch-level metric (``train/nll``, ``val/nll``, ...), numbered
    as the progress bar numbers it (``epoch 3/39``: Lightning's epoch and last epoch)."""

    def setup(self, trainer: Any, pl_module: LightningModule, stage: str) -> None:
        summary = data_summary(trainer.datamodule) if trainer.datamodule is not None else None
        if summary is not None and trainer.is_global_zero:
            text = summary if isinstance(summary, str) else json.dumps(summary, indent=1)
            details.info("data summary (%s):\n%s", type(trainer.datamodule).__name__, text)

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
        last = trainer.max_epochs - 1 if trainer.max_epochs is not None and trainer.max_epochs >= 0 else "?"
        details.info("epoch %d/%s: %s", trainer.current_epoch, last, text)


class ValidatedAt(Callback):
    """The optimizer step (``trainer.global_step``) after this process's last training batch and
    at the end of its last validation run (sanity checks excluded): the final weights'
    validation metrics are stale where training stepped after the validation
    (``check_val_every_n_epoch > 1``, a run stopped by ``max_steps`` mid-epoch)."""

    def __init__(self) -> None:
        self.trained: int | None = None
        self.validated: int | None = None

    def on_train_batch_end(self, trainer: Trainer, *args: Any) -> None:
        self.trained = int(trainer.global_step)

    def on_validation_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if not trainer.sanity_checking:
            self.validated = int(trainer.global_step)

    @property
    def stale(self) -> bool:
        """Whether this process trained after its last validation."""
        return self.trained is not None and self.trained != self.validated


class FollowMovedRun(Callback):
    """For a run resumed in its own directory after that directory was moved or copied: Lightning
    restores a ModelCheckpoint's best score and files only when its directory is the one saved,
    so the next epoch would overwrite ``best.ckpt`` whatever its score, and a resume with no epoch
    left would report the old directory's files. Before Lightning loads their states (its
    ``on_load_checkpoint`` hook), this points them at the files of the same names here, where
    those exist."""

    def on_load_checkpoint(self, trainer: Trainer, pl_module: LightningModule, checkpoint: dict[str, Any]) -> None:
        states = checkpoint.get("callbacks") or {}
        for cb in trainer.checkpoint_callbacks:
            if not isinstance(cb, ModelCheckpoint) or cb.dirpath is None:
                continue
            state, dirpath = states.get(cb.state_key), cb.dirpath
            if not state or state.get("dirpath") in (None, dirpath):
                continue
            if not (Path(dirpath) / Path(state.get("best_model_path") or "").name).is_file():
                continue  # its file is not here (deleted): Lightning's fresh start is right

            def here(path: str | None, dirpath: str | Path = dirpath) -> str | None:
                return str(Path(dirpath) / Path(path).name) if path else path

            state.update({k: here(state.get(k)) for k in ("best_model_path", "kth_best_model_path", "last_model_path")})
            state.update(
                dirpath=dirpath, best_k_models={here(k): v for k, v in (state.get("best_k_models") or {}).items()}
            )


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
        runs: list[dict[str, Any]] = []
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
