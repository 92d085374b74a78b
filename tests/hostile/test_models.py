"""Hostile inputs to the motion-model library and the modules built on it (tl.models.*, tl.LTISDE,
tl.DeployedFilter): bad parameters, dtypes, sizes, assignments and extreme rates."""

from __future__ import annotations

import math

import pytest
import torch

import torchsde_lti as tl
from tests.hostile.harness import Case, Finite, Raises, params, run_case

f64 = torch.float64
m = tl.models


def _sde(**kw) -> tl.LTISDE:
    eye = torch.eye(2, dtype=f64)
    return tl.LTISDE(-eye, eye, eye, **kw)


def _assign(name: str, value: torch.Tensor, **kw):
    return lambda: setattr(_sde(**kw), name, value)


def _ou_stationary(P) -> None:
    assert float(P) == pytest.approx(3.0 / (2 * 2.0), rel=1e-14)


def _cv_step(dt: float):
    def check(d) -> None:
        torch.testing.assert_close(d.A, torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=f64), rtol=1e-14, atol=0)
        torch.testing.assert_close(
            d.Q, torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], dtype=f64), rtol=1e-12, atol=0
        )

    return check


CASES = [
    Case("cv-q-negative", lambda: m.constant_velocity(q=-1.0), Raises(ValueError, r"q must be positive")),
    Case("cv-q-zero", lambda: m.constant_velocity(q=0.0), Raises(ValueError, r"q must be positive")),
    Case("cv-q-nan", lambda: m.constant_velocity(q=math.nan), Raises(ValueError, r"q contains NaN")),
    Case("cv-q-inf", lambda: m.constant_velocity(q=math.inf), Raises(ValueError, r"q contains NaN or Inf")),
    Case("cv-q-str", lambda: m.constant_velocity(q="1"), Raises(TypeError, r"q must be a tensor")),
    Case("cv-dim-0", lambda: m.constant_velocity(dim=0), Raises(ValueError, r"dim must be an integer >= 1")),
    Case("cv-dim-negative", lambda: m.constant_velocity(dim=-1), Raises(ValueError, r"dim must be an integer >= 1")),
    Case("cv-dim-float", lambda: m.constant_velocity(dim=1.5), Raises(ValueError, r"dim must be an integer >= 1")),
    Case(
        "cv-dim-str", lambda: m.constant_velocity(dim="2"), Raises((ValueError, TypeError), r"dim must be an integer")
    ),
    Case(
        "cv-dim-1-step",
        lambda: m.constant_velocity(dim=1, q=1.0, dtype=f64)(torch.tensor(0.5, dtype=f64)),
        Finite(_cv_step(0.5)),
    ),
    Case("ca-q-negative", lambda: m.constant_acceleration(q=-1.0), Raises(ValueError, r"q must be positive")),
    Case(
        "integrated-wiener-order-0",
        lambda: m.integrated_wiener(order=0),
        Raises(ValueError, r"order must be an integer >= 1"),
    ),
    Case(
        "integrated-wiener-order-float",
        lambda: m.integrated_wiener(order=1.5),
        Raises(ValueError, r"order must be an integer >= 1"),
    ),
    Case(
        "ou-theta-negative",
        lambda: m.ornstein_uhlenbeck(theta=-1.0, q=1.0),
        Raises(ValueError, r"theta must be positive"),
    ),
    Case(
        "ou-theta-zero", lambda: m.ornstein_uhlenbeck(theta=0.0, q=1.0), Raises(ValueError, r"theta must be positive")
    ),
    Case(
        "ou-stationary",
        lambda: m.ornstein_uhlenbeck(theta=2.0, q=3.0, dtype=f64).stationary_covariance(),
        Finite(_ou_stationary),
    ),
    Case("singer-alpha-zero", lambda: m.singer(alpha=0.0, q=1.0), Raises(ValueError, r"alpha must be positive")),
    Case("singer-alpha-nan", lambda: m.singer(alpha=math.nan, q=1.0), Raises(ValueError, r"alpha contains NaN")),
    Case("iou-k-1e10", lambda: m.integrated_ou(k=1e10, q=1.0, dtype=f64)(torch.tensor(1.0, dtype=f64)), Finite()),
    Case(
        "iou-k-1e-10-dt-1e10",
        lambda: m.integrated_ou(k=1e-10, q=1.0, dtype=f64)(torch.tensor(1e10, dtype=f64)),
        Finite(),
    ),
    Case("moored-k-negative", lambda: m.moored(k=-1.0, q=1.0), Raises(ValueError, r"k must be positive")),
    Case("matern-nu-bad", lambda: m.matern(nu=0.7), Raises(ValueError, r"nu must be one of")),
    Case(
        "matern-lengthscale-zero",
        lambda: m.matern(nu=1.5, lengthscale=0.0),
        Raises(ValueError, r"lengthscale must be positive"),
    ),
    Case(
        "matern-variance-negative",
        lambda: m.matern(nu=1.5, variance=-1.0),
        Raises(ValueError, r"variance must be positive"),
    ),
    Case("msd-m-zero", lambda: m.mass_spring_damper(m=0.0, k=1.0, c=0.1), Raises(ValueError, r"\bm must be positive")),
    Case(
        "msd-m-negative",
        lambda: m.mass_spring_damper(m=-1.0, k=1.0, c=0.1),
        Raises(ValueError, r"\bm must be positive"),
    ),
    Case(
        "msd-k-negative",
        lambda: m.mass_spring_damper(m=1.0, k=-1.0, c=0.1),
        Raises(ValueError, r"\bk must be positive"),
    ),
    Case(
        "companion-leading-zero",
        lambda: m.companion([1.0, 2.0, 0.0]),
        Raises(ValueError, r"leading coefficient a_n must be non-zero"),
    ),
    Case("companion-empty", lambda: m.companion([]), Raises(ValueError, r"a must hold coefficients")),
    Case("companion-nan", lambda: m.companion([1.0, math.nan, 1.0]), Raises(ValueError, r"a contains NaN")),
    Case(
        "transfer-den-constant",
        lambda: m.from_transfer_function([1.0], [0.0]),
        Raises(ValueError, r"den must have degree >= 1"),
    ),
    Case(
        "transfer-den-empty",
        lambda: m.from_transfer_function([1.0], []),
        Raises(ValueError, r"den must have degree >= 1"),
    ),
    Case(
        "transfer-improper",
        lambda: m.from_transfer_function([1.0, 2.0, 3.0], [1.0, 1.0]),
        Raises(ValueError, r"improper transfer function"),
    ),
    Case(
        "transfer-num-nan",
        lambda: m.from_transfer_function([math.nan], [1.0, 1.0]),
        Raises(ValueError, r"num contains NaN"),
    ),
    Case("block-diag-none", lambda: m.block_diag(), Raises(ValueError, r"sdes must contain at least one")),
    Case(
        "block-diag-tensor",
        lambda: m.block_diag(torch.eye(2)),
        Raises((ValueError, TypeError), r"sdes\[0\] must be an LTISDE"),
    ),
    Case(
        "position-observation-tensor",
        lambda: m.position_observation(torch.eye(2)),
        Raises(ValueError, r"model .* does not declare position_indices"),
    ),
    Case(
        "stationary-of-cv",
        lambda: m.constant_velocity(dim=1, dtype=f64).stationary_covariance(),
        Raises(ValueError, r"F must be Hurwitz"),
    ),
    # LTISDE
    Case(
        "lti-F-nan",
        lambda: tl.LTISDE(torch.eye(2, dtype=f64) * math.nan, torch.eye(2, dtype=f64), torch.eye(2, dtype=f64)),
        Raises(ValueError, r"F contains NaN"),
    ),
    Case("lti-B-wrong-rows", lambda: _sde(B=torch.eye(3, dtype=f64)), Raises(ValueError, r"B must have 2 rows")),
    Case("lti-learn-bogus", lambda: _sde(learn=("X",)), Raises(ValueError, r"learn must name some of")),
    Case("lti-constraint-bogus", lambda: _sde(F_constraint="bogus"), Raises(ValueError, r"F_constraint must be")),
    Case(
        "lti-hurwitz-unstable-start",
        lambda: tl.LTISDE(
            torch.eye(2, dtype=f64), torch.eye(2, dtype=f64), torch.eye(2, dtype=f64), F_constraint="hurwitz"
        ),
        Raises(ValueError, r"F must be Hurwitz"),
    ),
    Case("lti-method-bogus", lambda: _sde(method="euler"), Raises(ValueError, r"method must be one of")),
    Case("lti-dt-negative", lambda: _sde()(-torch.ones(3, dtype=f64)), Raises(ValueError, r"dt must be non-negative")),
    Case("lti-dt-nan", lambda: _sde()(torch.tensor(math.nan, dtype=f64)), Raises(ValueError, r"dt contains NaN")),
    Case("lti-assign-F-nan", _assign("F", torch.eye(2, dtype=f64) * math.nan), Raises(ValueError, r"F contains NaN")),
    Case("lti-assign-F-wrong-shape", _assign("F", torch.eye(3, dtype=f64)), Raises(ValueError, r"F must have 2 rows")),
    Case(
        "lti-assign-Qc-negative",
        _assign("Qc", -torch.eye(2, dtype=f64)),
        Raises(ValueError, r"Qc must be symmetric positive definite"),
    ),
    Case(
        "lti-hurwitz-assign-unstable",
        _assign("F", torch.eye(2, dtype=f64), F_constraint="hurwitz"),
        Raises(ValueError, r"F must be Hurwitz"),
    ),
    Case(
        "lti-unstable-dt-1e3",
        lambda: tl.LTISDE(torch.eye(2, dtype=f64), torch.eye(2, dtype=f64), torch.eye(2, dtype=f64))(
            torch.tensor(1e3, dtype=f64)
        ),
        Raises((ValueError, OverflowError, ArithmeticError), r"\bF\b|\bdt\b|overflow"),
    ),
    Case(
        "lti-propagate-P0-not-psd",
        lambda: m.constant_velocity(dim=1, dtype=f64).propagate(
            torch.zeros(2, dtype=f64), -torch.eye(2, dtype=f64), torch.tensor(1.0, dtype=f64)
        ),
        Raises(ValueError, r"P0 must be positive semi-definite"),
    ),
    Case(
        "deployed-filter-None",
        lambda: tl.DeployedFilter(None),
        Raises(TypeError, r"kf must be a KalmanFilter or an IMMFilter"),
    ),
]


@pytest.mark.parametrize("case", params(CASES))
def test_models(case: Case) -> None:
    run_case(case)
