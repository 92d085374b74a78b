"""Training an IMMFilter through the Lightning module and the Hydra configs (filter=imm, model=imm).

What is learned is read through ``kf.modes()`` for both filters (training.metrics.filter_values):
checked against the modules' own attributes; the Hydra run uses simulated tracks (no download);
resume from a checkpoint continues exactly like an uninterrupted run.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

import torchsde_lti as tl
from torchsde_lti import models
from torchsde_lti.training import KalmanFilterModule, train
from torchsde_lti.training.metrics import filter_values, flat_values, learned_values, parameter_table

CONF = Path(__file__).resolve().parents[2] / "conf"
# an IMM learner (moored + underway) on the tiny simulated data of experiment=tiny (truth: cv)
IMM_TINY = ["experiment=tiny", "model=imm", "filter=imm", "truth=cv", "test=false"]


def _cfg(tmp_path: Path, *overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("train", overrides=[f"output_dir={tmp_path}", *overrides])


def _imm() -> tl.IMMFilter:
    moored = models.moored(k=0.5, q=0.1, dim=2, dtype=torch.float64)
    underway = models.integrated_ou(k=0.05, q=0.3, dim=2, dtype=torch.float64)
    H = models.position_observation(underway)
    R = torch.stack([0.1 * torch.eye(2), 2.0 * torch.eye(2)]).double()
    rates = torch.tensor([[0.0, 0.01], [0.03, 0.0]], dtype=torch.float64)
    return tl.IMMFilter([moored, underway], H, R, rates, mode_prob0=torch.tensor([0.8, 0.2], dtype=torch.float64),
                        learn=("R", "rates", "mode_prob0"), mode_names=("moored", "underway"))


def test_modes_of_both_filters() -> None:
    imm = _imm()
    modes = imm.modes()
    assert [m.name for m in modes] == ["moored", "underway"]
    assert modes[0].sde is imm.models[0] and torch.equal(modes[1].R, imm.R[1]) and torch.equal(modes[0].H, imm.H)
    kf = tl.KalmanFilter(imm.models[1], imm.H, imm.R[1].detach())
    (mode,) = kf.modes()
    assert mode.name == "" and mode.sde is kf.sde and torch.equal(mode.R, kf.R)
    with pytest.raises(ValueError, match="mode_names"):
        tl.IMMFilter(list(imm.models), imm.H, imm.R.detach(), imm.rates.detach(), mode_names=("a", "a"))


def test_filter_values_of_an_imm_are_every_mode_and_the_chain() -> None:
    imm = _imm()
    v = filter_values(imm)
    assert float(v["moored/k"]) == pytest.approx(0.5) and float(v["underway/q"]) == pytest.approx(0.3)
    assert torch.equal(v["underway/R"], imm.R[1].detach()) and v["moored/F"].shape == (4, 4)
    assert float(v["rate[moored->underway]"]) == pytest.approx(0.01, rel=1e-12)
    assert float(v["rate[underway->moored]"]) == pytest.approx(0.03, rel=1e-12)
    assert float(v["mode_prob0[moored]"]) == pytest.approx(0.8, rel=1e-12)
    flat = flat_values(v)
    assert flat["underway/R[1]"] == pytest.approx(2.0) and "moored/Qc[0]" not in flat  # Qc follows from q
    # a single-model filter: exactly learned_values of its model
    kf = tl.KalmanFilter(imm.models[1], imm.H, imm.R[1].detach())
    a, b = filter_values(kf), learned_values(kf.sde, kf.R)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_parameter_table_of_an_imm_module_without_truth() -> None:
    module = KalmanFilterModule(_imm())
    rows = {r["name"]: r for r in parameter_table(module, None)}
    assert rows["moored/k"]["learned"] == pytest.approx(0.5) and math.isnan(rows["moored/k"]["true"])
    assert rows["underway/R[1,1]"]["learned"] == pytest.approx(2.0)
    assert rows["rate[underway->moored]"]["learned"] == pytest.approx(0.03, rel=1e-12)
    assert module.parameter_errors() == {} and module.identifiability_note() == ""


def test_k_step_loss_needs_a_kalman_filter() -> None:
    with pytest.raises(ValueError, match="k-step.*KalmanFilter.*IMMFilter"):
        KalmanFilterModule(_imm(), k_step=3, k_step_weight=1.0)
    KalmanFilterModule(_imm(), k_step=3, k_step_weight=0.0)  # off: fine


def test_imm_hydra_run_learns_and_reports(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path, *IMM_TINY, "trainer.max_epochs=2")
    metrics, objects = train(cfg)
    kf = objects["module"].kf
    assert isinstance(kf, tl.IMMFilter) and kf.mode_names == ("moored", "underway")
    assert math.isfinite(metrics["val/nll"]) and math.isfinite(metrics["train/nll"])
    assert float(kf.rates[0, 1].detach()) != pytest.approx(5.5556e-4, rel=1e-3)  # the switching rate was learned
    names = {r["name"] for r in json.loads((tmp_path / "metrics.json").read_text())["table"]}
    assert {"moored/k", "underway/q", "moored/R[0,0]", "rate[moored->underway]", "mode_prob0[underway]"} <= names
    assert "rate[moored->underway]" in (tmp_path / "results.md").read_text()
    hist = next(c for c in objects["callbacks"] if type(c).__name__ == "ParameterHistory").history
    assert len(hist) == 2 and "underway/k" in hist[-1] and "rate[underway->moored]" in hist[-1]


def test_imm_checkpoint_resume_continues_identically(tmp_path: Path) -> None:
    common = [*IMM_TINY, "module.scheduler.T_max=3"]
    _, full = train(_cfg(tmp_path / "full", *common, "trainer.max_epochs=3"))
    _, part = train(_cfg(tmp_path / "part", *common, "trainer.max_epochs=1"))
    ckpt = tmp_path / "part" / "checkpoints" / "last.ckpt"
    raw = torch.load(ckpt, weights_only=True)
    assert "kf.parametrizations.rates.original" in raw["state_dict"]
    _, resumed = train(_cfg(tmp_path / "resumed", *common, "trainer.max_epochs=3", f"ckpt_path={ckpt}"))
    a, b = full["module"].state_dict(), resumed["module"].state_dict()
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    key = "kf.parametrizations.rates.original"
    assert not torch.equal(a[key], part["module"].state_dict()[key])  # training moved the rates
