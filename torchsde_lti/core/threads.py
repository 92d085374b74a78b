"""Intra-op threads for the library's own calls: more threads never make a call slower.

For small work the fork and join of a parallel region cost more than they save, and on a
machine whose cores are busy every parallel region waits for a descheduled thread. Library
calls therefore run with one thread when their work is small or the machine is busy. Their
backward, which autograd runs after the call has returned, follows the same rule
(:func:`one_thread_backward`).
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

import torch
from torch import Tensor
from torch.utils import _pytree as pytree

from torchsde_lti.core.linalg import _plain_ops_required
from torchsde_lti.core.thresholds import PARALLEL_MIN_WORK

__all__ = ["intra_op_threads", "machine_busy", "one_thread_backward", "with_threads"]

_LOAD = {"checked": -1.0, "busy": False}
#: How long a reading of the machine's load is reused (s).
_LOAD_TTL = 1.0


def machine_busy() -> bool:
    """Whether more tasks are runnable than this process may use CPUs (``/proc/loadavg``'s
    running count, re-read at most once a second; False where it cannot be read)."""
    now = time.monotonic()
    if now - _LOAD["checked"] > _LOAD_TTL:
        try:
            with open("/proc/loadavg") as f:
                running = int(f.read().split()[3].split("/")[0])
            cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
            _LOAD["busy"] = running > cpus
        except (OSError, ValueError, IndexError):
            _LOAD["busy"] = False
        _LOAD["checked"] = now
    return bool(_LOAD["busy"])


@contextlib.contextmanager
def intra_op_threads(work: int) -> Iterator[None]:
    """Run the block with one intra-op thread when ``work`` (elements the call touches) is
    below :data:`~torchsde_lti.core.thresholds.PARALLEL_MIN_WORK` or the machine is busy,
    with the caller's thread count otherwise, restored on exit. (torch's thread count is
    process-wide: a torch call from another Python thread meanwhile runs with the same.)"""
    threads = torch.get_num_threads()
    if not isinstance(work, int):  # a symbolic size (torch.export with dynamic shapes): no guard on it
        yield
        return
    if threads == 1 or not (work < PARALLEL_MIN_WORK or machine_busy()):
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


#: The backward guard's state: nesting depth of guarded calls in the running backward, and the
#: thread count to restore (None when the guard did not lower it).
_BACKWARD: dict[str, Any] = {"depth": 0, "restore": None}


def _restore_threads() -> None:
    """Give the caller's thread count back (end of a guarded backward, or of the whole backward)."""
    if _BACKWARD["restore"] is not None:
        torch.set_num_threads(_BACKWARD["restore"])
    _BACKWARD["depth"], _BACKWARD["restore"] = 0, None


class _LowerInBackward(torch.autograd.Function):
    """Identity on a call's outputs; in the backward (which reaches it first) it lowers the
    thread count to one when the work is small or the machine is busy, and queues a callback
    that restores it at the end of the backward pass in any case."""

    @staticmethod
    def forward(ctx: Any, work: int, *outputs: Tensor) -> tuple[Tensor, ...]:
        ctx.work = work
        ctx.set_materialize_grads(False)
        return outputs

    @staticmethod
    def backward(ctx: Any, *grads: Tensor | None) -> tuple[Any, ...]:
        if _BACKWARD["depth"] == 0 and torch.get_num_threads() > 1:
            if ctx.work < PARALLEL_MIN_WORK or machine_busy():
                _BACKWARD["restore"] = torch.get_num_threads()
                torch.set_num_threads(1)
            torch.autograd.Variable._execution_engine.queue_callback(_restore_threads)
        _BACKWARD["depth"] += 1
        return (None, *grads)


class _RaiseInBackward(torch.autograd.Function):
    """Identity on a call's inputs; in the backward (reached once the call's whole backward has
    run) it restores the thread count that :class:`_LowerInBackward` lowered."""

    @staticmethod
    def forward(ctx: Any, *inputs: Tensor) -> tuple[Tensor, ...]:
        ctx.set_materialize_grads(False)
        return inputs

    @staticmethod
    def backward(ctx: Any, *grads: Tensor | None) -> tuple[Tensor | None, ...]:
        _BACKWARD["depth"] = max(0, _BACKWARD["depth"] - 1)
        if _BACKWARD["depth"] == 0:
            _restore_threads()
        return grads


def _guarded(work: int, tensors: Sequence[Tensor | None]) -> bool:
    """Whether a call's backward needs the guard: eager, reverse mode recording a graph, more
    than one thread (even tiny backward ops fork threads: ``bmm`` over a batch of small
    matrices does)."""
    if not isinstance(work, int) or torch.get_num_threads() == 1:
        return False
    if not torch.is_grad_enabled() or not any(t is not None and t.requires_grad for t in tensors):
        return False
    return not _plain_ops_required()


def one_thread_backward(work: int, tensors: Sequence[Tensor | None]) -> tuple[list[Tensor | None], Any]:
    """Let the backward of a library call follow :func:`intra_op_threads`'s rule.

    ``tensors``: the call's differentiable inputs. Returns them (wrapped in an identity node
    when guarded) and a function to apply to the call's outputs (likewise). In the backward the
    outputs' node lowers the thread count to one when ``work`` is below
    :data:`~torchsde_lti.core.thresholds.PARALLEL_MIN_WORK` or the machine is busy, and the
    inputs' node (reached when the call's backward is done) restores it; a callback at the end
    of the backward pass restores it whatever part of the graph ran. Unguarded (returned as
    they are): traced calls, forward-mode AD, no graph recorded, one thread.
    """
    if not _guarded(work, tensors):
        return list(tensors), lambda *outputs: outputs
    present = [i for i, t in enumerate(tensors) if t is not None and t.requires_grad]
    raised = _RaiseInBackward.apply(*(tensors[i] for i in present))
    wrapped = list(tensors)
    for i, t in zip(present, raised):
        wrapped[i] = t

    def lower(*outputs: Tensor | None) -> tuple[Tensor | None, ...]:
        idx = [i for i, t in enumerate(outputs) if t is not None and t.requires_grad]
        out = list(outputs)
        for i, t in zip(idx, _LowerInBackward.apply(work, *(outputs[i] for i in idx))):
            out[i] = t
        return tuple(out)

    return wrapped, lower


_R = TypeVar("_R")


def with_threads(work: int, fn: Callable[..., _R], *args: Any) -> _R:
    """``fn(*args)`` under :func:`intra_op_threads` ``(work)``, its backward under
    :func:`one_thread_backward`: the tensors among ``args`` and in the result (tensors,
    tuples and NamedTuples of them, nested) are wrapped when the guard applies."""
    guard = torch.get_num_threads() != 1 and torch.is_grad_enabled() and isinstance(work, int)
    if guard:  # (the cheap checks first: the arguments are flattened only when they may need it)
        leaves, spec = pytree.tree_flatten(args)
        tensors = [x if isinstance(x, Tensor) else None for x in leaves]
        guard = _guarded(work, tensors)
    if not guard:
        with intra_op_threads(work):
            return fn(*args)
    wrapped, finish = one_thread_backward(work, tensors)
    args = pytree.tree_unflatten([w if isinstance(x, Tensor) else x for w, x in zip(wrapped, leaves)], spec)
    with intra_op_threads(work):
        out = fn(*args)
    leaves, spec = pytree.tree_flatten(out)
    done = finish(*(x if isinstance(x, Tensor) else None for x in leaves))
    return pytree.tree_unflatten([d if isinstance(x, Tensor) else x for d, x in zip(done, leaves)], spec)
