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
from typing import NamedTuple

import torch
from torch import Tensor
from torch.utils.data import Dataset, Sampler

__all__ = ["EpochShuffleSampler", "Track", "TrackBatch", "TrackDataset", "collate_tracks", "pad_tracks", "unpad_tracks"]


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


_TRACK_FIELDS = [(f, TrackBatch.__annotations__[f]) for f in TrackBatch._fields if f not in ("mask", "lengths")]
#: One track of T steps: the fields of :class:`TrackBatch` without the batch dimension and
#: without ``mask`` / ``lengths`` (y (T, m) and dt (T,) required; ``origin`` (m,) and
#: ``track_id`` () are per-track; the rest optional, default None).
Track = NamedTuple("Track", _TRACK_FIELDS)  # type: ignore[misc]
Track.__new__.__defaults__ = (None,) * (len(_TRACK_FIELDS) - 2)


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
    """``collate_fn`` for a DataLoader over a :class:`TrackDataset`: pads to the longest track
    of the batch."""
    return pad_tracks(items)


def unpad_tracks(batch: TrackBatch) -> list[Track]:
    """The tracks of a padded batch, each cut to its length (inverse of :func:`pad_tracks`)."""
    out = []
    for i, Ti in enumerate(batch.lengths.tolist()):
        values = {}
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
