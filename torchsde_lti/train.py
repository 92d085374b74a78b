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
import math
import time
import warnings
from pathlib import Path
from typing import Any

import hydra
import lightning.pytorch as pl
import torch
from hydra.experimental.callback import Callback as HydraCallback
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from torchsde_lti.lightning_module import KalmanFilterModule, ParameterHistory, learned_values, same_model

__all__ = ["BestRun", "config_path", "format_table", "main", "parameter_table", "plot_run", "restart_learner", "train"]


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


def parameter_table(module: KalmanFilterModule, truth: dict[str, Any] | None) -> list[dict[str, Any]]:
    """Rows {"name", "true", "learned", "rel_error"} for every learned quantity.

    Named scalars and the diagonal of R are listed by value; the matrix errors (``expmF``:
    max over dt of ‖expm(F dt) − expm(F* dt)‖/‖expm(F* dt)‖; ``autocov``: the observed
    autocovariance, for a free F the data do not determine entrywise; ``Qc``, ``R``) by error only.
    """
    errors = module.parameter_errors()
    kf = module.kf
    learned = learned_values(kf.sde, kf.R, module.param_names)
    true: dict[str, Any] = {}
    if truth:
        paired = same_model(kf.sde, truth["sde"])
        true = learned_values(truth["sde"], truth.get("R"), module.param_names if paired else [])
        if not paired:
            true = {k: v for k, v in true.items() if k == "R"}
    rows: list[dict[str, Any]] = []
    for name, value in learned.items():
        if value.dim() == 0:
            t = float(true[name]) if name in true else math.nan
            rows.append({"name": name, "true": t, "learned": float(value), "rel_error": errors.get(name, math.nan)})
    if "R" in errors and "R" in true:
        for i, (a, b) in enumerate(zip(torch.diagonal(learned["R"]), torch.diagonal(true["R"]))):
            err = abs(float(a) - float(b)) / abs(float(b)) if float(b) != 0 else math.nan
            rows.append({"name": f"R[{i},{i}]", "true": float(b), "learned": float(a), "rel_error": err})
    for name in ("expmF", "autocov", "Qc", "R"):
        if name in errors:
            rows.append({"name": f"{name} (matrix)", "true": math.nan, "learned": math.nan, "rel_error": errors[name]})
    return rows


def restart_learner(kf: torch.nn.Module, jitter: float, seed: int) -> None:
    """Random restart: add N(0, jitter²) (generator seeded with ``seed``) to every raw parameter
    of the learner's motion model, in place (``jitter = 0``: keep the configured start).

    Raw parameters are unconstrained by construction (softplus / Cholesky / Hurwitz
    factors), so every perturbed start is valid: a Hurwitz F stays Hurwitz. A Hydra seed sweep
    (``experiment=restarts``) then runs K restarts and keeps the best validation NLL.
    """
    if not jitter > 0:
        return
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in kf.sde.parameters():
            if p.requires_grad:
                p.add_(jitter * torch.randn(p.shape, generator=g, dtype=torch.float64).to(p))


class BestRun(HydraCallback):
    """Hydra callback: after a multirun, pick the run with the best ``metric`` and report it.

    Reads every job's ``metrics.json`` under the sweep directory, writes ``best_run.json``
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
        return {"metric": self.metric, "best_dir": winner["dir"], "overrides": winner["overrides"],
                "value": winner["value"], "runs": runs}

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        result = self.best(sweep_dir)
        (sweep_dir / "best_run.json").write_text(json.dumps(result, indent=2))
        print(f"best of {len(result['runs'])} runs by {self.metric}: {result['value']:.6g} in {result['best_dir']} "
              f"({' '.join(map(str, result['overrides']))})")


def format_table(rows: list[dict[str, Any]]) -> str:
    """Markdown table of :func:`parameter_table` rows."""
    lines = ["| parameter | true | learned | rel. error |", "|---|---:|---:|---:|"]
    for r in rows:
        t = "" if math.isnan(r["true"]) else f"{r['true']:.4g}"
        v = "" if math.isnan(r["learned"]) else f"{r['learned']:.4g}"
        lines.append(f"| {r['name']} | {t} | {v} | {100 * r['rel_error']:.2f} % |")
    return "\n".join(lines)


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
        # the data's prior, when the learner has the truth's state (model=cv truth=singer: it does not)
        if int(instantiate(cfg.filter.sde).state_dim) == int(datamodule.m0.shape[-1]):
            prior = {"m0": datamodule.m0, "P0": datamodule.P0}
    if truth is not None and getattr(datamodule, "H", None) is not None:
        truth = {**truth, "H": datamodule.H}
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
    metrics["table"] = parameter_table(module, truth) if truth else []
    ckpt = next((c for c in callbacks if isinstance(c, pl.callbacks.ModelCheckpoint)), None)
    metrics["best_model_path"] = ckpt.best_model_path if ckpt is not None else ""
    history = next((c for c in callbacks if isinstance(c, ParameterHistory)), None)

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
        }
        (out_dir / "metrics.json").write_text(json.dumps(summary, indent=2, allow_nan=True))
        if metrics["table"]:
            text = f"# {cfg.model.get('name')}: true vs learned ({wall:.1f} s)\n\n{format_table(metrics['table'])}\n"
            text += f"\nskipped optimizer steps (non-finite loss or gradient): {module.skipped_steps}\n"
            if note:
                text += f"\nNot identifiable: {note}\n"
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


# --------------------------------------------------------------------------- plots


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
        if truth:
            from torchsde_lti.lightning_module import _flat

            paired = same_model(module.kf.sde, truth["sde"])
            true = _flat(learned_values(truth["sde"], truth.get("R"), module.param_names if paired else []))
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
    y, dt, mask, u, x = module._unpack(batch)
    y, dt = y[:1], dt[:1]
    u = u[:1] if u is not None else None
    x = x[:1] if x is not None else None
    T = int(mask[0].sum()) if mask is not None else y.shape[-2]
    y, dt = y[:, :T], dt[:, :T]
    u = u[:, :T] if u is not None else None
    with torch.no_grad():
        out = module.kf(y, dt, u=u)
        sm = module.kf.smooth(out)
    H = module.kf.H.detach().to(y.dtype)
    t = torch.cumsum(dt[0], 0)
    m = y.shape[-1]
    fig, axes = plt.subplots(m, 1, figsize=(8, 2.4 * m), sharex=True, squeeze=False)
    for i, ax in enumerate(axes[:, 0]):
        h = H[i]
        for label, mean, cov, color in (
            ("filtered", out.mean[0], out.cov[0], "C0"),
            ("smoothed", sm.mean[0], sm.cov[0], "C1"),
        ):
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
