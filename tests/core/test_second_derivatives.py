"""Second derivatives with respect to F at a nilpotent F (F = 0: a zero-initialised learned
drift; an integrator chain) on every path of the doubling method (and of ``"matrix_exp"``,
whose gradients are the doubling's).

The series of a nilpotent F (F^m = 0) terminates for the values, but the d-th derivative of F^k
with respect to F vanishes only for k ≥ (d+1) m (Q: 𝓛^k, k ≥ (d+2) m − 1): a series cut at the
terms the values (or the first derivatives) need gives wrong second derivatives — at F = 0 a
Hessian of zeros. Where F records a graph every path keeps the terms of order ≤ 2; third
derivatives are not claimed exact.
"""

from __future__ import annotations

import pytest
import torch
from torch.autograd.functional import hessian

import torchsde_lti as tl
from torchsde_lti.core import _doubling, discretization, series

F64 = torch.float64

# (path, number of steps, F shared by the steps or expanded to one per step): the per-element
# recurrence (F per step) and the one-parameter-set series (one F; a nilpotent F's series
# terminates: no halving, the full step).
PATHS = {
    "single": ("shared_series", 1, False),
    "few": ("per_element_doubling", 3, True),
    "per_element": ("per_element_doubling", 700, True),
    "shared": ("shared_series", 40, False),
}


def _spy(monkeypatch: pytest.MonkeyPatch, name: str) -> list[int]:
    """Count the calls of the path ``name`` (a module global of ``discretization``)."""
    calls: list[int] = []
    inner = getattr(discretization, name)

    def wrapped(*args, **kwargs):
        calls.append(1)
        return inner(*args, **kwargs)

    monkeypatch.setattr(discretization, name, wrapped)
    return calls


def _chain(n: int) -> torch.Tensor:
    """An integrator chain (nilpotent of index n); n = 2: constant velocity."""
    return torch.diag(torch.ones(n - 1, dtype=F64), 1)


def _problem(n: int, N: int, expand: bool, method: str = "doubling"):
    """fn(F) -> weighted sums of (A, Q, G) over N steps (F (n, n), expanded to (N, n, n) with
    ``expand``): small outputs for gradgradcheck."""
    g = torch.Generator().manual_seed(n + N)
    L = torch.randn(n, 2, generator=g, dtype=F64)
    Qc = torch.eye(2, dtype=F64)
    B = torch.randn(n, 1, generator=g, dtype=F64)
    dt = torch.empty(N, dtype=F64).uniform_(0.2, 0.9, generator=g)
    weights = [torch.randn(N, n, c, generator=g, dtype=F64) for c in (n, n, 1)]

    def fn(F: torch.Tensor) -> tuple[torch.Tensor, ...]:
        Fx = F.expand(N, n, n) if expand else F
        out = tl.discretize(Fx, L, Qc, dt, B=B, method=method)
        return tuple((x * w).sum() for x, w in zip(out, weights))

    return fn


@pytest.mark.parametrize("path", list(PATHS))
@pytest.mark.parametrize("n, kind", [(1, "zero"), (2, "zero"), (2, "chain"), (3, "chain")])
def test_gradgradcheck_at_nilpotent_F(path: str, n: int, kind: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """gradgradcheck (float64, finite differences of the gradient) at F = 0 and at an integrator
    chain, on each path; the path taken is checked."""
    name, N, expand = PATHS[path]
    calls = _spy(monkeypatch, name)
    F = (torch.zeros(n, n, dtype=F64) if kind == "zero" else _chain(n)).requires_grad_()
    fn = _problem(n, N, expand)
    assert torch.autograd.gradcheck(fn, (F,))
    assert calls
    assert torch.autograd.gradgradcheck(fn, (F,))


@pytest.mark.parametrize("N", [1, 40])
def test_gradgradcheck_matrix_exp_at_zero(N: int) -> None:
    """method="matrix_exp" (the doubling's gradients) at F = 0."""
    F = torch.zeros(2, 2, dtype=F64, requires_grad=True)
    assert torch.autograd.gradgradcheck(_problem(2, N, False, method="matrix_exp"), (F,))


@pytest.mark.parametrize("N", [1, 40])
def test_hessian_at_zero_is_exact(N: int) -> None:
    """At F = 0 the Hessian of sum(C ∘ A) is that of the term F² dt²/2:
    dt²/2 · sum(C ∘ (E_a E_b + E_b E_a)) (the hunt's reproducer: zeros before the fix)."""
    dt, C = 0.7, torch.tensor([[1.0, 2.0], [3.0, 4.0]], dtype=F64)
    steps = torch.full((N,), dt, dtype=F64) if N > 1 else torch.tensor(dt, dtype=F64)
    H = hessian(lambda F: (tl.transition_matrix(F, steps) * C).sum() / N, torch.zeros(2, 2, dtype=F64))
    E = torch.eye(4, dtype=F64).reshape(4, 2, 2)
    exact = torch.stack([torch.stack([((E[a] @ E[b] + E[b] @ E[a]) * C).sum() for b in range(4)]) for a in range(4)])
    torch.testing.assert_close(H.reshape(4, 4), exact * dt**2 / 2, rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("N", [1, 40])
def test_hessian_at_constant_velocity_matches_finite_differences(N: int) -> None:
    """Constant velocity: the Hessians of sum(C ∘ A) and sum(C ∘ Q) equal central differences of
    the (first-order exact) gradient — F ± ε is not nilpotent and takes the full series."""
    dt, C = 0.7, torch.tensor([[1.0, 2.0], [3.0, 4.0]], dtype=F64)
    steps = torch.full((N,), dt, dtype=F64) if N > 1 else torch.tensor(dt, dtype=F64)
    L, Qc = torch.tensor([[0.0], [1.0]], dtype=F64), torch.ones(1, 1, dtype=F64)
    Fcv = _chain(2)
    for pick in (0, 1):

        def f(F: torch.Tensor) -> torch.Tensor:
            return (tl.discretize(F, L, Qc, steps)[pick] * C).sum() / N

        def grad(F: torch.Tensor) -> torch.Tensor:
            F = F.clone().requires_grad_()
            return torch.autograd.grad(f(F), F)[0].reshape(4)

        eps = 1e-5
        fd = torch.stack(
            [(grad(Fcv + eps * D) - grad(Fcv - eps * D)) / (2 * eps) for D in torch.eye(4, dtype=F64).reshape(4, 2, 2)]
        )
        torch.testing.assert_close(hessian(f, Fcv).reshape(4, 4), fd, rtol=1e-7, atol=1e-8)


@pytest.mark.parametrize("path", list(PATHS))
def test_values_with_and_without_a_graph(path: str) -> None:
    """The terms kept for the derivatives change the values by rounding at most (at a
    nilpotent F they are exact zeros)."""
    _, N, expand = PATHS[path]
    F = _chain(3)
    fn = _problem(3, N, expand)
    with torch.no_grad():
        plain = fn(F)
    graph = fn(F.clone().requires_grad_())
    for a, b in zip(plain, graph):
        torch.testing.assert_close(a, b.detach(), rtol=1e-14, atol=1e-14)


def test_term_counts() -> None:
    """The degree rule: the least K of the truncation bound, at least 2n − 1 (each entry of a
    graded Q keeps its leading term) per element; at least 4n for one parameter set, whose rows
    of a nilpotent F (index m) stop at k < 4m (values, first and second derivatives)."""
    assert _doubling.series_degree(F64, 1) == 14 and _doubling.series_degree(torch.float32, 1) == 8
    assert _doubling.series_degree(F64, 9) == 17
    for F, m in ((torch.zeros(3, 3, dtype=F64), 1), (_chain(3), 3), (_chain(2), 2)):
        n = F.shape[0]
        s = series.shared_series(F, torch.eye(n, dtype=F64), None)
        assert s.coeff.shape[1] == max(23, 4 * n) + 1 and bool(s.nilpotent)  # (θ_shared = 1: 23 terms)
        assert int(s.terms.sum()) == 4 * m  # (k = 0 … 4m − 1)
    s = series.shared_series(-torch.eye(2, dtype=F64), torch.eye(2, dtype=F64), None)
    assert not bool(s.nilpotent) and bool(s.terms.all())


@pytest.mark.filterwarnings("ignore:.*torch.jit.script.*:DeprecationWarning")  # inside torch.func
@pytest.mark.parametrize("N", [1, 40])
def test_forward_mode_at_zero(N: int) -> None:
    """Forward mode (torch.func.jvp, whose F records no graph) and torch.func.hessian
    (forward over reverse) at F = 0 equal reverse mode and the exact Hessian."""
    dt = torch.full((N,), 0.7, dtype=F64) if N > 1 else torch.tensor(0.7, dtype=F64)
    L, Qc = torch.tensor([[0.0], [1.0]], dtype=F64), torch.ones(1, 1, dtype=F64)
    F, T = torch.zeros(2, 2, dtype=F64), torch.tensor([[0.0, 1.0], [1.0, 0.0]], dtype=F64)
    f = lambda F: tl.discretize(F, L, Qc, dt)[1]  # noqa: E731
    tangent = torch.func.jvp(f, (F,), (T,))[1]
    reference = torch.autograd.functional.jvp(f, (F.clone().requires_grad_(),), (T,))[1]
    torch.testing.assert_close(tangent, reference, rtol=1e-14, atol=1e-14)
    H = torch.func.hessian(lambda F: tl.transition_matrix(F, dt).sum() / N)(F)
    E = torch.eye(4, dtype=F64).reshape(4, 2, 2)
    exact = torch.stack([torch.stack([(E[a] @ E[b] + E[b] @ E[a]).sum() for b in range(4)]) for a in range(4)])
    torch.testing.assert_close(H.reshape(4, 4), exact * 0.7**2 / 2, rtol=1e-13, atol=1e-14)
