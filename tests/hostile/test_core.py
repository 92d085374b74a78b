"""Hostile inputs to the functional core and its layers: shapes, dtypes, NaN/Inf, sizes 0 and 1,
huge and tiny values (tl.discretize, transition_matrix, zero_order_hold, process_noise, propagate,
stationary_covariance, Transition, VanLoanNoise, Discretization)."""

from __future__ import annotations

import math

import pytest
import torch

import torchsde_lti as tl
from tests.hostile.harness import Case, Finite, Raises, params, run_case

f64, f32 = torch.float64, torch.float32


def _F(dtype: torch.dtype = f64) -> torch.Tensor:  # integrated OU, drag 1
    return torch.tensor([[0.0, 1.0], [0.0, -1.0]], dtype=dtype)


def _L(dtype: torch.dtype = f64) -> torch.Tensor:
    return torch.tensor([[0.0], [1.0]], dtype=dtype)


def _Qc(dtype: torch.dtype = f64) -> torch.Tensor:
    return torch.tensor([[1.0]], dtype=dtype)


def _B(dtype: torch.dtype = f64) -> torch.Tensor:
    return torch.tensor([[0.0], [1.0]], dtype=dtype)


def _chain(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    F = torch.diag(torch.ones(2, dtype=dtype), 1)  # x''' = white noise
    return F, torch.tensor([[0.0], [0.0], [1.0]], dtype=dtype), torch.ones(1, 1, dtype=dtype)


def _cv(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return torch.tensor([[0.0, 1.0], [0.0, 0.0]], dtype=dtype), _L(dtype), _Qc(dtype)


def _disc(*args, **kw):
    return lambda: tl.discretize(*args, **kw)


# --------------------------------------------------------------------------- value checks


def _is_identity_and_zero(d: tl.Discrete) -> None:
    eye = torch.eye(d.A.shape[-1], dtype=d.A.dtype)
    assert torch.equal(d.A, eye.expand_as(d.A)) and torch.equal(d.Q, torch.zeros_like(d.Q))


def _scalar_ou(k: float, q: float, dt: float, dtype: torch.dtype, rtol: float):
    """dx = -k x dt + dβ: A = e^{-k dt}, Q = q (1 - e^{-2 k dt}) / (2k)."""

    def check(d: tl.Discrete) -> None:
        A = math.exp(-k * dt)
        Q = q * -math.expm1(-2 * k * dt) / (2 * k)
        assert float(d.A) == pytest.approx(A, rel=rtol, abs=1e-300)
        assert float(d.Q) == pytest.approx(Q, rel=rtol)

    return check


def _cv_closed_form(dt: float, rtol: float):
    """Constant velocity: A = [[1, dt], [0, 1]], Q = [[dt³/3, dt²/2], [dt²/2, dt]]."""

    def check(d: tl.Discrete) -> None:
        A = torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=f64)
        Q = torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], dtype=f64)
        torch.testing.assert_close(d.A.to(f64), A, rtol=rtol, atol=0)
        torch.testing.assert_close(d.Q.to(f64), Q, rtol=rtol, atol=0)

    return check


def _chain_closed_form(dt: float, rtol: float):
    """x''' = white noise: Q_ij = dt^(5-i-j) / ((5-i-j) (2-i)! (2-j)!)."""

    def check(d: tl.Discrete) -> None:
        fact = [1.0, 1.0, 2.0]
        Q = torch.tensor(
            [[dt ** (5 - i - j) / ((5 - i - j) * fact[2 - i] * fact[2 - j]) for j in range(3)] for i in range(3)],
            dtype=f64,
        )
        torch.testing.assert_close(d.Q.to(f64), Q, rtol=rtol, atol=0)

    return check


def _psd(d: tl.Discrete) -> None:
    Q = d.Q.to(f64)
    torch.testing.assert_close(Q, Q.mT, rtol=0, atol=1e-12 * float(Q.abs().max().clamp_min(1e-300)))
    assert float(torch.linalg.eigvalsh(Q).min()) >= -1e-10 * float(Q.abs().max())


def _shape(*shape: int):
    def check(out) -> None:
        A = out.A if isinstance(out, tl.Discrete) else out
        assert tuple(A.shape) == shape

    return check


def _scaled_like(factor: float):
    """Q is linear in Qc: Q(factor Qc) = factor Q(Qc)."""

    def check(d: tl.Discrete) -> None:
        ref = tl.discretize(_F(), _L(), _Qc(), 1.0)
        torch.testing.assert_close(d.Q / factor, ref.Q, rtol=1e-12, atol=0)
        torch.testing.assert_close(d.A, ref.A, rtol=0, atol=0)

    return check


def _like_float64(tol: float):
    def check(d: tl.Discrete) -> None:
        ref = tl.discretize(_F(), _L(), _Qc(), 1.0)
        torch.testing.assert_close(d.A.to(f64), ref.A, rtol=tol, atol=tol)
        torch.testing.assert_close(d.Q.to(f64), ref.Q, rtol=tol, atol=tol)

    return check


CASES = [
    # shapes
    Case(
        "F-not-square",
        _disc(torch.zeros(2, 3, dtype=f64), _L(), _Qc(), 1.0),
        Raises(ValueError, r"F must be square.*\(2, 3\)"),
    ),
    Case("F-vector", _disc(torch.zeros(2, dtype=f64), _L(), _Qc(), 1.0), Raises(ValueError, r"F must be a matrix")),
    Case("F-scalar", _disc(torch.tensor(1.0, dtype=f64), _L(), _Qc(), 1.0), Raises(ValueError, r"\bF\b")),
    Case(
        "F-0x0",
        _disc(torch.zeros(0, 0, dtype=f64), torch.zeros(0, 1, dtype=f64), _Qc(), 1.0),
        Raises(ValueError, r"\bF\b"),
    ),
    Case(
        "L-wrong-rows", _disc(_F(), torch.zeros(3, 1, dtype=f64), _Qc(), 1.0), Raises(ValueError, r"L must have 2 rows")
    ),
    Case("Qc-wrong-shape", _disc(_F(), _L(), torch.eye(2, dtype=f64), 1.0), Raises(ValueError, r"Qc must have shape")),
    Case(
        "B-wrong-rows",
        _disc(_F(), _L(), _Qc(), 1.0, B=torch.zeros(3, 1, dtype=f64)),
        Raises(ValueError, r"B must have 2 rows"),
    ),
    Case(
        "batch-F3-dt4",
        _disc(_F().expand(3, 2, 2), _L(), _Qc(), torch.ones(4, dtype=f64)),
        Raises(ValueError, r"F: \(3\).*dt: \(4\)"),
    ),
    Case(
        "batch-broadcast-dt-2x3",
        _disc(_F().expand(3, 2, 2), _L(), _Qc(), torch.ones(2, 3, dtype=f64)),
        Finite(_shape(2, 3, 2, 2)),
    ),
    Case("dt-empty", _disc(_F(), _L(), _Qc(), torch.zeros(0, dtype=f64)), Finite(_shape(0, 2, 2))),
    Case("F-empty-batch", _disc(_F().expand(0, 2, 2), _L(), _Qc(), 1.0), Finite(_shape(0, 2, 2))),
    Case(
        "F-1x1-ou",
        _disc(-2.0 * torch.ones(1, 1, dtype=f64), torch.ones(1, 1, dtype=f64), 3.0 * _Qc(), 0.7),
        Finite(_scalar_ou(2.0, 3.0, 0.7, f64, 1e-12)),
    ),
    Case(
        "transition-F-not-square",
        lambda: tl.transition_matrix(torch.zeros(3, 2, dtype=f64), 1.0),
        Raises(ValueError, r"F must be square"),
    ),
    Case(
        "zoh-B-wrong-rows",
        lambda: tl.zero_order_hold(_F(), torch.zeros(3, 1, dtype=f64), 1.0),
        Raises(ValueError, r"B must have 2 rows"),
    ),
    Case(
        "process-noise-L-wrong",
        lambda: tl.process_noise(_F(), torch.zeros(1, 1, dtype=f64), _Qc(), 1.0),
        Raises(ValueError, r"\bL\b"),
    ),
    # dtypes and types
    Case(
        "F-int64",
        _disc(torch.tensor([[0, 1], [0, -1]]), _L(), _Qc(), 1.0),
        Raises(TypeError, r"F must be a real floating"),
    ),
    Case(
        "F-complex", _disc(_F().to(torch.complex128), _L(), _Qc(), 1.0), Raises(TypeError, r"F must be a real floating")
    ),
    Case("F-bool", _disc(torch.eye(2, dtype=torch.bool), _L(), _Qc(), 1.0), Raises(TypeError, r"\bF\b")),
    Case("F-None", _disc(None, _L(), _Qc(), 1.0), Raises(TypeError, r"F must be a tensor")),
    Case("F-str", _disc("F", _L(), _Qc(), 1.0), Raises(TypeError, r"F must be a tensor")),
    Case("F-nested-list", _disc([[0.0, 1.0], [0.0, -1.0]], _L(), _Qc(), 1.0), Finite(_like_float64(0.0))),
    Case("float16", _disc(_F(torch.float16), _L(torch.float16), _Qc(torch.float16), 1.0), Finite(_like_float64(5e-3))),
    Case(
        "bfloat16", _disc(_F(torch.bfloat16), _L(torch.bfloat16), _Qc(torch.bfloat16), 1.0), Finite(_like_float64(3e-2))
    ),
    Case(
        "mixed-f64-f32",
        _disc(_F(), _L(f32), _Qc(), 1.0),
        Finite(lambda d: (d.A.dtype == f64) or pytest.fail(f"dtype {d.A.dtype}")),
    ),
    Case("dt-python-int", _disc(_F(), _L(), _Qc(), 1), Finite(_like_float64(0.0))),
    Case("dt-int-tensor", _disc(_F(), _L(), _Qc(), torch.tensor(1)), Finite(_like_float64(1e-15))),
    Case("dt-complex", _disc(_F(), _L(), _Qc(), torch.tensor(1.0 + 0j)), Raises(TypeError, r"\bdt\b")),
    Case("dt-str", _disc(_F(), _L(), _Qc(), "1.0"), Raises(TypeError, r"\bdt\b")),
    Case("method-euler", _disc(_F(), _L(), _Qc(), 1.0, method="euler"), Raises(ValueError, r"method must be one of")),
    Case("method-None", _disc(_F(), _L(), _Qc(), 1.0, method=None), Raises((ValueError, TypeError), r"method")),
    # NaN / Inf / signs
    Case("F-nan", _disc(_F() * math.nan, _L(), _Qc(), 1.0), Raises(ValueError, r"F contains NaN or Inf")),
    Case("F-inf", _disc(_F() * math.inf, _L(), _Qc(), 1.0), Raises(ValueError, r"F contains NaN or Inf")),
    Case("L-nan", _disc(_F(), _L() * math.nan, _Qc(), 1.0), Raises(ValueError, r"L contains NaN or Inf")),
    Case("Qc-inf", _disc(_F(), _L(), _Qc() * math.inf, 1.0), Raises(ValueError, r"Qc contains NaN or Inf")),
    Case("B-nan", _disc(_F(), _L(), _Qc(), 1.0, B=_B() * math.nan), Raises(ValueError, r"B contains NaN or Inf")),
    Case("dt-nan", _disc(_F(), _L(), _Qc(), math.nan), Raises(ValueError, r"dt contains NaN or Inf")),
    Case("dt-inf", _disc(_F(), _L(), _Qc(), math.inf), Raises(ValueError, r"dt contains NaN or Inf")),
    Case("dt-negative", _disc(_F(), _L(), _Qc(), -1.0), Raises(ValueError, r"dt must be non-negative")),
    Case(
        "dt-negative-in-batch",
        _disc(_F(), _L(), _Qc(), torch.tensor([1.0, -1e-9, 2.0], dtype=f64)),
        Raises(ValueError, r"dt must be non-negative"),
    ),
    Case("Qc-negative", _disc(_F(), _L(), -_Qc(), 1.0), Raises(ValueError, r"Qc must be positive semi-definite")),
    Case(
        "Qc-asymmetric",
        _disc(_F(), torch.eye(2, dtype=f64), torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=f64), 1.0),
        Raises(ValueError, r"Qc must be symmetric"),
    ),
    # sizes 0 and huge / tiny values
    Case("dt-zero", _disc(_F(), _L(), _Qc(), 0.0, B=_B()), Finite(_is_identity_and_zero)),
    Case("dt-minus-zero", _disc(_F(), _L(), _Qc(), -0.0), Finite(_is_identity_and_zero)),
    Case(
        "dt-1e-300",
        _disc(_F(), _L(), _Qc(), 1e-300),
        Finite(lambda d: torch.testing.assert_close(d.A, torch.eye(2, dtype=f64), rtol=0, atol=1e-299)),
    ),
    Case(
        "Qc-zero",
        _disc(_F(), _L(), 0 * _Qc(), 1.0),
        Finite(lambda d: torch.equal(d.Q, torch.zeros_like(d.Q)) or pytest.fail(str(d.Q))),
    ),
    Case("Qc-1e300", _disc(_F(), _L(), 1e300 * _Qc(), 1.0), Finite(_scaled_like(1e300))),
    Case("Qc-1e-300", _disc(_F(), _L(), 1e-300 * _Qc(), 1.0), Finite(_scaled_like(1e-300))),
    Case(
        "F-stiff-1e200",
        _disc(-1e200 * torch.eye(2, dtype=f64), torch.eye(2, dtype=f64), torch.eye(2, dtype=f64), 1.0),
        Finite(lambda d: torch.testing.assert_close(d.Q, torch.eye(2, dtype=f64) / 2e200, rtol=1e-12, atol=0)),
    ),
    Case(
        "ou-dt-1e10-f64",
        _disc(-2.0 * torch.ones(1, 1, dtype=f64), torch.ones(1, 1, dtype=f64), 3.0 * _Qc(), 1e10),
        Finite(_scalar_ou(2.0, 3.0, 1e10, f64, 1e-12)),
    ),
    Case(
        "ou-dt-1e10-f32",
        _disc(-2.0 * torch.ones(1, 1), torch.ones(1, 1), 3.0 * _Qc(f32), 1e10),
        Finite(_scalar_ou(2.0, 3.0, 1e10, f32, 1e-5)),
    ),
    Case("iou-dt-1e10-psd", _disc(_F(), _L(), _Qc(), 1e10), Finite(_psd)),
    Case("cv-dt-1e6-f64", _disc(*_cv(f64), 1e6), Finite(_cv_closed_form(1e6, 1e-12))),
    Case("cv-dt-1e7-f32", _disc(*_cv(f32), 1e7), Finite(_cv_closed_form(1e7, 1e-4))),
    Case("cv-dt-1e8-f32", _disc(*_cv(f32), 1e8), Finite(_cv_closed_form(1e8, 1e-4))),
    Case("chain-dt-1e6-f64", _disc(*_chain(f64), 1e6), Finite(_chain_closed_form(1e6, 1e-12))),
    Case("chain-dt-1e4-f32", _disc(*_chain(f32), 1e4), Finite(_chain_closed_form(1e4, 1e-4))),
    Case("chain-dt-1e6-f32", _disc(*_chain(f32), 1e6), Finite(_chain_closed_form(1e6, 1e-4))),
    Case(
        "chain-transition-dt-1e6-f32",
        lambda: tl.transition_matrix(_chain(f32)[0], 1e6),
        Finite(
            lambda A: torch.testing.assert_close(
                A, torch.tensor([[1.0, 1e6, 5e11], [0.0, 1.0, 1e6], [0.0, 0.0, 1.0]]), rtol=1e-6, atol=0
            )
        ),
    ),
    Case(
        "unstable-dt-100-f64",
        _disc(torch.ones(1, 1, dtype=f64), torch.ones(1, 1, dtype=f64), _Qc(), 100.0),
        Finite(lambda d: pytest.approx(math.exp(100.0), rel=1e-12) == float(d.A) or pytest.fail(str(d.A))),
    ),
    Case(
        "unstable-dt-1000-f64",
        _disc(torch.ones(1, 1, dtype=f64), torch.ones(1, 1, dtype=f64), _Qc(), 1000.0),
        Raises((ValueError, OverflowError, ArithmeticError), r"\bF\b|\bdt\b|overflow"),
    ),
    Case(
        "unstable-dt-100-f32",
        _disc(torch.ones(1, 1), torch.ones(1, 1), _Qc(f32), 100.0),
        Raises((ValueError, OverflowError, ArithmeticError), r"\bF\b|\bdt\b|overflow"),
    ),
    Case(
        "transition-1x1-dt-1e10",
        lambda: tl.transition_matrix(-torch.ones(1, 1, dtype=f64), 1e10),
        Finite(lambda A: float(A) == 0.0 or pytest.fail(str(A))),
    ),
    # stationary covariance
    Case(
        "stationary-unstable",
        lambda: tl.stationary_covariance(torch.eye(2, dtype=f64), _L(), _Qc()),
        Raises(ValueError, r"F must be Hurwitz"),
    ),
    Case(
        "stationary-singular",
        lambda: tl.stationary_covariance(_F(), _L(), _Qc()),
        Raises(ValueError, r"F must be Hurwitz"),
    ),
    Case(
        "stationary-nan",
        lambda: tl.stationary_covariance(-torch.eye(2, dtype=f64) * math.nan, _L(), _Qc()),
        Raises(ValueError, r"\bF\b"),
    ),
    Case(
        "stationary-1x1",
        lambda: tl.stationary_covariance(-2.0 * torch.ones(1, 1, dtype=f64), torch.ones(1, 1, dtype=f64), 3.0 * _Qc()),
        Finite(lambda P: float(P) == pytest.approx(0.75, rel=1e-14) or pytest.fail(str(P))),
    ),
    # propagate
    Case(
        "propagate-P0-not-psd",
        lambda: tl.propagate(torch.zeros(2, dtype=f64), -torch.eye(2, dtype=f64), _F(), _L(), _Qc(), 1.0),
        Raises(ValueError, r"P0 must be positive semi-definite"),
    ),
    Case(
        "propagate-P0-nan",
        lambda: tl.propagate(torch.zeros(2, dtype=f64), torch.eye(2, dtype=f64) * math.nan, _F(), _L(), _Qc(), 1.0),
        Raises(ValueError, r"P0"),
    ),
    Case(
        "propagate-m0-wrong-size",
        lambda: tl.propagate(torch.zeros(3, dtype=f64), torch.eye(2, dtype=f64), _F(), _L(), _Qc(), 1.0),
        Raises(ValueError, r"m0 must have shape"),
    ),
    Case(
        "propagate-u-without-B",
        lambda: tl.propagate(
            torch.zeros(2, dtype=f64), torch.eye(2, dtype=f64), _F(), _L(), _Qc(), 1.0, u=torch.ones(1, dtype=f64)
        ),
        Raises(ValueError, r"u was given"),
    ),
    Case(
        "propagate-u-wrong-size",
        lambda: tl.propagate(
            torch.zeros(2, dtype=f64),
            torch.eye(2, dtype=f64),
            _F(),
            _L(),
            _Qc(),
            1.0,
            B=_B(),
            u=torch.ones(3, dtype=f64),
        ),
        Raises(ValueError, r"\bu\b"),
    ),
    Case(
        "propagate-m0-1e300",
        lambda: tl.propagate(torch.tensor([1e300, 0.0], dtype=f64), torch.eye(2, dtype=f64), _F(), _L(), _Qc(), 1.0),
        Finite(lambda mP: torch.testing.assert_close(mP[0], torch.tensor([1e300, 0.0], dtype=f64), rtol=1e-15, atol=0)),
    ),
    # layers
    Case(
        "Transition-dt-negative",
        lambda: tl.Transition()(-torch.eye(2, dtype=f64), -torch.ones(2, dtype=f64)),
        Raises(ValueError, r"dt must be non-negative"),
    ),
    Case("Transition-bad-method", lambda: tl.Transition(method="rk4"), Raises(ValueError, r"method must be one of")),
    Case(
        "VanLoanNoise-F-nan",
        lambda: tl.VanLoanNoise()(_F() * math.nan, _L(), _Qc(), 1.0),
        Raises(ValueError, r"F contains NaN"),
    ),
    Case("VanLoanNoise-bad-method", lambda: tl.VanLoanNoise(method="x"), Raises(ValueError, r"method must be one of")),
    Case(
        "Discretization-dt-nan",
        lambda: tl.Discretization()(_F(), _L(), _Qc(), torch.tensor([1.0, math.nan], dtype=f64)),
        Raises(ValueError, r"dt contains NaN"),
    ),
]


@pytest.mark.parametrize("case", params(CASES))
def test_core(case: Case) -> None:
    run_case(case)
