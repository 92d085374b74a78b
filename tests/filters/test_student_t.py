"""The Student-t filter (Roth, Özkan & Gustafsson 2013) as a noise model of every filter.

Against values computed elsewhere: the one-step predictive is scipy's multivariate t, a whole
sequence is a plain numpy reference filter (joint update, the posterior's dof brought back by
matching the covariance), the log-gamma ratio is mpmath's, the HPD level is scipy's F CDF;
ν → ∞ is the Kalman filter; the algorithms, the online step and the IMM agree; gradients by
gradcheck in float64.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats
from scipy.special import betainc as scipy_betainc

import torchsde_lti as tl
from torchsde_lti.evaluation import hpd_level, mixture_log_prob, predictive_dof
from torchsde_lti.evaluation.student_t import betainc, t_hpd_level
from torchsde_lti.filters import GaussianNoise, StudentTNoise, kalman_filter, kalman_step
from torchsde_lti.filters.imm import combine
from torchsde_lti.filters.noise import log_gamma_ratio

F64 = torch.float64
H2 = [[1.0, 0, 0, 0], [0, 0, 1.0, 0]]


def _problem(B: int = 3, T: int = 7, seed: int = 0, dtype: torch.dtype = F64):
    g = torch.Generator().manual_seed(seed)
    sde = tl.models.constant_velocity(dim=2, q=0.5, dtype=F64)
    dt = torch.rand(B, T, generator=g, dtype=F64) + 0.1
    with torch.no_grad():
        d = sde(dt)
    y = 3 * torch.randn(B, T, 2, generator=g, dtype=F64)
    y[0, 2, 1] = math.nan  # one missing component
    y[1, 3] = math.nan  # a missing report
    H = torch.tensor(H2, dtype=F64)
    R = torch.tensor([[0.3, 0.1], [0.1, 0.5]], dtype=F64)
    m0, P0 = torch.zeros(4, dtype=F64), 10 * torch.eye(4, dtype=F64)
    return tuple(x.to(dtype) for x in (y, d.A, d.Q, H, R, m0, P0))


def _reference(y, A, Q, H, R, m0, P0, nu):
    """A plain numpy Student-t filter, one series (float64): joint update over the observed
    components, log St by scipy, posterior scale (ν + Δ²)/(ν + d) P⁺ with ν + d dof, matched
    back to ν in its covariance."""
    m, P, lls = m0.copy(), P0.copy(), []
    for k in range(len(y)):
        m, P = A[k] @ m, A[k] @ P @ A[k].T + Q[k]
        o = ~np.isnan(y[k])
        if not o.any():
            lls.append(0.0)
            continue
        Ho, Ro = H[o], R[np.ix_(o, o)]
        S = Ho @ P @ Ho.T + Ro
        e = y[k][o] - Ho @ m
        lls.append(stats.multivariate_t(loc=np.zeros(o.sum()), shape=S, df=nu).logpdf(e))
        K = P @ Ho.T @ np.linalg.inv(S)
        d2, d = e @ np.linalg.solve(S, e), o.sum()
        m, P = m + K @ e, (nu + d2) / (nu + d) * (P - K @ S @ K.T)
        P = P * (nu + d) / (nu + d - 2) * (nu - 2) / nu
    return np.array(lls), m, P


@pytest.mark.parametrize("algorithm", ["sequential", "square_root"])
def test_filter_equals_a_plain_reference_student_t_filter(algorithm):
    y, A, Q, H, R, m0, P0 = _problem()
    nu = 3.5
    out = kalman_filter(y, A, Q, H, R, m0, P0, algorithm=algorithm, noise=StudentTNoise(torch.tensor(nu, dtype=F64)))
    for b in range(y.shape[0]):
        lls, m, P = _reference(*(x.numpy() for x in (y[b], A[b], Q[b], H, R, m0, P0)), nu)
        np.testing.assert_allclose(out.step_log_likelihood[b].numpy(), lls, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(out.mean[b, -1].numpy(), m, rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(out.cov[b, -1].numpy(), P, rtol=1e-11, atol=1e-11)


def test_one_step_predictive_is_the_multivariate_t():
    y, A, Q, H, R, m0, P0 = _problem()
    nu = 5.0
    out = kalman_filter(y, A, Q, H, R, m0, P0, noise=StudentTNoise(torch.tensor(nu, dtype=F64)))
    S, e = out.innovation_cov[2, 4].numpy(), out.innovation[2, 4].numpy()
    want = stats.multivariate_t(loc=np.zeros(2), shape=S, df=nu).logpdf(e)
    assert float(out.step_log_likelihood[2, 4]) == pytest.approx(want, rel=1e-13)
    # one component missing: the univariate t of the observed one
    S1, e1 = out.innovation_cov[0, 2, 0, 0].item(), out.innovation[0, 2, 0].item()
    want1 = stats.t(df=nu, scale=math.sqrt(S1)).logpdf(e1)
    assert float(out.step_log_likelihood[0, 2]) == pytest.approx(want1, rel=1e-13)
    assert float(out.step_log_likelihood[1, 3]) == 0.0  # a missing report adds 0


@pytest.mark.parametrize("nu", [1e8, 1e12])
def test_large_dof_is_the_kalman_filter(nu):
    """ν → ∞ is the Gaussian filter: the scale factor is 1 + O(Δ²/ν), the density's difference
    O(Δ⁴/ν) (Δ² up to ~100 on these residuals): ν = 1e8 agrees to ~4e-4, ν = 1e12 to ~4e-8."""
    args = _problem()
    g = kalman_filter(*args)
    t = kalman_filter(*args, noise=StudentTNoise(torch.tensor(nu, dtype=F64)))
    tol = 1e5 / nu
    torch.testing.assert_close(t.step_log_likelihood, g.step_log_likelihood, rtol=0, atol=tol)
    torch.testing.assert_close(t.cov, g.cov, rtol=tol, atol=0)
    torch.testing.assert_close(t.mean, g.mean, rtol=0, atol=tol)  # (the gains follow the rescaled P)


def test_log_gamma_ratio_against_mpmath_in_both_dtypes():
    mpmath = pytest.importorskip("mpmath")
    mpmath.mp.dps = 40
    xs = [1.0001, 1.5, 3.0, 7.999, 8.0, 8.001, 20.0, 1e3, 1e6, 5e7, 1e12]
    for a in (0.0, 0.5, 1.0, 1.5, 2.0):
        want = [float(mpmath.loggamma(x + a) - mpmath.loggamma(x) - a * mpmath.log(x)) for x in xs]
        got = log_gamma_ratio(torch.tensor(xs, dtype=F64), torch.tensor(a, dtype=F64))
        np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=2e-15)
        got32 = log_gamma_ratio(torch.tensor(xs, dtype=torch.float32), torch.tensor(a))
        np.testing.assert_allclose(got32.numpy(), want, rtol=0, atol=3e-6)  # lgamma(5e7) alone is ±32 in float32


def test_algorithms_agree_and_the_scan_refuses_the_t():
    args = _problem(seed=3)
    noise = StudentTNoise(torch.tensor(3.0, dtype=F64))
    seq = kalman_filter(*args, noise=noise)
    sqr = kalman_filter(*args, noise=noise, algorithm="square_root")
    for name in ("log_likelihood", "mean", "cov", "pred_cov", "innovation_cov"):
        torch.testing.assert_close(getattr(sqr, name), getattr(seq, name), rtol=1e-11, atol=1e-11, msg=name)
    with pytest.raises(ValueError, match="no associative scan"):
        kalman_filter(*args, noise=noise, algorithm="scan")


def test_structured_loop_scans_the_t_update():
    """The loop as torch's structured scan (torch.compile / torch.export's route), run eagerly
    here: the Student-t scale update travels in the scanned inputs."""
    import torchsde_lti.filters.sequential as sequential
    from torchsde_lti.filters.inputs import FilterInputs, complete_from_filtered, prepare_inputs

    y, A, Q, H, R, m0, P0 = _problem(seed=4)
    noise = StudentTNoise(torch.tensor(4.0, dtype=F64))
    prep = prepare_inputs(FilterInputs(y, A, Q, H, R, m0, P0))
    ref = sequential.sequential_filter(prep, noise=noise)
    with torch.no_grad(), pytest.MonkeyPatch.context() as mp:
        mp.setattr(sequential, "_run_compiled_loop", sequential._scan_loop)
        out = complete_from_filtered(prep, *sequential.structured_filtered(prep, noise), noise)
    for name in ("log_likelihood", "mean", "cov", "pred_cov"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name).detach(), rtol=1e-12, atol=1e-12, msg=name)


def test_online_step_is_the_sequence_step():
    y, A, Q, H, R, m0, P0 = _problem(seed=5)
    noise = StudentTNoise(torch.tensor(2.5, dtype=F64))
    seq = kalman_filter(y, A, Q, H, R, m0, P0, noise=noise)
    state = tl.KalmanState(m0.expand(3, 4), P0.expand(3, 4, 4))
    for k in range(y.shape[1]):
        state, step = kalman_step(state, y[:, k], A[:, k], Q[:, k], H, R, noise=noise)
        torch.testing.assert_close(step.log_likelihood, seq.step_log_likelihood[:, k], rtol=1e-13, atol=1e-13)
        torch.testing.assert_close(state.cov, seq.cov[:, k], rtol=1e-13, atol=1e-13)


def test_float32_agrees_with_float64():
    args64 = _problem(seed=6)
    args32 = _problem(seed=6, dtype=torch.float32)
    t64 = kalman_filter(*args64, noise=StudentTNoise(torch.tensor(3.0, dtype=F64)))
    t32 = kalman_filter(*args32, noise=StudentTNoise(torch.tensor(3.0)))
    torch.testing.assert_close(t32.log_likelihood.double(), t64.log_likelihood, rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(t32.cov.double(), t64.cov, rtol=1e-4, atol=1e-5)
    big = kalman_filter(*args32, noise=StudentTNoise(torch.tensor(1e7)))
    torch.testing.assert_close(big.log_likelihood, kalman_filter(*args32).log_likelihood, rtol=1e-5, atol=1e-3)


def test_gradcheck_through_dof_R_Q_and_y():
    y, A, Q, H, R, m0, P0 = _problem(B=2, T=4, seed=7)
    y = torch.nan_to_num(y, nan=0.5)

    def loglik(nu, R_, Q_, y_):
        return kalman_filter(y_, A, Q_, H, R_, m0, P0, noise=StudentTNoise(nu), validate_args=False).log_likelihood

    inputs = (torch.tensor(3.3, dtype=F64), R.clone(), Q[:, :1].clone(), y.clone())
    for x in inputs:
        x.requires_grad_(True)
    assert torch.autograd.gradcheck(loglik, inputs)
    # the large-ν branch of the log-gamma ratio (x = ν/2 ≥ 8) too
    big = (torch.tensor(40.0, dtype=F64, requires_grad=True), *inputs[1:])
    assert torch.autograd.gradcheck(loglik, big)


def test_dof_is_checked_and_must_broadcast():
    args = _problem()
    with pytest.raises(ValueError, match="finite and > 2"):
        kalman_filter(*args, noise=StudentTNoise(torch.tensor(2.0, dtype=F64)))
    with pytest.raises(ValueError, match="finite and > 2"):
        kalman_filter(*args, noise=StudentTNoise(torch.tensor(math.nan, dtype=F64)))
    with pytest.raises(ValueError, match="must broadcast to the filter's batch"):
        kalman_filter(*args, noise=StudentTNoise(torch.full((2,), 4.0, dtype=F64)))
    per_track = kalman_filter(*args, noise=StudentTNoise(torch.tensor([3.0, 4.0, 9.0], dtype=F64)))
    for b, nu in enumerate((3.0, 4.0, 9.0)):
        one = kalman_filter(*(x[b : b + 1] if x.dim() == 3 and x.shape[0] == 3 else x for x in args[:1]),
                            *(x[b : b + 1] for x in args[1:3]), *args[3:],
                            noise=StudentTNoise(torch.tensor(nu, dtype=F64)))  # fmt: skip
        torch.testing.assert_close(per_track.log_likelihood[b], one.log_likelihood[0], rtol=1e-13, atol=1e-13)


# --------------------------------------------------------------------------- modules


def _kf(noise=None, dtype=F64):
    sde = tl.models.constant_velocity(dim=2, q=0.5, dtype=dtype)
    R = torch.tensor([[0.3, 0.1], [0.1, 0.5]], dtype=dtype)
    return tl.KalmanFilter(sde, torch.tensor(H2, dtype=dtype), R, P0=10 * torch.eye(4, dtype=dtype), noise=noise)


def test_module_option_learns_dof_and_round_trips():
    kf = _kf(tl.StudentT(4.0))
    assert float(kf.noise.dof.detach()) == pytest.approx(4.0, rel=1e-14)
    kf.noise.dof = 7.5
    assert float(kf.noise.dof.detach()) == pytest.approx(7.5, rel=1e-14)
    g = torch.Generator().manual_seed(0)
    y, dt = torch.randn(4, 9, 2, generator=g, dtype=F64).cumsum(1), torch.rand(4, 9, generator=g, dtype=F64)
    out = kf(y, dt)
    (-out.log_likelihood.sum()).backward()
    raw = kf.noise.parametrizations.dof.original
    assert raw.grad is not None and math.isfinite(float(raw.grad))
    fresh = _kf(tl.StudentT(4.0))
    fresh.load_state_dict(kf.state_dict())
    assert float(fresh.noise.dof.detach()) == pytest.approx(7.5, rel=1e-14)
    torch.testing.assert_close(fresh(y, dt).log_likelihood, out.log_likelihood.detach())
    with torch.no_grad():  # finite and > 2 for any finite raw value
        for v in (-1e4, -30.0, 0.0, 30.0, 1e30):
            raw.fill_(v)
            assert math.isfinite(float(kf.noise.dof)) and float(kf.noise.dof) > 2.0
    assert isinstance(_kf().noise.model(), GaussianNoise)
    assert predictive_dof(_kf()) is None and float(predictive_dof(_kf(tl.StudentT(6.0)))) == pytest.approx(6.0)


def test_module_option_refuses_bad_values():
    with pytest.raises(ValueError, match="dof must be > 2"):
        tl.StudentT(2.0)
    with pytest.raises(ValueError, match="one number or one per IMM mode"):
        tl.StudentT(torch.tensor([[3.0, 4.0]]))
    # a ν per mode is an IMM's (tests/filters/test_student_t_modes.py)
    with pytest.raises(ValueError, match="a KalmanFilter takes one"):
        _kf(tl.StudentT(torch.tensor([3.0, 4.0])))
    with pytest.raises(TypeError, match="noise must be"):
        _kf("student_t")
    with pytest.raises(ValueError, match="must be > 2"):
        _kf(tl.StudentT(4.0)).noise.dof = 1.5


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_module_step_equals_forward(dtype):
    kf = _kf(tl.StudentT(3.2), dtype)
    g = torch.Generator().manual_seed(1)
    y = (3 * torch.randn(3, 6, 2, generator=g, dtype=F64)).cumsum(1).to(dtype)
    y[0, 2, 0] = math.nan
    dt = torch.rand(3, 6, generator=g, dtype=F64).to(dtype)
    with torch.no_grad():
        out = kf(y, dt)
        state = kf.initial_state(3)
        for k in range(6):
            state, step = kf.step(state, y[:, k], dt[:, k])
    tol = 1e-12 if dtype == F64 else 1e-5
    torch.testing.assert_close(step.log_likelihood, out.step_log_likelihood[:, -1], rtol=tol, atol=tol)
    torch.testing.assert_close(state.cov, out.cov[:, -1], rtol=tol, atol=tol)


# --------------------------------------------------------------------------- IMM


def _imm(noise=None, M=2):
    models = [tl.models.constant_velocity(dim=2, q=0.5, dtype=F64), tl.models.integrated_ou(0.7, 2.0, dim=2, dtype=F64)]
    rates = torch.tensor([[0.0, 0.1], [0.2, 0.0]], dtype=F64)[:M, :M]
    return tl.IMMFilter(models[:M], torch.tensor(H2, dtype=F64), torch.tensor([[0.3, 0.1], [0.1, 0.5]], dtype=F64),
                        rates, P0=10 * torch.eye(4, dtype=F64), noise=noise)  # fmt: skip


def test_imm_of_one_mode_is_the_kalman_filter_and_large_dof_is_the_gaussian_imm():
    y, *_ = _problem(seed=8)
    dt = torch.rand(3, 7, generator=torch.Generator().manual_seed(8), dtype=F64) + 0.1
    with torch.no_grad():
        a, b = _kf(tl.StudentT(3.5))(y, dt), _imm(tl.StudentT(3.5), M=1)(y, dt)
        torch.testing.assert_close(b.step_log_likelihood, a.step_log_likelihood, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(b.cov, a.cov, rtol=1e-12, atol=1e-12)
        g, t = _imm()(y, dt), _imm(tl.StudentT(1e12))(y, dt)
        torch.testing.assert_close(t.step_log_likelihood, g.step_log_likelihood, rtol=0, atol=1e-7)
        torch.testing.assert_close(t.cov, g.cov, rtol=1e-7, atol=1e-9)


def test_imm_step_equals_forward_and_log_likelihood_is_the_t_mixture():
    imm = _imm(tl.StudentT(3.0))
    y, *_ = _problem(seed=9)
    dt = torch.rand(3, 7, generator=torch.Generator().manual_seed(9), dtype=F64) + 0.1
    with torch.no_grad():
        out = imm(y, dt)
        state = imm.initial_state(3)
        for k in range(7):
            state, step = imm.step(state, y[:, k], dt[:, k])
            torch.testing.assert_close(step.log_likelihood, out.step_log_likelihood[:, k], rtol=1e-11, atol=1e-11)
            torch.testing.assert_close(state.mode_cov, out.mode_cov[:, k], rtol=1e-11, atol=1e-11)
        # step 5 of track 2 (all observed): log Σ_j c_j St(y; ŷ_j, S_j, ν) by scipy
        H = torch.tensor(H2, dtype=F64)
        c = out.pred_mode_probabilities[2, 5].numpy()
        mu = (out.mode_pred_mean[2, 5] @ H.mT).numpy()
        S = out.mode_innovation_cov[2, 5].numpy()
        want = np.log(
            sum(c[j] * stats.multivariate_t(loc=mu[j], shape=S[j], df=3.0).pdf(y[2, 5].numpy()) for j in range(2))
        )
        assert float(out.step_log_likelihood[2, 5]) == pytest.approx(want, rel=1e-12)


def test_mixing_matches_the_mixture_covariance():
    """combine with the t's spread weight (ν − 2)/ν: the matched t's covariance ν/(ν−2)·P is the
    mixture's covariance Σ p_j (ν/(ν−2) P_j + (m_j − x)(m_j − x)ᵀ)."""
    g = torch.Generator().manual_seed(2)
    p = torch.tensor([0.2, 0.8], dtype=F64)
    m = torch.randn(2, 3, generator=g, dtype=F64)
    X = torch.randn(2, 3, 3, generator=g, dtype=F64)
    P = X @ X.mT + torch.eye(3, dtype=F64)
    nu = torch.tensor(3.4, dtype=F64)
    x, Pm = combine(p, m, P, StudentTNoise(nu))
    k = nu / (nu - 2)
    want = sum(p[j] * (k * P[j] + torch.outer(m[j] - x, m[j] - x)) for j in range(2))
    torch.testing.assert_close(k * Pm, want, rtol=1e-13, atol=1e-13)


# --------------------------------------------------------------------------- evaluation


def test_betainc_and_the_hpd_level_against_scipy():
    rng = np.random.default_rng(0)
    a = rng.choice([0.5, 1.0, 1.5, 2.5], 400)
    b = np.exp(rng.uniform(np.log(1.01), np.log(1e5), 400))
    x = rng.uniform(0, 1, 400)
    x[:5], x[5:10] = 0.0, 1.0
    np.testing.assert_allclose(betainc(torch.tensor(a), torch.tensor(b), torch.tensor(x)).numpy(),
                               scipy_betainc(a, b, x), rtol=0, atol=1e-12)  # fmt: skip
    maha = np.array([0.0, 0.1, 1.0, 4.0, 10.0, 100.0])
    for m in (1, 2, 3):
        for nu in (2.5, 4.0, 30.0):
            got = t_hpd_level(torch.tensor(maha), m, nu).numpy()
            np.testing.assert_allclose(got, stats.f.cdf(maha / m, m, nu), rtol=0, atol=1e-13)


def test_mixture_density_and_level_of_t_predictives():
    g = torch.Generator().manual_seed(3)
    N, m = 50, 2
    y = torch.randn(N, m, generator=g, dtype=F64) * 3
    mu = torch.randn(N, 2, m, generator=g, dtype=F64)
    X = torch.randn(N, 2, m, m, generator=g, dtype=F64)
    S = X @ X.mT + 0.5 * torch.eye(m, dtype=F64)
    w = torch.tensor([0.3, 0.7], dtype=F64).expand(N, 2)
    got = mixture_log_prob(y, w, mu, S, 4.0)
    want = [np.log(sum(w[i, j].item() * stats.multivariate_t(mu[i, j].numpy(), S[i, j].numpy(), df=4.0).pdf(y[i].numpy())
                       for j in range(2))) for i in range(N)]  # fmt: skip
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-12)
    # a mixture of two identical components: the Monte Carlo level ≈ the one component's closed form
    same_mu, same_S = mu[:, :1].expand(N, 2, m), S[:, :1].expand(N, 2, m, m)
    exact = hpd_level(y, w[:, :1] / w[:, :1], mu[:, :1], S[:, :1], dof=4.0)
    mc = hpd_level(y, w, same_mu, same_S, dof=4.0, samples=4000)
    assert float((mc - exact).abs().max()) < 0.04


def test_t_predictive_is_calibrated_on_t_data():
    """Draws from the t predictive fall in its 86.5 % HPD region 86.5 % of the time (the region
    of a Gaussian with the same scale would hold far fewer at ν = 3)."""
    g = torch.Generator().manual_seed(4)
    N, nu = 20_000, 3.0
    S = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=F64).expand(N, 1, 2, 2)
    L = torch.linalg.cholesky(S[:, 0])
    z = torch.randn(N, 2, generator=g, dtype=F64)
    chi = 2.0 * torch._standard_gamma(torch.full((N,), nu / 2, dtype=F64), generator=g)
    y = (L @ z.unsqueeze(-1)).squeeze(-1) * torch.sqrt(nu / chi).unsqueeze(-1)
    w, mu = torch.ones(N, 1, dtype=F64), torch.zeros(N, 1, 2, dtype=F64)
    inside = (hpd_level(y, w, mu, S, dof=nu) <= 1 - math.exp(-2)).double().mean()
    assert abs(float(inside) - (1 - math.exp(-2))) < 0.01
    gauss = (hpd_level(y, w, mu, S) <= 1 - math.exp(-2)).double().mean()
    assert float(gauss) < 0.8


def test_imm_smoother_refuses_the_t():
    imm = _imm(tl.StudentT(4.0))
    y, *_ = _problem(seed=10)
    with torch.no_grad():
        out = imm(y, torch.ones(3, 7, dtype=F64))
    with pytest.raises(ValueError, match="not for noise=StudentT"):
        imm.smooth(out)


def test_training_through_the_config_learns_dof_and_reloads(tmp_path):
    """``filter/noise=student_t`` through the one training path (experiment=tiny): ν is a
    parameter that moves, the run reloads with it (``tl.runs.load_run``), val/cover2s is the t's."""
    from hydra import compose, initialize_config_dir

    from tests.training.test_imm_training import CONF
    from torchsde_lti.runs import load_run
    from torchsde_lti.training import train

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=[f"output_dir={tmp_path}", "experiment=tiny", "filter/noise=student_t"])
    metrics, objects = train(cfg)
    kf = objects["module"].kf
    assert isinstance(kf.noise, tl.StudentT) and float(kf.noise.dof.detach()) != pytest.approx(4.0, rel=1e-6)
    assert math.isfinite(metrics["val/nll"]) and 0.0 <= metrics["val/cover2s"] <= 1.0
    run = load_run(tmp_path)
    assert isinstance(run.filter.noise, tl.StudentT)
    ckpt = torch.load(run.checkpoint, weights_only=True)["state_dict"]
    torch.testing.assert_close(
        run.filter.noise.parametrizations.dof.original, ckpt["kf.noise.parametrizations.dof.original"]
    )


def test_the_gaussian_k_step_loss_refuses_a_t_filter():
    """The k-step term is a Gaussian density: with noise=StudentT it would score the wrong
    predictive without a word, so the module says which setting to change."""
    from torchsde_lti.training import KalmanFilterModule

    kf = _imm(tl.StudentT(4.0))
    with pytest.raises(ValueError, match="k_step_weight=0"):
        KalmanFilterModule(kf, k_step=2, k_step_weight=0.3)
    assert KalmanFilterModule(kf, k_step=2, k_step_weight=0.0).k_step_weight == 0.0
