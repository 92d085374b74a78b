"""The main job: learn a motion model with a Kalman-filter likelihood, configured by Hydra.

    python -m torchsde_lti.train                                   # default run (conf/train.yaml)
    python -m torchsde_lti.train model=singer data.noise=1.0       # override anything
    python -m torchsde_lti.train --multirun model=cv,integrated_ou,singer data.noise=0.1,1.0
    python -m torchsde_lti.train ckpt_path=<run>/checkpoints/last.ckpt    # resume, same overrides

Everything is built with ``hydra.utils.instantiate`` from ``_target_`` nodes; the logic
lives here in :func:`train`, which tests call with a composed config. A run writes into its
Hydra output directory: ``checkpoints/last.ckpt`` (end of the last completed epoch: the
reported weights and the resume point) and ``checkpoints/best.ckpt`` (lowest val/nll),
logger files, ``train.log`` (the config, the data summary, one line per epoch),
``metrics.json`` (strict JSON, schema in :mod:`torchsde_lti.training.report`),
``results.md`` and the plots ``loss.png``, ``track.png``, ``params.png``.

Interrupting: SIGTERM or SIGINT (Ctrl-C) stops the run at the next batch boundary
(:mod:`torchsde_lti.training.signals`), marks it ``interrupted`` in ``metrics.json`` and
``results.md`` (with the command that resumes it) and exits with ``128 + signal``
(143 / 130). Resuming from ``<run>/checkpoints/last.ckpt`` continues in ``<run>`` itself
(``hydra.run.dir`` follows the checkpoint); the CSV log keeps the epochs the checkpoint holds
and the resumed run appends the rest, so no epoch appears twice, and the result equals a run
that never stopped, bit for bit. Any other checkpoint (``best.ckpt``, a copied file) starts
a new run directory that continues from it.

Resuming restores the LR scheduler's own state, including the cosine schedule's
``T_max`` (= the original ``trainer.max_epochs``): a resumed run continues the same
schedule. Raising ``trainer.max_epochs`` beyond it makes the cosine LR climb back towards
its initial value, so :func:`train` warns about it.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import hydra
import lightning.pytorch as pl
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf

from torchsde_lti.training.callbacks import ParameterHistory
from torchsde_lti.training.checkpoints import RESUME_KEYS, check_state_dict, read_checkpoint
from torchsde_lti.training.config import check_config, instantiate_node
from torchsde_lti.training.metrics import parameter_table
from torchsde_lti.training.outputs import continue_csv_log, data_summary
from torchsde_lti.training.plots import plot_run
from torchsde_lti.training.report import RunReport
from torchsde_lti.training.signals import RunInterrupted, SignalGuard, StopOnSignal, StopRun

__all__ = ["config_path", "main", "restart_learner", "resume_run_dir", "train"]

log = logging.getLogger("torchsde_lti.training")


def resume_run_dir(ckpt_path: Any, default: str) -> str:
    """The run directory a resumed run writes into: ``<run>`` for ``<run>/checkpoints/last.ckpt``
    (an existing file), else ``default`` (a new directory).

    Registered as the OmegaConf resolver ``tl_resume_dir``, which ``hydra.run.dir`` uses.
    """
    if not isinstance(ckpt_path, str) or not ckpt_path:
        return default
    path = Path(ckpt_path)
    if path.name == "last.ckpt" and path.parent.name == "checkpoints" and path.is_file():
        return str(path.resolve().parent.parent)
    return default


OmegaConf.register_new_resolver("tl_resume_dir", resume_run_dir, replace=True)


def _instantiate_dict(cfg: DictConfig, key: str) -> list[Any]:
    """Instantiate every ``_target_`` child of a dict node (callbacks, loggers)."""
    node = cfg.get(key)
    if node is None:
        return []
    return [
        instantiate_node(cfg, f"{key}.{name}")
        for name, v in node.items()
        if isinstance(v, DictConfig) and "_target_" in v
    ]


def _warn_if_schedule_ends_early(
    ckpt_path: str | None, max_epochs: int | None, ckpt: dict[str, Any] | None = None
) -> None:
    """Warn when a resumed run trains past the restored scheduler's ``T_max``.

    Schedulers such as CosineAnnealingLR are periodic beyond ``T_max``; the value comes
    from the checkpoint, not from the config, so extending a finished run raises the LR.
    """
    if not ckpt_path or max_epochs is None or int(max_epochs) < 0:
        return
    if ckpt is None:
        ckpt = read_checkpoint(ckpt_path, require=())
    for state in ckpt.get("lr_schedulers", []):
        t_max = state.get("T_max") if isinstance(state, dict) else None
        if isinstance(t_max, int) and int(max_epochs) > t_max:
            warnings.warn(
                f"resuming from {ckpt_path}: its LR scheduler has T_max={t_max} (restored from the "
                f"checkpoint) but trainer.max_epochs={max_epochs}; past T_max the cosine LR rises "
                "again. Resume with the original max_epochs, or start a new run from the weights.",
                stacklevel=2,
            )


def restart_learner(kf: torch.nn.Module, jitter: float, seed: int) -> None:
    """Random restart: add N(0, jitter²) (generator seeded with ``seed``) to every raw parameter
    of the learner's motion models (``kf.modes()``: one for a KalmanFilter, every mode of an
    IMMFilter), in place (``jitter = 0``: keep the configured start).

    Raw parameters are unconstrained by construction (softplus / Cholesky / Hurwitz
    factors), so every perturbed start is valid: a Hurwitz F stays Hurwitz. A Hydra seed sweep
    (``experiment=restarts``) then runs K restarts and keeps the best validation NLL.
    """
    if not jitter > 0:
        return
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in (p for mode in kf.modes() for p in mode.sde.parameters()):
            if p.requires_grad:
                p.add_(jitter * torch.randn(p.shape, generator=g, dtype=torch.float64).to(p))


def _config_text(cfg: DictConfig) -> str:
    try:
        return OmegaConf.to_yaml(cfg, resolve=True)
    except Exception:  # noqa: BLE001 - an interpolation only Hydra's runtime can resolve: log it unresolved
        return OmegaConf.to_yaml(cfg)


def _overrides() -> list[str] | None:
    """The command-line overrides of this Hydra job (None outside a Hydra run)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    return [str(o) for o in HydraConfig.get().overrides.task]


def _build(cfg: DictConfig, guard: SignalGuard, resume: dict[str, Any] | None = None) -> dict[str, Any]:
    """Data, filter, Lightning module, callbacks, loggers and trainer of ``cfg`` (and "truth")."""
    if cfg.get("num_threads"):
        torch.set_num_threads(int(cfg.num_threads))
    pl.seed_everything(int(cfg.seed), workers=True, verbose=False)
    datamodule = instantiate_node(cfg, "data")
    truth = getattr(datamodule, "truth", None)
    prior: dict[str, Any] = {}
    if getattr(datamodule, "m0", None) is not None and getattr(datamodule, "P0", None) is not None:
        # the data's prior, used when the learner has the truth's state (model=cv truth=singer: it does not)
        prior = {"m0": datamodule.m0, "P0": datamodule.P0}
    if truth is not None and getattr(datamodule, "H", None) is not None:
        truth = {**truth, "H": datamodule.H}
    kf = instantiate_node(cfg, "filter")
    if prior and int(kf.state_dim) == int(prior["m0"].shape[-1]):
        kf = instantiate_node(cfg, "filter", **prior)
    restart_learner(kf, float(cfg.get("init_jitter") or 0.0), int(cfg.get("restart") or 0))
    module = instantiate_node(cfg, "module", kf=kf, truth=truth)
    callbacks = [*_instantiate_dict(cfg, "callbacks"), StopOnSignal(guard), _ValidatedAt()]
    if resume is not None:
        callbacks.append(_KeepBestOfMovedRun(resume.get("callbacks") or {}))
    # the best-so-far checkpoint saves before the last-epoch one at each epoch end, so that
    # last.ckpt (the resume point) holds the best's state after this epoch, not before it
    callbacks.sort(key=lambda c: isinstance(c, ModelCheckpoint) and c.monitor is None)
    loggers = _instantiate_dict(cfg, "logger")
    trainer: pl.Trainer = instantiate_node(cfg, "trainer", callbacks=callbacks, logger=loggers or False)
    if cfg.get("test") and not getattr(trainer, "fast_dev_run", False):
        _check_test_split(datamodule)
    return {
        "cfg": cfg,
        "datamodule": datamodule,
        "module": module,
        "trainer": trainer,
        "callbacks": callbacks,
        "loggers": loggers,
        "truth": truth,
    }


def _check_test_split(datamodule: pl.LightningDataModule) -> None:
    """ValueError before training where ``test=true`` finds no test batch (an empty test split),
    instead of failing (or testing nothing) after the fit. Sets the data up (once: the fit reuses it)."""
    datamodule.setup("fit")
    try:
        batches = len(datamodule.test_dataloader())
    except ValueError as err:
        raise ValueError(f"test=true, but the data have no test split: {err}; set test=false") from None
    if batches == 0:
        raise ValueError("test=true, but the data's test split is empty; set test=false or give it tracks")


class _ValidatedAt(pl.Callback):
    """The optimizer step (``trainer.global_step``) after this process's last training batch and
    at the end of its last validation run (sanity checks excluded): the final weights'
    validation metrics are stale where training stepped after the validation
    (``check_val_every_n_epoch > 1``, a run stopped by ``max_steps`` mid-epoch)."""

    def __init__(self) -> None:
        self.trained: int | None = None
        self.validated: int | None = None

    def on_train_batch_end(self, trainer: pl.Trainer, *args: Any) -> None:
        self.trained = int(trainer.global_step)

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not trainer.sanity_checking:
            self.validated = int(trainer.global_step)

    @property
    def stale(self) -> bool:
        """Whether this process trained after its last validation."""
        return self.trained is not None and self.trained != self.validated


class _KeepBestOfMovedRun(pl.Callback):
    """Resuming a run whose directory was moved or copied: Lightning restores the checkpoint
    callbacks' file paths as they were (in the old directory) and a monitoring one's best score
    only when its directory is unchanged, so the first epoch after the resume would overwrite
    ``best.ckpt`` whatever its score, and a resume with no epoch left to train would report the
    old directory's files. Before training, and at the end of a fit (which may have trained
    nothing), this points each ModelCheckpoint still holding the old path at the file of the
    same name in its own directory, where that file exists, and re-seeds a monitoring one's best
    score from the checkpoint resumed from."""

    def __init__(self, saved: dict[str, Any]) -> None:
        self.saved = saved

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._adopt(trainer)

    def on_fit_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._adopt(trainer)

    def _adopt(self, trainer: pl.Trainer) -> None:
        for cb in trainer.checkpoint_callbacks:
            if not isinstance(cb, ModelCheckpoint) or cb.dirpath is None:
                continue
            state = self.saved.get(cb.state_key) or {}
            path = state.get("best_model_path")
            if not path:
                continue
            moved = Path(cb.dirpath) / Path(path).name
            if not moved.is_file() or Path(path).parent.resolve() == moved.parent.resolve():
                continue  # no such file here, or the same directory
            if cb.best_model_path == path:
                cb.best_model_path = str(moved)
            score = state.get("best_model_score")
            if cb.monitor is not None and cb.best_model_score is None and score is not None:
                cb.best_model_score, cb.best_model_path = score, str(moved)
                cb.kth_value, cb.kth_best_model_path = score, str(moved)
                cb.best_k_models = {str(moved): score}


def _checkpoint_files(callbacks: list[Any]) -> tuple[str | None, str | None]:
    """(last, best) checkpoint files written by the run's ModelCheckpoints (None: none written).

    ``last``: the ModelCheckpoint without a monitor (it keeps the newest epoch); ``best``: the
    one monitoring a metric (it keeps the best epoch).
    """
    last = best = None
    for cb in callbacks:
        if isinstance(cb, ModelCheckpoint) and cb.best_model_path and Path(cb.best_model_path).is_file():
            if cb.monitor is None:
                last = last or cb.best_model_path
            else:
                best = best or cb.best_model_path
    return last, best


def _epoch_of(path: str | None) -> int | None:
    return int(read_checkpoint(path, require=("epoch",))["epoch"]) if path else None


def _table_at(module: Any, state_dict: dict[str, Any], truth: Any) -> tuple[list[dict[str, Any]], dict[str, float]]:
    """The true-vs-learned table and parameter errors of ``module`` with the weights ``state_dict``
    (loaded for the call, then the module's own weights are put back)."""
    own = {k: v.detach().clone() for k, v in module.state_dict().items()}
    try:
        module.load_state_dict(state_dict)
        return parameter_table(module, truth), module.parameter_errors()
    finally:
        module.load_state_dict(own)


def _floats(values: dict[str, Any]) -> dict[str, float]:
    return {k: float(v) for k, v in values.items()}


def _evaluate(cfg: DictConfig, objects: dict[str, Any], previous: dict[str, float], wall: float) -> dict[str, Any]:
    """Test (``cfg.test``) and collect the metrics and the table of the final weights.

    ``previous``: the epoch-level metrics an earlier process of this run reported; a run
    resumed after its last epoch (interrupted while testing) trains no epoch here, and keeps them.
    """
    trainer, module, truth = objects["trainer"], objects["module"], objects["truth"]
    metrics: dict[str, Any] = {**previous, **objects["fit_metrics"]}
    if cfg.get("test") and not trainer.fast_dev_run:
        for r in trainer.test(module, datamodule=objects["datamodule"], verbose=False):
            metrics.update(_floats(r))
    last, best = _checkpoint_files(objects["callbacks"])
    metrics["wall_time"] = wall
    metrics["param_errors"] = module.parameter_errors()
    metrics["skipped_steps"] = float(module.skipped_steps)
    if module.skipped_steps:
        warnings.warn(
            f"{module.skipped_steps} optimizer steps were skipped (non-finite loss or gradient)", stacklevel=3
        )
    metrics["table"] = parameter_table(module, truth)  # without a truth: what was learned
    metrics["best_model_path"] = best or ""
    metrics["checkpoints"] = {"last": last, "best": best}
    metrics["status"] = "completed"
    return metrics


def _report_completed(cfg: DictConfig, objects: dict[str, Any], report: RunReport, metrics: dict[str, Any]) -> None:
    """Write metrics.json / results.md of a completed run: the final weights (``last.ckpt``) and
    the best epoch (``best.ckpt``, its own table); print results.md."""
    trainer, module, truth, callbacks = objects["trainer"], objects["module"], objects["truth"], objects["callbacks"]
    last, best = metrics["checkpoints"]["last"], metrics["checkpoints"]["best"]
    best_info = None
    if best:
        ckpt = read_checkpoint(best)
        table, errors = _table_at(module, ckpt["state_dict"], truth)
        monitored = next((c for c in callbacks if isinstance(c, ModelCheckpoint) and c.monitor), None)
        score = monitored.best_model_score if monitored is not None else None
        best_info = {
            "checkpoint": best,
            "epoch": int(ckpt["epoch"]),
            "val/nll": None if score is None else float(score),
            "table": table,
            "param_errors": errors,
        }
    reported = {
        "checkpoint": last,
        "epoch": _epoch_of(last),
        "description": "the final weights, at the end of the last epoch"
        + ("" if last else " (not checkpointed: no ModelCheckpoint without a monitor ran)"),
    }
    title = f"{cfg.model.get('name')}: {'true vs learned' if truth else 'learned values'}"
    report.completed(
        title=title,
        wall_time=metrics["wall_time"],
        epochs=int(trainer.current_epoch),
        reported=reported,
        metrics={k: v for k, v in metrics.items() if isinstance(v, float)},
        param_errors=metrics["param_errors"],
        skipped_steps=module.skipped_steps,
        identifiability=module.identifiability_note() if truth else "",
        table=metrics["table"],
        best=best_info,
        data_summary=data_summary(objects["datamodule"]),
        data_text=_summary_text(objects["datamodule"]),
    )
    print("\n" + (report.run_dir / "results.md").read_text())


def _summary_text(datamodule: Any) -> str | None:
    """The datamodule's summary as it prints itself (None when it offers none)."""
    summary = getattr(datamodule, "summary", None)
    summary = summary() if callable(summary) else summary
    return None if summary is None else str(summary)


def train(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Train per ``cfg``; returns (metrics, objects).

    metrics: final ``trainer.callback_metrics`` as floats plus ``param_errors`` (dict),
    ``table`` (true vs learned rows of the final weights = ``last.ckpt``), ``wall_time`` (s),
    ``checkpoints`` ({"last", "best"} paths), ``best_model_path`` and ``status``.
    objects: "cfg", "datamodule", "module", "trainer", "callbacks", "loggers", "truth".

    Raises:
        ValueError / TypeError: a config value that cannot make a sensible run (naming the
            key), before any work; FileNotFoundError / CheckpointError: a ``ckpt_path`` that
            cannot be resumed from.
        RunInterrupted: SIGTERM / SIGINT stopped the run (after it wrote its report).
    """
    check_config(cfg)
    resume = read_checkpoint(cfg.ckpt_path, require=RESUME_KEYS) if cfg.get("ckpt_path") else None
    out_dir = Path(cfg.output_dir)
    log.info("run directory: %s", out_dir.resolve())
    log.info("config:\n%s", _config_text(cfg))
    state = _RunState()
    with SignalGuard() as guard:
        try:
            metrics = _run(cfg, guard, resume, out_dir, state)
        except (StopRun, SystemExit) as stop:
            signum = guard.received or _signal_of(stop)
            if signum is None:  # e.g. Lightning's exit after a KeyboardInterrupt raised by code
                _report_failed(
                    state,
                    stop,
                    f"the run stopped (SystemExit {stop.args[0] if stop.args else ''}) without a signal: e.g. a KeyboardInterrupt raised by code, which Lightning turns into an exit",
                )
                raise
            if state.report is None and "trainer" not in state.objects and int(os.environ.get("LOCAL_RANK", "0")) == 0:
                state.report = _new_report(cfg, out_dir, resume)  # stopped while building: still say so
            raise _interrupted(
                state.objects, state.report, signum, guard.received_during or guard.phase, out_dir
            ) from None
        except Exception as err:
            _report_failed(state, err)
            log.error("run failed: %s: %s", type(err).__name__, err)
            raise
    if guard.received is not None:
        log.warning("received %s after the run completed; its outputs are complete", guard.received.name)
    log.info("run completed: %s", out_dir.resolve())
    return metrics, state.objects


def _report_failed(state: _RunState, error: BaseException, message: str | None = None) -> None:
    """The failed report (rank zero, once built) with the epochs ``last.ckpt`` holds, if any."""
    if state.report is None:
        return
    try:
        last, _ = _checkpoint_files(state.objects.get("callbacks", []))
        epochs = (_epoch_of(last) + 1) if last else 0
    except Exception:  # noqa: BLE001 - the report of a failure must not fail itself
        last, epochs = None, None
    state.report.failed(RuntimeError(message) if message else error, epochs=epochs, checkpoint=last)


@dataclass
class _RunState:
    """What a run has built so far (for the report of an interrupted or failed run)."""

    objects: dict[str, Any] = field(default_factory=dict)
    report: RunReport | None = None


def _run(
    cfg: DictConfig, guard: SignalGuard, resume: dict[str, Any] | None, out_dir: Path, state: _RunState
) -> dict[str, Any]:
    """Build, fit, test, plot and report, phase by phase (``guard`` stops between them)."""
    ckpt_path = cfg.get("ckpt_path")
    state.objects = objects = _build(cfg, guard, resume)
    trainer, module = objects["trainer"], objects["module"]
    same_dir = False
    if resume is not None:
        check_state_dict(ckpt_path, resume["state_dict"], module)
        _warn_if_schedule_ends_early(ckpt_path, cfg.trainer.get("max_epochs"), resume)
        same_dir = Path(ckpt_path).resolve().parent.parent == out_dir.resolve()
        log.info(
            "resuming from %s (epoch %d) %s",
            ckpt_path,
            resume["epoch"],
            "in the same run directory" if same_dir else f"into the new run directory {out_dir}",
        )
    if trainer.is_global_zero:
        state.report = _new_report(cfg, out_dir, resume)
        state.report.running()
        for lg in objects["loggers"]:
            if same_dir:
                continue_csv_log(lg, int(resume["epoch"]))
            lg.log_hyperparams(OmegaConf.to_container(cfg, resolve=True))
    start = time.perf_counter()
    with guard.graceful("fit"), warnings.catch_warnings():
        if same_dir:
            warnings.filterwarnings("ignore", message=r"Checkpoint directory .* exists and is not empty")
        trainer.fit(module, datamodule=objects["datamodule"], ckpt_path=ckpt_path, weights_only=True)
    wall = time.perf_counter() - start
    objects["fit_metrics"] = _floats(trainer.callback_metrics)  # the test replaces callback_metrics
    validated = next(c for c in objects["callbacks"] if isinstance(c, _ValidatedAt))
    if validated.stale and not trainer.fast_dev_run and trainer.limit_val_batches:
        # the last validation saw older weights than the reported ones (last.ckpt): validate these
        with guard.graceful("fit"):
            for r in trainer.validate(module, datamodule=objects["datamodule"], verbose=False):
                objects["fit_metrics"].update(_floats(r))
    guard.stop_if_received()
    with guard.graceful("test"):
        metrics = _evaluate(cfg, objects, state.report.previous_metrics if state.report is not None else {}, wall)
    guard.stop_if_received()
    if trainer.is_global_zero and cfg.get("plots") and not trainer.fast_dev_run:
        history = next((c for c in objects["callbacks"] if isinstance(c, ParameterHistory)), None)
        with guard.graceful("plots"):
            plot_run(out_dir, module, objects["datamodule"], history.history if history else [], objects["truth"])
    guard.stop_if_received()
    if state.report is not None:
        with guard.graceful("outputs"):  # complete: a signal now no longer stops anything
            _report_completed(cfg, objects, state.report, metrics)
    return metrics


def _new_report(cfg: DictConfig, out_dir: Path, resume: dict[str, Any] | None) -> RunReport:
    return RunReport(
        out_dir,
        model=cfg.model.get("name"),
        noise=cfg.data.get("noise"),
        max_epochs=cfg.trainer.get("max_epochs"),
        overrides=_overrides(),
        resumed_from=(cfg.ckpt_path, int(resume["epoch"])) if resume is not None else None,
    )


def _signal_of(stop: BaseException) -> int | None:
    """The signal behind a stop: StopRun's own, SIGTERM for Lightning's SIGTERMException
    (e.g. broadcast to this rank by another one), None for any other SystemExit."""
    if isinstance(stop, StopRun):
        return stop.signum
    if isinstance(stop, SIGTERMException):
        return signal.SIGTERM
    return None


def _interrupted(
    objects: dict[str, Any], report: RunReport | None, signum: int, phase: str, out_dir: Path
) -> RunInterrupted:
    """Write the interrupted report (rank zero) and return the exception to raise."""
    last, _ = _checkpoint_files(objects.get("callbacks", []))
    epochs = (_epoch_of(last) + 1) if last else 0
    if report is not None:
        trainer = objects.get("trainer")
        metrics = objects.get("fit_metrics") or (_floats(trainer.callback_metrics) if trainer is not None else {})
        metrics = {**report.previous_metrics, **metrics}
        report.interrupted(
            signum,
            phase,
            epochs=epochs,
            checkpoint=last,
            metrics=metrics,
            data_summary=data_summary(objects.get("datamodule")),
        )
    stop = RunInterrupted(signum, phase, str(out_dir.resolve()), str(Path(last).resolve()) if last else None)
    log.error("%s", stop)
    return stop


def _route_lightning_logs() -> None:
    """Send Lightning's log records through the handlers Hydra configured (console and train.log).

    Imported before logging is configured, Lightning gives its loggers a console handler of
    their own and stops them propagating, which keeps its messages out of train.log.
    """
    if not logging.getLogger().handlers:
        return
    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logger = logging.getLogger(name)
        for handler in [h for h in logger.handlers if type(h) is logging.StreamHandler]:
            logger.removeHandler(handler)
        logger.propagate = True


def config_path() -> str:
    """Where the Hydra configs are: a checkout's top-level conf/, else the installed package's.

    A source checkout (editable install, ``PYTHONPATH``) has ``conf/`` next to the package
    directory; a wheel ships the same files inside the package as ``torchsde_lti/conf/``
    (setup.py maps the top-level conf/ to ``torchsde_lti.conf``). Both are returned as
    absolute paths, so the job runs from any working directory. (Hydra's
    ``pkg://torchsde_lti.conf`` would need an ``__init__.py`` in conf/.)
    """
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
    _route_lightning_logs()
    try:
        metrics, _ = train(cfg)
    except RunInterrupted as stop:
        sys.exit(stop.exit_code)
    value = metrics.get("val/nll")
    return float(value) if value is not None else None


if __name__ == "__main__":
    main()
