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

The result is a :class:`~torchsde_lti.data.loaded_tracks.Tracks` (flat numpy arrays with
per-track offsets) with its :class:`~torchsde_lti.data.loaded_tracks.LoadSummary`
(:mod:`torchsde_lti.data.loaded_tracks`); :mod:`torchsde_lti.data.splits` divides it into
object-disjoint or time splits and cuts it into training windows. Those names are also
importable from here.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from torchsde_lti.data.frames import EARTH_MEAN_RADIUS, KNOT, angular_distance, local_positions, local_velocities
from torchsde_lti.data.loaded_tracks import LoadSummary, Tracks, _ranges
from torchsde_lti.data.rules import REPORT_RULES, CleaningRules
from torchsde_lti.data.sources import Reports, read_reports
from torchsde_lti.data.splits import split_objects, split_time, track_windows, window_bounds

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


def load_tracks(
    source: str | os.PathLike[str],
    columns: Mapping[str, str | int] | str | None = None,
    *,
    rules: CleaningRules | Mapping[str, Any] | None = None,
    **changes: Any,
) -> Tracks:
    """Tracks from a ``.traj``, CSV or Parquet file, in per-track local metric frames.

    Args:
        source: a path, or a file name shipped by tracktable-data (e.g.
            ``"US_coastal_2020_06_30.traj"``); FileNotFoundError says where it looked.
        columns: CSV / Parquet role -> column (header name or 0-based position): id, time, lat,
            lon and optionally alt, sog, cog; None recognises the MarineCadastre AIS header
            (a shortcut for ``columns=`` of the rules).
        rules: the reading and cleaning rules (:class:`~torchsde_lti.data.CleaningRules`, or a
            mapping of its fields); None = its defaults.
        **changes: fields of :class:`~torchsde_lti.data.CleaningRules` replacing those of
            ``rules`` (``max_gap=600.0``, ``v_max=35.0``, ``min_reports=5``, ``cut_times=[...]``...).

    Returns:
        :class:`Tracks`, with ``.summary`` (:class:`LoadSummary`) counting every rule.

    Raises:
        TypeError, ValueError: for a rule of the wrong type or value (naming it), and for a file
            that cannot be read or cleaned (naming the file, the column and, where there is one,
            the row).
    """
    if columns is not None:
        changes["columns"] = columns
    checked = CleaningRules.coerce(rules, **changes)
    reports = read_reports(source, **checked.reading)
    return prepare_tracks(reports, rules=checked)


def prepare_tracks(
    reports: Reports, *, rules: CleaningRules | Mapping[str, Any] | None = None, **changes: Any
) -> Tracks:
    """The cleaning rules and frames of :func:`load_tracks` applied to already-read :class:`Reports`.

    Args:
        reports: the reports of one file (:func:`~torchsde_lti.data.read_reports`).
        rules: as in :func:`load_tracks` (its reading fields are not used here).
        **changes: fields of :class:`~torchsde_lti.data.CleaningRules` replacing those of ``rules``.

    Returns:
        Tracks: with ``.summary`` counting every rule.
    """
    rules = CleaningRules.coerce(rules, **changes)
    dims, frame, reference = rules.dims, rules.frame, rules.reference
    max_gap, v_max, max_extent, min_reports = rules.max_gap, rules.v_max, rules.max_extent, rules.min_reports
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

    # 1. valid positions (REPORT_RULES): invalid ones dropped, counted by reason; a likely swap refused
    valid, invalid = _valid_positions(rep, dims)
    _check_swap(rep, valid, recognised_header=rules.columns in (None, "ais"))
    counts["invalid_positions"] = int((~valid).sum())
    idx = np.flatnonzero(valid)
    if len(idx) == 0:
        reasons = ", ".join(f"{name} {count}" for name, count in invalid.items())
        raise ValueError(f"{rep.path}: no report has a valid position ({rep.rows} read; {reasons})")

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
    lat, lon = rep.lat[idx], np.where(rep.lon[idx] == 180.0, -180.0, rep.lon[idx])  # (the same meridian)
    start = ~same

    # 3. cuts at split times and at long gaps
    cuts = (rules.cut_instants().astype(np.int64) - t0_us) / 1e6
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
    alt = rep.alt[idx] if dims == 3 and rep.alt is not None else None

    # frames
    if frame == "local":
        origin = np.stack([lat[first], lon[first], alt[first] if alt is not None else np.zeros(len(first))], -1)
    else:
        ref = [*(reference or ()), 0.0][:3]  # (a common frame has a checked reference: lat, lon[, alt])
        origin = np.tile(np.array(ref, dtype=np.float64), (len(first), 1))
    o = origin[owner]
    pos = local_positions(lat, lon, o[:, 0], o[:, 1], alt, o[:, 2] if alt is not None else None)
    vel = sog = None
    unavailable: dict[str, int] = {}
    if rep.sog is not None and rep.cog is not None:
        sog, course, counts["courses_decoded"], unavailable = _speed_course(
            rep.sog[idx], rep.cog[idx], rules.course_encoding
        )
        vel = local_velocities(sog * KNOT, course, lat, lon, o[:, 0], o[:, 1])
    if rep.heading is not None:
        unavailable.update(_counts(REPORT_RULES["heading"].classify(rep.heading[idx])))

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
        rules=rules.as_dict(),
        **counts,
        invalid=invalid,
        unavailable=unavailable,
        decoded=dict(rep.decoded),
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


def _counts(masks: dict[str, np.ndarray]) -> dict[str, int]:
    """name -> number of True entries, the names with none left out."""
    return {name: int(mask.sum()) for name, mask in masks.items() if mask.any()}


def _valid_positions(rep: Reports, dims: int) -> tuple[np.ndarray, dict[str, int]]:
    """(N,) the reports with a valid latitude, longitude (and, 3-D, a finite altitude), and the
    invalid ones counted by their first reason (:data:`~torchsde_lti.data.REPORT_RULES`)."""
    bad = np.zeros(len(rep.lat), dtype=bool)
    invalid: dict[str, int] = {}
    masks = {**REPORT_RULES["lat"].classify(rep.lat), **REPORT_RULES["lon"].classify(rep.lon)}
    if dims == 3 and rep.alt is not None:
        masks["alt_missing"] = ~np.isfinite(rep.alt)
    for name, mask in masks.items():
        first = mask & ~bad
        if first.any():
            invalid[name] = int(first.sum())
        bad |= first
    return ~bad, invalid


def _check_swap(rep: Reports, valid: np.ndarray, recognised_header: bool) -> None:
    """Refuse latitude and longitude columns that look exchanged: most positions invalid while
    at least twice as many would be valid the other way round; or, with the MarineCadastre
    header recognised (US waters: no report both south of the equator and east of Greenwich),
    every valid position south-east and valid the other way round too."""
    lat_rule, lon_rule = REPORT_RULES["lat"], REPORT_RULES["lon"]
    # reports with two numbers, neither AIS's "not available": what a swap would show in
    lat_masks, lon_masks = lat_rule.classify(rep.lat), lon_rule.classify(rep.lon)
    numbers = ~(lat_masks["lat_missing"] | lat_masks["lat_not_available"])
    numbers &= ~(lon_masks["lon_missing"] | lon_masks["lon_not_available"])
    if not numbers.any():
        return
    other_way = lat_rule.valid(rep.lon) & lon_rule.valid(rep.lat) & numbers
    n_valid, n_other, n = int((valid & numbers).sum()), int(other_way.sum()), int(numbers.sum())
    most_invalid = n_valid < n / 2 and n_other >= 2 * n_valid
    south_east = (
        recognised_header
        and n_valid > 0
        and bool(np.all((rep.lat[valid] < 0) & (rep.lon[valid] > 0) & other_way[valid]))
    )
    if not (most_invalid or south_east):
        return
    names = rep.columns or {"lat": "lat", "lon": "lon"}
    lat_col, lon_col = names.get("lat", "lat"), names.get("lon", "lon")
    if most_invalid:
        why = (
            f"{n - n_valid} of {n} reports have no valid position (latitudes outside [-90, 90] in "
            f"{lat_col!r}), and {n_other} would be valid with {lat_col!r} as the longitude and {lon_col!r} as the "
            "latitude"
        )
    else:
        why = (
            f"all {n_valid} valid positions are south of the equator and east of Greenwich (latitude {lat_col!r} "
            f"{np.min(rep.lat[valid]):g} to {np.max(rep.lat[valid]):g}, longitude {lon_col!r} "
            f"{np.min(rep.lon[valid]):g} to {np.max(rep.lon[valid]):g}), where MarineCadastre (US waters) has no "
            "reports; if they really are there, name the columns, e.g. columns={'id': 'MMSI', 'time': "
            "'BaseDateTime', 'lat': 'LAT', 'lon': 'LON'}, which skips this check"
        )
    fix = {**names, "lat": lon_col, "lon": lat_col}
    raise ValueError(f"{rep.path}: the latitude and longitude columns look swapped: {why}. Swap them: columns={fix}")


def _speed_course(
    sog: np.ndarray, cog: np.ndarray, encoding: str
) -> tuple[np.ndarray, np.ndarray, int, dict[str, int]]:
    """(SOG knots with NaN = unavailable, COG degrees in [0, 360) or NaN, number of decoded COGs,
    the unavailable values counted by reason) under ``encoding`` (:class:`CleaningRules`)."""
    sog = np.asarray(sog, dtype=np.float64)
    cog = np.asarray(cog, dtype=np.float64)
    decoded = 0
    if encoding == "degrees":  # not AIS: any course modulo 360, a negative speed unavailable
        with np.errstate(invalid="ignore"):
            masks = {"sog_missing": ~np.isfinite(sog), "sog_out_of_range": sog < 0, "cog_missing": ~np.isfinite(cog)}
        return np.where(sog >= 0, sog, np.nan), np.mod(cog, 360.0), 0, _counts(masks)
    if encoding == "ais_int12":
        negative = cog < 0.0
        decoded = int(negative.sum())
        cog = np.where(negative, cog + 409.6, cog)
    sog_masks, cog_masks = REPORT_RULES["sog"].classify(sog), REPORT_RULES["cog"].classify(cog)
    sog = np.where(REPORT_RULES["sog"].valid(sog), sog, np.nan)
    cog = np.where(REPORT_RULES["cog"].valid(cog), cog, np.nan)
    return sog, cog, decoded, {**_counts(sog_masks), **_counts(cog_masks)}


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
