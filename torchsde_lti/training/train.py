"""The main job: learn a motion model with a Kalman-filter likelihood, configured by Hydra.

    python -m torchsde_lti.train                                   # default run (conf/train.yaml)
    python -m torchsde_lti.train model=singer data.noise=1.0       # override anything
    python -m torchsde_lti.train --multirun model=cv,integrated_ou,singer data.noise=0.1,1.0
    python -m torchsde_lti.train ckpt_path=<run>/checkpoints/last.ckpt    # resume, same overrides

Everything is built with ``hydra.utils.instantiate`` from ``_target_`` nodes; the logic
lives here in :func:`train`, which tests call with a composed config. A run writes into its
Hydra output directory: ``checkpoints/``, logger files, ``metrics.json`` (final metrics and
the true-vs-learned table), ``results.md`` and the plots ``loss.png``, ``track.png``,
``params.png``.

Resuming restores the LR scheduler's own state, including the cosine schedule's
``T_max`` (= the original ``trainer.max_epochs``): a resumed run continues the same
schedule. Raising ``trainer.max_epochs`` beyond it makes the cosine LR climb back towards
its initial value, so :func:`train` warns about it.
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path
from typing import Any

import hydra
import lightning.pytorch as pl
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from torchsde_lti.training.callbacks import ParameterHistory
from torchsde_lti.training.metrics import format_table, parameter_table
from torchsde_lti.training.plots import plot_run

__all__ = ["config_path", "main", "restart_learner", "train"]


def _instantiate_dict(node: DictConfig | None) -> list[Any]:
    """Instantiate every ``_target_`` child of a dict node (callbacks, loggers)."""
    if node is None:
        return []
    return [instantiate(v) for v in node.values() if isinstance(v, DictConfig) and "_target_" in v]


def _check_config(cfg: DictConfig) -> None:
    """Fail fast, before any work, on values that would only break later."""
    for key in ("model", "data", "trainer", "filter", "module"):
        if cfg.get(key) is None:
            raise ValueError(f"config is missing the '{key}' node")
    if cfg.get("dtype") not in ("float32", "float64"):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {cfg.get('dtype')!r}")


def _warn_if_schedule_ends_early(ckpt_path: str | None, max_epochs: int | None) -> None:
    """Warn when a resumed run trains past the restored scheduler's ``T_max``.

    Schedulers such as CosineAnnealingLR are periodic beyond ``T_max``; the value comes
    from the checkpoint, not from the config, so extending a finished run raises the LR.
    """
    if not ckpt_path or max_epochs is None or int(max_epochs) < 0:
        return
    ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=True)
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


def train(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Train per ``cfg``; returns (metrics, objects).

    metrics: final ``trainer.callback_metrics`` as floats plus ``param_errors`` (dict),
    ``table`` (true vs learned rows), ``wall_time`` (s) and ``best_model_path``.
    objects: "cfg", "datamodule", "module", "trainer", "callbacks", "loggers".
    """
    _check_config(cfg)
    if cfg.get("num_threads"):
        torch.set_num_threads(int(cfg.num_threads))
    pl.seed_everything(int(cfg.seed), workers=True, verbose=False)
    out_dir = Path(cfg.output_dir)
    datamodule = instantiate(cfg.data)
    truth = getattr(datamodule, "truth", None)
    prior: dict[str, Any] = {}
    if getattr(datamodule, "m0", None) is not None and getattr(datamodule, "P0", None) is not None:
        # the data's prior, used when the learner has the truth's state (model=cv truth=singer: it does not)
        prior = {"m0": datamodule.m0, "P0": datamodule.P0}
    if truth is not None and getattr(datamodule, "H", None) is not None:
        truth = {**truth, "H": datamodule.H}
    kf = instantiate(cfg.filter)
    if prior and int(kf.state_dim) == int(prior["m0"].shape[-1]):
        kf = instantiate(cfg.filter, **prior)
    restart_learner(kf, float(cfg.get("init_jitter") or 0.0), int(cfg.get("restart") or 0))
    module = instantiate(cfg.module, kf=kf, truth=truth)
    callbacks = _instantiate_dict(cfg.get("callbacks"))
    loggers = _instantiate_dict(cfg.get("logger"))
    trainer: pl.Trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)
    if trainer.is_global_zero and loggers:
        for lg in loggers:
            lg.log_hyperparams(OmegaConf.to_container(cfg, resolve=True))

    _warn_if_schedule_ends_early(cfg.get("ckpt_path"), cfg.trainer.get("max_epochs"))
    start = time.perf_counter()
    trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"), weights_only=True)
    wall = time.perf_counter() - start
    metrics: dict[str, Any] = {k: float(v) for k, v in trainer.callback_metrics.items()}
    if cfg.get("test") and not trainer.fast_dev_run:
        results = trainer.test(module, datamodule=datamodule, verbose=False)
        for r in results:
            metrics.update({k: float(v) for k, v in r.items()})
    metrics["wall_time"] = wall
    metrics["param_errors"] = module.parameter_errors()
    metrics["skipped_steps"] = float(module.skipped_steps)
    note = module.identifiability_note() if truth else ""
    if module.skipped_steps:
        warnings.warn(f"{module.skipped_steps} optimizer steps were skipped (non-finite loss or gradient)", stacklevel=2)
    metrics["table"] = parameter_table(module, truth)  # without a truth: what was learned
    ckpt = next((c for c in callbacks if isinstance(c, pl.callbacks.ModelCheckpoint)), None)
    metrics["best_model_path"] = ckpt.best_model_path if ckpt is not None else ""
    history = next((c for c in callbacks if isinstance(c, ParameterHistory)), None)
    data_summary = getattr(datamodule, "summary", None)  # real tracks: what the loader kept and removed

    if trainer.is_global_zero:
        out_dir.mkdir(parents=True, exist_ok=True)
        summary = {
            "model": cfg.model.get("name"),
            "noise": cfg.data.get("noise"),
            "wall_time": wall,
            "epochs": trainer.current_epoch,
            "metrics": {k: v for k, v in metrics.items() if isinstance(v, float)},
            "param_errors": metrics["param_errors"],
            "skipped_steps": module.skipped_steps,
            "identifiability": note,
            "table": metrics["table"],
            "data": data_summary.as_dict() if data_summary is not None else None,
        }
        (out_dir / "metrics.json").write_text(json.dumps(summary, indent=2, allow_nan=True))
        if metrics["table"]:
            title = "true vs learned" if truth else "learned values"
            text = f"# {cfg.model.get('name')}: {title} ({wall:.1f} s)\n\n{format_table(metrics['table'])}\n"
            text += f"\nskipped optimizer steps (non-finite loss or gradient): {module.skipped_steps}\n"
            if note:
                text += f"\nNot identifiable: {note}\n"
            if data_summary is not None:
                text += f"\n## Data\n\n```\n{data_summary}\n```\n"
            (out_dir / "results.md").write_text(text)
            print("\n" + text)
        if cfg.get("plots") and not trainer.fast_dev_run:
            plot_run(out_dir, module, datamodule, history.history if history else [], truth)
    objects = {
        "cfg": cfg,
        "datamodule": datamodule,
        "module": module,
        "trainer": trainer,
        "callbacks": callbacks,
        "loggers": loggers,
    }
    return metrics, objects


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
    """Hydra entry point; returns val/nll (for Hydra sweepers)."""
    metrics, _ = train(cfg)
    value = metrics.get("val/nll")
    return float(value) if value is not None else None


if __name__ == "__main__":
    main()
