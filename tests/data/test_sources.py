"""Reading trajectory files (torchsde_lti.data.sources): .traj, CSV, Parquet, malformed input,
file lookup, and no global side effects.

Oracles: values written into the test files here, plain-Python re-counts of the shipped files.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from torchsde_lti.data import AIS_COLUMNS, load_tracks, locate_file, read_reports

ROOT = Path(__file__).resolve().parents[2]


def _traj_line(
    obj: str,
    times: list[str],
    lonlat: list[tuple[float, float]],
    uuid: bool = True,
    props: list[tuple[str, str, list[str]]] = (),
    trailing: str = "",
) -> str:
    head = ["*T*"] + (["5e3b1b1c-0000-4000-8000-000000000000"] if uuid else []) + ["terrestrial", str(len(times)), "0"]
    head += ["*P*", "terrestrial", "2", "1", "1", str(len(props))] + [
        x for name, kind, _ in props for x in (name, kind)
    ]
    pts = []
    for k, (when, (lon, lat)) in enumerate(zip(times, lonlat)):
        pts += [obj, when, repr(lon), repr(lat)] + [vals[k] for _, _, vals in props]
    return ",".join(head + pts) + trailing


T3 = ["2020-06-30 00:00:01", "2020-06-30 00:00:02", "2020-06-30 00:01:00"]
P3 = [(-74.01, 40.61), (-74.02, 40.62), (-74.03, 40.63)]


@pytest.mark.parametrize("uuid", [True, False])
@pytest.mark.parametrize("trailing", ["", ","])
def test_traj_layouts(tmp_path: Path, uuid: bool, trailing: str) -> None:
    f = tmp_path / "a.traj"
    f.write_text(_traj_line("42", T3, P3, uuid=uuid, trailing=trailing) + "\n")
    r = read_reports(f)
    assert r.object_id.dtype == np.int64 and list(r.object_id) == [42] * 3
    np.testing.assert_array_equal(r.lon, [p[0] for p in P3])
    np.testing.assert_array_equal(r.lat, [p[1] for p in P3])
    assert (r.time[2] - r.time[0]) / np.timedelta64(1, "s") == 59.0
    assert r.rows == 3 and r.malformed == 0 and r.alt is None and r.sog is None


def test_traj_string_properties_with_commas_and_altitude(tmp_path: Path) -> None:
    f = tmp_path / "b.traj"
    props = [("altitude", "1", ["100", "200", "300"]), ("vessel-name", "2", ["A, B", "A, B", "C"])]
    f.write_text(_traj_line("UAL1", T3, P3, props=props) + "\n")
    r = read_reports(f)
    assert r.object_id.dtype.kind == "U" and r.object_id[0] == "UAL1"
    np.testing.assert_array_equal(r.alt, [100.0, 200.0, 300.0])
    np.testing.assert_array_equal(r.lat, [p[1] for p in P3])


def test_traj_altitude_kept_whatever_the_line_order(tmp_path: Path) -> None:
    # the first readable line decided: a first line without altitude dropped every later altitude
    with_alt = _traj_line("AB2", T3, P3, props=[("altitude", "1", ["3000", "3500", "4000"])])
    without = _traj_line("AB1", T3, P3)
    f = tmp_path / "alt.traj"
    for lines, nan_first in (([with_alt, without], False), ([without, with_alt], True)):
        f.write_text("\n".join(lines) + "\n")
        r = read_reports(f)
        assert r.alt is not None and len(r.alt) == 6
        alt, nan = (r.alt[3:], r.alt[:3]) if nan_first else (r.alt[:3], r.alt[3:])
        np.testing.assert_array_equal(alt, [3000.0, 3500.0, 4000.0])
        assert np.isnan(nan).all()
        assert load_tracks(f).dims == 3


def test_a_utf8_byte_order_mark_loses_no_line(tmp_path: Path) -> None:
    # the mark stayed in front of "*T*" (and of "#"): the first trajectory was malformed
    f = tmp_path / "bom.traj"
    f.write_text(_traj_line("1", T3, P3) + "\n" + _traj_line("2", T3, P3) + "\n", encoding="utf-8-sig")
    r = read_reports(f)
    assert r.malformed == 0 and sorted(set(r.object_id.tolist())) == [1, 2]
    f = tmp_path / "bom.csv"
    rows = "".join(f"F1,{t},{lon},{lat}\n" for t, (lon, lat) in zip(T3, P3))
    f.write_text("# object_id timestamp longitude latitude\n" + rows, encoding="utf-8-sig")
    r = read_reports(f, {"id": 0, "time": 1, "lon": 2, "lat": 3})
    assert (r.rows, r.malformed) == (3, 0) and list(r.lat) == [p[1] for p in P3]


def test_traj_malformed_lines_are_counted_not_silent(tmp_path: Path) -> None:
    f = tmp_path / "c.traj"
    good = _traj_line("1", T3, P3)
    f.write_text("\n".join([good, "*T*,bad", good.replace("40.62", "forty"), "", _traj_line("2", T3, P3)]) + "\n")
    r = read_reports(f)
    assert r.malformed == 2 and len(r.malformed_examples) == 2
    assert "line 2" in r.malformed_examples[0] and "line 3" in r.malformed_examples[1]
    assert sorted(set(r.object_id.tolist())) == [1, 2]
    tracks = load_tracks(f)
    assert tracks.summary.malformed == 2 and "malformed" in str(tracks.summary)


def test_csv_ais_header_recognised_and_values(tmp_path: Path) -> None:
    f = tmp_path / "ais.csv"
    f.write_text(
        "BaseDateTime,LON,LAT,MMSI,SOG,COG,Heading\n"
        "2020-06-30T00:00:00,-74.0,40.6,367000001,10.0,90.0,90\n"
        "2020-06-30T00:01:00,-74.01,40.6,367000001,102.3,360.0,511\n"
        "2020-06-30T00:02:00,-74.02,40.6,367000001,,45.0,90\n"
    )
    r = read_reports(f)
    assert r.object_id.dtype == np.int64 and r.sog is not None and r.rows == 3 and r.malformed == 0
    np.testing.assert_allclose(r.lon, [-74.0, -74.01, -74.02])
    assert np.isnan(r.sog[2]) and r.cog[1] == 360.0
    tr = load_tracks(f)
    # SOG 102.3 / COG 360 are AIS "not available"; an empty SOG too
    assert np.isfinite(tr.vel[0]).all() and np.isnan(tr.vel[1:]).all()
    np.testing.assert_allclose(tr.vel[0], [10 * 1852 / 3600, 0.0], atol=1e-9)  # due east at 10 kn


def test_csv_named_columns_comment_header_ragged_rows_and_offsets(tmp_path: Path) -> None:
    f = tmp_path / "points.csv"
    f.write_text(
        "# object_id timestamp longitude latitude altitude\n"
        "F1,2014-07-01 15:45:43-0000,28.8,40.9,1000\n"
        "F1,2014-07-01 17:46:43+0200,28.9,40.95,1100\n"
        "F1,2014-07-01 15:47:43-0000,29.0,,1200,extra\n"
        "F1,2014-07-01 15:48:43-0000,north,41.0,1300\n"
        "F1,2014-07-01 15:49:43-0000,29.1,41.05,1400\n"
    )
    r = read_reports(f, {"id": 0, "time": 1, "lon": 2, "lat": 3, "alt": 4}, altitude_unit="ft")
    assert r.rows == 5 and r.malformed == 2  # one ragged row, one unreadable longitude
    assert list(r.object_id) == ["F1"] * 3
    assert (r.time[1] - r.time[0]) / np.timedelta64(1, "s") == 60.0  # +0200 converted to UTC
    np.testing.assert_allclose(r.alt, [304.8, 335.28, 426.72])
    assert any("fields" in e for e in r.malformed_examples) and any("lon" in e for e in r.malformed_examples)
    with pytest.raises(ValueError, match="MarineCadastre"):
        read_reports(f)
    with pytest.raises(ValueError, match="missing roles"):
        read_reports(f, {"id": 0, "time": 1})


def test_one_unreadable_time_among_fractional_seconds_drops_that_row_only(tmp_path: Path) -> None:
    # the column's cast failed on the one bad row, and the fallback formats had no fractions: 0 of 6 read
    f = tmp_path / "frac.csv"
    rows = [f"1,2020-06-30T00:00:{s:02d}.500,40.7,-74.0{s}" for s in range(5)]
    f.write_text("\n".join(["id,t,lat,lon", *rows[:3], "1,not-a-time,40.7,-74.0", *rows[3:], ""]))
    r = read_reports(f, {"id": "id", "time": "t", "lat": "lat", "lon": "lon"})
    assert r.rows == 6 and r.malformed == 1 and "row 4" in r.malformed_examples[0]
    assert [str(t) for t in r.time] == [f"2020-06-30T00:00:{s:02d}.500000" for s in range(5)]
    f.write_text("id,t,lat,lon\n1,2020-06-30T02:00:01.25+02:00,1,2\n1,2020-06-30T00:00:02.5Z,1,2\n1,x,1,2\n")
    r = read_reports(f, {"id": "id", "time": "t", "lat": "lat", "lon": "lon"})
    assert r.malformed == 1 and [str(t) for t in r.time] == ["2020-06-30T00:00:01.250000", "2020-06-30T00:00:02.500000"]


COLS = {"id": "id", "time": "t", "lat": "lat", "lon": "lon"}


def _time_csv(path: Path, times: list[str]) -> Path:
    path.write_text("id,t,lat,lon\n" + "".join(f"1,{t},40.0,-74.0\n" for t in times))
    return path


@pytest.mark.parametrize(
    "odd",
    [
        "2020-06-30T00:00:30.123456789",
        " 2020-06-30T00:00:30.5",
        "2020-06-30T00:00:30.5Z",
        "2020-06-30T00:00:30.5+00:00",
    ],
)
def test_one_odd_iso_time_does_not_make_the_other_rows_malformed(tmp_path: Path, odd: str) -> None:
    # Arrow's cast reads a column all or nothing: one row it cannot read made all 21 malformed
    times = [f"2020-06-30T00:{m:02d}:00.250" for m in range(20)]
    r = read_reports(_time_csv(tmp_path / "odd.csv", [*times, odd]), COLS)
    assert (r.rows, r.malformed) == (21, 0)
    assert [str(t) for t in r.time[:20]] == [f"{t}000" for t in times]
    assert str(r.time[20]).startswith("2020-06-30T00:00:30.")
    # a row that is truly no time (30 February, hour 24, a 60-minute offset) is the only one lost
    bad = ["2020-02-30T00:00:00", "2020-06-30T24:00:00", "2020-06-30T00:00:00+01:60", "yesterday"]
    r = read_reports(_time_csv(tmp_path / "bad.csv", [*times, odd, *bad]), COLS)
    assert (r.rows, r.malformed, len(r.time)) == (25, 4, 21)
    assert all("time" in e for e in r.malformed_examples)


def test_nanosecond_fractions_truncate_to_the_microsecond(tmp_path: Path) -> None:
    times = [f"2020-06-30T00:{m:02d}:00.123456789" for m in range(10)]  # pandas' datetime64[ns] text
    r = read_reports(_time_csv(tmp_path / "ns.csv", times), COLS)
    assert r.malformed == 0 and [str(t) for t in r.time] == [t[:-3] for t in times]


def test_zone_designators_and_plain_times_mix_in_one_column(tmp_path: Path) -> None:
    # Z, offsets and no zone (taken as UTC) in one column: each converted to UTC, none dropped
    times = ["2020-06-30T00:00:00Z", "2020-06-30 00:01:00", "2020-06-30T02:02:00+02:00", "2020-06-29T19:03:00-0500"]
    r = read_reports(_time_csv(tmp_path / "zones.csv", times), COLS)
    assert r.malformed == 0
    assert [str(t) for t in r.time] == [f"2020-06-30T00:0{m}:00.000000" for m in range(4)]


@pytest.mark.parametrize(
    "form",
    [
        "2020-06-30",
        "2020-06-30T12",
        "2020-06-30 12:34",
        "2020-06-30T12:34:56.1",
        "2020-06-30T12:34:56.123456",
        "2020-06-30T12Z",
        "2020-06-30T12:34:56+02",
        "2020-06-30T12:34:56+0230",
        "2020-06-30 12:34:56.5-02:30",
    ],
)
def test_a_time_reads_the_same_in_a_clean_column_and_beside_an_unreadable_row(tmp_path: Path, form: str) -> None:
    # a clean column is read by one Arrow cast, a column with a bad row row by row: same times
    alone = read_reports(_time_csv(tmp_path / "alone.csv", [form]), COLS)
    beside = read_reports(_time_csv(tmp_path / "beside.csv", [form, "not a time"]), COLS)
    assert (alone.malformed, beside.malformed) == (0, 1)
    assert alone.time[0] == beside.time[0]


def test_positions_above_a_header_line_do_not_count_it_as_a_row(tmp_path: Path) -> None:
    f = tmp_path / "pos.csv"
    data = "1,2020-06-30T00:00:00,10,20\n1,2020-06-30T00:00:10,10,20.001\n"
    for text in ("MMSI,BaseDateTime,LAT,LON\n" + data, data):  # with and without a header
        f.write_text(text)
        r = read_reports(f, {"id": 0, "time": 1, "lat": 2, "lon": 3})
        assert r.rows == 2 and r.malformed == 0 and list(r.lon) == [20.0, 20.001]


def test_parquet_matches_csv(tmp_path: Path) -> None:
    pa = pytest.importorskip("pyarrow")
    pcsv = pytest.importorskip("pyarrow.csv")
    pq = pytest.importorskip("pyarrow.parquet")
    hour = locate_file("NYHarbor_2020_06_30_first_hour.csv")
    table = pcsv.read_csv(hour).slice(0, 2000)
    pq.write_table(table, tmp_path / "h.parquet")
    pcsv.write_csv(table, tmp_path / "h.csv")
    a, b = read_reports(tmp_path / "h.parquet"), read_reports(tmp_path / "h.csv")
    for field in ("object_id", "time", "lat", "lon", "sog", "cog"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert a.rows == b.rows == 2000 and isinstance(pa.__version__, str)


def test_missing_file_names_path_and_where_it_looked(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError) as err:
        load_tracks("US_coastal_2020_06_31.traj")
    msg = str(err.value)
    assert "US_coastal_2020_06_31.traj" in msg and str(Path.cwd()) in msg
    if locate_file.__module__ and _has_tracktable():
        assert "tracktable_data" in msg and "US_coastal_2020_06_30.traj" in msg  # the close match
    with pytest.raises(FileNotFoundError, match=str(tmp_path / "nope.csv")):
        read_reports(tmp_path / "nope.csv")


def _has_tracktable() -> bool:
    import importlib.util

    return importlib.util.find_spec("tracktable_data") is not None


GLOBAL_STATE = r"""
import json, logging, sys, warnings
import numpy as np, torch
def state():
    root = logging.getLogger()
    return {"tracebacklimit": getattr(sys, "tracebacklimit", None), "root_level": root.level,
            "root_handlers": len(root.handlers), "loggers": sorted(logging.root.manager.loggerDict),
            "warnings": len(warnings.filters), "np_err": np.geterr(), "np_print": np.get_printoptions()["precision"],
            "dtype": str(torch.get_default_dtype()), "threads": torch.get_num_threads()}
before = state()
import torchsde_lti as tl
imported = state()
tracks = tl.data.load_tracks("NYHarbor_2020_06_30_first_hour.csv", course_encoding="ais_int12", min_reports=5)
tl.data.load_tracks("prediction_observed_trajectories.traj")
try:
    tl.data.load_tracks("no_such_file.traj")
except FileNotFoundError:
    pass
after = state()
new_loggers = set(after.pop("loggers")) - set(imported.pop("loggers"))
before.pop("loggers")
print(json.dumps({"before": before, "imported": imported, "after": after, "tracktable_modules": sorted(
    m for m in sys.modules if m.startswith("tracktable_data")), "new_loggers": sorted(new_loggers),
    "reports": tracks.num_reports}))
"""


def test_a_copy_of_the_installed_reserved_file_is_refused_by_content(tmp_path: Path, monkeypatch) -> None:
    # whatever release of the reserved files the data folder holds: same file or same bytes is refused
    from torchsde_lti.data import sources
    from torchsde_lti.data.modules import TrackDataModule

    shipped = tmp_path / "pkg" / "NYHarbor_2020_12_08.traj"
    shipped.parent.mkdir()
    shipped.write_text(_traj_line("1", T3, P3) + "\n")
    monkeypatch.setattr(sources, "_example_dirs", lambda: [shipped.parent])
    assert locate_file(shipped.name) == shipped
    copy, other = tmp_path / "mine.traj", tmp_path / "other.traj"
    copy.write_bytes(shipped.read_bytes())
    links = [copy]
    try:
        os.link(shipped, tmp_path / "hard.traj")
        links.append(tmp_path / "hard.traj")
    except OSError:  # a file system without hard links
        pass
    for path in links:
        with pytest.raises(ValueError, match="is NYHarbor_2020_12_08.traj, reserved for evaluation"):
            TrackDataModule(str(path))
    other.write_text(_traj_line("2", T3, P3) + "\n")  # same size, other bytes: a training file
    assert other.stat().st_size == shipped.stat().st_size
    assert TrackDataModule(str(other)).source == str(other)


def test_loading_changes_no_global_state() -> None:
    """tracktable_data.data sets sys.tracebacklimit = 0 and configures the root logger at import:
    the loader finds the files without executing it, and changes nothing else either."""
    pytest.importorskip("pyarrow")
    if not _has_tracktable():
        pytest.skip("tracktable-data not installed")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    res = subprocess.run([sys.executable, "-c", GLOBAL_STATE], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["imported"] == out["after"]  # loading changes nothing
    # importing changes nothing either, except one warnings filter that sympy adds when torch.export imports it
    assert {k: v for k, v in out["before"].items() if k != "warnings"} == {
        k: v for k, v in out["imported"].items() if k != "warnings"
    }
    assert out["after"]["tracebacklimit"] is None and out["after"]["root_handlers"] == 0
    assert out["tracktable_modules"] in ([], ["tracktable_data"])  # the metadata-only __init__ at most
    assert not [name for name in out["new_loggers"] if name.startswith("tracktable")]
    assert out["reports"] == 8658


def test_ais_columns_constant() -> None:
    assert set(AIS_COLUMNS) == {"id", "time", "lat", "lon", "sog", "cog"}


def test_csv_numeric_times_are_epoch_seconds(tmp_path: Path) -> None:
    """A CSV time column of numbers (read as strings) is seconds since 1970-01-01 UTC."""
    path = tmp_path / "epoch.csv"
    path.write_text("id,t,lat,lon\na,1600000000,40.0,-74.0\na,1600000010.5,40.01,-74.0\nb,x,41.0,-73.0\n")
    rep = read_reports(path, {"id": "id", "time": "t", "lat": "lat", "lon": "lon"})
    expected = np.array(["2020-09-13T12:26:40", "2020-09-13T12:26:50.5"], dtype="datetime64[us]")
    np.testing.assert_array_equal(rep.time[:2], expected)

    assert rep.malformed == 1


def test_epoch_seconds_with_sub_microsecond_digits_nan_and_nanosecond_timestamps(tmp_path: Path) -> None:
    """Seconds as Python's time.time() writes them (more than 6 decimals) round to the
    microsecond; a NaN time is one malformed row; a timestamp[ns] column truncates to µs."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = {"id": "id", "time": "t", "lat": "lat", "lon": "lon"}
    csv = tmp_path / "fine.csv"
    csv.write_text("id,t,lat,lon\na,1733201014.6162397,40.0,-74.0\na,1733201015.1234565,40.001,-74.0\n")
    got = read_reports(csv, cols).time
    want = np.array(["2024-12-03T04:43:34.616240", "2024-12-03T04:43:35.123456"], dtype="datetime64[us]")
    assert np.abs(got - want).max() <= np.timedelta64(1, "us")
    for name, column, kept, malformed in (
        ("nan", pa.array([1600000000.0, float("nan"), 1600000020.0]), 2, 1),
        ("fine", pa.array([1600000000.0, 1600000010.123456789, 1600000020.0]), 3, 0),
        ("ns", pa.array([1600000000_000000000, 1600000010_123456789, 1600000020_000000000], pa.timestamp("ns")), 3, 0),
    ):
        path = tmp_path / f"{name}.parquet"
        pq.write_table(
            pa.table({"id": ["a"] * 3, "t": column, "lat": [40.0, 40.001, 40.002], "lon": [-74.0] * 3}), path
        )
        rep = read_reports(path, cols)
        assert (len(rep.time), rep.malformed) == (kept, malformed), name
    assert rep.time[1] == np.datetime64("2020-09-13T12:26:50.123456", "us")


def test_distinct_ids_that_read_as_one_integer_stay_distinct(tmp_path: Path) -> None:
    path = tmp_path / "ids.csv"
    rows = ["id,t,lat,lon", "007,2020-06-30T00:00:00,40.0,-74.0", "007,2020-06-30T00:01:00,40.001,-74.0"]
    rows += ["7,2020-06-30T00:00:00,-33.9,151.2", "7,2020-06-30T00:01:00,-33.901,151.2"]
    path.write_text("\n".join(rows) + "\n")
    cols = {"id": "id", "time": "t", "lat": "lat", "lon": "lon"}
    assert sorted(set(read_reports(path, cols).object_id.tolist())) == ["007", "7"]
    assert load_tracks(path, cols, min_reports=2).summary.tracks == 2
    path.write_text(path.read_text().replace("007", "8"))  # distinct integers: int64 ids
    assert sorted(set(read_reports(path, cols).object_id.tolist())) == [7, 8]


def test_csv_columns_mix_names_and_positions(tmp_path: Path) -> None:
    path = tmp_path / "mixed.csv"
    path.write_text("lon,vessel,when,lat\n-74.0,a,2020-06-30T00:00:00,40.0\n-74.0,a,2020-06-30T00:01:00,40.001\n")
    rep = read_reports(path, {"id": "vessel", "time": "when", "lat": 3, "lon": 0})
    np.testing.assert_array_equal(rep.lat, [40.0, 40.001])
    np.testing.assert_array_equal(rep.lon, [-74.0, -74.0])
    with pytest.raises(ValueError, match="not in the header"):
        read_reports(path, {"id": "vessel", "time": "when", "lat": 7, "lon": 0})


def test_traj_rows_account_for_malformed_lines(tmp_path: Path) -> None:
    """rows = malformed + … + reports also when a .traj line is malformed (one row per line)."""
    f = tmp_path / "acc.traj"
    good = _traj_line("1", T3, P3)
    f.write_text("\n".join([good, good.rsplit(",", 1)[0].replace('"1"', '"2"')]) + "\n")
    s = load_tracks(f, min_reports=2).summary
    accounted = s.malformed + s.invalid_positions + s.repeated_timestamps + s.jump_reports_dropped
    assert s.malformed == 1 and s.rows == accounted + s.short_reports + s.reports


def test_no_track_long_enough_raises_the_designed_error(tmp_path: Path) -> None:
    path = tmp_path / "short.csv"
    path.write_text("id,t,lat,lon\na,2020-06-30T00:00:00,40.0,-74.0\nb,2020-06-30T00:00:00,41.0,-74.0\n")
    with pytest.raises(ValueError, match="no track of >= 2 reports is left"):
        load_tracks(path, {"id": "id", "time": "t", "lat": "lat", "lon": "lon"}, min_reports=2)
