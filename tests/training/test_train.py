"""The Hydra entry point (torchsde_lti.training.train): configs, the main job, sweeps, on tiny problems.

Covers: every config group composes and instantiates; fast_dev_run end to end; resume from
a checkpoint continues exactly like an uninterrupted run; checkpoints load with
``weights_only=True``; a --multirun over two values launches two runs; a 2-process DDP
(gloo) run; bad config values fail fast; learner/truth pairing; random restarts through a
Hydra multirun. Loss pieces: test_module.py; parameter recovery: tests/evaluation/test_recovery.py.
"""

from __future__ import annotations

import copy
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from hydra.utils import instantiate

from torchsde_lti.training import KalmanFilterModule, train
from torchsde_lti.training.plots import epoch_rows

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
TINY = ["experiment=tiny"]


def _cfg(tmp_path: Path, *overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("train", overrides=[f"output_dir={tmp_path}", *overrides])


def _group(name: str) -> list[str]:
    return sorted(p.stem for p in (CONF / name).glob("*.yaml"))


# --------------------------------------------------------------------------- composition


@pytest.mark.parametrize(
    "model", [m for m in _group("model") if not m.startswith("imm")]
)  # imm*: test_imm_training.py, test_real_data.py
def test_model_configs_instantiate_filter_and_data(tmp_path: Path, model: str) -> None:
    cfg = _cfg(tmp_path, f"model={model}", *TINY)
    dm = instantiate(cfg.data)
    kf = instantiate(cfg.filter, m0=dm.m0, P0=dm.P0)
    module = instantiate(cfg.module, kf=kf, truth=dm.truth)
    assert isinstance(module, KalmanFilterModule)
    assert kf.H.shape == (cfg.model.obs_dim, kf.sde.state_dim)
    assert any(p.requires_grad for p in module.parameters())
    # the learner starts away from the truth
    assert max(module.parameter_errors().values()) > 0.5


@pytest.mark.parametrize("data", _group("data"))
def test_data_configs_instantiate_a_datamodule(tmp_path: Path, data: str) -> None:
    import lightning.pytorch as pl

    if data != "simulated":  # real tracks: the files come with the data extra
        pytest.importorskip("tracktable_data")
    cfg = _cfg(tmp_path, f"data={data}", *TINY) if data == "simulated" else _cfg(tmp_path, f"data={data}")
    assert isinstance(instantiate(cfg.data), pl.LightningDataModule)


@pytest.mark.parametrize("dt", _group("data/dt"))
def test_dt_configs_instantiate(tmp_path: Path, dt: str) -> None:
    cfg = _cfg(tmp_path, f"data/dt={dt}", *TINY)
    dm = instantiate(cfg.data)
    dm.setup()
    assert bool((dm.tracks["train"].dt[dm.tracks["train"].mask] > 0).all())


@pytest.mark.parametrize("trainer", _group("trainer"))
def test_trainer_configs_instantiate(tmp_path: Path, trainer: str) -> None:
    cfg = _cfg(tmp_path, f"trainer={trainer}")
    t = instantiate(cfg.trainer, logger=False, callbacks=[])
    assert t.max_epochs == cfg.trainer.max_epochs
    if trainer == "ddp":
        assert type(t.strategy).__name__ == "DDPStrategy" and t.strategy._process_group_backend == "gloo"


@pytest.mark.parametrize("logger", _group("logger"))
def test_logger_configs_instantiate(tmp_path: Path, logger: str) -> None:
    if logger == "tensorboard":
        pytest.importorskip("tensorboard")
    cfg = _cfg(tmp_path, f"logger={logger}")
    for node in cfg.logger.values():
        assert instantiate(node).save_dir == str(tmp_path)


def test_callback_configs_instantiate(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path)
    names = {type(instantiate(c)).__name__ for c in cfg.callbacks.values()}
    assert names == {"ModelCheckpoint", "RunLog"}
    # each checkpoint named for what it holds: the last epoch (no monitor), the best val/nll
    assert cfg.callbacks.best.monitor == "val/nll" and cfg.callbacks.best.filename == "best"
    assert cfg.callbacks.last.monitor is None and cfg.callbacks.last.filename == "last"


@pytest.mark.parametrize("experiment", _group("experiment"))
def test_experiment_configs_compose(tmp_path: Path, experiment: str) -> None:
    if experiment.startswith(("ais", "flights", "search_imm")):
        pytest.importorskip("tracktable_data")
    if experiment.startswith("search"):
        pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    cfg = _cfg(tmp_path, f"experiment={experiment}")
    assert cfg.data._target_ and cfg.filter._target_ and cfg.module._target_


def test_joblib_launcher_config_composes(tmp_path: Path) -> None:
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=["hydra/launcher=parallel"], return_hydra_config=True)
    assert "JoblibLauncher" in cfg.hydra.launcher._target_ and cfg.hydra.launcher.n_jobs == 2


# --------------------------------------------------------------------------- fail fast


def test_unknown_model_fails_fast(tmp_path: Path) -> None:
    with pytest.raises(ConfigCompositionException, match="nosuchmodel"):
        _cfg(tmp_path, "model=nosuchmodel")


@pytest.mark.parametrize(("override", "match"), [("data.noise=-0.5", "data.noise"), ("data.T=1", "data.T")])
def test_bad_values_fail_before_training(tmp_path: Path, override: str, match: str) -> None:
    cfg = _cfg(tmp_path, *TINY, override)
    with pytest.raises(ValueError, match=rf"config data .*{match}"):  # the target's ValueError, naming the node
        train(cfg)
    assert not (tmp_path / "checkpoints").exists()


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        (["filter=imm"], "filter=imm needs a bank of modes.*model=integrated_ou"),  # was: 'model.mode_names' not found
        (["model=imm", "~truth"], "model=imm is a bank of modes for filter=imm"),
    ],
)
def test_filter_and_model_mismatch_fails_fast(tmp_path: Path, overrides: list[str], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        train(_cfg(tmp_path, *TINY, *overrides))
    assert not (tmp_path / "checkpoints").exists()


def test_bad_dtype_fails_fast(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="dtype"):
        train(_cfg(tmp_path, *TINY, "dtype=float16"))


# --------------------------------------------------------------------------- training runs


def test_fast_dev_run_end_to_end(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path, *TINY, "+trainer.fast_dev_run=true")
    metrics, objects = train(cfg)
    assert math.isfinite(metrics["train/nll"]) and math.isfinite(metrics["val/nll"])
    assert set(metrics["param_errors"]) == {"k", "q", "expmF", "R"}
    assert (tmp_path / "metrics.json").exists()
    assert metrics["skipped_steps"] == 0.0


def test_any_learner_pairs_with_any_truth(tmp_path: Path) -> None:
    """model= picks the learner, truth= the simulated model: a CV learner on Singer data runs."""
    cfg = _cfg(tmp_path, "model=cv", "truth=singer", *TINY, "+trainer.fast_dev_run=true")
    assert cfg.data.sde._target_.endswith("singer") and cfg.filter.sde._target_.endswith("constant_velocity")
    metrics, objects = train(cfg)
    assert math.isfinite(metrics["val/nll"])
    assert objects["datamodule"].tracks["train"].x.shape[-1] == 6 and objects["module"].kf.sde.state_dim == 4
    # nothing to pair entrywise between a CV and a Singer model but R
    assert set(metrics["param_errors"]) == {"R"}
    # the default pairs the learner with its own truth
    assert _cfg(tmp_path, "model=singer").data.sde._target_.endswith("singer")


def test_config_path_finds_the_checkout_conf() -> None:
    from torchsde_lti.training import config_path

    assert Path(config_path()) == CONF


def test_restart_learner_perturbs_raw_parameters_reproducibly() -> None:
    import torchsde_lti as tl
    from torchsde_lti.training import restart_learner

    def make() -> tl.KalmanFilter:
        sde = tl.LTISDE(
            -torch.eye(2, dtype=torch.float64),
            torch.eye(2, dtype=torch.float64),
            torch.eye(2, dtype=torch.float64),
            F_constraint="hurwitz",
        )
        return tl.KalmanFilter(sde, torch.eye(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64))

    a, b, c = make(), make(), make()
    restart_learner(a, 0.5, 3)
    restart_learner(b, 0.5, 3)
    restart_learner(c, 0.0, 3)
    assert torch.equal(a.sde.F, b.sde.F) and not torch.equal(a.sde.F, c.sde.F)
    assert torch.equal(c.sde.F, -torch.eye(2, dtype=torch.float64))
    assert float(torch.linalg.eigvals(a.sde.F).real.max()) < 0  # a restart of a Hurwitz F is Hurwitz


def test_float32_training_keeps_float32(tmp_path: Path) -> None:
    metrics, objects = train(_cfg(tmp_path, *TINY, "dtype=float32", "trainer.max_epochs=1"))
    assert all(p.dtype == torch.float32 for p in objects["module"].parameters())
    assert math.isfinite(metrics["val/nll"])


def test_plots_and_table_written(tmp_path: Path) -> None:
    metrics, _ = train(_cfg(tmp_path, *TINY, "plots=true", "test=false"))
    for name in ("loss.png", "params.png", "map.png", "results.md"):
        assert (tmp_path / name).stat().st_size > 0
    summary = json.loads((tmp_path / "metrics.json").read_text())
    assert {r["name"] for r in summary["table"]} >= {"k", "q", "R[0,0]"}


def test_table_against_a_zero_noise_truth_gives_no_relative_error(tmp_path: Path) -> None:
    # R = 0 has no relative error: the R row used to show ‖R‖ (an absolute value) as a percentage
    from torchsde_lti.evaluation import parameter_table

    cfg = _cfg(tmp_path, *TINY, "data.noise=0")
    dm = instantiate(cfg.data)
    module = instantiate(cfg.module, kf=instantiate(cfg.filter, m0=dm.m0, P0=dm.P0), truth=dm.truth)
    rows = {
        r["name"]: r for r in parameter_table(module.kf, {**dm.truth, "H": dm.H}, module.param_names, module.compare)
    }
    assert "R (matrix)" not in rows
    row = rows["R (matrix, ‖·‖_F)"]
    assert row["true"] == 0.0 and math.isnan(row["rel_error"])
    assert row["learned"] == pytest.approx(float(torch.linalg.matrix_norm(module.kf.R.double())))
    assert math.isfinite(rows["k"]["rel_error"]) and math.isnan(rows["R[0,0]"]["rel_error"])


def test_epoch_metrics_are_per_observed_scalar_over_all_batches(tmp_path: Path) -> None:
    """val/nll = Σ NLL / Σ observed scalars and val/rmse = √(Σ squared errors / Σ observed scalars)
    over the epoch, whatever the batches' sizes (a batch of 7 tracks beside ones of 25)."""
    metrics, objects = train(_cfg(tmp_path, *TINY, "trainer.max_epochs=1", "test=false", "plots=false",
                                  "data.num_tracks.val=57", "data.batch_size=25"))  # fmt: skip
    module, dm = objects["module"], objects["datamodule"]
    nll = se = count = 0.0
    with torch.no_grad():
        for batch in dm.val_dataloader():
            _, _, out, info = module._step(batch)
            observed = info["observed"]
            nll -= float(out.log_likelihood.sum())
            err = torch.where(observed, out.pred_mean @ module.kf.H.mT - info["y"], 0.0)
            se, count = se + float((err**2).sum()), count + float(observed.sum())
    assert len(dm.val_dataloader()) == 3
    assert metrics["val/nll"] == pytest.approx(nll / count, rel=1e-10)
    assert metrics["val/rmse"] == pytest.approx(math.sqrt(se / count), rel=1e-10)


def test_checkpoints_are_named_for_what_they_hold_and_reports_say_which(tmp_path: Path) -> None:
    """last.ckpt = the last epoch = what the table and test metrics report; best.ckpt = lowest val/nll."""
    import csv

    from tests.training.helpers import load_strict_json
    from torchsde_lti.evaluation import parameter_table
    from torchsde_lti.training.outputs import to_jsonable

    # lr 2.0 overshoots: val/nll is lowest after epoch 0 and worse later, so best and last differ
    metrics, objects = train(_cfg(tmp_path, *TINY, "trainer.max_epochs=4", "module.optimizer.lr=2.0"))
    last = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)
    best = torch.load(tmp_path / "checkpoints" / "best.ckpt", weights_only=True)
    with (tmp_path / "csv" / "metrics.csv").open() as f:
        val = {int(r["epoch"]): float(r["val/nll"]) for r in csv.DictReader(f) if r["val/nll"]}
    assert last["epoch"] == 3 and best["epoch"] == min(val, key=val.get) == 0
    summary = load_strict_json(tmp_path / "metrics.json")
    assert summary["reported"]["checkpoint"] == "checkpoints/last.ckpt" and summary["reported"]["epoch"] == 3
    assert summary["best"]["checkpoint"] == "checkpoints/best.ckpt" and summary["best"]["epoch"] == 0
    assert summary["best"]["val/nll"] == val[0] and summary["metrics"]["val/nll"] == val[3]
    module, truth = objects["module"], objects["truth"]
    trainer = objects["trainer"]
    for ckpt, table in (
        (best, summary["best"]["table"]),
        (last, summary["table"]),
    ):  # last loaded last: the final weights
        module.load_state_dict(ckpt["state_dict"])
        assert to_jsonable(parameter_table(module.kf, truth, module.param_names, module.compare)) == table
    tested = trainer.test(module, datamodule=objects["datamodule"], verbose=False)[0]
    assert tested["test/nll"] == summary["metrics"]["test/nll"]  # the test metrics are last.ckpt's
    text = (tmp_path / "results.md").read_text()
    assert "`checkpoints/last.ckpt` (epoch 3)" in text and "`checkpoints/best.ckpt` (epoch 0" in text


@pytest.mark.parametrize("datamodule", ["SummarisedTracks", "SummaryAttributeTracks"])
def test_data_summary_is_logged_and_saved(tmp_path: Path, datamodule: str, caplog: pytest.LogCaptureFixture) -> None:
    from tests.training.helpers import load_strict_json

    caplog.set_level("INFO", logger="torchsde_lti.training")
    train(_cfg(tmp_path, *TINY, "trainer.max_epochs=1", f"data._target_=tests.training.helpers.{datamodule}"))
    expected = {"tracks": {"train": 8, "val": 4, "test": 4}, "undefined": None}
    assert load_strict_json(tmp_path / "metrics.json")["data_summary"] == expected
    assert f"data summary ({datamodule})" in caplog.text and '"train": 8' in caplog.text
    assert "epoch 0/0: " in caplog.text and "val/nll=" in caplog.text and "config:" in caplog.text


def test_resume_from_checkpoint_continues_identically(tmp_path: Path) -> None:
    # the interrupted run plans the same schedule (T_max) as the uninterrupted one
    common = [*TINY, "test=false", "module.scheduler.T_max=4"]
    _, full = train(_cfg(tmp_path / "full", *common, "trainer.max_epochs=4"))
    _, part = train(_cfg(tmp_path / "part", *common, "trainer.max_epochs=2"))
    ckpt = tmp_path / "part" / "checkpoints" / "last.ckpt"
    raw = torch.load(ckpt, weights_only=True)  # plain content only
    assert raw["epoch"] == 1
    _, resumed = train(_cfg(tmp_path / "resumed", *common, "trainer.max_epochs=4", f"ckpt_path={ckpt}"))
    a, b = full["module"].state_dict(), resumed["module"].state_dict()
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    # not trivially equal: training moved the parameters
    assert not torch.equal(
        a["kf.sde.parametrizations.k.original"], part["module"].state_dict()["kf.sde.parametrizations.k.original"]
    )
    # a new run directory: its CSV log starts at the resume point, with each epoch's learned values (the plots read them)
    rows = epoch_rows(tmp_path / "resumed" / "csv" / "metrics.csv")
    assert [r["epoch"] for r in rows] == [2.0, 3.0] and "param/k" in rows[-1]


def test_checkpoint_without_the_floors_loads_and_resumes(tmp_path: Path) -> None:
    """A checkpoint saved before the parametrisations' floors were saved (their entries deleted)
    loads into the filter (load_filter_weights) and resumes the run, exactly as the full one."""
    from torchsde_lti.nn.parametrizations import floor_state_keys
    from torchsde_lti.training import load_filter_weights

    common = [*TINY, "test=false", "module.scheduler.T_max=2"]
    _, part = train(_cfg(tmp_path / "part", *common, "trainer.max_epochs=1"))
    new = tmp_path / "part" / "checkpoints" / "last.ckpt"
    ckpt = torch.load(new, weights_only=True)
    floors = {f"kf.{k}" for k in floor_state_keys(part["module"].kf)}
    assert floors and floors <= set(ckpt["state_dict"])  # R, P0 and the model's positive scalars
    ckpt["state_dict"] = {k: v for k, v in ckpt["state_dict"].items() if k not in floors}
    old = tmp_path / "old.ckpt"
    torch.save(ckpt, old)
    kf_new, kf_old = copy.deepcopy(part["module"].kf), copy.deepcopy(part["module"].kf)
    load_filter_weights(kf_new, new)
    load_filter_weights(kf_old, old)
    for name in ("R", "P0"):
        assert torch.equal(getattr(kf_new, name), getattr(kf_old, name)), name
    for a, b in zip(kf_new.sde.matrices(), kf_old.sde.matrices()):
        assert (a is None and b is None) or torch.equal(a, b)
    _, from_new = train(_cfg(tmp_path / "from_new", *common, "trainer.max_epochs=2", f"ckpt_path={new}"))
    _, from_old = train(_cfg(tmp_path / "from_old", *common, "trainer.max_epochs=2", f"ckpt_path={old}"))
    a, b = from_new["module"].state_dict(), from_old["module"].state_dict()
    assert a.keys() == b.keys() and floors <= set(b)  # the resumed run saves the floors again
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_resume_past_restored_cosine_schedule_warns(tmp_path: Path) -> None:
    import warnings

    from torchsde_lti.training.train import _warn_if_schedule_ends_early

    # what Lightning stores for CosineAnnealingLR(T_max=3): resuming restores T_max=3
    opt = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], lr=0.05)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=3, eta_min=0.002)
    ckpt = tmp_path / "last.ckpt"
    torch.save({"lr_schedulers": [sched.state_dict()]}, ckpt)
    for _ in range(6):  # past T_max the LR climbs back to its initial value
        opt.step()
        sched.step()
    assert opt.param_groups[0]["lr"] == pytest.approx(0.05)
    with pytest.warns(UserWarning, match="T_max=3.*max_epochs=6"):
        _warn_if_schedule_ends_early(str(ckpt), 6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _warn_if_schedule_ends_early(str(ckpt), 3)
        _warn_if_schedule_ends_early(None, 6)


def _run(args: list[str], cwd: Path, timeout: float = 240) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.run(
        [sys.executable, "-m", "torchsde_lti.train", *args], cwd=cwd, env=env,
        capture_output=True, text=True, timeout=timeout,
    )  # fmt: skip


def test_multirun_launches_two_runs(tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    proc = _run(
        ["--multirun", "data.noise=0.1,1.0", *TINY, "trainer.max_epochs=1", f"hydra.sweep.dir={sweep}"], tmp_path
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    runs = sorted(p for p in sweep.iterdir() if p.is_dir() and p.name.isdigit())
    assert [p.name for p in runs] == ["0", "1"]
    noises = sorted(json.loads((p / "metrics.json").read_text())["noise"] for p in runs)
    assert noises == [0.1, 1.0]
    collect = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "collect_sweep.py"), str(sweep)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert collect.returncode == 0, collect.stderr[-3000:]
    summary = (sweep / "summary.md").read_text()
    assert "data.noise=0.1" in summary and "data.noise=1.0" in summary


def test_restarts_multirun_keeps_the_best_validation_nll(tmp_path: Path) -> None:
    sweep = tmp_path / "restarts"
    small = ["data.num_tracks.train=8", "data.num_tracks.val=4", "data.T=8", "data.T_min=5", "data.batch_size=4"]
    proc = _run(
        [
            "--multirun",
            "experiment=restarts",
            "model=hurwitz",
            *small,
            "restart=range(2)",
            "trainer.max_epochs=1",
            "test=false",
            "plots=false",
            f"hydra.sweep.dir={sweep}",
        ],
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    best = json.loads((sweep / "best_run.json").read_text())
    values = [json.loads((sweep / str(i) / "metrics.json").read_text())["metrics"]["val/nll"] for i in range(2)]
    assert len(best["runs"]) == 2 and best["value"] == min(values)
    assert values[0] != values[1]  # the restarts really started apart
    assert any(str(o).startswith("restart=") for o in best["overrides"])


def test_ddp_two_cpu_processes_gloo(tmp_path: Path) -> None:
    run_dir = tmp_path / "ddp"
    proc = _run(["trainer=ddp", *TINY, "trainer.max_epochs=1", "test=false", f"hydra.run.dir={run_dir}"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run_dir / "metrics.json").read_text())
    assert math.isfinite(summary["metrics"]["val/nll"])
    log = proc.stdout + proc.stderr
    assert "distributed_backend=gloo" in log and "MEMBER: 2/2" in log


@pytest.mark.parametrize("error", ["runtime", "keyboard"])
def test_a_failed_run_reports_the_epochs_its_last_checkpoint_holds(tmp_path: Path, error: str) -> None:
    """An exception (or a KeyboardInterrupt raised by code, which Lightning turns into an exit)
    after one epoch: metrics.json says failed, 1 epoch, and results.md how to resume."""
    fail = ["+callbacks.fail._target_=tests.training.helpers.FailAt", "+callbacks.fail.epoch=1"]
    with pytest.raises((RuntimeError, SystemExit)):
        train(_cfg(tmp_path, *TINY, "trainer.max_epochs=3", "plots=false", *fail, f"+callbacks.fail.error={error}"))
    summary = json.loads((tmp_path / "metrics.json").read_text())
    assert summary["status"] == "failed" and summary["epochs"] == 1
    assert "ckpt_path=" in (tmp_path / "results.md").read_text()
    assert torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)["epoch"] == 0


def test_a_failing_plot_leaves_the_run_completed(tmp_path: Path, monkeypatch, caplog) -> None:
    """model=cv truth=singer once crashed in plots.py after 40 epochs and the run was marked
    FAILED with an empty table: a plot is a warning, never a failed run."""
    from tests.training import helpers

    train_module = sys.modules["torchsde_lti.training.train"]  # (the package re-exports train())
    monkeypatch.setattr(train_module, "plot_run", helpers.failing_plot)
    caplog.set_level("WARNING", logger="torchsde_lti.training")
    metrics, _ = train(_cfg(tmp_path, *TINY, "trainer.max_epochs=1", "plots=true"))
    summary = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["status"] == summary["status"] == "completed" and summary["table"]
    assert "the plots failed" in caplog.text and "shapes (4,) and (6,)" in caplog.text


def test_train_restores_the_thread_count_and_the_global_rng_states(tmp_path: Path) -> None:
    """num_threads applies during the run only, and seed_everything's global seeding does not
    outlive it (in-process train() left torch at one thread and the RNGs seeded)."""
    import random

    import numpy as np

    from tests.training.helpers import ThreadsSeen

    def draw() -> tuple:
        return torch.rand(3), random.random(), float(np.random.rand())

    def seed() -> None:
        torch.manual_seed(123), random.seed(123), np.random.seed(123)

    before, env = torch.get_num_threads(), os.environ.get("PL_GLOBAL_SEED")
    other = 3 if before == 2 else 2
    torch.set_num_threads(other)
    try:
        seed()
        expected = draw()
        seed()
        seen = ["+callbacks.seen._target_=tests.training.helpers.ThreadsSeen"]
        _, objects = train(_cfg(tmp_path, *TINY, "trainer.max_epochs=1", "num_threads=1", *seen))
        assert next(c for c in objects["callbacks"] if isinstance(c, ThreadsSeen)).seen == {1}
        assert torch.get_num_threads() == other
        got = draw()
        assert torch.equal(got[0], expected[0]) and got[1:] == expected[1:]
        assert os.environ.get("PL_GLOBAL_SEED") == env
    finally:
        torch.set_num_threads(before)


def test_last_checkpoint_holds_the_final_epoch_without_validation_every_epoch(tmp_path: Path) -> None:
    metrics, _ = train(_cfg(tmp_path, *TINY, "trainer.max_epochs=3", "trainer.check_val_every_n_epoch=2"))
    summary = json.loads((tmp_path / "metrics.json").read_text())
    assert summary["reported"]["epoch"] == 2
    assert torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)["epoch"] == 2
    # the validation metrics are the final weights' too (the last validation ran at epoch 1:
    # they were that epoch's), so the logged parameter error is the reported one
    assert summary["metrics"]["val/param_error/k"] == pytest.approx(summary["param_errors"]["k"], rel=1e-6)
    assert metrics["val/nll"] == summary["metrics"]["val/nll"]


def test_max_steps_without_max_epochs_needs_the_schedule_length(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="module.scheduler.T_max"):
        train(_cfg(tmp_path, *TINY, "trainer.max_epochs=null", "+trainer.max_steps=5"))


def test_resuming_a_copied_run_keeps_its_best_checkpoint(tmp_path: Path) -> None:
    """Lightning restores the best score only in the original directory: a copy of the run,
    resumed, must not overwrite best.ckpt with a worse epoch (a large step makes epoch 1 worse
    than epoch 0 here)."""
    import shutil

    common = [*TINY, "test=false", "plots=false", "module.scheduler.T_max=2", "module.optimizer.lr=0.3"]
    common += ["data.num_tracks.train=200", "data.T=40", "data.T_min=30", "data.batch_size=20"]
    train(_cfg(tmp_path / "a", *common, "trainer.max_epochs=1"))
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    first = json.loads((tmp_path / "a" / "metrics.json").read_text())["best"]
    assert first["epoch"] == 0
    metrics, _ = train(
        _cfg(tmp_path / "b", *common, "trainer.max_epochs=2", f"ckpt_path={tmp_path / 'b/checkpoints/last.ckpt'}")
    )
    assert metrics["val/nll"] > first["val/nll"]  # epoch 1 is worse: best.ckpt must stay epoch 0
    best = json.loads((tmp_path / "b" / "metrics.json").read_text())["best"]
    assert best["epoch"] == 0 and best["val/nll"] == pytest.approx(first["val/nll"], rel=1e-12)
    assert torch.load(tmp_path / "b" / "checkpoints" / "best.ckpt", weights_only=True)["epoch"] == 0


def test_collect_sweep_plots_a_sweep_without_truth(tmp_path: Path) -> None:
    """Real-data runs have no parameter errors: the summary plot shows val/nll (a log scale of
    NaN bars made matplotlib raise, so collect_sweep.py crashed on any sweep over real data)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("collect_sweep", ROOT / "experiments" / "collect_sweep.py")
    assert spec is not None and spec.loader is not None
    collect_sweep = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(collect_sweep)
    rows = [
        {"run": str(i), "overrides": f"model={m}", "param_errors": {}, "metrics": {"val/nll": v}}
        for i, (m, v) in enumerate((("cv", 6.04), ("singer", 6.16)))
    ]
    collect_sweep.plot(rows, tmp_path / "summary.png")
    assert (tmp_path / "summary.png").stat().st_size > 0


def test_resuming_a_moved_run_with_no_epoch_left_names_its_own_checkpoints(tmp_path: Path) -> None:
    """A finished run, moved, resumed with nothing left to train (e.g. interrupted while
    testing): the report names the moved directory's last.ckpt and best.ckpt with the best's
    val/nll (it named the vanished originals' paths, or none)."""
    import shutil

    common = [*TINY, "test=false", "plots=false", "trainer.max_epochs=1"]
    train(_cfg(tmp_path / "a", *common))
    first = json.loads((tmp_path / "a" / "metrics.json").read_text())["best"]
    shutil.move(tmp_path / "a", tmp_path / "b")
    train(_cfg(tmp_path / "b", *common, f"ckpt_path={tmp_path / 'b' / 'checkpoints' / 'last.ckpt'}"))
    summary = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert summary["reported"]["checkpoint"] == "checkpoints/last.ckpt"
    assert summary["best"]["checkpoint"] == "checkpoints/best.ckpt"
    assert summary["best"]["val/nll"] == pytest.approx(first["val/nll"])
