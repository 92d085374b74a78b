"""Streaming the windows of a prepared dataset (:mod:`torchsde_lti.data.prepare`) in batches,
split by DDP rank and DataLoader worker, shuffled within a buffer, resumable mid-epoch (torch only).

    stream = WindowStream("prepared/", "train", batch_size=64, seed=0)
    loader = DataLoader(stream, batch_size=None, num_workers=2)    # TrackBatch es
    stream.set_position(epoch=3, skip=120)                         # resume: the next batch is batch 120 of epoch 3

What an epoch is: a plan computed from the dataset's metadata alone (the files' row groups and
two small columns, ``object_id`` and ``length``, read once), the same in every process:

1. the split: an object's windows all go to one split, by a seeded hash of its id
   (``u = hash(seed, id) in [0, 1)``: train below ``fractions[0]``, val below
   ``fractions[0] + fractions[1]``, test above), so the shares are those of the objects on
   average, not exactly;
2. the units (Parquet row groups, ``row_group_windows`` windows each) in a seeded random order
   (seed, epoch), their windows of the split in file order within a unit; with ``shuffle``, the
   windows are then shuffled within consecutive blocks of ``buffer_windows`` (a shuffle buffer);
3. the rank's share: rank r of R takes the r-th of R equal, contiguous parts (training: every
   rank ``N // R`` windows, the ``N mod R`` left over are not seen in that epoch; evaluation:
   parts differ by at most one window, every window seen once);
4. batches: :class:`~torchsde_lti.data.tracks.BucketBatchSampler` over the rank's windows (pools
   of ``pool_batches`` batches sorted by length, the batches of a pool in a seeded order), so
   every rank has the same number of batches;
5. workers: batch j of the rank (counting from the resume point ``skip``) is made by DataLoader
   worker ``(j - skip) mod K``; PyTorch's DataLoader takes batches from its workers in turn, so
   the batches arrive in plan order, whatever K.

A resumed epoch (:meth:`WindowStream.set_position`) starts at batch ``skip`` of the same plan:
every window of the epoch is seen exactly once, in the same order as without the interruption.
Memory per worker: the decoded row groups that the pool being made spans (about
``buffer_windows + batch_size * pool_batches`` windows), plus the metadata (12 bytes a window).

A batch is a :class:`~torchsde_lti.data.tracks.TrackBatch` made by
:func:`~torchsde_lti.data.tracks.collate_tracks` from :class:`~torchsde_lti.data.tracks.Track` s
as :func:`~torchsde_lti.data.track_windows` makes them: ``y`` positions (m) in the track's frame,
minus the window's first one with ``center`` (kept in ``origin``), ``dt`` seconds from the
previous report (0 first), ``t`` seconds since the window's first report, ``vel`` / ``sog``
where the data have them, and ``track_id`` the window's row in the dataset (:meth:`object_id`
gives its object).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import IterableDataset, Sampler, get_worker_info

from torchsde_lti.data.tracks import BucketBatchSampler, Track, TrackBatch, collate_tracks

__all__ = ["SPLITS", "WindowStream", "object_split"]

SPLITS = ("train", "val", "test")
_PER_STEP = ("time", "east", "north", "up", "vel_east", "vel_north", "sog")


def object_split(object_id: np.ndarray, fractions: Sequence[float], seed: int) -> np.ndarray:
    """(N,) int8 split of each object id: 0 train, 1 val, 2 test, by a seeded hash in [0, 1).

    Args:
        object_id: (N,) int64 ids (MMSI) or strings.
        fractions: (train, val, test) shares, non-negative, summing to 1.
        seed: the hash's seed (another seed, another split).

    Returns:
        ndarray: (N,) int8.
    """
    f = [float(x) for x in fractions]
    if len(f) != 3 or any(x < 0 for x in f) or not math.isclose(sum(f), 1.0):
        raise ValueError(f"fractions must be 3 non-negative numbers summing to 1, got {list(fractions)}")
    ids = np.asarray(object_id)
    if ids.dtype.kind in "iu":  # splitmix64 of (id + seed), in uint64 arithmetic (wraps)
        with np.errstate(over="ignore"):
            z = ids.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15) * np.uint64(int(seed) + 1)
            z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            z = z ^ (z >> np.uint64(31))
        u = (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)
    else:
        uniq, inverse = np.unique(ids.astype(str), return_inverse=True)
        codes = np.array([zlib.crc32(f"{seed}:{s}".encode()) for s in uniq.tolist()], dtype=np.float64)
        u = (codes / float(1 << 32))[inverse]
    return np.where(u < f[0], 0, np.where(u < f[0] + f[1], 1, 2)).astype(np.int8)


class _Positions(Sampler[int]):
    """0, 1, ..., n - 1 with an ``epoch`` (what BucketBatchSampler reads from its sampler)."""

    def __init__(self, n: int, epoch: int) -> None:
        self.n, self.epoch = n, epoch

    def __iter__(self) -> Iterator[int]:
        return iter(range(self.n))

    def __len__(self) -> int:
        return self.n


class WindowStream(IterableDataset):
    """The windows of one split of a prepared dataset, as batches (the module docstring).

    Args:
        root: the prepared dataset's folder (``prepare_dataset``'s ``out``).
        split: "train", "val" or "test".
        fractions: (train, val, test) shares of the objects; seed: the split's and the order's seed.
        batch_size: windows per batch; pool_batches: batches per length-sorted pool.
        buffer_windows: the shuffle buffer (windows shuffled within consecutive blocks of it).
        shuffle: a new order every epoch (training); False: file order, no shuffling (evaluation).
        center: subtract each window's first position (kept in ``origin``).
        dtype: of the batches' floating tensors.
        rank, world_size: this process's DDP rank and the number of processes.
        even: every rank the same number of windows (training under DDP: equal batch counts);
            False: every window once (ranks differ by at most one window).

    Raises:
        FileNotFoundError: no prepared windows under ``root``.
        ValueError: bad arguments (naming them), or a split without windows.
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "train",
        *,
        fractions: Sequence[float] = (0.6, 0.2, 0.2),
        seed: int = 0,
        batch_size: int = 64,
        pool_batches: int = 50,
        buffer_windows: int = 4096,
        shuffle: bool = True,
        center: bool = True,
        dtype: torch.dtype = torch.float32,
        rank: int = 0,
        world_size: int = 1,
        even: bool = True,
    ) -> None:
        import pyarrow.parquet as pq

        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        for name, value in (
            ("batch_size", batch_size),
            ("pool_batches", pool_batches),
            ("buffer_windows", buffer_windows),
        ):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if not 0 <= int(rank) < int(world_size):
            raise ValueError(f"rank must be in [0, world_size = {world_size}), got {rank}")
        self.root = Path(root)
        self.files = sorted((self.root / "windows").glob("*.parquet"))
        if not self.files:
            raise FileNotFoundError(
                f"no prepared windows under {self.root / 'windows'}: run python -m torchsde_lti.prepare"
            )
        self.split, self.seed, self.shuffle, self.center, self.dtype = (
            split,
            int(seed),
            bool(shuffle),
            bool(center),
            dtype,
        )
        self.batch_size, self.pool_batches, self.buffer_windows = batch_size, pool_batches, buffer_windows
        self.rank, self.world_size, self.even = int(rank), int(world_size), bool(even)
        self.epoch, self.skip = 0, 0
        # metadata: units (file, row group) and per window its unit, split and length
        units, ids, lengths = [], [], []
        for i, path in enumerate(self.files):
            meta = pq.ParquetFile(path)
            for g in range(meta.num_row_groups):
                units.append((i, g, meta.metadata.row_group(g).num_rows))
            table = meta.read(columns=["object_id", "length"])
            ids.append(table["object_id"].to_numpy())
            lengths.append(table["length"].to_numpy().astype(np.int32))
        counts = np.array([n for _, _, n in units], dtype=np.int64)
        self.units = [(i, g) for i, g, _ in units]
        self.unit_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.unit_of = np.repeat(np.arange(len(units)), counts)
        object_id = (
            np.concatenate(ids)
            if all(a.dtype.kind in "iu" for a in ids)
            else np.concatenate([a.astype(str) for a in ids])
        )
        self.lengths = np.concatenate(lengths)
        self.member = np.flatnonzero(object_split(object_id, fractions, seed) == SPLITS.index(split))
        self._object_ids = object_id
        if len(self.member) < self.world_size:
            raise ValueError(
                f"{self.root}: the {split} split has {len(self.member)} windows, fewer than world_size = {self.world_size}"
            )

    # ------------------------------------------------------------------ the plan
    def set_position(self, epoch: int, skip: int = 0) -> None:
        """Iterate epoch ``epoch`` from its batch ``skip`` (a resumed epoch), in every worker."""
        if int(skip) < 0:
            raise ValueError(f"skip must be >= 0, got {skip}")
        self.epoch, self.skip = int(epoch), int(skip)

    def object_id(self, window: int | np.ndarray) -> Any:
        """The object (MMSI) of window(s) ``window`` (``TrackBatch.track_id``)."""
        return self._object_ids[window]

    def _rank_windows(self, epoch: int) -> np.ndarray:
        """Steps 2 and 3 of the module docstring: this rank's windows (dataset rows), in order."""
        g = np.random.default_rng([self.seed, epoch])
        unit_rank = np.empty(len(self.units), dtype=np.int64)
        unit_rank[g.permutation(len(self.units)) if self.shuffle else np.arange(len(self.units))] = np.arange(
            len(self.units)
        )
        order = self.member[np.argsort(unit_rank[self.unit_of[self.member]], kind="stable")]
        if self.shuffle:
            block = np.arange(len(order)) // self.buffer_windows
            order = order[np.lexsort((g.random(len(order)), block))]
        n, r, w = len(order), self.rank, self.world_size
        if self.even:
            share = n // w
            return order[r * share : (r + 1) * share]
        return order[r * n // w : (r + 1) * n // w]

    def _sampler(self, epoch: int) -> tuple[np.ndarray, BucketBatchSampler]:
        """Step 4: this rank's windows and the batch sampler over their positions."""
        rows = self._rank_windows(epoch)
        sampler = BucketBatchSampler(
            _Positions(len(rows), epoch), self.lengths[rows].tolist(), self.batch_size,
            pool_batches=self.pool_batches, shuffle=self.shuffle, seed=self.seed,
        )  # fmt: skip
        return rows, sampler

    def batches(self, epoch: int | None = None) -> list[np.ndarray]:
        """This rank's batches of epoch ``epoch`` (default: the set one), each (B,) dataset rows."""
        rows, sampler = self._sampler(self.epoch if epoch is None else int(epoch))
        return [rows[np.asarray(b, dtype=np.int64)] for b in sampler]

    def __len__(self) -> int:
        """Batches of this rank in an epoch (the same every epoch)."""
        return len(self._sampler(self.epoch)[1])

    # ------------------------------------------------------------------ reading
    def __iter__(self) -> Iterator[TrackBatch]:
        info = get_worker_info()
        workers, me = (info.num_workers, info.id) if info is not None else (1, 0)
        plan = self.batches()
        mine = [j for j in range(self.skip, len(plan)) if (j - self.skip) % workers == me]
        last_use: dict[int, int] = {}
        for j in mine:
            for u in np.unique(self.unit_of[plan[j]]).tolist():
                last_use[u] = j
        cache: dict[int, dict[str, np.ndarray]] = {}
        for j in mine:
            tracks = []
            for row in plan[j].tolist():
                u = int(self.unit_of[row])
                if u not in cache:
                    cache[u] = self._read_unit(u)
                tracks.append(self._track(cache[u], row - int(self.unit_start[u]), row))
            for u in [u for u in cache if last_use[u] <= j]:
                del cache[u]
            yield collate_tracks(tracks)

    def _read_unit(self, u: int) -> dict[str, np.ndarray]:
        """A row group's per-step columns, flat, with ``offsets`` (windows + 1,)."""
        import pyarrow.parquet as pq

        i, g = self.units[u]
        source = pq.ParquetFile(self.files[i])
        names = [c for c in _PER_STEP if c in source.schema_arrow.names]
        table = source.read_row_group(g, columns=names)
        out = {}
        for name in names:
            col = table[name].combine_chunks()
            out[name] = col.values.to_numpy(zero_copy_only=False)
            out["offsets"] = col.offsets.to_numpy().astype(np.int64) - int(col.offsets[0].as_py())
        return out

    def _track(self, unit: dict[str, np.ndarray], k: int, row: int) -> Track:
        a, b = int(unit["offsets"][k]), int(unit["offsets"][k + 1])
        time = unit["time"][a:b]
        pos = np.stack([unit[c][a:b] for c in ("east", "north", "up") if c in unit], axis=-1)
        origin = pos[0] if self.center else np.zeros_like(pos[0])
        dt = np.diff(time, prepend=time[0]) / 1e6
        as_t = lambda x: torch.tensor(x, dtype=torch.float64).to(self.dtype)  # noqa: E731
        vel = np.stack([unit["vel_east"][a:b], unit["vel_north"][a:b]], axis=-1) if "vel_east" in unit else None
        return Track(
            y=as_t(pos - origin),
            dt=as_t(dt),
            t=as_t((time - time[0]) / 1e6),
            vel=None if vel is None else as_t(vel),
            sog=as_t(unit["sog"][a:b]) if "sog" in unit else None,
            origin=as_t(origin),
            track_id=torch.tensor(row, dtype=torch.int64),
        )
