"""The automatic filter choice and the chunked associative scan (issue 10, item 3)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from tests.reference import random_problem, reference_batch, to_torch
from torchsde_lti.filters import (
    kalman_filter,
    parallel_kalman_filter,
    parallel_rts_smoother,
    prefers_scan,
    rts_smoother,
)

F64 = torch.float64


@pytest.mark.parametrize("chunk", [1, 5, 7, 40])
def test_chunked_scan_matches_numpy_reference(chunk):
    """Chunks of any length (1 … > T, dividing T or not) give the reference filter, with
    controls, missing components and fully missing steps."""
    d = random_problem(np.random.default_rng(1), batch=(2,), T=21)
    ref = reference_batch(d)
    t = to_torch(d)
    out = parallel_kalman_filter(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], G=t["G"], u=t["u"],
                                 chunk=chunk)
    for name in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(getattr(out, name).numpy(), ref[name], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.step_log_likelihood.numpy(), ref["ll"], atol=1e-9)
    np.testing.assert_allclose(out.log_likelihood.numpy(), ref["ll"].sum(-1), atol=1e-9)
    seq = kalman_filter(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], G=t["G"], u=t["u"])
    for name in ("innovation", "innovation_cov", "transition", "process_noise", "observed"):
        np.testing.assert_allclose(getattr(out, name).numpy(), getattr(seq, name).numpy(), atol=1e-9)
    # the smoother runs on the concatenated result
    np.testing.assert_allclose(parallel_rts_smoother(out).mean.numpy(), rts_smoother(seq).mean.numpy(), atol=1e-8)


def test_chunked_scan_with_per_step_mask():
    d = random_problem(np.random.default_rng(2), batch=(3,), T=10, missing=False)
    t = to_torch(d)
    mask = torch.rand(3, 10, generator=torch.Generator().manual_seed(0)) > 0.3
    args = (t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"])
    out = parallel_kalman_filter(*args, mask=mask, chunk=3)
    seq = kalman_filter(*args, mask=mask)
    np.testing.assert_allclose(out.mean.numpy(), seq.mean.numpy(), atol=1e-9)
    np.testing.assert_allclose(out.log_likelihood.numpy(), seq.log_likelihood.numpy(), atol=1e-9)


def test_prefers_scan_rule():
    cpu = torch.device("cpu")
    assert prefers_scan(1, 200, cpu) and prefers_scan(16, 10_000, cpu)
    assert not prefers_scan(17, 200, cpu) and not prefers_scan(1000, 200, cpu)
    assert not prefers_scan(1, 1, cpu)


def test_kalman_filter_auto_choice_and_forcing():
    cv = tl.models.constant_velocity(dim=1, q=0.7, dtype=F64)
    H, R = torch.tensor([[1.0, 0.0]], dtype=F64), torch.tensor([[0.3]], dtype=F64)
    g = torch.Generator().manual_seed(0)
    results = {}
    for B in (3, 40):
        y = torch.randn(B, 25, 1, generator=g, dtype=F64)
        dt = torch.rand(B, 25, generator=g, dtype=F64) + 0.1
        for parallel in (None, True, False):
            kf = tl.KalmanFilter(cv, H, R, P0=torch.eye(2, dtype=F64), parallel=parallel)
            expected = (B <= 16) if parallel is None else parallel
            assert kf.uses_scan(y.shape[:-2], dt.shape[:-1], 25, y.device) == expected
            out = kf(y, dt)
            results[B, parallel] = (out, kf.smooth(out))
        for parallel in (None, True):
            for a, b in zip(results[B, parallel], results[B, False]):
                np.testing.assert_allclose(a.mean.detach().numpy(), b.mean.detach().numpy(), atol=1e-9)
                np.testing.assert_allclose(a.cov.detach().numpy(), b.cov.detach().numpy(), atol=1e-9)
    sq = tl.KalmanFilter(cv, H, R, square_root=True)
    assert not sq.uses_scan((1,), (1,), 200, torch.device("cpu"))


def test_auto_choice_gradients_equal_loop():
    """Training through the automatic choice (the scan for few tracks) gives the loop's gradients."""
    g = torch.Generator().manual_seed(3)
    y = torch.randn(2, 30, 1, generator=g, dtype=F64).cumsum(1)
    dt = torch.rand(2, 30, generator=g, dtype=F64) + 0.05
    grads = []
    for parallel in (None, False):
        sde = tl.models.ornstein_uhlenbeck(0.8, 0.5, dtype=F64)  # learnable θ, q (stationary prior)
        kf = tl.KalmanFilter(sde, torch.tensor([[1.0]], dtype=F64), torch.tensor([[0.2]], dtype=F64), parallel=parallel)
        (-kf(y, dt).log_likelihood.sum()).backward()
        grads.append([p.grad.clone() for p in kf.parameters() if p.grad is not None])
    assert grads[0] and len(grads[0]) == len(grads[1])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)
