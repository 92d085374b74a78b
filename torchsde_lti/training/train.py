"""The main job: learn a motion model with a Kalman-filter likelihood, configured by Hydra.

    python -m torchsde_lti.train                                   # default run (conf/train.yaml)
    python -m torchsde_lti.train model=singer data.noise=1.0       # override anything
    python -m torchsde_lti.train --multirun model=cv,integrated_ou,singer data.noise=0.1,1.0
    python -m torchsde_lti.train ckpt_path=<run>/checkpoints/last.ckpt    # resume, same overrides

:func:`train` builds everything with ``hydra.utils.instantiate`` and runs the phases setup, fit,
test, plots, outputs. A run writes Lightning's ``checkpoints/last.ckpt`` (the last completed
epoch: the weights it reports, the resume point) and ``checkpoints/best.ckpt`` (lowest val/nll),
the logger files, ``config.yaml`` (resolved: :func:`~torchsde_lti.runs.load_run` reads it),
``train.log``, ``metrics.json`` and ``results.md`` (:class:`~torchsde_lti.training.report.RunCard`)
and the figures. SIGTERM / SIGINT stop it at the next batch boundary (:mod:`.signals`): it says
so and exits ``128 + signal``. Resuming from ``<run>/checkpoints/last.ckpt`` continues in
``<run>`` (``hydra.run.dir`` follows it) and ends bit for bit where a run that never stopped
ends; another checkpoint starts a new run directory. ``num_threads`` applies during the run only.
"""

from __future__ import annotations

import logging
import os
import random
import signal
import sys
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import hydra
import lightning.pytorch as pl
import numpy as np
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf

from torchsde_lti.evaluation import identifiability_note, parameter_table
from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import KalmanFilter
from torchsde_lti.training.callbacks import FollowMovedRun
from torchsde_lti.training.checkpoints import RESUME_KEYS, load_weights, read_checkpoint
from torchsde_lti.training.config import check_config, instantiate_node
from torchsde_lti.training.outputs import continue_csv_log, data_summary, to_jsonable, write_text
from torchsde_lti.training.plots import plot_run
from torchsde_lti.training.report import RunCard
from torchsde_lti.training.signals import RunInterrupted, SignalGuard

__all__ = ["config_path", "main", "restart_learner", "resume_run_dir", "train"]

log = logging.getLogger("torchsde_lti.training")
#: the run's details (the config, one line per epoch): train.log only, not the console (conf/hydra/job_logging)
details = logging.getLogger("torchsde_lti.training.details")


def resume_run_dir(ckpt_path: Any, default: str) -> str:
    """The run directory a resumed run writes into (the OmegaConf resolver ``tl_resume_dir`` of
    ``hydra.run.dir``): ``<run>`` for an existing ``<run>/checkpoints/last.ckpt``, else ``default``."""
    path = Path(ckpt_path) if isinstance(ckpt_path, str) and ckpt_path else None
    if path is not None and path.name == "last.ckpt" and path.parent.name == "checkpoints" and path.is_file():
        return str(path.resolve().parent.parent)
    return default


OmegaConf.register_new_resolver("tl_resume_dir", resume_run_dir, replace=True)


def restart_learner(kf: KalmanFilter | IMMFilter, jitter: float, seed: int) -> None:
    """Random restart: add N(0, jitter²) (a generator seeded with ``seed``) to every raw parameter
    of the learner's motion models (``kf.modes()``), in place (``jitter = 0``: keep the start).

    Raw parameters are unconstrained by construction, so every perturbed start is valid (a
    Hurwitz F stays Hurwitz); a Hydra sweep over the seed (``experiment=restarts``) keeps the best.
    """
    if not jitter > 0:
        return
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in (p for mode in kf.modes() for p in mode.sde.parameters()):
            if p.requires_grad:
                p.add_(jitter * torch.randn(p.shape, generator=g, dtype=torch.float64).to(p))


def train(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Train per ``cfg``; returns (metrics, objects).

    Args:
        cfg: the composed config (``conf/train.yaml`` and its overrides).

    Returns:
        metrics: the final epoch-level metrics as floats (``val/nll``, ``test/*``, ...) plus
        ``param_errors`` (dict), ``table`` (true vs learned rows of ``last.ckpt``), ``wall_time``
        (s), ``checkpoints`` ({"last", "best"} paths), ``best_model_path`` and ``status``;
        objects: "cfg", "datamodule", "module", "trainer", "callbacks", "loggers", "truth".

    Raises:
        ValueError / TypeError: a config value that cannot make a sensible run (naming the key),
            before any work; FileNotFoundError / CheckpointError: a ``ckpt_path`` that cannot be
            resumed from. RunInterrupted: SIGTERM / SIGINT stopped the run (after its report).
    """
    check_config(cfg)
    resume = read_checkpoint(cfg.ckpt_path, require=RESUME_KEYS) if cfg.get("ckpt_path") else None
    run = _Run(cfg, resume)
    log.info("run directory: %s", run.out_dir.resolve())
    details.info("config:\n%s", _config_text(cfg))
    with _process_state(cfg.get("num_threads"), run.same_dir), SignalGuard() as guard:
        try:
            for phase in ("setup", "fit", "test", "plots", "outputs"):
                guard.stop_if_received()
                guard.phase = phase
                getattr(run, phase)(guard)
        except SystemExit as stop:  # Lightning's SIGTERMException, or its exit after a KeyboardInterrupt
            signum = guard.received or (signal.SIGTERM if isinstance(stop, SIGTERMException) else None)
            if signum is None:
                run.failed(RuntimeError(f"the run stopped ({type(stop).__name__} {stop}) without a signal"))
                raise
            raise run.interrupted(signum, guard.received_during or guard.phase) from None
        except Exception as err:
            run.failed(err)
            log.error("run failed: %s: %s", type(err).__name__, err)
            raise
    if guard.received is not None:
        log.warning("received %s after the run completed; its outputs are complete", guard.received.name)
    log.info("run completed: %s", run.out_dir.resolve())
    return run.metrics, run.objects


class _Run:
    """One run's objects, phase by phase; rank zero writes its :class:`RunCard`."""

    def __init__(self, cfg: DictConfig, resume: dict[str, Any] | None) -> None:
        self.cfg, self.resume, self.out_dir = cfg, resume, Path(cfg.output_dir)
        self.same_dir = resume is not None and Path(cfg.ckpt_path).resolve().parent.parent == self.out_dir.resolve()
        self.objects: dict[str, Any] = {}
        self.card: RunCard | None = None
        self.metrics: dict[str, Any] = {}  # (an earlier process's epoch-level metrics, for a resume with none left)
        self.wall = 0.0

    def setup(self, guard: SignalGuard) -> None:
        """Data, filter (with the data's prior where it has the learner's state), module, callbacks, loggers, trainer."""
        cfg = self.cfg
        pl.seed_everything(int(cfg.seed), workers=True, verbose=False)
        datamodule = instantiate_node(cfg, "data")
        truth = getattr(datamodule, "truth", None)
        if truth is not None and getattr(datamodule, "H", None) is not None:
            truth = {**truth, "H": datamodule.H}
        kf = instantiate_node(cfg, "filter")
        m0, P0 = getattr(datamodule, "m0", None), getattr(datamodule, "P0", None)
        if m0 is not None and P0 is not None and int(kf.state_dim) == int(m0.shape[-1]):
            kf = instantiate_node(cfg, "filter", m0=m0, P0=P0)
        restart_learner(kf, float(cfg.get("init_jitter") or 0.0), int(cfg.get("restart") or 0))
        module = instantiate_node(cfg, "module", kf=kf, truth=truth)
        callbacks = [*_instantiate_dict(cfg, "callbacks"), guard, *([FollowMovedRun()] if self.same_dir else [])]
        # best saves before last at each epoch end, so last.ckpt (the resume point) holds best's updated state
        callbacks.sort(key=lambda c: isinstance(c, ModelCheckpoint) and c.monitor is None)
        loggers = _instantiate_dict(cfg, "logger")
        trainer: pl.Trainer = instantiate_node(cfg, "trainer", callbacks=callbacks, logger=loggers or False)
        self.objects = dict(cfg=cfg, datamodule=datamodule, module=module, trainer=trainer, callbacks=callbacks)
        self.objects.update(loggers=loggers, truth=truth)
        if cfg.get("test") and not _fast_dev_run(trainer):
            _check_test_split(datamodule)
        if self.resume is not None:
            load_weights(module, self.resume["state_dict"], cfg.ckpt_path)  # another model fails here, not in fit
            _warn_if_schedule_ends_early(cfg.ckpt_path, cfg.trainer.get("max_epochs"), self.resume)
            log.info("resuming from %s (epoch %d) into %s", cfg.ckpt_path, self.resume["epoch"], self.out_dir)
        if trainer.is_global_zero:
            self._new_card()
            write_text(self.out_dir / "config.yaml", _config_text(cfg))
            for lg in loggers:
                if self.same_dir:
                    continue_csv_log(lg, int(self.resume["epoch"]))  # type: ignore[index]
                lg.log_hyperparams(OmegaConf.to_container(cfg, resolve=True))

    def fit(self, guard: SignalGuard) -> None:
        """``Trainer.fit``; validates the final weights again where the last validation saw older
        ones (``check_val_every_n_epoch > 1``, ``max_steps``)."""
        trainer, module, datamodule = (self.objects[k] for k in ("trainer", "module", "datamodule"))
        start = time.perf_counter()
        trainer.fit(module, datamodule=datamodule, ckpt_path=self.cfg.get("ckpt_path"), weights_only=True)
        self.wall = time.perf_counter() - start
        self.metrics.update(_scores(trainer.callback_metrics))
        if module.validation_stale and not _fast_dev_run(trainer) and trainer.limit_val_batches:
            for r in trainer.validate(module, datamodule=datamodule, verbose=False):
                self.metrics.update(_scores(r))

    def test(self, guard: SignalGuard) -> None:
        """Test the final weights (``cfg.test``)."""
        trainer, module = self.objects["trainer"], self.objects["module"]
        if self.cfg.get("test") and not _fast_dev_run(trainer):
            for r in trainer.test(module, datamodule=self.objects["datamodule"], verbose=False):
                self.metrics.update(_scores(r))
        if module.skipped_steps:
            warnings.warn(
                f"{module.skipped_steps} optimizer steps were skipped (non-finite loss or gradient)", stacklevel=2
            )
        self.metrics.update(wall_time=self.wall, skipped_steps=float(module.skipped_steps))

    def plots(self, guard: SignalGuard) -> None:
        """The run's figures (rank zero); a plot that fails is a warning, never a failed run."""
        trainer, module, datamodule, truth = (self.objects[k] for k in ("trainer", "module", "datamodule", "truth"))
        if not (trainer.is_global_zero and self.cfg.get("plots") and not _fast_dev_run(trainer)):
            return
        csv_log = [Path(lg.log_dir) / "metrics.csv" for lg in self.objects["loggers"] if isinstance(lg, CSVLogger)]
        try:
            plot_run(self.out_dir, module, datamodule, truth, *csv_log[:1])
        except Exception as err:  # noqa: BLE001 - a picture must not fail a finished run
            log.warning("the plots failed (the run's results are complete): %s: %s", type(err).__name__, err)

    def outputs(self, guard: SignalGuard) -> None:
        """The tables of the final weights (``last.ckpt``) and of the best epoch (``best.ckpt``);
        rank zero writes and prints the card."""
        module, truth, callbacks = self.objects["module"], self.objects["truth"], self.objects["callbacks"]
        last, best = _checkpoint_files(callbacks)
        table = parameter_table(module.kf, truth, module.param_names, module.compare)
        self.metrics.update(param_errors=module.parameter_errors(), table=table, best_model_path=best or "")
        self.metrics.update(checkpoints={"last": last, "best": best}, status="completed")
        if (card := self.card) is None:
            return
        if best:
            ckpt, monitored = (
                read_checkpoint(best),
                next(c for c in callbacks if isinstance(c, ModelCheckpoint) and c.monitor),
            )
            score = None if monitored.best_model_score is None else float(monitored.best_model_score)
            card.best = {"checkpoint": card.relative(best), "epoch": int(ckpt["epoch"]), "val/nll": score}
            card.best.update(zip(("table", "param_errors"), _table_at(module, ckpt["state_dict"], truth)))
        card.status, card.wall_time, card.epochs = "completed", self.wall, int(self.objects["trainer"].current_epoch)
        description = "the final weights, at the end of the last epoch"
        card.reported = {"checkpoint": card.relative(last), "epoch": _epoch_of(last), "description": description}
        card.metrics = {k: v for k, v in self.metrics.items() if isinstance(v, float)}
        card.param_errors, card.table, card.skipped_steps = self.metrics["param_errors"], table, module.skipped_steps
        card.identifiability = identifiability_note(module.kf) if truth else ""
        summary = getattr(self.objects["datamodule"], "summary", None)
        summary = summary() if callable(summary) else summary
        card.data_summary = None if summary is None else to_jsonable(summary)
        card.write(None if summary is None else str(summary))
        print("\n" + (self.out_dir / "results.md").read_text())

    def interrupted(self, signum: int, phase: str) -> RunInterrupted:
        """Write the interrupted card (rank zero) and return the exception to raise."""
        last, epochs = self._resume_point()
        if self.card is None and "trainer" not in self.objects and int(os.environ.get("LOCAL_RANK", "0")) == 0:
            self._new_card()  # stopped while building: still say so
        resume_from = str(Path(last).resolve()) if last else None
        if (card := self.card) is not None:
            trainer = self.objects.get("trainer")
            metrics = {**self.metrics, **(_scores(trainer.callback_metrics) if trainer and not self.wall else {})}
            card.status, card.epochs, card.metrics = (
                "interrupted",
                epochs,
                {k: v for k, v in metrics.items() if isinstance(v, float)},
            )
            card.interruption = {
                "signal": signal.Signals(signum).name, "phase": phase, "epochs_completed": epochs,
                "resume_checkpoint": resume_from, "resume_command": card.resume_command(last) if last else None,
            }  # fmt: skip
            card.data_summary = data_summary(self.objects.get("datamodule"))
            card.write()
        stop = RunInterrupted(signum, phase, str(self.out_dir.resolve()), resume_from)
        log.error("%s", stop)
        return stop

    def failed(self, error: BaseException) -> None:
        """The failed card (rank zero, once built), naming its resume point where it has one."""
        if (card := self.card) is None:
            return
        card.status, card.error = "failed", f"{type(error).__name__}: {error}"
        try:
            last, card.epochs = self._resume_point()
            if last:
                card.reported = {
                    "checkpoint": card.relative(last),
                    "epoch": card.epochs - 1,
                    "description": "the resume point",
                }
        except Exception:  # noqa: BLE001, S110 - the report of a failure must not fail itself
            pass
        card.write()

    def _resume_point(self) -> tuple[str | None, int]:
        """(``last.ckpt``'s path or None, the epochs it holds)."""
        last, _ = _checkpoint_files(self.objects.get("callbacks", []))
        return last, (_epoch_of(last) or 0) + 1 if last else 0

    def _new_card(self) -> None:
        """A running card, written; a resumed run keeps its directory's earlier resumes and epoch-level metrics."""
        cfg = self.cfg
        card = RunCard(
            str(self.out_dir.resolve()), cfg.model.get("name"), cfg.data.get("noise"), cfg.trainer.get("max_epochs")
        )
        card.overrides = _overrides()
        if self.resume is not None:
            old = card.previous()
            scores = (old.get("metrics") or {}).items()
            self.metrics = {k: float(v) for k, v in scores if isinstance(v, (int, float)) and not k.startswith("test/")}
            epoch = int(self.resume["epoch"])
            card.resumed_from = [
                *(old.get("resumed_from") or []),
                {"checkpoint": str(Path(cfg.ckpt_path).resolve()), "epoch": epoch},
            ]
            card.epochs = epoch + 1
        self.card = card
        card.write()


def _instantiate_dict(cfg: DictConfig, key: str) -> list[Any]:
    """Instantiate every ``_target_`` child of a dict node (callbacks, loggers)."""
    node = cfg.get(key) or {}
    return [
        instantiate_node(cfg, f"{key}.{k}") for k, v in node.items() if isinstance(v, DictConfig) and "_target_" in v
    ]


def _fast_dev_run(trainer: pl.Trainer) -> bool:
    return bool(getattr(trainer, "fast_dev_run", False))


def _scores(values: dict[str, Any]) -> dict[str, float]:
    """Logged values as floats, without the learned values (``param/*``, the tables hold them)."""
    return {k: float(v) for k, v in values.items() if not k.startswith("param/")}


def _check_test_split(datamodule: pl.LightningDataModule) -> None:
    """ValueError before training where ``test=true`` finds no test batch (sets the data up: the fit reuses them)."""
    datamodule.setup("fit")
    try:
        batches = len(datamodule.test_dataloader())
    except ValueError as err:
        raise ValueError(f"test=true, but the data have no test split: {err}; set test=false") from None
    if batches == 0:
        raise ValueError("test=true, but the data's test split is empty; set test=false or give it tracks")


def _warn_if_schedule_ends_early(
    ckpt_path: str | None, max_epochs: int | None, ckpt: dict[str, Any] | None = None
) -> None:
    """Warn when a resumed run trains past the restored scheduler's ``T_max`` (the checkpoint's,
    not the config's): past it a cosine LR rises again."""
    if not ckpt_path or max_epochs is None or int(max_epochs) < 0:
        return
    for state in (ckpt or read_checkpoint(ckpt_path, require=())).get("lr_schedulers", []):
        t_max = state.get("T_max") if isinstance(state, dict) else None
        if isinstance(t_max, int) and int(max_epochs) > t_max:
            warnings.warn(
                f"resuming from {ckpt_path}: its LR scheduler has T_max={t_max} (restored from the checkpoint) but "
                f"trainer.max_epochs={max_epochs}; past T_max the cosine LR rises again. Resume with the original "
                "max_epochs, or start a new run from the weights.",
                stacklevel=2,
            )


def _checkpoint_files(callbacks: list[Any]) -> tuple[str | None, str | None]:
    """(last, best) files the run's ModelCheckpoints wrote (None: none): ``last`` by the one
    without a monitor, ``best`` by the one monitoring a metric."""
    written = [
        c
        for c in callbacks
        if isinstance(c, ModelCheckpoint) and c.best_model_path and Path(c.best_model_path).is_file()
    ]
    last = next((c.best_model_path for c in written if c.monitor is None), None)
    return last, next((c.best_model_path for c in written if c.monitor is not None), None)


def _epoch_of(path: str | None) -> int | None:
    return int(read_checkpoint(path, require=("epoch",))["epoch"]) if path else None


def _table_at(module: Any, state_dict: dict[str, Any], truth: Any) -> tuple[list[dict[str, Any]], dict[str, float]]:
    """The table and parameter errors of ``module`` with the weights ``state_dict`` (its own put back after)."""
    own = {k: v.detach().clone() for k, v in module.state_dict().items()}
    try:
        module.load_state_dict(state_dict)
        return parameter_table(module.kf, truth, module.param_names, module.compare), module.parameter_errors()
    finally:
        module.load_state_dict(own)


def _config_text(cfg: DictConfig) -> str:
    try:
        return OmegaConf.to_yaml(cfg, resolve=True)
    except Exception:  # noqa: BLE001 - an interpolation only Hydra's runtime can resolve: unresolved
        return OmegaConf.to_yaml(cfg)


def _overrides() -> list[str] | None:
    """The command-line overrides of this Hydra job (None outside a Hydra run)."""
    from hydra.core.hydra_config import HydraConfig

    return [str(o) for o in HydraConfig.get().overrides.task] if HydraConfig.initialized() else None


def _no_advert(record: logging.LogRecord) -> bool:
    return "💡 Tip" not in record.getMessage()


@contextmanager
def _process_state(num_threads: int | None, resuming_in_place: bool) -> Iterator[None]:
    """Around a run: torch's intra-op thread count set to ``num_threads`` (null or 0: unchanged),
    the one place the package sets it; Lightning's cloud-logger advert, its FutureWarning about
    torch's ``LeafSpec`` and, resuming in place, its warning about the non-empty checkpoint
    directory silenced. On return the thread count, the global RNG states ``seed_everything``
    seeds (Python, NumPy, torch's CPU and, where CUDA was in use already, CUDA's: forking them
    would initialise it) and Lightning's seed variables are put back."""
    threads, py_rng, np_rng = torch.get_num_threads(), random.getstate(), np.random.get_state()
    env = {k: os.environ.get(k) for k in ("PL_GLOBAL_SEED", "PL_SEED_WORKERS")}
    rank_zero = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    rank_zero.addFilter(_no_advert)
    devices = list(range(torch.cuda.device_count())) if torch.cuda.is_initialized() else []
    try:
        with torch.random.fork_rng(devices=devices), warnings.catch_warnings():
            warnings.filterwarnings("ignore", r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning)
            if resuming_in_place:
                warnings.filterwarnings("ignore", r"Checkpoint directory .* exists and is not empty")
            if num_threads:
                torch.set_num_threads(int(num_threads))
            yield
    finally:
        rank_zero.removeFilter(_no_advert)
        torch.set_num_threads(threads)
        random.setstate(py_rng)
        np.random.set_state(np_rng)
        for key, value in env.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def config_path() -> str:
    """Where the Hydra configs are: a checkout's top-level ``conf/``, else the installed
    package's ``torchsde_lti/conf/`` (a wheel ships them there); absolute, so the job runs from
    any working directory."""
    import torchsde_lti

    package = Path(torchsde_lti.__file__).resolve().parent
    for candidate in (package.parent / "conf", package / "conf"):
        if (candidate / "train.yaml").is_file():
            return str(candidate)
    raise FileNotFoundError(f"no Hydra configs (conf/train.yaml) next to or inside {package}")


@hydra.main(version_base="1.3", config_path=config_path(), config_name="train")
def main(cfg: DictConfig) -> float | None:
    """Hydra entry point; returns val/nll (for Hydra sweepers). An interrupted run exits with
    ``128 + signal`` (143 for SIGTERM, 130 for SIGINT), so no scheduler records it as a success."""
    try:
        metrics, _ = train(cfg)
    except RunInterrupted as stop:
        sys.exit(stop.exit_code)
    value = metrics.get("val/nll")
    return float(value) if value is not None else None


if __name__ == "__main__":
    main()
