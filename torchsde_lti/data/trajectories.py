"""Trajectories from any file: cleaning rules that count what they remove, per-track metric frames.

:func:`load_tracks` = :func:`~torchsde_lti.data.sources.read_reports` (parse, count malformed
lines) + :func:`prepare_tracks`, whose rules run in this order, each counted in
:class:`LoadSummary`:

1. reports without a valid position (non-finite, |lat| > 90; 3-D: no finite altitude) are dropped;
2. reports are grouped by object id (and, for ``.traj`` files, by the file's own trajectory)
   and sorted by time; a report repeating its predecessor's timestamp is dropped (first kept);
3. a track is cut at every ``cut_times`` instant (a split in time) and at every gap longer
   than ``max_gap`` seconds;
4. implausible jumps: a report whose implied speed from the last kept report exceeds
   ``v_max`` (m/s, great-circle distance) is dropped when the next report is consistent with
   the last kept one (a lone outlier), else the track is cut there (a teleport, or two
   transmitters sharing an id);
5. a track is cut where it leaves the disc of radius ``max_extent`` around its own origin
   (``frame="local"``: keeps the tangent-plane distortion below ``max_extent² / 2R²``,
   7.7e-4 at 250 km);
6. tracks with fewer than ``min_reports`` reports are dropped.

Positions are metres in each track's own east/north(/altitude) frame with the origin at its
first report (``frame="local"``, :mod:`torchsde_lti.data.frames`), or in one fixed frame at
``reference`` (``frame="common"``). Speed over ground (knots) and course over ground become
a velocity (m/s) in the same frame. Times are seconds since the file's first report.

:class:`Tracks` holds everything as flat numpy arrays with per-track offsets (memory linear
in the number of reports); :func:`split_objects` / :func:`split_time` divide it,
:func:`track_windows` cuts it into :class:`~torchsde_lti.data.tracks.Track` windows of at most
``max_len`` reports for training.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torchsde_lti.data.frames import EARTH_MEAN_RADIUS, KNOT, angular_distance, local_positions, local_velocities
from torchsde_lti.data.sources import Reports, read_reports
from torchsde_lti.data.tracks import Track

__all__ = [
    "LoadSummary",
    "Tracks",
    "load_tracks",
    "prepare_tracks",
    "split_objects",
    "split_time",
    "track_windows",
    "window_bounds",
]

_COURSE_ENCODINGS = ("ais", "ais_int12", "degrees")


@dataclass(frozen=True)
class LoadSummary:
    """What :func:`load_tracks` read, removed and kept; every report read is accounted for:
    ``rows = malformed + invalid_positions + repeated_timestamps + jump_reports_dropped +
    short_reports + reports``."""

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
            ("invalid positions dropped", self.invalid_positions),
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
        """The tracks ``indices`` (in that order), same frames and summary."""
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        lengths = self.lengths[idx]
        offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        rows = _ranges(self.offsets[idx], lengths)
        per_report = {
            k: (None if getattr(self, k) is None else getattr(self, k)[rows])
            for k in ("t", "pos", "lat", "lon", "alt", "vel", "sog")
        }
        return dataclasses.replace(
            self, object_id=self.object_id[idx], offsets=offsets, origin=self.origin[idx], **per_report
        )


def _ranges(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Concatenated aranges [starts[i], starts[i] + lengths[i]) without a Python loop."""
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    seg = np.repeat(np.arange(len(lengths)), lengths)
    first = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    return (np.asarray(starts, dtype=np.int64)[seg] + np.arange(total) - first[seg]).astype(np.int64)


def load_tracks(
    source: str | os.PathLike[str],
    columns: Mapping[str, str | int] | str | None = None,
    *,
    format: str | None = None,
    time_format: str | None = None,
    altitude_unit: str = "m",
    dims: int | None = None,
    frame: str = "local",
    reference: Sequence[float] | None = None,
    course_encoding: str = "ais",
    max_gap: float | None = 1800.0,
    v_max: float | None = None,
    min_reports: int = 2,
    max_extent: float | None = 250_000.0,
    cut_times: Sequence[str | np.datetime64] = (),
) -> Tracks:
    """Tracks from a ``.traj``, CSV or Parquet file, in per-track local metric frames.

    Args:
        source: a path, or a file name shipped by tracktable-data (e.g.
            ``"US_coastal_2020_06_30.traj"``); FileNotFoundError says where it looked.
        columns: CSV / Parquet role -> column (header name or 0-based position): id, time, lat,
            lon and optionally alt, sog, cog; None recognises the MarineCadastre AIS header.
        format: "traj", "csv" or "parquet" (default: the suffix).
        time_format: strptime format when times are not ISO 8601.
        altitude_unit: "m" or "ft".
        dims: 2 or 3 (east, north, altitude); None = 3 when the file has a non-zero altitude.
        frame: "local" (each track's own origin, its first report) or "common" (``reference``).
        reference: (lat, lon[, alt]) of the common frame.
        course_encoding: SOG/COG conventions: "ais" (SOG >= 102.3 kn and COG outside [0, 360)
            unavailable), "ais_int12" (also decodes a COG stored as a signed 12-bit field:
            negative v -> v + 409.6), "degrees" (any COG, taken modulo 360).
        max_gap: cut tracks at gaps longer than this (s); None = never.
        v_max: implied speed (m/s) above which a jump is implausible; None = no check.
        min_reports: drop tracks with fewer reports (>= 2).
        max_extent: cut tracks leaving this radius (m) around their origin (local frames only);
            None = never.
        cut_times: instants (ISO 8601 strings or datetime64) at which every track is cut, so
            that a split in time keeps each part in its own frame.

    Returns:
        :class:`Tracks`, with ``.summary`` (:class:`LoadSummary`) counting every rule.
    """
    reports = read_reports(source, columns, format=format, time_format=time_format, altitude_unit=altitude_unit)
    return prepare_tracks(
        reports,
        dims=dims,
        frame=frame,
        reference=reference,
        course_encoding=course_encoding,
        max_gap=max_gap,
        v_max=v_max,
        min_reports=min_reports,
        max_extent=max_extent,
        cut_times=cut_times,
    )


def _check_rules(
    frame: str,
    reference: Sequence[float] | None,
    course_encoding: str,
    max_gap: float | None,
    v_max: float | None,
    min_reports: int,
    max_extent: float | None,
    dims: int | None,
) -> None:
    if frame not in ("local", "common"):
        raise ValueError(f"frame must be 'local' or 'common', got {frame!r}")
    if frame == "common" and (reference is None or len(reference) not in (2, 3)):
        raise ValueError(f"frame='common' needs reference=(lat, lon[, alt]), got {reference!r}")
    if course_encoding not in _COURSE_ENCODINGS:
        raise ValueError(f"course_encoding must be one of {_COURSE_ENCODINGS}, got {course_encoding!r}")
    for name, value in (("max_gap", max_gap), ("v_max", v_max), ("max_extent", max_extent)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number or None, got {value!r}")
    if int(min_reports) < 2:
        raise ValueError(f"min_reports must be >= 2 (a track needs a time step), got {min_reports}")
    if dims not in (None, 2, 3):
        raise ValueError(f"dims must be 2, 3 or None, got {dims!r}")


def prepare_tracks(
    reports: Reports,
    *,
    dims: int | None = None,
    frame: str = "local",
    reference: Sequence[float] | None = None,
    course_encoding: str = "ais",
    max_gap: float | None = 1800.0,
    v_max: float | None = None,
    min_reports: int = 2,
    max_extent: float | None = 250_000.0,
    cut_times: Sequence[str | np.datetime64] = (),
) -> Tracks:
    """The cleaning rules and frames of :func:`load_tracks` applied to already-read :class:`Reports`.

    Args:
        reports: the reports of one file (:func:`~torchsde_lti.data.read_reports`).
        dims, frame, reference, course_encoding, max_gap, v_max, min_reports, max_extent, cut_times:
            as in :func:`load_tracks`.

    Returns:
        Tracks: with ``.summary`` counting every rule.
    """
    _check_rules(frame, reference, course_encoding, max_gap, v_max, min_reports, max_extent, dims)
    rep = reports
    has_alt = rep.alt is not None and bool(np.any(np.isfinite(rep.alt) & (rep.alt != 0)))
    if dims is None:
        dims = 3 if has_alt else 2
    if dims == 3 and rep.alt is None:
        raise ValueError(f"dims=3 needs an altitude column, and {rep.path} has none")
    counts = dict.fromkeys(
        (
            "invalid_positions",
            "repeated_timestamps",
            "time_cuts",
            "gap_splits",
            "jump_reports_dropped",
            "jump_splits",
            "extent_splits",
            "short_tracks",
            "short_reports",
            "courses_decoded",
        ),
        0,
    )

    # 1. valid positions
    valid = np.isfinite(rep.lat) & np.isfinite(rep.lon) & (np.abs(rep.lat) <= 90.0)
    if dims == 3:
        valid &= np.isfinite(rep.alt)
    counts["invalid_positions"] = int((~valid).sum())
    idx = np.flatnonzero(valid)
    if len(idx) == 0:
        raise ValueError(f"{rep.path}: no report has a valid position ({rep.rows} read)")

    # 2. group by (object, file segment), sort by time (stable: equal times keep file order)
    uniq, codes = np.unique(rep.object_id[idx], return_inverse=True)
    seg = rep.segment[idx] if rep.segment is not None else np.zeros(len(idx), dtype=np.int64)
    tus = rep.time[idx].astype("datetime64[us]").astype(np.int64)
    order = np.lexsort((tus, seg, codes))
    idx, codes, seg, tus = idx[order], codes[order], seg[order], tus[order]
    same = np.concatenate([[False], (codes[1:] == codes[:-1]) & (seg[1:] == seg[:-1])])
    repeated = same & np.concatenate([[False], tus[1:] == tus[:-1]])
    counts["repeated_timestamps"] = int(repeated.sum())
    keep = ~repeated
    idx, codes, tus, same = idx[keep], codes[keep], tus[keep], same[keep]
    same = np.concatenate([[False], (codes[1:] == codes[:-1]) & same[1:]])  # neighbours after the drop

    t0_us = int(tus.min())
    t = (tus - t0_us) / 1e6
    lat, lon = rep.lat[idx], ((rep.lon[idx] + 180.0) % 360.0) - 180.0
    start = ~same

    # 3. cuts at split times and at long gaps
    cuts = np.sort(np.array([(np.datetime64(c, "us").astype(np.int64) - t0_us) / 1e6 for c in cut_times]))
    if len(cuts):
        bins = np.searchsorted(cuts, t, side="right")
        crossing = same & np.concatenate([[False], bins[1:] != bins[:-1]])
        counts["time_cuts"] = int(crossing.sum())
        start |= crossing
    if max_gap is not None:
        gap = ~start & np.concatenate([[False], np.diff(t) > max_gap])
        counts["gap_splits"] = int(gap.sum())
        start |= gap

    # 4. implausible jumps
    if v_max is not None:
        keep, start, dropped, splits = _reject_jumps(t, lat, lon, start, float(v_max))
        counts["jump_reports_dropped"], counts["jump_splits"] = dropped, splits
        idx, t, lat, lon, start = idx[keep], t[keep], lat[keep], lon[keep], start[keep]

    # 5. extent (local frames)
    if frame == "local" and max_extent is not None:
        start, counts["extent_splits"] = _cut_extent(lat, lon, start, max_extent / EARTH_MEAN_RADIUS)

    # 6. short tracks
    first = np.flatnonzero(start)
    lengths = np.diff(np.concatenate([first, [len(t)]]))
    short = lengths < int(min_reports)
    counts["short_tracks"], counts["short_reports"] = int(short.sum()), int(lengths[short].sum())
    if short.any():
        rows = _ranges(first[~short], lengths[~short])
        idx, t, lat, lon = idx[rows], t[rows], lat[rows], lon[rows]
        lengths = lengths[~short]
        first = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)[: len(lengths)]
    if len(first) == 0:
        raise ValueError(f"{rep.path}: no track of >= {min_reports} reports is left ({rep.rows} read)")
    offsets = np.concatenate([first, [len(t)]]).astype(np.int64)
    owner = np.repeat(np.arange(len(first)), lengths)
    alt = rep.alt[idx] if dims == 3 else None

    # frames
    if frame == "local":
        origin = np.stack([lat[first], lon[first], alt[first] if alt is not None else np.zeros(len(first))], -1)
    else:
        ref = [float(x) for x in reference] + [0.0] * (3 - len(reference))
        origin = np.tile(np.array(ref, dtype=np.float64), (len(first), 1))
    o = origin[owner]
    pos = local_positions(lat, lon, o[:, 0], o[:, 1], alt, o[:, 2] if alt is not None else None)
    vel = sog = None
    if rep.sog is not None and rep.cog is not None:
        sog, course, counts["courses_decoded"] = _speed_course(rep.sog[idx], rep.cog[idx], course_encoding)
        vel = local_velocities(sog * KNOT, course, lat, lon, o[:, 0], o[:, 1])

    summary = LoadSummary(
        source=rep.path,
        rows=int(rep.rows),
        malformed=int(rep.malformed),
        malformed_examples=rep.malformed_examples,
        objects=len(np.unique(rep.object_id[idx[first]])),
        tracks=len(first),
        reports=len(t),
        dims=int(dims),
        frame=frame,
        rules={
            "max_gap": max_gap,
            "v_max": v_max,
            "min_reports": int(min_reports),
            "max_extent": max_extent,
            "cut_times": [str(c) for c in cut_times],
            "course_encoding": course_encoding,
            "reference": None if reference is None else [float(x) for x in reference],
        },
        **counts,
    )
    return Tracks(
        object_id=rep.object_id[idx[first]],
        offsets=offsets,
        t=t,
        pos=pos,
        lat=lat,
        lon=lon,
        alt=alt,
        vel=vel,
        sog=sog,
        origin=origin,
        t0=np.datetime64(t0_us, "us"),
        frame=frame,
        summary=summary,
    )


def _speed_course(sog: np.ndarray, cog: np.ndarray, encoding: str) -> tuple[np.ndarray, np.ndarray, int]:
    """(SOG knots with NaN = unavailable, COG degrees in [0, 360) or NaN, number of decoded COGs)."""
    sog = np.asarray(sog, dtype=np.float64)
    cog = np.asarray(cog, dtype=np.float64)
    decoded = 0
    if encoding == "degrees":
        return np.where(sog >= 0, sog, np.nan), np.mod(cog, 360.0), 0
    if encoding == "ais_int12":
        negative = cog < 0.0
        decoded = int(negative.sum())
        cog = np.where(negative, cog + 409.6, cog)
    sog = np.where((sog >= 0) & (sog < 102.25), sog, np.nan)
    cog = np.where((cog >= 0.0) & (cog < 360.0), cog, np.nan)
    return sog, cog, decoded


def _speeds(t: np.ndarray, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """(N - 1,) great-circle speed (m/s) between consecutive reports."""
    d = angular_distance(lat[:-1], lon[:-1], lat[1:], lon[1:]) * EARTH_MEAN_RADIUS
    return d / np.diff(t)


def _reject_jumps(
    t: np.ndarray, lat: np.ndarray, lon: np.ndarray, start: np.ndarray, v_max: float
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Rule 4 of the module docstring: (keep mask, new start flags, reports dropped, cuts)."""
    keep = np.ones(len(t), dtype=bool)
    start = start.copy()
    if len(t) < 2:
        return keep, start, 0, 0
    fast = (_speeds(t, lat, lon) > v_max) & ~start[1:]
    if not fast.any():
        return keep, start, 0, 0
    first = np.flatnonzero(start)
    bounds = np.concatenate([first, [len(t)]])
    flagged = np.unique(np.searchsorted(first, np.flatnonzero(fast) + 1, side="right") - 1)
    step_ok = np.concatenate([[True], ~fast])  # step_ok[i]: the step (i - 1 -> i) is plausible
    dropped = cuts = 0

    def speed(a: int, b: int) -> float:
        return float(angular_distance(lat[a], lon[a], lat[b], lon[b])) * EARTH_MEAN_RADIUS / (t[b] - t[a])

    for s in flagged:
        a, b = int(bounds[s]), int(bounds[s + 1])
        last = a
        for i in range(a + 1, b):
            if step_ok[i] if last == i - 1 else speed(last, i) <= v_max:
                last = i
            elif i + 1 < b and speed(last, i + 1) <= v_max:
                keep[i] = False  # a lone outlier
                dropped += 1
            else:
                start[i] = True  # the track continues elsewhere: cut
                cuts += 1
                last = i
    return keep, start, dropped, cuts


def _cut_extent(lat: np.ndarray, lon: np.ndarray, start: np.ndarray, limit: float) -> tuple[np.ndarray, int]:
    """Rule 5: cut where a track leaves the angular radius ``limit`` (radians) around its origin."""
    start = start.copy()
    first = np.flatnonzero(start)
    owner_first = first[np.cumsum(start) - 1]
    far = angular_distance(lat[owner_first], lon[owner_first], lat, lon) > limit
    if not far.any():
        return start, 0
    bounds = np.concatenate([first, [len(lat)]])
    cuts = 0
    for s in np.unique(np.searchsorted(first, np.flatnonzero(far), side="right") - 1):
        a, b = int(bounds[s]), int(bounds[s + 1])
        while a < b:
            out = np.flatnonzero(angular_distance(lat[a], lon[a], lat[a:b], lon[a:b]) > limit)
            if len(out) == 0:
                break
            a += int(out[0])
            start[a] = True
            cuts += 1
    return start, cuts


# ---------------------------------------------------------------------------- splits and windows
def split_objects(
    tracks: Tracks, fractions: Sequence[float] = (0.6, 0.2, 0.2), seed: int = 0
) -> tuple[Tracks, Tracks, Tracks]:
    """Object-disjoint (train, val, test) splits: every track of an object goes where the object goes.

    The sorted distinct object ids (K of them) are permuted with ``seed`` and cut into
    val = round(f_val K), test = round(f_test K), train = the rest.

    Args:
        tracks: the tracks to split.
        fractions: (train, val, test) shares of the objects, non-negative, summing to 1.
        seed: the permutation's seed.

    Returns:
        tuple[Tracks, Tracks, Tracks]: train, val and test.
    """
    if len(fractions) != 3 or any(f < 0 for f in fractions) or not math.isclose(sum(fractions), 1.0):
        raise ValueError(f"fractions must be 3 non-negative numbers summing to 1, got {list(fractions)}")
    ids, owner = np.unique(tracks.object_id, return_inverse=True)
    k = len(ids)
    perm = np.random.default_rng(seed).permutation(k)
    n_val, n_test = round(fractions[1] * k), round(fractions[2] * k)
    n_train = k - n_val - n_test
    parts = (perm[:n_train], perm[n_train : n_train + n_val], perm[n_train + n_val :])
    out = []
    for part in parts:
        chosen = np.zeros(k, dtype=bool)
        chosen[part] = True
        out.append(tracks.subset(np.flatnonzero(chosen[owner])))
    return out[0], out[1], out[2]


def split_time(tracks: Tracks, boundaries: Sequence[str | np.datetime64]) -> list[Tracks]:
    """Tracks grouped by the interval of their first report: [-inf, b1), [b1, b2), ..., [bk, inf).

    Args:
        tracks: tracks loaded with ``cut_times=boundaries``, so that none spans a boundary.
        boundaries: increasing instants (ISO 8601 strings or datetime64).

    Returns:
        list[Tracks]: k + 1 groups, in time order.

    Raises:
        ValueError: for boundaries that do not increase, or a track spanning one.
    """
    cuts = np.array(
        [(np.datetime64(b, "us") - tracks.t0).astype("timedelta64[us]").astype(np.int64) / 1e6 for b in boundaries]
    )
    if np.any(np.diff(cuts) <= 0):
        raise ValueError(f"boundaries must increase, got {list(map(str, boundaries))}")
    first_t, last_t = tracks.t[tracks.offsets[:-1]], tracks.t[tracks.offsets[1:] - 1]
    bins = np.searchsorted(cuts, first_t, side="right")
    if np.any(bins != np.searchsorted(cuts, last_t, side="right")):
        raise ValueError("some tracks span a split boundary: load them with cut_times=boundaries")
    return [tracks.subset(np.flatnonzero(bins == k)) for k in range(len(cuts) + 1)]


def window_bounds(lengths: np.ndarray, max_len: int | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut tracks of ``lengths`` into ceil(L / max_len) windows of near-equal length (<= max_len).

    Args:
        lengths: (K,) track lengths.
        max_len: the longest window (>= 2); None = one window per track.

    Returns:
        tuple[ndarray, ndarray, ndarray]: (track index, start, stop) per window, start/stop relative
        to the track.
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    if max_len is None:
        n = np.ones_like(lengths)
    else:
        if int(max_len) < 2:
            raise ValueError(f"max_len must be >= 2 or None, got {max_len}")
        n = -(-lengths // int(max_len))
    owner = np.repeat(np.arange(len(lengths)), n)
    j = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    L, k = lengths[owner], n[owner]
    return owner, (j * L) // k, ((j + 1) * L) // k


def track_windows(
    tracks: Tracks, max_len: int | None = None, center: bool = True, dtype: torch.dtype = torch.float32
) -> list[Track]:
    """Training windows as :class:`~torchsde_lti.data.tracks.Track` s (:func:`window_bounds`).

    Args:
        tracks: the tracks to cut.
        max_len: the longest window (reports); None = whole tracks.
        center: subtract each window's first report from its positions (kept in ``origin``).
        dtype: of the returned tensors.

    Returns:
        list[Track]: per window y (T, d) positions, dt (T,) seconds from the previous report
        (dt[0] = 0: the prior sits at the first report), t (T,) seconds since ``tracks.t0``,
        vel (T, 2) and sog (T,) where the file has SOG/COG, and track_id, the track's index in
        ``tracks`` (``tracks.object_id[track_id]`` is the object).
    """
    owner, a, b = window_bounds(tracks.lengths, max_len)
    a = a + tracks.offsets[owner]
    b = b + tracks.offsets[owner]
    as_t = lambda x: torch.as_tensor(np.ascontiguousarray(x, dtype=np.float64)).to(dtype)  # noqa: E731
    pos64 = np.ascontiguousarray(tracks.pos, dtype=np.float64)  # (centred in float64, then cast)
    t = as_t(tracks.t)
    vel = as_t(tracks.vel) if tracks.vel is not None else None
    sog = as_t(tracks.sog) if tracks.sog is not None else None
    dt_all = np.concatenate([[0.0], np.diff(tracks.t)])
    dt_all[a] = 0.0
    dt = as_t(dt_all)
    out = []
    for k, (i, j) in enumerate(zip(a.tolist(), b.tolist())):
        origin = pos64[i] if center else np.zeros_like(pos64[i])
        out.append(
            Track(
                y=torch.as_tensor(pos64[i:j] - origin).to(dtype),
                dt=dt[i:j],
                t=t[i:j],
                vel=None if vel is None else vel[i:j],
                sog=None if sog is None else sog[i:j],
                origin=torch.tensor(origin, dtype=dtype),
                track_id=torch.tensor(int(owner[k]), dtype=torch.int64),
            )
        )
    return out
