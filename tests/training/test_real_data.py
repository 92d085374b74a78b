"""The real-data experiments (ships and aircraft) through the one training path, on small slices
of the shipped files, and the optional launchers: submitit (local executor) and Optuna.

Full runs are experiments (README, experiments/results/bench_tracks_scale.md); these check that every
experiment composes, loads, trains a step and saves what its data summary says.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from tests.training.test_train import CONF, _cfg, _run

pytest.importorskip("tracktable_data", reason="the trajectory files come with the data extra")
pytest.importorskip("pyarrow")

from torchsde_lti.data import locate_file  # noqa: E402
from torchsde_lti.training import train  # noqa: E402


def _slice(name: str, tmp_path: Path, first: int = 40, also: str | None = None, extra: int = 15) -> Path:
    """The first ``first`` trajectory lines of a shipped .traj file (plus ``extra`` lines containing ``also``)."""
    lines = locate_file(name).read_text().splitlines(keepends=True)
    picked = lines[:first] + ([ln for ln in lines[first:] if also in ln[:400]][:extra] if also else [])
    out = tmp_path / name
    out.write_text("".join(picked))
    return out


@pytest.mark.parametrize(
    ("experiment", "source", "also"),
    [
        ("ais_us_coastal", "US_coastal_2020_06_30.traj", None),
        ("ais_ny_week", "NYHarbor_2020_12_first_week.traj", "2020-12-07"),
        ("flights", "prediction_historical_trajectories.traj", None),
        ("flights", "SampleTrajectories.traj", None),
        ("flights_3d", None, None),
    ],
)
def test_real_data_experiment_trains_a_step(
    tmp_path: Path, experiment: str, source: str | None, also: str | None
) -> None:
    overrides = [f"experiment={experiment}", "+trainer.fast_dev_run=true", "plots=false", "data.batch_size=16"]
    if source is not None:
        overrides.append(f"data.source={_slice(source, tmp_path, also=also)}")
    metrics, objects = train(_cfg(tmp_path, *overrides))
    assert math.isfinite(metrics["train/nll"]) and math.isfinite(metrics["val/nll"])
    dm = objects["datamodule"]
    summary = json.loads((tmp_path / "metrics.json").read_text())["data_summary"]
    assert summary["load"]["reports"] == dm.tracks.num_reports > 0
    assert summary["splits"]["train"]["windows"] == len(dm.windows["train"])
    assert "## Data" in (tmp_path / "results.md").read_text()
    kf = objects["module"].kf
    dims = 3 if experiment == "flights_3d" else 2
    assert dm.tracks.dims == dims and kf.H.shape[-2] == dims
    if experiment == "ais_ny_week":  # a split in time: training before 7 Dec, validation after
        train_t, val_t = dm.splits["train"].t, dm.splits["val"].t
        assert train_t.max() < val_t.min()
        assert "val" in summary["splits"] and "test" not in summary["splits"]
    else:  # vessel / flight disjoint
        ids = [set(dm.splits[s].object_id.tolist()) for s in ("train", "val", "test")]
        assert not (ids[0] & ids[1] or ids[0] & ids[2] or ids[1] & ids[2])


def test_test_true_without_a_test_split_fails_before_training(tmp_path: Path) -> None:
    # the NY week's split in time has train and val only: test=true used to train, then raise
    source = _slice("NYHarbor_2020_12_first_week.traj", tmp_path, also="2020-12-07")
    overrides = ["experiment=ais_ny_week", f"data.source={source}", "test=true", "plots=false", "trainer.max_epochs=1"]
    with pytest.raises(ValueError, match="test=true, but the data have no test split.*set test=false"):
        train(_cfg(tmp_path, *overrides))
    assert not (tmp_path / "checkpoints").exists()


def test_slurm_launcher_config_composes() -> None:
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(
            "train", overrides=["hydra/launcher=slurm", "trainer=ddp", "trainer.num_nodes=2"], return_hydra_config=True
        )
    assert cfg.hydra.launcher._target_.endswith("SlurmLauncher") and cfg.hydra.launcher.nodes == 1
    assert cfg.trainer.num_nodes == 2 and cfg.trainer.strategy.process_group_backend == "gloo"


def test_submitit_local_sweep_runs_each_job(tmp_path: Path) -> None:
    """hydra/launcher=local_jobs: submitit's local executor, one process per run (Slurm's path, here)."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    sweep = tmp_path / "sweep"
    proc = _run(
        [
            "-m",
            "hydra/launcher=local_jobs",
            "experiment=tiny",
            "model=cv,integrated_ou",
            "trainer.max_epochs=1",
            "test=false",
            f"hydra.sweep.dir={sweep}",
        ],
        tmp_path,
        timeout=400,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Submitit 'local' sweep" in proc.stdout + proc.stderr
    models = {json.loads((sweep / k / "metrics.json").read_text())["model"] for k in ("0", "1")}
    assert models == {"cv", "integrated_ou"} and any((sweep / ".submitit").iterdir())


def test_optuna_search_runs_trials(tmp_path: Path) -> None:
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    sweep = tmp_path / "search"
    proc = _run(
        [
            "-m",
            "experiment=search",
            "hydra.sweeper.n_trials=3",
            "hydra.sweeper.sampler.n_startup_trials=2",
            "data.num_tracks.train=8",
            "data.num_tracks.val=4",
            "data.num_tracks.test=4",
            "data.T=8",
            "data.T_min=5",
            "data.batch_size=4",
            "trainer.max_epochs=1",
            "trainer.enable_progress_bar=false",
            f"hydra.sweep.dir={sweep}",
        ],
        tmp_path,
        timeout=400,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    best = (sweep / "optimization_results.yaml").read_text()
    assert "best_params" in best and "module.optimizer.lr" in best and "model" in best
    runs = [json.loads((sweep / k / "metrics.json").read_text()) for k in ("0", "1", "2")]
    assert all(math.isfinite(r["metrics"]["val/nll"]) for r in runs)


def test_imm_mode_count_search_space_instantiates(tmp_path: Path) -> None:
    """experiment=search_imm searches model=imm (2 modes) vs imm3 (3 modes): both build."""
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    for model, modes in (("imm", 2), ("imm3", 3)):
        cfg = _cfg(tmp_path, "experiment=search_imm", f"model={model}")
        kf = instantiate(cfg.filter)
        assert len(kf.modes()) == modes and kf.R.shape == (modes, 2, 2)
