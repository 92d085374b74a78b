"""The figures and results.md of a run (training.plots, training.report): which figures a run
draws for which model, the learner/truth pairing that crashed the plot step, the units and the
columns of results.md."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from torchsde_lti.evaluation.figures import _ellipse, _moving_tracks
from torchsde_lti.training import train
from torchsde_lti.training.report import format_table, markdown_table, score_rows

CONF = Path(__file__).resolve().parents[2] / "conf"


def _train(tmp_path: Path, *overrides: str) -> dict:
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=[f"output_dir={tmp_path}", "experiment=tiny", "plots=true", *overrides])
    metrics, _ = train(cfg)
    return metrics


def _figures(run: Path) -> set[str]:
    return {p.name for p in run.glob("*.png")}


def test_a_cv_learner_on_singer_data_draws_its_figures(tmp_path: Path) -> None:
    """The learner's 4-state H met the truth's 6 states in plots.py (a crash after training)."""
    metrics = _train(tmp_path, "model=cv", "truth=singer", "test=false")
    assert metrics["status"] == "completed"
    assert _figures(tmp_path) == {"loss.png", "params.png", "map.png", "forecast.png"}
    text = (tmp_path / "results.md").read_text()
    assert "![tracks on a map" in text and "(map.png)" in text and "(forecast.png)" in text


def test_an_imm_run_draws_its_mode_probabilities(tmp_path: Path) -> None:
    _train(tmp_path, "model=imm", "filter=imm", "truth=cv", "test=false")
    assert {"map.png", "modes.png", "forecast.png"} <= _figures(tmp_path)


def test_one_dimensional_observations_are_drawn_against_time(tmp_path: Path) -> None:
    """msd observes one position and has inputs: a time plot, no map, no forecast figure."""
    _train(tmp_path, "model=msd", "test=false")
    figures = _figures(tmp_path)
    assert "track.png" in figures and "map.png" not in figures and "forecast.png" not in figures


def test_the_map_shows_the_tracks_that_move_not_the_moored_ones() -> None:
    y = torch.zeros(5, 6, 2)
    y[1] = torch.linspace(0, 50, 6).unsqueeze(-1)  # under way
    y[3, :, 0] = torch.linspace(0, 500, 6)  # further
    y[4, :, 1] = torch.tensor([0.0, 1, math.nan, 2, 1, 0])  # moored, with a missing report
    mask = torch.ones(5, 6, dtype=torch.bool)
    mask[3, 4:] = False  # padding does not count
    y[3, 4:] = math.nan
    assert _moving_tracks(y, mask, 3) == [3, 1, 4]


def test_the_ellipse_is_the_2_sigma_contour() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    c, s = math.cos(0.3), math.sin(0.3)
    Rot = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    cov = Rot @ torch.diag(torch.tensor([9.0, 1.0], dtype=torch.float64)) @ Rot.T
    _ellipse(ax, torch.tensor([1.0, 2.0]), cov, "C0")
    e = ax.patches[0]
    assert e.width == pytest.approx(12.0) and e.height == pytest.approx(4.0)
    assert math.radians(e.angle) % math.pi == pytest.approx(0.3)
    plt.close(fig)


def test_results_md_scores_have_units_and_only_the_columns_that_apply() -> None:
    metrics = {"val/nll": 1.25, "val/rmse": 3.0, "test/nll": 1.5, "test/rmse": 3.5, "train/nll": 9.0}
    text = score_rows(metrics, "m")
    assert text.splitlines()[0] == "| split | NLL (nats per observed scalar) | one-step RMSE (m) |"
    assert "| validation | 1.25 | 3 |" in text and "| test | 1.5 | 3.5 |" in text
    assert score_rows({"train/nll": 1.0}, "m") == ""
    with_coverage = score_rows({**metrics, "val/cover2s": 0.86}, "m")
    assert "2σ coverage (share)" in with_coverage and "| test | 1.5 | 3.5 |  |" in with_coverage


def test_results_md_table_of_real_data_has_no_true_column() -> None:
    learned = [{"name": "q", "true": math.nan, "learned": 0.5, "rel_error": math.nan}]
    assert format_table(learned).splitlines()[0] == "| parameter | learned |"
    recovered = [{"name": "q", "true": 1.0, "learned": 1.1, "rel_error": 0.1}]
    assert format_table(recovered).splitlines()[2] == "| q | 1 | 1.1 | 10.00 % |"
    assert markdown_table(["a", "b"], [["x", ""]]) == "| a |\n|---|\n| x |"
