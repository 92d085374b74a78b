"""discretize / transition_matrix / zero_order_hold / propagate against independent references."""

from __future__ import annotations

import math

import mpmath
import numpy as np
import pytest
import scipy.linalg
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchsde_lti as tl
from tests.reference import integrator_chain_Q, mp_discretize, quad_discretize, rel_err
from torchsde_lti.core.discretization import zero_order_hold

METHODS = ["doubling", "matrix_exp"]
f64 = torch.float64


def t64(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, dtype=np.float64))


def random_stable(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(n, n))
    return M - (np.linalg.eigvals(M).real.max() + rng.uniform(0.2, 1.0)) * np.eye(n)


# --------------------------------------------------------------------------- closed forms


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("dt", [1e-3, 0.37, 1.0, 5.0])
def test_constant_velocity_closed_form(method: str, dt: float) -> None:
    q = 0.7
    F = t64([[0, 1], [0, 0]])
    L = t64([[0], [1]])
    B = t64([[0], [1]])
    d = tl.discretize(F, L, t64([[q]]), t64(dt), B=B, method=method)
    np.testing.assert_allclose(d.A, [[1, dt], [0, 1]], rtol=1e-12, atol=0)
    np.testing.assert_allclose(d.Q, q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]), rtol=1e-12, atol=0)
    np.testing.assert_allclose(d.G, [[dt**2 / 2], [dt]], rtol=1e-12, atol=0)


@pytest.mark.parametrize("dt", [1e-4, 0.5, 3.0, 1e3])
def test_constant_acceleration_closed_form(dt: float) -> None:
    q = 2.5
    F = t64([[0, 1, 0], [0, 0, 1], [0, 0, 0]])
    L = t64([[0], [0], [1]])
    d = tl.discretize(F, L, t64([[q]]), t64(dt))
    np.testing.assert_allclose(d.A, [[1, dt, dt**2 / 2], [0, 1, dt], [0, 0, 1]], rtol=1e-12, atol=0)
    np.testing.assert_allclose(d.Q, integrator_chain_Q(3, q, dt), rtol=1e-12, atol=0)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("theta_dt", [1e-6, 0.3, 2.0, 15.0])
def test_scalar_ou_closed_form(method: str, theta_dt: float) -> None:
    theta, q = 1.7, 0.9
    dt = theta_dt / theta
    d = tl.discretize(t64([[-theta]]), t64([[1.0]]), t64([[q]]), t64(dt), method=method)
    np.testing.assert_allclose(d.A[0, 0], math.exp(-theta * dt), rtol=1e-12)
    np.testing.assert_allclose(d.Q[0, 0], q / (2 * theta) * -math.expm1(-2 * theta * dt), rtol=1e-12)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("dt", [0.01, 0.8, 4.0])
def test_integrated_ou_closed_form(method: str, dt: float) -> None:
    # position integrates velocity; velocity: dv = -k v dt + dβ,  E[dβ²] = q dt
    k, q = 1.3, 0.6
    with mpmath.workdps(40):  # the closed form cancels for small dt: evaluate it at 40 digits
        K, T = mpmath.mpf(k), mpmath.mpf(dt)
        e1, e2 = mpmath.exp(-K * T), mpmath.exp(-2 * K * T)
        A_ref = np.array([[1, float((1 - e1) / K)], [0, float(e1)]])
        Q_ref = q * np.array(
            [
                [
                    float((T - 2 * (1 - e1) / K + (1 - e2) / (2 * K)) / K**2),
                    float(((1 - e1) / K - (1 - e2) / (2 * K)) / K),
                ],
                [float(((1 - e1) / K - (1 - e2) / (2 * K)) / K), float((1 - e2) / (2 * K))],
            ]
        )
    d = tl.discretize(t64([[0, 1], [0, -k]]), t64([[0], [1]]), t64([[q]]), t64(dt), method=method)
    if method == "doubling":
        np.testing.assert_allclose(d.A, A_ref, rtol=1e-12, atol=1e-300)
        np.testing.assert_allclose(d.Q, Q_ref, rtol=1e-12, atol=0)
    else:  # the block exponential cancels in small entries: 2e-11 in A, 4e-7 in Q[0, 0] seen
        assert rel_err(d.A, A_ref) < 1e-10 and rel_err(d.Q, Q_ref) < 1e-10


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("a", [-2.0, -1e-9, 0.0, 1e-9, 0.7])
def test_scalar_zero_order_hold(method: str, a: float) -> None:
    b, dt = 1.9, 0.6
    expected = b * dt if a == 0 else math.expm1(a * dt) / a * b
    d = tl.discretize(t64([[a]]), t64([[1.0]]), t64([[1.0]]), t64(dt), B=t64([[b]]), method=method)
    np.testing.assert_allclose(d.G[0, 0], expected, rtol=1e-12)
    A, G = zero_order_hold(t64([[a]]), t64([[b]]), t64(dt))
    np.testing.assert_allclose(G[0, 0], expected, rtol=1e-12)


# --------------------------------------------------------------------------- scipy / quadrature


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("seed", range(4))
def test_random_models_match_scipy_and_quadrature(method: str, seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, s, p = 3 + seed % 2, 2, 2
    F = rng.normal(size=(n, n))
    L = rng.normal(size=(n, s))
    M = rng.normal(size=(s, s))
    Qc = M @ M.T
    B = rng.normal(size=(n, p))
    dt = float(rng.uniform(0.05, 1.5))
    A_ref, Q_ref, G_ref = quad_discretize(F, L @ Qc @ L.T, B, dt)
    d = tl.discretize(t64(F), t64(L), t64(Qc), t64(dt), B=t64(B), method=method)
    assert rel_err(d.A, A_ref) < 1e-12
    assert rel_err(d.Q, Q_ref) < 1e-11
    assert rel_err(d.G, G_ref) < 1e-12
    np.testing.assert_allclose(tl.transition_matrix(t64(F), t64(dt)), A_ref, rtol=1e-11, atol=1e-13)


def test_transition_matrix_batched_against_scipy() -> None:
    rng = np.random.default_rng(7)
    F = rng.normal(size=(4, 4)) * 3
    dt = rng.exponential(1.0, size=(5, 6))
    A = tl.transition_matrix(t64(F), t64(dt))
    assert A.shape == (5, 6, 4, 4)
    for idx in np.ndindex(5, 6):
        ref = scipy.linalg.expm(F * dt[idx])
        assert rel_err(A[idx], ref) < 1e-12


# --------------------------------------------------------------------------- ODEs, semigroup, stationarity


@pytest.mark.parametrize("method", METHODS)
def test_moment_odes_by_finite_differences(method: str) -> None:
    rng = np.random.default_rng(3)
    n = 3
    F, L, B = t64(rng.normal(size=(n, n))), t64(rng.normal(size=(n, 2))), t64(rng.normal(size=(n, 1)))
    Qc = t64(np.diag([0.5, 2.0]))
    m0, u = t64(rng.normal(size=n)), t64([0.7])
    M = rng.normal(size=(n, n))
    P0 = t64(M @ M.T)
    t, h = 0.8, 1e-5

    def moments(time: float):
        return tl.propagate(m0, P0, F, L, Qc, t64(time), B=B, u=u, method=method)

    (m_plus, P_plus), (m_minus, P_minus), (m, P) = moments(t + h), moments(t - h), moments(t)
    dm = (m_plus - m_minus) / (2 * h)
    dP = (P_plus - P_minus) / (2 * h)
    np.testing.assert_allclose(dm, F @ m + B @ u, rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(dP, F @ P + P @ F.T + L @ Qc @ L.T, rtol=1e-7, atol=1e-7)


@pytest.mark.parametrize("method", METHODS)
def test_semigroup(method: str) -> None:
    rng = np.random.default_rng(11)
    F = t64(random_stable(3, 11))
    L, Qc = t64(rng.normal(size=(3, 3))), t64(np.eye(3))
    s, t = t64(0.4), t64(1.3)
    ds, dt_, dst = (tl.discretize(F, L, Qc, x, method=method) for x in (s, t, s + t))
    np.testing.assert_allclose(dst.A, dt_.A @ ds.A, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(dst.Q, dt_.A @ ds.Q @ dt_.A.T + dt_.Q, rtol=1e-11, atol=1e-14)


def test_stationary_covariance_residual_and_limit() -> None:
    F = t64(random_stable(4, 5))
    rng = np.random.default_rng(5)
    L, Qc = t64(rng.normal(size=(4, 2))), t64([[1.0, 0.3], [0.3, 0.5]])
    P = tl.stationary_covariance(F, L, Qc)
    W = L @ Qc @ L.T
    residual = F @ P + P @ F.T + W
    assert float(residual.abs().max()) < 1e-12 * float(W.abs().max())
    ref = scipy.linalg.solve_continuous_lyapunov(F.numpy(), -W.numpy())
    assert rel_err(P, ref) < 1e-12
    d = tl.discretize(F, L, Qc, t64(1e4))
    assert rel_err(d.Q, P.numpy()) < 1e-12
    assert torch.linalg.eigvalsh(P).min() > 0


def test_stationary_covariance_batched_and_float32() -> None:
    F = torch.stack([t64(random_stable(3, i)) for i in range(4)])
    L, Qc = t64(np.eye(3)), t64(np.eye(3))
    P = tl.stationary_covariance(F, L, Qc)
    assert P.shape == (4, 3, 3)
    for i in range(4):
        ref = scipy.linalg.solve_continuous_lyapunov(F[i].numpy(), -np.eye(3))
        assert rel_err(P[i], ref) < 1e-12
    P32 = tl.stationary_covariance(F.float(), L.float(), Qc.float())
    assert P32.dtype == torch.float32
    assert rel_err(P32.double(), P.numpy()) < 1e-4


def test_stationary_covariance_rejects_unstable() -> None:
    with pytest.raises(ValueError, match="Hurwitz"):
        tl.stationary_covariance(t64([[0, 1], [0, 0]]), t64([[0], [1]]), t64([[1.0]]))


# --------------------------------------------------------------------------- stiff and large-dt cases


def _non_normal() -> np.ndarray:
    # eigenvalues -1e-3 and -1e3 with strong coupling
    return np.array([[-1e-3, 50.0], [0.0, -1e3]])


def _jordan() -> np.ndarray:
    return np.array([[-2.0, 1.0, 0.0], [0.0, -2.0, 1.0], [0.0, 0.0, -2.0]])


STIFF_CASES = [
    # name, F, L, Qc, dt
    ("integrated_ou_kdt_1", np.array([[0, 1], [0, -3.0]]), np.array([[0], [1.0]]), np.array([[2.0]]), 1 / 3),
    ("integrated_ou_kdt_20", np.array([[0, 1], [0, -3.0]]), np.array([[0], [1.0]]), np.array([[2.0]]), 20 / 3),
    ("integrated_ou_kdt_60", np.array([[0, 1], [0, -3.0]]), np.array([[0], [1.0]]), np.array([[2.0]]), 20.0),
    ("non_normal_dt_1e-3", _non_normal(), np.eye(2), np.eye(2), 1e-3),
    ("non_normal_dt_1", _non_normal(), np.eye(2), np.eye(2), 1.0),
    ("non_normal_dt_50", _non_normal(), np.eye(2), np.eye(2), 50.0),
    ("jordan_dt_0.1", _jordan(), np.eye(3), np.eye(3), 0.1),
    ("jordan_dt_30", _jordan(), np.eye(3), np.eye(3), 30.0),
]


@pytest.mark.parametrize("case", STIFF_CASES, ids=[c[0] for c in STIFF_CASES])
def test_stiff_against_high_precision(case, dtype: torch.dtype) -> None:
    _, F, L, Qc, dt = case
    # the reference is computed from the inputs as rounded to the tested dtype
    Ft, Lt, Qct, dtt = (torch.as_tensor(x, dtype=dtype) for x in (F, L, Qc, dt))
    W = (Lt.double() @ Qct.double() @ Lt.double().T).numpy()
    A_ref, Q_ref = mp_discretize(Ft.double().numpy(), W, float(dtt))
    d = tl.discretize(Ft, Lt, Qct, dtt)
    tol = 1e-10 if dtype == f64 else 1e-4
    assert torch.isfinite(d.Q).all() and torch.isfinite(d.A).all()
    assert torch.equal(d.Q, d.Q.mT)
    assert rel_err(d.A, A_ref) < tol
    assert rel_err(d.Q, Q_ref) < tol
    eig_min = float(torch.linalg.eigvalsh(d.Q.double()).min())
    assert eig_min >= -10 * torch.finfo(dtype).eps * float(d.Q.double().abs().max())


@pytest.mark.parametrize("lam_dt", [100.0, 1000.0])
def test_scalar_ou_extreme_rate(lam_dt: float, dtype: torch.dtype) -> None:
    lam, q = 250.0, 3.0
    dt = lam_dt / lam
    d = tl.discretize(
        torch.tensor([[-lam]], dtype=dtype),
        torch.ones(1, 1, dtype=dtype),
        torch.tensor([[q]], dtype=dtype),
        torch.tensor(dt, dtype=dtype),
    )
    ref = q / (2 * lam) * -math.expm1(-2 * lam_dt)
    tol = 1e-10 if dtype == f64 else 1e-4
    assert abs(float(d.Q) - ref) / ref < tol
    assert float(d.A) == pytest.approx(math.exp(-lam_dt), abs=1e-30)


@pytest.mark.parametrize("dt", [1e-4, 1e3])
def test_nilpotent_chain_extreme_dt(dt: float, dtype: torch.dtype) -> None:
    order, q = 4, 0.3
    F = torch.diag(torch.ones(order - 1, dtype=dtype), 1)
    L = torch.zeros(order, 1, dtype=dtype)
    L[-1, 0] = 1
    dtt = torch.tensor(dt, dtype=dtype)
    d = tl.discretize(F, L, torch.tensor([[q]], dtype=dtype), dtt)
    Q_ref = integrator_chain_Q(order, float(torch.tensor(q, dtype=dtype)), float(dtt))
    tol = 1e-10 if dtype == f64 else 1e-4
    # entrywise, not just normwise: entries span dt^1 .. dt^7
    np.testing.assert_allclose(d.Q.double().numpy(), Q_ref, rtol=tol, atol=0)


@pytest.mark.parametrize("dt", [1e-6, 1e-5, 1e-3])
def test_graded_q_of_a_short_step_is_accurate_entrywise(dt: float) -> None:
    """A Singer model's Q spans dt⁵ to dt: each entry to rounding of its own size (Q[0, 0] at
    dt = 1e-6 was accurate to 1.7e-7, its α-gradient 0: the series stopped at power n − 1)."""
    sde = tl.models.singer(0.6, 2.0, dim=1, dtype=torch.float64)
    F, L, Qc = sde.F.detach(), sde.L.detach(), sde.Qc.detach()
    A_ref, Q_ref = mp_discretize(F.numpy(), (L @ Qc @ L.T).numpy(), dt)
    d = tl.discretize(F, L, Qc, t64(dt))
    np.testing.assert_allclose(d.Q.numpy(), Q_ref, rtol=1e-13, atol=0)
    np.testing.assert_allclose(d.A.numpy(), A_ref, rtol=1e-13, atol=1e-300)


def test_van_loan_is_inaccurate_where_doubling_is_not() -> None:
    """Documents the trap: the plain block exponential cancels catastrophically."""
    F, L, Qc = t64([[0, 1], [0, -3.0]]), t64([[0], [1.0]]), t64([[2.0]])
    dt = t64(20.0)
    A_ref, Q_ref = mp_discretize(F.numpy(), (L @ Qc @ L.T).numpy(), 20.0)
    naive = tl.discretize(F, L, Qc, dt, method="matrix_exp", validate_args=False)
    robust = tl.discretize(F, L, Qc, dt)
    assert rel_err(naive.Q, Q_ref) > 1e-3 and float(torch.linalg.eigvalsh(naive.Q).min()) < 0
    assert rel_err(robust.Q, Q_ref) < 1e-13
    # checked (the default), the non-PSD Q is refused instead of returned
    with pytest.raises(
        ValueError, match="method='matrix_exp' gave a process noise Q that is not positive semi-definite"
    ):
        tl.discretize(F, L, Qc, dt, method="matrix_exp")


def test_matrix_exp_non_psd_q_is_refused_by_the_filter_module() -> None:
    # Singer α = 50 over dt = 1 (float64): Van Loan's Q has eigenvalue −283, and the square-root
    # filter returned a finite, wrong log-likelihood (−61.0 against the doubling's −80.3)
    sde = tl.models.singer(50.0, 2.0, dim=1, dtype=torch.float64)
    H, R = t64([[1.0, 0.0, 0.0]]), t64([[0.1]])
    y, dt = torch.randn(1, 20, 1, dtype=torch.float64), torch.ones(1, 20, dtype=torch.float64)
    kf = tl.KalmanFilter(sde, H, R, P0=torch.eye(3, dtype=torch.float64), algorithm="square_root", method="matrix_exp")
    with pytest.raises(ValueError, match="not positive semi-definite"):
        kf(y, dt)
    kf.validate_args = False
    assert torch.isfinite(kf(y, dt).log_likelihood).all()  # unchecked: what Van Loan gives
    kf.validate_args, kf.method = True, "doubling"
    assert torch.isfinite(kf(y, dt).log_likelihood).all()


# --------------------------------------------------------------------------- batching


@pytest.mark.parametrize("method", METHODS)
def test_batched_irregular_dt_equals_loop(method: str) -> None:
    rng = np.random.default_rng(0)
    F = t64(random_stable(3, 2))
    L, Qc, B = t64(rng.normal(size=(3, 2))), t64(np.eye(2)), t64(rng.normal(size=(3, 1)))
    # a batch mixing tiny, moderate and huge steps (different numbers of doublings)
    longest = 300.0 if method == "doubling" else 30.0  # matrix_exp's −Fᵀ block overflows at 300
    dt = t64(np.concatenate([[0.0, 1e-6], rng.exponential(1.0, size=20), [40.0, longest]]).reshape(4, 6))
    # matrix_exp's Q at dt 30-40 has lost PSD (refused when checked): this compares layouts, unchecked
    checked = method == "doubling"
    d = tl.discretize(F, L, Qc, dt, B=B, method=method, validate_args=checked)
    assert d.A.shape == (4, 6, 3, 3) and d.Q.shape == (4, 6, 3, 3) and d.G.shape == (4, 6, 3, 1)
    # torch.matrix_exp picks its Taylor degree from the whole batch: looser for matrix_exp
    rtol, atol = (1e-13, 1e-15) if method == "doubling" else (1e-11, 1e-14)
    for idx in np.ndindex(4, 6):
        single = tl.discretize(F, L, Qc, dt[idx], B=B, method=method, validate_args=checked)
        np.testing.assert_allclose(d.A[idx], single.A, rtol=rtol, atol=atol)
        np.testing.assert_allclose(d.Q[idx], single.Q, rtol=rtol, atol=atol)
        np.testing.assert_allclose(d.G[idx], single.G, rtol=rtol, atol=atol)


def test_batched_parameters_broadcast_against_dt() -> None:
    rng = np.random.default_rng(1)
    F = torch.stack([t64(random_stable(2, i)) for i in range(3)])[:, None]  # (3, 1, 2, 2)
    L, Qc = t64(np.eye(2)), t64(np.diag([1.0, 2.0]))
    dt = t64(rng.exponential(1.0, size=(3, 5)))
    d = tl.discretize(F, L, Qc, dt)
    assert d.Q.shape == (3, 5, 2, 2)
    for i in range(3):
        for t in range(5):
            A_ref, Q_ref, _ = quad_discretize(F[i, 0].numpy(), np.diag([1.0, 2.0]), None, float(dt[i, t]))
            assert rel_err(d.A[i, t], A_ref) < 1e-12
            assert rel_err(d.Q[i, t], Q_ref) < 1e-11


@settings(max_examples=25, deadline=None)
@given(
    f_batch=st.lists(st.integers(1, 3), min_size=0, max_size=2),
    dt_batch=st.lists(st.integers(1, 3), min_size=0, max_size=2),
    n=st.integers(1, 3),
    seed=st.integers(0, 10_000),
)
def test_broadcast_shapes_property(f_batch, dt_batch, n, seed) -> None:
    """Output batch = broadcast(F batch, dt batch) and every element equals its single call."""
    # make the two batch shapes broadcastable by construction: pad and replace mismatches by 1
    width = max(len(f_batch), len(dt_batch))
    fb = [1] * (width - len(f_batch)) + f_batch
    db = [1] * (width - len(dt_batch)) + dt_batch
    db = [d if (d == f or d == 1 or f == 1) else 1 for f, d in zip(fb, db)]
    fb = fb[width - len(f_batch) :] if f_batch else []
    db = db[width - len(dt_batch) :] if dt_batch else []
    gen = torch.Generator().manual_seed(seed)
    F = torch.randn(*fb, n, n, generator=gen, dtype=f64)
    dt = torch.rand(tuple(db), generator=gen, dtype=f64) * 3
    L, Qc = torch.eye(n, dtype=f64), torch.eye(n, dtype=f64)
    d = tl.discretize(F, L, Qc, dt)
    batch = torch.broadcast_shapes(tuple(fb), tuple(db))
    assert d.A.shape == (*batch, n, n) and d.Q.shape == (*batch, n, n)
    Fb, dtb = F.expand(*batch, n, n), dt.expand(batch)
    for idx in np.ndindex(*batch):
        single = tl.discretize(Fb[idx], L, Qc, dtb[idx])
        np.testing.assert_allclose(d.A[idx], single.A, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(d.Q[idx], single.Q, rtol=1e-12, atol=1e-14)


# --------------------------------------------------------------------------- gradients


def _sym(X: torch.Tensor) -> torch.Tensor:
    return 0.5 * (X + X.mT)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("F_kind", ["random", "nilpotent"])
def test_gradcheck_all_inputs(method: str, F_kind: str) -> None:
    rng = np.random.default_rng(4)
    n = 3
    F0 = rng.normal(size=(n, n)) if F_kind == "random" else np.diag(np.ones(n - 1), 1)
    F = t64(F0).requires_grad_()
    L = t64(rng.normal(size=(n, 2))).requires_grad_()
    M = rng.normal(size=(2, 2))
    Qc = t64(M @ M.T + np.eye(2)).requires_grad_()
    B = t64(rng.normal(size=(n, 1))).requires_grad_()
    dt = t64([0.3, 1.7, 6.0]).requires_grad_()

    def fn(F, L, Qc, B, dt):
        d = tl.discretize(F, L, _sym(Qc), dt, B=B, method=method)
        return d.A, d.Q, d.G

    assert torch.autograd.gradcheck(fn, (F, L, Qc, B, dt), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_matrix_exp_gradient_is_the_exact_maps_where_its_own_backward_fails() -> None:
    """torch.matrix_exp's backward of the Van Loan block went wrong long before its values:
    a Matérn-5/2 (lengthscale 1.3) over dt = 20 gave dQ[0,0]/dℓ = 2e21 where the exact value is
    ≈ 0 (Q has converged to P∞). The method's values stay the block's; its gradient is the doubling's."""
    ell = t64(1.3).requires_grad_()

    def matern52() -> torch.Tensor:
        lam = 5.0**0.5 / ell
        zero, one = 0 * lam, 1 + 0 * lam
        return torch.stack([torch.stack([zero, one, zero]), torch.stack([zero, zero, one]),
                            torch.stack([-(lam**3), -3 * lam**2, -3 * lam])])  # fmt: skip

    L, Qc = t64([[0.0], [0.0], [1.0]]), t64([[1.0]])
    for dt in (0.5, 10.0, 20.0):
        naive = tl.discretize(matern52(), L, Qc, t64(dt), method="matrix_exp")
        exact = tl.discretize(matern52(), L, Qc, t64(dt))
        torch.testing.assert_close(naive.Q, exact.Q, rtol=1e-6, atol=1e-9)  # the values: close
        g_naive = torch.autograd.grad(naive.Q[0, 0] + naive.A.sum(), ell)[0]
        g_exact = torch.autograd.grad(exact.Q[0, 0] + exact.A.sum(), ell)[0]
        torch.testing.assert_close(g_naive, g_exact, rtol=1e-12, atol=1e-12)
    # without a gradient asked for, the block exponential alone (no doubling)
    with torch.no_grad():
        d = tl.discretize(matern52(), L, Qc, t64(20.0), method="matrix_exp")
    assert not d.Q.requires_grad


def test_gradcheck_propagate_and_stationary() -> None:
    rng = np.random.default_rng(8)
    F = t64(random_stable(2, 8)).requires_grad_()
    L = t64(rng.normal(size=(2, 2))).requires_grad_()
    Qc = t64(np.eye(2)).requires_grad_()
    m0 = t64([0.3, -1.0]).requires_grad_()
    P0 = t64([[1.0, 0.2], [0.2, 0.5]]).requires_grad_()
    dt = t64(0.9).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda F, L, Qc, m0, P0, dt: tl.propagate(m0, _sym(P0), F, L, _sym(Qc), dt), (F, L, Qc, m0, P0, dt)
    )
    assert torch.autograd.gradcheck(lambda F, L, Qc: tl.stationary_covariance(F, L, _sym(Qc)), (F, L, Qc))


def test_float32_and_dtype_promotion() -> None:
    F = torch.tensor([[0.0, 1.0], [0.0, -0.5]])
    L, Qc = torch.tensor([[0.0], [1.0]]), torch.tensor([[1.0]])
    d32 = tl.discretize(F, L, Qc, 0.5)
    assert d32.A.dtype == torch.float32 and d32.Q.dtype == torch.float32
    d64 = tl.discretize(F.double(), L, Qc, 0.5)
    assert d64.Q.dtype == torch.float64
    assert rel_err(d32.Q.double(), d64.Q.numpy()) < 1e-6


def test_propagate_matches_manual_moments() -> None:
    F, L, Qc, B = t64([[0, 1], [-2, -0.3]]), t64([[0], [1]]), t64([[0.4]]), t64([[0], [1]])
    m0, P0, u = t64([1.0, 0.0]), t64(np.eye(2)), t64([0.5])
    d = tl.discretize(F, L, Qc, t64(0.7), B=B)
    m, P = tl.propagate(m0, P0, F, L, Qc, t64(0.7), B=B, u=u)
    np.testing.assert_allclose(m, d.A @ m0 + d.G @ u, rtol=1e-14)
    np.testing.assert_allclose(P, d.A @ P0 @ d.A.T + d.Q, rtol=1e-14)


def test_process_noise_and_zero_order_hold_are_the_discretize_blocks() -> None:
    F, L, Qc, B = t64([[0, 1], [-2, -0.3]]), t64([[0], [1]]), t64([[0.4]]), t64([[0], [1]])
    dt = t64([0.1, 2.0])
    d = tl.discretize(F, L, Qc, dt, B=B)
    np.testing.assert_allclose(tl.process_noise(F, L, Qc, dt), d.Q, rtol=1e-15)
    A, G = tl.zero_order_hold(F, B, dt)
    np.testing.assert_allclose(A, d.A, rtol=1e-15)
    np.testing.assert_allclose(G, d.G, rtol=1e-15)


def test_matrix_exp_overflow_of_a_marginally_stable_f_names_the_method() -> None:
    """Singer (integrators next to a stable mode) in float32 over a long step: the doubling
    is finite, matrix_exp overflows through its −Fᵀ block and the error says so."""
    import torchsde_lti as tl

    m = tl.models.singer(0.5, 2.0, dtype=torch.float32).matrices()
    dt = torch.tensor([300.0])
    assert torch.isfinite(tl.discretize(m.F, m.L, m.Qc, dt).Q).all()
    with pytest.raises(ValueError, match="method='matrix_exp' overflows"):
        tl.discretize(m.F, m.L, m.Qc, dt, method="matrix_exp")


@pytest.mark.parametrize("n, p", [(1, 2), (2, 3)])
def test_matrix_exp_with_noise_and_more_inputs_than_states(n: int, p: int) -> None:
    """method="matrix_exp" with W and B of p > n columns: G (n, p) as the doubling's and the
    zero-order-hold quadrature's (the block's zero row took min(n, p) columns: a size error)."""
    g = torch.Generator().manual_seed(n + p)
    F = -torch.eye(n, dtype=torch.float64) + 0.3 * torch.randn(n, n, generator=g, dtype=torch.float64)
    L, Qc = torch.eye(n, dtype=torch.float64), torch.eye(n, dtype=torch.float64)
    B = torch.randn(n, p, generator=g, dtype=torch.float64)
    d = tl.discretize(F, L, Qc, 0.7, B=B, method="matrix_exp")
    ref = tl.discretize(F, L, Qc, 0.7, B=B)
    Fn = F.numpy()
    G_quad = scipy.linalg.expm(np.block([[Fn, B.numpy()], [np.zeros((p, n + p))]]) * 0.7)[:n, n:]
    assert d.G is not None and d.G.shape == (n, p)
    np.testing.assert_allclose(d.G.numpy(), G_quad, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(d.Q, ref.Q, rtol=1e-12, atol=1e-14)


def test_propagate_returns_both_moments_over_the_whole_batch() -> None:
    """propagate with one m0 (n,) and three P0 (3, n, n): m and P both of batch (3,) (m came back
    (n,)), each the single-prior result."""
    F = torch.tensor([[0.0, 1.0], [-1.0, -0.5]], dtype=torch.float64)
    L, Qc = torch.tensor([[0.0], [1.0]], dtype=torch.float64), torch.eye(1, dtype=torch.float64)
    m0 = torch.tensor([1.0, -2.0], dtype=torch.float64)
    P0 = torch.stack([k * torch.eye(2, dtype=torch.float64) for k in (1.0, 2.0, 3.0)])
    m, P = tl.propagate(m0, P0, F, L, Qc, torch.tensor(0.5, dtype=torch.float64))
    assert m.shape == (3, 2) and P.shape == (3, 2, 2)
    for i in range(3):
        mi, Pi = tl.propagate(m0, P0[i], F, L, Qc, 0.5)
        torch.testing.assert_close(m[i], mi, rtol=0, atol=0)
        torch.testing.assert_close(P[i], Pi, rtol=0, atol=0)


def test_matrix_exp_overflow_names_the_stable_block() -> None:
    """A finite exact result that method="matrix_exp" overflows (a fast stable mode next to a slightly
    unstable one): the error names the −Fᵀ block and the doubling, not the unstable mode or float64."""
    F = torch.diag(torch.tensor([-50.0, 0.01], dtype=torch.float64))
    I2 = torch.eye(2, dtype=torch.float64)
    assert bool(torch.isfinite(tl.discretize(F, I2, I2, 100.0).Q).all())
    with pytest.raises(ValueError, match=r"−Fᵀ block.*method='doubling'") as err:
        tl.discretize(F, I2, I2, 100.0, method="matrix_exp")
    assert "float64" not in str(err.value).split("(", 1)[1]
