"""Shaping filters (seed 003): augmented model, steady-state start (the model's prior_covariance()),
the KalmanFilter's default prior."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch

import torchsde_lti as tl
from tests.reference import numpy_kalman_filter, scipy_discretize

F64 = torch.float64


def first_order_with_ou_input(a=1.3, b=0.4, q=0.9, dtype=F64):
    """ẋ = −a x + f,  ḟ = −b f + w,  E[w w] = q δ: state [x, f]."""
    system = tl.models.ornstein_uhlenbeck(a, 1.0, dtype=dtype)  # its q is unused: f replaces its noise
    shaping = tl.models.ornstein_uhlenbeck(b, q, dtype=dtype)
    return tl.models.shaped(system, shaping)


def closed_form(a, b, q, t):
    """Variance of x and covariance of x, f from the steady-state start (x(0) = 0, f stationary)."""
    s2 = q / (2 * b)
    P_xf = s2 * (1 - math.exp(-(a + b) * t)) / (a + b)
    P_xx = (
        2
        * s2
        / (a + b)
        * ((1 - math.exp(-2 * a * t)) / (2 * a) - (math.exp(-(a + b) * t) - math.exp(-2 * a * t)) / (a - b))
    )
    return P_xx, P_xf, s2


def test_augmented_matrices_and_start():
    model = first_order_with_ou_input(1.3, 0.4, 0.9)
    np.testing.assert_allclose(model.F.detach().numpy(), [[-1.3, 1.0], [0.0, -0.4]], atol=1e-15)
    np.testing.assert_allclose(model.L.detach().numpy(), [[0.0], [1.0]], atol=0)
    np.testing.assert_allclose(model.Qc.detach().numpy(), [[0.9]], atol=1e-15)
    assert model.B is None
    np.testing.assert_allclose(model.prior_covariance().detach().numpy(), [[0.0, 0.0], [0.0, 0.9 / 0.8]], atol=1e-14)


def test_first_order_system_with_ou_input_matches_closed_form():
    a, b, q = 1.3, 0.4, 0.9
    model = first_order_with_ou_input(a, b, q)
    P0 = model.prior_covariance()
    m0 = torch.zeros(2, dtype=F64)
    for t in (0.1, 0.5, 1.0, 3.0, 7.0, 20.0):
        _, P = model.propagate(m0, P0, t)
        P_xx, P_xf, s2 = closed_form(a, b, q, t)
        np.testing.assert_allclose(P.detach().numpy(), [[P_xx, P_xf], [P_xf, s2]], atol=1e-13, rtol=1e-12)
    # the augmented P∞: the classic σ² / (a (a + b)) for the system state
    P_inf = model.stationary_covariance().detach().numpy()
    s2 = q / (2 * b)
    np.testing.assert_allclose(P_inf, [[s2 / (a * (a + b)), s2 / (a + b)], [s2 / (a + b), s2]], rtol=1e-13)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_propagate_keeps_the_shaping_block_at_its_P_inf(dtype):
    """Mass–spring–damper driven by a Matérn-3/2 force: shaping block constant, system block 0 → P∞."""
    system = tl.models.mass_spring_damper(m=2.0, k=3.0, c=0.8, dtype=dtype)
    shaping = tl.models.matern(1.5, lengthscale=1.5, variance=0.7, dtype=dtype)
    model = tl.models.shaped(system, shaping, C=torch.tensor([[1.0, 0.0]], dtype=dtype))
    n_s = 2
    P0 = model.prior_covariance()
    assert torch.all(P0[:n_s, :] == 0) and torch.all(P0[:, :n_s] == 0)
    P_f = shaping.stationary_covariance()
    torch.testing.assert_close(P0[n_s:, n_s:], P_f)
    P_inf = model.stationary_covariance()
    # slowest time constant of the augmented F
    tau = 1.0 / float(-torch.linalg.eigvals(model.F.detach().double()).real.max())
    ts = torch.linspace(0.0, 10 * tau, 41, dtype=dtype)
    m0 = torch.zeros(4, dtype=dtype)
    _, P = model.propagate(m0, P0, ts)  # (41, 4, 4), batched over t
    tol = 1e-12 if dtype == F64 else 2e-6
    block_err = (P[:, n_s:, n_s:] - P_f).abs().amax().item()
    assert block_err <= tol * max(1.0, P_f.abs().max().item()), block_err
    # t = 0: the start itself, every entry involving a system state 0
    assert P[0, :n_s, :].abs().max().item() == 0.0 and P[0, :, :n_s].abs().max().item() == 0.0
    # the system block converges to the augmented P∞
    err = (P - P_inf).abs().flatten(-2).amax(-1).double()
    assert err[-1] < 1e-4 * err[0]
    _, P_late = model.propagate(m0, P0, torch.tensor(60 * tau, dtype=dtype))
    torch.testing.assert_close(P_late, P_inf, atol=tol * 10, rtol=tol * 10)


def test_augmented_lyapunov_residual_is_at_rounding_level_and_matches_scipy():
    system = tl.models.mass_spring_damper(m=2.0, k=3.0, c=0.8, dtype=F64)
    shaping = tl.models.matern(1.5, lengthscale=1.5, variance=0.7, dtype=F64)
    model = tl.models.shaped(system, shaping, C=torch.tensor([[1.0, 0.0]], dtype=F64))
    F, L, Qc = (x.detach().numpy() for x in (model.F, model.L, model.Qc))
    P = model.stationary_covariance().detach().numpy()
    W = L @ Qc @ L.T
    residual = np.abs(F @ P + P @ F.T + W).max()
    assert residual <= 1e-13 * np.abs(F).max() * np.abs(P).max(), residual
    np.testing.assert_allclose(P, scipy.linalg.solve_continuous_lyapunov(F, -W), rtol=1e-11, atol=1e-14)


def test_kalman_filter_default_prior_is_the_shaping_start_and_follows_the_parameters():
    model = first_order_with_ou_input(1.3, 0.4, 0.9)
    H = torch.tensor([[1.0, 0.0]], dtype=F64)
    kf = tl.KalmanFilter(model, H, torch.tensor([[0.1]], dtype=F64))
    assert kf.prior_mode == "model"
    torch.testing.assert_close(kf.initial_state().cov, model.prior_covariance())
    model.shaping.theta = 0.25  # a new shaping filter: P∞_f = q / (2 θ)
    np.testing.assert_allclose(kf.initial_state().cov.detach().numpy(), [[0, 0], [0, 0.9 / 0.5]], atol=1e-13)
    # the explicit alternatives: a diffuse prior, or the whole state's P∞ as a given tensor
    diffuse = tl.KalmanFilter(model, H, torch.tensor([[0.1]], dtype=F64), P0="diffuse")
    assert diffuse.prior_mode == "diffuse"
    torch.testing.assert_close(diffuse.initial_state().cov, 1e4 * torch.eye(2, dtype=F64))
    given = tl.KalmanFilter(model, H, torch.tensor([[0.1]], dtype=F64), P0=model.stationary_covariance().detach())
    assert given.prior_mode == "given"
    with pytest.raises(ValueError, match="P0 must be a tensor, None .* or 'diffuse', got 'steady'"):
        tl.KalmanFilter(model, H, torch.eye(1, dtype=F64), P0="steady")
    with pytest.raises(ValueError, match="the model prior covariance is singular"):
        tl.KalmanFilter(model, H, torch.eye(1, dtype=F64), learn=("P0",))


def test_gradient_of_the_start_wrt_the_shaping_parameters():
    q = 0.9
    model = first_order_with_ou_input(1.3, 0.4, q)
    raw = model.shaping.parametrizations.theta.original
    P_ff = model.prior_covariance()[1, 1]
    (g_P,) = torch.autograd.grad(P_ff, raw)
    theta = model.shaping.theta
    (g_theta,) = torch.autograd.grad(theta, raw)
    torch.testing.assert_close(g_P, -q / (2 * theta.detach() ** 2) * g_theta, atol=1e-12, rtol=1e-10)


def test_filter_from_the_singular_start_matches_numpy_reference():
    """The seed-003 prior is singular (system rows 0): the filters handle it exactly."""
    rng = np.random.default_rng(0)
    system = tl.models.mass_spring_damper(m=1.0, k=2.0, c=0.5, dtype=F64)
    model = tl.models.shaped(system, tl.models.ornstein_uhlenbeck(0.7, 1.5, dtype=F64))
    H = np.array([[1.0, 0.0, 0.0]])
    R = np.array([[0.05]])
    T = 15
    dt = rng.exponential(0.4, size=T)
    y = rng.standard_normal((T, 1))
    y[[3, 4, 9]] = np.nan
    u = rng.standard_normal((T, 1))
    F, L, Qc, B = (x.detach().numpy() for x in (model.F, model.L, model.Qc, model.B))
    A, Q, G = scipy_discretize(F, L, Qc, np.asarray(dt), B)
    P0 = model.prior_covariance().detach().numpy()
    ref = numpy_kalman_filter(y, A, Q, H, R, np.zeros(3), P0, c=(G @ u[..., None])[..., 0])
    for kw in ({"algorithm": "sequential"}, {"algorithm": "scan"}, {"algorithm": "square_root"}):
        kf = tl.KalmanFilter(model, torch.tensor(H), torch.tensor(R), **kw)
        out = kf(torch.tensor(y), torch.tensor(dt), u=torch.tensor(u))
        np.testing.assert_allclose(out.mean.detach().numpy(), ref["mean"], atol=1e-9, rtol=0)
        np.testing.assert_allclose(out.cov.detach().numpy(), ref["cov"], atol=1e-9, rtol=0)
        np.testing.assert_allclose(out.log_likelihood.item(), ref["ll"].sum(), atol=1e-9, rtol=0)


def test_batched_shaping_parameters_equal_loop():
    thetas = torch.tensor([0.3, 0.8, 2.0], dtype=F64)
    system = tl.models.ornstein_uhlenbeck(1.0, 1.0, dtype=F64)
    batched = tl.models.shaped(system, tl.models.ornstein_uhlenbeck(thetas, 0.5, dtype=F64))
    P = batched.prior_covariance()
    assert P.shape == (3, 2, 2) and batched.F.shape == (3, 2, 2)
    for i, th in enumerate(thetas.tolist()):
        single = tl.models.shaped(system, tl.models.ornstein_uhlenbeck(th, 0.5, dtype=F64))
        torch.testing.assert_close(P[i], single.prior_covariance(), atol=1e-14, rtol=0)
        torch.testing.assert_close(batched.F[i], single.F, atol=1e-14, rtol=0)


def test_shaped_bad_input():
    system = tl.models.mass_spring_damper(m=1.0, k=2.0, c=0.5, dtype=F64)
    with pytest.raises(TypeError, match="shaping must be an LTISDE"):
        tl.models.shaped(system, "ou")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="C must have"):
        tl.models.shaped(system, tl.models.ornstein_uhlenbeck(1.0, 1.0, dtype=F64), C=torch.ones(2, 1, dtype=F64))
    with pytest.raises(ValueError, match="C is needed"):
        tl.models.shaped(system, tl.models.ornstein_uhlenbeck(1.0, 1.0, dim=2, dtype=F64))
    with pytest.raises(ValueError, match="strictly proper"):
        tl.models.shaped(system, tl.models.from_transfer_function([1.0, 1.0], [1.0, 2.0], dtype=F64))
    unstable = tl.models.shaped(system, tl.models.integrated_wiener(1, 1, dtype=F64))
    with pytest.raises(ValueError, match="Hurwitz"):
        unstable.prior_covariance()
