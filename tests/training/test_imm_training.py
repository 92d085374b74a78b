"""Training an IMMFilter through the Lightning module and the Hydra configs (filter=imm, model=imm).

What is learned is read through ``kf.modes()`` for both filters (evaluation.filter_values):
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
from torchsde_lti.evaluation import (
    filter_values,
    flat_values,
    identifiability_note,
    imm_k_step_nll,
    learned_values,
    parameter_table,
)
from torchsde_lti.training import KalmanFilterModule, train
from torchsde_lti.training.plots import epoch_rows

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
    return tl.IMMFilter(
        [moored, underway],
        H,
        R,
        rates,
        mode_prob0=torch.tensor([0.8, 0.2], dtype=torch.float64),
        learn=("R", "rates", "mode_prob0"),
        mode_names=("moored", "underway"),
    )


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


def test_filter_values_report_a_learned_student_t_nu_shared_or_per_mode() -> None:
    """A learned ν is what the filter learned too: ``dof`` (one ν), ``<mode>/dof`` (a ν per mode),
    logged per epoch (param/…) and in the parameter table; a fixed ν is not."""
    imm = _imm()
    t_kf = tl.KalmanFilter(imm.models[1], imm.H, imm.R[1].detach(), noise=tl.StudentT(5.0))
    assert float(filter_values(t_kf)["dof"]) == pytest.approx(5.0, rel=1e-12)
    fixed = tl.KalmanFilter(imm.models[1], imm.H, imm.R[1].detach(), noise=tl.StudentT(5.0, learn=False))
    assert "dof" not in filter_values(fixed)
    modes = tl.IMMFilter(
        list(imm.models),
        imm.H,
        imm.R.detach(),
        imm.rates.detach(),
        mode_names=imm.mode_names,
        noise=tl.StudentT([3.0, 7.0]),
    )
    flat = flat_values(filter_values(modes))
    assert flat["moored/dof"] == pytest.approx(3.0, rel=1e-12) and flat["underway/dof"] == pytest.approx(7.0, rel=1e-12)
    rows = {r["name"]: r for r in parameter_table(modes, None)}
    assert rows["underway/dof"]["learned"] == pytest.approx(7.0, rel=1e-12) and math.isnan(rows["underway/dof"]["true"])


def test_parameter_table_of_an_imm_module_without_truth() -> None:
    module = KalmanFilterModule(_imm())
    rows = {r["name"]: r for r in parameter_table(module.kf, None)}
    assert rows["moored/k"]["learned"] == pytest.approx(0.5) and math.isnan(rows["moored/k"]["true"])
    assert rows["underway/R[1,1]"]["learned"] == pytest.approx(2.0)
    assert rows["rate[underway->moored]"]["learned"] == pytest.approx(0.03, rel=1e-12)
    assert module.parameter_errors() == {} and identifiability_note(module.kf) == ""


def _imm_batch(B: int = 3, T: int = 25) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    dt = torch.rand(B, T, generator=g, dtype=torch.float64) * 5 + 0.5
    y = torch.cumsum(torch.randn(B, T, 2, generator=g, dtype=torch.float64), dim=1)
    return y, dt


def test_imm_k_step_loss_at_k_1_is_the_filters_step_likelihood_without_switching() -> None:
    """k = 1: the forecast over one gap. Without switches within it (the rates fixed at 0) that is
    the filter's own prediction, so the loss is its step likelihood; with switching the forecast
    adds the switches within the gap (exact moments) and moves away from it, a little."""
    imm = _imm()
    y, dt = _imm_batch()
    still = tl.IMMFilter(
        list(imm.models), imm.H, imm.R, torch.zeros(2, 2, dtype=torch.float64), mode_prob0=imm.mode_prob0, learn=()
    )
    for f, tol in ((still, 1e-10), (imm, None)):
        module = KalmanFilterModule(f, k_step=1, k_step_weight=1.0)
        out = f(y, dt)
        got = module.k_step_nll(out, y, ~torch.isnan(y), 1, dt)
        want = -out.step_log_likelihood[:, 1:].sum()
        if tol is not None:
            torch.testing.assert_close(got, want, rtol=tol, atol=tol)
        else:
            assert 0 < abs(float(got - want)) < 1e-3 * abs(float(want))


def test_imm_k_step_loss_is_the_forecast_mixture_at_the_lead() -> None:
    imm = _imm()
    y, dt = _imm_batch(B=2, T=12)
    out = imm(y, dt)
    k = 4
    got = imm_k_step_nll(imm, out, y, dt, torch.ones_like(y, dtype=torch.bool), k)
    total = 0.0
    for bb in range(2):  # by hand: one forecast per origin, a mixture density per target
        for tt in range(12 - k):
            lead = dt[bb, tt + 1 : tt + k + 1].sum()
            with torch.no_grad():
                fc = imm.forecast(
                    (out.mode_probabilities[bb, tt], out.mode_mean[bb, tt], out.mode_cov[bb, tt]), lead.reshape(1)
                )
            dens = sum(
                float(fc.mode_probabilities[0, j])
                * math.exp(
                    float(
                        torch.distributions.MultivariateNormal(fc.mode_obs_mean[0, j], fc.mode_obs_cov[0, j]).log_prob(
                            y[bb, tt + k]
                        )
                    )
                )
                for j in range(2)
            )
            total -= math.log(dens)
    assert float(got) == pytest.approx(total, rel=1e-9)
    # padding (unobserved targets) does not count; gradients reach the rates and the models
    obs = torch.ones_like(y, dtype=torch.bool)
    obs[0, -3:] = False
    part = imm_k_step_nll(imm, out, y, dt, obs, k)
    assert float(part) < float(got)
    part.backward()
    assert imm.parametrizations.rates.original.grad is not None


def test_imm_k_step_loss_trains_through_the_module() -> None:
    imm = _imm()
    y, dt = _imm_batch()
    module = KalmanFilterModule(imm, k_step=[2, 5], k_step_weight=0.5)
    assert module.k_steps == [2, 5] and module.hparams.k_step == [2, 5]
    batch = tl.data.pad_tracks([tl.data.Track(y=y[i], dt=dt[i]) for i in range(3)])
    loss, nll, out, info = module._step(batch)
    extra = sum(module.k_step_nll(out, info["y"], info["observed"], k, dt) for k in (2, 5))
    torch.testing.assert_close(loss, nll + 0.5 * extra / info["count"])
    with pytest.raises(ValueError, match="k_step"):
        KalmanFilterModule(_imm(), k_step=[-1], k_step_weight=1.0)


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
    hist = epoch_rows(tmp_path / "csv" / "metrics.csv")
    assert len(hist) == 2 and "param/underway/k" in hist[-1] and "param/rate[underway->moored]" in hist[-1]


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


@pytest.mark.parametrize("batch", [2, 3])  # equal to M (ran, with track b through mode b's H) and not (raised)
def test_eval_rmse_of_an_imm_with_per_mode_H_scores_the_mixture_prediction(batch: int) -> None:
    """val/rmse's one-step prediction of an IMM with H per mode (M, m, n) is the mixture's
    Σ_j c_j H_j m⁻_j (written out here from the filter's per-mode outputs)."""
    from torchsde_lti.data.tracks import TrackBatch

    modes = [
        models.constant_velocity(dim=2, dtype=torch.float64),
        models.integrated_ou(0.5, 1.0, dim=2, dtype=torch.float64),
    ]
    H0 = models.position_observation(modes[0])
    H = torch.stack([H0, 2.0 * H0])
    imm = tl.IMMFilter(modes, H, torch.eye(2, dtype=torch.float64), torch.ones(2, 2, dtype=torch.float64))
    module = KalmanFilterModule(imm)
    g = torch.Generator().manual_seed(batch)
    y = torch.randn(batch, 5, 2, generator=g, dtype=torch.float64)
    dt = torch.rand(batch, 5, generator=g, dtype=torch.float64)
    module._eval_step(
        TrackBatch(y=y, dt=dt, mask=torch.ones(batch, 5, dtype=torch.bool), lengths=torch.full((batch,), 5)), "val"
    )
    out = imm(y, dt)
    per_mode = torch.stack([out.mode_pred_mean[..., j, :] @ H[j].mT for j in range(2)], -2)  # (B, T, M, m)
    pred = (out.pred_mode_probabilities.unsqueeze(-1) * per_mode).sum(-2)
    assert module._sums["val"]["rmse"][0].item() == pytest.approx(((pred - y) ** 2).sum().item(), rel=1e-12)
