"""The LightningModule (torchsde_lti.training.module): loss pieces and robust optimizer steps."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from torchsde_lti import models
from torchsde_lti.data import TrackBatch, isotropic_covariance, simulate_tracks
from torchsde_lti.training.module import KalmanFilterModule


def test_one_step_ahead_loss_equals_prediction_error_decomposition() -> None:
    """k = 1: scoring y_{t+1} from the filtered state at t is the filter's own step likelihood."""
    import torchsde_lti as tl

    sde = models.integrated_ou(k=0.7, q=1.3, dim=2).to(torch.float64)
    H = models.position_observation(sde)
    tr = simulate_tracks(sde, H, isotropic_covariance(0.4, 2), 3, 12, p_missing=0.2, seed=2)
    kf = tl.KalmanFilter(sde, H, isotropic_covariance(0.4, 2), m0=torch.zeros(4), P0=torch.eye(4))
    module = KalmanFilterModule(kf, k_step=1, k_step_weight=1.0)
    out = kf(tr.y, tr.dt)
    observed = ~torch.isnan(tr.y)
    got = module.k_step_nll(out, tr.y, observed)
    ref = -out.step_log_likelihood[..., 1:].sum()
    assert torch.allclose(got, ref, rtol=1e-10)


def _nan_batch_module(skip: bool) -> tuple[KalmanFilterModule, list]:
    import torchsde_lti as tl

    sde = models.integrated_ou(k=0.7, q=1.3, dim=1).to(torch.float64)
    H = models.position_observation(sde)
    kf = tl.KalmanFilter(sde, H, isotropic_covariance(0.4, 1), m0=torch.zeros(2), P0=torch.eye(2))
    module = KalmanFilterModule(kf, optimizer=lambda params: torch.optim.Adam(params, lr=0.1), skip_nonfinite=skip)
    tr = simulate_tracks(sde, H, isotropic_covariance(0.4, 1), 4, 10, seed=1)
    bad_y = tr.y.clone()
    bad_y[0, 3, 0] = 1e200  # finite, but its squared residual overflows: loss and gradients non-finite
    good = TrackBatch(y=tr.y, dt=tr.dt, mask=tr.mask, lengths=tr.lengths)
    return module, [good, good._replace(y=bad_y), good]


def test_nonfinite_step_is_skipped_and_counted(tmp_path: Path) -> None:
    import lightning.pytorch as pl

    module, batches = _nan_batch_module(skip=True)
    before = {k: v.clone() for k, v in module.state_dict().items()}
    trainer = pl.Trainer(
        max_epochs=1,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=tmp_path,
    )
    with pytest.warns(RuntimeWarning, match="non-finite loss or gradient.*skipped"):
        trainer.fit(module, train_dataloaders=torch.utils.data.DataLoader(batches, batch_size=None))
    assert module.skipped_steps == 1
    after = module.state_dict()
    assert all(bool(torch.isfinite(v).all()) for v in after.values())
    assert any(not torch.equal(before[k], after[k]) for k in before)  # the good steps trained


def test_nonfinite_step_is_skipped_before_the_trainer_clips(tmp_path: Path) -> None:
    """The skip runs in ``on_before_optimizer_step``, before Lightning's ``gradient_clip_val``:
    a clipped non-finite gradient (NaN after clipping) never reaches the optimizer."""
    import lightning.pytorch as pl

    module, batches = _nan_batch_module(skip=True)
    trainer = pl.Trainer(
        max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
        enable_model_summary=False, default_root_dir=tmp_path, gradient_clip_val=1e-3,
    )  # fmt: skip
    with pytest.warns(RuntimeWarning, match="skipped"):
        trainer.fit(module, train_dataloaders=torch.utils.data.DataLoader(batches, batch_size=None))
    assert module.skipped_steps == 1
    assert all(bool(torch.isfinite(v).all()) for v in module.state_dict().values())


def test_k_step_loss_and_rmse_include_the_feedthrough() -> None:
    """A filter with D (y = H x + D u + v): the k-step prediction and the logged one-step RMSE
    are H m + D u (they left D u out: k = 1 gave 1163.2 where the filter's own one-step
    predictive NLL is 105.7)."""
    import math

    import torchsde_lti as tl

    torch.manual_seed(0)
    sde = tl.models.constant_velocity(dim=1, q=1.0, dtype=torch.float64)
    kf = tl.KalmanFilter(sde, tl.models.position_observation(sde), 0.25 * torch.eye(1, dtype=torch.float64),
                         D=torch.tensor([[2.0]], dtype=torch.float64))  # fmt: skip
    module = KalmanFilterModule(kf, k_step=1, k_step_weight=1.0)
    B, T = 3, 20
    dt = torch.rand(B, T, dtype=torch.float64) + 0.1
    u = torch.full((B, T, 1), 3.0, dtype=torch.float64)
    y = torch.randn(B, T, 1, dtype=torch.float64).cumsum(1) + 6.0
    y[1, 4] = float("nan")
    with torch.no_grad():
        out = kf(y, dt, u=u)
        k1 = module.k_step_nll(out, y, ~torch.isnan(y), 1, dt, u)
        torch.testing.assert_close(k1, -out.step_log_likelihood[:, 1:].sum(), rtol=1e-12, atol=1e-12)
        with pytest.raises(ValueError, match=r"u must have shape \(\.\.\., K, 1\) to match D \(1, 1\)"):
            kf.feedthrough(torch.ones(B, T, 2, dtype=torch.float64))
        batch = TrackBatch(y=y, dt=dt, mask=torch.ones(B, T, dtype=torch.bool), lengths=torch.full((B,), T), u=u)
        module._sums.clear()
        module._eval_step(batch, "val")
        sums = module._sums["val"]["rmse"]
    observed = ~torch.isnan(y)
    reference = math.sqrt(float((out.innovation[observed] ** 2).sum()) / int(observed.sum()))
    assert math.sqrt(float(sums[0] / sums[1])) == pytest.approx(reference, rel=1e-12)


def test_coverage_counts_reports_inside_the_chi_square_region_of_their_observed_coordinates() -> None:
    """val/cover2s: the share of reports after each window's first whose observed coordinates
    lie in the predictive's 86.5 % region, νᵀS⁻¹ν <= the chi-square quantile of the observed
    dimension (d² <= 4 for two coordinates; scipy's quantile for one), reports with one
    coordinate missing included, padding and wholly missing reports left out."""
    import math

    stats = pytest.importorskip("scipy.stats")
    import torchsde_lti as tl

    torch.manual_seed(1)
    sde = tl.models.constant_velocity(dim=2, q=0.5, dtype=torch.float64)
    kf = tl.KalmanFilter(sde, tl.models.position_observation(sde), 0.3 * torch.eye(2, dtype=torch.float64))
    module = KalmanFilterModule(kf)
    B, T = 4, 30
    dt = torch.rand(B, T, dtype=torch.float64) + 0.1
    y = 1.5 * torch.randn(B, T, 2, dtype=torch.float64).cumsum(1)
    y[0, 3, 1] = y[2, 7, 0] = y[3, 9, 0] = math.nan  # one coordinate missing
    y[1, 5] = math.nan  # a whole report missing
    mask = torch.ones(B, T, dtype=torch.bool)
    mask[3, 25:] = False  # padding
    batch = TrackBatch(y=y, dt=dt, mask=mask, lengths=mask.sum(-1))
    with torch.no_grad():
        module._sums.clear()
        module._eval_step(batch, "val")
        inside, scored = module._sums["val"]["cover2s"].tolist()
        out = kf(torch.where(mask.unsqueeze(-1), y, math.nan), torch.where(mask, dt, 0.0))
    expected_inside = expected_scored = 0
    for b in range(B):
        for t in range(1, T):
            seen = [i for i in range(2) if mask[b, t] and not math.isnan(float(y[b, t, i]))]
            if not seen:
                continue
            nu = out.innovation[b, t, seen]
            S = out.innovation_cov[b, t][seen][:, seen]
            d2 = float(nu @ torch.linalg.solve(S, nu))
            expected_scored += 1
            expected_inside += d2 <= stats.chi2.ppf(1 - math.exp(-2), len(seen))
    assert scored == expected_scored == B * (T - 1) - 1 - 5
    assert inside == expected_inside and 0 < inside < scored
