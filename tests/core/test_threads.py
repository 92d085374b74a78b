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


class _SeenInBackward(torch.autograd.Function):
    """Identity that records the thread count its backward runs at."""

    seen: list[int] = []

    @staticmethod
    def forward(ctx, x):  # type: ignore[no-untyped-def]
        return x.view_as(x)

    @staticmethod
    def backward(ctx, g):  # type: ignore[no-untyped-def]
        _SeenInBackward.seen.append(torch.get_num_threads())
        return g


def _discretize_recording(monkeypatch, busy: bool) -> list[int]:
    """Thread counts seen inside the doubling's backward of a guarded discretize call (the guard
    made to lower the threads for this small call), and after the backward."""
    from torchsde_lti.core import discretization

    monkeypatch.setattr(threads, "machine_busy", lambda: busy)
    monkeypatch.setattr(threads, "PARALLEL_MIN_WORK", 0)  # "small" work would lower it regardless
    inner = discretization.doubling
    monkeypatch.setattr(
        discretization,
        "doubling",
        lambda x, **kw: tuple(None if t is None else _SeenInBackward.apply(t) for t in inner(x, **kw)),
    )
    _SeenInBackward.seen = []
    F = (-torch.eye(2, dtype=torch.float64) + 0.1).requires_grad_()
    d = tl.discretize(
        F, torch.eye(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64), torch.rand(3, dtype=torch.float64)
    )
    assert torch.get_num_threads() == 2
    (d.A.sum() + d.Q.sum()).backward()
    return [*_SeenInBackward.seen, torch.get_num_threads()]


def test_backward_of_a_call_runs_single_threaded_on_a_busy_machine(two_threads, monkeypatch) -> None:
    seen = _discretize_recording(monkeypatch, busy=True)
    assert seen[:-1] == [1, 1] and seen[-1] == 2  # (A and Q's backward) at 1 thread; the caller's 2 after


def test_backward_keeps_the_threads_of_a_quiet_machine(two_threads, monkeypatch) -> None:
    assert _discretize_recording(monkeypatch, busy=False) == [2, 2, 2]


def test_thread_count_restored_when_the_backward_stops_inside_a_call(two_threads, monkeypatch) -> None:
    """Gradients of an intermediate: the inputs' node never runs; the end-of-backward callback
    restores the caller's count."""
    monkeypatch.setattr(threads, "machine_busy", lambda: True)
    x = torch.rand(3, requires_grad=True)
    mid = x * 2.0
    (out,) = threads._LowerInBackward.apply(threads.PARALLEL_MIN_WORK, mid.exp())
    torch.autograd.grad(out.sum(), mid)
    assert torch.get_num_threads() == 2 and threads._BACKWARD == {"depth": 0, "restore": None}


def test_guarded_call_keeps_first_and_second_derivatives(two_threads, monkeypatch) -> None:
    monkeypatch.setattr(threads, "machine_busy", lambda: True)
    f64 = torch.float64
    F = torch.tensor([[-0.7, 0.4], [-0.2, -1.1]], dtype=f64, requires_grad=True)
    Qc = torch.tensor([[0.8]], dtype=f64, requires_grad=True)
    L = torch.tensor([[0.3], [1.0]], dtype=f64)
    dt = torch.tensor([0.4, 2.5], dtype=f64, requires_grad=True)

    def fn(F, Qc, dt):  # type: ignore[no-untyped-def]
        d = tl.discretize(F, L, Qc, dt)
        return d.A, d.Q

    assert torch.autograd.gradcheck(fn, (F, Qc, dt))
    assert torch.autograd.gradgradcheck(fn, (F, Qc, dt))
    assert torch.get_num_threads() == 2


def test_guarded_filter_and_smoother_give_the_same_gradients_and_restore(two_threads, monkeypatch) -> None:
    monkeypatch.setattr(threads, "machine_busy", lambda: True)
    f64 = torch.float64
    sde = tl.models.constant_velocity(dim=1, q=0.5, dtype=f64)
    H, R = torch.tensor([[1.0, 0.0]], dtype=f64), torch.tensor([[0.3]], dtype=f64)
    y, dt = torch.randn(4, 9, 1, dtype=f64), 0.1 + torch.rand(4, 9, dtype=f64)
    grads = []
    guarded = threads._guarded
    for guard in (False, True):
        monkeypatch.setattr(threads, "_guarded", guarded if guard else lambda work, tensors: False)
        q = torch.tensor(0.5, dtype=f64, requires_grad=True)
        d = tl.discretize(sde.F, sde.L, q * sde.Qc, dt)
        res = tl.filters.kalman_filter(y, d.A, d.Q, H, R, torch.zeros(2, dtype=f64), torch.eye(2, dtype=f64))
        smoothed = tl.filters.rts_smoother(res)
        grads.append(torch.autograd.grad(res.log_likelihood.sum() + smoothed.mean.square().sum(), q)[0])
        assert torch.get_num_threads() == 2
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-14, atol=0)
