"""The output equation y = H x + D u + v: KalmanFilter(D=...), the functional filters, forecasts."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from tests.reference import numpy_kalman_filter, scipy_discretize

F64 = torch.float64

F_NP = np.array([[0.0, 1.0, 0.0], [-2.0, -0.7, 0.4], [0.0, 0.0, -0.5]])
L_NP = np.array([[0.0], [0.5], [1.0]])
QC_NP = np.array([[0.8]])
B_NP = np.array([[0.0, 0.0], [1.0, 0.2], [0.0, 1.0]])
H_NP = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.5]])
R_NP = np.array([[0.3, 0.05], [0.05, 0.2]])
D_NP = np.array([[0.7, -0.3], [0.0, 1.2]])


def make_sde(with_B=True, dtype=F64):
    t = lambda x: torch.as_tensor(x, dtype=dtype)  # noqa: E731
    return tl.LTISDE(t(F_NP), t(L_NP), t(QC_NP), t(B_NP) if with_B else None)


def problem(rng, batch=3, T=20):
    dt = rng.exponential(0.5, size=(batch, T))
    dt[:, 0] = 0.0
    y = rng.standard_normal((batch, T, 2))
    y[rng.random((batch, T)) < 0.2] = np.nan  # missing steps
    y[0, 4, 1] = np.nan  # a partially observed step
    u = rng.standard_normal((batch, T, 2))
    return dt, y, u


M0 = np.array([0.3, -0.1, 0.2])
P0 = np.diag([1.0, 0.5, 2.0])


@pytest.mark.parametrize("variant", ["sequential", "scan", "square_root"])
def test_filter_with_feedthrough_matches_numpy_reference(variant):
    rng = np.random.default_rng(0)
    dt, y, u = problem(rng)
    kw = {"algorithm": variant}
    kf = tl.KalmanFilter(
        make_sde(),
        torch.tensor(H_NP),
        torch.tensor(R_NP),
        m0=torch.tensor(M0),
        P0=torch.tensor(P0),
        D=torch.tensor(D_NP),
        **kw,
    )
    out = kf(torch.tensor(y), torch.tensor(dt), u=torch.tensor(u))
    for b in range(y.shape[0]):
        A, Q, G = scipy_discretize(F_NP, L_NP, QC_NP, np.asarray(dt[b]), B_NP)
        c = (G @ u[b][..., None])[..., 0]
        ref = numpy_kalman_filter(y[b], A, Q, H_NP, R_NP, M0, P0, c=c, Du=u[b] @ D_NP.T)
        np.testing.assert_allclose(out.mean[b].detach().numpy(), ref["mean"], atol=1e-9, rtol=0)
        np.testing.assert_allclose(out.cov[b].detach().numpy(), ref["cov"], atol=1e-9, rtol=0)
        np.testing.assert_allclose(out.step_log_likelihood[b].detach().numpy(), ref["ll"], atol=1e-9, rtol=0)
    # innovations are y − D u − H m⁻ on observed components
    innov = y - u @ D_NP.T - (out.pred_mean.detach().numpy() @ H_NP.T)
    np.testing.assert_allclose(out.innovation.detach().numpy(), np.nan_to_num(innov, nan=0.0), atol=1e-9)


def test_feedthrough_without_input_matrix():
    """An SDE without B: u acts on the observation only."""
    rng = np.random.default_rng(1)
    dt, y, u = problem(rng, batch=2, T=12)
    kf = tl.KalmanFilter(
        make_sde(with_B=False),
        torch.tensor(H_NP),
        torch.tensor(R_NP),
        m0=torch.tensor(M0),
        P0=torch.tensor(P0),
        D=torch.tensor(D_NP),
    )
    out = kf(torch.tensor(y), torch.tensor(dt), u=torch.tensor(u))
    for b in range(2):
        A, Q, _ = scipy_discretize(F_NP, L_NP, QC_NP, np.asarray(dt[b]), None)
        ref = numpy_kalman_filter(y[b], A, Q, H_NP, R_NP, M0, P0, Du=u[b] @ D_NP.T)
        np.testing.assert_allclose(out.mean[b].detach().numpy(), ref["mean"], atol=1e-9, rtol=0)
        np.testing.assert_allclose(out.log_likelihood[b].item(), ref["ll"].sum(), atol=1e-9, rtol=0)
    # no input given: D u = 0, the plain filter
    plain = tl.KalmanFilter(
        make_sde(with_B=False), torch.tensor(H_NP), torch.tensor(R_NP), m0=torch.tensor(M0), P0=torch.tensor(P0)
    )
    torch.testing.assert_close(
        kf(torch.tensor(y), torch.tensor(dt)).mean, plain(torch.tensor(y), torch.tensor(dt)).mean
    )


def test_functional_filter_equals_module_and_float32_is_close():
    rng = np.random.default_rng(2)
    dt, y, u = problem(rng, batch=2, T=10)
    A, Q, G = scipy_discretize(F_NP, L_NP, QC_NP, np.asarray(dt.ravel()), B_NP)
    A, Q, G = A.reshape(2, 10, 3, 3), Q.reshape(2, 10, 3, 3), G.reshape(2, 10, 3, 2)
    t = lambda x: torch.tensor(x)  # noqa: E731
    out = tl.kalman_filter(t(y), t(A), t(Q), t(H_NP), t(R_NP), t(M0), t(P0), G=t(G), u=t(u), D=t(D_NP))
    kf = tl.KalmanFilter(make_sde(), t(H_NP), t(R_NP), m0=t(M0), P0=t(P0), D=t(D_NP))
    ref = kf(t(y), t(dt), u=t(u))
    torch.testing.assert_close(out.mean, ref.mean, atol=1e-9, rtol=0)
    kf32 = tl.KalmanFilter(
        make_sde(dtype=torch.float32),
        t(H_NP).float(),
        t(R_NP).float(),
        m0=t(M0).float(),
        P0=t(P0).float(),
        D=t(D_NP).float(),
    )
    out32 = kf32(t(y).float(), t(dt).float(), u=t(u).float())
    assert out32.mean.dtype == torch.float32
    torch.testing.assert_close(out32.mean.double(), ref.mean, atol=2e-4, rtol=2e-4)


def test_batched_D_equals_loop():
    rng = np.random.default_rng(3)
    dt, y, u = problem(rng, batch=3, T=8)
    Ds = torch.tensor(rng.standard_normal((3, 2, 2)))
    t = lambda x: torch.tensor(x)  # noqa: E731
    batched = tl.KalmanFilter(make_sde(), t(H_NP), t(R_NP), m0=t(M0), P0=t(P0), D=Ds)(t(y), t(dt), u=t(u))
    for b in range(3):
        single = tl.KalmanFilter(make_sde(), t(H_NP), t(R_NP), m0=t(M0), P0=t(P0), D=Ds[b])(
            t(y[b]), t(dt[b]), u=t(u[b])
        )
        torch.testing.assert_close(batched.mean[b], single.mean, atol=1e-12, rtol=0)
        torch.testing.assert_close(batched.log_likelihood[b], single.log_likelihood, atol=1e-12, rtol=0)


def test_gradcheck_wrt_D():
    rng = np.random.default_rng(4)
    dt, y, u = problem(rng, batch=1, T=6)
    A, Q, G = scipy_discretize(F_NP, L_NP, QC_NP, np.asarray(dt[0]), B_NP)
    t = lambda x: torch.tensor(x)  # noqa: E731
    D = t(D_NP).requires_grad_(True)

    def f(D):
        out = tl.kalman_filter(t(y[0]), t(A), t(Q), t(H_NP), t(R_NP), t(M0), t(P0), G=t(G), u=t(u[0]), D=D)
        return out.log_likelihood, out.mean

    assert torch.autograd.gradcheck(f, (D,))

    # learnable D in the module: a Parameter whose gradient is the functional one
    kf = tl.KalmanFilter(make_sde(), t(H_NP), t(R_NP), m0=t(M0), P0=t(P0), D=t(D_NP), learn=("D", "R"))
    assert isinstance(kf.D, torch.nn.Parameter) and any(p is kf.D for p in kf.parameters())
    kf(t(y), t(dt), u=t(u)).log_likelihood.sum().backward()
    ll = f(D)[0]
    (g,) = torch.autograd.grad(ll, D)
    torch.testing.assert_close(kf.D.grad, g, atol=1e-9, rtol=1e-9)


def test_forecast_includes_D_u():
    rng = np.random.default_rng(5)
    dt, y, u = problem(rng, batch=2, T=6)
    t = lambda x: torch.tensor(x)  # noqa: E731
    kf = tl.KalmanFilter(make_sde(), t(H_NP), t(R_NP), m0=t(M0), P0=t(P0), D=t(D_NP))
    out = kf(t(y), t(dt), u=t(u))
    horizons = torch.tensor([0.5, 1.0, 2.5], dtype=F64)
    uf = torch.tensor(rng.standard_normal((2, 3, 2)))
    fc = kf.forecast(out, horizons, u=uf)
    m_last = out.mean[:, -1].detach().numpy()
    A, _, G = scipy_discretize(F_NP, L_NP, QC_NP, np.asarray(horizons.numpy()), B_NP)
    mean_ref = np.einsum("kij,bj->bki", A, m_last) + np.einsum("kij,bkj->bki", G, uf.numpy())
    obs_ref = mean_ref @ H_NP.T + uf.numpy() @ D_NP.T
    np.testing.assert_allclose(fc.mean.detach().numpy(), mean_ref, atol=1e-10)
    np.testing.assert_allclose(fc.obs_mean.detach().numpy(), obs_ref, atol=1e-10)
    # no inputs: no G u, no D u
    fc0 = kf.forecast(out, horizons)
    np.testing.assert_allclose(fc0.obs_mean.detach().numpy(), np.einsum("kij,bj->bki", A, m_last) @ H_NP.T, atol=1e-10)


def test_bad_D_or_u_shapes_raise_naming_them():
    t = lambda x: torch.tensor(x)  # noqa: E731
    sde = make_sde()
    with pytest.raises(ValueError, match="D"):
        tl.KalmanFilter(sde, t(H_NP), t(R_NP), D=t(D_NP[:1]))  # 1 row, H has 2
    with pytest.raises(ValueError, match="D must have shape"):
        tl.KalmanFilter(sde, t(H_NP), t(R_NP), D=t(np.ones((2, 3))))  # 3 inputs, B has 2
    with pytest.raises(ValueError, match="learn contains 'D'"):
        tl.KalmanFilter(sde, t(H_NP), t(R_NP), learn=("D",))
    kf = tl.KalmanFilter(make_sde(with_B=False), t(H_NP), t(R_NP), D=t(D_NP))
    y, dt = torch.zeros(4, 2, dtype=F64), torch.ones(4, dtype=F64)
    with pytest.raises(ValueError, match="u must have shape"):
        kf(y, dt, u=torch.zeros(4, 3, dtype=F64))
    with pytest.raises(ValueError, match="u must have shape"):
        kf.forecast(
            (torch.zeros(3, dtype=F64), torch.eye(3, dtype=F64)),
            torch.ones(2, dtype=F64),
            u=torch.zeros(2, 5, dtype=F64),
        )
    A = torch.eye(3, dtype=F64).expand(4, 3, 3)
    Q = 0.1 * A
    args = (y, A, Q, t(H_NP), t(R_NP), torch.zeros(3, dtype=F64), torch.eye(3, dtype=F64))
    with pytest.raises(ValueError, match="u must have shape .* D"):
        tl.kalman_filter(*args, u=torch.zeros(4, 3, dtype=F64), D=t(D_NP))
    with pytest.raises(ValueError, match="u is None"):
        tl.kalman_filter(*args, D=t(D_NP))
    with pytest.raises(ValueError, match="D must have"):
        tl.kalman_filter(*args, u=torch.zeros(4, 2, dtype=F64), D=torch.zeros(3, 2, dtype=F64))
    with pytest.raises(ValueError, match="D has 3 steps"):
        tl.kalman_filter(*args, u=torch.zeros(4, 2, dtype=F64), D=torch.zeros(3, 2, 2, dtype=F64), algorithm="scan")
