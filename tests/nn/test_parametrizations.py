"""Parametrisations: constraints hold for arbitrary raw values, right_inverse round-trips.

References are independent of the library: numpy eigenvalues / Cholesky, scipy's
Lyapunov solver, and the math.log1p/exp definition of softplus.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import scipy.linalg
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from torchsde_lti.nn.parametrizations import (
    Generator,
    Hurwitz,
    IntegratorChain,
    Positive,
    PositiveDefinite,
    default_floor,
    hurwitz_floor,
    integrator_chain,
    softplus,
    softplus_inverse,
)

F64 = torch.float64
SETTINGS = settings(max_examples=40, deadline=None)


def raw_arrays(shape: tuple[int, ...], bound: float) -> st.SearchStrategy[np.ndarray]:
    return arrays(np.float64, shape, elements=st.floats(-bound, bound, allow_nan=False, allow_infinity=False))


# ------------------------------------------------------------------------- softplus
def test_softplus_matches_definition_and_inverts() -> None:
    x = torch.tensor([-700.0, -50.0, -1.0, 0.0, 1e-8, 1.0, 19.0, 21.0, 50.0, 700.0], dtype=F64)
    ref = torch.tensor(
        [math.log1p(math.exp(v)) if v < 30 else v + math.log1p(math.exp(-v)) for v in x.tolist()], dtype=F64
    )
    torch.testing.assert_close(softplus(x), ref, rtol=1e-15, atol=0)
    y = torch.tensor([1e-300, 1e-12, 1e-3, 1.0, 25.0, 1e6], dtype=F64)
    # conditioning: softplus(x) ≈ e^x for x ≪ 0, so the relative error is ≈ |x| eps (x = −690 for 1e-300)
    raw = softplus_inverse(y)
    rel = ((softplus(raw) - y) / y).abs()
    assert bool((rel <= 4 * (raw.abs() + 1) * torch.finfo(F64).eps).all()), rel


# ------------------------------------------------------------------------- Positive
@SETTINGS
@given(raw_arrays((5,), 200.0))
def test_positive_is_positive_for_any_raw(raw: np.ndarray) -> None:
    p = Positive()
    for dtype in (torch.float32, torch.float64):
        value = p(torch.as_tensor(raw, dtype=dtype))
        assert bool((value > 0).all()) and bool(torch.isfinite(value).all())
        assert bool((value >= default_floor(dtype)).all())


@SETTINGS
@given(st.floats(1e-10, 1e10))
def test_positive_round_trip(v: float) -> None:
    p = Positive().to(F64)
    raw = p.right_inverse(v)
    assert raw.dtype == F64
    assert abs(float(p(raw)) / v - 1.0) < 1e-13


def test_positive_right_inverse_casts_to_raw_dtype() -> None:
    p = Positive().to(torch.float32)
    assert p.right_inverse(torch.tensor(2.0, dtype=F64)).dtype == torch.float32


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_positive_rejects_bad_values(bad: float) -> None:
    with pytest.raises(ValueError, match="q"):
        Positive(name="q").right_inverse(torch.tensor([1.0, bad]))


# ------------------------------------------------------------------------- PositiveDefinite
@SETTINGS
@given(st.integers(1, 5).flatmap(lambda n: raw_arrays((2, n, n), 30.0)))
def test_positive_definite_for_any_raw(raw: np.ndarray) -> None:
    value = PositiveDefinite()(torch.as_tensor(raw)).numpy()
    assert np.array_equal(value, np.swapaxes(value, -1, -2))
    # eigenvalues of C Cᵀ are the squared singular values of C: positive; checked with numpy
    # up to rounding relative to the largest entry
    eig = np.linalg.eigvalsh(value)
    scale = np.abs(value).max(axis=(-2, -1))
    assert (eig.min(axis=-1) >= -1e-12 * scale).all()
    # and the factor's diagonal is bounded below by the floor, so the value is PD
    c = PositiveDefinite().factor(torch.as_tensor(raw))
    assert bool((torch.diagonal(c, dim1=-2, dim2=-1) >= default_floor(F64)).all())


@SETTINGS
@given(st.integers(1, 5).flatmap(lambda n: raw_arrays((n, n), 3.0)))
def test_positive_definite_round_trip(raw: np.ndarray) -> None:
    n = raw.shape[0]
    a = raw + 0.0
    value = a @ a.T + 0.1 * np.eye(n)  # symmetric PD, built with numpy
    p = PositiveDefinite().to(F64)
    back = p(p.right_inverse(torch.as_tensor(value))).numpy()
    np.testing.assert_allclose(back, value, rtol=1e-12, atol=1e-12 * np.abs(value).max())
    # the raw preimage is the numpy Cholesky factor with softplus⁻¹ on its diagonal
    chol = np.linalg.cholesky(value)
    raw_back = p.right_inverse(torch.as_tensor(value)).numpy()
    np.testing.assert_allclose(np.tril(raw_back, -1), np.tril(chol, -1), rtol=1e-12, atol=1e-14)


def test_positive_definite_rejects_indefinite_and_asymmetric() -> None:
    p = PositiveDefinite(name="Qc")
    with pytest.raises(ValueError, match="Qc"):
        p.right_inverse(torch.tensor([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(ValueError, match="Qc.*symmetric"):
        p.right_inverse(torch.tensor([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="Qc"):
        p.right_inverse(torch.ones(2, 3))


def test_size_is_checked_on_assignment() -> None:
    p = PositiveDefinite(name="Qc", size=2)
    with pytest.raises(ValueError, match=r"Qc.*\(3, 3\)"):
        p.right_inverse(torch.eye(3))
    assert p.right_inverse(torch.eye(2).expand(4, 2, 2)).shape == (4, 2, 2)  # batches are fine
    h = Hurwitz(name="F", size=2)
    with pytest.raises(ValueError, match=r"F.*\(3, 3\)"):
        h.right_inverse(-torch.eye(3))
    assert h.right_inverse(-torch.eye(2)).shape == (3, 2, 2)
    with pytest.raises(ValueError, match="size"):
        PositiveDefinite(size=0)


# ------------------------------------------------------------------------- Hurwitz
@SETTINGS
@given(st.integers(1, 5).flatmap(lambda n: raw_arrays((3, n, n), 3.0)))
def test_hurwitz_for_any_raw(raw: np.ndarray) -> None:
    h = Hurwitz()
    F = h(torch.as_tensor(raw)).numpy()
    assert np.linalg.eigvals(F).real.max() < 0
    # Lyapunov certificate with the parametrisation's own S and R, multiplied through by S
    # (no inverse): F S⁻¹ + S⁻¹ Fᵀ = −2R  <=>  S F + Fᵀ S = −2 S R S
    J, R, S = (x.numpy() for x in h.components(torch.as_tensor(raw)))
    np.testing.assert_allclose(J, -J.T, rtol=0, atol=0)
    assert np.linalg.eigvalsh(R).min() > 0 and np.linalg.eigvalsh(S).min() > 0
    np.testing.assert_allclose(F, (J - R) @ S, rtol=1e-12, atol=1e-12 * np.abs(F).max())
    lhs = S @ F + F.T @ S
    tol = 1e3 * np.finfo(np.float64).eps * np.abs(S).max() ** 2 * max(1.0, np.abs(R).max(), np.abs(J).max())
    np.testing.assert_allclose(lhs, -2 * S @ R @ S, rtol=0, atol=tol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_hurwitz_floors_are_relative(dtype: torch.dtype) -> None:
    """λ_min(R) ≥ δ(‖C_R C_Rᵀ‖ + ‖J‖) and λ_min(S) ≥ δ‖C_S C_Sᵀ‖, for raw values of any size."""
    g = torch.Generator().manual_seed(0)
    h = Hurwitz().to(dtype)
    delta = hurwitz_floor(dtype)
    for scale in (1e-3, 1.0, 1e3):
        raw = scale * torch.randn(3, 4, 4, generator=g, dtype=torch.float64)
        J, R, S = (x.to(torch.float64) for x in h.components(raw.to(dtype)))
        assert float(torch.linalg.eigvalsh(R).min()) >= 0.99 * delta * float(torch.linalg.matrix_norm(J, 2))
        assert float(torch.linalg.eigvalsh(S).min()) >= 0.99 * delta * float(torch.linalg.eigvalsh(S).max()) / (
            1 + 4 * delta
        )
        F = h(raw.to(dtype)).to(torch.float64)
        assert float(torch.linalg.eigvals(F).real.max()) < 0


@SETTINGS
@given(st.integers(1, 5).flatmap(lambda n: raw_arrays((3, n, n), 0.5)))
def test_hurwitz_round_trip_of_reached_values(raw: np.ndarray) -> None:
    """Every reached F round-trips to 1e-10: through the default floor, or — where that
    preimage is out of reach (it raises, naming the floor; e.g. all raw entries −0.5 at
    n = 5, R and S near their floors) — through the documented remedy, a 10× smaller floor."""
    h = Hurwitz().to(F64)
    F = h(torch.as_tensor(raw))
    try:
        back = h(h.right_inverse(F))
    except ValueError as err:
        assert "out of reach of the floor" in str(err)
        h = Hurwitz(floor=1e-4).to(F64)
        back = h(h.right_inverse(F))
    assert float(torch.linalg.matrix_norm(back - F) / torch.linalg.matrix_norm(F)) < 1e-10


def test_hurwitz_out_of_reach_raises_naming_the_floor() -> None:
    F = torch.diag(torch.tensor([-1.0, -1e5], dtype=F64))  # time scales 1e5 apart > 1/floor
    with pytest.raises(ValueError, match="out of reach of the floor"):
        Hurwitz().right_inverse(F)
    h = Hurwitz(floor=1e-6).to(F64)  # a smaller floor reaches it
    torch.testing.assert_close(h(h.right_inverse(F)), F, rtol=1e-10, atol=1e-10)


def _hostile_sgd(n: int, dtype: torch.dtype, lr: float, steps: int, seed: int) -> int:
    """Plain SGD on the unbounded random-sign loss −ξ₁ Σ A − 3 ξ₂ tr Q (issue 11).

    Returns how many float64 steps reached an F beyond ``right_inverse``'s reach."""
    import torchsde_lti as tl

    g = torch.Generator().manual_seed(seed)
    eye = torch.eye(n, dtype=dtype)
    sde = tl.LTISDE(-eye, eye, eye, F_constraint="hurwitz")
    param = sde.parametrizations.F[0]
    opt = torch.optim.SGD(sde.parameters(), lr=lr)
    reach_failures: list[int] = []
    for _ in range(steps):
        dt = torch.rand(8, generator=g).to(dtype)
        xi = torch.randint(0, 2, (2,), generator=g).to(dtype) * 2 - 1
        d = sde(dt)
        loss = -(d.A.sum() * xi[0]) - 3.0 * torch.diagonal(d.Q, dim1=-2, dim2=-1).sum() * xi[1]
        opt.zero_grad()
        loss.backward()
        opt.step()
        with torch.no_grad():
            F, Qc = sde.F.to(F64), sde.Qc.to(F64)
            assert bool(torch.isfinite(F).all()) and bool(torch.isfinite(Qc).all())
            assert np.linalg.eigvals(F.numpy()).real.max() < 0
            # Qc = C Cᵀ is PD by certificate: its Cholesky factor has a positive, finite diagonal
            qc_param = sde.parametrizations.Qc[0]
            diag = torch.diagonal(qc_param.factor(sde.parametrizations.Qc.original.to(F64)))
            assert bool((diag > 0).all()) and bool(torch.isfinite(diag).all())
            if dtype == F64:
                try:
                    raw = param.right_inverse(F)
                except ValueError as err:  # reached, but beyond the R = rI preimage (documented)
                    assert "out of reach" in str(err)
                    reach_failures.append(1)
                    continue
                back = param(raw)
                assert float(torch.linalg.matrix_norm(back - F) / torch.linalg.matrix_norm(F)) < 1e-10
    return len(reach_failures)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [2, 3, 4, 6])
def test_hurwitz_survives_hostile_sgd(n: int, dtype: torch.dtype) -> None:
    """Short version of the 200-step study in experiments/results/hurwitz_robustness.md."""
    for lr in (0.1, 0.5, 1.0):
        _hostile_sgd(n, dtype, lr, steps=12, seed=n)


def random_hurwitz(rng: np.random.Generator, n: int) -> np.ndarray:
    M = rng.normal(size=(n, n))
    shift = np.linalg.eigvals(M).real.max() + rng.uniform(0.1, 2.0)
    return M - shift * np.eye(n)


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_hurwitz_right_inverse_reaches_any_hurwitz_matrix(n: int) -> None:
    rng = np.random.default_rng(n)
    h = Hurwitz().to(F64)
    for _ in range(5):
        F = random_hurwitz(rng, n)
        raw = h.right_inverse(torch.as_tensor(F))
        np.testing.assert_allclose(h(raw).numpy(), F, rtol=1e-9, atol=1e-10 * np.abs(F).max())
        # the preimage is (r K, r I, P⁻¹ / r) with P scipy's solution of F P + P Fᵀ = −2I
        J, R, S = (x.numpy() for x in h.components(raw))
        P_ref = scipy.linalg.solve_continuous_lyapunov(F, -2 * np.eye(n))
        r = R[0, 0]
        np.testing.assert_allclose(R, r * np.eye(n), rtol=1e-12, atol=1e-12 * r)
        np.testing.assert_allclose(r * S @ P_ref, np.eye(n), rtol=0, atol=1e-9)
        # well scaled: the raw entries stay O(1) for these O(1) matrices
        assert float(raw.abs().max()) < 20


def test_hurwitz_batched_round_trip() -> None:
    rng = np.random.default_rng(0)
    F = np.stack([random_hurwitz(rng, 3) for _ in range(4)])
    h = Hurwitz().to(F64)
    raw = h.right_inverse(torch.as_tensor(F))
    assert raw.shape == (4, 3, 3, 3)
    np.testing.assert_allclose(h(raw).numpy(), F, rtol=1e-9, atol=1e-10)


def test_hurwitz_rejects_unstable() -> None:
    with pytest.raises(ValueError, match="Hurwitz"):
        Hurwitz().right_inverse(torch.tensor([[0.5, 1.0], [0.0, -1.0]]))
    with pytest.raises(ValueError, match="Hurwitz"):
        Hurwitz().right_inverse(torch.tensor([[0.0, 1.0], [-1.0, 0.0]]))  # marginal: eigenvalues ±i


def test_hurwitz_stays_stable_under_large_learning_rate() -> None:
    """Adam at lr=1 pulling F towards an unstable target: F stays Hurwitz at every step."""
    torch.manual_seed(0)
    h = Hurwitz().to(F64)
    target = torch.tensor([[1.0, 3.0, 0.0], [-2.0, 0.5, 1.0], [0.0, 0.0, 2.0]], dtype=F64)
    raw = torch.nn.Parameter(h.right_inverse(-torch.eye(3, dtype=F64)))
    opt = torch.optim.Adam([raw], lr=1.0)
    worst = -math.inf
    for _ in range(150):
        F = h(raw)
        loss = ((F - target) ** 2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        with torch.no_grad():
            F = h(raw).numpy()
        assert np.isfinite(F).all()
        worst = max(worst, np.linalg.eigvals(F).real.max())
    assert worst < 0


# ------------------------------------------------------------------------- IntegratorChain
def cv_drag_matrix(f_v: np.ndarray, order: int) -> np.ndarray:
    """Hand-built per-axis integrator chain with drag block f_v on the highest derivatives."""
    d = f_v.shape[0]
    n = order * d
    F = np.zeros((n, n))
    for a in range(d):
        for k in range(order - 1):
            F[a * order + k, a * order + k + 1] = 1.0
        for b in range(d):
            F[a * order + order - 1, b * order + order - 1] = f_v[a, b]
    return F


@pytest.mark.parametrize("order,dim", [(1, 2), (2, 2), (3, 2), (2, 3)])
def test_integrator_chain_structure_and_round_trip(order: int, dim: int) -> None:
    rng = np.random.default_rng(order * 10 + dim)
    f_v = rng.normal(size=(dim, dim))
    p = IntegratorChain(order, dim, drag="free").to(F64)
    F = p(torch.as_tensor(f_v)).numpy()
    np.testing.assert_array_equal(F, cv_drag_matrix(f_v, order))
    np.testing.assert_array_equal(p.right_inverse(torch.as_tensor(F)).numpy(), f_v)


@SETTINGS
@given(raw_arrays((3, 2, 2), 3.0))
def test_integrator_chain_hurwitz_drag(raw: np.ndarray) -> None:
    p = IntegratorChain(2, 2, drag="hurwitz").to(F64)
    F = p(torch.as_tensor(raw)).numpy()
    f_v = F[np.ix_([1, 3], [1, 3])]
    assert np.linalg.eigvals(f_v).real.max() < 0
    np.testing.assert_array_equal(F - cv_drag_matrix(f_v, 2), np.zeros((4, 4)))


@SETTINGS
@given(raw_arrays((3, 2, 2), 0.5))
def test_integrator_chain_hurwitz_drag_round_trip(raw: np.ndarray) -> None:
    """Raw values of moderate size: the reached F_v lies within the preimage's reach."""
    p = IntegratorChain(2, 2, drag="hurwitz").to(F64)
    F = p(torch.as_tensor(raw)).numpy()
    back = p(p.right_inverse(torch.as_tensor(F))).numpy()
    np.testing.assert_allclose(back, F, rtol=1e-10, atol=1e-10 * np.abs(F).max())


def test_integrator_chain_rejects_other_structure() -> None:
    p = IntegratorChain(2, 2)
    F = torch.zeros(4, 4)
    F[0, 1] = 1.0  # the second axis lost its integrator
    with pytest.raises(ValueError, match="F"):
        p.right_inverse(F)
    with pytest.raises(ValueError, match="F"):
        p.right_inverse(torch.zeros(3, 3))
    with pytest.raises(ValueError, match="order"):
        IntegratorChain(0, 2)
    with pytest.raises(ValueError, match="dim"):
        IntegratorChain(2, 0)
    with pytest.raises(ValueError, match="drag"):
        IntegratorChain(2, 2, drag="stable")  # type: ignore[arg-type]


def test_integrator_chain_matrices_by_hand() -> None:
    chain, sel = integrator_chain(3, 2, dtype=torch.float64)  # [x, x', x'', y, y', y'']
    expected = np.zeros((6, 6))
    expected[0, 1] = expected[1, 2] = expected[3, 4] = expected[4, 5] = 1.0
    np.testing.assert_array_equal(chain.numpy(), expected)
    np.testing.assert_array_equal(sel.numpy(), [[0, 0], [0, 0], [1, 0], [0, 0], [0, 0], [0, 1]])
    assert chain.dtype == torch.float64


# --------------------------------------------------------------------------- Generator, ModeProbabilities


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_generator_is_a_generator_for_any_raw_and_round_trips(dtype: torch.dtype) -> None:
    from torchsde_lti.nn.parametrizations import Generator

    g = Generator().to(dtype=dtype)
    raw = 30.0 * torch.randn(5, 3, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64).to(dtype)
    lam = g(raw)
    off = ~torch.eye(3, dtype=torch.bool)
    assert lam.dtype == dtype and bool((lam[:, off] > 0).all()) and bool(torch.isfinite(lam).all())
    assert torch.allclose(lam.sum(-1), torch.zeros(5, 3, dtype=dtype), atol=1e-4 if dtype == torch.float32 else 1e-12)
    # expm(Λ dt) is a stochastic matrix
    Pi = torch.linalg.matrix_exp(lam.double()[0] * 7.0)
    assert torch.allclose(Pi.sum(-1), torch.ones(3, dtype=torch.float64), atol=1e-10) and bool((Pi > -1e-12).all())
    rates = torch.tensor([[0.0, 0.2, 1e-3], [3.0, 0.0, 0.5], [0.01, 0.02, 0.0]], dtype=torch.float64)
    back = g(g.right_inverse(rates.tolist()))  # Python lists cast to the raw dtype
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    assert torch.allclose(back[off].double(), rates[off], rtol=tol)
    with pytest.raises(ValueError, match="rates"):
        g.right_inverse(torch.tensor([[0.0, 0.0], [1.0, 0.0]]))


def test_mode_probabilities_softmax_and_round_trip() -> None:
    from torchsde_lti.nn.parametrizations import ModeProbabilities

    p = ModeProbabilities().to(dtype=torch.float64)
    v = torch.tensor([0.7, 0.2, 0.1], dtype=torch.float64)
    assert torch.allclose(p(p.right_inverse(v)), v, rtol=1e-14)
    out = p(torch.tensor([50.0, -50.0, 0.0], dtype=torch.float64))
    assert float(out.sum()) == pytest.approx(1.0) and bool((out >= 0).all())
    with pytest.raises(ValueError, match="mode_prob0"):
        p.right_inverse([0.5, 0.5, 0.0])


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_values_stay_finite_for_huge_raw_entries(dtype: torch.dtype) -> None:
    """Raw entries beyond the saturation bound enter logarithmically: PositiveDefinite and
    Hurwitz stay finite (and Hurwitz stable) up to the dtype's largest numbers."""
    top = float(torch.finfo(dtype).max)
    for big in (1e10, 1e20, top / 2):
        pd = PositiveDefinite().to(dtype)(torch.full((3, 3), big, dtype=dtype))
        assert bool(torch.isfinite(pd).all())
        F = Hurwitz().to(dtype)(
            torch.full((3, 3, 3), big, dtype=dtype) * torch.tensor([1.0, -1.0, 1.0], dtype=dtype)[:, None, None]
        )
        assert bool(torch.isfinite(F).all())
        assert float(torch.linalg.eigvals(F.double()).real.max()) < 0
    for big in (1e10, 1e20, top / 2, top):  # Generator: each rate was finite, their sums -inf
        lam = Generator().to(dtype)(torch.full((3, 3), big, dtype=dtype))
        assert lam.dtype == dtype and bool(torch.isfinite(lam).all())
        assert bool((lam.sum(-1).abs() <= 1e-6 * lam.diagonal().abs()).all())
        assert bool(torch.isfinite(torch.linalg.matrix_exp(lam.double() * 1e-300)).all())
    # ordinary raw values are untouched by the saturation (round trips as before)
    rates = torch.tensor([[0.0, 0.3, 2.0], [1.5, 0.0, 5.0], [0.25, 1e3, 0.0]], dtype=dtype)
    gen = Generator().to(dtype)
    raw = gen.right_inverse(rates)
    torch.testing.assert_close(gen(raw), rates - torch.diag_embed(rates.sum(-1)), rtol=1e-5, atol=1e-5)
    assert bool((raw.abs() < 1e4).all())
    pd = PositiveDefinite().to(dtype)
    value = torch.tensor([[4.0, 1.0], [1.0, 2.0]], dtype=dtype)
    torch.testing.assert_close(pd(pd.right_inverse(value)), value)


# --------------------------------------------------------------------------- the default floor across dtypes
F32 = torch.float32
EPS32 = float(torch.finfo(F32).eps)
FLOORED = ("q", "Qc", "rates")


def _floored_module(dtype: torch.dtype, scale: float = 1.0) -> torch.nn.Module:
    """q (Positive), Qc (PositiveDefinite) and rates (Generator) of size ~1e-6 (times ``scale``),
    where the default floor (float32 eps ≈ 1.2e-7) is a tenth of the value."""
    from torch.nn.utils import parametrize

    from torchsde_lti.nn.parametrizations import Generator

    m = torch.nn.Module()
    m.q = torch.nn.Parameter(scale * torch.tensor([1e-6, 1e-3, 2.0], dtype=dtype))
    # eigenvalues ≈ 4.3e-6 and 0.7e-6; Cholesky diagonal ≈ 2e-3 and 8.7e-4
    m.Qc = torch.nn.Parameter(scale * torch.tensor([[4e-6, 1e-6], [1e-6, 1e-6]], dtype=dtype))
    m.rates = torch.nn.Parameter(scale * torch.tensor([[0.0, 1e-6], [3e-6, 0.0]], dtype=dtype))
    parametrize.register_parametrization(m, "q", Positive(name="q").to(dtype))
    parametrize.register_parametrization(m, "Qc", PositiveDefinite(name="Qc", size=2).to(dtype))
    parametrize.register_parametrization(m, "rates", Generator().to(dtype))
    return m


def _values(m: torch.nn.Module) -> dict[str, torch.Tensor]:
    with torch.no_grad():
        return {k: getattr(m, k).to(F64) for k in FLOORED}


def _assert_same_values(got: dict[str, torch.Tensor], want: dict[str, torch.Tensor], rtol: float) -> None:
    for k in FLOORED:
        torch.testing.assert_close(got[k], want[k], rtol=rtol, atol=0, msg=lambda s, k=k: f"{k}: {s}")


def _floor_keys(state: dict[str, torch.Tensor]) -> list[str]:
    return [k for k in state if k.endswith("._extra_state")]


def test_default_floor_does_not_change_with_double() -> None:
    """Built in float32 (floor float32 eps), then .double(): the values stay those of the float32
    module to float32 rounding (a floor switched to float64 eps moved q = 1e-6 to 8.8e-7)."""
    m = _floored_module(F32)
    before = _values(m)
    assert float(before["q"][0]) == pytest.approx(1e-6, rel=1e-6)
    m.double()
    assert m.parametrizations.q.original.dtype == F64
    _assert_same_values(_values(m), before, rtol=4 * EPS32)


def test_default_floor_does_not_change_with_float() -> None:
    m = _floored_module(F64)
    before = _values(m)
    m.float()
    assert m.parametrizations.Qc.original.dtype == F32
    _assert_same_values(_values(m), before, rtol=4 * EPS32)


def test_state_dict_saved_in_float32_loads_into_a_float64_model() -> None:
    """A float32 checkpoint (through torch.save / torch.load(weights_only=True)) loaded into a model
    built in float64 gives the float32 model's values: the floor travels with the weights."""
    import io

    src = _floored_module(F32, scale=3.0)
    want = _values(src)
    buf = io.BytesIO()
    torch.save(src.state_dict(), buf)
    buf.seek(0)
    dst = _floored_module(F64)
    dst.load_state_dict(torch.load(buf, weights_only=True), strict=True)
    assert dst.parametrizations.q.original.dtype == F64
    _assert_same_values(_values(dst), want, rtol=4 * EPS32)
    # and the other way round
    src64 = _floored_module(F64, scale=3.0)
    dst32 = _floored_module(F32)
    dst32.load_state_dict(src64.state_dict())
    _assert_same_values(_values(dst32), _values(src64), rtol=4 * EPS32)


@pytest.mark.parametrize("dtype", [F32, F64])
def test_state_dict_without_the_floor_loads_as_before(dtype: torch.dtype) -> None:
    """A state dict saved before floors were saved (the floor entries deleted) loads with
    strict=True and gives what it gave then: the floor is the eps of the model's raw dtype."""
    src = _floored_module(F32, scale=3.0)
    state = src.state_dict()
    floors = _floor_keys(state)
    assert len(floors) == len(FLOORED), sorted(state)
    old = {k: v for k, v in state.items() if k not in floors}
    dst = _floored_module(dtype)
    dst.load_state_dict(old, strict=True)
    eps = float(torch.finfo(dtype).eps)
    with torch.no_grad():
        raw = {k: old[f"parametrizations.{k}.original"].to(dtype) for k in FLOORED}
        q = softplus(raw["q"]) + eps
        diag = softplus(torch.diagonal(raw["Qc"])) + eps
        c = torch.tril(raw["Qc"], -1) + torch.diag(diag)
        off = ~torch.eye(2, dtype=torch.bool)
        rates = torch.where(off, softplus(raw["rates"]) + eps, 0.0)
        want = {"q": q, "Qc": c @ c.mT, "rates": rates - torch.diag(rates.sum(-1))}
    got = _values(dst)
    for k in FLOORED:
        torch.testing.assert_close(got[k], want[k].to(F64), rtol=2 * float(torch.finfo(dtype).eps), atol=0)
    if dtype == F32:  # the float32 model reads the old checkpoint exactly as the model that saved it
        for k in FLOORED:
            assert torch.equal(got[k], _values(src)[k])
    # from then on the floor is fixed (and saved): a later dtype change keeps the values
    assert len(_floor_keys(dst.state_dict())) == len(FLOORED)
    dst.to(F64 if dtype == F32 else F32)
    _assert_same_values(_values(dst), got, rtol=4 * EPS32)


def test_default_floor_is_fixed_by_the_first_tensor_seen() -> None:
    """Never registered (no right_inverse): the first forward fixes the floor at its dtype's eps."""
    raw = torch.tensor([-30.0, 0.0, 3.0], dtype=F32)
    p = Positive()
    first = p(raw)
    torch.testing.assert_close(first, softplus(raw) + EPS32, rtol=0, atol=0)
    torch.testing.assert_close(p(raw.double()), softplus(raw.double()) + EPS32, rtol=0, atol=0)
    q = Positive().to(F64)
    raw64 = q.right_inverse(torch.tensor([1e-6], dtype=F64))  # right_inverse fixes it: float64 eps
    assert float(q.to(F32)(raw64.float())) == pytest.approx(1e-6, rel=4 * EPS32)


def test_explicit_floor_is_kept() -> None:
    """An explicit floor is used as given, whatever the dtype and whatever a loaded state says."""
    p = Positive(floor=1e-3).to(F32)
    raw = p.right_inverse(torch.tensor([2e-3]))
    assert float(p.double()(raw.double())) == pytest.approx(2e-3, rel=4 * EPS32)
    other = Positive(floor=1e-5)
    other.load_state_dict(p.state_dict())
    assert float(other(raw.double())) == pytest.approx(1e-5 + float(softplus(raw.double())), rel=1e-15)


def test_reset_default_floors() -> None:
    """The default floors become the eps of the given dtype (raw tensors kept, so values move by
    the floor change); explicit floors stay; a filter's cached online model sees the change."""
    import torchsde_lti as tl
    from torchsde_lti.nn.parametrizations import reset_default_floors

    m = _floored_module(F32).double()
    raw = {k: getattr(m.parametrizations, k).original.detach().clone() for k in FLOORED}
    reset_default_floors(m, F64)
    with torch.no_grad():
        torch.testing.assert_close(m.q, softplus(raw["q"]) + float(torch.finfo(F64).eps), rtol=0, atol=0)
    p = Positive(floor=1e-3)
    reset_default_floors(p, F64)
    assert float(p(torch.tensor(-50.0, dtype=F64))) == pytest.approx(1e-3, rel=1e-12)
    with pytest.raises(TypeError):
        reset_default_floors(m, torch.int64)

    sde = tl.models.constant_velocity(dim=1, q=1e-6)  # built in float32 (floor float32 eps)
    kf = tl.KalmanFilter(sde, tl.models.position_observation(sde), 1e-6 * torch.eye(1)).double()
    state, y = kf.initial_state(2), torch.zeros(2, 1, dtype=F64)
    with torch.no_grad():
        before = kf.step(state, y, 1.0)[0].cov
        reset_default_floors(kf, F64)
        after = kf.step(state, y, 1.0)[0].cov
        fresh = copy.deepcopy(kf).step(state, y, 1.0)[0].cov
    assert not torch.equal(before, after)
    torch.testing.assert_close(after, fresh, rtol=0, atol=0)


@pytest.mark.parametrize("bad", [-1e-7, math.nan, math.inf])
def test_a_bad_saved_floor_is_refused_naming_the_parametrisation(bad: float) -> None:
    m = _floored_module(F64)
    state = m.state_dict()
    state["parametrizations.q.0._extra_state"] = torch.tensor(bad, dtype=F64)
    with pytest.raises(ValueError, match=r"Positive\('q'\): the saved floor"):
        m.load_state_dict(state)
