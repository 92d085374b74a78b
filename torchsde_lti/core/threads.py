"""Intra-op threads for the library's own calls: more threads never make a call slower.

For small work the fork and join of a parallel region cost more than they save, and on a
machine whose cores are busy every parallel region waits for a descheduled thread. Library
calls therefore run with one thread when their work is small or the machine is busy.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator

import torch

from torchsde_lti.core.thresholds import PARALLEL_MIN_WORK

__all__ = ["intra_op_threads", "machine_busy"]

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
