"""SIGTERM / SIGINT during a run: stop at a safe point, say so, exit ``128 + signal``.

Inside ``Trainer.fit`` / ``Trainer.test`` Lightning's own signal connector handles SIGTERM: it
stops the loops at the next batch boundary with its ``SIGTERMException`` (after the epoch-end
checkpoint when the signal comes in the last batch). :class:`SignalGuard`, around the whole
run, records the signal (Lightning composes its handler with it), re-sends a first SIGINT
(Ctrl-C) as SIGTERM so that it takes the same path (a second one interrupts at once), raises
Lightning's exception itself between phases (:meth:`SignalGuard.stop_if_received`), while the
data and the model are built (phase "setup": nothing to keep), and, as a Lightning callback,
when training or testing starts after a signal that came before Lightning's handler was there.
The resume point is ``last.ckpt``: the interrupted epoch is trained again on resume.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from types import FrameType
from typing import Any

from lightning.pytorch import Callback, LightningModule, Trainer
from lightning.pytorch.utilities.exceptions import SIGTERMException

__all__ = ["RunInterrupted", "SignalGuard"]

log = logging.getLogger(__name__)


class RunInterrupted(RuntimeError):
    """A run stopped by a signal, after writing what it had (raised by ``train``).

    Attributes:
        signum: the signal (``signal.SIGTERM`` / ``signal.SIGINT``).
        exit_code: ``128 + signum`` (143 / 130), what ``python -m torchsde_lti.train`` exits with.
        phase: "setup", "fit", "test", "plots" or "outputs": where the signal came.
        run_dir: the run's directory.
        resume_from: the checkpoint to resume from (``ckpt_path=...``); None when no epoch completed.
    """

    def __init__(self, signum: int, phase: str, run_dir: str, resume_from: str | None) -> None:
        self.signum = signal.Signals(signum)
        self.exit_code = 128 + int(self.signum)
        self.phase, self.run_dir, self.resume_from = phase, run_dir, resume_from
        how = f"resume with ckpt_path={resume_from}" if resume_from else "no epoch completed: nothing to resume"
        super().__init__(f"run interrupted by {self.signum.name} during {phase} ({run_dir}); {how}")


class SignalGuard(Callback):
    """Context manager and Lightning callback: record SIGTERM / SIGINT for the duration of a run.

    ``received`` is the first signal (None until one comes), ``phase`` the phase running now (set
    by the caller) and ``received_during`` the one the signal came in. The previous handlers are
    restored on exit; outside the main thread (where Python cannot set handlers) it installs none.
    """

    def __init__(self) -> None:
        self.received: signal.Signals | None = None
        self.received_during: str | None = None
        self.phase = "setup"
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> SignalGuard:
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in (signal.SIGTERM, signal.SIGINT)}
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous = {}

    def stop_if_received(self) -> None:
        """Raise Lightning's ``SIGTERMException`` if a signal came (between phases, and when
        training or testing starts)."""
        if self.received is not None:
            raise SIGTERMException()

    def on_train_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        self.stop_if_received()

    def on_test_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        self.stop_if_received()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.received is not None:
            if signum == signal.SIGINT:
                raise KeyboardInterrupt  # a second Ctrl-C: stop now
            return
        self.received, self.received_during = signal.Signals(signum), self.phase
        log.warning("received %s during %s: stopping at the next safe point", self.received.name, self.phase)
        if self.phase == "setup":
            raise SIGTERMException()  # building the data and the model: nothing to keep, stop now
        if signum == signal.SIGINT:
            os.kill(os.getpid(), signal.SIGTERM)  # the graceful path Lightning takes for SIGTERM
