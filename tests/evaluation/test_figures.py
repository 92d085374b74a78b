"""evaluation.figures: which figures a filter on a batch of tracks gets, and that they are files."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import torchsde_lti as tl
from torchsde_lti.evaluation import track_figures

F64 = torch.float64


def _kf(dim: int) -> tl.KalmanFilter:
    sde = tl.models.constant_velocity(dim=dim, q=0.5, dtype=F64)
    return tl.KalmanFilter(sde, tl.models.position_observation(sde), 0.25 * torch.eye(dim, dtype=F64))


def _tracks(dim: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    y = torch.cumsum(torch.randn(5, 30, dim, generator=g, dtype=F64), 1)
    dt = torch.rand(5, 30, generator=g, dtype=F64) + 0.5
    mask = torch.arange(30) < torch.tensor([30, 25, 30, 12, 30])[:, None]  # padded tracks
    return y, dt, mask


def test_two_dimensional_tracks_get_a_map_and_a_forecast_figure(tmp_path: Path) -> None:
    paths = track_figures(tmp_path, _kf(2), *_tracks(2))
    assert [p.name for p in paths] == ["map.png", "forecast.png"]
    assert all(p.stat().st_size > 1000 for p in paths)


def test_one_dimensional_tracks_are_drawn_against_time(tmp_path: Path) -> None:
    paths = track_figures(tmp_path, _kf(1), *_tracks(1))
    assert paths[0].name == "track.png" and paths[0].is_file()


def test_an_imm_adds_its_mode_probabilities(tmp_path: Path) -> None:
    modes = [tl.models.constant_velocity(dim=2, q=0.5, dtype=F64), tl.models.integrated_ou(1.0, 0.01, dim=2, dtype=F64)]
    rates = torch.tensor([[0.0, 0.1], [0.1, 0.0]], dtype=F64)
    imm = tl.IMMFilter(modes, tl.models.position_observation(modes[0]), 0.25 * torch.eye(2, dtype=F64), rates)
    assert [p.name for p in track_figures(tmp_path, imm, *_tracks(2))] == ["map.png", "modes.png", "forecast.png"]


def test_a_filter_it_cannot_draw_is_a_type_error(tmp_path: Path) -> None:
    with pytest.raises(TypeError, match="track_figures draws"):
        track_figures(tmp_path, torch.nn.Linear(2, 2), *_tracks(2))  # type: ignore[arg-type]
