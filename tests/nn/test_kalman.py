"""KalmanFilter module: against numpy/scipy references (discretisation by scipy.linalg.expm)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch
from torch.func import functional_call

import torchsde_lti as tl
from tests.reference import numpy_kalman_filter, numpy_rts, scipy_discretize

F64 = torch.float64


def damped_model(with_input=True):
    """A Hurwitz 4-state model (two damped oscillators) with inputs."""
    F = np.array([[0.0, 1.0, 0, 0], [-2.0, -0.7, 0.1, 0], [0, 0, 0.0, 1.0], [0, 0.2, -1.0, -0.4]])
    L = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.3, 1.0]])
    Qc = np.array([[0.5, 0.1], [0.1, 0.8]])
    B = np.array([[0.0], [1.0], [0.0], [0.5]]) if with_input else None
    return F, L, Qc, B


def make_sde(F, L, Qc, B=None, learn=("F", "Qc")):
    t = lambda x: None if x is None else torch.as_tensor(x, dtype=F64)  # noqa: E731
    return tl.LTISDE(t(F), t(L), t(Qc), t(B), learn=learn)


H_NP = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.5]])
R_NP = np.array([[0.3, 0.05], [0.05, 0.2]])


def test_filter_and_smoother_match_numpy_with_irregular_dt_missing_and_inputs():
    rng = np.random.default_rng(0)
    F, L, Qc, B = damped_model()
    Bt, T = 3, 25
    dt = rng.exponential(0.4, size=(Bt, T))
    dt[:, 0] = 0.0
    y = rng.standard_normal((Bt, T, 2))
    y[rng.random((Bt, T)) < 0.2] = np.nan
    y[0, 3, 1] = np.nan
    u = rng.standard_normal((Bt, T, 1))
    m0 = np.array([0.5, 0.0, -0.2, 0.1])
    P0 = np.diag([1.0, 2.0, 0.5, 1.5])
    kf = tl.KalmanFilter(
        make_sde(F, L, Qc, B), torch.tensor(H_NP), torch.tensor(R_NP), m0=torch.tensor(m0), P0=torch.tensor(P0)
    )
    out = kf(torch.tensor(y), torch.tensor(dt), u=torch.tensor(u))
    sm = kf.smooth(out)
    A, Q, G = scipy_discretize(F, L, Qc, dt, B)
    for b in range(Bt):
        c = (G[b] @ u[b][..., None])[..., 0]
        ref = numpy_kalman_filter(y[b], A[b], Q[b], H_NP, R_NP, m0, P0, c)
        np.testing.assert_allclose(out.mean[b].detach().numpy(), ref["mean"], atol=1e-9)
        np.testing.assert_allclose(out.cov[b].detach().numpy(), ref["cov"], atol=1e-9)
        np.testing.assert_allclose(out.step_log_likelihood[b].detach().numpy(), ref["ll"], atol=1e-9)
        ms, Ps = numpy_rts(ref["mean"], ref["cov"], ref["pred_mean"], ref["pred_cov"], A[b])
        np.testing.assert_allclose(sm.mean[b].detach().numpy(), ms, atol=1e-9)
        np.testing.assert_allclose(sm.cov[b].detach().numpy(), Ps, atol=1e-9)


def test_default_prior_is_stationary_for_hurwitz_and_diffuse_otherwise():
    F, L, Qc, _ = damped_model(with_input=False)
    kf = tl.KalmanFilter(make_sde(F, L, Qc), torch.tensor(H_NP), torch.tensor(R_NP))
    assert kf.prior_mode == "model"
    P_inf = scipy.linalg.solve_continuous_lyapunov(F, -L @ Qc @ L.T)
    np.testing.assert_allclose(kf.initial_state().cov.detach().numpy(), P_inf, atol=1e-10)
    cv = tl.models.constant_velocity(dim=2, q=1.0, dtype=F64)
    kf2 = tl.KalmanFilter(cv, tl.models.position_observation(cv), 0.1 * torch.eye(2, dtype=F64))
    assert kf2.prior_mode == "diffuse"
    torch.testing.assert_close(kf2.initial_state().cov, kf2.diffuse_variance * torch.eye(4, dtype=F64))


def test_constant_velocity_model_matches_closed_form_reference():
    from tests.reference import cv_matrices

    rng = np.random.default_rng(1)
    q = 0.8
    cv = tl.models.constant_velocity(dim=2, q=q, dtype=F64)
    H = tl.models.position_observation(cv)
    R = torch.tensor(R_NP)
    P0 = 10.0 * torch.eye(4, dtype=F64)
    kf = tl.KalmanFilter(cv, H, R, P0=P0)
    dt = rng.uniform(0.01, 3.0, size=(4, 40))
    y = rng.standard_normal((4, 40, 2)) * 5
    y[:, 10:13] = np.nan
    out = kf(torch.tensor(y), torch.tensor(dt))
    A, Q, _ = cv_matrices(dt, q=q)
    for b in range(4):
        ref = numpy_kalman_filter(y[b], A[b], Q[b], H.numpy(), R_NP, np.zeros(4), P0.numpy())
        np.testing.assert_allclose(out.mean[b].detach().numpy(), ref["mean"], atol=1e-9)
        np.testing.assert_allclose(out.log_likelihood[b].item(), ref["ll"].sum(), atol=1e-9)


def test_gradcheck_wrt_F_Qc_H_R_m0_P0_dt():
    rng = np.random.default_rng(2)
    F, L, Qc, _ = damped_model(with_input=False)
    kf = tl.KalmanFilter(
        make_sde(F, L, Qc, learn=("F", "Qc")),
        torch.tensor(H_NP),
        torch.tensor(R_NP),
        m0=torch.zeros(4, dtype=F64),
        P0=torch.eye(4, dtype=F64),
        learn=("H", "R", "m0", "P0"),
    )
    names = [n for n, _ in kf.named_parameters()]
    assert len(names) == 6, names  # F, Qc, H, R, m0, P0
    y = torch.tensor(rng.standard_normal((2, 4, 2)))
    y[0, 1, 0] = float("nan")
    dt = torch.tensor(rng.uniform(0.1, 1.0, size=(2, 4)), requires_grad=True)
    params = [p.detach().clone().requires_grad_(True) for _, p in kf.named_parameters()]

    def f(dt_, *ps):
        out = functional_call(kf, dict(zip(names, ps)), (y, dt_))
        return out.log_likelihood, out.mean[..., -1, :]

    assert torch.autograd.gradcheck(f, (dt, *params), eps=1e-6, atol=1e-6)


def test_scan_module_equals_sequential_and_batch_equals_loop():
    rng = np.random.default_rng(3)
    F, L, Qc, B = damped_model()
    sde = make_sde(F, L, Qc, B)
    H, R = torch.tensor(H_NP), torch.tensor(R_NP)
    seq = tl.KalmanFilter(sde, H, R, algorithm="sequential")
    par = tl.KalmanFilter(sde, H, R, algorithm="scan")
    y = torch.tensor(rng.standard_normal((2, 3, 11, 2)))
    y[1, 2, 4] = float("nan")
    dt = torch.tensor(rng.exponential(0.5, size=(2, 3, 11)))
    u = torch.tensor(rng.standard_normal((2, 3, 11, 1)))
    a, b = seq(y, dt, u=u), par(y, dt, u=u)
    assert a.mean.shape == (2, 3, 11, 4) and a.log_likelihood.shape == (2, 3)
    for name in ("mean", "cov", "pred_cov", "step_log_likelihood"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=1e-9)
    torch.testing.assert_close(seq.smooth(a).cov, par.smooth(a).cov, rtol=0, atol=1e-9)
    for i in range(2):
        for j in range(3):
            s = seq(y[i, j], dt[i, j], u=u[i, j])
            torch.testing.assert_close(a.mean[i, j], s.mean, rtol=0, atol=1e-12)
            torch.testing.assert_close(a.log_likelihood[i, j], s.log_likelihood, rtol=0, atol=1e-12)


def test_parameter_batch_lines_up_with_series_batch():
    """SDE with a batch of 3 models (F (3, n, n)) and dt (3, T): model s filters track s."""
    rng = np.random.default_rng(4)
    F, L, Qc, _ = damped_model(with_input=False)
    Fs = np.stack([F, 0.5 * F, 2.0 * F])
    sde = make_sde(Fs, L, Qc)
    H, R = torch.tensor(H_NP), torch.tensor(R_NP)
    kf = tl.KalmanFilter(sde, H, R, P0=torch.eye(4, dtype=F64))
    T = 3  # T equal to the batch size on purpose: a wrong alignment would still broadcast
    y = torch.tensor(rng.standard_normal((3, T, 2)))
    dt = torch.tensor(rng.uniform(0.1, 1.0, size=(3, T)))
    out = kf(y, dt)
    for s in range(3):
        single = tl.KalmanFilter(make_sde(Fs[s], L, Qc), H, R, P0=torch.eye(4, dtype=F64))(y[s], dt[s])
        torch.testing.assert_close(out.mean[s], single.mean, rtol=0, atol=1e-12)
    # a shared dt grid (T,) is filtered by all three models
    out2 = kf(y, dt[0])
    single = tl.KalmanFilter(make_sde(Fs[1], L, Qc), H, R, P0=torch.eye(4, dtype=F64))(y[1], dt[0])
    torch.testing.assert_close(out2.mean[1], single.mean, rtol=0, atol=1e-12)


def test_forecast_matches_scipy_moments():
    rng = np.random.default_rng(5)
    F, L, Qc, B = damped_model()
    kf = tl.KalmanFilter(make_sde(F, L, Qc, B), torch.tensor(H_NP), torch.tensor(R_NP))
    y = torch.tensor(rng.standard_normal((2, 6, 2)))
    out = kf(y, torch.full((2, 6), 0.3, dtype=F64))
    horizons = np.array([0.0, 0.5, 2.0, 10.0])
    u = rng.standard_normal((2, 4, 1))
    fc = kf.forecast(out, torch.tensor(horizons), u=torch.tensor(u))
    A, Q, G = scipy_discretize(F, L, Qc, horizons, B)
    mT, PT = out.mean[:, -1].detach().numpy(), out.cov[:, -1].detach().numpy()
    for b in range(2):
        for k in range(4):
            m_ref = A[k] @ mT[b] + G[k] @ u[b, k]
            P_ref = A[k] @ PT[b] @ A[k].T + Q[k]
            np.testing.assert_allclose(fc.mean[b, k].detach().numpy(), m_ref, atol=1e-10)
            np.testing.assert_allclose(fc.cov[b, k].detach().numpy(), P_ref, atol=1e-10)
            np.testing.assert_allclose(fc.obs_cov[b, k].detach().numpy(), H_NP @ P_ref @ H_NP.T + R_NP, atol=1e-10)


def test_learned_R_stays_positive_definite_and_gradients_finite_with_missing_tracks():
    rng = np.random.default_rng(6)
    cv = tl.models.constant_velocity(dim=2, q=1.0, dtype=F64)
    kf = tl.KalmanFilter(cv, tl.models.position_observation(cv), 0.5 * torch.eye(2, dtype=F64))
    assert isinstance(kf.parametrizations.R.original, torch.nn.Parameter)
    y = torch.tensor(rng.standard_normal((3, 10, 2)))
    y[2] = float("nan")  # a track with no observation at all
    dt = torch.tensor(rng.uniform(0.1, 1.0, size=(3, 10)))
    opt = torch.optim.SGD(kf.parameters(), lr=0.5)
    for _ in range(5):
        opt.zero_grad()
        loss = -kf(y, dt).log_likelihood.sum()
        loss.backward()
        for p in kf.parameters():
            assert torch.isfinite(p.grad).all()
        opt.step()
    assert float(torch.linalg.eigvalsh(kf.R.detach()).min()) > 0


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda kf, y, dt: kf(y[..., :1], dt), "rows"),
        (lambda kf, y, dt: kf(y, dt[..., :-1]), "dt must have shape"),
        (lambda kf, y, dt: kf(y, -dt), "non-negative"),
        (lambda kf, y, dt: kf(y, dt, u=torch.zeros(2, 5, 1, dtype=F64)), "no input matrix B"),
    ],
)
def test_bad_call_raises(call, match):
    cv = tl.models.constant_velocity(dim=2, q=1.0, dtype=F64)
    kf = tl.KalmanFilter(cv, tl.models.position_observation(cv), torch.eye(2, dtype=F64))
    y, dt = torch.zeros(2, 5, 2, dtype=F64), torch.ones(2, 5, dtype=F64)
    with pytest.raises(ValueError, match=match):
        call(kf, y, dt)


def test_bad_construction_raises():
    cv = tl.models.constant_velocity(dim=2, q=1.0, dtype=F64)
    H = tl.models.position_observation(cv)
    with pytest.raises(ValueError, match="H must have 4 columns"):
        tl.KalmanFilter(cv, H[:, :3], torch.eye(2, dtype=F64))
    with pytest.raises(ValueError, match="R must be symmetric"):
        tl.KalmanFilter(cv, H, torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=F64))
    with pytest.raises(ValueError, match="R must be symmetric positive definite"):
        tl.KalmanFilter(cv, H, -torch.eye(2, dtype=F64))
    with pytest.raises(ValueError, match="R must have shape"):
        tl.KalmanFilter(cv, H, torch.eye(3, dtype=F64))
    with pytest.raises(ValueError, match="learn"):
        tl.KalmanFilter(cv, H, torch.eye(2, dtype=F64), learn=("Q",))


def test_float32_module_runs_and_matches_float64():
    rng = np.random.default_rng(7)
    y = rng.standard_normal((2, 30, 2)) * 3
    dt = rng.uniform(0.01, 2.0, size=(2, 30))
    res = []
    for dtype in (torch.float32, F64):
        cv = tl.models.constant_velocity(dim=2, q=1.0, dtype=dtype)
        kf = tl.KalmanFilter(cv, tl.models.position_observation(cv), 0.5 * torch.eye(2, dtype=dtype))
        out = kf(torch.tensor(y, dtype=dtype), torch.tensor(dt, dtype=dtype))
        assert out.mean.dtype == dtype
        res.append(out.log_likelihood.detach().double())
    torch.testing.assert_close(res[0], res[1], rtol=1e-4, atol=1e-3)


def _small_filter() -> tuple[tl.KalmanFilter, torch.Tensor, torch.Tensor]:
    sde = tl.models.integrated_ou(k=0.5, q=1.0, dim=2).double()
    kf = tl.KalmanFilter(sde, tl.models.position_observation(sde), 0.3 * torch.eye(2, dtype=torch.float64))
    y = torch.randn(3, 6, 2, dtype=torch.float64)
    dt = torch.rand(3, 6, dtype=torch.float64)
    return kf, y, dt


def test_nan_parameter_after_diverged_step_raises() -> None:
    """A NaN learned parameter must fail loudly, not give a silent NaN likelihood."""
    kf, y, dt = _small_filter()
    with torch.no_grad():
        kf.sde.parametrizations.q.original.fill_(float("nan"))
    with pytest.raises(ValueError, match=r"(Qc|F) contains NaN or Inf"):
        kf(y, dt)


def test_inf_measurement_and_nan_input_raise() -> None:
    kf, y, dt = _small_filter()
    y[1, 2, 0] = float("inf")
    with pytest.raises(ValueError, match=r"y contains Inf"):
        kf(y, dt)
    B = torch.tensor([[0.0], [1.0], [0.0], [0.0]], dtype=torch.float64)
    sde = tl.LTISDE(
        torch.tensor([[0, 1, 0, 0], [0, -0.5, 0, 0], [0, 0, 0, 1], [0, 0, 0, -0.5]], dtype=torch.float64),
        torch.tensor([[0, 0], [1, 0], [0, 0], [0, 1]], dtype=torch.float64),
        torch.eye(2, dtype=torch.float64),
        B,
    )
    kf_u = tl.KalmanFilter(sde, tl.models.position_observation(kf.sde), torch.eye(2, dtype=torch.float64))
    u = torch.zeros(3, 6, 1, dtype=torch.float64)
    u[0, 3, 0] = float("nan")
    with pytest.raises(ValueError, match=r"u contains NaN or Inf"):
        kf_u(torch.randn(3, 6, 2, dtype=torch.float64), dt, u=u)


def test_assigning_wrong_sized_R_raises() -> None:
    kf, _, _ = _small_filter()
    with pytest.raises(ValueError, match=r"R"):
        kf.R = torch.eye(3, dtype=torch.float64)
    kf.R = 2.0 * torch.eye(2, dtype=torch.float64)
    assert torch.allclose(kf.R, 2.0 * torch.eye(2, dtype=torch.float64))
