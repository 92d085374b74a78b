"""The algorithm choice (``algorithm="auto"`` names the sequential loop), one function under
every ``algorithm=`` and ``validate_args``, and no host reads without validation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from tests.reference import random_problem, to_torch
from torchsde_lti.filters import ALGORITHMS, choose_algorithm, kalman_filter, rts_smoother

F64 = torch.float64
NAMES = ("y", "A", "Q", "H", "R", "m0", "P0")


def test_auto_is_the_sequential_loop_whatever_the_call():
    """The choice depends on no size, dtype or device (no constant tuned to a machine): "auto"
    is the loop; a named algorithm is itself; an unknown one is refused, naming the choices."""
    for device in ("cpu", "meta"):
        for dtype in (torch.float32, F64):
            for B, T in ((1, 1), (1, 10_000), (16, 200), (10**6, 5)):
                assert choose_algorithm("auto", B, T, torch.device(device), dtype) == "sequential"
    for algorithm in ALGORITHMS[1:]:
        assert choose_algorithm(algorithm, 1, 200, torch.device("cpu")) == algorithm
    with pytest.raises(ValueError, match=r"kalman_filter has the algorithms .*got algorithm='parallel'"):
        choose_algorithm("parallel")
    t = to_torch(random_problem(np.random.default_rng(2), batch=(2,), T=6))
    out = kalman_filter(*(t[k] for k in NAMES))
    with pytest.raises(ValueError, match="rts_smoother has the algorithms"):
        rts_smoother(out, algorithm="square_root")
    with pytest.raises(ValueError, match="kalman_filter has the algorithms"):
        kalman_filter(*(t[k] for k in NAMES), algorithm="parallel")


def test_kalman_filter_auto_is_the_loop_and_forcing_runs_each_algorithm():
    """The name "auto" (KalmanFilter's default) names the sequential loop at every batch; a forced algorithm
    runs; all agree with the loop, smoothed too."""
    cv = tl.models.constant_velocity(dim=1, q=0.7, dtype=F64)
    H, R = torch.tensor([[1.0, 0.0]], dtype=F64), torch.tensor([[0.3]], dtype=F64)
    g = torch.Generator().manual_seed(0)
    results = {}
    for B in (3, 40):
        y = torch.randn(B, 25, 1, generator=g, dtype=F64)
        dt = torch.rand(B, 25, generator=g, dtype=F64) + 0.1
        for algorithm in ("auto", "scan", "sequential"):
            kf = tl.KalmanFilter(cv, H, R, P0=torch.eye(2, dtype=F64), algorithm=algorithm)
            expected = "sequential" if algorithm == "auto" else algorithm
            assert kf.algorithm_for(B, 25, y.device) == expected
            out = kf(y, dt)
            results[B, algorithm] = (out, kf.smooth(out))
        for algorithm in ("auto", "scan"):
            for a, b in zip(results[B, algorithm], results[B, "sequential"]):
                np.testing.assert_allclose(a.mean.detach().numpy(), b.mean.detach().numpy(), atol=1e-9)
                np.testing.assert_allclose(a.cov.detach().numpy(), b.cov.detach().numpy(), atol=1e-9)
    sq = tl.KalmanFilter(cv, H, R, algorithm="square_root")
    assert sq.algorithm_for(1, 200, torch.device("cpu")) == "square_root"
    with pytest.raises(ValueError, match=r"KalmanFilter has the algorithms .*got algorithm='parallel'"):
        tl.KalmanFilter(cv, H, R, algorithm="parallel")


def test_one_function_and_one_gradient_under_every_algorithm_and_validate_flag():
    """Q, R, P0 with a rounding-level asymmetry (accepted by the checks): validate_args=True and
    False give bit-identical results per algorithm (validation only raises), and the gradient of
    the log-likelihood with respect to Q, R, P0 is one symmetric matrix under every algorithm and
    flag, to 1e-9 relative (it differed by ~10 % between flags and algorithms when validation
    symmetrised and the unchecked path read the given triangles)."""
    t = to_torch(random_problem(np.random.default_rng(21), batch=(3,), T=9, missing=True))
    noise = {
        k: 1e-15 * torch.randn(t[k].shape, dtype=F64, generator=torch.Generator().manual_seed(i))
        for i, k in enumerate(("Q", "R", "P0"))
    }
    grads, outs = {}, {}
    for algorithm in ALGORITHMS[1:]:
        for validate in (True, False):
            leaves = {k: (t[k] + noise[k]).requires_grad_(True) for k in noise}
            args = {**t, **leaves}
            out = kalman_filter(
                *(args[k] for k in NAMES), G=t["G"], u=t["u"], algorithm=algorithm, validate_args=validate
            )
            outs[algorithm, validate] = out
            grads[algorithm, validate] = torch.autograd.grad(out.log_likelihood.sum(), list(leaves.values()))
        for a, b in zip(outs[algorithm, True], outs[algorithm, False]):
            assert torch.equal(a, b), algorithm
    ref = grads["sequential", True]
    for key, g in grads.items():
        for gx, rx in zip(g, ref):
            torch.testing.assert_close(gx, gx.mT, rtol=0, atol=0)
            torch.testing.assert_close(gx, rx, rtol=1e-9, atol=1e-12, msg=str(key))


def test_an_asymmetric_Q_is_refused_with_validation_and_read_through_its_symmetric_part_without():
    t = to_torch(random_problem(np.random.default_rng(22), batch=(2,), T=5, missing=False))
    skew = torch.zeros_like(t["Q"])
    skew[..., 0, 1] = 1e-3 * t["Q"][..., 0, 0]  # far beyond rounding; Q + its symmetric part stays PSD
    args = {**t, "Q": t["Q"] + skew}
    with pytest.raises(ValueError, match="Q must be symmetric"):
        kalman_filter(*(args[k] for k in NAMES))
    for algorithm in ALGORITHMS[1:]:
        got = kalman_filter(*(args[k] for k in NAMES), algorithm=algorithm, validate_args=False)
        want = kalman_filter(*({**t, "Q": t["Q"] + 0.5 * (skew + skew.mT)}[k] for k in NAMES), algorithm=algorithm)
        torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("algorithm", ALGORITHMS[1:])
def test_without_validation_nothing_is_read_to_the_host(algorithm):
    """On the meta device (shapes, no values) every algorithm and smoother runs with
    validate_args=False: no value steers a route and nothing is copied to the host (any ``bool``,
    ``item`` or ``any()`` of a value would raise); masks and NaN are always the masked path."""
    t = to_torch(random_problem(np.random.default_rng(23), batch=(2,), T=6))
    meta = {k: v.to("meta") for k, v in t.items()}
    mask = torch.ones(2, 6, dtype=torch.bool, device="meta")
    out = kalman_filter(
        *(meta[k] for k in NAMES), G=meta["G"], u=meta["u"], mask=mask, algorithm=algorithm, validate_args=False
    )
    assert out.mean.device.type == "meta" and out.mean.shape == t["y"].shape[:-1] + (4,)
    for smoother in ("sequential", "scan"):
        assert rts_smoother(out, algorithm=smoother).cov.shape == out.cov.shape


def test_float32_default_over_a_long_gap_matches_float64() -> None:
    """One track, 10 reports, 2900 missing steps (a 1450 s gap: predicted/measured variance
    ~1e11), 2 reports: the float32 default (the loop) and the square-root filter match float64.
    (The float32 scan returns NaN at the first report after the gap: its combine solves with
    I + C J, entries ~1e11 of rank one, whose elimination cancels; experiments/results/scan_float32.md.)"""
    rng = np.random.default_rng(0)
    T = 10 + 2900 + 2
    y = rng.normal(size=(1, T, 1)).cumsum(1)
    y[0, 10:2910] = np.nan
    lls = {}
    for dtype in (torch.float64, torch.float32):
        sde = tl.models.constant_velocity(dim=1, q=1.0, dtype=dtype)
        with torch.no_grad():
            d = sde(torch.full((1, T), 0.5, dtype=dtype), series=True)
        args = (
            torch.tensor(y, dtype=dtype),
            d.A,
            d.Q,
            tl.models.position_observation(sde),
            0.01 * torch.eye(1, dtype=dtype),
        )
        for algorithm in ("auto", "square_root"):
            out = kalman_filter(*args, torch.zeros(2, dtype=dtype), torch.eye(2, dtype=dtype), algorithm=algorithm)
            lls[dtype, algorithm] = float(out.log_likelihood)
    for algorithm in ("auto", "square_root"):
        assert abs(lls[torch.float32, algorithm] - lls[torch.float64, "auto"]) < 1e-3, algorithm


@pytest.mark.parametrize("algorithm", ["sequential", "square_root", "scan"])
def test_a_per_step_mask_of_one_step_keeps_the_batch(algorithm):
    """T = 1, m = 2: a per-step mask written (B, T, 1) = (3, 1, 1), y's number of dims, is read
    as (..., T, 1) (it was read as (..., T) with a batch (3, 1): results (3, 3)); the result is
    that of y with NaN where the mask is False."""
    g = torch.Generator().manual_seed(5)
    B, m, n = 3, 2, 2
    y = torch.randn(B, 1, m, generator=g, dtype=F64)
    A, Q = torch.eye(n, dtype=F64), 0.1 * torch.eye(n, dtype=F64)
    H, R = torch.eye(m, n, dtype=F64), 0.5 * torch.eye(m, dtype=F64)
    m0, P0 = torch.zeros(n, dtype=F64), torch.eye(n, dtype=F64)
    mask = torch.tensor([True, False, True]).reshape(B, 1, 1)
    want = kalman_filter(torch.where(mask, y, float("nan")), A, Q, H, R, m0, P0, algorithm="sequential")
    out = kalman_filter(y, A, Q, H, R, m0, P0, mask=mask, algorithm=algorithm)
    assert out.log_likelihood.shape == (B,)
    torch.testing.assert_close(out.log_likelihood, want.log_likelihood, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.mean, want.mean, rtol=0, atol=1e-12)
