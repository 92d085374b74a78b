"""Library calls choose their intra-op threads (one for small work or a busy machine) and
restore the caller's setting, also when the call raises."""

from __future__ import annotations

import pytest
import torch

import torchsde_lti as tl
from torchsde_lti.core import threads
from torchsde_lti.core.thresholds import PARALLEL_MIN_WORK


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_small_work_runs_single_threaded_and_restores(two_threads, monkeypatch) -> None:
    monkeypatch.setattr(threads, "machine_busy", lambda: False)
    seen = []
    with threads.intra_op_threads(10):
        seen.append(torch.get_num_threads())
    with threads.intra_op_threads(PARALLEL_MIN_WORK):
        seen.append(torch.get_num_threads())
    assert seen == [1, 2] and torch.get_num_threads() == 2
    with pytest.raises(RuntimeError), threads.intra_op_threads(10):
        raise RuntimeError("inside")
    assert torch.get_num_threads() == 2


def test_busy_machine_runs_single_threaded(two_threads, monkeypatch) -> None:
    monkeypatch.setattr(threads, "machine_busy", lambda: True)
    with threads.intra_op_threads(10 * PARALLEL_MIN_WORK):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2


def test_discretize_leaves_the_setting(two_threads) -> None:
    tl.discretize(-torch.eye(2), torch.eye(2), torch.eye(2), torch.rand(3))
    assert torch.get_num_threads() == 2
    assert isinstance(threads.machine_busy(), bool)
