"""The filter's discretisation entry point (batch-last layout, one-GEMM full-step series)
against independent references (scipy expm / quadrature, closed-form integrator chains)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch

import torchsde_lti as tl
from tests.reference import integrator_chain_Q, quad_discretize
from torchsde_lti.core import discretize_series as _discretize_series

f64 = torch.float64


def _cv_matrices() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    F = torch.zeros(1, 4, 4, dtype=f64)
    F[0, 0, 1] = F[0, 2, 3] = 1.0
    L = torch.zeros(1, 4, 2, dtype=f64)
    L[0, 1, 0] = L[0, 3, 1] = 1.0
    Qc = torch.tensor([[[1.3, 0.4], [0.4, 0.9]]], dtype=f64)
    return F, L, Qc


@pytest.mark.parametrize("shape", [(7,), (3, 7), (2, 3, 5)])
def test_nilpotent_series_matches_closed_form(shape):
    F, L, Qc = _cv_matrices()
    dt = torch.rand(shape, dtype=f64, generator=torch.Generator().manual_seed(0)) * 3.0
    d = _discretize_series(F, L, Qc, dt)
    assert d.A.shape == (*shape, 4, 4) and d.Q.shape == (*shape, 4, 4) and d.G is None
    assert torch.equal(d.Q, d.Q.mT)  # exactly symmetric
    W = (L[0] @ Qc[0] @ L[0].T).numpy()
    for idx in np.ndindex(*shape):
        h = float(dt[idx])
        A_ref = scipy.linalg.expm(F[0].numpy() * h)
        # CV with correlated axes: Q = kron(W_vel, chain(q = 1)) up to the [x, vx, y, vy] order
        Q_ref = np.kron(W[np.ix_([1, 3], [1, 3])], integrator_chain_Q(2, 1.0, h))
        np.testing.assert_allclose(d.A[idx].numpy(), A_ref, rtol=0, atol=1e-14)
        np.testing.assert_allclose(d.Q[idx].numpy(), Q_ref, rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("batched_params", [False, True])
def test_doubling_series_with_input_matches_quadrature(batched_params):
    rng = np.random.default_rng(1)
    n, p = 3, 2
    M = rng.normal(size=(n, n))
    Fn = M - (np.linalg.eigvals(M).real.max() + 0.5) * np.eye(n)
    Ln = rng.normal(size=(n, 2))
    Bn = rng.normal(size=(n, p))
    S = 2 if batched_params else 1
    F = torch.tensor(Fn).expand(S, 1, n, n)
    L = torch.tensor(Ln).expand(S, 1, n, 2)
    Qc = torch.eye(2, dtype=f64).expand(S, 1, 2, 2)
    B = torch.tensor(Bn).expand(S, 1, n, p)
    dt = torch.tensor(rng.uniform(0.0, 4.0, size=(S, 6)))
    d = _discretize_series(F, L, Qc, dt, B)
    assert d.A.shape == (S, 6, n, n) and d.G is not None and d.G.shape == (S, 6, n, p)
    for s in range(S):
        for k in range(6):
            A_ref, Q_ref, G_ref = quad_discretize(Fn, Ln @ Ln.T, Bn, float(dt[s, k]))
            np.testing.assert_allclose(d.A[s, k].numpy(), A_ref, rtol=1e-12, atol=1e-14)
            np.testing.assert_allclose(d.Q[s, k].numpy(), Q_ref, rtol=1e-10, atol=1e-13)
            np.testing.assert_allclose(d.G[s, k].numpy(), G_ref, rtol=1e-12, atol=1e-14)


def test_series_gradients():
    F, L, Qc = _cv_matrices()
    dt = torch.tensor([[0.3, 1.7, 0.05], [2.5, 0.1, 0.9]], dtype=f64, requires_grad=True)
    Fr = F.clone().requires_grad_(True)
    Qr = Qc.clone().requires_grad_(True)

    def fn(F_, Qc_, dt_):
        d = _discretize_series(F_, L, 0.5 * (Qc_ + Qc_.mT), dt_)
        return d.A, d.Q

    assert torch.autograd.gradcheck(fn, (Fr, Qr, dt))


def test_kalman_filter_uses_same_values_as_public_discretize():
    cv = tl.models.constant_velocity(dim=2, q=0.7, dtype=f64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=f64)
    kf = tl.KalmanFilter(cv, H, 0.3 * torch.eye(2, dtype=f64), P0=10 * torch.eye(4, dtype=f64))
    dt = torch.rand(3, 9, dtype=f64, generator=torch.Generator().manual_seed(2)) * 2
    d_pub = cv(dt, series=True)
    d_kf = kf._discretize(dt)
    A_ref = torch.tensor(np.stack([[scipy.linalg.expm(cv.F.detach().numpy() * float(h)) for h in row] for row in dt]))
    torch.testing.assert_close(d_kf.A, A_ref, rtol=0, atol=1e-13)
    torch.testing.assert_close(d_kf.Q, d_pub.Q, rtol=1e-13, atol=1e-15)


def _quantised_case(seed: int = 3):
    g = torch.Generator().manual_seed(seed)
    dt = torch.randint(0, 6, (4, 30), generator=g).to(f64) * 0.5  # 6 distinct gaps, incl. 0
    y = torch.randn(4, 30, 2, generator=g, dtype=f64)
    y[1, 5:9] = float("nan")
    y[2, 3, 0] = float("nan")
    return y, dt


@pytest.mark.parametrize("algorithm", ["sequential", "scan"])
def test_unique_dt_equals_plain_path(algorithm):
    y, dt = _quantised_case()
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=f64)
    outs, grads = [], []
    for unique in (False, True):
        cv = tl.models.constant_velocity(dim=2, q=0.7, dtype=f64)
        kf = tl.KalmanFilter(
            cv, H, 0.3 * torch.eye(2, dtype=f64), P0=10 * torch.eye(4, dtype=f64), algorithm=algorithm, unique_dt=unique
        )
        out = kf(y, dt)
        (-out.log_likelihood.sum()).backward()
        outs.append(out)
        grads.append([p.grad.clone() for p in kf.parameters()])
    for a, b in zip(outs[0][:8], outs[1][:8]):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    for a, b in zip(grads[0], grads[1]):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_unique_dt_gathers_exact_matrices():
    y, dt = _quantised_case(4)
    cv = tl.models.constant_velocity(dim=2, q=1.1, dtype=f64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=f64)
    kf = tl.KalmanFilter(cv, H, torch.eye(2, dtype=f64), unique_dt=True)
    d = kf._discretize(dt)
    assert d.A.shape == (4, 30, 4, 4)
    for idx in [(0, 0), (1, 7), (3, 29), (2, 11)]:
        h = float(dt[idx])
        A_ref = scipy.linalg.expm(cv.F.detach().numpy() * h)
        Q_ref = np.kron(np.eye(2) * 1.1, integrator_chain_Q(2, 1.0, h))
        np.testing.assert_allclose(d.A[idx].detach().numpy(), A_ref, atol=1e-14)
        np.testing.assert_allclose(d.Q[idx].detach().numpy(), Q_ref, rtol=1e-13, atol=1e-15)


def test_unique_dt_with_one_parameter_set_of_size_one_batch_dims():
    """discretize_series(unique=True) of one parameter set carried with batch dims of size 1
    (F (1, 1, n, n): what a KalmanFilter of an SDE of batch (1,) passes) and few distinct dt:
    the values of unique=False (it raised an expand error)."""
    F = torch.tensor([[[[0.0, 1.0], [-2.0, -0.3]]]], dtype=torch.float64)
    L = torch.tensor([[0.0], [1.0]], dtype=torch.float64).expand(1, 1, 2, 1)
    Qc = torch.eye(1, dtype=torch.float64).expand(1, 1, 1, 1)
    dt = torch.tensor([[0.5, 1.0, 0.5], [1.0, 2.0, 0.5]], dtype=torch.float64)
    got = _discretize_series(F, L, Qc, dt, unique=True)
    want = _discretize_series(F, L, Qc, dt, unique=False)
    torch.testing.assert_close(got.A, want.A, rtol=0, atol=1e-15)
    torch.testing.assert_close(got.Q, want.Q, rtol=0, atol=1e-15)
