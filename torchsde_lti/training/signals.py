"""SIGTERM / SIGINT during a run: stop at a safe point, say so, exit non-zero.

How a signal travels (:class:`SignalGuard`, installed by :func:`~torchsde_lti.training.train`
for the whole run):

* inside ``Trainer.fit`` / ``Trainer.test`` (``guard.graceful(...)``) a SIGTERM reaches
  Lightning's own signal connector, which stops the loops at the next batch boundary by
  raising its ``SIGTERMException`` (after the epoch-end checkpoint when the signal comes in
  the last batch); this guard is composed into that handler and only records the signal.
  A SIGINT (Ctrl-C) is re-sent as SIGTERM to this process, so it takes the same path; a
  second SIGINT interrupts at once (Lightning's KeyboardInterrupt path).
  :class:`StopOnSignal` covers the moments Lightning's handler is not installed yet
  (data and model setup inside ``fit``): it raises the same exception when training starts;
* everywhere else (building the data and the model) the guard raises :class:`StopRun` at
  once; plots and output files are finished first (``graceful``), then the run stops.

The resume point is the state at the end of the last completed epoch (``last.ckpt``, written
by Lightning's ModelCheckpoint every epoch), not a mid-epoch snapshot: Lightning's loaders
here are not resumable mid-epoch and the epoch means being accumulated are not in a
checkpoint, so only an epoch-end state resumes bit-identically. The interrupted epoch is
trained again on resume.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

from lightning.pytorch import Callback
from lightning.pytorch.utilities.exceptions import SIGTERMException

__all__ = ["RunInterrupted", "SignalGuard", "StopOnSignal", "StopRun"]

log = logging.getLogger(__name__)

SIGNALS = (signal.SIGTERM, signal.SIGINT)


class StopRun(BaseException):
    """Raised by :class:`SignalGuard` outside Lightning's loops (a BaseException, like
    KeyboardInterrupt, so that no ``except Exception`` on the way swallows it)."""

    def __init__(self, signum: int) -> None:
        self.signum = signal.Signals(signum)
        super().__init__(f"received {self.signum.name}")


class RunInterrupted(RuntimeError):
    """A run stopped by a signal, after writing what it had (raised by ``train``).

    Attributes:
        signum: the signal (``signal.SIGTERM`` / ``signal.SIGINT``).
        exit_code: ``128 + signum`` (143 for SIGTERM, 130 for SIGINT), what
            ``python -m torchsde_lti.train`` exits with.
        run_dir: the run's directory.
        resume_from: the checkpoint to resume from (``ckpt_path=...``), or None when no
            epoch completed.
    """

    def __init__(self, signum: int, phase: str, run_dir: str, resume_from: str | None) -> None:
        self.signum = signal.Signals(signum)
        self.exit_code = 128 + int(self.signum)
        self.phase, self.run_dir, self.resume_from = phase, run_dir, resume_from
        how = f"resume with ckpt_path={resume_from}" if resume_from else "no epoch completed: nothing to resume"
        super().__init__(f"run interrupted by {self.signum.name} during {phase} ({run_dir}); {how}")


class SignalGuard:
    """Context manager: record SIGTERM / SIGINT for the duration of a run (see the module doc).

    ``received`` is the first signal (None until one comes) and ``phase`` the phase it came
    in. Previous handlers are restored on exit. Outside the main thread (where Python cannot
    set handlers) it records nothing and installs nothing.
    """

    def __init__(self) -> None:
        self.received: signal.Signals | None = None
        self.phase = "setup"
        self.received_during: str | None = None
        self._graceful = False
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> SignalGuard:
        if threading.current_thread() is threading.main_thread():
            for signum in SIGNALS:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous = {}

    @contextmanager
    def graceful(self, phase: str) -> Iterator[None]:
        """Within: a signal is recorded and the work stops at its own safe point (see module doc)."""
        self.phase, self._graceful = phase, True
        try:
            yield
        finally:
            self._graceful = False

    def enter_phase(self, phase: str) -> None:
        """Name the (non-graceful) phase that runs next, for the record of an interruption."""
        self.phase = phase

    def stop_if_received(self) -> None:
        """Raise :class:`StopRun` if a signal came (call between phases)."""
        if self.received is not None:
            raise StopRun(self.received)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        first = self.received is None
        if first:
            self.received, self.received_during = signal.Signals(signum), self.phase
            log.warning("received %s during %s: stopping at the next safe point", self.received.name, self.phase)
        if not self._graceful:
            raise StopRun(signum)
        if signum == signal.SIGINT:
            if not first:
                raise KeyboardInterrupt  # a second Ctrl-C: stop now
            os.kill(os.getpid(), signal.SIGTERM)  # the graceful path Lightning takes for SIGTERM


class StopOnSignal(Callback):
    """Raise Lightning's ``SIGTERMException`` when training or testing starts after a signal that
    came before Lightning's own handler was installed (data/model setup inside ``fit``)."""

    def __init__(self, guard: SignalGuard) -> None:
        self.guard = guard

    def _check(self) -> None:
        if self.guard.received is not None:
            raise SIGTERMException()

    def on_train_start(self, trainer: Any, pl_module: Any) -> None:
        self._check()

    def on_test_start(self, trainer: Any, pl_module: Any) -> None:
        self._check()
