"""The IMM's exact forecast moments (filters.imm_forecast) and the action of the exponential it
rests on (core.transition_apply): against torch.matrix_exp, the Kalman filter's forecast (one
mode), the IMM's one-shot prediction (no switching, and its limit over vanishing sub-steps), a
Monte Carlo simulation of the switching SDE, gradcheck, float32 and batch shapes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from torchsde_lti.core import transition_apply
from torchsde_lti.core.linalg import noise_covariance
from torchsde_lti.filters import GaussianNoise, StudentTNoise, imm_forecast, imm_predict

F64 = torch.float64
#: Gaussian modes, Student-t modes with one ν, and with a ν per mode (3 modes).
NOISES = [
    GaussianNoise(),
    StudentTNoise(torch.tensor(4.0, dtype=F64)),
    StudentTNoise(torch.tensor([3.0, 5.0, 9.0], dtype=F64), True),
]


def _hurwitz(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    F = torch.randn(n, n, generator=g, dtype=F64)
    return F - (torch.linalg.eigvals(F).real.max() + 0.3) * torch.eye(n, dtype=F64)


@pytest.mark.parametrize("n", [1, 3, 12])
def test_transition_apply_equals_the_matrix_exponential(n: int) -> None:
    F = _hurwitz(n, n)
    dt = torch.cat([torch.zeros(1, dtype=F64), torch.logspace(-6, 4, 40, dtype=F64)])
    x = torch.randn(41, n, dtype=F64)
    ref = (torch.matrix_exp(F * dt[:, None, None]) @ x.unsqueeze(-1)).squeeze(-1)
    got = transition_apply(F, dt, x)
    assert torch.equal(got[0], x[0])  # dt = 0: x itself
    assert ((got - ref).norm(dim=-1) / x.norm(dim=-1)).max() < 1e-13
    # a few parameter sets broadcast against the batch
    Fs = torch.stack([F, 3.0 * F, torch.zeros(n, n, dtype=F64)])[:, None]
    ref3 = (torch.matrix_exp(Fs * dt[:, None, None]) @ x.unsqueeze(-1)).squeeze(-1)
    assert ((transition_apply(Fs, dt, x) - ref3).norm(dim=-1) / x.norm(dim=-1)).max() < 1e-13
    # float32 in, float32 out, to its precision
    got32 = transition_apply(F.float(), dt.float(), x.float())
    assert got32.dtype == torch.float32
    assert ((got32.double() - ref).norm(dim=-1) / x.norm(dim=-1)).max() < 1e-6


def test_transition_apply_checks_its_arguments() -> None:
    F, x = _hurwitz(3, 2), torch.ones(3, dtype=F64)
    with pytest.raises(ValueError, match="F must be square"):
        transition_apply(torch.ones(3, 2, dtype=F64), 1.0, x)
    with pytest.raises(ValueError, match=r"x must have shape \(\.\.\., 3\)"):
        transition_apply(F, 1.0, torch.ones(2, dtype=F64))
    with pytest.raises(ValueError, match="batch shapes do not broadcast"):
        transition_apply(F, torch.ones(4, dtype=F64), torch.ones(5, 3, dtype=F64))
    with pytest.raises(ValueError, match="dt must be non-negative"):
        transition_apply(F, -1.0, x)
    with pytest.raises(ValueError, match="x contains NaN"):
        transition_apply(F, 1.0, torch.full((3,), float("nan"), dtype=F64))
    with pytest.raises(ValueError, match="overflows float64"):
        transition_apply(-F, 1e4, x)  # an unstable F: e^(1e4 Re λ)
    assert torch.isnan(transition_apply(F, 1.0, torch.full((3,), float("nan"), dtype=F64), validate_args=False)).all()


def test_transition_apply_gradients() -> None:
    F = _hurwitz(3, 1).requires_grad_()
    dt = torch.tensor([0.3, 2.5, 40.0], dtype=F64, requires_grad=True)
    x = torch.randn(3, 3, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(transition_apply, (F, dt, x))


def _bank(dof: torch.Tensor | None = None) -> tuple[list[tl.LTISDE], torch.Tensor, torch.Tensor]:
    sdes = [
        tl.models.constant_velocity(dim=2, q=0.5, dtype=F64),
        tl.models.integrated_ou(1.5, 0.05, dim=2, dtype=F64),
        tl.models.integrated_ou(0.2, 2.0, dim=2, dtype=F64),
    ]
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64)
    return sdes, H, 0.3 * torch.eye(2, dtype=F64)


def _state(M: int, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    prob = torch.softmax(torch.randn(4, M, generator=g, dtype=F64), -1)
    mean = 100.0 * torch.randn(4, M, n, generator=g, dtype=F64)
    C = torch.randn(4, M, n, n, generator=g, dtype=F64)
    return prob, mean, C @ C.mT + 0.1 * torch.eye(n, dtype=F64)


def _matrices(sdes: list[tl.LTISDE]) -> tuple[torch.Tensor, torch.Tensor]:
    mats = [s.matrices() for s in sdes]
    return torch.stack([m.F for m in mats]), torch.stack([noise_covariance(m.L, m.Qc) for m in mats])


def _one_shot(prob, mean, cov, sdes, rates, h, noise):  # type: ignore[no-untyped-def]
    """The IMM's own prediction over each horizon h (K,): imm_predict with the exact per-mode
    discretisation and Pi = expm(Λ h)."""
    d = [tl.discretize(*s.matrices()[:3], h) for s in sdes]
    A, Q = torch.stack([x.A for x in d], -3), torch.stack([x.Q for x in d], -3)
    Pi = torch.matrix_exp(rates * h[:, None, None])
    return imm_predict(prob, mean, cov, A, Q, Pi, noise)


@pytest.mark.parametrize("noise", NOISES, ids=["gaussian", "t-shared", "t-per-mode"])
def test_without_switching_it_is_the_imm_prediction(noise) -> None:  # type: ignore[no-untyped-def]
    sdes, _, _ = _bank()
    F, W = _matrices(sdes)
    prob, mean, cov = _state(3, 4)
    h = torch.tensor([0.0, 0.7, 30.0, 900.0], dtype=F64)
    rates = torch.zeros(3, 3, dtype=F64)
    a = imm_forecast(prob, mean, cov, F, W, rates, h.expand(4, 4), noise)
    b = _one_shot(prob, mean, cov, sdes, rates, h, noise)
    for x, y in zip(a, b):
        assert torch.allclose(x, y, rtol=1e-9, atol=1e-9 * float(y.abs().max()))


def test_one_mode_is_the_kalman_forecast() -> None:
    sdes, H, R = _bank()
    kf = tl.KalmanFilter(sdes[1], H, R, P0=10 * torch.eye(4, dtype=F64))
    imm = tl.IMMFilter([sdes[1]], H, R, torch.zeros(1, 1, dtype=F64), P0=10 * torch.eye(4, dtype=F64))
    y, dt = torch.randn(3, 15, 2, dtype=F64).cumsum(1), torch.rand(3, 15, dtype=F64) + 0.1
    h = torch.tensor([1.0, 60.0, 600.0], dtype=F64)
    a, b = imm.forecast(imm(y, dt), h), kf.forecast(kf(y, dt), h)
    assert torch.allclose(a.mean, b.mean, rtol=1e-10, atol=1e-9)
    assert torch.allclose(a.cov, b.cov, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("noise", NOISES, ids=["gaussian", "t-shared", "t-per-mode"])
def test_it_is_the_limit_of_the_imm_prediction_over_vanishing_steps(noise) -> None:  # type: ignore[no-untyped-def]
    """N one-shot IMM predictions of h/N each converge to the exact moments, the error ~ 1/N; for
    t modes too (scales mixed as covariances r_i P_i, the process noise added to the scale)."""
    sdes, _, _ = _bank()
    F, W = _matrices(sdes)
    prob, mean, cov = _state(3, 4, seed=1)
    rates = tl.nn.parametrizations.generator_from_rates(
        torch.tensor([[0, 0.05, 0.02], [0.1, 0, 0.05], [0.01, 0.2, 0]], dtype=F64)
    )
    h = 60.0
    exact = imm_forecast(prob, mean, cov, F, W, rates, torch.full((4, 1), h, dtype=F64), noise)
    errors = []
    for N in (64, 512):
        p, m, P = prob, mean, cov
        for _ in range(N):
            step = _one_shot(p, m, P, sdes, rates, torch.tensor([h / N], dtype=F64), noise)
            p, m, P = step.mode_probabilities[:, 0], step.mode_mean[:, 0], step.mode_cov[:, 0]
        errors.append(
            [
                float((exact.mean[:, 0] - step.mean[:, 0]).abs().max()),
                float((exact.cov[:, 0] - step.cov[:, 0]).abs().max()),
            ]
        )
    one_shot = _one_shot(prob, mean, cov, sdes, rates, torch.tensor([h], dtype=F64), noise)
    assert float((exact.mean[:, 0] - one_shot.mean[:, 0]).abs().max()) > 20 * errors[1][0]  # it is not the one-shot
    for coarse, fine in zip(*errors):
        assert 5.0 < coarse / fine < 11.0  # first order: 8× the steps, ~1/8 the error


def test_moments_match_a_simulation_of_the_switching_sde() -> None:
    """A scalar two-mode OU with switching, simulated exactly (holding times, exact OU segments),
    40,000 paths: mode probabilities, conditional means and variances within 4.5 standard errors."""
    a, w = np.array([-0.4, -2.5]), np.array([0.3, 4.0])
    lam = np.array([[-0.7, 0.7], [1.5, -1.5]])
    h, N = 2.0, 40_000
    rng = np.random.default_rng(0)
    prob0, mean0, var0 = np.array([0.6, 0.4]), np.array([1.0, -2.0]), np.array([0.5, 0.2])
    mode = (rng.random(N) > prob0[0]).astype(int)
    x = mean0[mode] + np.sqrt(var0[mode]) * rng.standard_normal(N)
    left = np.full(N, h)
    while (left > 0).any():
        hold = rng.exponential(1.0 / -lam[mode, mode])
        tau = np.minimum(hold, left)
        decay = np.exp(a[mode] * tau)
        x = decay * x + np.sqrt(w[mode] * (1 - decay**2) / (-2 * a[mode])) * rng.standard_normal(N)
        switch = (hold < left) & (left > 0)
        left = left - tau
        mode = np.where(switch, 1 - mode, mode)
    t = lambda v: torch.tensor(v, dtype=F64)  # noqa: E731
    fc = imm_forecast(
        t(prob0), t(mean0)[:, None], t(var0)[:, None, None], t(a)[:, None, None], t(w)[:, None, None], t(lam), t([h])
    )
    for j in range(2):
        xs = x[mode == j]
        p = len(xs) / N
        assert abs(float(fc.mode_probabilities[0, j]) - p) < 4.5 * np.sqrt(p * (1 - p) / N)
        assert abs(float(fc.mode_mean[0, j, 0]) - xs.mean()) < 4.5 * xs.std() / np.sqrt(len(xs))
        assert abs(float(fc.mode_cov[0, j, 0, 0]) / xs.var() - 1) < 4.5 * np.sqrt(2 / len(xs)) + 0.01


def test_gradients_and_float32() -> None:
    sdes, _, _ = _bank()
    F, W = _matrices(sdes)
    prob, mean, cov = _state(3, 4, seed=2)
    rates = tl.nn.parametrizations.generator_from_rates(torch.full((3, 3), 0.05, dtype=F64))
    h = torch.tensor([[5.0, 300.0]], dtype=F64).expand(4, 2)

    def f(p, m, P, F_, W_, L_):  # type: ignore[no-untyped-def]
        out = imm_forecast(torch.softmax(p, -1), m, P, F_, W_, L_, h[:1])
        return out.mean, out.cov, out.mode_cov

    args = (prob[:1].log(), mean[:1] / 100, cov[:1], F, W, rates)
    assert torch.autograd.gradcheck(f, tuple(a.detach().clone().requires_grad_() for a in args))
    # float32 in and out, coordinates of 1e5 m: float32's rounding of the result only (float64 inside)
    args32 = tuple(
        x.float() for x in (prob, mean + torch.tensor([1e5, 3.0, -2e5, 1.0], dtype=F64), cov, F, W, rates, h)
    )
    got = imm_forecast(*args32, GaussianNoise(), True)  # (the total of float32 probabilities is not 1 to float64 eps)
    ref = imm_forecast(*(x.double() for x in args32))
    assert got.cov.dtype == torch.float32
    for a, b in zip(got, ref):
        assert ((a.double() - b).abs() / b.abs().amax((-2, -1), keepdim=True).clamp_min(1e-30)).max() < 1e-6


def test_batch_shapes_and_parameters_per_element() -> None:
    sdes, _, _ = _bank()
    F, W = _matrices(sdes)
    prob, mean, cov = _state(3, 4, seed=3)
    rates = tl.nn.parametrizations.generator_from_rates(torch.full((3, 3), 0.02, dtype=F64))
    h = torch.tensor([10.0, 100.0, 1000.0], dtype=F64)
    shared = imm_forecast(prob, mean, cov, F, W, rates, h)  # (K,) shared by the batch
    assert shared.mean.shape == (4, 3, 4) and shared.mode_cov.shape == (4, 3, 3, 4, 4)
    # per-element parameters: element i with W scaled by i + 1 equals the shared call with that W
    scales = torch.arange(1.0, 5.0, dtype=F64)
    per = imm_forecast(prob, mean, cov, F.expand(4, 3, 4, 4), W * scales[:, None, None, None], rates, h)
    for i in range(4):
        one = imm_forecast(prob[i], mean[i], cov[i], F, W * scales[i], rates, h)
        assert torch.allclose(per.cov[i], one.cov, rtol=1e-10, atol=1e-9)
        assert torch.allclose(per.mean[i], one.mean, rtol=1e-10, atol=1e-9)


def test_the_filters_own_states_are_valid_forecast_origins_after_huge_residuals() -> None:
    """Reports far off every mode (log-likelihoods ~ −1e4) leave mode probabilities that still sum
    to 1 within the state check's tolerance (they summed to 1 only within |ℓ| eps, 2e-12, before
    they were normalised by a softmax), so a forecast from every filtered state is accepted."""
    sdes, H, R = _bank()
    imm = tl.IMMFilter(sdes, H, R, torch.full((3, 3), 0.1, dtype=F64), P0=10 * torch.eye(4, dtype=F64))
    g = torch.Generator().manual_seed(0)
    y = 10.0 * torch.randn(4, 100, 2, generator=g, dtype=F64).cumsum(1).cumsum(1)
    dt = torch.rand(4, 100, generator=g, dtype=F64) + 0.1
    with torch.no_grad():
        out = imm(y, dt)
        assert float(out.step_log_likelihood.min()) < -1e3  # the premise: huge residuals
        assert float((out.mode_probabilities.sum(-1) - 1).abs().max()) <= 3 * torch.finfo(F64).eps
        state = (out.mode_probabilities, out.mode_mean, out.mode_cov)
        fc = imm.forecast(state, torch.tensor([300.0], dtype=F64))
    assert fc.mean.shape == (4, 100, 1, 4) and bool(torch.isfinite(fc.cov).all())


def test_a_horizon_beyond_the_accuracy_of_the_squarings_raises() -> None:
    """Σ p = 1 exactly, so its drift measures what ~log2(h ν) squarings lost: within √eps up to
    1e7 s here, and a clear error beyond (not mode probabilities of 1e-227, as unchecked)."""
    sdes, H, R = _bank()
    imm = tl.IMMFilter(sdes[:2], H, R, torch.full((2, 2), 0.1, dtype=F64))
    out = imm(torch.randn(2, 10, 2, dtype=F64), torch.ones(2, 10, dtype=F64))
    fc = imm.forecast(out, torch.tensor([900.0, 1e7], dtype=F64))
    assert float((fc.mode_probabilities.sum(-1) - 1).abs().max()) < 1e-12 and bool(torch.isfinite(fc.cov).all())
    with pytest.raises(ValueError, match="horizons up to 1e\\+10 loses accuracy"):
        imm.forecast(out, 1e10)


def test_moments_that_overflow_raise() -> None:
    """An unstable mode over a long horizon: its moments leave float64, a clear error."""
    unstable = tl.LTISDE(0.5 * torch.eye(2, dtype=F64), torch.eye(2, dtype=F64), torch.eye(2, dtype=F64))
    imm = tl.IMMFilter([unstable, unstable], torch.eye(2, dtype=F64), torch.eye(2, dtype=F64), torch.full((2, 2), 0.1))
    out = imm(torch.randn(1, 3, 2, dtype=F64), torch.ones(1, 3, dtype=F64))
    assert bool(torch.isfinite(imm.forecast(out, 60.0).cov).all())
    with pytest.raises(ValueError, match="forecast overflows float64 for horizons up to 3e\\+03"):
        imm.forecast(out, 3000.0)
