"""Test helpers for runs: callbacks that signal or slow down a run, and a strict JSON reader.

:class:`SignalAt` sends this process a signal at an exact point of a run, so the signal tests
interrupt training where they mean to (mid-epoch, mid-validation) without timing races;
:class:`Sleep` slows a run down so that a test can signal it from outside. Configured like any
callback: ``+callbacks.kill._target_=tests.training.helpers.SignalAt``.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path
from typing import Any

from lightning.pytorch import Callback


def _reject(constant: str) -> Any:
    raise ValueError(f"not strict JSON: bare {constant}")


def load_strict_json(path: str | Path) -> Any:
    """``json.loads`` that rejects the non-standard NaN / Infinity / -Infinity literals."""
    return json.loads(Path(path).read_text(), parse_constant=_reject)


class Sleep(Callback):
    """Sleep ``seconds`` after every training batch (changes no result: nothing random is drawn)."""

    def __init__(self, seconds: float) -> None:
        self.seconds = float(seconds)

    def on_train_batch_end(self, *args: Any, **kwargs: Any) -> None:
        time.sleep(self.seconds)


class SignalAt(Callback):
    """Send ``signum`` to this process after batch ``batch`` of epoch ``epoch`` of ``stage``
    ("train" or "validation"), once."""

    def __init__(self, epoch: int, batch: int = 0, signum: int = int(signal.SIGTERM), stage: str = "train") -> None:
        if stage not in ("train", "validation"):
            raise ValueError(f"stage must be 'train' or 'validation', got {stage!r}")
        self.epoch, self.batch, self.signum, self.stage = int(epoch), int(batch), int(signum), stage
        self.sent = False

    def _maybe_send(self, trainer: Any, batch_idx: int, stage: str) -> None:
        if not self.sent and stage == self.stage and trainer.current_epoch == self.epoch and batch_idx == self.batch:
            self.sent = True
            os.kill(os.getpid(), self.signum)

    def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int) -> None:
        self._maybe_send(trainer, batch_idx, "train")

    def on_validation_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int,
                                dataloader_idx: int = 0) -> None:
        if not trainer.sanity_checking:
            self._maybe_send(trainer, batch_idx, "validation")
