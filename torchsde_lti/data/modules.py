"""Lightning DataModules: simulated tracks from a known LTISDE, and real tracks from any file.

The only place in :mod:`torchsde_lti.data` that imports Lightning; both yield
:class:`~torchsde_lti.data.tracks.TrackBatch` batches through the one
:func:`~torchsde_lti.data.tracks.collate_tracks`.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.pytorch import LightningDataModule
from torch import Tensor
from torch.utils.data import DataLoader, SequentialSampler

from torchsde_lti.data.loaded_tracks import LoadSummary, Tracks
from torchsde_lti.data.rules import CleaningRules, _instants
from torchsde_lti.data.simulate import ExponentialDt, isotropic_covariance, simulate_tracks
from torchsde_lti.data.sources import _RESERVED_CONTENT, RESERVED_FOR_EVALUATION, locate_file
from torchsde_lti.data.splits import split_objects, split_time, track_windows
from torchsde_lti.data.tracks import (
    BucketBatchSampler,
    EpochShuffleSampler,
    TrackBatch,
    TrackDataset,
    collate_tracks,
    padding_waste,
    unpad_tracks,
)
from torchsde_lti.data.trajectories import load_tracks

__all__ = ["DataSummary", "SimulatedTracks", "TrackDataModule"]

log = logging.getLogger(__name__)


class SimulatedTracks(LightningDataModule):
    """Tracks simulated exactly from a known LTISDE, split into train/val/test.

    Args:
        sde: the true LTISDE (simulated in float64; the original is left untouched).
        H: (m, n) observation matrix (e.g. ``tl.models.position_observation(sde)``).
        noise: observation noise standard deviation σ; R = σ² I (must be >= 0).
        num_tracks: {"train": .., "val": .., "test": ..} tracks per split.
        T: steps per track (>= 2); T_min: shortest track (default T: all equal).
        dt: a dt sampler (``RegularDt``, ``ExponentialDt``, ``BurstDt`` or any
            ``f(shape, generator) -> Tensor``).
        p_missing: probability that a step's observation is missing.
        control_std: i.i.d. Gaussian control inputs (needs ``sde.B``); None = no inputs.
        init_std: prior standard deviation of every state coordinate at t0 (m0 = 0).
        batch_size: tracks per batch (None: a whole split per batch); seed: simulation and shuffling seed;
        dtype: "float64" or "float32" for the batches.

    Attributes after construction: ``truth`` = {"sde", "R"} (for parameter errors),
    ``m0`` (n,) and ``P0`` (n, n), the prior shared with the filter.
    """

    def __init__(
        self,
        sde: torch.nn.Module,
        H: Tensor,
        noise: float = 0.5,
        num_tracks: Mapping[str, int] | None = None,
        T: int = 100,
        T_min: int | None = None,
        dt: Any = None,
        p_missing: float = 0.0,
        control_std: float | None = None,
        init_std: float = 1.0,
        batch_size: int | None = 64,
        seed: int = 0,
        dtype: str = "float64",
    ) -> None:
        super().__init__()
        if not (isinstance(noise, (int, float)) and noise >= 0 and math.isfinite(noise)):
            raise ValueError(f"data.noise (observation noise std) must be a finite number >= 0, got {noise!r}")
        if int(T) < 2:
            raise ValueError(f"data.T (steps per track) must be >= 2, got {T}")
        if T_min is not None and not 2 <= int(T_min) <= int(T):
            raise ValueError(f"data.T_min must satisfy 2 <= T_min <= T = {T}, got {T_min}")
        if not 0 <= p_missing < 1:
            raise ValueError(f"data.p_missing must be in [0, 1), got {p_missing}")
        if not init_std > 0:
            raise ValueError(f"data.init_std must be positive, got {init_std}")
        if batch_size is not None and int(batch_size) < 1:
            raise ValueError(f"data.batch_size must be >= 1 or null (a whole split per batch), got {batch_size}")
        if dtype not in ("float32", "float64"):
            raise ValueError(f"data.dtype must be 'float32' or 'float64', got {dtype!r}")
        splits = {"train": 200, "val": 50, "test": 50} if num_tracks is None else dict(num_tracks)
        for k in ("train", "val", "test"):
            if int(splits.get(k, 0)) < 1:
                raise ValueError(f"data.num_tracks.{k} must be >= 1, got {splits.get(k)}")
        self.sde = sde
        self.H = torch.as_tensor(H, dtype=torch.float64).detach()
        m, n = self.H.shape
        self.noise, self.T, self.T_min = float(noise), int(T), T_min
        self.num_tracks = {k: int(splits[k]) for k in ("train", "val", "test")}
        self.dt_sampler = ExponentialDt(0.1) if dt is None else dt
        self.p_missing, self.control_std = float(p_missing), control_std
        self.batch_size = None if batch_size is None else int(batch_size)
        self.seed, self.dtype = int(seed), getattr(torch, dtype)
        self.R = isotropic_covariance(self.noise, m)
        self.m0 = torch.zeros(n, dtype=torch.float64)
        self.P0 = float(init_std) ** 2 * torch.eye(n, dtype=torch.float64)
        self.truth = {"sde": sde, "R": self.R}
        self.tracks: dict[str, TrackBatch] = {}

    def _simulate(self, split: str) -> TrackBatch:
        offset = {"train": 0, "val": 1, "test": 2}[split]
        return simulate_tracks(
            self.sde, self.H, self.R, self.num_tracks[split], self.T,
            dt_sampler=self.dt_sampler, T_min=self.T_min, p_missing=self.p_missing,
            control_std=self.control_std, m0=self.m0, P0=self.P0,
            seed=self.seed * 1_000_003 + offset,
        )  # fmt: skip

    def setup(self, stage: str | None = None) -> None:
        """Simulate all three splits once (deterministic, so every DDP rank agrees)."""
        for split in ("train", "val", "test"):
            if split not in self.tracks:
                self.tracks[split] = self._simulate(split)

    def dataset(self, split: str) -> TrackDataset:
        if split not in self.tracks:
            self.setup()
        batch = self.tracks[split]
        cast = {
            k: v.to(self.dtype) for k, v in batch._asdict().items() if isinstance(v, Tensor) and v.is_floating_point()
        }
        return TrackDataset(unpad_tracks(batch._replace(**cast)))

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        ds = self.dataset(split)
        sampler = EpochShuffleSampler(len(ds), self.seed) if shuffle else None
        size = len(ds) if self.batch_size is None else self.batch_size
        return DataLoader(ds, batch_size=max(size, 1), sampler=sampler, collate_fn=collate_tracks)

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False)


@dataclass(frozen=True)
class DataSummary:
    """What a :class:`TrackDataModule` trains on: the loader's counts and, per split, objects,
    tracks, windows, reports, batches and the padding waste of its batches."""

    load: LoadSummary
    split: str
    max_len: int | None
    batch_size: int | None
    splits: dict[str, dict[str, float]]

    def as_dict(self) -> dict[str, Any]:
        return {
            "load": self.load.as_dict(),
            "split": self.split,
            "max_len": self.max_len,
            "batch_size": self.batch_size,
            "splits": self.splits,
        }

    def __str__(self) -> str:
        lines = [
            str(self.load),
            f"  split by {self.split}; windows of <= {self.max_len or 'all'} reports, "
            f"batches of {self.batch_size or 'a whole split'}:",
        ]
        for name, row in self.splits.items():
            lines.append(
                f"  {name:>5}: {row['objects']} objects, {row['tracks']} tracks, {row['windows']} windows, "
                f"{row['reports']} reports, {row['batches']} batches, padding waste "
                f"{100 * row['padding_waste']:.1f} %"
            )
        return "\n".join(lines)


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _reserved_file(source: str | os.PathLike[str]) -> str | None:
    """The name of the file of :data:`~torchsde_lti.data.sources.RESERVED_FOR_EVALUATION` that
    ``source`` is, else None.

    By name: as written ("x.traj/" and "x.traj/." name x.traj) and the file it resolves to (through
    links). By identity: the installed reserved file itself (a hard link). By content: the size and
    sha256 of a reserved file as tracktable-data 1.7.3.1 ships it or as the installed
    tracktable-data holds it (a renamed copy; only a file of a reserved file's size is hashed).
    """
    names = {Path(str(source)).name}
    try:
        path = locate_file(source)
        names.add(path.resolve().name)
    except (FileNotFoundError, OSError):
        path = None
    for name in RESERVED_FOR_EVALUATION:
        if name in names:
            return name
    if path is None:
        return None
    size = path.stat().st_size
    same_size = [(name, digest) for name, (n, digest) in _RESERVED_CONTENT.items() if n == size]
    for name in RESERVED_FOR_EVALUATION:
        try:
            shipped = locate_file(name)
        except FileNotFoundError:
            continue
        if os.path.samefile(path, shipped):
            return name
        if shipped.stat().st_size == size:  # (another release of tracktable-data than the table's)
            same_size.append((name, _sha256(shipped)))
    mine = _sha256(path) if same_size else None
    return next((name for name, digest in same_size if digest == mine), None)


def _check_count(name: str, value: object, low: int | None, allow_none: bool) -> None:
    """An integer >= ``low`` (or None when allowed), else TypeError / ValueError naming ``name``."""
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be an integer{' or null' if allow_none else ''}, got {value!r}")
    if low is not None and value < low:
        raise ValueError(f"{name} must be >= {low}{' or null' if allow_none else ''}, got {value}")


class TrackDataModule(LightningDataModule):
    """Real tracks from any trajectory file (:func:`~torchsde_lti.data.load_tracks`) as padded,
    masked :class:`~torchsde_lti.data.tracks.TrackBatch` es of similar-length windows.

    Args:
        source: the file (:func:`load_tracks`).
        rules: the reading and cleaning rules (:class:`~torchsde_lti.data.CleaningRules` or a
            mapping of its fields); None = its defaults with ``min_reports=5``.
        split: "objects" (object-disjoint train/val/test with ``fractions`` and ``seed``:
            every track of a vessel or flight lands in one split) or "time" (``boundaries``:
            train before the first, val before the second, test after it; tracks are cut at
            the boundaries when loaded).
        max_len: cut tracks into windows of at most this many reports (None: whole tracks).
        batch_size: windows per batch, bucketed by length (:class:`BucketBatchSampler`);
            None = a whole split in one batch (full-batch optimisers such as L-BFGS).
        pool_batches: batches per length-sorted pool of the training sampler.
        center: subtract each window's first position (kept in ``origin``).
        dtype: "float32" or "float64" for the batches.
        **changes: fields of :class:`~torchsde_lti.data.CleaningRules` replacing those of
            ``rules`` (what the ``data=`` configs set: ``max_gap``, ``v_max``, ``min_reports``,
            ``columns``...). With ``split="time"`` the ``boundaries`` are added to its ``cut_times``.

    After :meth:`setup`: ``tracks`` (all kept :class:`~torchsde_lti.data.Tracks`), ``splits``
    (name -> Tracks), ``windows`` (name -> list of Track) and ``summary``
    (:class:`DataSummary`, logged at INFO on rank 0; the training job saves it).
    The files in :data:`~torchsde_lti.data.sources.RESERVED_FOR_EVALUATION` are refused, by name,
    link or content (a renamed copy too).
    """

    def __init__(
        self,
        source: str,
        rules: CleaningRules | Mapping[str, Any] | None = None,
        split: str = "objects",
        fractions: Sequence[float] = (0.6, 0.2, 0.2),
        boundaries: Sequence[str] | None = None,
        seed: int = 0,
        max_len: int | None = None,
        batch_size: int | None = None,
        pool_batches: int = 50,
        center: bool = True,
        dtype: str = "float32",
        **changes: Any,
    ) -> None:
        super().__init__()
        if not isinstance(source, (str, os.PathLike)):
            raise TypeError(f"data.source must be a path, got {type(source).__name__} {source!r}")
        reserved = _reserved_file(source)
        if reserved is not None:
            raise ValueError(
                f"data.source={source!r} is {reserved}, reserved for evaluation (never train, tune or select "
                "on it); evaluate frozen, already trained models on it instead"
            )
        if split not in ("objects", "time"):
            raise ValueError(f"data.split must be 'objects' or 'time', got {split!r}")
        if split == "time" and not boundaries:
            raise ValueError("data.split='time' needs data.boundaries (1 or 2 ISO 8601 instants)")
        for name, value, low in (
            ("batch_size", batch_size, 1),
            ("max_len", max_len, 2),
            ("pool_batches", pool_batches, 1),
        ):
            _check_count(f"data.{name}", value, low, allow_none=name != "pool_batches")
        _check_count("data.seed", seed, None, allow_none=False)
        if isinstance(fractions, (str, bytes)) or not isinstance(fractions, Sequence):
            raise TypeError(f"data.fractions must be 3 numbers (train, val, test), got {fractions!r}")
        if dtype not in ("float32", "float64"):
            raise ValueError(f"data.dtype must be 'float32' or 'float64', got {dtype!r}")
        base = CleaningRules.coerce(rules if rules is not None else {"min_reports": 5}, **changes)
        if split == "time":  # tracks are cut at the split boundaries, so that none spans one
            cuts = [*base.cut_times, *(str(b) for b in _instants("data.boundaries", boundaries))]
            base = base.replace(cut_times=list(dict.fromkeys(cuts)))
        self.rules = base
        self.source = str(source)
        self.split = str(split)
        self.fractions = [float(f) for f in fractions]  # (checked by split_objects)
        self.boundaries = list(_instants("data.boundaries", boundaries)) if boundaries else []
        self.seed = int(seed)
        self.max_len = None if max_len is None else int(max_len)
        self.batch_size = None if batch_size is None else int(batch_size)
        self.pool_batches = int(pool_batches)
        self.center = bool(center)
        self.dtype = getattr(torch, dtype)
        # plain Python values only, so checkpoints load with torch.load(weights_only=True)
        self.save_hyperparameters(
            {
                "source": self.source,
                **self.rules.as_dict(),
                "split": self.split,
                "fractions": self.fractions,
                "boundaries": self.boundaries,
                "seed": self.seed,
                "max_len": self.max_len,
                "batch_size": self.batch_size,
                "pool_batches": self.pool_batches,
                "center": self.center,
                "dtype": str(dtype),
            }
        )
        self.tracks: Tracks | None = None
        self.splits: dict[str, Tracks] = {}
        self.windows: dict[str, list[Any]] = {}
        self.summary: DataSummary | None = None

    def setup(self, stage: str | None = None) -> None:
        """Load, clean, split and window once (deterministic, so every DDP rank agrees)."""
        if self.tracks is not None:
            return
        self.tracks = load_tracks(self.source, rules=self.rules)
        parts: Sequence[Tracks] = (
            split_objects(self.tracks, self.fractions, self.seed)
            if self.split == "objects"
            else split_time(self.tracks, self.boundaries)
        )
        self.splits = {name: part for name, part in zip(("train", "val", "test"), parts) if len(part)}
        for name in ("train", "val"):
            if name not in self.splits:
                raise ValueError(f"{self.source}: the {name} split is empty (split={self.split!r})")
        self.windows = {
            name: track_windows(part, self.max_len, self.center, self.dtype) for name, part in self.splits.items()
        }
        rows = {}
        for name, part in self.splits.items():
            batches = list(self._batch_sampler(name))
            rows[name] = {
                "objects": len(np.unique(part.object_id)),
                "tracks": len(part),
                "windows": len(self.windows[name]),
                "reports": part.num_reports,
                "batches": len(batches),
                "padding_waste": padding_waste(batches, self._lengths(name)),
            }
        self.summary = DataSummary(
            self.tracks.summary,
            self.split if self.split == "objects" else f"time at {', '.join(self.boundaries)}",
            self.max_len,
            self.batch_size,
            rows,
        )
        from lightning.fabric.utilities.rank_zero import rank_zero_only

        if getattr(rank_zero_only, "rank", 0) == 0:
            log.info("data: %s", self.summary)

    def _lengths(self, split: str) -> list[int]:
        return [int(w.dt.shape[0]) for w in self.windows[split]]

    def _batch_sampler(self, split: str) -> BucketBatchSampler:
        n = len(self.windows[split])
        train = split == "train"
        sampler = EpochShuffleSampler(n, self.seed) if train else SequentialSampler(range(n))
        size = n if self.batch_size is None else self.batch_size
        if train or self.batch_size is None:
            return BucketBatchSampler(
                sampler,
                self._lengths(split),
                max(size, 1),
                pool_batches=self.pool_batches,
                shuffle=train,
                seed=self.seed,
            )
        # evaluation: one sorted pool, batches closed early rather than padded by more than 10 %
        return BucketBatchSampler(
            sampler, self._lengths(split), size, pool_batches=max(1, math.ceil(n / size)), shuffle=False, max_waste=0.1
        )

    def _loader(self, split: str) -> DataLoader:
        if not self.windows:
            self.setup()
        if split not in self.windows:
            raise ValueError(f"no {split} split in {self.source} (split={self.split!r}, boundaries={self.boundaries})")
        return DataLoader(
            TrackDataset(self.windows[split]), batch_sampler=self._batch_sampler(split), collate_fn=collate_tracks
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader("train")

    def val_dataloader(self) -> DataLoader:
        return self._loader("val")

    def test_dataloader(self) -> DataLoader:
        return self._loader("test")
