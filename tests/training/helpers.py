"""Test helpers for runs: callbacks that signal or slow down a run, and a strict JSON reader.

:class:`SignalAt` sends this process a signal at an exact point of a run, so the signal tests
interrupt training where they mean to (mid-epoch, mid-validation) without timing races;
:class:`Sleep` slows a run down so that a test can signal it from outside. Configured like any
callback: ``+callbacks.kill._target_=tests.training.helpers.SignalAt``. :class:`SummarisedTracks`
and :class:`SummaryAttributeTracks` are datamodules that offer a data summary.
"""

from __future__ import annotations

import json
import math
import os
import signal
import time
from pathlib import Path
from typing import Any

from lightning.pytorch import Callback

from torchsde_lti.data.modules import SimulatedTracks


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
    ("train", "validation", or "test": there after batch ``batch`` of the test, whatever the epoch;
    "setup": in the callbacks' setup hook, before Lightning installs its own signal handler), once."""

    def __init__(self, epoch: int, batch: int = 0, signum: int = int(signal.SIGTERM), stage: str = "train") -> None:
        if stage not in ("train", "validation", "test", "setup"):
            raise ValueError(f"stage must be 'train', 'validation', 'test' or 'setup', got {stage!r}")
        self.epoch, self.batch, self.signum, self.stage = int(epoch), int(batch), int(signum), stage
        self.sent = False

    def _maybe_send(self, trainer: Any, batch_idx: int, stage: str) -> None:
        epoch_matches = stage == "test" or trainer.current_epoch == self.epoch
        if not self.sent and stage == self.stage and epoch_matches and batch_idx == self.batch:
            self.sent = True
            os.kill(os.getpid(), self.signum)

    def setup(self, trainer: Any, pl_module: Any, stage: str) -> None:
        if self.stage == "setup" and not self.sent:
            self.sent = True
            os.kill(os.getpid(), self.signum)

    def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int) -> None:
        self._maybe_send(trainer, batch_idx, "train")

    def on_validation_batch_end(
        self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int, dataloader_idx: int = 0
    ) -> None:
        if not trainer.sanity_checking:
            self._maybe_send(trainer, batch_idx, "validation")

    def on_test_batch_end(
        self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int, dataloader_idx: int = 0
    ) -> None:
        self._maybe_send(trainer, batch_idx, "test")


def _track_counts(dm: Any) -> dict[str, Any]:
    return {"tracks": {k: int(v.y.shape[0]) for k, v in dm.tracks.items()}, "undefined": math.nan}


class SummarisedTracks(SimulatedTracks):
    """SimulatedTracks with a ``summary()`` method, as a datamodule that reports its data does."""

    def summary(self) -> dict[str, Any]:
        return _track_counts(self)


class SummaryAttributeTracks(SimulatedTracks):
    """SimulatedTracks with a ``summary`` attribute filled in by ``setup``."""

    def setup(self, stage: str | None = None) -> None:
        super().setup(stage)
        self.summary = _track_counts(self)


class FailAt(Callback):
    """Raise in the first training batch of epoch ``epoch``: a RuntimeError (``error="runtime"``)
    or a KeyboardInterrupt raised by code (``error="keyboard"``, which Lightning turns into an exit)."""

    def __init__(self, epoch: int, error: str = "runtime") -> None:
        self.epoch, self.error = int(epoch), error

    def on_train_batch_start(self, trainer: Any, *args: Any) -> None:
        if trainer.current_epoch == self.epoch:
            raise KeyboardInterrupt if self.error == "keyboard" else RuntimeError("boom mid-epoch")


class ThreadsSeen(Callback):
    """The torch intra-op thread counts seen in the training batches (``seen``)."""

    def __init__(self) -> None:
        self.seen: set[int] = set()

    def on_train_batch_end(self, *args: Any, **kwargs: Any) -> None:
        import torch

        self.seen.add(torch.get_num_threads())


def failing_plot(*args: Any, **kwargs: Any) -> Any:
    """A plot step that raises (as plotting a 4-state learner against a 6-state truth once did)."""
    raise ValueError("plot failed: shapes (4,) and (6,) not aligned")


class SignalOnInit(SimulatedTracks):
    """SimulatedTracks that sends this process SIGTERM while it is being built (before Lightning runs)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1)  # the handler runs at the next bytecode; it raises before this returns
