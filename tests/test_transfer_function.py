"""from_transfer_function: against scipy.signal (tf2ss, freqs, cont2discrete)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal
import torch

import torchsde_lti as tl
from tests.reference import numpy_kalman_filter, scipy_discretize

F64 = torch.float64

CASES = [
    ([1.0], [1.0, 3.0, 2.0]),  # strictly proper, monic
    ([2.0, 1.0, 3.0], [4.0, 3.0, 2.0]),  # proper (D ≠ 0), non-monic
    ([0.5, -1.0], [2.0, 1.0, 5.0, 0.7]),  # order 3
    ([3.0, 0.0, 1.0, 2.0], [1.5, 2.0, 4.0, 1.0]),  # order 3, proper
]


def matrices(model):
    return tuple(x.detach().numpy() for x in (model.F, model.B, model.C, model.D))


@pytest.mark.parametrize("num, den", CASES)
def test_matches_tf2ss_up_to_the_documented_ordering(num, den):
    model = tl.models.from_transfer_function(num, den, dtype=F64)
    F, B, C, D = matrices(model)
    As, Bs, Cs, Ds = scipy.signal.tf2ss(num, den)
    n = F.shape[0]
    J = np.eye(n)[::-1]
    a_n = den[0]
    np.testing.assert_allclose(J @ F @ J, As, atol=1e-14)
    np.testing.assert_allclose(a_n * J @ B, Bs, atol=1e-14)
    np.testing.assert_allclose(C @ J / a_n, Cs, atol=1e-14)
    np.testing.assert_allclose(D, Ds, atol=1e-14)
    assert (D[0, 0] != 0) == (len(num) == len(den))
    np.testing.assert_array_equal(model.L.detach().numpy(), B)  # noise enters where u does


@pytest.mark.parametrize("num, den", CASES)
def test_frequency_response_matches_scipy_freqs(num, den):
    model = tl.models.from_transfer_function(num, den, dtype=F64)
    F, B, C, D = matrices(model)
    w = np.logspace(-2, 2, 20)
    _, h_ref = scipy.signal.freqs(num, den, worN=w)
    n = F.shape[0]
    h = np.array([(C @ np.linalg.solve(1j * wk * np.eye(n) - F, B) + D)[0, 0] for wk in w])
    np.testing.assert_allclose(h, h_ref, rtol=1e-10, atol=1e-10 * np.abs(h_ref).max())


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_noise_free_zoh_response_matches_cont2discrete(dtype):
    num, den = CASES[1]
    model = tl.models.from_transfer_function(num, den, dtype=dtype)
    rng = np.random.default_rng(0)
    T = 25
    dt = rng.uniform(0.02, 1.5, size=T)  # irregular
    u = rng.standard_normal((T, 1))
    # torchsde_lti: one batched exact discretisation, then the recursion x⁺ = A x + G u, y = C x + D u
    d = model(torch.tensor(dt, dtype=dtype), series=True)
    A = d.A.detach().double().numpy().reshape(T, 2, 2)
    G = d.G.detach().double().numpy().reshape(T, 2, 1)
    F, B, C, D = (x.astype(np.float64) for x in matrices(model))
    x_tl = np.zeros(2)
    x_sp = np.zeros(2)
    y_tl, y_sp = [], []
    for k in range(T):
        y_tl.append((C @ x_tl + D @ u[k])[0])
        y_sp.append((C @ x_sp + D @ u[k])[0])
        Ad, Bd, _, _, _ = scipy.signal.cont2discrete((F, B, C, D), dt[k], method="zoh")
        x_tl = A[k] @ x_tl + G[k] @ u[k]
        x_sp = Ad @ x_sp + Bd @ u[k]
        tol = 1e-12 if dtype == F64 else 1e-5
        np.testing.assert_allclose(A[k], Ad, atol=tol, rtol=tol)
        np.testing.assert_allclose(G[k], Bd, atol=tol, rtol=tol)
    tol = 1e-12 if dtype == F64 else 1e-4
    np.testing.assert_allclose(np.array(y_tl), np.array(y_sp), atol=tol, rtol=tol)
    np.testing.assert_allclose(x_tl, x_sp, atol=tol, rtol=tol)


def test_kalman_filter_with_the_models_C_and_D():
    num, den = CASES[3]
    model = tl.models.from_transfer_function(num, den, q=0.3, dtype=F64)
    rng = np.random.default_rng(1)
    T = 15
    dt = rng.exponential(0.3, size=T)
    y = rng.standard_normal((T, 1))
    y[5] = np.nan
    u = rng.standard_normal((T, 1))
    R = np.array([[0.2]])
    kf = tl.KalmanFilter(model, model.C, torch.tensor(R), D=model.D, P0=torch.eye(3, dtype=F64))
    out = kf(torch.tensor(y), torch.tensor(dt), u=torch.tensor(u))
    F, B, C, D = matrices(model)
    A, Q, G = scipy_discretize(F, model.L.detach().numpy(), model.Qc.detach().numpy(), np.asarray(dt), B)
    ref = numpy_kalman_filter(y, A, Q, C, R, np.zeros(3), np.eye(3), c=(G @ u[..., None])[..., 0], Du=u @ D.T)
    np.testing.assert_allclose(out.mean.detach().numpy(), ref["mean"], atol=1e-9, rtol=0)
    np.testing.assert_allclose(out.log_likelihood.item(), ref["ll"].sum(), atol=1e-9, rtol=0)


def test_C_and_D_follow_the_learned_denominator():
    model = tl.models.from_transfer_function([2.0, 1.0, 3.0], [4.0, 3.0, 2.0], dtype=F64)
    assert isinstance(model.a, torch.nn.Parameter)
    model.C.sum().backward()
    assert model.a.grad is not None and torch.any(model.a.grad != 0)
    with torch.no_grad():
        model.a.copy_(torch.tensor([1.0, 1.0, 1.0], dtype=F64))  # den = s² + s + 1
    _, _, Cs, Ds = scipy.signal.tf2ss([2.0, 1.0, 3.0], [1.0, 1.0, 1.0])
    np.testing.assert_allclose(model.C.detach().numpy()[:, ::-1], Cs, atol=1e-14)
    np.testing.assert_allclose(model.D.detach().numpy(), Ds, atol=1e-14)


def test_leading_zeros_batches_and_companion_outputs():
    a = tl.models.from_transfer_function([0.0, 0.0, 1.0], [0.0, 1.0, 3.0, 2.0], dtype=F64)
    b = tl.models.from_transfer_function([1.0], [1.0, 3.0, 2.0], dtype=F64)
    torch.testing.assert_close(a.F, b.F)
    torch.testing.assert_close(a.C, b.C)
    dens = torch.tensor([[1.0, 3.0, 2.0], [2.0, 1.0, 5.0]], dtype=F64)
    batched = tl.models.from_transfer_function(torch.tensor([1.0, 0.5], dtype=F64), dens)
    assert batched.F.shape == (2, 2, 2) and batched.C.shape == (2, 1, 2) and batched.D.shape == (2, 1, 1)
    for i in range(2):
        single = tl.models.from_transfer_function([1.0, 0.5], dens[i].tolist(), dtype=F64)
        torch.testing.assert_close(batched.F[i], single.F)
        torch.testing.assert_close(batched.C[i], single.C)
    with pytest.raises(ValueError, match="position_indices"):
        tl.models.position_observation(b)  # the output is C x + D u: H = model.C
    msd = tl.models.mass_spring_damper(1.0, 2.0, 0.5, dtype=F64)
    comp = tl.models.companion([2.0, 0.5, 1.0], dtype=F64)
    for model in (msd, comp):
        assert model.D.shape == (1, 1) and float(model.D) == 0.0
        assert model.C.shape == (1, model.state_dim)


def test_improper_and_degenerate_transfer_functions_raise():
    with pytest.raises(ValueError, match="improper"):
        tl.models.from_transfer_function([1.0, 0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="degree >= 1"):
        tl.models.from_transfer_function([1.0], [2.0])
    with pytest.raises(ValueError, match="num and den"):
        tl.models.from_transfer_function(1.0, [1.0, 2.0])
    with pytest.raises(ValueError, match="den"):
        tl.models.from_transfer_function([1.0], [1.0, float("nan")])
