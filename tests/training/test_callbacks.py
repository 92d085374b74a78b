"""Callbacks (torchsde_lti.training.callbacks): BestRun's pick over a sweep."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from torchsde_lti.training.callbacks import BestRun


def _fake_sweep(root: Path, values: list[float | None]) -> None:
    for i, v in enumerate(values):
        run = root / str(i)
        (run / ".hydra").mkdir(parents=True)
        metrics = {} if v is None else {"val/nll": v}
        (run / "metrics.json").write_text(json.dumps({"metrics": metrics}))
        (run / ".hydra" / "overrides.yaml").write_text(f"- restart={i}\n")


def test_best_run_picks_the_lowest_and_writes_best_run_json(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    _fake_sweep(tmp_path, [0.7, 0.2, None, 0.5])
    BestRun("val/nll").on_multirun_end(OmegaConf.create({"hydra": {"sweep": {"dir": str(tmp_path)}}}))
    best = json.loads((tmp_path / "best_run.json").read_text())
    assert best["value"] == 0.2 and best["overrides"] == ["restart=1"] and best["best_dir"].endswith("/1")
    assert sorted(r["value"] for r in best["runs"]) == [0.2, 0.5, 0.7]  # the run without the metric is left out
    assert "0.2" in capsys.readouterr().out
    assert BestRun("val/nll", mode="max").best(tmp_path)["value"] == 0.7


def test_best_run_rejects_bad_mode_and_empty_sweeps(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="mode"):
        BestRun(mode="median")
    with pytest.raises(ValueError, match="finite val/nll"):
        BestRun().best(tmp_path)
