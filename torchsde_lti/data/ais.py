"""Real ship tracks (AIS) from New York Harbor as irregularly sampled 2-D tracking data.

The reports come from the optional package ``tracktable-data`` (BSD-3, ``pip install -e
.[data]``), file ``python_example_data/NYHarbor_2020_06_30_first_hour.csv``: one hour of
AIS position reports (columns BaseDateTime, LON, LAT, MMSI, SOG, COG, Heading, ...).
Nothing is downloaded at run time and no data is copied into this repository.

Pipeline (:func:`load_ais`):

1. parse with :mod:`csv` (no pandas), group reports by vessel (MMSI), sort by time;
2. drop exact duplicate rows (none in the shipped file), then any further report whose
   (MMSI, BaseDateTime) repeats an earlier one (first kept; 2 rows in the shipped file).
   Those 2 repeat position, SOG and COG exactly and differ only in the voyage ETA: one
   position message joined with two static messages, not two measurements. Keeping them
   would feed the filter a dt = 0 double update with the same measurement noise;
3. convert lon/lat to a local east/north frame in metres: the WGS84 local tangent plane
   (ENU, height 0) at :data:`REFERENCE_LATLON`, via ECEF coordinates. Inside the harbour
   (< 35 km from the reference) it differs from geodesic distances by < 1e-4 relative
   (tangent-plane foreshortening ~ d^2 / 6 R^2 plus ellipsoid vs sphere), see tests;
4. keep irregular sampling: ``t`` are seconds since the first report in the file;
5. speed over ground (knots) and course over ground (degrees clockwise from true north)
   become an independent east/north velocity in m/s, rotated from the vessel's own local
   east/north into the reference frame. The COG column of this file stores the 12-bit
   AIS field read as a signed integer (values in [-204.8, 204.7]); it is decoded by
   adding 409.6 to negative values (checked against Heading: median |COG - Heading|
   falls from 5.6 to 2.4 degrees for vessels above 3 knots). COG = 360 ("not
   available") and SOG = 102.3 ("not available") give NaN velocity;
6. drop vessels with fewer than ``min_reports`` reports; split VESSELS (not reports) into
   train / val / test with a fixed seed (:func:`split_vessels`).

Batches (:func:`ais_batch`, :class:`~torchsde_lti.data.tracks.TrackBatch`) are padded to the longest track with ``mask`` False on
padding; ``y`` is NaN there as well, so a Kalman filter treating NaN as missing and one
using ``mask`` agree. Positions may be centred on each track's first report
(``center=True``, default) so that a zero prior mean with a few-metre prior variance
describes the first position; the subtracted ``origin`` is returned with the batch.
"""

from __future__ import annotations

import csv
import math
from collections import defaultdict
from datetime import datetime
from pathlib import Path
from typing import Iterable, NamedTuple, Sequence

import numpy as np
import torch

from torchsde_lti.data.tracks import Track, TrackBatch, pad_tracks

__all__ = [
    "AIS_FILE",
    "REFERENCE_LATLON",
    "AISData",
    "AISTrack",
    "ais_batch",
    "decode_cog",
    "geodetic_to_enu",
    "load_ais",
    "load_traj",
    "load_traj",
    "locate_ais_file",
    "sog_cog_to_enu",
    "split_vessels",
    "to_track",
]

AIS_FILE = "NYHarbor_2020_06_30_first_hour.csv"
#: Origin of the east/north frame: Upper New York Bay, 40.65 N, 74.05 W (WGS84).
REFERENCE_LATLON = (40.65, -74.05)
#: One international knot in m/s.
KNOT = 1852.0 / 3600.0
_WGS84_A = 6378137.0
_WGS84_F = 1.0 / 298.257223563
_WGS84_E2 = _WGS84_F * (2.0 - _WGS84_F)


class AISTrack(NamedTuple):
    """One vessel's reports, time-sorted.

    mmsi: vessel id; t: (T,) seconds since the file's first report (float64, strictly
    increasing); pos: (T, 2) east, north in metres; vel: (T, 2) east, north velocity in
    m/s from SOG/COG (NaN where unavailable); lonlat: (T, 2) degrees as reported;
    sog: (T,) knots as reported.
    """

    mmsi: int
    t: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    lonlat: np.ndarray
    sog: np.ndarray


class AISData(NamedTuple):
    """All surviving tracks plus the counts of what the loader removed (``counts``)."""

    tracks: list[AISTrack]
    counts: dict[str, int]
    t0: datetime


def locate_ais_file(name: str = AIS_FILE) -> Path:
    """Path of ``name`` inside the installed ``tracktable_data`` package.

    Raises ModuleNotFoundError with an install hint when the optional package is absent.
    """
    try:
        from tracktable_data import data as ttd
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ModuleNotFoundError(
            "the AIS example needs the optional package tracktable-data: "
            "pip install -e .[data]"
        ) from err
    return Path(ttd.retrieve(name))


def _ecef(lat_deg: np.ndarray, lon_deg: np.ndarray) -> np.ndarray:
    """WGS84 geodetic (height 0) -> ECEF metres, (..., 3)."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = _WGS84_A / np.sqrt(1.0 - _WGS84_E2 * np.sin(lat) ** 2)
    return np.stack(
        [
            n * np.cos(lat) * np.cos(lon),
            n * np.cos(lat) * np.sin(lon),
            n * (1.0 - _WGS84_E2) * np.sin(lat),
        ],
        axis=-1,
    )


def _enu_basis(lat_deg: np.ndarray, lon_deg: np.ndarray) -> np.ndarray:
    """Rows = east, north, up unit vectors in ECEF at the given points, (..., 3, 3)."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    sl, cl, sp, cp = np.sin(lon), np.cos(lon), np.sin(lat), np.cos(lat)
    zero = np.zeros_like(sl)
    east = np.stack([-sl, cl, zero], axis=-1)
    north = np.stack([-sp * cl, -sp * sl, cp], axis=-1)
    up = np.stack([cp * cl, cp * sl, sp], axis=-1)
    return np.stack([east, north, up], axis=-2)


def geodetic_to_enu(
    lat: np.ndarray, lon: np.ndarray, reference: tuple[float, float] = REFERENCE_LATLON
) -> np.ndarray:
    """Local tangent-plane coordinates (east, north) in metres, (..., 2).

    ENU of the WGS84 point (lat, lon, height 0) about ``reference`` = (lat0, lon0):
    [e, n, u] = R(lat0, lon0) (X(lat, lon) - X(lat0, lon0)) with X the ECEF position;
    the up component is dropped. lat, lon: (...) degrees.
    """
    lat = np.asarray(lat, dtype=np.float64)
    lon = np.asarray(lon, dtype=np.float64)
    if lat.shape != lon.shape:
        raise ValueError(f"lat and lon must have the same shape, got {lat.shape} and {lon.shape}")
    lat0, lon0 = reference
    d = _ecef(lat, lon) - _ecef(np.float64(lat0), np.float64(lon0))
    basis = _enu_basis(np.float64(lat0), np.float64(lon0))
    return np.einsum("ij,...j->...i", basis[:2], d)


def decode_cog(cog: np.ndarray) -> np.ndarray:
    """Course over ground in [0, 360) degrees from this file's signed 12-bit encoding.

    Negative values v stand for v + 409.6 (raw tenths of a degree read as int12);
    360 ("not available") and anything outside [0, 360) becomes NaN.
    """
    cog = np.asarray(cog, dtype=np.float64)
    out = np.where(cog < 0.0, cog + 409.6, cog)
    return np.where((out >= 0.0) & (out < 360.0), out, np.nan)


def sog_cog_to_enu(
    sog_knots: np.ndarray,
    cog_deg: np.ndarray,
    lat: np.ndarray,
    lon: np.ndarray,
    reference: tuple[float, float] = REFERENCE_LATLON,
) -> np.ndarray:
    """Velocity (east, north) in m/s in the reference tangent plane, (..., 2).

    SOG in knots, COG decoded (degrees clockwise from true north, NaN = unavailable).
    Local velocity [s sin c, s cos c, 0] at (lat, lon) is mapped to ECEF with the local
    ENU basis and back with the reference basis; the rotation between the two frames is
    below 0.3 degrees in the harbour. SOG >= 102.3 (not available) gives NaN; SOG = 0
    gives zero velocity even without a course.
    """
    sog = np.asarray(sog_knots, dtype=np.float64)
    cog = np.asarray(cog_deg, dtype=np.float64)
    speed = np.where(sog < 102.25, sog * KNOT, np.nan)
    c = np.radians(cog)
    ve = np.where(speed == 0.0, 0.0, speed * np.sin(c))
    vn = np.where(speed == 0.0, 0.0, speed * np.cos(c))
    local = np.stack([ve, vn, np.zeros_like(ve)], axis=-1)
    ecef = np.einsum("...ji,...j->...i", _enu_basis(lat, lon), local)
    ref = _enu_basis(np.float64(reference[0]), np.float64(reference[1]))
    return np.einsum("ij,...j->...i", ref[:2], ecef)


def load_ais(
    path: str | Path | None = None,
    min_reports: int = 5,
    reference: tuple[float, float] = REFERENCE_LATLON,
) -> AISData:
    """Parse the AIS csv into time-sorted per-vessel tracks (see module docstring).

    path: csv file; default the NY Harbor hour from ``tracktable_data``.
    min_reports: vessels with fewer surviving reports are dropped.
    Returns tracks sorted by MMSI and ``counts`` with keys rows, exact_duplicates,
    repeated_timestamps, vessels_all, vessels_dropped_short, reports_dropped_short,
    vessels, reports.
    """
    if min_reports < 2:
        raise ValueError(f"min_reports must be >= 2 to have a time step, got {min_reports}")
    path = locate_ais_file() if path is None else Path(path)
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    needed = {"BaseDateTime", "LON", "LAT", "MMSI", "SOG", "COG"}
    if not rows or not needed <= set(rows[0]):
        raise ValueError(f"{path} lacks columns {sorted(needed)}")
    counts = {"rows": len(rows), "exact_duplicates": 0, "repeated_timestamps": 0}
    seen_rows: set[tuple[str, ...]] = set()
    seen_keys: set[tuple[str, str]] = set()
    by_vessel: dict[int, list[tuple[float, float, float, float, float]]] = defaultdict(list)
    times = [datetime.fromisoformat(r["BaseDateTime"]) for r in rows]
    t0 = min(times)
    for r, when in zip(rows, times):
        full = tuple(r.values())
        if full in seen_rows:
            counts["exact_duplicates"] += 1
            continue
        seen_rows.add(full)
        key = (r["MMSI"], r["BaseDateTime"])
        if key in seen_keys:
            counts["repeated_timestamps"] += 1
            continue
        seen_keys.add(key)
        by_vessel[int(r["MMSI"])].append(
            (
                (when - t0).total_seconds(),
                float(r["LON"]),
                float(r["LAT"]),
                float(r["SOG"]),
                float(r["COG"]),
            )
        )
    counts["vessels_all"] = len(by_vessel)
    tracks: list[AISTrack] = []
    short_v = short_r = 0
    for mmsi in sorted(by_vessel):
        rec = np.array(sorted(by_vessel[mmsi]), dtype=np.float64)
        if len(rec) < min_reports:
            short_v += 1
            short_r += len(rec)
            continue
        t, lon, lat, sog, cog = rec.T
        pos = geodetic_to_enu(lat, lon, reference)
        vel = sog_cog_to_enu(sog, decode_cog(cog), lat, lon, reference)
        tracks.append(AISTrack(mmsi, t, pos, vel, np.stack([lon, lat], -1), sog))
    counts["vessels_dropped_short"] = short_v
    counts["reports_dropped_short"] = short_r
    counts["vessels"] = len(tracks)
    counts["reports"] = sum(len(tr.t) for tr in tracks)
    return AISData(tracks, counts, t0)


def dt_summary(tracks: Iterable[AISTrack]) -> dict[str, float]:
    """Count, quantiles (min, 5, 25, 50, 75, 95, max) and mean of within-track dt, seconds."""
    dts = np.concatenate([np.diff(tr.t) for tr in tracks] or [np.zeros(0)])
    if dts.size == 0:
        return {"n": 0}
    qs = np.percentile(dts, [0, 5, 25, 50, 75, 95, 100])
    keys = ["min", "p05", "p25", "median", "p75", "p95", "max"]
    return {"n": int(dts.size), "mean": float(dts.mean()), **dict(zip(keys, map(float, qs)))}


def split_vessels(
    n: int, fractions: Sequence[float] = (0.6, 0.2, 0.2), seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Disjoint index arrays (train, val, test) covering range(n), from a seeded permutation.

    Sizes: val = round(f_val n), test = round(f_test n), train = the rest.
    """
    if len(fractions) != 3 or any(f < 0 for f in fractions) or not math.isclose(sum(fractions), 1.0):
        raise ValueError(f"fractions must be 3 non-negative numbers summing to 1, got {fractions}")
    perm = np.random.default_rng(seed).permutation(n)
    n_val, n_test = round(fractions[1] * n), round(fractions[2] * n)
    n_train = n - n_val - n_test
    return (
        np.sort(perm[:n_train]),
        np.sort(perm[n_train : n_train + n_val]),
        np.sort(perm[n_train + n_val :]),
    )


def to_track(track: AISTrack, center: bool = True, dtype: torch.dtype = torch.float32) -> Track:
    """One vessel as a :class:`~torchsde_lti.data.tracks.Track`: y (T, 2) positions in metres
    (minus the first report when ``center``, recorded in ``origin`` (2,)), dt (T,) seconds
    from the previous report (dt[0] = 0: the prior sits at the first report), t (T,) seconds
    since file start, vel (T, 2) SOG/COG velocity in m/s, sog (T,) knots, track_id = MMSI."""
    origin = track.pos[0] if center else np.zeros(2)
    dt = np.concatenate([[0.0], np.diff(track.t)])
    as_t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64), dtype=dtype)  # noqa: E731
    return Track(
        y=as_t(track.pos - origin),
        dt=as_t(dt),
        t=as_t(track.t),
        vel=as_t(track.vel),
        sog=as_t(track.sog),
        origin=as_t(origin),
        track_id=torch.tensor(track.mmsi, dtype=torch.int64),
    )


def ais_batch(tracks: Sequence[AISTrack], center: bool = True, dtype: torch.dtype = torch.float32) -> TrackBatch:
    """Vessels padded into one :class:`~torchsde_lti.data.tracks.TrackBatch` (:func:`to_track`
    then :func:`~torchsde_lti.data.tracks.pad_tracks`)."""
    if len(tracks) == 0:
        raise ValueError("ais_batch needs at least one track, got 0")
    return pad_tracks([to_track(tr, center, dtype) for tr in tracks])


# ---------------------------------------------------------------------------- tracktable .traj files
_TS = "%Y-%m-%d %H:%M:%S"


def _parse_traj_line(fields: list[str]) -> tuple[int, list[tuple[datetime, float, float]]]:
    """One trajectory line of a tracktable ``.traj`` file -> (object id, [(time, lon, lat), ...]).

    Layout: ``*T*, uuid, domain, N points, n_traj_props, (name, type, value) * n, *P*, domain,
    dim, has_id, has_time, k, (name, type) * k`` then N points of ``id, time, lon, lat,
    k property values``. A string property may contain commas (vessel names): it then runs
    until the next point's ``id, time`` (or the end of the line).
    """
    if len(fields) < 5 or fields[0] != "*T*":
        raise ValueError(f"not a trajectory line: {fields[:5]}")
    n_points, n_tprops = int(fields[3]), int(fields[4])
    i = 5 + 3 * n_tprops
    if fields[i] != "*P*" or fields[i + 2] != "2" or fields[i + 3] != "1" or fields[i + 4] != "1":
        raise ValueError(f"expected 2-D points with id and timestamp, got header {fields[i:i + 6]}")
    k = int(fields[i + 5])
    types = [fields[i + 7 + 2 * p] for p in range(k)]
    j = i + 6 + 2 * k
    points: list[tuple[datetime, float, float]] = []
    obj = fields[j] if j < len(fields) else ""
    for _ in range(n_points):
        if fields[j] != obj:
            raise ValueError(f"point {len(points)} has object id {fields[j]!r}, expected {obj!r}")
        when = datetime.strptime(fields[j + 1], _TS)
        points.append((when, float(fields[j + 2]), float(fields[j + 3])))
        j += 4
        for p, kind in enumerate(types):
            j += 1
            if kind == "2" and p == k - 1:  # trailing string: may contain commas
                while j < len(fields) and not (fields[j] == obj and j + 1 < len(fields)
                                               and len(fields[j + 1]) == 19 and fields[j + 1][4] == "-"):
                    j += 1
    if j != len(fields) and not (j == len(fields) - 1 and fields[-1] == ""):  # a trailing comma is fine
        raise ValueError(f"{len(fields) - j} unparsed fields after {n_points} points")
    return int(obj), points


def load_traj(
    name: str | Path,
    min_reports: int = 5,
    reference: tuple[float, float] = REFERENCE_LATLON,
) -> AISData:
    """Tracks from a tracktable ``.traj`` file (e.g. ``NYHarbor_2020_12_08.traj``).

    ``name``: a path, or a file name inside the installed ``tracktable_data`` package
    (:func:`locate_ais_file`). Each trajectory line becomes one :class:`AISTrack` (the file's
    own segmentation; one vessel may have several), time-sorted, with repeated timestamps
    dropped (first kept) and positions in the same east/north frame as :func:`load_ais`.
    These files carry no SOG/COG: ``vel`` and ``sog`` are NaN, so velocity checks and
    SOG-based splits are not available (they evaluate to NaN). ``t`` are seconds since the
    file's first report. ``counts``: trajectories, unparsed_trajectories (malformed lines,
    skipped), repeated_timestamps, vessels_dropped_short, reports_dropped_short, vessels
    (distinct ids kept), tracks, reports.
    """
    if min_reports < 2:
        raise ValueError(f"min_reports must be >= 2 to have a time step, got {min_reports}")
    path = Path(name)
    if not path.exists():
        path = locate_ais_file(str(name))
    parsed: list[tuple[int, list[tuple[datetime, float, float]]]] = []
    counts = {"trajectories": 0, "unparsed_trajectories": 0, "repeated_timestamps": 0}
    with open(path) as fh:
        for line in fh:
            if not line.strip():
                continue
            counts["trajectories"] += 1
            try:
                parsed.append(_parse_traj_line(line.rstrip("\n").split(",")))
            except (ValueError, IndexError):
                counts["unparsed_trajectories"] += 1
    if not parsed:
        raise ValueError(f"{path}: no trajectory could be parsed")
    t0 = min(p[0] for _, pts in parsed for p in pts)
    tracks: list[AISTrack] = []
    short_v = short_r = 0
    for obj, pts in parsed:
        pts = sorted(pts)
        keep, seen = [], set()
        for p in pts:
            if p[0] in seen:
                counts["repeated_timestamps"] += 1
                continue
            seen.add(p[0])
            keep.append(p)
        if len(keep) < min_reports:
            short_v += 1
            short_r += len(keep)
            continue
        t = np.array([(p[0] - t0).total_seconds() for p in keep])
        lon = np.array([p[1] for p in keep])
        lat = np.array([p[2] for p in keep])
        nan = np.full(len(keep), np.nan)
        tracks.append(AISTrack(obj, t, geodetic_to_enu(lat, lon, reference), np.stack([nan, nan], -1),
                               np.stack([lon, lat], -1), nan.copy()))
    counts["vessels_dropped_short"] = short_v
    counts["reports_dropped_short"] = short_r
    counts["vessels"] = len({tr.mmsi for tr in tracks})
    counts["tracks"] = len(tracks)
    counts["reports"] = sum(len(tr.t) for tr in tracks)
    return AISData(tracks, counts, t0)
