"""tl.pretrained: every shipped filter loads by name and reproduces its card's validation metrics on
its shipped slice (a library change that breaks one fails here); older cards and state dicts load."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

import torchsde_lti as tl
from torchsde_lti.data.splits import track_windows
from torchsde_lti.data.tracks import pad_tracks
from torchsde_lti.nn.parametrizations import floor_state_keys

FORMAT0 = Path(__file__).parent / "format0"


def test_names_list_the_shipped_files() -> None:
    names = tl.pretrained.names()
    assert {"ais-us-imm", "ais-ny-imm", "ais-us-cv"} <= set(names)
    assert names == sorted(names)
    with pytest.raises(ValueError, match="ais-us-imm"):  # the message lists the names
        tl.pretrained.load("no-such-model")


@pytest.mark.parametrize("name", tl.pretrained.names())
def test_every_shipped_filter_loads_and_reproduces_its_card(name: str) -> None:
    kf, card = tl.pretrained.load(name)
    assert isinstance(kf, (tl.KalmanFilter, tl.IMMFilter)) and not kf.training
    assert all(p.dtype == torch.float64 for p in kf.parameters())
    assert card.name == name and card.format == tl.pretrained.FORMAT and card.command.startswith("python -m")
    assert card.data["source"] and card.data["trained_on"] == "train" and card.library_version
    assert len(card.cov_scale) == (len(kf.modes()) if isinstance(kf, tl.IMMFilter) else 1)
    assert set(card.validation["metrics"]) == set(tl.pretrained.VALIDATION_METRICS)
    result = tl.pretrained.check(tl.pretrained.Pretrained(kf, card))
    bad = {k: v for k, v in result.items() if not v["ok"]}
    assert not bad, f"{name}: validation metrics moved away from the card: {bad}"
    for key, value in card.learned.items():  # what the card says was learned is what the weights hold
        assert value == pytest.approx(_learned(kf)[key], rel=1e-9), key


def _learned(kf: tl.KalmanFilter | tl.IMMFilter) -> dict[str, float]:
    from torchsde_lti.evaluation import filter_values, flat_values

    return flat_values(filter_values(kf))


def test_check_fails_when_the_filter_changes() -> None:
    """The check can fail: a filter whose noise moved does not reproduce its card."""
    kf, card = tl.pretrained.load("ais-us-cv")
    kf.sde.q = kf.sde.q * 1.01
    result = tl.pretrained.check(tl.pretrained.Pretrained(kf, card))
    assert not result["nll"]["ok"] and not result["fc_rmse_15"]["ok"]


def test_a_format0_card_and_its_old_state_dict_still_load(tmp_path: Path) -> None:
    """The study card of an older version: constant_velocity with the option k it no longer takes
    (`TypeError: unknown model options ['k']` before), a state dict without the parametrisations'
    floors; it loads, upgraded, and its filter holds the learned values its card lists."""
    raw = json.loads((FORMAT0 / "cv_train.json").read_text())
    assert raw["filter"]["sde"]["k"] == 0.01 and "format" not in raw
    old = torch.load(FORMAT0 / "cv_train.pt", weights_only=True)
    kf, card = tl.pretrained.load_card(FORMAT0 / "cv_train.json")
    assert not (floor_state_keys(kf) & set(old))  # written before the floors were saved
    assert "k" not in card.filter["sde"] and card.format == tl.pretrained.FORMAT and card.validation == {}
    assert kf.sde.q.item() == pytest.approx(raw["learned"]["q"], rel=1e-12)
    assert torch.diagonal(kf.R).tolist() == pytest.approx([raw["learned"]["R[0]"], raw["learned"]["R[1]"]], rel=1e-12)
    batch = pad_tracks(
        track_windows(tl.pretrained.validation_tracks(tl.pretrained.card("ais-us-cv")), 32, dtype=torch.float64)[:4]
    )
    assert torch.isfinite(kf(batch.y, batch.dt, mask=batch.mask).log_likelihood).all()
    with pytest.raises(ValueError, match="no validation record"):
        tl.pretrained.check(tl.pretrained.Pretrained(kf, card))


def test_bad_cards_raise_naming_the_file(tmp_path: Path) -> None:
    for name in ("cv_train.json", "cv_train.pt"):
        shutil.copy(FORMAT0 / name, tmp_path / name)
    card = json.loads((tmp_path / "cv_train.json").read_text())
    (tmp_path / "future.json").write_text(json.dumps({**card, "format": 99}))
    with pytest.raises(ValueError, match=r"future\.json.*format 99"):
        tl.pretrained.read_card(tmp_path / "future.json")
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"broken\.json"):
        tl.pretrained.read_card(tmp_path / "broken.json")
    (tmp_path / "nofilter.json").write_text(json.dumps({k: v for k, v in card.items() if k != "filter"}))
    with pytest.raises(ValueError, match=r"nofilter\.json.*'filter'"):
        tl.pretrained.read_card(tmp_path / "nofilter.json")
    torch.save({"wrong": torch.zeros(1)}, tmp_path / "cv_train.pt")
    with pytest.raises(ValueError, match=r"cv_train\.pt"):
        tl.pretrained.load_card(tmp_path / "cv_train.json")


def test_shipped_files_are_package_data() -> None:
    """setup.py ships every file of the pretrained folder in a wheel (json, pt, npz)."""
    setup = (Path(tl.__file__).resolve().parents[1] / "setup.py").read_text()
    suffixes = {p.suffix for p in tl.pretrained.FILES.iterdir()}
    assert suffixes <= {".json", ".pt", ".npz"}
    for suffix in suffixes:
        assert f'"files/*{suffix}"' in setup
