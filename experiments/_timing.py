"""The one timing helper of experiments/: medians of repeats, paired A/B in alternation, 1 and 2
threads, the load printed beside every table.

    from _timing import median_s, paired_s, at_threads, machine_line, Tee

- :func:`median_s`: median CPU seconds (``time.process_time``: a shared machine's other jobs
  add no time slices of theirs, only cache and core sharing) of one call over ``repeat`` timings
  of ``inner`` calls, after ``warmup`` calls; ``clock=time.perf_counter`` for wall time (compiles,
  file I/O);
- :func:`paired_s`: two callables timed in alternation (a, b, a, b, ...), so that both see the
  same load: their ratio is what a benchmark reports;
- :func:`at_threads`: a measurement at 1 and 2 intra-op threads (the thread count restored);
- :func:`machine_line`: torch version, threads, the load average (``os.getloadavg``) and a note
  that the machine is shared, for the head and the foot of a table;
- :class:`Tee`: print a table and keep a copy to write into ``experiments/results/``.

Benchmarks set threads themselves (this is a script helper, not library code).
"""

from __future__ import annotations

import io
import os
import statistics
import time
from collections.abc import Callable, Iterable
from typing import TypeVar

import torch

__all__ = ["Tee", "at_threads", "machine_line", "median_s", "paired_s"]

R = TypeVar("R")


def median_s(
    fn: Callable[[], object],
    repeat: int,
    warmup: int = 3,
    inner: int = 1,
    clock: Callable[[], float] = time.process_time,
) -> float:
    """Median seconds of one call of ``fn`` (``repeat`` timings of ``inner`` calls, after ``warmup``)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = clock()
        for _ in range(inner):
            fn()
        times.append((clock() - t0) / inner)
    return statistics.median(times)


def paired_s(
    fa: Callable[[], object],
    fb: Callable[[], object],
    repeat: int,
    warmup: int = 3,
    inner: int = 1,
    clock: Callable[[], float] = time.process_time,
) -> tuple[float, float]:
    """Median seconds of ``fa`` and of ``fb``, timed in alternation."""
    for _ in range(warmup):
        fa()
        fb()
    ta: list[float] = []
    tb: list[float] = []
    for _ in range(repeat):
        for fn, out in ((fa, ta), (fb, tb)):
            t0 = clock()
            for _ in range(inner):
                fn()
            out.append((clock() - t0) / inner)
    return statistics.median(ta), statistics.median(tb)


def at_threads(measure: Callable[[], R], threads: Iterable[int] = (1, 2)) -> dict[int, R]:
    """``measure()`` with each intra-op thread count in ``threads``; the previous count restored."""
    before = torch.get_num_threads()
    try:
        out = {}
        for n in threads:
            torch.set_num_threads(n)
            out[n] = measure()
        return out
    finally:
        torch.set_num_threads(before)


def machine_line() -> str:
    """torch, threads and the 1-minute load average (the machine is shared: figures are noisy)."""
    load = os.getloadavg()[0]
    return (
        f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {os.cpu_count()} CPUs, "
        f"load average {load:.2f} (shared machine: medians of repeats)"
    )


class Tee(io.TextIOBase):
    """Writes to several text streams (the terminal and the saved copy)."""

    def __init__(self, *streams: io.TextIOBase) -> None:
        self.streams = streams

    def write(self, text: str) -> int:
        for stream in self.streams:
            stream.write(text)
            stream.flush()
        return len(text)
