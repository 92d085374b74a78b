r"""Tracks and batches of tracks (torch only): ONE track type, ONE batch type, ONE pad/collate.

Simulated tracks and real (AIS) tracks go through the same pipeline::

    Track (one track, T_i steps)  --pad_tracks / collate_tracks-->  TrackBatch (B, T)
    TrackDataset(list of Track)   --DataLoader(collate_fn=collate_tracks)-->  TrackBatch

:class:`TrackBatch` is what :class:`~torchsde_lti.training.module.KalmanFilterModule`
consumes and what any other data module must yield:

    y       (B, T, m)  observations; NaN = missing (a whole row, or single coordinates)
    dt      (B, T)     step lengths; dt[:, 0] is the time from t0 to the first observation
    mask    (B, T)     bool, True on real steps, False on padding
    lengths (B,)       int64 number of real steps
    u       (B, T, p)  optional control inputs, held over the step that ends at t_k
    x       (B, T, n)  optional true states (simulated data)
    t       (B, T)     optional observation times
    vel     (B, T, d)  optional measured velocity (AIS SOG/COG; NaN where unavailable)
    sog     (B, T)     optional reported speed (AIS, knots)
    origin  (B, m)     optional offset subtracted from y (per-track centring)
    track_id (B,)      optional int64 track identifier (AIS: MMSI)

Padding: a padded step has ``dt = 0`` (so A = I, Qd = 0, G = 0: the state does not move),
``y = NaN`` (no update, no log-likelihood term), ``u = 0``, ``x`` and ``t`` held at their
last value, ``vel = NaN``, ``sog = 0``. A Kalman filter therefore carries its last filtered
state through the padding unchanged and the padding contributes exactly nothing to the
likelihood, whether or not ``mask`` is passed on.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor
from torch.utils.data import BatchSampler, Dataset, Sampler

__all__ = [
    "BucketBatchSampler",
    "EpochShuffleSampler",
    "Track",
    "TrackBatch",
    "TrackDataset",
    "collate_tracks",
    "pad_tracks",
    "padding_waste",
    "unpad_tracks",
]


class TrackBatch(NamedTuple):
    """A padded batch of B tracks; fields and padding in the module docstring."""

    y: Tensor
    dt: Tensor
    mask: Tensor
    lengths: Tensor
    u: Tensor | None = None
    x: Tensor | None = None
    t: Tensor | None = None
    vel: Tensor | None = None
    sog: Tensor | None = None
    origin: Tensor | None = None
    track_id: Tensor | None = None


class Track(NamedTuple):
    """One track of T steps: the fields of :class:`TrackBatch` without the batch dimension and
    without ``mask`` / ``lengths`` (y (T, m) and dt (T,) required; ``origin`` (m,) and
    ``track_id`` () are per-track; the rest optional, default None)."""

    y: Tensor
    dt: Tensor
    u: Tensor | None = None
    x: Tensor | None = None
    t: Tensor | None = None
    vel: Tensor | None = None
    sog: Tensor | None = None
    origin: Tensor | None = None
    track_id: Tensor | None = None


# Per-step fields and their padding rule: a fill value, or None = repeat the last value.
_PAD: dict[str, float | None] = {"y": math.nan, "dt": 0.0, "u": 0.0, "x": None, "t": None, "vel": math.nan, "sog": 0.0}


def _pad_field(x: Tensor, pad: int, fill: float | None) -> Tensor:
    if pad == 0:
        return x
    if fill is None:
        tail = x[-1:].expand(pad, *x.shape[1:])
    else:
        tail = x.new_full((pad, *x.shape[1:]), fill)
    return torch.cat([x, tail])


def pad_tracks(tracks: Sequence[Track], length: int | None = None) -> TrackBatch:
    """Pad variable-length tracks into one :class:`TrackBatch`.

    Args:
        tracks: :class:`Track` s, each with y (T_i, m) and dt (T_i,); optional fields must be
            given for all tracks or none.
        length: T of the batch (default: the longest track); ValueError if a track is longer.
    """
    if len(tracks) == 0:
        raise ValueError("tracks must not be empty")
    lengths = [int(tr.dt.shape[0]) for tr in tracks]
    T = max(lengths) if length is None else int(length)
    fields: dict[str, list[Tensor]] = {}
    for i, (tr, Ti) in enumerate(zip(tracks, lengths)):
        if Ti > T or tr.y.shape[0] != Ti:
            raise ValueError(f"track {i}: y {tuple(tr.y.shape)} and dt {tuple(tr.dt.shape)} must share T <= {T}")
        for name, value in tr._asdict().items():
            if (value is None) != (name not in fields) and i > 0:
                raise ValueError(f"track {i}: field {name!r} must be given for all tracks or none")
            if value is None:
                continue
            per_step = name in _PAD
            fields.setdefault(name, []).append(_pad_field(value, T - Ti, _PAD[name]) if per_step else value)
    batch = {k: torch.stack(v) for k, v in fields.items()}
    steps = torch.arange(T)
    lengths_t = torch.tensor(lengths, dtype=torch.int64)
    return TrackBatch(mask=steps < lengths_t.unsqueeze(1), lengths=lengths_t, **batch)


def collate_tracks(items: Sequence[Track]) -> TrackBatch:
    """``collate_fn`` for a DataLoader over a :class:`TrackDataset`: pads to the longest track.

    Args:
        items: the batch's tracks (y (T_i, m), dt (T_i,), optional per-step fields).

    Returns:
        TrackBatch: y (B, T, m) NaN-padded, dt (B, T) 0-padded, mask (B, T), lengths (B,).
    """
    return pad_tracks(items)


def unpad_tracks(batch: TrackBatch) -> list[Track]:
    """The tracks of a padded batch, each cut to its length (inverse of :func:`pad_tracks`).

    Args:
        batch: a padded :class:`TrackBatch` of B tracks.

    Returns:
        list[Track]: B tracks, track i with ``lengths[i]`` steps.
    """
    out = []
    for i, Ti in enumerate(batch.lengths.tolist()):
        values: dict[str, Any] = {}
        for name in Track._fields:
            v = getattr(batch, name)
            values[name] = None if v is None else (v[i, :Ti] if name in _PAD else v[i])
        out.append(Track(**values))
    return out


class TrackDataset(Dataset):
    """A list of :class:`Track` s; item i is track i (collate with :func:`collate_tracks`)."""

    def __init__(self, tracks: Sequence[Track]) -> None:
        self.tracks = list(tracks)

    def __len__(self) -> int:
        return len(self.tracks)

    def __getitem__(self, i: int) -> Track:
        return self.tracks[i]


class EpochShuffleSampler(Sampler[int]):
    """Random permutation that depends only on (seed, epoch), so a resumed run sees the
    same batches as an uninterrupted one (Lightning calls ``set_epoch`` every epoch)."""

    def __init__(self, n: int, seed: int = 0) -> None:
        self.n, self.seed, self.epoch = int(n), int(seed), 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __iter__(self) -> Iterator[int]:
        g = torch.Generator().manual_seed(self.seed * 100_003 + self.epoch)
        return iter(torch.randperm(self.n, generator=g).tolist())

    def __len__(self) -> int:
        return self.n


class BucketBatchSampler(BatchSampler):
    """Batches of similar-length tracks, so that padding wastes little.

    Indices drawn from ``sampler`` are taken ``pool_batches * batch_size`` at a time, sorted
    by ``lengths`` and cut into batches of ``batch_size``; with ``shuffle`` the batches of a
    pool are emitted in an order seeded by (``seed``, the sampler's ``epoch``). With
    ``max_waste`` a batch is also closed early when the next (longer) item would make more than
    that share of its steps padding: every batch then wastes at most ``max_waste``, at the price
    of a data-dependent number of batches (for evaluation; training under DDP needs the same
    number of batches on every process, so keep it None there). Under DDP
    Lightning rebuilds this sampler around its distributed sampler (the ``sampler``
    argument), so each process buckets its own shard of tracks; the order stays a function of
    (seed, epoch), so a resumed run sees the same batches.

    Args:
        sampler: yields dataset indices (e.g. :class:`EpochShuffleSampler`).
        lengths: (N,) length of every dataset item.
        batch_size: items per batch; drop_last: drop a pool's last, smaller batch.
        pool_batches: batches per sorted pool (larger: less padding, less randomness).
        shuffle: emit each pool's batches in a seeded random order; seed: its seed.
        max_waste: cap on each batch's padding share (None = fixed batch sizes).
    """

    def __init__(
        self,
        sampler: Sampler[int] | Sequence[int],
        lengths: Sequence[int],
        batch_size: int,
        drop_last: bool = False,
        pool_batches: int = 50,
        shuffle: bool = True,
        seed: int = 0,
        max_waste: float | None = None,
    ) -> None:
        super().__init__(sampler, int(batch_size), bool(drop_last))
        if int(pool_batches) < 1:
            raise ValueError(f"pool_batches must be >= 1, got {pool_batches}")
        if max_waste is not None and not 0.0 <= float(max_waste) < 1.0:
            raise ValueError(f"max_waste must be in [0, 1) or None, got {max_waste}")
        self.lengths = torch.as_tensor(lengths, dtype=torch.int64)
        self.pool_batches, self.shuffle, self.seed = int(pool_batches), bool(shuffle), int(seed)
        self.max_waste = None if max_waste is None else float(max_waste)

    def _cut(self, items: list[int]) -> list[list[int]]:
        """Length-sorted items -> batches of <= batch_size (and <= max_waste padding)."""
        if self.max_waste is None:
            return [items[i : i + self.batch_size] for i in range(0, len(items), self.batch_size)]
        lengths = self.lengths[items].tolist()
        batches: list[list[int]] = []
        cur: list[int] = []
        used = 0
        for item, n in zip(items, lengths):
            if cur and (len(cur) == self.batch_size or used + n < (1.0 - self.max_waste) * (len(cur) + 1) * n):
                batches.append(cur)
                cur, used = [], 0
            cur.append(item)
            used += n
        return batches + ([cur] if cur else [])

    def _emit(self, pool: list[int], g: torch.Generator) -> list[list[int]]:
        order = torch.argsort(self.lengths[pool], stable=True).tolist()
        batches = self._cut([pool[k] for k in order])
        if self.drop_last and batches and len(batches[-1]) < self.batch_size:
            batches.pop()
        if self.shuffle:
            batches = [batches[k] for k in torch.randperm(len(batches), generator=g).tolist()]
        return batches

    def __iter__(self) -> Iterator[list[int]]:
        epoch = int(getattr(self.sampler, "epoch", 0))
        g = torch.Generator().manual_seed(self.seed * 100_003 + epoch + 1)
        size = self.pool_batches * self.batch_size
        pool: list[int] = []
        for idx in self.sampler:
            pool.append(int(idx))
            if len(pool) == size:
                yield from self._emit(pool, g)
                pool = []
        if pool:
            yield from self._emit(pool, g)

    def __len__(self) -> int:
        if self.max_waste is not None:
            return sum(1 for _ in self)
        n = len(self.sampler)  # type: ignore[arg-type]
        full, rest = divmod(n, self.pool_batches * self.batch_size)
        tail = rest // self.batch_size if self.drop_last else math.ceil(rest / self.batch_size)
        return full * self.pool_batches + tail


def padding_waste(batches: Sequence[Sequence[int]], lengths: Sequence[int]) -> float:
    """Share of padded steps: 1 - Σ lengths / Σ (batch size x longest item), over ``batches``.

    Args:
        batches: each batch as the indices of its items.
        lengths: the length of every item.

    Returns:
        float: in [0, 1); 0 for no batches.
    """
    lengths_t = torch.as_tensor(lengths, dtype=torch.int64)
    used = padded = 0
    for b in batches:
        ls = lengths_t[list(b)]
        used += int(ls.sum())
        padded += len(b) * int(ls.max()) if len(b) else 0
    return 1.0 - used / padded if padded else 0.0
