"""Motion models: closed forms, Stone Soup, scipy and the Bessel-form Matérn kernel as references."""

from __future__ import annotations

import datetime
import io
import math

import mpmath
import numpy as np
import pytest
import scipy.linalg
import scipy.special
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from stonesoup.models.transition.linear import (
    CombinedLinearGaussianTransitionModel,
    ConstantAcceleration,
    ConstantNthDerivative,
    ConstantVelocity,
    KnownTurnRate,
    OrnsteinUhlenbeck,
    Singer,
)
from torch.func import functional_call

import torchsde_lti as tl
from torchsde_lti import models

F64 = torch.float64
RTOL = 1e-10


def np64(x: torch.Tensor) -> np.ndarray:
    return x.detach().to(F64).numpy()


def close(actual: torch.Tensor, expected: np.ndarray, rtol: float = RTOL) -> None:
    expected = np.asarray(expected, dtype=np.float64)
    np.testing.assert_allclose(np64(actual), expected, rtol=rtol, atol=rtol * 1e-3 * max(1.0, np.abs(expected).max()))


def delta(dt: float) -> datetime.timedelta:
    return datetime.timedelta(seconds=dt)


# ----------------------------------------------------------------------------- integrator chains
@pytest.mark.parametrize("dt", [0.01, 0.5, 3.0])
@pytest.mark.parametrize("q", [0.3, 2.0])
def test_constant_velocity_closed_form_and_stone_soup(dt: float, q: float) -> None:
    cv = models.constant_velocity(dim=2, q=q, dtype=F64)
    d = cv(dt)
    A1 = np.array([[1.0, dt], [0.0, 1.0]])
    Q1 = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    close(d.A, scipy.linalg.block_diag(A1, A1))  # state [x, vx, y, vy]
    close(d.Q, scipy.linalg.block_diag(Q1, Q1))
    ss = CombinedLinearGaussianTransitionModel([ConstantVelocity(noise_diff_coeff=q)] * 2)
    close(d.A, ss.matrix(time_interval=delta(dt)))
    close(d.Q, ss.covar(time_interval=delta(dt)))
    np.testing.assert_array_equal(models.position_observation(cv).numpy(), [[1, 0, 0, 0], [0, 0, 1, 0]])


@pytest.mark.parametrize("dt", [0.05, 1.0, 4.0])
def test_constant_acceleration_closed_form_and_stone_soup(dt: float) -> None:
    q = 0.7
    ca = models.constant_acceleration(dim=3, q=q, dtype=F64)
    d = ca(dt)
    A1 = np.array([[1.0, dt, dt**2 / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    Q1 = q * np.array(
        [[dt**5 / 20, dt**4 / 8, dt**3 / 6], [dt**4 / 8, dt**3 / 3, dt**2 / 2], [dt**3 / 6, dt**2 / 2, dt]]
    )
    close(d.A, scipy.linalg.block_diag(A1, A1, A1))
    close(d.Q, scipy.linalg.block_diag(Q1, Q1, Q1))
    ss = ConstantAcceleration(noise_diff_coeff=q)
    close(d.Q[:3, :3], ss.covar(time_interval=delta(dt)))
    assert ca.position_indices == (0, 3, 6)


@pytest.mark.parametrize("order", [1, 2, 4, 5])
def test_integrated_wiener_any_order(order: int) -> None:
    q, dt = 1.7, 0.8
    d = models.integrated_wiener(order, dim=1, q=q, dtype=F64)(dt)
    if order == 1:  # Brownian motion
        close(d.A, [[1.0]])
        close(d.Q, [[q * dt]])
        return
    ss = ConstantNthDerivative(constant_derivative=order - 1, noise_diff_coeff=q)
    close(d.A, ss.matrix(time_interval=delta(dt)))
    close(d.Q, ss.covar(time_interval=delta(dt)))


# ----------------------------------------------------------------------------- Singer / OU family
def singer_closed_form(alpha: float, q: float, T: float) -> tuple[np.ndarray, np.ndarray]:
    """Singer (1970) transition and noise covariance (spectral density q), evaluated in mpmath."""
    with mpmath.workdps(50):
        a, q, T = mpmath.mpf(alpha), mpmath.mpf(q), mpmath.mpf(T)
        e1, e2, aT = mpmath.exp(-a * T), mpmath.exp(-2 * a * T), a * T
        A = [[1, T, (aT - 1 + e1) / a**2], [0, 1, (1 - e1) / a], [0, 0, e1]]
        q11 = q / (2 * a**5) * (1 - e2 + 2 * aT + 2 * aT**3 / 3 - 2 * aT**2 - 4 * aT * e1)
        q12 = q / (2 * a**4) * (e2 + 1 - 2 * e1 + 2 * aT * e1 - 2 * aT + aT**2)
        q13 = q / (2 * a**3) * (1 - e2 - 2 * aT * e1)
        q22 = q / (2 * a**3) * (4 * e1 - 3 - e2 + 2 * aT)
        q23 = q / (2 * a**2) * (e2 + 1 - 2 * e1)
        q33 = q / (2 * a) * (1 - e2)
        Q = [[q11, q12, q13], [q12, q22, q23], [q13, q23, q33]]
        return np.array(A, dtype=float), np.array(Q, dtype=float)


@pytest.mark.parametrize("alpha,dt", [(0.05, 0.3), (0.5, 1.0), (2.0, 0.1), (3.0, 5.0)])
def test_singer_closed_form_and_stone_soup(alpha: float, dt: float) -> None:
    q = 1.3
    d = models.singer(alpha, q, dim=2, dtype=F64)(dt)
    A1, Q1 = singer_closed_form(alpha, q, dt)
    close(d.A, scipy.linalg.block_diag(A1, A1))
    close(d.Q, scipy.linalg.block_diag(Q1, Q1))
    ss = Singer(damping_coeff=alpha, noise_diff_coeff=q)
    close(d.A[:3, :3], ss.matrix(time_interval=delta(dt)))
    close(d.Q[:3, :3], ss.covar(time_interval=delta(dt)))


def integrated_ou_closed_form(k: float, q: float, T: float) -> tuple[np.ndarray, np.ndarray]:
    with mpmath.workdps(50):
        k, q, T = mpmath.mpf(k), mpmath.mpf(q), mpmath.mpf(T)
        e1, e2 = mpmath.exp(-k * T), mpmath.exp(-2 * k * T)
        A = [[1, (1 - e1) / k], [0, e1]]
        q11 = q / k**2 * (T - 2 * (1 - e1) / k + (1 - e2) / (2 * k))
        q12 = q / k * ((1 - e1) / k - (1 - e2) / (2 * k))
        q22 = q * (1 - e2) / (2 * k)
        return np.array(A, dtype=float), np.array([[q11, q12], [q12, q22]], dtype=float)


@pytest.mark.parametrize("k,dt", [(0.02, 0.5), (0.7, 1.0), (4.0, 3.0)])
def test_integrated_ou_closed_form_and_stone_soup(k: float, dt: float) -> None:
    q = 0.4
    d = models.integrated_ou(k, q, dim=2, dtype=F64)(dt)
    A1, Q1 = integrated_ou_closed_form(k, q, dt)
    close(d.A, scipy.linalg.block_diag(A1, A1))
    close(d.Q, scipy.linalg.block_diag(Q1, Q1))
    ss = OrnsteinUhlenbeck(damping_coeff=k, noise_diff_coeff=q)
    close(d.A[:2, :2], ss.matrix(time_interval=delta(dt)))
    close(d.Q[:2, :2], ss.covar(time_interval=delta(dt)))


@pytest.mark.parametrize("theta,dt", [(0.1, 0.2), (1.5, 1.0), (10.0, 2.0)])
def test_ornstein_uhlenbeck_closed_form(theta: float, dt: float) -> None:
    q = 2.5
    ou = models.ornstein_uhlenbeck(theta, q, dim=3, dtype=F64)
    d = ou(dt)
    close(d.A, math.exp(-theta * dt) * np.eye(3))
    close(d.Q, q * -math.expm1(-2 * theta * dt) / (2 * theta) * np.eye(3))
    close(ou.stationary_covariance(), q / (2 * theta) * np.eye(3))


# ----------------------------------------------------------------------------- Matérn
def matern_bessel(nu: float, ell: float, var: float, tau: np.ndarray) -> np.ndarray:
    """General Matérn covariance via the modified Bessel function K_ν (scipy)."""
    r = np.sqrt(2 * nu) * np.abs(tau) / ell
    return var * 2 ** (1 - nu) / scipy.special.gamma(nu) * r**nu * scipy.special.kv(nu, r)


@pytest.mark.parametrize("nu", [0.5, 1.5, 2.5])
@pytest.mark.parametrize("ell,var", [(0.4, 1.0), (2.0, 3.5)])
def test_matern_kernel_from_state_space(nu: float, ell: float, var: float) -> None:
    gp = models.matern(nu, lengthscale=ell, variance=var, dtype=F64)
    taus = np.array([0.01, 0.1, 0.5, 1.0, 2.5, 6.0])
    P_inf = gp.stationary_covariance()
    A = gp.transition_matrix(torch.as_tensor(taus))  # (6, m, m)
    k_sde = (A @ P_inf)[:, 0, 0]  # H expm(Fτ) P∞ Hᵀ
    close(k_sde, matern_bessel(nu, ell, var, taus))
    close(P_inf[0, 0], var)
    close(gp.kernel(torch.as_tensor(taus, dtype=F64)), matern_bessel(nu, ell, var, taus))
    # Q over a step is P∞ − A P∞ Aᵀ for the stationary process (scipy expm reference)
    F = np64(gp.F)
    P = np64(P_inf)
    A1 = scipy.linalg.expm(F * 0.7)
    close(gp(0.7).Q, P - A1 @ P @ A1.T, rtol=1e-9)


def test_matern_stationary_covariance_closed_forms() -> None:
    ell, var = 0.8, 2.0
    lam3, lam5 = math.sqrt(3) / ell, math.sqrt(5) / ell
    close(models.matern(1.5, ell, var, dtype=F64).stationary_covariance(), np.diag([var, lam3**2 * var]))
    kappa = lam5**2 * var / 3
    P5 = np.array([[var, 0, -kappa], [0, kappa, 0], [-kappa, 0, lam5**4 * var]])
    close(models.matern(2.5, ell, var, dtype=F64).stationary_covariance(), P5)
    m12 = models.matern(0.5, ell, var, dtype=F64)
    close(m12.F, [[-1 / ell]])
    close(m12.Qc, [[2 * var / ell]])


# ----------------------------------------------------------------------------- ODE systems
def test_companion_reproduces_mass_spring_damper() -> None:
    m, k, c = 2.0, 3.0, 0.5
    msd = models.mass_spring_damper(m, k, c, dtype=F64)
    comp = models.companion([k, c, m], dtype=F64)
    close(msd.F, [[0.0, 1.0], [-k / m, -c / m]])
    close(msd.B, [[0.0], [1.0 / m]])
    close(comp.F, np64(msd.F), rtol=1e-15)
    close(comp.B, np64(msd.B), rtol=1e-15)
    np.testing.assert_array_equal(msd.C.numpy(), [[1.0, 0.0]])
    np.testing.assert_array_equal(comp.C.numpy(), [[1.0, 0.0]])


def test_companion_third_order_hand_derived() -> None:
    a0, a1, a2, a3 = 6.0, 11.0, 6.0, 2.0  # 2 y''' + 6 y'' + 11 y' + 6 y = u
    comp = models.companion([a0, a1, a2, a3], q=0.5, dtype=F64)
    close(comp.F, [[0, 1, 0], [0, 0, 1], [-3.0, -5.5, -3.0]])
    close(comp.B, [[0], [0], [0.5]])
    np.testing.assert_array_equal(comp.C.numpy(), [[1.0, 0.0, 0.0]])
    assert comp.state_dim == 3 and comp.input_dim == 1


def test_mass_spring_damper_discretisation_vs_scipy() -> None:
    m, k, c, q, dt = 1.5, 4.0, 0.3, 0.2, 0.6
    msd = models.mass_spring_damper(m, k, c, q=q, dtype=F64)
    F = np.array([[0.0, 1.0], [-k / m, -c / m]])
    B = np.array([[0.0], [1.0 / m]])
    Z = np.zeros((3, 3))
    Z[:2, :2], Z[:2, 2:] = F * dt, B * dt
    E = scipy.linalg.expm(Z)
    C = np.block([[F, q * B @ B.T], [np.zeros((2, 2)), -F.T]]) * dt
    V = scipy.linalg.expm(C)
    d = msd(dt)
    close(d.A, E[:2, :2])
    close(d.G, E[:2, 2:])
    close(d.Q, V[:2, 2:] @ V[:2, :2].T)


# ----------------------------------------------------------------------------- composition
def test_block_diag_and_position_observation() -> None:
    cv = models.constant_velocity(dim=1, q=0.5, dtype=F64)
    msd = models.mass_spring_damper(1.0, 2.0, 0.5, dtype=F64)
    gp = models.matern(1.5, 1.0, 1.0, dtype=F64)
    bd = models.block_diag(cv, msd, gp)
    parts = [cv.matrices(), msd.matrices(), gp.matrices()]
    for name in ("F", "L", "Qc"):
        close(getattr(bd, name), scipy.linalg.block_diag(*(np64(getattr(p, name)) for p in parts)), rtol=0)
    close(bd.B, np.array([[0, 0, 0, 1.0, 0, 0]]).T, rtol=0)
    assert bd.position_indices == (0, 2, 4)
    np.testing.assert_array_equal(models.position_observation(bd).numpy()[:, [0, 2, 4]], np.eye(3))
    assert models.block_diag(cv, gp).B is None
    d = bd(0.3)
    close(d.Q[:2, :2], np64(cv(0.3).Q), rtol=1e-14)
    # parameters of every part are learned jointly
    names = {n for n, _ in bd.named_parameters()}
    assert "parts.2.parametrizations.lengthscale.original" in names and len(names) == 7


# ----------------------------------------------------------------------------- parameters
ALL_MODELS = {
    "cv": lambda: models.constant_velocity(2, 0.5, dtype=F64),
    "iw": lambda: models.integrated_wiener(3, 1, 0.5, dtype=F64),
    "singer": lambda: models.singer(0.8, 1.2, dim=2, dtype=F64),
    "iou": lambda: models.integrated_ou(0.6, 0.9, dim=2, dtype=F64),
    "ou": lambda: models.ornstein_uhlenbeck(1.1, 0.3, dim=2, dtype=F64),
    "matern": lambda: models.matern(2.5, 0.9, 1.7, dtype=F64),
    "msd": lambda: models.mass_spring_damper(1.3, 2.0, 0.4, q=0.6, dtype=F64),
    "companion": lambda: models.companion([1.0, 0.5, 2.0, 1.5], q=0.3, dtype=F64),
    "block": lambda: models.block_diag(
        models.constant_velocity(1, 0.5, dtype=F64), models.matern(1.5, 0.9, 1.0, dtype=F64)
    ),
    "turn": lambda: models.turn_rate(-0.07, 0.8, dtype=F64),
    "aircraft": lambda: models.block_diag(  # horizontal turn + vertical CV, their own noise
        models.turn_rate(0.03, 17.0, dtype=F64), models.constant_velocity(1, 0.27, dtype=F64)
    ),
}


def test_learned_scalars_are_readable_and_assignable() -> None:
    s = models.singer(0.8, 1.2, dim=2, dtype=F64)
    assert {n for n, _ in s.named_parameters()} == {"parametrizations.alpha.original", "parametrizations.q.original"}
    assert abs(s.alpha.item() - 0.8) < 1e-15 and abs(s.q.item() - 1.2) < 1e-15
    s.q = 3.0
    close(s.Qc, 3.0 * np.eye(2), rtol=1e-15)
    with pytest.raises(ValueError, match="q"):
        s.q = -1.0
    with pytest.raises(AttributeError, match="alpha"):
        s.F = torch.eye(6, dtype=F64)
    free = s.to_free(learn=("F",))
    assert isinstance(free, tl.LTISDE)
    close(free.F, np64(s.F), rtol=0)


@pytest.mark.parametrize("name", sorted(ALL_MODELS))
def test_gradcheck_reaches_every_raw_parameter(name: str) -> None:
    model = ALL_MODELS[name]()
    assert isinstance(model, tl.LTISDE)
    names = [n for n, _ in model.named_parameters()]
    values = tuple(p.detach().clone().requires_grad_(True) for _, p in model.named_parameters())
    dt = torch.tensor([0.4, 1.3], dtype=F64)

    def fn(*raw: torch.Tensor):
        d = functional_call(model, dict(zip(names, raw)), (dt,))
        return tuple(x for x in d if x is not None)

    assert torch.autograd.gradcheck(fn, values)
    model.zero_grad()
    d = model(dt)
    (d.A.sum() + d.Q.sum() + (0 if d.G is None else d.G.sum())).backward()
    for n, p in model.named_parameters():
        assert p.grad is not None and bool(p.grad.abs().sum() > 0), n


@pytest.mark.parametrize("name", sorted(ALL_MODELS))
def test_state_dict_round_trip_and_float32(name: str) -> None:
    src = ALL_MODELS[name]()
    with torch.no_grad():
        for p in src.parameters():
            p.add_(0.37)  # move away from the construction values
    dst = ALL_MODELS[name]()
    buf = io.BytesIO()
    torch.save(src.state_dict(), buf)
    buf.seek(0)
    dst.load_state_dict(torch.load(buf))
    for a, b in zip(src.matrices(), dst.matrices()):
        assert (a is None and b is None) or torch.equal(a, b)
    m64 = src.matrices()
    src32 = src.to(torch.float32)
    m32 = src32.matrices()
    for a, b in zip(m64, m32):
        if a is not None:
            assert b.dtype == torch.float32
            np.testing.assert_allclose(np64(b), np64(a), rtol=1e-5, atol=1e-6)
    d = src32(torch.tensor([0.1, 1.0]))
    assert d.Q.dtype == torch.float32
    assert bool((torch.linalg.eigvalsh(d.Q.double()) > -1e-5 * d.Q.abs().amax()).all())


def test_batched_scalars_equal_loop() -> None:
    alphas = torch.tensor([0.3, 1.0, 2.5], dtype=F64)
    qs = torch.tensor([0.5, 1.0, 2.0], dtype=F64)
    batched = models.singer(alphas, qs, dim=2)
    assert batched.batch_shape == (3,)
    dt = torch.tensor([0.2, 0.7, 1.5], dtype=F64)
    d = batched(dt)
    for i in range(3):
        A1, Q1 = singer_closed_form(float(alphas[i]), float(qs[i]), float(dt[i]))
        close(d.A[i], scipy.linalg.block_diag(A1, A1))
        close(d.Q[i], scipy.linalg.block_diag(Q1, Q1))
    gp = models.matern(1.5, torch.tensor([0.5, 1.0, 2.0], dtype=F64), 1.0)
    P = gp.stationary_covariance()
    assert P.shape == (3, 2, 2)
    close(P[:, 1, 1], (3.0 / np.array([0.5, 1.0, 2.0]) ** 2))


@pytest.mark.parametrize("make", [models.singer, models.integrated_ou], ids=["singer", "integrated_ou"])
def test_batched_noise_with_shared_rate_equals_loop(make) -> None:
    # one shared rate (alpha / k) with a batch of 3 spectral densities q: the batch comes from q only
    rate = 0.8
    qs = torch.tensor([0.5, 1.0, 2.0], dtype=F64)
    closed = singer_closed_form if make is models.singer else integrated_ou_closed_form
    batched = make(rate, qs, dim=2)
    assert batched.batch_shape == (3,)
    dt = torch.tensor([0.2, 0.7, 1.5], dtype=F64)
    d = batched(dt)
    for i in range(3):
        A1, Q1 = closed(rate, float(qs[i]), float(dt[i]))
        close(d.A[i], scipy.linalg.block_diag(A1, A1))
        close(d.Q[i], scipy.linalg.block_diag(Q1, Q1))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-60, 60, allow_nan=False), min_size=4, max_size=4))
def test_positive_for_arbitrary_raw_values(raws: list[float]) -> None:
    msd = models.mass_spring_damper(1.0, 1.0, 1.0, q=1.0, dtype=F64)
    with torch.no_grad():
        for name, raw in zip(("m", "k", "c", "q"), raws):
            msd.parametrizations[name].original.fill_(raw)
    for name in ("m", "k", "c", "q"):
        assert getattr(msd, name).item() > 0
    assert msd.Qc.item() > 0
    # positive m, k, c: the oscillator is stable (trace < 0, det > 0)
    F = np64(msd.F)
    assert np.trace(F) < 0 and np.linalg.det(F) > 0


@pytest.mark.parametrize("nu", [0.5, 1.5, 2.5])
@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("raws", [(-20.0, 100.0), (-1e6, 1e6), (1e6, -1e6), (0.0, 3e30)])
def test_matern_matrices_finite_for_extreme_raw_values(
    nu: float, dtype: torch.dtype, raws: tuple[float, float]
) -> None:
    """Qc = c σ² λ^{2ν} stays finite (and positive) for any finite raw lengthscale and variance:
    float32 ν = 5/2 at the lengthscale floor overflowed to Inf."""
    gp = models.matern(nu, dtype=dtype)
    with torch.no_grad():
        gp.parametrizations.lengthscale.original.fill_(raws[0])
        gp.parametrizations.variance.original.fill_(raws[1])
    mats = gp.matrices()
    assert bool(torch.isfinite(mats.F).all()) and bool(torch.isfinite(mats.Qc).all()) and mats.Qc.item() > 0


def test_scalars_stay_positive_under_large_learning_rate() -> None:
    s = models.singer(0.8, 1.2, dim=1, dtype=F64)
    opt = torch.optim.SGD(s.parameters(), lr=50.0)
    for _ in range(100):
        loss = (s.alpha + 3.0) ** 2 + (s.q + 3.0) ** 2  # minimum at negative values
        opt.zero_grad()
        loss.backward()
        opt.step()
        assert s.alpha.item() > 0 and s.q.item() > 0
        assert torch.isfinite(s(1.0).Q).all()


# ----------------------------------------------------------------------------- turning


def turn_noise_closed_form(omega: float, q: float, dt: float) -> np.ndarray:
    """The exact Q of the coordinated turn, [x, vx, y, vy] (derived by hand: the docstring's forms)."""
    s, c = math.sin(omega * dt), math.cos(omega * dt)
    pp, pv, cross = 2 * q * (dt - s / omega) / omega**2, q * (1 - c) / omega**2, q * (dt - s / omega) / omega
    return np.array([[pp, pv, 0.0, cross], [pv, q * dt, -cross, 0.0], [0.0, -cross, pp, pv], [cross, 0.0, pv, q * dt]])


@pytest.mark.parametrize("omega", [0.1, -0.03, 1.5, -2.0])
@pytest.mark.parametrize("dt", [0.5, 2.0, 30.0])
def test_turn_rate_transition_is_stone_soups_known_turn_rate(omega: float, dt: float) -> None:
    d = models.turn_rate(omega, 0.6, dtype=F64)(dt)
    ss = KnownTurnRate(turn_noise_diff_coeffs=np.array([0.6, 0.6]), turn_rate=omega)
    np.testing.assert_allclose(np64(d.A), ss.matrix(time_interval=delta(dt)), rtol=0, atol=1e-12)


@pytest.mark.parametrize("omega,dt", [(0.1, 2.0), (-0.1, 2.0), (0.02, 15.0), (1.3, 0.7), (-0.5, 9.0)])
def test_turn_rate_noise_is_the_exact_integral(omega: float, dt: float) -> None:
    """Q against quadrature of ∫ e^{Fτ} L Qc Lᵀ e^{Fτ}ᵀ dτ (scipy) and the closed form; Stone Soup's
    KnownTurnRate covariance is the constant-velocity one and lacks the cross terms."""
    from scipy.integrate import quad_vec

    q = 0.8
    model = models.turn_rate(omega, q, dtype=F64)
    F, L = np64(model.F), np64(model.L)
    quad, _ = quad_vec(lambda t: (E := scipy.linalg.expm(F * t) @ L) @ E.T * q, 0.0, dt, epsabs=1e-14, epsrel=1e-13)
    Q = np64(model(dt).Q)
    np.testing.assert_allclose(Q, quad, rtol=1e-9, atol=1e-12 * np.abs(quad).max())
    np.testing.assert_allclose(Q, turn_noise_closed_form(omega, q, dt), rtol=1e-9, atol=1e-12 * np.abs(quad).max())
    if (omega, dt) == (0.1, 2.0):  # the figure: ±0.133 where Stone Soup has 0 (here q = 0.8)
        assert Q[0, 3] / q == pytest.approx(0.1331, abs=5e-4) and Q[1, 2] / q == pytest.approx(-0.1331, abs=5e-4)
        ss = KnownTurnRate(turn_noise_diff_coeffs=np.array([q, q]), turn_rate=omega).covar(time_interval=delta(dt))
        assert ss[0, 3] == 0.0 and ss[1, 2] == 0.0


def turn_closed_form_mp(omega: float, q: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """A and Q of the coordinated turn in 50-digit arithmetic (mpmath): no cancellation at small ω."""
    with mpmath.workdps(50):
        w, h, q_ = mpmath.mpf(omega), mpmath.mpf(dt), mpmath.mpf(q)
        if w == 0:
            sw, cw, dw = h, mpmath.mpf(0), h**3 / 6  # sin(ωh)/ω, (1 - cos ωh)/ω, (h - sin(ωh)/ω)/ω² at ω = 0
            cos_, sin_ = mpmath.mpf(1), mpmath.mpf(0)
            one_c = h**2 / 2  # (1 - cos ωh)/ω²
        else:
            sw, cw = mpmath.sin(w * h) / w, (1 - mpmath.cos(w * h)) / w
            dw, cos_, sin_ = (h - mpmath.sin(w * h) / w) / w**2, mpmath.cos(w * h), mpmath.sin(w * h)
            one_c = (1 - mpmath.cos(w * h)) / w**2
        A = [[1, sw, 0, -cw], [0, cos_, 0, -sin_], [0, cw, 1, sw], [0, sin_, 0, cos_]]
        pp, pv, cross = 2 * q_ * dw, q_ * one_c, q_ * dw * w
        Q = [[pp, pv, 0, cross], [pv, q_ * h, -cross, 0], [0, -cross, pp, pv], [cross, 0, pv, q_ * h]]
        return np.array(A, dtype=float), np.array(Q, dtype=float)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_turn_rate_tends_to_constant_velocity_as_omega_goes_to_zero(dtype: torch.dtype) -> None:
    """ω → 0 is continuous (no 1/ω is evaluated): A and Q match the closed form (50 digits) at
    tiny ω, equal constant velocity at ω = 0, and stay PSD in float32."""
    tol = 2e-6 if dtype == torch.float32 else 1e-12
    for dt in (0.5, 10.0, 120.0):
        for omega in (1e-3, -1e-5, 1e-8, 0.0, -1e-12):
            d = models.turn_rate(omega, 0.9, dtype=dtype)(torch.tensor(dt, dtype=dtype))
            A, Q = turn_closed_form_mp(omega, 0.9, dt)
            np.testing.assert_allclose(np64(d.A), A, rtol=0, atol=tol * np.abs(A).max())
            np.testing.assert_allclose(np64(d.Q), Q, rtol=0, atol=tol * np.abs(Q).max())
            assert bool((torch.linalg.eigvalsh(d.Q.double()) > -tol * d.Q.abs().amax()).all())
    dt = torch.tensor([0.5, 10.0, 120.0], dtype=F64)
    exact, cv = models.turn_rate(0.0, 0.9, dtype=F64)(dt), models.constant_velocity(2, 0.9, dtype=F64)(dt)
    torch.testing.assert_close(exact.A, cv.A, rtol=0, atol=1e-13)
    torch.testing.assert_close(exact.Q, cv.Q, rtol=1e-12, atol=1e-12)


def test_turn_rate_gradients_at_zero_and_batched_rates_equal_loop() -> None:
    """gradcheck through ω at 0 (straight flight) and ±; left/straight/right as one batched module."""
    dt = torch.tensor([0.7, 4.0], dtype=F64)
    for w0 in (0.0, 0.2, -0.2):
        omega = torch.tensor(w0, dtype=F64, requires_grad=True)

        def fn(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            model = models.turn_rate(0.0, 0.5, dtype=F64)
            d = functional_call(model, {"parametrizations.omega.original": w}, (dt,))
            return d.A, d.Q

        assert torch.autograd.gradcheck(fn, (omega,))
    rates = torch.tensor([0.05, 0.0, -0.05], dtype=F64)
    bank = models.turn_rate(rates, 2.0)
    assert bank.batch_shape == (3,) and bank.omega.dtype == F64
    d = bank(torch.tensor([3.0, 3.0, 3.0], dtype=F64))
    for i, w in enumerate(rates.tolist()):
        one = models.turn_rate(w, 2.0, dtype=F64)(3.0)
        torch.testing.assert_close(d.A[i], one.A, rtol=1e-14, atol=1e-14)
        torch.testing.assert_close(d.Q[i], one.Q, rtol=1e-13, atol=1e-13)
    bank.omega = torch.tensor([0.1, 0.0, -0.1])
    assert bank.omega.tolist() == pytest.approx([0.1, 0.0, -0.1])
    assert models.position_observation(bank).tolist() == [[1, 0, 0, 0], [0, 0, 1, 0]]


def test_aircraft_composition_keeps_horizontal_and_vertical_noise_apart() -> None:
    """block_diag(turn_rate, constant_velocity(1)): [x, vx, y, vy, z, vz], the horizontal turn and
    the vertical CV with their own q; positions (0, 2, 4)."""
    model = ALL_MODELS["aircraft"]()
    d = model(5.0)
    turn, vert = models.turn_rate(0.03, 17.0, dtype=F64)(5.0), models.constant_velocity(1, 0.27, dtype=F64)(5.0)
    torch.testing.assert_close(d.A, torch.block_diag(turn.A, vert.A))
    torch.testing.assert_close(d.Q, torch.block_diag(turn.Q, vert.Q))
    assert model.position_indices == (0, 2, 4)


# ----------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "make,match",
    [
        (lambda: models.constant_velocity(2, 0.0), "q"),
        (lambda: models.constant_velocity(2, -1.0), "q"),
        (lambda: models.constant_velocity(0, 1.0), "dim"),
        (lambda: models.constant_velocity(1.5, 1.0), "dim"),
        (lambda: models.integrated_wiener(0, 1, 1.0), "order"),
        (lambda: models.singer(-0.1, 1.0), "alpha"),
        (lambda: models.singer(0.1, float("nan")), "q"),
        (lambda: models.integrated_ou(0.0, 1.0), "k"),
        (lambda: models.ornstein_uhlenbeck(-2.0, 1.0), "theta"),
        (lambda: models.matern(2.0, 1.0, 1.0), "nu"),
        (lambda: models.matern("3/2", 1.0, 1.0), "nu"),
        (lambda: models.matern(1.5, 0.0, 1.0), "lengthscale"),
        (lambda: models.matern(1.5, 1.0, -1.0), "variance"),
        (lambda: models.mass_spring_damper(0.0, 1.0, 1.0), "m"),
        (lambda: models.mass_spring_damper(1.0, 1.0, -1.0), "c"),
        (lambda: models.companion([1.0]), "a"),
        (lambda: models.companion([1.0, 2.0, 0.0]), "a"),
        (lambda: models.block_diag(), "sdes"),
        (lambda: models.block_diag(models.constant_velocity(1, 1.0), torch.eye(2)), "sdes"),
        (lambda: models.singer(torch.tensor([0.1, 0.2]), torch.tensor([1.0, 2.0, 3.0])), "alpha.*q"),
        (lambda: models.companion(torch.ones(2, 3), q=torch.ones(3)), "a.*q"),
        (lambda: models.turn_rate(float("nan"), 1.0), "omega"),
        (lambda: models.turn_rate(0.1, 0.0), "q"),
        (lambda: models.turn_rate(torch.zeros(2), torch.ones(3)), "omega.*q"),
    ],
)
def test_bad_input_raises_value_error(make, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make()


def test_position_observation_needs_positions() -> None:
    sde = tl.LTISDE(-torch.eye(2), torch.eye(2), torch.eye(2))
    with pytest.raises(ValueError, match="position"):
        models.position_observation(sde)


def test_moored_discretisation_closed_form() -> None:
    k, q, h = 0.3, 0.02, 7.0
    sde = tl.models.moored(k=torch.tensor(k, dtype=torch.float64), q=torch.tensor(q, dtype=torch.float64))
    with torch.no_grad():
        d = sde(torch.tensor(h, dtype=torch.float64))
    F = np.array([[0, 1], [0, -k]])
    A1 = scipy.linalg.expm(F * h)
    Q1 = np.array([[q * h, 0], [0, 0]])  # noise enters the position only: Q = q h on x
    A = np.kron(np.eye(2), A1)
    np.testing.assert_allclose(d.A.numpy(), A, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(d.Q.numpy(), np.kron(np.eye(2), Q1), rtol=1e-10, atol=1e-14)
    assert sde.position_indices == (0, 2)


def test_block_diag_starts_each_part_from_its_own_prior() -> None:
    """Independent parts observed separately: the joint log-likelihood of block_diag equals the
    sum of the parts' own (each filter from its model's default prior: a shaped part's
    steady-state start, a stationary part's P∞, a non-Hurwitz part diffuse)."""
    F64 = torch.float64
    M = tl.models
    g = torch.Generator().manual_seed(0)
    y, dt = torch.randn(25, 2, generator=g, dtype=F64), torch.rand(25, generator=g, dtype=F64)
    R = torch.tensor([[0.1]], dtype=F64)
    H1 = torch.tensor([[1.0, 0.0]], dtype=F64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64)
    gp = M.matern(1.5, 1.0, 1.0, dtype=F64)
    for first in (
        M.shaped(M.ornstein_uhlenbeck(1.3, 1.0, dtype=F64), M.ornstein_uhlenbeck(0.4, 0.9, dtype=F64)),
        M.constant_velocity(1, 1.0, dtype=F64),
    ):
        with torch.no_grad():
            parts = tl.KalmanFilter(first, H1, R)(y[:, :1], dt).log_likelihood
            parts = parts + tl.KalmanFilter(gp, H1, R)(y[:, 1:], dt).log_likelihood
            joint = tl.KalmanFilter(M.block_diag(first, gp), H, 0.1 * torch.eye(2, dtype=F64))(y, dt).log_likelihood
        torch.testing.assert_close(joint, parts, rtol=1e-12, atol=1e-10)


def test_compositions_check_the_parts_batch_shapes() -> None:
    M = tl.models
    with pytest.raises(ValueError, match="batch shapes do not broadcast"):
        M.block_diag(M.singer(torch.ones(3), 1.0), M.constant_velocity(1, torch.ones(2)))
    with pytest.raises(ValueError, match="batch shapes do not broadcast"):
        M.shaped(M.ornstein_uhlenbeck(torch.ones(3), 1.0), M.ornstein_uhlenbeck(torch.ones(2), 1.0))


def test_unknown_option_raises_type_error() -> None:
    """A misspelt or unsupported option (``method=`` belongs to the SDE and the filter) is
    refused, naming the options a factory takes; it was silently ignored."""
    for make in (
        lambda **o: models.singer(0.6, 2.0, dim=2, **o),
        lambda **o: models.constant_velocity(2, **o),
        lambda **o: models.matern(1.5, 1.0, 1.0, **o),
        lambda **o: models.from_transfer_function([1.0], [1.0, 2.0, 3.0], 1.0, **o),
    ):
        with pytest.raises(TypeError, match=r"unknown model options \['method'\].*'validate_args'"):
            make(method="matrix_exp")
        assert make(dtype=torch.float64).matrices().F.dtype == torch.float64


def test_prior_covariance_refuses_a_bad_diffuse_variance() -> None:
    model = tl.models.block_diag(tl.models.constant_velocity(1, 1.0), tl.models.matern(1.5, 1.0, 1.0))
    for bad in (-1.0, 0.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="diffuse_variance"):
            model.prior_covariance(diffuse_variance=bad)


# ----------------------------------------------------------------------------- configs


def _filter_of(experiment: str) -> tl.KalmanFilter | tl.IMMFilter:
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    conf = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("train", overrides=[f"experiment={experiment}"])
    return instantiate(cfg.filter)


def test_turning_bank_and_aircraft_axes_from_the_configs() -> None:
    """model=imm_turn: left / straight / right modes (turn_rate with ω of both signs and constant
    velocity); model=aircraft: horizontal and vertical constant velocity with their own q."""
    imm = _filter_of("flights_turn")
    assert isinstance(imm, tl.IMMFilter) and imm.mode_names == ("left", "straight", "right")
    left, straight, right = (mode.sde for mode in imm.modes())
    from torchsde_lti.models._turning import TurnRate

    assert isinstance(left, TurnRate) and isinstance(right, TurnRate) and left.omega.item() > 0 > right.omega.item()
    assert torch.equal(straight.F, models.constant_velocity(2).F.to(straight.F.dtype))
    kf = _filter_of("flights_3d_axes")
    horizontal, vertical = kf.sde.parts
    assert horizontal.dim == 2 and vertical.dim == 1 and kf.sde.position_indices == (0, 2, 4)
    assert horizontal.q.item() != vertical.q.item()
    assert {n for n, _ in kf.sde.named_parameters()} == {
        "parts.0.parametrizations.q.original",
        "parts.1.parametrizations.q.original",
    }
