"""Hostile inputs to the filters and smoothers: tl.kalman_filter, tl.KalmanFilter (filter, smooth,
forecast), tl.rts_smoother (both algorithms) and tl.IMMFilter — shapes, dtypes, NaN/Inf,
sizes 0 and 1, huge and tiny values."""

from __future__ import annotations

import math

import pytest
import torch

import torchsde_lti as tl
from tests.hostile.harness import Case, Finite, Raises, params, run_case

f64, f32 = torch.float64, torch.float32
B, T = 3, 6


def _cv(dtype: torch.dtype = f64, **kw) -> tl.KalmanFilter:
    sde = tl.models.constant_velocity(dim=2, q=1.0, dtype=dtype)
    return tl.KalmanFilter(sde, tl.models.position_observation(sde), torch.eye(2, dtype=dtype), **kw)


def _y(dtype: torch.dtype = f64, scale: float = 1.0) -> torch.Tensor:
    return scale * torch.randn(B, T, 2, dtype=dtype, generator=torch.Generator().manual_seed(0))


def _dt(dtype: torch.dtype = f64, scale: float = 1.0) -> torch.Tensor:
    return scale * (0.1 + torch.rand(B, T, dtype=dtype, generator=torch.Generator().manual_seed(1)))


def _out() -> tl.FilterResult:
    return _cv()(_y(), _dt())


def _functional(**changes) -> tl.FilterResult:
    """tl.kalman_filter on a random walk in 2-D (A = I, Q = I, H = I, R = I), with ``changes``."""
    eye = torch.eye(2, dtype=f64)
    args = {
        "y": _y(),
        "A": eye.expand(B, T, 2, 2),
        "Q": eye.expand(B, T, 2, 2),
        "H": eye,
        "R": eye,
        "m0": torch.zeros(2, dtype=f64),
        "P0": eye,
    }
    args.update(changes)
    return tl.kalman_filter(**args)


def _loglik(value: float, rtol: float = 1e-12):
    def check(out) -> None:
        torch.testing.assert_close(
            out.log_likelihood, torch.full_like(out.log_likelihood, value), rtol=rtol, atol=1e-12
        )

    return check


def _one_step_loglik(out: tl.FilterResult) -> None:
    """T = 1 with the prior N(0, I): y_1 ~ N(H A m0, H (A P0 Aᵀ + Q) Hᵀ + R)."""
    kf, y, dt = _cv(P0=torch.eye(4, dtype=f64)), _y()[:, :1], _dt()[:, :1]
    d = kf.sde(dt[:, 0])
    P = d.A @ torch.eye(4, dtype=f64) @ d.A.mT + d.Q
    S = kf.H @ P @ kf.H.mT + kf.R
    ref = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=f64), S).log_prob(y[:, 0])
    torch.testing.assert_close(out.log_likelihood, ref, rtol=1e-12, atol=1e-12)


def _shape(*shape: int):
    def check(out) -> None:
        assert tuple(out.mean.shape) == shape, out.mean.shape

    return check


def _imm(dtype: torch.dtype = f64, models=None, **kw) -> tl.IMMFilter:
    underway = tl.models.integrated_ou(k=0.005, q=0.01, dim=2, dtype=dtype)
    moored = tl.models.moored(k=0.05, q=0.01, dim=2, dtype=dtype)
    I2 = torch.eye(2, dtype=dtype)
    args = {
        "models": [moored, underway] if models is None else models,
        "H": tl.models.position_observation(underway),
        "R": torch.stack([25 * I2, 400 * I2]),
        "rates": torch.tensor([[0, 1 / 1800], [1 / 1800, 0]], dtype=dtype),
    }
    args.update(kw)
    return tl.IMMFilter(**args)


def _imm_one_mode_equals_kalman(out) -> None:
    sde = tl.models.integrated_ou(k=0.5, q=1.0, dim=2, dtype=f64)
    kf = tl.KalmanFilter(sde, tl.models.position_observation(sde), torch.eye(2, dtype=f64), P0=torch.eye(4, dtype=f64))
    ref = kf(_y(), _dt())
    torch.testing.assert_close(out.log_likelihood, ref.log_likelihood, rtol=1e-10, atol=1e-10)


def _imm_one_mode():
    sde = tl.models.integrated_ou(k=0.5, q=1.0, dim=2, dtype=f64)
    return tl.IMMFilter(
        [sde],
        tl.models.position_observation(sde),
        torch.eye(2, dtype=f64)[None],
        torch.zeros(1, 1, dtype=f64),
        P0=torch.eye(4, dtype=f64),
        learn=("R",),
    )


def _smooth_one_step() -> tl.SmootherResult:
    kf = _cv()
    return kf.smooth(kf(_y()[:, :1], _dt()[:, :1]))


CASES = [
    # KalmanFilter: shapes and sizes
    Case("kf-y-1d", lambda: _cv()(torch.zeros(T, dtype=f64), _dt()[0]), Raises(ValueError, r"y must have shape")),
    Case("kf-T-0", lambda: _cv()(_y()[:, :0], _dt()[:, :0]), Raises(ValueError, r"y must have at least one step")),
    Case("kf-m-0", lambda: _cv()(torch.zeros(B, T, 0, dtype=f64), _dt()), Raises(ValueError, r"\by\b")),
    Case(
        "kf-y-wrong-m", lambda: _cv()(torch.zeros(B, T, 3, dtype=f64), _dt()), Raises(ValueError, r"y has 3 components")
    ),
    Case("kf-dt-wrong-T", lambda: _cv()(_y(), _dt()[:, :2]), Raises(ValueError, r"dt must have shape")),
    Case("kf-T-1", lambda: _cv(P0=torch.eye(4, dtype=f64))(_y()[:, :1], _dt()[:, :1]), Finite(_one_step_loglik)),
    Case("kf-B-0", lambda: _cv()(_y()[:0], _dt()[:0]), Finite(_shape(0, T, 4))),
    Case("kf-B-1-T-1", lambda: _cv()(_y()[:1, :1], _dt()[:1, :1]), Finite(_shape(1, 1, 4))),
    Case("kf-no-batch", lambda: _cv()(_y()[0], _dt()[0]), Finite(_shape(T, 4))),
    # dtypes and types
    Case("kf-y-int", lambda: _cv()(torch.ones(B, T, 2, dtype=torch.int64), _dt()), Finite(_shape(B, T, 4))),
    Case("kf-y-list", lambda: _cv()(_y().tolist(), _dt()), Finite(_shape(B, T, 4))),
    Case("kf-y-None", lambda: _cv()(None, _dt()), Raises(TypeError, r"\by\b")),
    Case("kf-y-str", lambda: _cv()("y", _dt()), Raises(TypeError, r"\by\b")),
    Case("kf-y-complex", lambda: _cv()(_y().to(torch.complex128), _dt()), Raises(TypeError, r"\by\b")),
    Case("kf-f64-y-f32", lambda: _cv()(_y(f32), _dt(f32)), Finite(_shape(B, T, 4))),
    # NaN / Inf / missing
    Case("kf-y-all-nan", lambda: _cv()(_y() * math.nan, _dt()), Finite(_loglik(0.0))),
    Case(
        "kf-mask-all-false", lambda: _cv()(_y(), _dt(), mask=torch.zeros(B, T, dtype=torch.bool)), Finite(_loglik(0.0))
    ),
    Case("kf-y-inf", lambda: _cv()(_y() * math.inf, _dt()), Raises(ValueError, r"y contains Inf")),
    Case("kf-y-minus-inf", lambda: _cv()(-_y().abs() * math.inf, _dt()), Raises(ValueError, r"y contains Inf")),
    Case("kf-dt-negative", lambda: _cv()(_y(), -_dt()), Raises(ValueError, r"dt must be non-negative")),
    Case("kf-dt-nan", lambda: _cv()(_y(), _dt() * math.nan), Raises(ValueError, r"dt contains NaN")),
    Case("kf-dt-inf", lambda: _cv()(_y(), _dt() * math.inf), Raises(ValueError, r"dt contains NaN or Inf")),
    Case(
        "kf-mask-wrong-shape",
        lambda: _cv()(_y(), _dt(), mask=torch.ones(B, T - 1, dtype=torch.bool)),
        Raises(ValueError, r"mask must have shape"),
    ),
    Case(
        "kf-mask-float",
        lambda: _cv()(_y(), _dt(), mask=torch.ones(B, T)),
        Raises((ValueError, TypeError), r"mask must be a bool"),
    ),
    Case(
        "kf-u-without-B",
        lambda: _cv()(_y(), _dt(), u=torch.ones(B, T, 1, dtype=f64)),
        Raises(ValueError, r"u was given"),
    ),
    # huge / tiny values
    Case("kf-y-1e20-f64", lambda: _cv()(_y(scale=1e20), _dt()), Finite()),
    Case("kf-y-1e-300-f64", lambda: _cv()(_y(scale=1e-300), _dt()), Finite()),
    Case("kf-y-1e-30-f32", lambda: _cv(f32)(_y(f32, 1e-30), _dt(f32)), Finite()),
    Case("kf-y-1e10-f32", lambda: _cv(f32)(_y(f32, 1e10), _dt(f32)), Finite()),
    Case(
        "kf-y-1e20-f32",
        lambda: _cv(f32)(_y(f32, 1e20), _dt(f32)),
        Raises((ValueError, OverflowError, ArithmeticError), r"\by\b|float32|overflow"),
    ),
    Case(
        "kf-y-1e200-f64",
        lambda: _cv()(_y(scale=1e200), _dt()),
        Raises((ValueError, OverflowError, ArithmeticError), r"\by\b|float64|overflow"),
    ),
    Case("kf-dt-1e10-f64", lambda: _cv()(_y(), _dt(scale=1e10)), Finite()),
    Case("kf-dt-1e6-f32", lambda: _cv(f32)(_y(f32), _dt(f32, 1e6)), Finite()),
    Case("kf-dt-zero", lambda: _cv()(_y(), torch.zeros(B, T, dtype=f64)), Finite()),
    # KalmanFilter construction
    Case(
        "kf-R-negative",
        lambda: tl.KalmanFilter(
            tl.models.constant_velocity(dim=2, q=1.0, dtype=f64), torch.eye(2, 4, dtype=f64), -torch.eye(2, dtype=f64)
        ),
        Raises(ValueError, r"R must be symmetric positive definite"),
    ),
    Case(
        "kf-R-nan",
        lambda: tl.KalmanFilter(
            tl.models.constant_velocity(dim=2, q=1.0, dtype=f64),
            torch.eye(2, 4, dtype=f64),
            torch.eye(2, dtype=f64) * math.nan,
        ),
        Raises(ValueError, r"R contains NaN"),
    ),
    Case(
        "kf-H-wrong-columns",
        lambda: tl.KalmanFilter(
            tl.models.constant_velocity(dim=2, q=1.0, dtype=f64), torch.eye(3, dtype=f64), torch.eye(2, dtype=f64)
        ),
        Raises(ValueError, r"H must have 4 columns"),
    ),
    Case("kf-P0-bogus", lambda: _cv(P0="bogus"), Raises(ValueError, r"P0 must be a tensor, None .* or .diffuse.")),
    Case("kf-m0-wrong-size", lambda: _cv(m0=torch.zeros(3, dtype=f64)), Raises(ValueError, r"m0")),
    Case(
        "kf-sde-None",
        lambda: tl.KalmanFilter(None, torch.eye(2, 4, dtype=f64), torch.eye(2, dtype=f64)),
        Raises(TypeError, r"sde must be an LTISDE"),
    ),
    Case(
        "kf-sde-tensor",
        lambda: tl.KalmanFilter(torch.eye(4, dtype=f64), torch.eye(2, 4, dtype=f64), torch.eye(2, dtype=f64)),
        Raises(TypeError, r"sde must be an LTISDE"),
    ),
    Case("kf-learn-bogus", lambda: _cv(learn=("bogus",)), Raises(ValueError, r"learn must name some of")),
    Case(
        "kf-diffuse-variance-negative",
        lambda: _cv(P0="diffuse", diffuse_variance=-1.0)(_y(), _dt()),
        Raises(ValueError, r"diffuse_variance"),
    ),
    Case(
        "kf-diffuse-variance-nan",
        lambda: _cv(P0="diffuse", diffuse_variance=math.nan)(_y(), _dt()),
        Raises(ValueError, r"diffuse_variance"),
    ),
    # smoothing and forecasting
    Case("smooth-ok", lambda: _cv().smooth(_out()), Finite()),
    Case("smooth-T-1", lambda: _smooth_one_step(), Finite()),
    Case("smooth-tuple", lambda: _cv().smooth(tuple(_out())), Raises(TypeError, r"FilterResult|\bout\b|result")),
    Case("rts-tuple", lambda: tl.rts_smoother(tuple(_out())), Raises(TypeError, r"FilterResult|result")),
    Case("rts-None", lambda: tl.rts_smoother(None), Raises(TypeError, r"FilterResult|result")),
    Case(
        "scan-rts-tuple",
        lambda: tl.rts_smoother(tuple(_out()), algorithm="scan"),
        Raises(TypeError, r"FilterResult|result"),
    ),
    Case("forecast-dt-negative", lambda: _cv().forecast(_out(), -1.0), Raises(ValueError, r"dt must be non-negative")),
    Case("forecast-dt-nan", lambda: _cv().forecast(_out(), math.nan), Raises(ValueError, r"dt contains NaN")),
    Case("forecast-dt-1e10", lambda: _cv().forecast(_out(), 1e10), Finite()),
    Case("forecast-dt-1e100", lambda: _cv().forecast(_out(), 1e100), Raises(ValueError, r"forecast overflows")),
    Case(
        "forecast-from-mean-cov",
        lambda: _cv().forecast(
            (torch.zeros(4, dtype=f64), torch.eye(4, dtype=f64)), torch.tensor([0.5, 2.0], dtype=f64)
        ),
        Finite(),
    ),
    Case(
        "forecast-state-wrong-size",
        lambda: _cv().forecast((torch.zeros(3, dtype=f64), torch.eye(3, dtype=f64)), 1.0),
        Raises(ValueError, r"\bm0\b|\bmean\b|state|shape"),
    ),
    # the functional filter
    Case("fn-ok", lambda: _functional(), Finite()),
    Case(
        "fn-R-not-psd",
        lambda: _functional(R=-torch.eye(2, dtype=f64)),
        Raises(ValueError, r"R must be positive semi-definite"),
    ),
    Case(
        "fn-Q-nan",
        lambda: _functional(Q=torch.full((B, T, 2, 2), math.nan, dtype=f64)),
        Raises(ValueError, r"Q contains NaN"),
    ),
    Case(
        "fn-A-nan",
        lambda: _functional(A=torch.full((B, T, 2, 2), math.nan, dtype=f64)),
        Raises(ValueError, r"A contains NaN"),
    ),
    Case(
        "fn-H-inf",
        lambda: _functional(H=torch.eye(2, dtype=f64) * math.inf),
        Raises(ValueError, r"H contains NaN or Inf"),
    ),
    Case(
        "fn-A-not-square",
        lambda: _functional(A=torch.ones(B, T, 1, 2, dtype=f64)),
        Raises(ValueError, r"A must be square"),
    ),
    Case(
        "fn-A-wrong-T",
        lambda: _functional(A=torch.eye(2, dtype=f64).expand(B, T + 1, 2, 2)),
        Raises(ValueError, r"\bA\b"),
    ),
    Case(
        "fn-P0-not-psd",
        lambda: _functional(P0=-torch.eye(2, dtype=f64)),
        Raises(ValueError, r"P0 must be positive semi-definite"),
    ),
    Case(
        "fn-m0-wrong-size", lambda: _functional(m0=torch.zeros(3, dtype=f64)), Raises(ValueError, r"m0 must have shape")
    ),
    Case(
        "fn-all-zero-noise",
        lambda: _functional(
            Q=torch.zeros(B, T, 2, 2, dtype=f64), R=torch.zeros(2, 2, dtype=f64), P0=torch.zeros(2, 2, dtype=f64)
        ),
        Raises(ValueError, r"\bR\b.*positive definite"),
    ),
    Case(
        "fn-T-0",
        lambda: _functional(
            y=_y()[:, :0], A=torch.eye(2, dtype=f64).expand(B, 0, 2, 2), Q=torch.eye(2, dtype=f64).expand(B, 0, 2, 2)
        ),
        Raises(ValueError, r"y must have at least one step"),
    ),
    Case("fn-u-without-G", lambda: _functional(u=torch.ones(B, T, 1, dtype=f64)), Raises(ValueError, r"\bu\b|\bG\b")),
    Case(
        "fn-G-without-u", lambda: _functional(G=torch.ones(B, T, 2, 1, dtype=f64)), Raises(ValueError, r"\bu\b|\bG\b")
    ),
    # IMM
    Case("imm-ok", lambda: _imm()(_y(), _dt()), Finite()),
    Case("imm-one-mode-equals-kalman", lambda: _imm_one_mode()(_y(), _dt()), Finite(_imm_one_mode_equals_kalman)),
    Case("imm-y-all-nan", lambda: _imm()(_y() * math.nan, _dt()), Finite(_loglik(0.0))),
    Case("imm-T-0", lambda: _imm()(_y()[:, :0], _dt()[:, :0]), Raises(ValueError, r"\by\b")),
    Case("imm-dt-negative", lambda: _imm()(_y(), -_dt()), Raises(ValueError, r"dt must be non-negative")),
    Case("imm-dt-1e10-f64", lambda: _imm()(_y(), torch.full((B, T), 1e10, dtype=f64)), Finite()),
    Case("imm-dt-1e20-f64", lambda: _imm()(_y(), torch.full((B, T), 1e20, dtype=f64)), Finite()),
    Case("imm-dt-1e10-f32", lambda: _imm(f32)(_y(f32), torch.full((B, T), 1e10)), Finite()),
    Case("imm-dt-1e12-f32", lambda: _imm(f32)(_y(f32), torch.full((B, T), 1e12)), Finite()),
    Case("imm-no-models", lambda: _imm(models=[]), Raises(ValueError, r"models must contain at least one")),
    Case(
        "imm-model-not-sde",
        lambda: _imm(models=[torch.eye(4, dtype=f64), torch.eye(4, dtype=f64)]),
        Raises(TypeError, r"models"),
    ),
    Case(
        "imm-rates-negative",
        lambda: _imm(rates=torch.tensor([[0, -0.1], [0.1, 0]], dtype=f64)),
        Raises(ValueError, r"rates must be >= 0"),
    ),
    Case(
        "imm-rates-nan",
        lambda: _imm(rates=torch.tensor([[0, math.nan], [0.1, 0]], dtype=f64)),
        Raises(ValueError, r"rates"),
    ),
    Case(
        "imm-rates-wrong-shape",
        lambda: _imm(rates=torch.zeros(3, 3, dtype=f64)),
        Raises(ValueError, r"rates must have shape"),
    ),
    Case(
        "imm-mode-prob0-not-summing-to-1",
        lambda: _imm(mode_prob0=torch.tensor([0.5, 0.7], dtype=f64)),
        Raises(ValueError, r"mode_prob0"),
    ),
    Case(
        "imm-mode-prob0-negative",
        lambda: _imm(mode_prob0=torch.tensor([-0.5, 1.5], dtype=f64)),
        Raises(ValueError, r"mode_prob0"),
    ),
    Case("imm-mode-names-wrong-length", lambda: _imm(mode_names=("a",)), Raises(ValueError, r"mode_names")),
    Case("imm-R-wrong-count", lambda: _imm(R=torch.eye(2, dtype=f64).expand(3, 2, 2)), Raises(ValueError, r"\bR\b")),
]


@pytest.mark.parametrize("case", params(CASES))
def test_filters(case: Case) -> None:
    run_case(case)


def _batch_mismatches() -> dict[str, object]:
    """Calls whose batch shapes do not broadcast (y of 3 tracks against 2 or 4 elsewhere)."""
    F64 = torch.float64
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64)
    R = torch.diag(torch.tensor([0.1, 0.2], dtype=F64))
    cv = tl.models.constant_velocity(dim=2, q=1.0, dtype=F64)
    kf = tl.KalmanFilter(cv, H, R, P0=10 * torch.eye(4, dtype=F64))
    rates = torch.tensor([[0.0, 0.2], [0.3, 0.0]], dtype=F64)
    imm = tl.IMMFilter([cv, tl.models.constant_velocity(dim=2, q=5.0, dtype=F64)], H, R, rates)
    y, dt = torch.randn(3, 5, 2, dtype=F64), torch.rand(3, 5, dtype=F64)
    A, Q = torch.eye(4, dtype=F64).expand(2, 5, 4, 4), 0.1 * torch.eye(4, dtype=F64)
    m0, P0 = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    F, L, Qc = -torch.eye(2, dtype=F64), torch.eye(2, dtype=F64), torch.eye(2, dtype=F64)
    ones = torch.ones
    return {
        "kf, dt batch (auto)": lambda: kf(y, torch.rand(2, 5, dtype=F64)),
        "kalman_filter, A batch (scan)": lambda: tl.kalman_filter(y, A, Q, H, R, m0, P0, algorithm="scan"),
        "kalman_filter, A batch (sequential)": lambda: tl.kalman_filter(y, A, Q, H, R, m0, P0, algorithm="sequential"),
        "kf, mask batch": lambda: kf(y, dt, mask=ones(2, 5, dtype=torch.bool)),
        "kf.step, mask components": lambda: kf.step(
            kf.initial_state(3), y[:, 0], dt[:, 0], mask=ones(3, 3, dtype=torch.bool)
        ),
        "kf.step, y batch": lambda: kf.step(kf.initial_state(3), torch.randn(4, 2, dtype=F64), dt[:, 0]),
        "imm, dt batch": lambda: imm(y, torch.rand(2, 5, dtype=F64)),
        "imm.step, y batch": lambda: imm.step(imm.initial_state(3), torch.randn(4, 2, dtype=F64), torch.rand(4)),
        "propagate, m0 batch": lambda: tl.propagate(torch.zeros(5, 2, dtype=F64), L, F, L, Qc, ones(4, dtype=F64)),
        "propagate, P0 batch": lambda: tl.propagate(torch.zeros(2, dtype=F64), L.expand(3, 2, 2), F, L, Qc, ones(4)),
    }


def _named_batch_mismatches() -> dict[str, tuple[object, str]]:
    """Calls of 3 tracks against a batch of 4 in u or in the model (its H, R or parameters),
    each with the argument the error must name."""
    F64 = torch.float64
    T, m, p = 5, 1, 1
    H, R = torch.tensor([[1.0, 0.0]], dtype=F64), torch.eye(1, dtype=F64)
    A, Q = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=F64), 0.1 * torch.eye(2, dtype=F64)
    m0, P0 = torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64)
    y, u4 = torch.randn(3, T, m, dtype=F64), torch.ones(4, T, p, dtype=F64)
    col = torch.tensor([[0.0], [1.0]], dtype=F64)
    sde_B = tl.LTISDE(torch.tensor([[0.0, 1.0], [-1.0, -0.3]], dtype=F64), col, torch.eye(1, dtype=F64), B=col)
    kf_D = tl.KalmanFilter(sde_B, H, R, D=torch.ones(m, p, dtype=F64))
    cv = tl.models.constant_velocity(dim=1, dtype=F64)
    kf_H = tl.KalmanFilter(cv, H.expand(4, m, 2), R)
    kf_R = tl.KalmanFilter(cv, H, R.expand(4, m, m))
    kf_q = tl.KalmanFilter(tl.models.constant_velocity(dim=1, q=torch.ones(4, dtype=F64), dtype=F64), H, R, P0=P0)
    state3 = (torch.zeros(3, 2, dtype=F64), P0.expand(3, 2, 2))
    y3, dt = torch.randn(3, m, dtype=F64), torch.ones(2, dtype=F64)
    return {
        "kalman_filter, u batch (D)": (
            lambda: tl.kalman_filter(y, A, Q, H, R, m0, P0, D=torch.ones(m, p, dtype=F64), u=u4),
            "u: (4)",
        ),
        "kalman_filter, u batch (G)": (
            lambda: tl.kalman_filter(y, A, Q, H, R, m0, P0, G=torch.ones(3, T, 2, p, dtype=F64), u=u4),
            "u: (4)",
        ),
        "kf with B and D, u batch": (lambda: kf_D(y, torch.ones(3, T, dtype=F64), u=u4), "u: (4)"),
        "kf.step with D, u batch": (lambda: kf_D.step(kf_D.initial_state(3), y3, 1.0, u=u4[:, 0]), "u: (4)"),
        "kf.step, R batch": (lambda: kf_R.step(state3, y3, 1.0), "R: (4)"),
        "kf.step, parameter batch": (lambda: kf_q.step(state3, y3, 1.0), "Qc: (4)"),
        "kf.predict, parameter batch": (lambda: kf_q.predict(state3, 1.0), "Qc: (4)"),
        "kf.forecast, H batch": (lambda: kf_H.forecast(state3, dt), "H: (4)"),
        "kf.forecast, R batch": (lambda: kf_R.forecast(state3, dt), "R: (4)"),
        "kf.forecast, parameter batch": (lambda: kf_q.forecast(state3, dt), "Qc: (4)"),
    }


@pytest.mark.parametrize("name", list(_named_batch_mismatches()))
def test_batch_mismatches_in_u_or_the_model_name_that_argument(name: str) -> None:
    call, named = _named_batch_mismatches()[name]
    with pytest.raises(ValueError, match="batch shapes do not broadcast") as info:
        call()  # type: ignore[operator]
    assert named in str(info.value) and "(3)" in str(info.value), str(info.value)


@pytest.mark.parametrize("name", list(_batch_mismatches()))
def test_batch_shapes_that_do_not_broadcast_raise_value_errors_naming_the_arguments(name: str) -> None:
    with pytest.raises(ValueError, match="batch shapes do not broadcast|mask must have shape"):
        _batch_mismatches()[name]()  # type: ignore[operator]
