"""evaluation.calibration: HPD levels (closed form vs Monte Carlo, uniform under the model), the
scalar covariance inflation (recovers a known scale), and evaluate_filter's calibrated predictive
(= the filter with Q, R and the prior all scaled, for a Kalman filter)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from tests.evaluation.test_scores import simulated_cv
from torchsde_lti.evaluation.baseline import cv_filter
from torchsde_lti.evaluation.calibration import (
    NOMINAL_2SIGMA,
    calibrate_filter,
    fit_cov_scale,
    fit_mode_scales,
    hpd_level,
)
from torchsde_lti.evaluation.predictive import one_step_predictive
from torchsde_lti.evaluation.scores import evaluate_filter, summary

f64 = torch.float64


def random_mixture(N: int, M: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(N, M, generator=g, dtype=f64) + 0.1
    w = w / w.sum(-1, keepdim=True)
    mu = 3.0 * torch.randn(N, M, 2, generator=g, dtype=f64)
    A = torch.randn(N, M, 2, 2, generator=g, dtype=f64)
    S = A @ A.mT + 0.3 * torch.eye(2, dtype=f64)
    return w, mu, S


def draw(w: torch.Tensor, mu: torch.Tensor, S: torch.Tensor, scale: float, seed: int) -> torch.Tensor:
    """One draw per row from Σ_j w_j N(mu_j, scale S_j)."""
    g = torch.Generator().manual_seed(seed)
    j = torch.multinomial(w, 1, generator=g)[:, 0]
    rows = torch.arange(len(j))
    L = torch.linalg.cholesky(scale * S[rows, j])
    return mu[rows, j] + (L @ torch.randn(len(j), 2, 1, generator=g, dtype=f64)).squeeze(-1)


def test_gaussian_level_is_the_chi2_cdf_and_matches_monte_carlo_of_a_split_component() -> None:
    w, mu, S = random_mixture(400, 1, 0)
    y = draw(w, mu, S, 1.0, 1)
    d = (y - mu[:, 0]).unsqueeze(-1)
    maha = (d.mT @ torch.linalg.solve(S[:, 0], d)).reshape(-1)
    closed = hpd_level(y, w, mu, S)
    assert torch.allclose(closed, 1.0 - torch.exp(-0.5 * maha), atol=1e-12)  # chi²_2 CDF
    # the same Gaussian written as two equal components: the Monte Carlo path
    two = hpd_level(y, torch.cat([w, w], -1) / 2, torch.cat([mu, mu], 1), torch.cat([S, S], 1), samples=4000, seed=2)
    assert (two - closed).abs().max() < 0.04  # 4000 draws: standard error <= 0.008
    # scale: d² / c
    assert torch.allclose(hpd_level(y, w, mu, S, 2.0), 1.0 - torch.exp(-0.25 * maha), atol=1e-12)


def test_levels_are_uniform_when_the_data_come_from_the_predictive() -> None:
    w, mu, S = random_mixture(3000, 3, 3)
    y = draw(w, mu, S, 1.0, 4)
    lev = hpd_level(y, w, mu, S, samples=400, seed=5).numpy()
    for a in (0.25, 0.5, NOMINAL_2SIGMA, 0.95):
        assert abs(np.mean(lev <= a) - a) < 0.03  # 3000 reports: se <= 0.009
    # a too-wide predictive over-covers, a too-narrow one under-covers
    assert np.mean(hpd_level(y, w, mu, S, 2.0, samples=400).numpy() <= NOMINAL_2SIGMA) > NOMINAL_2SIGMA + 0.04
    assert np.mean(hpd_level(y, w, mu, S, 0.5, samples=400).numpy() <= NOMINAL_2SIGMA) < NOMINAL_2SIGMA - 0.04


@pytest.mark.parametrize("M, true_scale", [(1, 2.5), (1, 0.4), (3, 0.6), (2, 1.8)])
def test_fit_cov_scale_recovers_the_scale_of_the_data(M: int, true_scale: float) -> None:
    w, mu, S = random_mixture(4000, M, 10 + M)
    y = draw(w, mu, S, true_scale, 11)
    c = fit_cov_scale(y, w, mu, S, samples=300, seed=1)
    assert c == pytest.approx(true_scale, rel=0.08)
    cover = np.mean(hpd_level(y, w, mu, S, c, samples=300, seed=1).numpy() <= NOMINAL_2SIGMA)
    assert cover == pytest.approx(NOMINAL_2SIGMA, abs=0.002)  # the fit matches the coverage it targets


def test_fit_mode_scales_recovers_one_scale_per_predicted_mode() -> None:
    """Two well-separated modes, each report predicted in one of them (weight 0.999: the mixture's
    86.5 % region is that mode's ellipse), the data of mode 0 drawn with covariance 0.5 S_0 and of
    mode 1 with 2 S_1: the fit finds [0.5, 2]."""
    N = 2000
    w, mu, S = random_mixture(N, 2, 21)
    first = torch.arange(N) % 2 == 0
    w = torch.where(first[:, None], torch.tensor([0.999, 0.001], dtype=f64), torch.tensor([0.001, 0.999], dtype=f64))
    mu[:, 1] = mu[:, 0] + 200.0  # far apart: each report's density is its own mode's
    j = (~first).long()
    rows = torch.arange(N)
    scale = torch.where(first, 0.5, 2.0).to(f64)
    L = torch.linalg.cholesky(scale[:, None, None] * S[rows, j])
    y = mu[rows, j] + (L @ torch.randn(N, 2, 1, generator=torch.Generator().manual_seed(22), dtype=f64)).squeeze(-1)
    c = fit_mode_scales(y, w, mu, S, samples=200, seed=1)
    assert c == pytest.approx([0.5, 2.0], rel=0.1)
    single = fit_cov_scale(y, w, mu, S, samples=200, seed=1)
    assert 0.6 < single < 1.8  # one scale for both: between them
    lev = hpd_level(y, w, mu, S, c, samples=200, seed=1).numpy()
    for g in (first.numpy(), ~first.numpy()):
        assert np.mean(lev[g] <= NOMINAL_2SIGMA) == pytest.approx(NOMINAL_2SIGMA, abs=0.02)


def test_fit_cov_scale_widens_the_bracket_and_clips_to_bounds() -> None:
    w, mu, S = random_mixture(2000, 1, 7)
    assert fit_cov_scale(*(draw(w, mu, S, 9.0, 8), w, mu, S)) == pytest.approx(9.0, rel=0.08)
    assert fit_cov_scale(*(draw(w, mu, S, 9.0, 8), w, mu, S), bounds=(0.5, 3.0)) == 3.0
    assert fit_cov_scale(*(draw(w, mu, S, 0.01, 8), w, mu, S), bounds=(0.5, 3.0)) == 0.5


def test_bad_input_raises() -> None:
    w, mu, S = random_mixture(5, 2, 0)
    y = torch.zeros(5, 2, dtype=f64)
    with pytest.raises(ValueError, match="must agree"):
        hpd_level(y[:4], w, mu, S)
    with pytest.raises(ValueError, match="mu"):
        hpd_level(y, w, mu[0], S)
    with pytest.raises(ValueError, match="scale"):
        hpd_level(y, w, mu, S, scale=0.0)
    with pytest.raises(ValueError, match="one per component"):
        hpd_level(y, w, mu, S, scale=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="target"):
        fit_cov_scale(y, w, mu, S, target=1.0)
    with pytest.raises(ValueError, match="bounds"):
        fit_cov_scale(y, w, mu, S, bounds=(2.0, 1.0))
    with pytest.raises(ValueError, match="at least one report"):
        fit_cov_scale(y[:0], w[:0], mu[:0], S[:0])
    tracks = simulated_cv(0.05, 10.0, 2, 20, seed=0)
    with pytest.raises(ValueError, match="cov_scale"):
        evaluate_filter(cv_filter(0.05, 10.0), tracks, cov_scale=-1.0)
    with pytest.raises(ValueError, match="cov_scale"):
        evaluate_filter(cv_filter(0.05, 10.0), tracks, cov_scale=[1.0, 2.0])


def test_calibrated_kalman_predictive_is_the_filter_with_q_r_and_prior_scaled() -> None:
    """For a linear Kalman filter, S -> c S is exactly Q, R, P0 -> c Q, c R, c P0 (same gain)."""
    tracks = simulated_cv(0.05, 10.0, 6, 60, seed=1)
    c = 1.7
    a = summary(evaluate_filter(cv_filter(0.05, 10.0, diffuse_variance=100.0), tracks, cov_scale=c))
    b = summary(evaluate_filter(cv_filter(0.05 * c, 10.0 * math.sqrt(c), diffuse_variance=100.0 * c), tracks))
    assert a["reports_moving"] > 0 and np.isfinite(a["fc_rmse_5"])
    for k in ("nll", "nll_moving", "nll_moored", "cover2s", "cover2s_moving", "rmse1", "fc_rmse_5", "fc_rmse_15"):
        np.testing.assert_allclose(a[k], b[k], rtol=1e-9, atol=1e-12, equal_nan=True, err_msg=k)


def test_cov_scale_one_equals_the_filter_likelihood_for_an_imm() -> None:
    tracks = simulated_cv(0.05, 10.0, 4, 40, seed=2)
    slow = tl.models.integrated_ou(k=0.01, q=0.01, dim=2, dtype=f64)
    fast = tl.models.integrated_ou(k=0.05, q=0.5, dim=2, dtype=f64)
    H = tl.models.position_observation(slow)
    R = torch.stack([25.0 * torch.eye(2), 100.0 * torch.eye(2)]).to(f64)
    imm = tl.IMMFilter([slow, fast], H, R, torch.tensor([[0.0, 1e-3], [1e-3, 0.0]], dtype=f64), diffuse_variance=100.0)
    own = evaluate_filter(imm, tracks, horizons=())
    mixed = evaluate_filter(imm, tracks, horizons=(), cov_scale=1.0 + 1e-12)  # the mixture density path
    assert np.allclose(own.nll, mixed.nll, rtol=1e-9, atol=1e-9)


def test_calibrate_filter_hits_the_target_on_its_tracks_and_corrects_a_wrong_noise() -> None:
    tracks = simulated_cv(0.05, 10.0, 30, 80, seed=3)
    right, wrong = cv_filter(0.05, 10.0), cv_filter(0.05, 25.0)  # R 6x too large: too wide a predictive
    (c_right,), (c_wrong,) = calibrate_filter(right, tracks), calibrate_filter(wrong, tracks)
    assert 0.85 < c_right < 1.2
    assert c_wrong < 0.75
    for model, c in ((right, c_right), (wrong, c_wrong)):
        cover = summary(evaluate_filter(model, tracks, horizons=(), cov_scale=c))["cover2s"]
        assert cover == pytest.approx(NOMINAL_2SIGMA, abs=0.003)
    pred = one_step_predictive(right, tracks)
    assert pred["y"].shape == (tracks.num_reports - len(tracks), 2) and pred["w"].shape[-1] == 1
