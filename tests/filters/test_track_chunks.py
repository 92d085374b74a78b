"""The sequential loop over chunks of tracks (eager CPU calls at one intra-op thread whose
per-track covariances take more than ``filters.sequential.CHUNKED_MIN_BYTES``): values and gradients equal to the loop over
all tracks at once, for one and two batch dims, inputs, missing data, time-varying H and a
covariance batch that is not the tracks' (which runs unchunked)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.reference import random_problem, to_torch
from torchsde_lti.filters import kalman_filter, sequential

F64 = torch.float64


@pytest.fixture(autouse=True)
def _one_thread():
    """Chunks of tracks are taken at one intra-op thread."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _run(kw: dict, grad: bool) -> tuple[torch.Tensor, ...]:
    kw = {k: v.detach().requires_grad_(grad and v.is_floating_point()) for k, v in kw.items()}
    out = kalman_filter(**kw, algorithm="sequential")
    values = (out.log_likelihood, out.mean, out.cov, out.pred_mean, out.pred_cov, out.innovation, out.innovation_cov)
    if not grad:
        return values
    loss = out.log_likelihood.sum() + out.mean.square().sum() + out.cov.sum()
    return values + torch.autograd.grad(loss, [kw["A"], kw["Q"], kw["P0"], kw["y"]])


@pytest.mark.parametrize("batch", [(7,), (5, 3)])
@pytest.mark.parametrize("grad", [False, True])
def test_chunks_of_tracks_equal_all_tracks_at_once(batch, grad, monkeypatch) -> None:
    kw = to_torch(random_problem(np.random.default_rng(len(batch)), batch=batch, T=9))
    kw["H"] = torch.randn(9, 2, 4, dtype=F64, generator=torch.Generator().manual_seed(1))  # time-varying H
    whole = _run(kw, grad)
    calls = []
    loop = sequential._loop
    monkeypatch.setattr(sequential, "_loop", lambda prep: calls.append(prep.mean_batch) or loop(prep))
    monkeypatch.setattr(sequential, "CHUNKED_MIN_BYTES", 0)
    monkeypatch.setattr(sequential, "CHUNK_BYTES", 2 * 16 * 8 * (batch[1] if len(batch) > 1 else 1))  # 2 rows a chunk
    chunked = _run(kw, grad)
    assert [s[0] for s in calls] == [2] * (batch[0] // 2) + ([1] if batch[0] % 2 else [])
    for a, b in zip(chunked, whole):
        torch.testing.assert_close(a, b, rtol=1e-13, atol=1e-13)


def test_a_covariance_batch_shared_by_the_tracks_runs_unchunked(monkeypatch) -> None:
    """One (A, Q, P0) for every track (a shared grid, nothing missing): the covariance recursion
    runs once, not per chunk of tracks."""
    kw = to_torch(random_problem(np.random.default_rng(3), batch=(6,), T=5, missing=False))
    kw["A"], kw["Q"], kw["P0"] = kw["A"][0], kw["Q"][0], kw["P0"][0]
    kw["G"] = kw["G"][0]
    calls = []
    loop = sequential._loop
    monkeypatch.setattr(sequential, "_loop", lambda prep: calls.append(prep.mean_batch) or loop(prep))
    monkeypatch.setattr(sequential, "CHUNKED_MIN_BYTES", 0)
    monkeypatch.setattr(sequential, "CHUNK_BYTES", 1)
    kalman_filter(**kw, algorithm="sequential")
    assert calls == [torch.Size([6])]


def test_more_threads_run_unchunked(monkeypatch) -> None:
    """Inside a call running at two or more threads (large work on a quiet machine) the loop
    takes all tracks at once: chunks are many small ops, each a parallel region."""
    from torchsde_lti.filters.inputs import FilterInputs, prepare_inputs

    kw = to_torch(random_problem(np.random.default_rng(4), batch=(6,), T=4))
    prep = prepare_inputs(FilterInputs(**kw))
    monkeypatch.setattr(sequential, "CHUNKED_MIN_BYTES", 0)
    monkeypatch.setattr(sequential, "CHUNK_BYTES", 1)
    assert sequential._chunk_rows(prep) == 1
    torch.set_num_threads(2)
    assert sequential._chunk_rows(prep) is None
