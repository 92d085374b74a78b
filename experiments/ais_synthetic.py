"""Synthetic national AIS in MarineCadastre's daily CSV format, written chunk by chunk.

    python experiments/ais_synthetic.py --out /work/tmp/ais --days 7            # ~ 8 M reports a day
    python experiments/ais_synthetic.py --out /tmp/small --days 1 --vessels 300 --zip

One file per day, ``AIS_YYYY_MM_DD.csv`` (or ``.zip`` holding it), with MarineCadastre's 17
columns (``MMSI, BaseDateTime, LAT, LON, SOG, COG, Heading, VesselName, IMO, CallSign,
VesselType, Status, Length, Width, Draft, Cargo, TransceiverClass``). What a day holds, and why:

- vessels: 20-30 k distinct MMSIs a day (MarineCadastre's US national files: ~25 k), a fixed
  fleet of which each day sees a random part; class A (70 %) and class B transceivers;
- each vessel is on air for a stretch of the day (1 h to all day), moored / anchored (55 %) or
  under way at 3-25 kn with a slowly wandering course (a random walk, 1 deg / sqrt(min));
- nominal report intervals of ITU-R M.1371: class A 10 s (< 14 kn), 6 s (14-23 kn), 2 s
  (> 23 kn), 3 min at anchor or moored; class B 30 s under way, 3 min still; thinned to at most
  one report a minute per vessel (``--thin 60``: MarineCadastre's national files are; ``--thin 0``
  keeps every nominal report), each received with probability ``--received`` (0.8): ~7 M reports
  a day, as June 2022's 249 M reports a month;
- outages: per vessel, 0-3 gaps of 10 min to 3 h without reports;
- positions start in one of the US coastal boxes below (ports, approaches, the Great Lakes,
  Alaska, Hawaii, Puerto Rico); a transit of at most a few hundred km stays in the region;
- the faults that real files have, at small rates: AIS "not available" values (lat 91, lon 181,
  SOG 102.3, COG 360, heading 511), repeated timestamps, and MMSI clashes (two ships, one id).

Rows are written in time order within each chunk of vessels (MarineCadastre files are not
sorted by vessel). Deterministic given ``--seed``. Memory: one chunk of vessels at a time.
"""

from __future__ import annotations

import argparse
import datetime as dt
import time
import zipfile
from pathlib import Path

import numpy as np

COLUMNS = [
    "MMSI", "BaseDateTime", "LAT", "LON", "SOG", "COG", "Heading", "VesselName", "IMO", "CallSign",
    "VesselType", "Status", "Length", "Width", "Draft", "Cargo", "TransceiverClass",
]  # fmt: skip
# (lat_min, lat_max, lon_min, lon_max): coastal waters around US ports and approaches
BOXES = np.array(
    [
        (40.3, 40.8, -74.3, -73.6),  # New York / New Jersey
        (36.8, 39.3, -76.5, -75.9),  # Chesapeake Bay
        (25.5, 27.0, -80.3, -79.9),  # Florida east coast
        (29.0, 29.8, -95.2, -94.0),  # Houston / Galveston
        (28.8, 30.0, -90.5, -89.0),  # Mississippi delta
        (33.5, 33.9, -118.5, -118.0),  # Los Angeles / Long Beach
        (37.4, 38.1, -122.6, -122.0),  # San Francisco Bay
        (47.2, 48.4, -123.0, -122.2),  # Puget Sound
        (41.5, 46.0, -87.8, -86.5),  # Lake Michigan
        (41.4, 42.6, -83.0, -79.0),  # Lake Erie
        (59.0, 61.0, -152.0, -149.0),  # Cook Inlet, Alaska
        (20.5, 21.7, -158.3, -156.8),  # Hawaii
        (18.0, 18.6, -67.3, -65.5),  # Puerto Rico
        (42.0, 42.6, -71.0, -70.3),  # Boston
        (32.0, 32.9, -80.0, -79.0),  # Charleston
    ]
)
WEIGHTS = np.array([12, 10, 8, 10, 9, 10, 8, 8, 5, 4, 3, 3, 2, 5, 3], dtype=np.float64)
NOT_AVAILABLE = {"LAT": 91.0, "LON": 181.0, "SOG": 102.3, "COG": 360.0, "Heading": 511.0}
EARTH = 6_371_008.8
KNOT = 1852.0 / 3600.0


def fleet(size: int, seed: int) -> dict[str, np.ndarray]:
    """The fleet: MMSI, class A or B, still or under way, speed (kn) and home box of each vessel."""
    g = np.random.default_rng(seed)
    mmsi = 200_000_000 + g.choice(600_000_000, size, replace=False).astype(np.int64)
    class_a = g.random(size) < 0.7
    still = g.random(size) < 0.55
    speed = np.where(still, 0.0, np.clip(g.gamma(4.0, 3.0, size), 3.0, 25.0))
    box = g.choice(len(BOXES), size, p=WEIGHTS / WEIGHTS.sum())
    return {"mmsi": mmsi, "class_a": class_a, "still": still, "speed": speed, "box": box}


def interval(class_a: np.ndarray, still: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """Nominal seconds between reports (ITU-R M.1371)."""
    moving_a = np.where(speed > 23, 2.0, np.where(speed > 14, 6.0, 10.0))
    return np.where(still, 180.0, np.where(class_a, moving_a, 30.0))


def day_chunk(
    f: dict[str, np.ndarray], day0: np.datetime64, received: float, thin: float, g: np.random.Generator
) -> dict[str, np.ndarray]:
    """The reports of the vessels of ``f`` (a chunk of the fleet) over one day, as columns."""
    n = len(f["mmsi"])
    on_air = np.where(f["still"], g.uniform(3600, 86_400, n), g.uniform(3600, 16 * 3600, n))
    start = g.uniform(0, 86_400 - on_air)
    # the nominal schedule (thinned to one report per `thin` s), each report received with prob. `received`
    step = np.maximum(interval(f["class_a"], f["still"], f["speed"]), thin)
    count = np.maximum(1, (on_air / step).astype(np.int64))
    owner = np.repeat(np.arange(n), count)
    total = int(count.sum())
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    k = np.arange(total) - np.repeat(first, count)
    t = start[owner] + step[owner] * (k + g.uniform(0.0, 0.3, total))
    heard = g.random(total) < received
    owner, t = owner[heard], t[heard]
    count = np.bincount(owner, minlength=n)
    total = int(count.sum())
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    # outages: 0-3 per vessel, 10 min to 3 h
    keep = t < 86_400
    for _ in range(3):
        when = g.uniform(0, 86_400, n)
        length = np.where(g.random(n) < 0.5, g.uniform(600, 3 * 3600, n), 0.0)
        keep &= ~((t >= when[owner]) & (t < when[owner] + length[owner]))
    # motion: course random walk, constant speed (knots), flat-earth steps in degrees
    box = BOXES[f["box"]]
    lat0 = g.uniform(box[:, 0], box[:, 1])
    lon0 = g.uniform(box[:, 2], box[:, 3])
    course0 = g.uniform(0, 360, n)
    dts = np.diff(t, prepend=0.0)
    dts[first] = 0.0
    course = course0[owner] + _segment_cumsum(g.normal(0, 1.0, total) * np.sqrt(dts / 60.0), first, count)
    speed = f["speed"][owner] * np.exp(g.normal(0, 0.03, total))
    still = f["still"][owner]
    speed = np.where(still, np.abs(g.normal(0, 0.05, total)), speed)
    step_m = speed * KNOT * dts
    north = _segment_cumsum(step_m * np.cos(np.radians(course)), first, count)
    east = _segment_cumsum(step_m * np.sin(np.radians(course)), first, count)
    lat = lat0[owner] + np.degrees(north / EARTH) + np.where(still, g.normal(0, 3e-5, total), 0.0)
    lon = lon0[owner] + np.degrees(east / (EARTH * np.cos(np.radians(lat0[owner]))))
    lon += np.where(still, g.normal(0, 3e-5, total), 0.0)
    cog = np.mod(course, 360.0)
    heading = np.mod(np.round(cog + g.normal(0, 2, total)), 360.0)
    cols = {
        "MMSI": f["mmsi"][owner],
        "t": np.floor(t).astype(np.int64),
        "LAT": np.round(lat, 5),
        "LON": np.round(lon, 5),
        "SOG": np.round(speed, 1),
        "COG": np.round(cog, 1),
        "Heading": heading,
        "Status": np.where(still, np.where(f["speed"][owner] == 0, 5, 1), 0),
        "class_a": f["class_a"][owner],
    }
    cols = {k: v[keep] for k, v in cols.items()}
    m = len(cols["t"])
    # faults: not-available values, repeated timestamps (a duplicate row), MMSI clashes
    for name, value in NOT_AVAILABLE.items():
        cols[name] = np.where(g.random(m) < (0.02 if name == "Heading" else 5e-4), value, cols[name])
    dup = np.flatnonzero(g.random(m) < 1e-3)
    cols = {k: np.insert(v, dup, v[dup]) for k, v in cols.items()}
    order = np.argsort(cols["t"], kind="stable")
    cols = {k: v[order] for k, v in cols.items()}
    cols["BaseDateTime"] = day0 + cols.pop("t").astype("timedelta64[s]")
    return cols


def _segment_cumsum(x: np.ndarray, first: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Cumulative sums of ``x`` restarting at each segment (segments ``first[i]`` of ``count[i]``)."""
    c = np.cumsum(x)
    base = np.repeat(c[first] - x[first], count)
    return c - base


def to_table(cols: dict[str, np.ndarray], names: dict[int, str]):  # noqa: ANN201 - pyarrow.Table
    """MarineCadastre's 17 columns as a pyarrow table (times as ``YYYY-MM-DDTHH:MM:SS``)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    ts = pa.array(cols["BaseDateTime"].astype("datetime64[s]"))
    m = len(ts)
    empty = pa.nulls(m, pa.string())
    vessel = np.array([names[i] for i in cols["MMSI"].tolist()], dtype=object) if names else None
    return pa.table(
        {
            "MMSI": cols["MMSI"],
            "BaseDateTime": pc.strftime(ts, format="%Y-%m-%dT%H:%M:%S"),
            "LAT": cols["LAT"],
            "LON": cols["LON"],
            "SOG": cols["SOG"],
            "COG": cols["COG"],
            "Heading": cols["Heading"],
            "VesselName": pa.array(vessel) if vessel is not None else empty,
            "IMO": empty,
            "CallSign": empty,
            "VesselType": np.where(cols["class_a"], 70, 37),
            "Status": cols["Status"],
            "Length": np.where(cols["class_a"], 120.0, 12.0),
            "Width": np.where(cols["class_a"], 20.0, 4.0),
            "Draft": np.where(cols["class_a"], 8.5, 1.5),
            "Cargo": empty,
            "TransceiverClass": np.where(cols["class_a"], "A", "B"),
        }
    )


def write_day(
    path: Path,
    f: dict[str, np.ndarray],
    day: dt.date,
    vessels: int,
    received: float,
    thin: float,
    seed: int,
    chunk: int,
) -> int:
    """Write one day (``vessels`` of the fleet ``f``); returns the number of rows."""
    import pyarrow.csv as pcsv

    g = np.random.default_rng([seed, day.toordinal()])
    chosen = np.sort(g.choice(len(f["mmsi"]), vessels, replace=False))
    clashes = g.choice(chosen, max(1, vessels // 2000), replace=False)  # two ships with one MMSI
    day0 = np.datetime64(day.isoformat(), "s")
    rows = 0
    csv_path = path.with_suffix(".csv")
    schema = to_table(day_chunk(_take(f, chosen[:1]), day0, received, thin, g), {}).schema
    options = pcsv.WriteOptions(include_header=False, quoting_style="none")
    with open(csv_path, "wb") as fh, pcsv.CSVWriter(fh, schema, write_options=options) as out:
        fh.write((",".join(COLUMNS) + "\n").encode())
        for a in range(0, vessels, chunk):
            part = _take(f, chosen[a : a + chunk])
            extra = np.isin(chosen[a : a + chunk], clashes)
            if extra.any():  # the clashing twin: same MMSI, its own box and motion
                twin = _take(f, chosen[a : a + chunk][extra])
                twin["box"] = (twin["box"] + 3) % len(BOXES)
                part = {k: np.concatenate([part[k], twin[k]]) for k in part}
            table = to_table(day_chunk(part, day0, received, thin, g), {})
            out.write_table(table)
            rows += table.num_rows
    if path.suffix == ".zip":
        with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
            z.write(csv_path, csv_path.name)
        csv_path.unlink()
    return rows


def _take(f: dict[str, np.ndarray], idx: np.ndarray) -> dict[str, np.ndarray]:
    return {k: v[idx] for k, v in f.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--days", type=int, default=1)
    p.add_argument("--start", default="2024-01-01")
    p.add_argument("--vessels", type=int, default=0, help="vessels a day (default: 20-30 k, drawn per day)")
    p.add_argument("--received", type=float, default=0.8, help="probability that a report is received")
    p.add_argument("--thin", type=float, default=60.0, help="at most one report a vessel per THIN s (0: every report)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--chunk", type=int, default=2000, help="vessels per chunk written")
    p.add_argument("--zip", action="store_true", help="write AIS_*.zip (a CSV inside) as MarineCadastre ships them")
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    f = fleet(max(40_000, 2 * args.vessels), args.seed)
    g = np.random.default_rng(args.seed)
    start = dt.date.fromisoformat(args.start)
    total = 0
    for d in range(args.days):
        day = start + dt.timedelta(days=d)
        vessels = args.vessels or int(g.integers(20_000, 30_001))
        path = args.out / f"AIS_{day:%Y_%m_%d}.{'zip' if args.zip else 'csv'}"
        t0 = time.perf_counter()
        rows = write_day(path, f, day, vessels, args.received, args.thin, args.seed, args.chunk)
        total += rows
        print(f"{path.name}: {vessels} vessels, {rows:,} reports, {time.perf_counter() - t0:.1f} s", flush=True)
    print(f"total: {total:,} reports in {args.days} files under {args.out}")


if __name__ == "__main__":
    main()
