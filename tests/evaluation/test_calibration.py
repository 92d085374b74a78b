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
    OnlineScale,
    calibrate_filter,
    fit_cov_scale,
    fit_mode_scales,
    hpd_level,
    online_scales,
)
from torchsde_lti.evaluation.predictive import frozen_copy, mixture_log_prob, one_step_predictive, predictive_batches
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


def slow_fast_imm(r_slow: float, r_fast: float) -> tl.IMMFilter:
    """Two integrated-OU modes (slow, fast) observing position with R = r² I each."""
    slow = tl.models.integrated_ou(k=0.01, q=0.01, dim=2, dtype=f64)
    fast = tl.models.integrated_ou(k=0.05, q=0.5, dim=2, dtype=f64)
    H = tl.models.position_observation(slow)
    R = torch.stack([r_slow**2 * torch.eye(2), r_fast**2 * torch.eye(2)]).to(f64)
    return tl.IMMFilter([slow, fast], H, R, torch.tensor([[0.0, 1e-3], [1e-3, 0.0]], dtype=f64), diffuse_variance=100.0)


def test_cov_scale_one_equals_the_filter_likelihood_for_an_imm() -> None:
    tracks = simulated_cv(0.05, 10.0, 4, 40, seed=2)
    imm = slow_fast_imm(5.0, 10.0)
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


def reference_online_scales(rate: float, level: float, y, w, mu, S, scored):  # type: ignore[no-untyped-def]
    """A plain loop over tracks and reports (one Gaussian component: the chi-square test)."""
    B, T = scored.shape
    before = np.ones((B, T))
    for b in range(B):
        ell = 0.0
        for k in range(T):
            before[b, k] = math.exp(ell)
            if scored[b, k]:
                d = (y[b, k] - mu[b, k, 0]).numpy()
                maha = float(d @ np.linalg.solve(before[b, k] * S[b, k, 0].numpy(), d))
                miss = 1.0 - math.exp(-0.5 * maha) > level
                ell += rate * (miss - (1.0 - level))
    return before


def test_online_scale_equals_a_plain_loop_and_its_miss_share_identity() -> None:
    B, T = 5, 60
    w, mu, S = random_mixture(B * T, 1, 7)
    w, mu, S = w.reshape(B, T, 1), mu.reshape(B, T, 1, 2), S.reshape(B, T, 1, 2, 2)
    y = draw(w.reshape(-1, 1), mu.reshape(-1, 1, 2), S.reshape(-1, 1, 2, 2), 3.0, 8).reshape(B, T, 2)
    scored = torch.rand(B, T, generator=torch.Generator().manual_seed(9)) < 0.8
    scored[:, 0] = False
    rule = OnlineScale(rate=0.3)
    before, after = online_scales(rule, y, w, mu, S, scored)
    np.testing.assert_allclose(
        before.numpy(), reference_online_scales(0.3, rule.level, y, w, mu, S, scored), rtol=1e-12
    )
    assert torch.equal(after[:, :-1], before[:, 1:])  # a forecast from k uses the scale report k+1 gets
    assert torch.equal(before[:, 0], torch.ones(B, dtype=f64))
    # the share of misses over a track is exactly 1 - level + log(s_final) / (rate K)
    level = hpd_level(y[scored], w[scored], mu[scored], before[scored][:, None, None, None] * S[scored])
    miss = torch.zeros(B, T, dtype=f64)
    miss[scored] = (level > rule.level).to(f64)
    K = scored.sum(-1).to(f64)
    want = 1.0 - rule.level + torch.log(after[:, -1]) / (rule.rate * K)
    assert torch.allclose(miss.sum(-1) / K, want, atol=1e-12)


def test_online_scale_restores_the_nominal_coverage_of_a_filter_with_the_wrong_noise() -> None:
    """A filter whose R is 5x too small (or 4x too large) for the data: far from 86.5 % on its own,
    near it with the scale adapted per track from past reports only; a right filter stays there
    (rate 0.4: NLL 11.19 -> 11.24, the price of a noisy scale; 0.1: 11.20)."""
    tracks = simulated_cv(0.05, 10.0, 12, 150, seed=4)
    for r, off in ((10.0, False), (10.0 / math.sqrt(5.0), True), (20.0, True)):
        kf = cv_filter(0.05, r)
        fixed = summary(evaluate_filter(kf, tracks, horizons=(300.0,)))
        online = summary(evaluate_filter(kf, tracks, horizons=(300.0,), online_scale=OnlineScale(rate=0.4)))
        assert (abs(fixed["cover2s"] - NOMINAL_2SIGMA) > 0.06) == off
        assert online["cover2s"] == pytest.approx(NOMINAL_2SIGMA, abs=0.02)
        assert online["fc_rmse_5"] == fixed["fc_rmse_5"]  # the means are unchanged
        if off:  # a slower adaptation (less noise in the scale) also lowers the NLL
            slow = summary(evaluate_filter(kf, tracks, horizons=(), online_scale=OnlineScale(rate=0.1)))
            assert slow["nll"] < fixed["nll"] - 0.03


def test_online_scale_nll_is_the_scaled_mixture_density() -> None:
    """evaluate_filter's NLL with an online scale: -log of the predictive mixture with every
    component's covariance times the track's scale before the report (IMM, Monte Carlo levels)."""
    tracks = simulated_cv(0.05, 10.0, 4, 40, seed=2)
    imm = slow_fast_imm(2.0, 4.0)
    rule = OnlineScale(rate=0.5)
    recs = evaluate_filter(imm, tracks, horizons=(), online_scale=rule, samples=200, cov_scale=[1.0, 2.0])
    want = []
    with torch.no_grad():
        for p in predictive_batches(frozen_copy(imm), tracks):
            S = torch.tensor([1.0, 2.0], dtype=f64)[:, None, None] * p.S
            before, _ = online_scales(rule, p.batch.y, p.w, p.mu, S, p.scored, samples=200)
            S = before[..., None, None, None] * S
            want.append(-mixture_log_prob(p.batch.y[p.scored], p.w[p.scored], p.mu[p.scored], S[p.scored]).numpy())
    np.testing.assert_allclose(recs.nll, np.concatenate(want), rtol=1e-12)
    assert not np.allclose(recs.nll, evaluate_filter(imm, tracks, horizons=(), cov_scale=[1.0, 2.0]).nll)


@pytest.mark.parametrize("kwargs", [{"rate": 0.0}, {"rate": float("nan")}, {"level": 1.0}, {"level": 0.0}])
def test_online_scale_refuses_a_bad_rule(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        OnlineScale(**kwargs)
    with pytest.raises(TypeError, match="rate must be a number, got str"):
        OnlineScale(rate="0.4")  # type: ignore[arg-type]


def test_online_scale_float32_empty_and_unscored_batches() -> None:
    rule = OnlineScale()
    w, mu, S = random_mixture(8, 2, 3)
    y = draw(w, mu, S, 1.0, 4)
    args = [t.reshape(2, 4, *t.shape[1:]).float() for t in (y, w, mu, S)]
    before, after = online_scales(rule, *args, torch.zeros(2, 4, dtype=torch.bool))
    assert before.dtype == torch.float32 and torch.equal(before, torch.ones(2, 4)) and torch.equal(after, before)
    scored = torch.ones(2, 4, dtype=torch.bool)
    before, after = online_scales(rule, *args, scored)
    assert torch.isfinite(after).all() and not torch.equal(after, torch.ones(2, 4))
    empty = online_scales(rule, *(t[:, :0] for t in args), scored[:, :0])
    assert empty[0].shape == empty[1].shape == (2, 0)
    with pytest.raises(ValueError, match="scored"):
        online_scales(rule, *args, scored[:, :3])
