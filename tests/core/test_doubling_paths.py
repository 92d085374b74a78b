"""The doubling method's recurrence and its one specialisation agree with each other and with
independent references.

``doubling`` runs the general per-element recurrence (``per_element_doubling``: Horner series on
the sub-step, masked doubling: a Python loop eagerly, torch's while_loop traced) or, for ONE
parameter set, ``shared_series`` (series terms once, one product for the batch, the same
doubling). Both must give the same (A, Q, G) to rounding, on benign and stiff elements, with
gradients, eagerly, compiled and exported.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch

import torchsde_lti as tl
from torchsde_lti.core._doubling import per_element_doubling
from torchsde_lti.core.series import shared_series
from torchsde_lti.core.validation import sde_inputs

F64 = torch.float64


def _problem(n: int, p: int, N: int, kind: str, seed: int, dtype: torch.dtype = F64):
    g = torch.Generator().manual_seed(seed)
    F = torch.randn(N, n, n, generator=g, dtype=F64)
    if kind == "stiff":  # fast and slow modes, long steps: A decays, the E → A switch runs
        F = F + torch.diag_embed(-torch.logspace(-3, 4, n, dtype=F64)).expand(N, n, n)
    elif kind == "nilpotent":
        F = torch.triu(F, 1)
    L = torch.randn(N, n, 2, generator=g, dtype=F64)
    Qc = torch.eye(2, dtype=F64).expand(N, 2, 2) * (1e6 if kind == "big_noise" else 1.0)
    B = torch.randn(N, n, p, generator=g, dtype=F64) if p else None
    dt = torch.exp(torch.empty(N, dtype=F64).uniform_(-7.0, 3.0, generator=g))
    dt[0] = 0.0
    cast = lambda x: None if x is None else x.to(dtype)  # noqa: E731
    return cast(F), cast(L), cast(Qc), cast(dt), cast(B)


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().amax() / b.abs().amax().clamp_min(1e-300))


def _vs_scipy(F, W, B, dt):
    """(A, Q, G) of one element from scipy's expm of the Van Loan and ZOH blocks (accurate
    where the element is benign)."""
    n = F.shape[0]
    E = scipy.linalg.expm(np.block([[F, W], [np.zeros((n, n)), -F.T]]) * dt)
    Z = scipy.linalg.expm(np.block([[F, B], [np.zeros((B.shape[1], n + B.shape[1]))]]) * dt)
    return E[:n, :n], E[:n, n:] @ E[:n, :n].T, Z[:n, n:]


@pytest.mark.parametrize("kind", ["random", "stiff", "nilpotent", "big_noise"])
@pytest.mark.parametrize("p", [0, 2])
def test_a_batch_equals_its_elements_called_one_at_a_time(kind: str, p: int) -> None:
    """The masked doubling (every element through the most halvings, the done ones held) gives
    each element what a call of that element alone gives."""
    for n in (1, 2, 3, 5):
        F, L, Qc, dt, B = _problem(n, p, 9, kind, seed=n)
        x = sde_inputs(F, L, Qc, dt, B)
        A1, Q1, G1 = per_element_doubling(x)
        for i in range(9):  # per element: decayed A of a stiff element is small but exact
            xi = sde_inputs(F[i], L[i], Qc[i], dt[i], None if B is None else B[i])
            Ai, Qi, Gi = per_element_doubling(xi)
            for a, c in ((A1, Ai), (Q1, Qi)) + (((G1, Gi),) if p else ()):
                assert _rel(a[i], c) < 1e-12
        assert torch.equal(Q1, Q1.mT)


def test_per_element_against_scipy_van_loan() -> None:
    """Benign elements (‖F‖ dt ≤ 5, where scipy's full-step Van Loan is accurate)."""
    F, L, Qc, dt, B = _problem(3, 1, 12, "random", seed=3)
    A, Q, G = per_element_doubling(sde_inputs(F, L, Qc, dt, B))
    for i in range(12):
        if float(dt[i] * F[i].abs().sum(0).max()) > 5.0:
            continue
        W = (L[i] @ Qc[i] @ L[i].T).numpy()
        A_r, Q_r, G_r = _vs_scipy(F[i].numpy(), W, B[i].numpy(), float(dt[i]))
        assert _rel(A[i], torch.as_tensor(A_r)) < 1e-12
        assert _rel(Q[i], torch.as_tensor(Q_r)) < 1e-11
        assert _rel(G[i], torch.as_tensor(G_r)) < 1e-12


@pytest.mark.parametrize("kind", ["random", "nilpotent"])
def test_shared_path_equals_per_element_path_for_one_parameter_set(kind: str) -> None:
    F, L, Qc, _, B = _problem(4, 1, 1, kind, seed=5)
    dt = torch.tensor([0.0, 1e-4, 0.3, 2.0, 40.0] * 8, dtype=F64)
    x = sde_inputs(F[0], L[0], Qc[0], dt, B[0])
    series = shared_series(x.F, x.W, x.B)
    shared = series(dt)
    for batch_last in (False, True):
        for a, b in zip(per_element_doubling(x, batch_last), series(dt, batch_last)):
            assert _rel(a, b) < 1e-12
    assert all(a.shape == b.shape for a, b in zip(shared, per_element_doubling(x)))


def test_float32_psd_and_close_to_float64() -> None:
    F, L, Qc, dt, _ = _problem(4, 0, 40, "stiff", seed=7, dtype=torch.float32)
    A, Q, _ = per_element_doubling(sde_inputs(F, L, Qc, dt))
    A64, Q64, _ = per_element_doubling(sde_inputs(F.double(), L.double(), Qc.double(), dt.double()))
    for i in range(40):
        assert _rel(A[i].double(), A64[i]) < 1e-4
        assert _rel(Q[i].double(), Q64[i]) < 1e-4
    eig = torch.linalg.eigvalsh(Q.double())
    assert bool((eig >= -1e-6 * eig.abs().amax(-1, keepdim=True)).all())


def test_gradcheck_with_doubling_and_switch() -> None:
    """Gradients through the sub-step series, the sorted doubling and the E → A switch."""
    F, L, Qc, _, B = _problem(3, 1, 1, "random", seed=4)
    F = (F[0] - 0.5 * torch.eye(3, dtype=F64)).requires_grad_()
    L, B = L[0].requires_grad_(), B[0].requires_grad_()
    dt = torch.tensor([0.3, 1.7, 6.0, 25.0], dtype=F64, requires_grad=True)

    def fn(F, L, B, dt):
        return per_element_doubling(sde_inputs(F, L, Qc[0], dt, B))

    assert torch.autograd.gradcheck(fn, (F, L, B, dt), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_empty_batches() -> None:
    """An empty batch (per-element or shared parameters) gives empty results of the right shapes."""
    import torchsde_lti as tl

    L, Qc = torch.eye(2, dtype=F64), torch.eye(2, dtype=F64)
    d = tl.discretize(torch.randn(0, 2, 2, dtype=F64), L, Qc, torch.ones(0, dtype=F64))
    assert d.A.shape == d.Q.shape == (0, 2, 2)
    d = tl.discretize(-torch.eye(2, dtype=F64), L, Qc, torch.ones(0, 3, dtype=F64), B=torch.ones(2, 1, dtype=F64))
    assert d.A.shape == (0, 3, 2, 2) and d.G is not None and d.G.shape == (0, 3, 2, 1)


@pytest.mark.parametrize("N", [5, 300])
def test_per_element_first_and_second_derivatives(N: int) -> None:
    """First and second derivatives through the per-element recurrence: the series, the masked
    doubling (held elements, the E → A switch) of stiff elements."""
    F0, L0, Qc, dt0, B = _problem(2, 1, N, "stiff", seed=5)
    shift = torch.linalg.eigvals(F0).real.amax(-1).clamp_min(0.0) + 0.1  # stable: bounded values
    F0 = F0 - shift[:, None, None] * torch.eye(2, dtype=F64)
    g = torch.Generator().manual_seed(6)
    weights = [torch.randn(N, 2, c, generator=g, dtype=F64) for c in (2, 2, 1)]
    a = torch.tensor(0.7, dtype=F64, requires_grad=True)
    b = torch.tensor(1.3, dtype=F64, requires_grad=True)
    L = L0[:1].clone().requires_grad_()  # shared by all elements

    def fn(a, b, L):
        out = per_element_doubling(sde_inputs(F0 * a, L, Qc, dt0 * b, B))
        return tuple((x * w).sum() for x, w in zip(out, weights))

    assert torch.autograd.gradcheck(fn, (a, b, L), eps=1e-6, atol=1e-6, rtol=1e-5)
    assert torch.autograd.gradgradcheck(fn, (a, b, L), eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.filterwarnings("ignore:.*torch.jit.script.*:DeprecationWarning")  # inside torch.func
@pytest.mark.parametrize("n, N", [(2, 300), (5, 40)])
def test_per_element_paths_under_torch_func_and_forward_mode(n: int, N: int) -> None:
    """torch.func.grad / jvp and forward-mode AD through the per-element recurrence equal
    reverse-mode autograd. (vmap does not apply: the number of halvings is data-dependent
    control flow; the batch dimensions are the vectorisation.)"""
    import torch.autograd.forward_ad as fwAD

    import torchsde_lti as tl

    g = torch.Generator().manual_seed(7)
    F = -torch.eye(n, dtype=F64) - 0.3 * torch.randn(N, n, n, generator=g, dtype=F64)
    L, Qc = torch.ones(n, 1, dtype=F64), torch.ones(1, 1, dtype=F64)
    dt = torch.rand(N, generator=g, dtype=F64) * 10
    V = torch.randn(N, n, n, generator=g, dtype=F64)

    def loss(F: torch.Tensor) -> torch.Tensor:
        d = tl.discretize(F, L, Qc, dt)
        return d.Q.sum() + d.A.sum()

    Fr = F.clone().requires_grad_()
    (want,) = torch.autograd.grad(loss(Fr), Fr)
    assert torch.allclose(torch.func.grad(loss)(F), want, rtol=1e-12, atol=1e-12)
    directional = (want * V).sum()
    assert torch.allclose(torch.func.jvp(loss, (F,), (V,))[1], directional, rtol=1e-10)
    with fwAD.dual_level():
        tangent = fwAD.unpack_dual(loss(fwAD.make_dual(F, V))).tangent
    assert torch.allclose(tangent, directional, rtol=1e-10)


@pytest.mark.parametrize("N", [1, 100])
@pytest.mark.parametrize("dtype, scale", [(torch.float32, 1e20), (torch.float64, 1e160)])
def test_huge_entries_and_huge_steps(N: int, dtype: torch.dtype, scale: float) -> None:
    """Finite parameters at the edge of the float range: F and Qc ~ 1e20 (float32) / 1e160
    (float64) with ‖F‖ dt ≈ 3 (the squares in the norms overflow), and dt near the largest
    float (‖F‖ dt overflows: A → 0, Q → P∞), per element and shared, against scipy / the
    stationary covariance."""
    import torchsde_lti as tl

    F0 = np.array([[-1.0, 0.5], [0.0, -2.0]])
    tol = 1e-12 if dtype == F64 else 2e-5
    F = torch.tensor(F0 * scale, dtype=dtype).expand(N, 2, 2)
    eye = torch.eye(2, dtype=dtype)
    d = tl.discretize(F, eye, eye * scale, torch.full((N,), 3.0 / scale, dtype=dtype))
    C = np.block([[F0, np.eye(2)], [np.zeros((2, 2)), -F0.T]]) * 3.0
    E = scipy.linalg.expm(C)
    A, Q = E[:2, :2], E[:2, 2:] @ E[:2, :2].T  # s = u / scale: the scales cancel in Q
    assert np.abs(d.A.double().numpy() - A).max() < tol
    assert np.abs(d.Q.double().numpy() - Q).max() < tol * np.abs(Q).max()

    huge = torch.full((N,), torch.finfo(dtype).max / 2, dtype=dtype)
    P = tl.stationary_covariance(torch.tensor(F0, dtype=dtype), eye, eye)
    for Fi in (torch.tensor(F0, dtype=dtype).expand(N, 2, 2), torch.tensor(F0, dtype=dtype)):
        d = tl.discretize(Fi, eye, eye, huge)
        assert float(d.A.abs().max()) == 0.0
        assert float((d.Q - P).abs().max()) < 10 * tol


def test_inference_mode_first_then_autograd() -> None:
    """A first call under torch.inference_mode (filling any cache of the core) does not break
    a later call with gradients."""
    import subprocess
    import sys

    code = (
        "import torch, torchsde_lti as tl\n"
        "F = torch.randn(5, 3, 3, dtype=torch.float64) - 2 * torch.eye(3, dtype=torch.float64)\n"
        "I = torch.eye(3, dtype=torch.float64)\n"
        "with torch.inference_mode():\n"
        "    tl.discretize(F, I, I, torch.rand(5, dtype=torch.float64))\n"
        "F.requires_grad_()\n"
        "tl.discretize(F, I, I, torch.rand(5, dtype=torch.float64)).Q.sum().backward()\n"
        "assert torch.isfinite(F.grad).all()\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)  # a fresh process: an empty cache


@pytest.mark.parametrize("order", [2, 3])
def test_shared_nilpotent_series_gradients(order: int) -> None:
    """The terminating series of an integrator chain, with F requiring grad: gradcheck in
    float64, the same gradient as the per-element algorithm (which doubles), and finite
    values and gradients in float32 at a step whose unneeded coefficients overflow."""
    F0 = torch.diag(torch.ones(order - 1, dtype=F64), 1)
    L = torch.zeros(order, 1, dtype=F64)
    L[-1] = 1.0
    Qc = torch.tensor([[0.7]], dtype=F64)
    dt = torch.tensor([0.0, 1e-3, 0.4, 2.5, 30.0] * 8, dtype=F64)

    def shared(F):
        x = sde_inputs(F, L, Qc, dt)
        return shared_series(x.F, x.W, x.B)(dt)[:2]

    F = F0.clone().requires_grad_()
    assert torch.autograd.gradcheck(shared, (F,), eps=1e-7, atol=1e-5, rtol=1e-6)
    weights = torch.randn(2, 40, order, order, dtype=F64, generator=torch.Generator().manual_seed(1))
    (g_shared,) = torch.autograd.grad(sum((w * t).sum() for w, t in zip(weights, shared(F))), F)
    A, Q, _ = per_element_doubling(sde_inputs(F, L, Qc, dt))
    (g_element,) = torch.autograd.grad((weights[0] * A).sum() + (weights[1] * Q).sum(), F)
    assert _rel(g_shared, g_element) < 1e-10

    F32 = F0.float().requires_grad_()
    x = sde_inputs(F32, L.float(), Qc.float(), torch.full((40,), 3e7))
    A, Q, _ = shared_series(x.F, x.W, x.B)(x.dt)
    assert torch.isfinite(A).all() and torch.isfinite(Q).all()  # CA: Q_00 ≈ 8.5e35 fits
    (g,) = torch.autograd.grad(A.sum(), F32)
    assert torch.isfinite(g).all()


@pytest.mark.parametrize("kind", ["random", "stiff", "big_noise"])
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_shared_series_equals_the_per_element_recurrence(kind: str, dtype: torch.dtype) -> None:
    """One parameter set's SharedSeries (formed once, called on many steps: what the online
    step keeps per parameter version) gives the (A, Q, G) of the general per-element recurrence,
    in both output layouts; Q exactly symmetric and PSD in both dtypes (a stable F: A and Q
    finite over steps up to 1e3)."""
    F, L, Qc, _, B = _problem(4, 2, 1, kind, seed=21)
    F = F[0] - (torch.linalg.eigvals(F[0]).real.max().clamp_min(0) + 0.2) * torch.eye(4, dtype=F64)
    g = torch.Generator().manual_seed(1)
    dt = torch.cat([torch.zeros(1, dtype=F64), 10.0 ** (torch.rand(299, generator=g, dtype=F64) * 9 - 6)])
    x = sde_inputs(F, L[0], Qc[0], dt, B[0])
    series = shared_series(x.F.to(dtype), x.W.to(dtype), x.B.to(dtype))
    eager, eager_bl = series(dt.to(dtype)), series(dt.to(dtype), batch_last=True)
    reference = per_element_doubling(x)
    tol = 1e-12 if dtype == F64 else 1e-5
    for a, c, d in zip(eager, eager_bl, reference):
        assert a.dtype == dtype and a.shape == d.shape and c.shape == (*d.shape[1:], d.shape[0])
        assert _rel(a.double(), d) < tol and _rel(c.movedim(-1, 0).double(), d) < tol
    assert torch.equal(eager[1], eager[1].mT)
    eig = torch.linalg.eigvalsh(eager[1].double())
    assert eig.min() >= -1e-6 * torch.linalg.matrix_norm(eager[1].double(), 2).amax()


def test_discretization_series_of_a_nilpotent_f_differentiates_with_respect_to_f() -> None:
    """A nilpotent F recording gradients: the series keeps the terms whose value is zero but
    whose derivative is not, so d/dF of its (A, Q) equals that of core's discretize (gradcheck)."""
    from torchsde_lti.core.discretization import discretization_series, discretize

    L = torch.tensor([[0.0], [0.0], [1.0]], dtype=F64)
    Qc = torch.tensor([[0.7]], dtype=F64)
    dt = torch.tensor([0.0, 0.3, 2.5], dtype=F64)
    F = torch.diag(torch.ones(2, dtype=F64), 1).requires_grad_()

    def via_series(F: torch.Tensor) -> tuple[torch.Tensor, ...]:
        A, Q, _ = discretization_series(F, L @ Qc @ L.mT, None)(dt)
        return A, Q

    assert torch.autograd.gradcheck(via_series, (F,), eps=1e-7, atol=1e-5, rtol=1e-6)
    weights = torch.randn(2, 3, 3, 3, dtype=F64, generator=torch.Generator().manual_seed(2))
    (g_series,) = torch.autograd.grad(sum((w * t).sum() for w, t in zip(weights, via_series(F))), F)
    ref = discretize(F, L, Qc, dt)
    (g_ref,) = torch.autograd.grad((weights[0] * ref.A).sum() + (weights[1] * ref.Q).sum(), F)
    assert _rel(g_series, g_ref) < 1e-10


def test_discretization_series_rejects_bad_shapes() -> None:
    """The public series of one parameter set checks shapes and names the argument."""
    from torchsde_lti.core import discretization_series

    F, W, B = -torch.eye(3, dtype=F64), torch.eye(3, dtype=F64), torch.ones(3, 1, dtype=F64)
    assert discretization_series(F, W, B)(torch.tensor([0.5], dtype=F64))[2].shape == (1, 3, 1)
    for args, kwargs, message in (
        ((torch.ones(2, 3, dtype=F64), None), {}, "F must be square"),
        ((F.expand(2, 3, 3), W), {}, r"F must be one \(n, n\) matrix"),
        ((torch.zeros(0, 0, dtype=F64), None), {}, "at least one state"),
        ((F, torch.eye(2, dtype=F64)), {}, "W must have 3 rows"),
        ((F, torch.ones(3, 2, dtype=F64)), {}, "W must have 3 columns"),
        ((F, W.expand(2, 3, 3)), {}, "W must be one matrix with 3 rows"),
        ((F, W, torch.ones(2, 1, dtype=F64)), {}, "B must have 3 rows"),
        ((F, W.float()), {}, "W must have F's dtype"),
    ):
        with pytest.raises(ValueError, match=message):
            discretization_series(*args, **kwargs)
    with pytest.raises(TypeError, match="F must be a real floating tensor"):
        discretization_series(torch.eye(3, dtype=torch.int64), None)


def _exported(series, L: torch.Tensor, Qc: torch.Tensor, F_example: torch.Tensor, dt_example: torch.Tensor):
    """A shared series and the per-element doubling exported with a dynamic batch: the
    programs (dt) -> (A, Q) and (F, dt) -> (A, Q)."""
    from torch.export import Dim

    class Shared(torch.nn.Module):
        def forward(self, dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            A, Q, _ = series(dt)
            return A, Q

    class PerElement(torch.nn.Module):
        def forward(self, F: torch.Tensor, dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            A, Q, _ = per_element_doubling(sde_inputs(F, L, Qc, dt, validate_args=False))
            return A, Q

    b = Dim("b")
    shared = torch.export.export(Shared(), (dt_example,), dynamic_shapes=({0: b},)).module()
    per_element = torch.export.export(PerElement(), (F_example, dt_example), dynamic_shapes=({0: b}, {0: b}))
    return shared, per_element.module()


def test_export_with_a_dynamic_batch_equals_eager() -> None:
    """The shared series and the per-element recurrence exported with a dynamic batch (the
    doubling as torch's while_loop) give the eager values on a batch larger than the example,
    steps over 18 decades (every halving runs: no cap on the number of doublings)."""
    _, L, Qc, _, _ = _problem(3, 0, 1, "random", seed=7)
    F = torch.tensor([[-1000.0, 0.0, 0.0], [1.0, -1.0, 0.0], [0.5, 2.0, -0.01]], dtype=F64)  # fast and slow
    series = shared_series(F, L[0] @ Qc[0] @ L[0].mT, None)
    dt = 10.0 ** (torch.rand(3000, generator=torch.Generator().manual_seed(0), dtype=F64) * 18 - 6)
    shared, per_element = _exported(series, L[0], Qc[0], F.expand(5, 3, 3).contiguous(), dt[:5])
    for got, want in zip(shared(dt), series(dt)):
        assert _rel(got, want) <= 1e-12
    want = per_element_doubling(sde_inputs(F.expand(3000, 3, 3), L[0], Qc[0], dt))
    for got, w in zip(per_element(F.expand(3000, 3, 3).contiguous(), dt), want):
        assert _rel(got, w) <= 1e-12


@pytest.mark.slow  # torch.compile: ≈ 30 s
def test_compiled_values_and_gradients_equal_eager() -> None:
    """torch.compile (fullgraph: the doubling as a differentiable while_loop) of the per-element
    recurrence and of the shared series: the eager values and gradients with respect to F, Qc
    and dt, for steps whose halvings differ by 40."""
    g = torch.Generator().manual_seed(3)
    F0 = torch.tensor([[-1000.0, 0.0], [1.0, -1.0]], dtype=F64)
    L = torch.eye(2, dtype=F64)
    dt0 = torch.tensor([1e-3, 1.0, 1e6, 1e9], dtype=F64)
    weights = torch.randn(2, 4, 2, 2, generator=g, dtype=F64)

    def per_element(F, Qc, dt):  # type: ignore[no-untyped-def]
        A, Q, _ = per_element_doubling(sde_inputs(F, L, Qc, dt, validate_args=False))
        return (weights[0] * A).sum() + (weights[1] * Q).sum()

    def shared(F, Qc, dt):  # type: ignore[no-untyped-def]
        A, Q, _ = shared_series(F, Qc, None)(dt)
        return (weights[0] * A).sum() + (weights[1] * Q).sum()

    for fn, F in ((per_element, F0.expand(4, 2, 2).contiguous()), (shared, F0)):
        results = []
        for run in (fn, torch.compile(fn, fullgraph=True)):
            args = [t.clone().requires_grad_() for t in (F, torch.eye(2, dtype=F64), dt0)]
            value = run(*args)
            results.append((value, *torch.autograd.grad(value, args)))
        for a, b in zip(*results):
            assert _rel(a, b) <= 1e-12


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_q_is_exactly_symmetric_on_every_path(dtype: torch.dtype) -> None:
    """Q == Qᵀ bit for bit (the average X + Xᵀ; torch.lerp(X, Xᵀ, 1/2) is not): one element, one
    shared F (series), many per-element F, matrix_exp."""
    g = torch.Generator().manual_seed(3)
    for n in (2, 3, 6):
        M = torch.randn(3000, n, n, generator=g, dtype=F64)
        F = (M - 2.0 * n * torch.eye(n, dtype=F64)).to(dtype)
        C = torch.randn(3000, n, n, generator=g, dtype=F64)
        Qc = (C @ C.mT / n + 0.1 * torch.eye(n, dtype=F64)).to(dtype)
        L = torch.eye(n, dtype=dtype)
        dt = torch.logspace(-3, 3, 3000, dtype=F64).to(dtype)
        calls = {
            "one element": (F[0], L, Qc[0], dt[:1], "doubling"),
            "shared": (F[0], L, Qc[0], dt, "doubling"),
            "per element": (F, L, Qc, dt, "doubling"),
            "matrix_exp": (F[:50], L, Qc[:50], dt[:50] * 1e-3, "matrix_exp"),
        }
        for name, (F_, L_, Qc_, dt_, method) in calls.items():
            Q = tl.discretize(F_, L_, Qc_, dt_, method=method).Q
            assert torch.equal(Q, Q.mT), (name, n)
    # a lightly damped oscillator over long steps: Q before symmetrisation far from symmetric
    F = torch.tensor([[0.0, 1.0], [-100.0, -0.1]], dtype=dtype)
    L, Qc1 = torch.tensor([[0.0], [1.0]], dtype=dtype), torch.ones(1, 1, dtype=dtype)
    for N in (3, 40, 3000):
        Q = tl.discretize(F.expand(N, 2, 2) if N == 3000 else F, L, Qc1, torch.full((N,), 1000.0, dtype=dtype)).Q
        assert torch.equal(Q, Q.mT), N
    W = tl.core.linalg.noise_covariance(torch.randn(50, 4, 2, generator=g).to(dtype), Qc[:50, :2, :2])
    assert torch.equal(W, W.mT)


def test_export_of_the_public_discretize_with_a_dynamic_per_element_batch() -> None:
    """``discretize`` itself (not the inner per-element function) exported with every
    element's own F, L, Qc and dt on a dynamic batch: one program for every batch size (the
    one-parameter-set test read the symbolic batch and fixed it), equal to eager."""
    from torch.export import Dim

    class PerElement(torch.nn.Module):
        def forward(self, F: torch.Tensor, L: torch.Tensor, Qc: torch.Tensor, dt: torch.Tensor):
            d = tl.discretize(F, L, Qc, dt)
            return d.A, d.Q

    g = torch.Generator().manual_seed(5)

    def args(N: int) -> tuple[torch.Tensor, ...]:
        X = torch.randn(N, 2, 2, generator=g, dtype=F64)
        F = X - X.mT - 0.5 * torch.eye(2, dtype=F64)
        return (
            F,
            torch.eye(2, dtype=F64).expand(N, 2, 2),
            torch.eye(2, dtype=F64).expand(N, 2, 2),
            torch.rand(N, generator=g, dtype=F64) * 10,
        )

    N = Dim("N", min=1, max=100_000)
    program = torch.export.export(PerElement(), args(12), dynamic_shapes=({0: N},) * 4).module()
    for size in (1, 5, 700):
        a = args(size)
        for got, want in zip(program(*a), PerElement()(*a)):
            assert got.shape == want.shape and _rel(got, want) <= 1e-12
