"""Every public function of the core rejects bad input with a message naming the argument."""

from __future__ import annotations

import pytest
import torch

import torchsde_lti as tl

f64 = torch.float64


def good():
    F = torch.tensor([[0.0, 1.0], [0.0, -1.0]], dtype=f64)
    L = torch.tensor([[0.0], [1.0]], dtype=f64)
    Qc = torch.tensor([[1.0]], dtype=f64)
    B = torch.tensor([[0.0], [1.0]], dtype=f64)
    return F, L, Qc, B


def test_non_square_F() -> None:
    F, L, Qc, _ = good()
    with pytest.raises(ValueError, match=r"F must be square.*\(2, 3\)"):
        tl.discretize(torch.zeros(2, 3, dtype=f64), L, Qc, 1.0)
    with pytest.raises(ValueError, match=r"F must be square"):
        tl.transition_matrix(torch.zeros(3, 2, dtype=f64), 1.0)
    with pytest.raises(ValueError, match=r"F must be a matrix"):
        tl.transition_matrix(torch.zeros(3, dtype=f64), 1.0)


def test_L_rows() -> None:
    F, _, Qc, _ = good()
    with pytest.raises(ValueError, match=r"L must have 2 rows.*\(3, 1\)"):
        tl.discretize(F, torch.zeros(3, 1, dtype=f64), Qc, 1.0)


def test_Qc_shape_for_L() -> None:
    F, L, _, _ = good()
    with pytest.raises(ValueError, match=r"Qc must have shape \(\.\.\., 1, 1\).*L \(2, 1\).*\(2, 2\)"):
        tl.discretize(F, L, torch.eye(2, dtype=f64), 1.0)


def test_Qc_not_symmetric() -> None:
    F, _, _, _ = good()
    with pytest.raises(ValueError, match=r"Qc must be symmetric"):
        tl.discretize(F, torch.eye(2, dtype=f64), torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=f64), 1.0)


def test_Qc_not_psd() -> None:
    F, _, _, _ = good()
    with pytest.raises(ValueError, match=r"Qc must be positive semi-definite"):
        tl.discretize(F, torch.eye(2, dtype=f64), torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=f64), 1.0)
    # a PSD matrix with rounding-level negative eigenvalue is accepted, in float32 too
    v = torch.tensor([[1.0], [1.0]])
    tl.discretize(F.float(), torch.eye(2), v @ v.T, 1.0)


def test_B_rows() -> None:
    F, L, Qc, _ = good()
    with pytest.raises(ValueError, match=r"B must have 2 rows.*\(3, 1\)"):
        tl.discretize(F, L, Qc, 1.0, B=torch.zeros(3, 1, dtype=f64))


def test_B_without_columns_and_missing_dt_or_B() -> None:
    """A B of no columns (every path: few elements, per element, one F for many steps), a
    missing dt, and zero_order_hold without B: ValueErrors naming them (were a reshape
    RuntimeError, a dropped G and bare AssertionErrors)."""
    F, L, Qc, _ = good()
    B0 = torch.zeros(2, 0, dtype=f64)
    for dt in (1.0, torch.ones(300, dtype=f64)):
        with pytest.raises(ValueError, match=r"B must have at least one column.*\(2, 0\)"):
            tl.discretize(F, L, Qc, dt, B=B0)
    with pytest.raises(ValueError, match="B must have at least one column"):
        tl.core.zero_order_hold(F, B0, 1.0)
    for call in (lambda: tl.discretize(F, L, Qc, None), lambda: tl.core.transition_matrix(F, None)):
        with pytest.raises(ValueError, match="dt is required"):
            call()
    with pytest.raises(ValueError, match="B is required"):
        tl.core.zero_order_hold(F, None, 1.0)  # type: ignore[arg-type]


def test_negative_dt() -> None:
    F, L, Qc, _ = good()
    with pytest.raises(ValueError, match=r"dt must be non-negative"):
        tl.discretize(F, L, Qc, torch.tensor([0.5, -0.1], dtype=f64))
    with pytest.raises(ValueError, match=r"dt must be non-negative"):
        tl.transition_matrix(F, -1.0)


def test_dt_not_broadcastable() -> None:
    F, L, Qc, _ = good()
    Fb = F.expand(3, 2, 2)
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: F: \(3\).*dt: \(4\)"):
        tl.discretize(Fb, L, Qc, torch.ones(4, dtype=f64))


@pytest.mark.parametrize("which", ["F", "L", "Qc", "B", "dt"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_nan_inf_inputs(which: str, bad: float) -> None:
    F, L, Qc, B = good()
    args = {"F": F.clone(), "L": L.clone(), "Qc": Qc.clone(), "B": B.clone(), "dt": torch.tensor(1.0, dtype=f64)}
    args[which].view(-1)[0] = bad
    with pytest.raises(ValueError, match=rf"{which} contains NaN or Inf"):
        tl.discretize(args["F"], args["L"], args["Qc"], args["dt"], B=args["B"])


def test_unknown_method() -> None:
    F, L, Qc, _ = good()
    with pytest.raises(ValueError, match=r"method must be one of"):
        tl.discretize(F, L, Qc, 1.0, method="euler")


def test_propagate_bad_moments_and_inputs() -> None:
    F, L, Qc, B = good()
    with pytest.raises(ValueError, match=r"m0 must have shape \(\.\.\., 2\).*\(3\)"):
        tl.propagate(torch.zeros(3, dtype=f64), torch.eye(2, dtype=f64), F, L, Qc, 1.0)
    with pytest.raises(ValueError, match=r"P0 must have 2 rows"):
        tl.propagate(torch.zeros(2, dtype=f64), torch.eye(3, dtype=f64), F, L, Qc, 1.0)
    with pytest.raises(ValueError, match=r"P0 must be positive semi-definite"):
        tl.propagate(torch.zeros(2, dtype=f64), -torch.eye(2, dtype=f64), F, L, Qc, 1.0)
    with pytest.raises(ValueError, match=r"u was given.*no input matrix B"):
        tl.propagate(torch.zeros(2, dtype=f64), torch.eye(2, dtype=f64), F, L, Qc, 1.0, u=torch.ones(1, dtype=f64))
    with pytest.raises(ValueError, match=r"u must have shape \(\.\.\., 1\)"):
        tl.propagate(torch.zeros(2, dtype=f64), torch.eye(2, dtype=f64), F, L, Qc, 1.0, B=B, u=torch.ones(2, dtype=f64))


def test_type_errors() -> None:
    F, L, Qc, _ = good()
    with pytest.raises(TypeError, match=r"F must be a real floating tensor"):
        tl.discretize(F.to(torch.complex128), L, Qc, 1.0)
    with pytest.raises(TypeError, match=r"dt must be a tensor or array-like"):
        tl.discretize(F, L, Qc, "one second")


def test_value_checks_can_be_skipped_for_checked_arguments() -> None:
    """validate_args=False (inner calls on already-checked arguments) skips the value checks
    of every core function; the default checks them."""
    F, L, Qc, _ = good()
    nan = torch.tensor(float("nan"), dtype=f64)
    d = tl.discretize(F, L, Qc, nan, validate_args=False)
    assert torch.isnan(d.A).any()
    for call in (
        lambda v: tl.discretize(F, L, Qc, nan, validate_args=v),
        lambda v: tl.transition_matrix(F, nan, validate_args=v),
        lambda v: tl.process_noise(F, L, Qc, nan, validate_args=v),
        lambda v: tl.zero_order_hold(F, L, nan, validate_args=v),
        lambda v: tl.propagate(torch.zeros(2, dtype=f64), torch.eye(2, dtype=f64), F, L, Qc, nan, validate_args=v),
    ):
        call(False)
        with pytest.raises(ValueError, match="dt"):
            call(True)
    with pytest.raises(ValueError, match="Hurwitz"):
        tl.stationary_covariance(torch.eye(2, dtype=f64), L, Qc)
    tl.stationary_covariance(torch.eye(2, dtype=f64), L, Qc, validate_args=False)


@pytest.mark.parametrize("k", [1, 2, 3, 5])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_psd_test_decides_by_the_smallest_eigenvalue_at_every_scale(k: int, dtype: torch.dtype) -> None:
    """The PSD test (a Cholesky factor of x/max|x| + tol I) accepts every matrix whose smallest
    eigenvalue is ≥ 0 and refuses every one below −2 tol of its largest entry, at scales from
    1e-150 to 1e150 (float32: 1e-30 … 1e30), the zero matrix included (a dt = 0 step's Q: it
    was refused, the shift tol·tiny underflowing); an asymmetric matrix is refused."""
    from torchsde_lti.core.validation import _psd_test, psd_tolerance

    g = torch.Generator().manual_seed(k)
    N = 2000
    V = torch.linalg.qr(torch.randn(N, k, k, generator=g, dtype=f64)).Q
    tol = psd_tolerance(torch.zeros(1, k, dtype=dtype))
    low = torch.empty(N, 1, dtype=f64).uniform_(-10 * tol, 10 * tol, generator=g)
    lam = torch.cat([low, torch.ones(N, max(k - 1, 1), dtype=f64)], -1)[:, :k]
    decades = 150 if dtype == f64 else 30
    scale = torch.logspace(-decades, decades, N, dtype=f64)
    x = (0.5 * ((V * lam[:, None, :]) @ V.mT) * scale[:, None, None]).to(dtype)
    x = 0.5 * (x + x.mT)
    passes = [bool(_psd_test(x[i : i + 1])[0]) for i in range(N)]
    lowest = low[:, 0] / lam.abs().amax(-1) if k > 1 else torch.sign(low[:, 0])
    for i in range(N):
        if lowest[i] >= 0:
            assert passes[i], (i, x[i])
        elif lowest[i] < -2 * tol:
            assert not passes[i], (i, x[i])
    assert bool(_psd_test(torch.zeros(3, k, k, dtype=dtype))[0])
    if k == 2:
        assert not bool(_psd_test(torch.tensor([[[1.0, 0.5], [0.0, 1.0]]], dtype=dtype))[0])


@pytest.mark.parametrize("dtype, dt", [(torch.float64, 1000.0), (torch.float32, 100.0)])
def test_overflowing_results_raise_naming_the_cause(dtype: torch.dtype, dt: float) -> None:
    """An unstable F over a long step: the exact A = e^{dt} exceeds the dtype's range. Public
    calls raise instead of returning inf/NaN; inner calls (validate_args=False) do not check."""
    F, L, Qc = torch.eye(2, dtype=dtype), torch.eye(2, dtype=dtype), torch.eye(2, dtype=dtype)
    step = torch.tensor(dt, dtype=dtype)
    for call in (
        lambda v: tl.discretize(F, L, Qc, step, validate_args=v),
        lambda v: tl.transition_matrix(F, step, validate_args=v),
        lambda v: tl.zero_order_hold(F, L, step, validate_args=v),
        lambda v: tl.core.discretize_series(F, L, Qc, step.expand(40), validate_args=v),
    ):
        with pytest.raises(ValueError, match=r"overflows .*A.*rightmost eigenvalue has real part 1"):
            call(True)
        call(False)
    assert torch.isfinite(tl.discretize(F, L, Qc, torch.tensor(5.0, dtype=dtype)).Q).all()


def _large(N: int = 100, n: int = 3):
    """A call of more than PYTHON_CHECK_MAX_VALUES values (the checks run on tensors)."""
    g = torch.Generator().manual_seed(0)
    F = torch.randn(N, n, n, generator=g, dtype=f64) - 2 * torch.eye(n, dtype=f64)
    C = torch.randn(N, n, n, generator=g, dtype=f64)
    return F, torch.eye(n, dtype=f64), C @ C.mT + 0.1 * torch.eye(n, dtype=f64), torch.rand(N, generator=g, dtype=f64)


@pytest.mark.parametrize("which", ["F", "L", "Qc", "dt"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_large_calls_raise_the_same_errors(which: str, bad: float) -> None:
    args = dict(zip(("F", "L", "Qc", "dt"), (t.clone() for t in _large())))
    args[which].view(-1)[-1] = bad
    with pytest.raises(ValueError, match=rf"{which} contains NaN or Inf"):
        tl.discretize(args["F"], args["L"], args["Qc"], args["dt"])
    F, L, Qc, dt = _large()
    dt[7] = -0.1
    with pytest.raises(ValueError, match=r"dt must be non-negative"):
        tl.discretize(F, L, Qc, dt)
    F, L, Qc, dt = _large()
    Qc[3, 0, 1] += 0.5
    with pytest.raises(ValueError, match=r"Qc must be symmetric"):
        tl.discretize(F, L, Qc, dt)
    Qc[3] = torch.tensor([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=f64)
    with pytest.raises(ValueError, match=r"Qc must be positive semi-definite"):
        tl.discretize(F, L, Qc, dt)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_large_calls_accept_semi_definite_and_zero_noise(dtype: torch.dtype) -> None:
    """A singular Qc (no Cholesky factor) and a zero Qc pass the declared PSD constraint."""
    F, L, Qc, dt = (t.to(dtype) for t in _large())
    v = torch.ones(3, 1, dtype=dtype)
    Qc[5] = v @ v.T
    Qc[6] = 0.0
    d = tl.discretize(F, L, Qc, dt)
    assert torch.isfinite(d.Q).all() and float(d.Q[6].abs().max()) == 0.0


def _count_host_reads(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every read of a tensor's value to the host (bool, int, float, item, tolist) from now on."""
    reads: list[str] = []
    for name in ("__bool__", "__int__", "__float__", "__index__", "item", "tolist"):
        inner = getattr(torch.Tensor, name)

        def counted(self, *args, _inner=inner, _name=name):  # type: ignore[no-untyped-def]
            reads.append(_name)
            return _inner(self, *args)

        monkeypatch.setattr(torch.Tensor, name, counted)
    return reads


@pytest.mark.parametrize("N, shared", [(100, False), (100, True), (2, False), (1, True)])
def test_unchecked_calls_read_only_the_number_of_doublings(
    monkeypatch: pytest.MonkeyPatch, N: int, shared: bool
) -> None:
    """validate_args=False reads nothing to the host but the numbers of doublings (one read: how
    many elements take each, for the eager grouping), in small calls too (they
    read every value to check them on Python floats, checked or not); a checked call reads its
    checks' outcomes too (one for the arguments, one for the result)."""
    F, L, Qc, dt = _large(N)
    B = torch.ones(3, 1, dtype=f64)
    if shared:
        F, Qc = F[0], Qc[0]
    counts = []
    for validate in (False, True):
        reads = _count_host_reads(monkeypatch)
        tl.discretize(F, L, Qc, dt, B=B, validate_args=validate)
        counts.append(len(reads))
        monkeypatch.undo()
    assert counts == [1, 3]


@pytest.mark.parametrize("method", ["doubling", "matrix_exp"])
def test_validation_never_changes_a_result(method: str) -> None:
    """The same values and gradients with and without validate_args (bit for bit)."""
    F, L, Qc, dt = _large(20)
    outs = []
    for validate in (False, True):
        args = [t.clone().requires_grad_() for t in (F, Qc, dt)]
        d = tl.discretize(args[0], L, args[1], args[2] * 1e-2, method=method, validate_args=validate)
        grads = torch.autograd.grad(d.A.square().sum() + d.Q.square().sum(), args)
        outs.append((d.A, d.Q, *grads))
    for a, b in zip(*outs):
        assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matrix_exp_noise_of_a_zero_step_is_accepted(dtype: torch.dtype) -> None:
    """Issue 40: ``model=singer dtype=float32 filter.method=matrix_exp`` stopped at once with
    "Q not positive semi-definite": a dt = 0 step's Q = 0 failed the PSD check (its shift, tol
    times the smallest normal float, underflowed). A zero Q passes; the Singer model over the
    steps of that run (0 and 0.1 … 10) gives a checked, symmetric Q, PSD to its tolerance."""
    with torch.no_grad():
        m = tl.models.singer(0.6, 2.0, dim=2, dtype=dtype).matrices()
    dt = torch.cat([torch.zeros(3, dtype=dtype), torch.logspace(-1, 1, 50, dtype=dtype)])
    d = tl.discretize(m.F, m.L, m.Qc, dt, method="matrix_exp")
    assert float(d.Q[:3].abs().max()) == 0.0 and torch.equal(d.Q, d.Q.mT)
    eig = torch.linalg.eigvalsh(d.Q.double())
    assert bool((eig >= -(torch.finfo(dtype).eps ** 0.5) * d.Q.double().abs().amax((-2, -1))[:, None]).all())
    tl.core.discretization.check_matrix_exp_noise(torch.zeros(4, 6, 6, dtype=dtype))
