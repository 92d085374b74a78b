"""Small calls of the default method: the doubling's power series (no torch.matrix_exp), accurate
against a 60-digit reference normwise and in Q's smallest eigen-direction, symmetric and
positive definite; integrator chains at tiny steps keep every entry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from tests.reference import mp_doubling

F64, F32 = torch.float64, torch.float32


def _problem(n: int, N: int, seed: int):
    """Per-element Hurwitz F, SPD Qc, L = I, dt log-uniform in [1e-3, 10] (float64)."""
    g = torch.Generator().manual_seed(seed)
    M = torch.randn(N, n, n, generator=g, dtype=F64) / math.sqrt(n)
    F = M - (torch.linalg.eigvals(M).real.amax(-1) + 0.5)[:, None, None] * torch.eye(n, dtype=F64)
    C = torch.randn(N, n, n, generator=g, dtype=F64)
    Qc = C @ C.mT / n + 0.1 * torch.eye(n, dtype=F64)
    dt = torch.exp(torch.empty(N, dtype=F64).uniform_(math.log(1e-3), math.log(10.0), generator=g))
    return F, torch.eye(n, dtype=F64), Qc, dt


@pytest.mark.parametrize("dtype", [F32, F64], ids=["f32", "f64"])
@pytest.mark.parametrize("n", [1, 2, 4, 8])
def test_small_calls_are_accurate_and_positive_definite(count_matrix_exp: list, n: int, dtype: torch.dtype) -> None:
    F, L, Qc, dt = (t.to(dtype) for t in _problem(n, 6, seed=n))
    d = tl.discretize(F, L, Qc, dt)
    assert not count_matrix_exp  # the default never calls torch.matrix_exp
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


def test_one_element_where_matrix_exp_of_the_van_loan_block_loses_digits() -> None:
    """A benign call (‖F‖ dt = 0.02, Qc SPD) on which torch.matrix_exp of the Van Loan block
    gives Q to 3e-11 only (its norm-based Taylor degree); the default is exact to rounding."""
    F, L, Qc, _ = _problem(4, 1, seed=0)
    F, Qc = F[0], Qc[0]
    dt = 0.02 / torch.linalg.matrix_norm(F)
    A_ref, Q_ref, _ = mp_doubling(F.numpy(), (L @ Qc @ L.T).numpy(), None, float(dt))
    d = tl.discretize(F, L, Qc, dt)
    naive = tl.discretize(F, L, Qc, dt, method="matrix_exp")
    assert np.linalg.norm(naive.Q.numpy() - Q_ref) > 1e-12 * np.linalg.norm(Q_ref)
    assert np.linalg.norm(d.Q.numpy() - Q_ref) <= 1e-14 * np.linalg.norm(Q_ref)
    assert np.linalg.norm(d.A.numpy() - A_ref) <= 1e-14 * np.linalg.norm(A_ref)


def test_integrator_chains_at_tiny_steps_keep_every_entry(count_matrix_exp: list) -> None:
    """A constant-acceleration Q at dt = 1e-4 spans q dt⁵/20 … q dt; torch.matrix_exp's
    norm-based Taylor degree drops its small entries, the default keeps them."""
    ca = tl.models.constant_acceleration(dim=1, q=2.5, dtype=F64)
    dt = torch.tensor(1e-4, dtype=F64)
    with torch.no_grad():
        d = ca(dt)
        assert not count_matrix_exp
        assert abs(float(d.Q[0, 0]) / (2.5 * 1e-20 / 20) - 1) < 1e-12
        naive = ca(dt, method="matrix_exp")
    assert count_matrix_exp
    assert abs(float(naive.Q[0, 0]) / (2.5 * 1e-20 / 20) - 1) > 1e-3
