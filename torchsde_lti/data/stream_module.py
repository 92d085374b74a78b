"""The Lightning DataModule of streamed training: ``python -m torchsde_lti.train data=stream data.root=...``.

:class:`StreamDataModule` serves the windows of a prepared dataset
(:func:`~torchsde_lti.data.prepare_dataset`) through :class:`~torchsde_lti.data.WindowStream`:
nothing is loaded whole, each DDP process (``trainer.global_rank`` of ``trainer.world_size``)
and each DataLoader worker reads its own share. Resuming mid-epoch: the module counts the
training batches that reach the model (``on_before_batch_transfer``) and saves (epoch, count)
in the checkpoint (its ``state_dict``); a run resumed from that checkpoint starts the epoch at
the next batch of the same plan, so no window is repeated or skipped. (The run's checkpoints
must then be written within the epoch, e.g. ``callbacks.last.every_n_epochs=null
+callbacks.last.every_n_train_steps=500``; an end-of-epoch checkpoint resumes at the next epoch.)
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.pytorch import LightningDataModule
from torch.utils.data import DataLoader

from torchsde_lti.data.prepare import PreparedSummary
from torchsde_lti.data.stream import SPLITS, WindowStream, object_split
from torchsde_lti.data.tracks import TrackBatch

__all__ = ["StreamDataModule", "StreamSummary"]


@dataclass(frozen=True)
class StreamSummary:
    """What a :class:`StreamDataModule` trains on: the preparation's summary (the loader's counts
    over every file) and, per split, the windows and batches of this process."""

    prepared: PreparedSummary
    splits: dict[str, dict[str, int]]

    def as_dict(self) -> dict[str, Any]:
        return {"prepared": self.prepared.as_dict(), "splits": self.splits}

    def __str__(self) -> str:
        lines = [str(self.prepared)]
        for name, row in self.splits.items():
            lines.append(f"  {name:>5}: {row['windows']} windows, {row['batches']} batches (this process)")
        return "\n".join(lines)


class _EpochLoader(DataLoader):
    """A DataLoader that tells its :class:`WindowStream` the epoch and the resume point before
    each pass (in the main process, so the workers it starts copy them)."""

    def __init__(self, dataset: WindowStream, owner: StreamDataModule | None, num_workers: int) -> None:
        super().__init__(dataset, batch_size=None, num_workers=num_workers, persistent_workers=False)
        self.owner = owner
        self.passes = 0

    def __iter__(self) -> Any:
        stream: WindowStream = self.dataset  # type: ignore[assignment]
        if self.owner is not None:
            epoch, skip = self.owner._position()
        else:
            epoch, skip = self.passes, 0
        self.passes += 1
        stream.set_position(epoch, skip)
        return super().__iter__()

    # Lightning's mark of a resumable loader; the position itself lives in the DataModule's state
    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        return None


class StreamDataModule(LightningDataModule):
    """Batches of windows streamed from a prepared dataset (see the module docstring).

    Args:
        root: the prepared dataset's folder.
        fractions: (train, val, test) shares of the objects (a seeded hash of each id, so the shares
            hold on average); seed: the split's and the order's seed.
        batch_size: windows per batch; pool_batches: batches per length-sorted pool.
        buffer_windows: the training shuffle buffer (windows).
        num_workers: DataLoader worker processes per DDP process (0: in the training process).
        center: subtract each window's first position (kept in ``origin``).
        dtype: "float32" or "float64" for the batches.

    After :meth:`setup`: ``summary`` (:class:`StreamSummary`; the training job saves it).
    """

    def __init__(
        self,
        root: str,
        fractions: Sequence[float] = (0.6, 0.2, 0.2),
        seed: int = 0,
        batch_size: int = 64,
        pool_batches: int = 50,
        buffer_windows: int = 4096,
        num_workers: int = 0,
        center: bool = True,
        dtype: str = "float32",
    ) -> None:
        super().__init__()
        if dtype not in ("float32", "float64"):
            raise ValueError(f"data.dtype must be 'float32' or 'float64', got {dtype!r}")
        if isinstance(num_workers, bool) or not isinstance(num_workers, int) or num_workers < 0:
            raise ValueError(f"data.num_workers must be an integer >= 0, got {num_workers!r}")
        object_split(np.zeros(0, dtype=np.int64), fractions, 0)  # checks the fractions
        self.root = Path(str(root)).expanduser()
        self.options = {
            "fractions": [float(f) for f in fractions],
            "seed": int(seed),
            "batch_size": int(batch_size),
            "pool_batches": int(pool_batches),
            "buffer_windows": int(buffer_windows),
            "center": bool(center),
            "dtype": getattr(torch, dtype),
        }
        self.num_workers = int(num_workers)
        self.save_hyperparameters(
            {"root": str(root), **{**self.options, "dtype": dtype}, "num_workers": self.num_workers}
        )
        self.summary: StreamSummary | None = None
        self._done = 0  # training batches of the current epoch that reached the model
        self._epoch = 0
        self._resume: tuple[int, int] | None = None

    def _where(self) -> tuple[int, int]:
        """(rank, world size): the trainer's, else 0 of 1."""
        trainer = self.trainer
        if trainer is not None:
            return int(trainer.global_rank), int(trainer.world_size)
        return 0, 1

    def stream(self, split: str) -> WindowStream:
        """The :class:`WindowStream` of ``split`` for this process."""
        rank, world = self._where()
        train = split == "train"
        return WindowStream(self.root, split, shuffle=train, even=train, rank=rank, world_size=world, **self.options)

    def setup(self, stage: str | None = None) -> None:
        """Read the dataset's summary and count this process's windows and batches per split."""
        if self.summary is not None:
            return
        if not (self.root / "summary.json").is_file():
            raise FileNotFoundError(
                f"data.root={str(self.root)!r} holds no prepared dataset (no summary.json): prepare it with "
                f"python -m torchsde_lti.prepare source=... out={self.root}"
            )
        prepared = PreparedSummary.from_dict(json.loads((self.root / "summary.json").read_text()))
        splits = {}
        for split in SPLITS:
            try:
                s = self.stream(split)
            except ValueError:
                continue
            splits[split] = {"windows": int(sum(len(b) for b in s.batches(0))), "batches": len(s)}
        for split in ("train", "val"):
            if split not in splits:
                raise ValueError(
                    f"data.root={str(self.root)!r}: the {split} split has no windows (fractions {self.options['fractions']})"
                )
        self.summary = StreamSummary(prepared, splits)

    # ------------------------------------------------------------------ loaders
    def _loader(self, split: str) -> _EpochLoader:
        self.setup()
        try:
            stream = self.stream(split)
        except ValueError as err:
            raise ValueError(f"no {split} split in {self.root}: {err}") from None
        return _EpochLoader(stream, self if split == "train" else None, self.num_workers)

    def train_dataloader(self) -> _EpochLoader:
        return self._loader("train")

    def val_dataloader(self) -> _EpochLoader:
        return self._loader("val")

    def test_dataloader(self) -> _EpochLoader:
        return self._loader("test")

    # ------------------------------------------------------------------ resuming mid-epoch
    def _position(self) -> tuple[int, int]:
        """(epoch, first batch) of the training pass about to start."""
        trainer = self.trainer
        epoch = int(trainer.current_epoch) if trainer is not None else self._epoch
        skip = 0
        if self._resume is not None and self._resume[0] == epoch:
            skip = self._resume[1]
        self._resume = None
        self._epoch, self._done = epoch, skip
        return epoch, skip

    def on_before_batch_transfer(self, batch: TrackBatch, dataloader_idx: int) -> TrackBatch:
        trainer = self.trainer
        if trainer is not None and trainer.training:
            self._done += 1
        return batch

    def state_dict(self) -> dict[str, Any]:
        """(epoch, training batches of it done): where a resumed run continues."""
        return {"epoch": self._epoch, "batches": self._done}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._resume = (int(state_dict["epoch"]), int(state_dict["batches"]))
