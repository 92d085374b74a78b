"""The automatic filter choice (``algorithm="auto"``) and the chunked associative scan."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from tests.reference import random_problem, reference_batch, to_torch
from torchsde_lti.filters import choose_algorithm, kalman_filter, prefers_scan, rts_smoother

F64 = torch.float64


@pytest.mark.parametrize("chunk", [1, 5, 7, 40])
def test_chunked_scan_matches_numpy_reference(chunk):
    """Chunks of any length (1 … > T, dividing T or not) give the reference filter, with
    controls, missing components and fully missing steps."""
    d = random_problem(np.random.default_rng(1), batch=(2,), T=21)
    ref = reference_batch(d)
    t = to_torch(d)
    out = kalman_filter(
        t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], G=t["G"], u=t["u"], algorithm="scan", chunk=chunk
    )
    for name in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(getattr(out, name).numpy(), ref[name], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.step_log_likelihood.numpy(), ref["ll"], atol=1e-9)
    np.testing.assert_allclose(out.log_likelihood.numpy(), ref["ll"].sum(-1), atol=1e-9)
    seq = kalman_filter(
        t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], G=t["G"], u=t["u"], algorithm="sequential"
    )
    for name in ("innovation", "innovation_cov", "transition", "process_noise", "observed"):
        np.testing.assert_allclose(getattr(out, name).numpy(), getattr(seq, name).numpy(), atol=1e-9)
    # the smoother runs on the concatenated result
    np.testing.assert_allclose(
        rts_smoother(out, algorithm="scan").mean.numpy(),
        rts_smoother(seq, algorithm="sequential").mean.numpy(),
        atol=1e-8,
    )


def test_chunked_scan_with_per_step_mask():
    d = random_problem(np.random.default_rng(2), batch=(3,), T=10, missing=False)
    t = to_torch(d)
    mask = torch.rand(3, 10, generator=torch.Generator().manual_seed(0)) > 0.3
    args = (t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"])
    out = kalman_filter(*args, mask=mask, algorithm="scan", chunk=3)
    seq = kalman_filter(*args, mask=mask, algorithm="sequential")
    np.testing.assert_allclose(out.mean.numpy(), seq.mean.numpy(), atol=1e-9)
    np.testing.assert_allclose(out.log_likelihood.numpy(), seq.log_likelihood.numpy(), atol=1e-9)


@pytest.mark.parametrize(
    "shape, chunk",
    [((2, 7, 1), 3), ((2, 7, 1), 2), ((7, 2), 2), ((2, 7), 2), ((2, 7, 2), 3), ((7, 1), 1)],
)
def test_chunked_scan_slices_every_mask_form(shape, chunk):
    """Per-step masks (..., T) and (..., T, 1) and per-component ones (..., T, m) with fewer
    dims than y, in chunks of any length (chunk == m, a last chunk of one step): the result of
    the sequential filter on y with NaN where the mask is False."""
    g = torch.Generator().manual_seed(3)
    B, T, m, n = 2, 7, 2, 2
    y = torch.randn(B, T, m, generator=g, dtype=F64)
    A, Q = torch.eye(n, dtype=F64).expand(T, n, n), 0.1 * torch.eye(n, dtype=F64).expand(T, n, n)
    H, R = torch.eye(m, n, dtype=F64), 0.5 * torch.eye(m, dtype=F64)
    m0, P0 = torch.zeros(n, dtype=F64), torch.eye(n, dtype=F64)
    mask = torch.rand(shape, generator=g) > 0.4
    full = mask[..., None] if shape == (B, T) else mask
    y_nan = torch.where(full.expand(B, T, m), y, float("nan"))
    want = kalman_filter(y_nan, A, Q, H, R, m0, P0, algorithm="sequential")
    out = kalman_filter(y, A, Q, H, R, m0, P0, mask=mask, algorithm="scan", chunk=chunk)
    for name in ("mean", "cov", "step_log_likelihood", "log_likelihood"):
        torch.testing.assert_close(getattr(out, name), getattr(want, name), rtol=0, atol=1e-9)


@pytest.mark.parametrize("chunk", [0, -1, 2.0, True])
def test_chunked_scan_refuses_a_bad_chunk(chunk):
    """chunk must be a positive int or None: a ValueError naming it (0, -1 and 2.0 raised
    range()'s or torch.cat's errors; True ran)."""
    t = to_torch(random_problem(np.random.default_rng(4), batch=(2,), T=5))
    with pytest.raises(ValueError, match=rf"chunk must be a positive integer or None, got {chunk!r}"):
        kalman_filter(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], algorithm="scan", chunk=chunk)


def test_prefers_scan_rule():
    cpu = torch.device("cpu")
    assert prefers_scan(1, 200, cpu) and prefers_scan(16, 10_000, cpu)
    assert not prefers_scan(17, 200, cpu) and not prefers_scan(1000, 200, cpu)
    assert not prefers_scan(1, 1, cpu)
    assert choose_algorithm("auto", 1, 200, cpu) == "scan" and choose_algorithm("auto", 17, 200, cpu) == "sequential"
    for algorithm in ("sequential", "square_root", "scan"):
        assert choose_algorithm(algorithm, 1, 200, cpu) == algorithm
    with pytest.raises(ValueError, match=r"kalman_filter has the algorithms .*got algorithm='parallel'"):
        choose_algorithm("parallel", 1, 200, cpu)


def test_functional_auto_runs_the_chosen_algorithm(monkeypatch):
    """kalman_filter(algorithm="auto") runs the scan for few tracks and the loop for many;
    rts_smoother likewise; unknown algorithms raise, naming the choices."""
    import torchsde_lti.filters.kalman as kalman_module
    import torchsde_lti.filters.smoothers as smoothers_module

    ran = []
    for name in ("chunked_scan", "sequential_filter"):
        original = getattr(kalman_module, name)
        monkeypatch.setattr(kalman_module, name, lambda *a, _f=original, _n=name, **k: (ran.append(_n), _f(*a, **k))[1])
    original_scan = smoothers_module._scan_smoother
    monkeypatch.setattr(
        smoothers_module, "_scan_smoother", lambda *a: (ran.append("scan smoother"), original_scan(*a))[1]
    )
    for B, expected in ((2, "chunked_scan"), (17, "sequential_filter")):
        d = random_problem(np.random.default_rng(B), batch=(B,), T=6)
        t = to_torch(d)
        ran.clear()
        out = kalman_filter(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"])
        rts_smoother(out)
        assert ran == [expected] + (["scan smoother"] if B <= 16 else [])
    with pytest.raises(ValueError, match="rts_smoother has the algorithms"):
        rts_smoother(out, algorithm="square_root")
    with pytest.raises(ValueError, match="kalman_filter has the algorithms"):
        kalman_filter(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], algorithm="parallel")


def test_kalman_filter_auto_choice_and_forcing():
    cv = tl.models.constant_velocity(dim=1, q=0.7, dtype=F64)
    H, R = torch.tensor([[1.0, 0.0]], dtype=F64), torch.tensor([[0.3]], dtype=F64)
    g = torch.Generator().manual_seed(0)
    results = {}
    for B in (3, 40):
        y = torch.randn(B, 25, 1, generator=g, dtype=F64)
        dt = torch.rand(B, 25, generator=g, dtype=F64) + 0.1
        for algorithm in ("auto", "scan", "sequential"):
            kf = tl.KalmanFilter(cv, H, R, P0=torch.eye(2, dtype=F64), algorithm=algorithm)
            expected = ("scan" if B <= 16 else "sequential") if algorithm == "auto" else algorithm
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


def test_auto_choice_gradients_equal_loop():
    """Training through the automatic choice (the scan for few tracks) gives the loop's gradients."""
    g = torch.Generator().manual_seed(3)
    y = torch.randn(2, 30, 1, generator=g, dtype=F64).cumsum(1)
    dt = torch.rand(2, 30, generator=g, dtype=F64) + 0.05
    grads = []
    for algorithm in ("auto", "sequential"):
        sde = tl.models.ornstein_uhlenbeck(0.8, 0.5, dtype=F64)  # learnable θ, q (stationary prior)
        kf = tl.KalmanFilter(
            sde, torch.tensor([[1.0]], dtype=F64), torch.tensor([[0.2]], dtype=F64), algorithm=algorithm
        )
        (-kf(y, dt).log_likelihood.sum()).backward()
        grads.append([p.grad.clone() for p in kf.parameters() if p.grad is not None])
    assert grads[0] and len(grads[0]) == len(grads[1])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)


def test_auto_runs_the_loop_in_float32_where_the_scan_loses_a_long_gap() -> None:
    """One track, 10 reports, 2900 missing steps (a 1450 s gap: predicted/measured variance
    ~1e11), 2 reports: the float32 scan's combine gives NaN there, so float32 "auto" runs the
    loop and matches float64."""
    import numpy as np

    import torchsde_lti as tl

    rng = np.random.default_rng(0)
    T = 10 + 2900 + 2
    y = rng.normal(size=(1, T, 1)).cumsum(1)
    y[0, 10:2910] = np.nan
    lls = {}
    for dtype in (torch.float64, torch.float32):
        sde = tl.models.constant_velocity(dim=1, q=1.0, dtype=dtype)
        kf = tl.KalmanFilter(
            sde, tl.models.position_observation(sde), 0.01 * torch.eye(1, dtype=dtype), P0=torch.eye(2, dtype=dtype)
        )
        assert kf.algorithm_for(1, T, torch.device("cpu")) == ("scan" if dtype == torch.float64 else "sequential")
        with torch.no_grad():
            lls[dtype] = float(kf(torch.tensor(y, dtype=dtype), torch.full((1, T), 0.5, dtype=dtype)).log_likelihood)
    assert abs(lls[torch.float32] - lls[torch.float64]) < 1e-3


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
