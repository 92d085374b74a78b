"""The design card's layers (Transition, VanLoanNoise, Discretization) and method= everywhere.

"matrix_exp" must really call torch.matrix_exp (counted), agree with the doubling default to
1e-12 on benign inputs (float64), and the filter with method="matrix_exp" must equal the
default filter to 1e-9. Values are also checked against scipy's block exponentials.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from tests.reference import scipy_discretize

F64 = torch.float64


def benign(seed: int = 0, batch: tuple[int, ...] = (5,), n: int = 3, s: int = 2, p: int = 2):
    g = torch.Generator().manual_seed(seed)
    F = 0.5 * torch.randn(*batch, n, n, generator=g, dtype=F64) - 0.3 * torch.eye(n, dtype=F64)
    L = torch.randn(*batch, n, s, generator=g, dtype=F64)
    C = torch.randn(*batch, s, s, generator=g, dtype=F64)
    Qc = C @ C.mT + 0.1 * torch.eye(s, dtype=F64)
    B = torch.randn(*batch, n, p, generator=g, dtype=F64)
    dt = 0.05 + torch.rand(*batch, generator=g, dtype=F64)
    return F, L, Qc, B, dt


def test_transition_layer_matrix_exp_calls_torch_and_agrees(count_matrix_exp: list) -> None:
    F, _, _, B, dt = benign()
    A_me = tl.Transition(method="matrix_exp")(F, dt)
    assert len(count_matrix_exp) == 1 and count_matrix_exp[0][-2:] == (3, 3)
    A_me2, G_me = tl.Transition(method="matrix_exp")(F, dt, B=B)
    assert len(count_matrix_exp) == 2 and count_matrix_exp[1][-2:] == (5, 5)  # ZOH block n + p
    A_db = tl.Transition()(F, dt)  # small calls may be routed to torch.matrix_exp (test_routing.py)
    A_db2, G_db = tl.Transition(method="doubling")(F, dt, B=B)
    for a, b in ((A_me, A_db), (A_me2, A_db2), (G_me, G_db)):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)
    A_ref, _, G_ref = zip(
        *(
            scipy_discretize(F[i].numpy(), np.zeros((3, 1)), np.zeros((1, 1)), float(dt[i]), B[i].numpy())
            for i in range(5)
        )
    )
    np.testing.assert_allclose(A_me.numpy(), np.stack(A_ref), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(G_me.numpy(), np.stack(G_ref), rtol=1e-12, atol=1e-13)


def test_van_loan_noise_layer_matrix_exp_calls_torch_and_agrees(count_matrix_exp: list) -> None:
    F, L, Qc, _, dt = benign(seed=1)
    Q_me = tl.VanLoanNoise(method="matrix_exp")(F, L, Qc, dt)
    assert len(count_matrix_exp) == 1 and count_matrix_exp[0][-2:] == (6, 6)  # Van Loan block 2n
    Q_db = tl.VanLoanNoise()(F, L, Qc, dt)
    assert torch.allclose(Q_me, Q_db, rtol=1e-12, atol=1e-12)
    assert torch.equal(Q_me, Q_me.mT)
    Q_ref = np.stack([scipy_discretize(F[i].numpy(), L[i].numpy(), Qc[i].numpy(), float(dt[i]))[1] for i in range(5)])
    np.testing.assert_allclose(Q_me.numpy(), Q_ref, rtol=1e-11, atol=1e-13)


def test_discretization_layer_is_one_joint_evaluation(count_matrix_exp: list) -> None:
    F, L, Qc, B, dt = benign(seed=2)
    d = tl.Discretization(method="matrix_exp")(F, L, Qc, dt, B)
    assert len(count_matrix_exp) == 1 and count_matrix_exp[0][-2:] == (8, 8)  # [[F, W, B], [0, -Fᵀ, 0], [0, 0, 0]]
    ref = tl.discretize(F, L, Qc, dt, B=B)
    for a, b in zip(d, ref):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("method", ["doubling", "matrix_exp"])
def test_layers_broadcast_float32_and_gradients(method: str) -> None:
    F, L, Qc, B, _ = benign(seed=3, batch=(1,))
    dt = torch.tensor([[0.1, 0.7], [0.3, 1.2]], dtype=F64)  # (2, 2) against F (1, n, n)
    d = tl.Discretization(method=method)(F, L, Qc, dt, B)
    assert d.A.shape == (2, 2, 3, 3) and d.Q.shape == (2, 2, 3, 3) and d.G.shape == (2, 2, 3, 2)
    d32 = tl.Discretization(method=method)(*(x.float() for x in (F, L, Qc)), dt.float(), B.float())
    assert d32.A.dtype == torch.float32
    assert torch.allclose(d32.Q.double(), d.Q, rtol=1e-4, atol=1e-5)
    args = [x[0].clone().requires_grad_() for x in (F, L, Qc)] + [torch.tensor(0.4, dtype=F64, requires_grad=True)]

    def noise(F_: torch.Tensor, L_: torch.Tensor, Qc_: torch.Tensor, dt_: torch.Tensor) -> torch.Tensor:
        return tl.VanLoanNoise(method=method)(F_, L_, 0.5 * (Qc_ + Qc_.mT), dt_)

    assert torch.autograd.gradcheck(noise, args)
    assert torch.autograd.gradcheck(lambda F_, dt_: tl.Transition(method=method)(F_, dt_), (args[0], args[3]))


def test_unknown_method_raises() -> None:
    with pytest.raises(ValueError, match="method must be one of"):
        tl.Transition(method="pade")
    F, L, Qc, _, dt = benign()
    with pytest.raises(ValueError, match="method"):
        tl.discretize(F, L, Qc, dt, method="euler")
    with pytest.raises(ValueError, match="method"):
        tl.LTISDE(F[0], L[0], Qc[0], method="euler")


def test_method_reaches_sde_and_filter(count_matrix_exp: list) -> None:
    """KalmanFilter(method="matrix_exp") discretises through torch.matrix_exp and equals the default filter."""
    sde = tl.models.singer(alpha=0.4, q=0.8, dim=2, dtype=F64)
    H = tl.models.position_observation(sde)
    R = 0.3 * torch.eye(2, dtype=F64)
    g = torch.Generator().manual_seed(4)
    dt = 0.05 + torch.rand(3, 40, generator=g, dtype=F64)
    y = torch.randn(3, 40, 2, generator=g, dtype=F64)
    y[0, 5] = float("nan")
    ref = tl.KalmanFilter(sde, H, R)(y, dt)
    assert not count_matrix_exp
    kf = tl.KalmanFilter(sde, H, R, method="matrix_exp")
    assert kf.discretization_method == "matrix_exp"
    out = kf(y, dt)
    assert count_matrix_exp, "method='matrix_exp' did not reach torch.matrix_exp"
    assert torch.allclose(out.log_likelihood, ref.log_likelihood, rtol=1e-9, atol=1e-9)
    assert torch.allclose(out.mean, ref.mean, rtol=1e-9, atol=1e-9)
    assert torch.allclose(out.cov, ref.cov, rtol=1e-9, atol=1e-9)
    fc_ref = tl.KalmanFilter(sde, H, R).forecast(ref, torch.tensor([0.5, 2.0], dtype=F64))
    fc = kf.forecast(out, torch.tensor([0.5, 2.0], dtype=F64))
    assert torch.allclose(fc.cov, fc_ref.cov, rtol=1e-9, atol=1e-9)
    # the SDE's own default method is used when the filter has none
    sde.method = "matrix_exp"
    n_calls = len(count_matrix_exp)
    out2 = tl.KalmanFilter(sde, H, R)(y, dt)
    assert len(count_matrix_exp) > n_calls
    assert torch.allclose(out2.log_likelihood, ref.log_likelihood, rtol=1e-9, atol=1e-9)
    d = sde(dt)
    assert torch.allclose(d.A, tl.discretize(sde.F, sde.L, sde.Qc, dt).A, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("method", ["doubling", "matrix_exp"])
def test_functional_method_keyword(method: str) -> None:
    F, L, Qc, B, dt = benign(seed=5)
    d = tl.discretize(F, L, Qc, dt, B=B, method=method)
    assert torch.allclose(tl.transition_matrix(F, dt, method=method), d.A, rtol=1e-12, atol=1e-13)
    A, G = tl.zero_order_hold(F, B, dt, method=method)
    assert torch.allclose(A, d.A, rtol=1e-12, atol=1e-13) and torch.allclose(G, d.G, rtol=1e-12, atol=1e-13)
    assert torch.allclose(tl.process_noise(F, L, Qc, dt, method=method), d.Q, rtol=1e-12, atol=1e-13)
    m, P = tl.propagate(torch.zeros(3, dtype=F64), torch.eye(3, dtype=F64), F, L, Qc, dt, method=method)
    assert torch.allclose(P, d.A @ d.A.mT + d.Q, rtol=1e-12, atol=1e-12)
