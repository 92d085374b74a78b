"""Loaders that never mislead (issue 38, item 4): every case a new user met on real files gives a
clear error naming the argument, the file, the column and the row, or a drop counted by name.

Each test failed on the loaders before this change (they are written against the keyword API that
both versions share)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("pyarrow")
pytest.importorskip("pymap3d")

from torchsde_lti.data import (  # noqa: E402
    load_tracks,
    prepare_tracks,
    read_reports,
    split_objects,
    split_time,
    track_windows,
)
from torchsde_lti.data.modules import TrackDataModule  # noqa: E402

HEADER = "MMSI,BaseDateTime,LAT,LON,SOG,COG,Heading\n"


def _track(mmsi: int, lat: float = 40.6, lon: float = -74.0, n: int = 6, extra: str = "5.0,90.0,91") -> list[str]:
    """n reports one minute apart, moving north 110 m a minute (a plausible ship)."""
    return [f"{mmsi},2020-06-30T00:{i:02d}:00,{lat + 0.001 * i:.4f},{lon},{extra}" for i in range(n)]


def _write(path: Path, rows: list[str], header: str = HEADER) -> Path:
    path.write_text(header + "\n".join(rows) + "\n")
    return path


# ---------------------------------------------------------------------------- AIS "not available", ranges
def test_ais_not_available_values_are_dropped_and_counted_by_name(tmp_path: Path) -> None:
    rows = (
        _track(1)
        + [f"2,2020-06-30T00:{i:02d}:00,91,{-74 + 0.001 * i},5.0,90.0,91" for i in range(6)]  # AIS: lat n/a
        + _track(3, lon=181.0)  # AIS: longitude not available (was wrapped to -179)
        + _track(4, lon=200.0)  # out of range (was wrapped to -160)
        + _track(5, lat=-95.0)
        + [r.replace("5.0,90.0,91", "102.3,360.0,511") for r in _track(6)]  # SOG, COG, heading n/a
        + [r.replace("5.0,90.0,91", "150.0,361.5,400") for r in _track(7)]  # out of range: unavailable
    )
    tracks = load_tracks(_write(tmp_path / "ais.csv", rows), {**_AIS, "heading": "Heading"}, min_reports=2)
    s = tracks.summary
    assert s.invalid == {"lat_not_available": 6, "lat_out_of_range": 6, "lon_not_available": 6, "lon_out_of_range": 6}
    assert s.invalid_positions == sum(s.invalid.values()) == 24
    assert s.unavailable == {
        "sog_not_available": 6,
        "sog_out_of_range": 6,
        "cog_not_available": 6,
        "cog_out_of_range": 6,
        "heading_not_available": 6,
        "heading_out_of_range": 6,
    }
    assert sorted(tracks.object_id.tolist()) == [1, 6, 7]
    assert np.all(tracks.lon == -74.0)  # nothing wrapped
    assert np.isnan(tracks.vel[tracks.offsets[1] :]).all() and np.isfinite(tracks.vel[: tracks.offsets[1]]).all()
    text = str(s)
    for name in ("lat_not_available 6", "lon_out_of_range 6", "sog_not_available 6", "heading_not_available 6"):
        assert name in text


_AIS = {"id": "MMSI", "time": "BaseDateTime", "lat": "LAT", "lon": "LON", "sog": "SOG", "cog": "COG"}


def test_no_valid_position_names_the_reasons(tmp_path: Path) -> None:
    rows = [f"1,2020-06-30T00:{i:02d}:00,91,{-74 + 0.001 * i},,," for i in range(6)]
    path = _write(tmp_path / "na.csv", rows + _track(2, lon=181.0))
    with pytest.raises(ValueError, match=r"na\.csv: no report has a valid position.*lat_not_available 6"):
        load_tracks(path)


def test_unwrapped_traj_longitudes_are_decoded_and_counted() -> None:
    """tracktable writes longitudes unwrapped across the antimeridian: the format's convention,
    decoded into [-180, 180) by the .traj reader and counted (CSV and Parquet values are not)."""
    r = read_reports("SampleTrajectories.traj")
    assert r.decoded["lon_unwrapped"] > 20_000 and np.all((r.lon >= -180) & (r.lon < 180))
    assert load_tracks("SampleTrajectories.traj").summary.decoded == r.decoded


def test_one_column_for_lat_and_lon_is_refused(tmp_path: Path) -> None:
    path = _write(tmp_path / "a.csv", _track(1))
    with pytest.raises(ValueError, match="'LAT' is lat and lon"):
        load_tracks(path, {"id": "MMSI", "time": "BaseDateTime", "lat": "LAT", "lon": "LAT"})
    with pytest.raises(ValueError, match="2 is lat and lon"):
        read_reports(path, {"id": 0, "time": 1, "lat": 2, "lon": 2})


def test_a_parquet_latitude_of_booleans_is_refused(tmp_path: Path) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = tmp_path / "b.parquet"
    n = 5
    pq.write_table(
        pa.table(
            {
                "MMSI": [1] * n,
                "BaseDateTime": [f"2020-06-30T00:0{i}:00" for i in range(n)],
                "LAT": [True] * n,
                "LON": [-74.0] * n,
                "SOG": [1.0] * n,
                "COG": [1.0] * n,
            }
        ),
        path,
    )
    with pytest.raises(TypeError, match=re.escape(f"{path}: the lat column 'LAT' holds bool values, not numbers")):
        load_tracks(path)


@pytest.mark.parametrize("reference", [(91.0, -74.0), (float("nan"), -74.0), (40.0, 181.0), (40.0, float("nan"))])
def test_a_common_frame_reference_out_of_range_or_nan_is_refused(tmp_path: Path, reference: tuple) -> None:
    path = _write(tmp_path / "a.csv", _track(1))
    with pytest.raises(ValueError, match="reference (latitude|longitude)"):
        load_tracks(path, frame="common", reference=reference)
    with pytest.raises(ValueError, match="reference (latitude|longitude)"):
        prepare_tracks(read_reports(path), frame="common", reference=reference)


# ---------------------------------------------------------------------------- lat/lon swapped
def _swapped_coast(tmp_path: Path, west_of: float | None = None, step: int = 40) -> Path:
    """Every ``step``-th report of the US national day (both coasts, Alaska, Hawaii; or those west of
    ``west_of``) written with the MarineCadastre header and latitude and longitude exchanged."""
    r = read_reports("US_coastal_2020_06_30.traj")
    keep = np.flatnonzero(r.lon < (west_of if west_of is not None else np.inf))[::step]
    rows = [
        f"{i},{str(t)[:19]},{lon:.5f},{lat:.5f},,,"
        for i, t, lat, lon in zip(r.object_id[keep], r.time[keep], r.lat[keep], r.lon[keep], strict=True)
    ]
    return _write(tmp_path / "swapped.csv", rows)


def test_swapped_columns_name_the_columns_and_the_fix(tmp_path: Path) -> None:
    path = _swapped_coast(tmp_path)  # the whole coast, the MarineCadastre header recognised
    with pytest.raises(ValueError, match="look swapped") as err:
        load_tracks(path, v_max=35.0)
    message = str(err.value)
    assert str(path) in message and "'LAT'" in message and "'LON'" in message
    assert "'lat': 'LON', 'lon': 'LAT'" in message  # the fix, ready to paste
    west = _swapped_coast(tmp_path, west_of=-100.0, step=5)  # columns named: the rule "most positions invalid"
    named = {"id": "MMSI", "time": "BaseDateTime", "lat": "LAT", "lon": "LON"}
    with pytest.raises(ValueError, match=r"look swapped: (\d+) of \1 reports have no valid position") as err:
        load_tracks(west, named)
    assert "columns={'id': 'MMSI', 'time': 'BaseDateTime', 'lat': 'LON', 'lon': 'LAT'}" in str(err.value)
    assert len(load_tracks(west, {**named, "lat": "LON", "lon": "LAT"})) > 10  # the fix loads


def test_swapped_columns_all_south_east_under_the_marinecadastre_header(tmp_path: Path) -> None:
    """NY Harbor with LAT and LON exchanged: every position valid, all of them in Antarctica."""
    rows = [f"{m},2020-06-30T00:{i:02d}:00,{-74.0 + 0.001 * i:.4f},40.6,," for m in (1, 2) for i in range(6)]
    path = _write(tmp_path / "ny.csv", rows, "MMSI,BaseDateTime,LAT,LON,SOG,COG\n")
    with pytest.raises(
        ValueError, match="look swapped: all 12 valid positions are south of the equator and east of Greenwich"
    ):
        load_tracks(path)
    cols = {"id": "MMSI", "time": "BaseDateTime", "lat": "LAT", "lon": "LON"}
    assert len(load_tracks(path, cols)) == 2  # named columns: taken as given
    australia = _write(tmp_path / "au.csv", _track(1, lat=-33.9, lon=151.2), "MMSI,BaseDateTime,LAT,LON,SOG,COG,H\n")
    assert len(load_tracks(australia)) == 1  # (swapped, 151.2 would be no latitude: no swap)


# ---------------------------------------------------------------------------- ids and times that do not read
@pytest.mark.parametrize(
    ("rows", "kwargs", "expected"),
    [
        (
            [r[1:] for r in _track(1)],
            {},
            r"the id column 'MMSI' is empty in 6 of 6 rows, e.g. data row 1: id column 'MMSI' unreadable: empty",
        ),
        (
            [f"1,1e20,40.6,-74.0,,,{i}" for i in range(5)],
            {},
            r"the time column 'BaseDateTime' does not read .* in 5 of 5 rows, e.g. data row 1: .* '1e20'",
        ),
        (
            _track(1),
            {"time_format": "%d/%m/%Y %H:%M"},
            r"time column 'BaseDateTime' does not read with time_format='%d/%m/%Y %H:%M' in 6 of 6 rows, "
            r"e.g. data row 1: .*'2020-06-30T00:00:00'",
        ),
        ([], {}, "a header and no data rows"),
    ],
)
def test_ids_or_times_that_do_not_read_say_so(tmp_path: Path, rows: list[str], kwargs: dict, expected: str) -> None:
    path = _write(tmp_path / "bad.csv", rows)
    with pytest.raises(ValueError, match=expected) as err:
        load_tracks(path, **kwargs)
    assert str(path) in str(err.value) and "valid position" not in str(err.value)


def test_an_unreadable_row_is_named_with_its_column_and_value(tmp_path: Path) -> None:
    path = _write(tmp_path / "one.csv", _track(1) + ["1,2020-06-30T00:30:00,north,-74.0,,,"])
    r = read_reports(path)
    assert r.malformed == 1 and r.malformed_examples == ("data row 7: lat column 'LAT' unreadable: 'north'",)


# ---------------------------------------------------------------------------- files pyarrow cannot read
@pytest.mark.parametrize(
    ("name", "content", "expected"),
    [
        ("empty.csv", b"", "no data: the file is empty"),
        ("comments.csv", b"# a\n# b\n", "no data: the file is empty after 2 '#' comment lines"),
        ("garbage.csv", bytes(range(256)) * 8, "not a CSV text file"),
        ("latin1.csv", HEADER.encode() + b"caf\xe9,2020-06-30T00:00:00,40,-74,,,\n", "cannot be read as CSV"),
        ("truncated.parquet", b"PAR1\x15\x04\x15\x00", "cannot be read as PARQUET"),
        ("empty.parquet", b"", "cannot be read as PARQUET"),
    ],
)
def test_unreadable_files_are_named(tmp_path: Path, name: str, content: bytes, expected: str) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(ValueError, match=re.escape(f"{path}: ") + ".*" + re.escape(expected)):
        load_tracks(path)
    # the same through data.source= (the training job builds this DataModule from the config)
    dm = TrackDataModule(str(path))
    with pytest.raises(ValueError, match=re.escape(str(path))):
        dm.setup("fit")


def test_a_truncated_parquet_file_is_named(tmp_path: Path) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    whole = tmp_path / "whole.parquet"
    n = 50
    pq.write_table(
        pa.table({"MMSI": [1] * n, "BaseDateTime": ["2020-06-30T00:00:00"] * n, "LAT": [40.0] * n, "LON": [-74.0] * n}),
        whole,
    )
    cut = tmp_path / "cut.parquet"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    with pytest.raises(ValueError, match=re.escape(f"{cut}: cannot be read as PARQUET")):
        load_tracks(cut)


def test_column_positions_out_of_range_name_the_position_and_the_column_count(tmp_path: Path) -> None:
    path = _write(tmp_path / "p.csv", _track(1), header="")
    with pytest.raises(ValueError, match=r"columns\['lat'\]=99 is out of range: the file has 7 columns"):
        load_tracks(path, {"id": 0, "time": 1, "lat": 99, "lon": 3})
    path = _write(tmp_path / "h.csv", _track(1), header="a,b,c,d,e,f,g\n")
    with pytest.raises(ValueError, match=r"columns\['lon'\]=12 is not in the header .* 7 columns"):
        load_tracks(path, {"id": 0, "time": 1, "lat": "c", "lon": 12})


def test_columns_as_a_list_is_a_type_error_naming_columns(tmp_path: Path) -> None:
    path = _write(tmp_path / "a.csv", _track(1))
    with pytest.raises(TypeError, match="^columns must be a mapping"):
        load_tracks(path, ["MMSI", "BaseDateTime", "LAT", "LON"])


def test_a_hash_comment_header_is_not_called_the_header(tmp_path: Path) -> None:
    path = _write(tmp_path / "c.csv", _track(1), header="# " + HEADER)
    with pytest.raises(ValueError, match="comment line 1") as err:
        load_tracks(path)
    message = str(err.value)
    assert "header found" not in message and "line 2" in message
    # the fix it proposes reads the file
    suggested = eval(re.search(r"columns=(\{[^}]*\})", message).group(1))  # noqa: S307 - our own message
    assert suggested == {"id": 0, "time": 1, "lat": 2, "lon": 3, "sog": 4, "cog": 5, "heading": 6}
    assert len(load_tracks(path, suggested)) == 1
    data_first = _write(tmp_path / "d.csv", _track(1), header="")
    with pytest.raises(ValueError, match="line 1, where the header should be, holds data"):
        load_tracks(data_first)


# ---------------------------------------------------------------------------- arguments
def test_cut_times_and_boundaries_are_checked_naming_the_argument(tmp_path: Path) -> None:
    path = _write(tmp_path / "a.csv", _track(1) + _track(2))
    with pytest.raises(TypeError, match="cut_times must be a sequence of instants, not a single str"):
        load_tracks(path, cut_times="2020-06-30T00:03:00")
    with pytest.raises(ValueError, match=r"cut_times\[1\]='2020-06-31'"):
        load_tracks(path, cut_times=["2020-06-30T00:03:00", "2020-06-31"])
    tracks = load_tracks(path, cut_times=["2020-06-30T00:03:00"])
    with pytest.raises(ValueError, match=r"boundaries\[0\]='noon'"):
        split_time(tracks, ["noon"])
    with pytest.raises(TypeError, match="boundaries must be a sequence"):
        split_time(tracks, "2020-06-30T00:03:00")
    with pytest.raises(ValueError, match=r"data\.boundaries\[0\]='2020-06-30T24:61'"):
        TrackDataModule(str(path), split="time", boundaries=["2020-06-30T24:61"])


def test_subset_reports_the_index_given(tmp_path: Path) -> None:
    tracks = load_tracks(_write(tmp_path / "a.csv", [r for m in range(12) for r in _track(m)]))
    assert len(tracks) == 12
    for bad in ([-1], [12], [0, 13]):
        with pytest.raises(IndexError, match=f"index {[b for b in bad if not 0 <= b < 12][0]} is out of range for 12"):
            tracks.subset(bad)
    with pytest.raises(TypeError, match="integers"):
        tracks.subset(np.ones(12, dtype=bool))
    assert len(tracks.subset([])) == 0 and tracks.subset([11]).object_id[0] == tracks.object_id[11]


def test_split_objects_never_returns_an_empty_split_with_a_positive_share(tmp_path: Path) -> None:
    tracks = load_tracks(_write(tmp_path / "a.csv", _track(1) + _track(2)))
    with pytest.raises(ValueError, match=r"2 objects cannot fill .* the train split \(share 0.34\)"):
        split_objects(tracks, (0.34, 0.33, 0.33))
    train, val, test = split_objects(tracks, (0.5, 0.5, 0.0))  # a share of 0: an empty split, as asked
    assert (len(train), len(val), len(test)) == (1, 1, 0)


def test_track_windows_refuses_an_integer_dtype(tmp_path: Path) -> None:
    tracks = load_tracks(_write(tmp_path / "a.csv", _track(1)))
    with pytest.raises(TypeError, match="dtype must be a floating-point"):
        track_windows(tracks, dtype=torch.int64)
    assert track_windows(tracks, dtype=torch.float64)[0].y.dtype == torch.float64


def test_wrong_argument_types_name_the_argument(tmp_path: Path) -> None:
    path = _write(tmp_path / "a.csv", _track(1))
    with pytest.raises(TypeError, match="^source must be a path"):
        load_tracks(123)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="^data.source must be a path"):
        TrackDataModule(None)  # type: ignore[arg-type]
    for name, value, error in (
        ("max_len", "64", TypeError),
        ("max_len", 1, ValueError),
        ("batch_size", 0, ValueError),
        ("batch_size", 2.5, TypeError),
        ("pool_batches", None, TypeError),
        ("seed", "0", TypeError),
        ("fractions", "0.6,0.2,0.2", TypeError),
    ):
        with pytest.raises(error, match=f"data.{name}"):
            TrackDataModule(str(path), **{name: value})
    with pytest.raises(TypeError, match="max_gap must be a positive number"):
        TrackDataModule(str(path), max_gap="30 min")
