"""Small calls of the default method go to one torch.matrix_exp exactly where the a-priori
bound of ``_matrix_exp.accurate`` holds, and are accurate there: Q normwise and in its
smallest eigen-direction against a 60-digit reference, symmetric positive definite."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from tests.reference import mp_doubling
from torchsde_lti.core import _matrix_exp

F64, F32 = torch.float64, torch.float32


@pytest.fixture
def calls(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, ...]]:
    seen: list[tuple[int, ...]] = []
    original = torch.matrix_exp

    def counting(x: torch.Tensor) -> torch.Tensor:
        seen.append(tuple(x.shape))
        return original(x)

    monkeypatch.setattr(torch, "matrix_exp", counting)
    return seen


def _benign(n: int, N: int, dtype: torch.dtype, seed: int = 0, scale: float = 0.9):
    """Per-element F with ‖F‖_F dt = scale · θ_F, well-conditioned W (Qc SPD, L = I)."""
    g = torch.Generator().manual_seed(seed)
    F = torch.randn(N, n, n, generator=g, dtype=F64)
    C = torch.randn(N, n, n, generator=g, dtype=F64)
    Qc = C @ C.mT / n + 0.5 * torch.eye(n, dtype=F64)
    theta_f, theta_c, _ = _matrix_exp.ROUTE_BOUNDS[dtype]
    f, w = torch.linalg.matrix_norm(F), torch.linalg.matrix_norm(Qc)
    step = torch.minimum(theta_f / f, theta_c / (2 * f.square() + w.square()).sqrt())
    dt = scale * step * torch.rand(N, generator=g, dtype=F64).clamp_min(0.05)
    return F.to(dtype), torch.eye(n, dtype=dtype), Qc.to(dtype), dt.to(dtype)


@pytest.mark.parametrize("dtype", [F32, F64], ids=["f32", "f64"])
@pytest.mark.parametrize("n", [1, 2, 4, 8])
def test_routed_calls_are_accurate_and_positive_definite(calls: list, n: int, dtype: torch.dtype) -> None:
    F, L, Qc, dt = _benign(n, 6, dtype, seed=n)
    d = tl.discretize(F, L, Qc, dt)
    assert len(calls) == 1  # routed: one torch.matrix_exp of the (6, 2n, 2n) Van Loan blocks
    tol = 2e-6 if dtype == F32 else 1e-13
    for i in range(6):
        W = (L @ Qc[i] @ L.T).double().numpy()
        A_ref, Q_ref, _ = mp_doubling(F[i].double().numpy(), W, None, float(dt[i]))
        Qi = d.Q[i].double().numpy()
        assert np.linalg.norm(d.A[i].double().numpy() - A_ref) <= tol * np.linalg.norm(A_ref)
        assert np.linalg.norm(Qi - Q_ref) <= tol * np.linalg.norm(Q_ref)
        lam, lam_ref = np.linalg.eigvalsh(Qi), np.linalg.eigvalsh(Q_ref)
        assert lam.min() > 0 and abs(lam.min() - lam_ref.min()) <= 10 * tol * lam_ref.max()
        assert np.array_equal(Qi, Qi.T)


@pytest.mark.parametrize("dtype", [F32, F64], ids=["f32", "f64"])
def test_calls_outside_the_bound_take_the_doubling(calls: list, dtype: torch.dtype) -> None:
    F, L, Qc, dt = _benign(3, 4, dtype)
    tl.discretize(F, L, Qc, dt)
    assert len(calls) == 1
    tl.discretize(F, L, Qc, 3.0 * dt)  # ‖F‖ dt beyond θ_F
    tl.discretize(F, L, 1e6 * Qc, dt)  # ‖C‖ dt beyond θ_C: torch would square
    rank_one = torch.zeros(3, 1, dtype=dtype)
    rank_one[-1] = 1.0
    tl.discretize(F, rank_one, Qc[:, :1, :1], dt)  # rank-deficient W: a graded Q
    tl.discretize(F[0], L, Qc[0], torch.full((1000,), 1e-3, dtype=dtype))  # many elements
    tl.discretize(F.half(), L.half(), Qc.half(), dt.half())  # no bound for half precision
    assert len(calls) == 1
    tl.discretize(F, L, Qc, dt, method="matrix_exp")
    assert len(calls) == 2


def test_integrator_chains_at_tiny_steps_keep_every_entry(calls: list) -> None:
    """The reason for the conditioning bound: a constant-acceleration Q at dt = 1e-4 spans
    q dt⁵/20 … q dt; torch.matrix_exp's norm-based Taylor degree drops its small entries."""
    ca = tl.models.constant_acceleration(dim=1, q=2.5, dtype=F64)
    dt = torch.tensor(1e-4, dtype=F64)
    with torch.no_grad():
        d = ca(dt)
        assert not calls
        assert abs(float(d.Q[0, 0]) / (2.5 * 1e-20 / 20) - 1) < 1e-12
        naive = ca(dt, method="matrix_exp")
    assert abs(float(naive.Q[0, 0]) / (2.5 * 1e-20 / 20) - 1) > 1e-3
