"""What :func:`~torchsde_lti.data.load_tracks` returns: :class:`Tracks`, many tracks as flat
numpy arrays, and its :class:`LoadSummary`, what the loader read, removed and kept.

:class:`Tracks` holds everything as flat numpy arrays with per-track offsets (memory linear
in the number of reports): track i is reports ``offsets[i]:offsets[i + 1]``;
:meth:`Tracks.subset` selects tracks without a Python loop over reports. The loader and its
cleaning rules are :mod:`torchsde_lti.data.trajectories`; the splits and training windows
:mod:`torchsde_lti.data.splits`.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["LoadSummary", "Tracks"]


@dataclass(frozen=True)
class LoadSummary:
    """What :func:`load_tracks` read, removed and kept; every report read is accounted for:
    ``rows = malformed + invalid_positions + repeated_timestamps + jump_reports_dropped +
    short_reports + reports``.

    ``invalid`` counts the dropped positions by their first reason (``"lat_not_available"``,
    ``"lon_out_of_range"``, ``"lat_missing"``, ``"alt_missing"``...; its values sum to
    ``invalid_positions``); ``unavailable`` counts the speeds, courses and headings of the kept
    reports that are unavailable (NaN), by reason (``"sog_not_available"``, ``"cog_missing"``...);
    reasons with no report are left out (:data:`~torchsde_lti.data.REPORT_RULES`); ``decoded``
    counts values the reader converted from the file format's convention
    (:attr:`~torchsde_lti.data.Reports.decoded`: ``"lon_unwrapped"``).
    """

    source: str
    rows: int
    malformed: int
    malformed_examples: tuple[str, ...]
    invalid_positions: int
    repeated_timestamps: int
    time_cuts: int
    gap_splits: int
    jump_reports_dropped: int
    jump_splits: int
    extent_splits: int
    short_tracks: int
    short_reports: int
    courses_decoded: int
    objects: int
    tracks: int
    reports: int
    dims: int
    frame: str
    rules: dict[str, Any]
    invalid: dict[str, int] = dataclasses.field(default_factory=dict)
    unavailable: dict[str, int] = dataclasses.field(default_factory=dict)
    decoded: dict[str, int] = dataclasses.field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """Plain Python values (JSON-ready)."""
        out = dataclasses.asdict(self)
        out["malformed_examples"] = list(self.malformed_examples)
        return out

    def __str__(self) -> str:
        r = self.rules
        off = lambda key, text: text.format(r[key]) if r.get(key) is not None else f"{key} off"  # noqa: E731
        rows = [
            ("malformed lines / rows skipped", self.malformed),
            ("invalid positions dropped", f"{self.invalid_positions}{_reasons(self.invalid)}"),
            ("repeated timestamps dropped", self.repeated_timestamps),
            (f"cuts at split times ({len(r.get('cut_times') or ())})", self.time_cuts),
            (f"cuts at gaps: {off('max_gap', '> {} s')}", self.gap_splits),
            (f"jumps: {off('v_max', '> {} m/s')}: reports dropped", self.jump_reports_dropped),
            (f"jumps: {off('v_max', '> {} m/s')}: tracks cut", self.jump_splits),
            (f"cuts at extent: {off('max_extent', '{} m from the origin')}", self.extent_splits),
            (
                f"tracks < {r.get('min_reports')} reports dropped (reports)",
                f"{self.short_tracks} ({self.short_reports})",
            ),
        ]
        if self.unavailable:
            rows.append(("speeds / courses unavailable (reports kept)", _reasons(self.unavailable).strip(" ()")))
        if self.decoded:
            rows.append(("values decoded from the file's convention", _reasons(self.decoded).strip(" ()")))
        if self.courses_decoded:
            rows.append(("COG decoded from signed 12-bit AIS", self.courses_decoded))
        width = max(len(k) for k, _ in rows)
        lines = [f"{os.path.basename(self.source)}: {self.rows} reports read"]
        lines += [f"  {k:<{width}}  {v}" for k, v in rows]
        lines += [
            f"  kept: {self.tracks} tracks of {self.objects} objects, {self.reports} reports "
            f"({self.dims}-D, {self.frame} frame{'s' if self.frame == 'local' else ''})"
        ]
        lines += [f"  malformed, e.g.: {e}" for e in self.malformed_examples]
        return "\n".join(lines)


@dataclass(frozen=True, eq=False)
class Tracks:
    """Tracks as flat arrays: track i is reports ``offsets[i]:offsets[i + 1]``, time-sorted.

    S tracks, N reports, d = 2 (east, north) or 3 (east, north, altitude):
    object_id (S,) int64 or str; offsets (S + 1,) int64; t (N,) float64 seconds since ``t0``
    (strictly increasing within a track); pos (N, d) metres in the track's frame; lat, lon (N,)
    degrees (lon in [-180, 180)); alt (N,) metres or None; vel (N, 2) m/s east, north from
    SOG/COG (NaN where unavailable) or None; sog (N,) knots or None; origin (S, 3) the frame
    origin (lat, lon, alt) of each track; t0 datetime64[us]; frame "local" or "common";
    summary what the loader did.
    """

    object_id: np.ndarray
    offsets: np.ndarray
    t: np.ndarray
    pos: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    alt: np.ndarray | None
    vel: np.ndarray | None
    sog: np.ndarray | None
    origin: np.ndarray
    t0: np.datetime64
    frame: str
    summary: LoadSummary

    def __len__(self) -> int:
        return len(self.offsets) - 1

    @property
    def lengths(self) -> np.ndarray:
        """(S,) reports per track."""
        return np.diff(self.offsets)

    @property
    def num_reports(self) -> int:
        return int(self.offsets[-1])

    @property
    def dims(self) -> int:
        return int(self.pos.shape[-1])

    def track(self, i: int) -> dict[str, np.ndarray]:
        """Track ``i`` as views: t, pos, lat, lon (and alt, vel, sog where present)."""
        a, b = int(self.offsets[i]), int(self.offsets[i + 1])
        out = {
            k: getattr(self, k)[a:b]
            for k in ("t", "pos", "lat", "lon", "alt", "vel", "sog")
            if getattr(self, k) is not None
        }
        return out

    def subset(self, indices: Sequence[int] | np.ndarray) -> Tracks:
        """The tracks ``indices`` (in that order), same frames and summary.

        Args:
            indices: track numbers in [0, len(self)) (no negative ones, no boolean mask:
                ``np.flatnonzero(mask)`` gives the numbers of a mask).

        Raises:
            TypeError: for indices that are not integers; IndexError: for one out of range,
                naming it.
        """
        given = np.asarray(indices).reshape(-1)
        if given.size and not np.issubdtype(given.dtype, np.integer):
            raise TypeError(
                f"Tracks.subset: indices must be integers (np.flatnonzero(mask) for a mask), got {given.dtype} values"
            )
        idx = given.astype(np.int64)
        outside = (idx < 0) | (idx >= len(self))
        if outside.any():
            raise IndexError(
                f"Tracks.subset: index {int(idx[outside][0])} is out of range for {len(self)} tracks (0 to {len(self) - 1})"
            )
        lengths = self.lengths[idx]
        offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        rows = _ranges(self.offsets[idx], lengths)
        per_report: dict[str, Any] = {
            k: (None if getattr(self, k) is None else getattr(self, k)[rows])
            for k in ("t", "pos", "lat", "lon", "alt", "vel", "sog")
        }
        return dataclasses.replace(
            self, object_id=self.object_id[idx], offsets=offsets, origin=self.origin[idx], **per_report
        )


def _reasons(counts: dict[str, int]) -> str:
    """' (name n, name n)' for the summary's text, '' for none."""
    return f" ({', '.join(f'{name} {n}' for name, n in counts.items())})" if counts else ""


def _ranges(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Concatenated aranges [starts[i], starts[i] + lengths[i]) without a Python loop."""
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    seg = np.repeat(np.arange(len(lengths)), lengths)
    first = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    return (np.asarray(starts, dtype=np.int64)[seg] + np.arange(total) - first[seg]).astype(np.int64)
