"""LTISDE module: matrices, discretisation vs scipy, assignment, batching, state_dict, dtype, gradients."""

from __future__ import annotations

import io

import numpy as np
import pytest
import scipy.linalg
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from torch.func import functional_call

import torchsde_lti as tl
from tests.reference import scipy_discretize
from torchsde_lti.nn.parametrizations import IntegratorChain

F64 = torch.float64


# ----------------------------------------------------------------------------- references
def example_matrices(seed: int = 0, n: int = 3, s: int = 2, p: int = 1):
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(n, n))
    F = M - (np.linalg.eigvals(M).real.max() + 0.5) * np.eye(n)  # Hurwitz
    L = rng.normal(size=(n, s))
    a = rng.normal(size=(s, s))
    Qc = a @ a.T + 0.5 * np.eye(s)
    B = rng.normal(size=(n, p))
    return F, L, Qc, B


def t(x: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(x, dtype=F64)


@pytest.fixture
def mats():
    return example_matrices()


# ----------------------------------------------------------------------------- construction
def test_reads_back_matrices_and_registers_parameters_and_buffers(mats) -> None:
    F, L, Qc, B = mats
    sde = tl.LTISDE(t(F), t(L), t(Qc), t(B), learn=("F", "Qc"))
    np.testing.assert_allclose(sde.F.detach().numpy(), F, rtol=1e-15, atol=0)
    np.testing.assert_array_equal(sde.L.numpy(), L)
    np.testing.assert_allclose(sde.Qc.detach().numpy(), Qc, rtol=1e-14, atol=1e-15)
    np.testing.assert_array_equal(sde.B.numpy(), B)
    params = {n for n, _ in sde.named_parameters()}
    buffers = {n for n, _ in sde.named_buffers() if not n.endswith("_ref")}
    assert params == {"parametrizations.F.original", "parametrizations.Qc.original"}
    assert buffers == {"parametrizations.L.original", "parametrizations.B.original"}
    assert (sde.state_dim, sde.noise_dim, sde.input_dim) == (3, 2, 1)
    assert sde.batch_shape == torch.Size([])
    no_b = tl.LTISDE(t(F), t(L), t(Qc))
    assert no_b.B is None and no_b.input_dim == 0 and no_b(0.1).G is None


def test_learn_everything_and_nothing(mats) -> None:
    F, L, Qc, B = mats
    sde = tl.LTISDE(t(F), t(L), t(Qc), t(B), learn=("F", "L", "Qc", "B"))
    assert len(list(sde.parameters())) == 4
    frozen = tl.LTISDE(t(F), t(L), t(Qc), t(B), learn=())
    assert len(list(frozen.parameters())) == 0
    np.testing.assert_allclose(frozen.Qc.numpy(), Qc, rtol=1e-14)


# ----------------------------------------------------------------------------- computations vs scipy
@pytest.mark.parametrize("method", ["doubling", "matrix_exp"])
def test_forward_matches_scipy(mats, method: str) -> None:
    F, L, Qc, B = mats
    sde = tl.LTISDE(t(F), t(L), t(Qc), t(B), F_constraint="hurwitz")
    dts = [0.05, 0.7, 2.0]
    d = sde(t(np.array(dts)), method=method)
    assert d.A.shape == (3, 3, 3) and d.Q.shape == (3, 3, 3) and d.G.shape == (3, 3, 1)
    for i, dt in enumerate(dts):
        A, Q, G = scipy_discretize(F, L, Qc, dt, B)
        np.testing.assert_allclose(d.A[i].detach().numpy(), A, rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(d.Q[i].detach().numpy(), Q, rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(d.G[i].detach().numpy(), G, rtol=1e-10, atol=1e-13)


def test_stationary_transition_and_propagate_match_scipy(mats) -> None:
    F, L, Qc, B = mats
    sde = tl.LTISDE(t(F), t(L), t(Qc), t(B))
    P_inf = scipy.linalg.solve_continuous_lyapunov(F, -L @ Qc @ L.T)
    np.testing.assert_allclose(sde.stationary_covariance().detach().numpy(), P_inf, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(
        sde.transition_matrix(0.4).detach().numpy(), scipy.linalg.expm(0.4 * F), rtol=1e-10, atol=1e-14
    )
    m0, P0, u = np.array([1.0, -2.0, 0.5]), np.diag([1.0, 2.0, 0.5]), np.array([0.3])
    m, P = sde.propagate(t(m0), t(P0), 0.4, u=t(u))
    A, Q, G = scipy_discretize(F, L, Qc, 0.4, B)
    np.testing.assert_allclose(m.detach().numpy(), A @ m0 + G @ u, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(P.detach().numpy(), A @ P0 @ A.T + Q, rtol=1e-10, atol=1e-13)


# ----------------------------------------------------------------------------- assignment
def test_assignment_goes_through_right_inverse_in_place(mats) -> None:
    F, L, Qc, B = mats
    sde = tl.LTISDE(t(F), t(L), t(Qc), t(B), learn=("F", "L", "Qc", "B"), F_constraint="hurwitz")
    before = {n: id(p) for n, p in sde.named_parameters()}
    F2, L2, Qc2, B2 = example_matrices(seed=7)
    sde.F, sde.L, sde.Qc, sde.B = t(F2), t(L2), t(Qc2), t(B2)
    np.testing.assert_allclose(sde.F.detach().numpy(), F2, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sde.Qc.detach().numpy(), Qc2, rtol=1e-13, atol=1e-14)
    np.testing.assert_array_equal(sde.L.detach().numpy(), L2)
    np.testing.assert_array_equal(sde.B.detach().numpy(), B2)
    assert before == {n: id(p) for n, p in sde.named_parameters()}  # optimiser keeps its tensors
    sde.Qc = 2.0 * np.eye(2)  # array-like and float32 tensors are cast to the module's dtype
    assert sde.Qc.dtype == F64
    sde.L = torch.ones(3, 2, dtype=torch.float32)
    assert sde.L.dtype == F64


def test_bad_assignment_raises(mats) -> None:
    F, L, Qc, B = mats
    sde = tl.LTISDE(t(F), t(L), t(Qc), t(B), F_constraint="hurwitz")
    with pytest.raises(ValueError, match="Qc"):
        sde.Qc = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=F64)
    with pytest.raises(ValueError, match="Hurwitz"):
        sde.F = torch.eye(3, dtype=F64)
    with pytest.raises(ValueError, match="L"):
        sde.L = torch.ones(2, 2, dtype=F64)


def test_assignment_of_wrong_size_raises_and_keeps_the_module(mats) -> None:
    # L (3, 2): Qc must stay (2, 2); F (3, 3) even where the new value would satisfy the constraint
    F, L, Qc, B = mats
    sde = tl.LTISDE(t(F), t(L), t(Qc), t(B), F_constraint="hurwitz")
    with pytest.raises(ValueError, match=r"Qc.*\(3, 3\)"):
        sde.Qc = torch.eye(3, dtype=F64)  # symmetric PD, but not (s, s)
    with pytest.raises(ValueError, match=r"F.*\(4, 4\)"):
        sde.F = -torch.eye(4, dtype=F64)  # Hurwitz, but not (n, n)
    assert sde.Qc.shape == (2, 2) and sde.F.shape == (3, 3)
    np.testing.assert_allclose(sde(t(np.array(0.3))).Q.detach().numpy(), scipy_discretize(F, L, Qc, 0.3)[1], rtol=1e-9)


# ----------------------------------------------------------------------------- batching
def test_batched_parameters_equal_loop() -> None:
    Fs, Ls, Qcs = zip(*(example_matrices(seed)[:3] for seed in range(4)))
    F = t(np.stack(Fs))  # (4, n, n): four different drifts
    Qc = t(np.stack(Qcs))
    L = t(Ls[0])  # shared noise gain broadcasts
    sde = tl.LTISDE(F, L, Qc, F_constraint="hurwitz")
    assert sde.batch_shape == (4,)
    dt = t(np.array([0.1, 0.5, 1.0, 3.0]))
    d = sde(dt)
    series = sde(t(np.linspace(0.1, 2.0, 12).reshape(4, 3)), series=True)
    assert series.A.shape == (4, 3, 3, 3)
    for i in range(4):
        single = tl.LTISDE(F[i], L, Qc[i])
        di = single(dt[i])
        torch.testing.assert_close(d.A[i], di.A, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(d.Q[i], di.Q, rtol=1e-12, atol=1e-14)
        for k in range(3):
            dk = single(t(np.linspace(0.1, 2.0, 12).reshape(4, 3))[i, k])
            torch.testing.assert_close(series.Q[i, k], dk.Q, rtol=1e-12, atol=1e-14)
    # plain right-aligned broadcasting: one dt per step shared by the 4 models
    assert sde(t(np.array([[0.1], [0.2]]))).A.shape == (2, 4, 3, 3)


# ----------------------------------------------------------------------------- state_dict and dtype
def test_state_dict_round_trip_is_exact(mats) -> None:
    F, L, Qc, B = mats
    src = tl.LTISDE(t(F), t(L), t(Qc), t(B), learn=("F", "L", "Qc", "B"), F_constraint="hurwitz")
    opt = torch.optim.Adam(src.parameters(), lr=0.1)
    for _ in range(5):  # move away from the initial values
        loss = src(0.3).Q.sum() + src.F.sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    F2, L2, Qc2, B2 = example_matrices(seed=3)
    dst = tl.LTISDE(t(F2), t(L2), t(Qc2), t(B2), learn=("F", "L", "Qc", "B"), F_constraint="hurwitz")
    dst.load_state_dict(src.state_dict())
    for a, b in zip(src.matrices(), dst.matrices()):
        assert torch.equal(a, b)
    buf = io.BytesIO()
    torch.save(src.state_dict(), buf)
    buf.seek(0)
    dst2 = tl.LTISDE(t(F2), t(L2), t(Qc2), t(B2), learn=("F", "L", "Qc", "B"), F_constraint="hurwitz")
    dst2.load_state_dict(torch.load(buf))
    assert torch.equal(src(0.7).Q, dst2(0.7).Q)


def test_to_float32(mats) -> None:
    F, L, Qc, B = mats
    sde = tl.LTISDE(t(F), t(L), t(Qc), t(B), F_constraint="hurwitz").to(torch.float32)
    m = sde.matrices()
    assert all(x.dtype == torch.float32 for x in m)
    np.testing.assert_allclose(m.F.detach().numpy(), F, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(m.Qc.detach().numpy(), Qc, rtol=1e-5, atol=1e-6)
    d = sde(torch.tensor([0.01, 1.0, 50.0]))
    assert d.Q.dtype == torch.float32
    _, Q_ref, _ = scipy_discretize(F, L, Qc, 1.0, B)
    np.testing.assert_allclose(d.Q[1].detach().numpy(), Q_ref, rtol=1e-4, atol=1e-5)
    assert bool((torch.linalg.eigvalsh(d.Q.detach().double()) > -1e-6).all())
    sde.Qc = torch.eye(2, dtype=F64)  # assignment in float64 is cast to float32
    assert sde.Qc.dtype == torch.float32


# ----------------------------------------------------------------------------- gradients
def _gradcheck_module(sde: torch.nn.Module, dt: torch.Tensor) -> None:
    names = [n for n, _ in sde.named_parameters()]
    values = tuple(p.detach().clone().requires_grad_(True) for _, p in sde.named_parameters())
    assert names, "module has no parameters"

    def fn(dt_: torch.Tensor, *raw: torch.Tensor):
        d = functional_call(sde, dict(zip(names, raw)), (dt_,))
        return tuple(x for x in d if x is not None)

    assert torch.autograd.gradcheck(fn, (dt.clone().requires_grad_(True), *values))
    # every raw parameter receives a non-zero gradient from a generic scalar loss
    sde.zero_grad()
    d = sde(dt)
    (d.A.sum() + d.Q.sum() + (0 if d.G is None else d.G.sum())).backward()
    for n, p in sde.named_parameters():
        assert p.grad is not None and bool(p.grad.abs().sum() > 0), n


@pytest.mark.parametrize("constraint", [None, "hurwitz"])
def test_gradcheck_every_raw_parameter(constraint) -> None:
    F, L, Qc, B = example_matrices(seed=1, n=2, s=2, p=1)  # small: gradcheck cost ∝ number of raw entries
    sde = tl.LTISDE(t(F), t(L), t(Qc), t(B), learn=("F", "L", "Qc", "B"), F_constraint=constraint)
    _gradcheck_module(sde, t(np.array([0.3, 1.1])))


def test_gradcheck_integrator_chain_drag() -> None:
    F = np.zeros((4, 4))
    F[0, 1] = F[2, 3] = 1.0
    F[1, 1], F[3, 3], F[1, 3] = -0.5, -1.0, 0.2
    L = np.zeros((4, 2))
    L[1, 0] = L[3, 1] = 1.0
    sde = tl.LTISDE(t(F), t(L), t(np.eye(2)), F_constraint=IntegratorChain(2, 2, drag="hurwitz"))
    np.testing.assert_allclose(sde.F.detach().numpy(), F, rtol=1e-10, atol=1e-12)
    assert dict(sde.named_parameters())["parametrizations.F.original"].shape == (3, 2, 2)
    _gradcheck_module(sde, t(np.array([0.5])))


# ----------------------------------------------------------------------------- invariants under optimisation
raw_values = arrays(np.float64, (3, 3, 3), elements=st.floats(-4, 4, allow_nan=False))
qc_values = arrays(np.float64, (2, 2), elements=st.floats(-40, 40, allow_nan=False))


@settings(max_examples=25, deadline=None)
@given(raw_values, qc_values)
def test_constraints_hold_for_arbitrary_raw_parameters(raw_f: np.ndarray, raw_qc: np.ndarray) -> None:
    F, L, Qc, _ = example_matrices()
    sde = tl.LTISDE(t(F), t(L), t(Qc), F_constraint="hurwitz")
    with torch.no_grad():
        sde.parametrizations.F.original.copy_(t(raw_f))
        sde.parametrizations.Qc.original.copy_(t(raw_qc))
    m = sde.matrices()
    assert np.linalg.eigvals(m.F.detach().numpy()).real.max() < 0
    qc = m.Qc.detach().numpy()
    assert np.array_equal(qc, qc.T)
    assert np.linalg.eigvalsh(qc).min() >= -1e-12 * np.abs(qc).max()


def test_constraints_hold_after_many_large_steps() -> None:
    """Adam (lr=2) drives F to an unstable target and Qc to an indefinite one; the constraints hold."""
    F, L, Qc, _ = example_matrices()
    sde = tl.LTISDE(t(F), t(L), t(Qc), F_constraint="hurwitz")
    target_F = t(np.array([[2.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 3.0, 0.5]]))
    target_Qc = t(np.array([[1.0, 3.0], [3.0, -2.0]]))
    opt = torch.optim.Adam(sde.parameters(), lr=2.0)
    for _ in range(100):
        m = sde.matrices()
        loss = ((m.F - target_F) ** 2).sum() + ((m.Qc - target_Qc) ** 2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        with torch.no_grad():
            m = sde.matrices()
            assert torch.linalg.eigvals(m.F).real.max() < 0
            assert torch.linalg.cholesky_ex(m.Qc).info == 0


# ----------------------------------------------------------------------------- bad input
def test_bad_construction_raises_value_error(mats) -> None:
    F, L, Qc, B = mats
    with pytest.raises(ValueError, match="learn"):
        tl.LTISDE(t(F), t(L), t(Qc), learn=("F", "R"))
    with pytest.raises(ValueError, match="learn.*B"):
        tl.LTISDE(t(F), t(L), t(Qc), learn=("B",))
    with pytest.raises(ValueError, match="F"):
        tl.LTISDE(t(F[:, :2]), t(L), t(Qc))
    with pytest.raises(ValueError, match=r"L.*\(2, 2\)"):
        tl.LTISDE(t(F), t(L[:2]), t(Qc))
    with pytest.raises(ValueError, match="Qc"):
        tl.LTISDE(t(F), t(L), t(np.eye(3)))
    with pytest.raises(ValueError, match="B"):
        tl.LTISDE(t(F), t(L), t(Qc), t(B[:2]))
    with pytest.raises(ValueError, match="batch shapes"):
        tl.LTISDE(t(np.stack([F, F])), t(L), t(np.stack([Qc, Qc, Qc])))
    with pytest.raises(ValueError, match="F_constraint"):
        tl.LTISDE(t(F), t(L), t(Qc), F_constraint="stable")
    with pytest.raises(ValueError, match="Hurwitz"):
        tl.LTISDE(t(-F), t(L), t(Qc), F_constraint="hurwitz")
    with pytest.raises(ValueError, match="Qc"):
        tl.LTISDE(t(F), t(L), t(-Qc))
    with pytest.raises(ValueError, match="F"):
        tl.LTISDE(t(F * np.nan), t(L), t(Qc))


def test_integrator_chain_constraint_declares_positions() -> None:
    from torchsde_lti.nn.parametrizations import IntegratorChain

    F = torch.zeros(6, 6, dtype=torch.float64)
    for axis in range(2):
        F[3 * axis, 3 * axis + 1] = F[3 * axis + 1, 3 * axis + 2] = 1.0
        F[3 * axis + 2, 3 * axis + 2] = -0.5
    L = torch.zeros(6, 2, dtype=torch.float64)
    L[2, 0] = L[5, 1] = 1.0
    sde = tl.LTISDE(F, L, torch.eye(2, dtype=torch.float64), F_constraint=IntegratorChain(3, 2, drag="hurwitz"))
    H = tl.models.position_observation(sde)
    expected = torch.zeros(2, 6, dtype=torch.float64)
    expected[0, 0] = expected[1, 3] = 1.0
    assert torch.equal(H, expected)


def test_to_free_keeps_position_indices() -> None:
    # a model's free copy has the same state ordering, so position_observation still works
    cv = tl.models.constant_velocity(dim=2, q=1.0, dtype=F64)
    free = cv.to_free()
    assert free.position_indices == (0, 2)
    np.testing.assert_array_equal(tl.models.position_observation(free).numpy(), [[1, 0, 0, 0], [0, 0, 1, 0]])
    plain = tl.LTISDE(t(np.zeros((2, 2))), t(np.eye(2)), t(np.eye(2)))
    assert plain.to_free().position_indices is None
