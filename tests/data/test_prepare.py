"""Out-of-core preparation (torchsde_lti.data.prepare): the oracle is ``load_tracks`` on the same
file: the same cleaned reports (ids, times, positions) in the same tracks, the same counted summary,
whatever the buckets, chunks and workers; a killed run resumes to the same dataset."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from torchsde_lti.data import load_tracks
from torchsde_lti.data.prepare import find_sources, prepare_dataset

AIS_HEADER = "MMSI,BaseDateTime,LAT,LON,SOG,COG,Heading,VesselName,IMO,CallSign,VesselType,Status,Length,Width,Draft,Cargo,TransceiverClass"


def _ais_csv(path: Path, vessels: int, seed: int, day: str = "2024-01-01", faults: bool = True) -> Path:
    """A small MarineCadastre-style day: moving and moored vessels, gaps, a few AIS faults."""
    g = np.random.default_rng(seed)
    lines = [AIS_HEADER]
    for v in range(vessels):
        mmsi = 366_000_000 + seed * 1000 + v
        n = int(g.integers(3, 120))
        t = np.sort(g.choice(86_000, n, replace=False))
        moving = v % 2 == 0
        lat = 40.5 + np.cumsum(g.normal(0, 1e-3 if moving else 1e-6, n))
        lon = -74.0 + np.cumsum(g.normal(0, 1e-3 if moving else 1e-6, n))
        sog = np.abs(g.normal(8 if moving else 0, 1, n)).round(1)
        cog = g.uniform(0, 360, n).round(1)
        for k in range(n):
            la, lo, s, c = f"{lat[k]:.5f}", f"{lon[k]:.5f}", f"{sog[k]}", f"{cog[k]}"
            if faults and g.random() < 0.02:
                la = "91"  # AIS "not available"
            if faults and g.random() < 0.02:
                s = "102.3"
            stamp = np.datetime64(day) + np.timedelta64(int(t[k]), "s")
            lines.append(f"{mmsi},{str(stamp)},{la},{lo},{s},{c},511,,,,70,0,,,,,A")
    if faults:
        lines.insert(5, "garbage,line")  # a malformed row
    path.write_text("\n".join(lines) + "\n")
    return path


def _windows(out: Path) -> pa.Table:
    files = sorted((out / "windows").glob("*.parquet"))
    return pa.concat_tables([pq.read_table(f) for f in files])


def _tracks_as_rows(tracks) -> dict[tuple, tuple]:  # noqa: ANN001
    """{(object, first time us): (times, lat, lon)} of every track of a Tracks."""
    t0 = tracks.t0.astype("datetime64[us]").astype(np.int64)
    out = {}
    for i in range(len(tracks)):
        tr = tracks.track(i)
        times = t0 + np.round(tr["t"] * 1e6).astype(np.int64)
        out[(str(tracks.object_id[i]), int(times[0]))] = (times, tr["lat"], tr["lon"])
    return out


def _prepared_as_rows(out: Path) -> dict[tuple, tuple]:
    table = _windows(out).to_pydict()
    return {
        (str(o), int(t[0])): (np.array(t), np.array(la), np.array(lo))
        for o, t, la, lo in zip(table["object_id"], table["time"], table["lat"], table["lon"])
    }


def _assert_same_reports(expected: dict, got: dict) -> None:
    assert expected.keys() == got.keys()
    for key, (t, la, lo) in expected.items():
        gt, gla, glo = got[key]
        np.testing.assert_array_equal(gt, t)
        np.testing.assert_array_equal(gla, la)
        np.testing.assert_array_equal(glo, lo)


def _assert_same_table(a: pa.Table, b: pa.Table) -> None:
    """Equal columns, NaN equal to NaN (unavailable velocities)."""
    assert a.schema == b.schema and a.num_rows == b.num_rows
    for name in a.column_names:
        x, y = a[name].combine_chunks(), b[name].combine_chunks()
        if pa.types.is_list(x.type):
            assert x.offsets.equals(y.offsets), name
            x, y = x.flatten(), y.flatten()
        np.testing.assert_array_equal(x.to_numpy(zero_copy_only=False), y.to_numpy(zero_copy_only=False), err_msg=name)


def _summary_dict(summary) -> dict:  # noqa: ANN001
    d = summary.as_dict()
    d.pop("source")
    d.pop("malformed_examples")
    return d


RULES = {"v_max": 35.0, "min_reports": 5}


@pytest.fixture(scope="module")
def national_day(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    pytest.importorskip("tracktable_data")
    out = tmp_path_factory.mktemp("prepared") / "day"
    # 3 buckets and 4 MiB chunks: the day's reports travel through every path of the preparation
    summary = prepare_dataset("US_coastal_2020_06_30.traj", out, max_len=None, buckets=3, chunk_bytes=4 << 20, **RULES)
    return load_tracks("US_coastal_2020_06_30.traj", **RULES), summary, out


def test_national_day_prepares_to_the_reports_of_load_tracks(national_day: tuple) -> None:
    """Preparing the real national day gives the cleaned reports, tracks and counts of load_tracks."""
    tracks, summary, out = national_day
    _assert_same_reports(_tracks_as_rows(tracks), _prepared_as_rows(out))
    assert _summary_dict(summary.load) == _summary_dict(tracks.summary)
    assert summary.windows == len(tracks) and summary.buckets == 3


def test_prepared_positions_are_the_loader_frames(national_day: tuple) -> None:
    """east/north are load_tracks' positions in each track's own frame."""
    tracks, _, out = national_day
    table = _windows(out).to_pydict()
    by_key = {
        (str(o), int(t[0])): (e, n)
        for o, t, e, n in zip(table["object_id"], table["time"], table["east"], table["north"])
    }
    t0 = tracks.t0.astype("datetime64[us]").astype(np.int64)
    for i in range(0, len(tracks), 97):
        tr = tracks.track(i)
        e, n = by_key[(str(tracks.object_id[i]), int(t0 + round(tr["t"][0] * 1e6)))]
        np.testing.assert_allclose(np.stack([e, n], -1), tr["pos"], rtol=0, atol=1e-6)


@pytest.mark.parametrize("workers", [1, 2])
def test_many_files_zip_and_parquet_give_one_files_tracks(tmp_path: Path, workers: int) -> None:
    """A day split over a CSV, a zipped CSV and a Parquet file prepares to the tracks of the whole
    day loaded at once; rows and malformed rows are counted over the files."""
    day = _ais_csv(tmp_path / "day.csv", 40, seed=1)
    lines = day.read_text().splitlines()
    header, rows = lines[0], lines[1:]
    parts = tmp_path / "parts"
    parts.mkdir()
    # whole vessels per part (a vessel's reports in two files would be cut at the files' boundary otherwise)
    part = lambda r: zlib.crc32(r.split(",")[0].encode()) % 3  # noqa: E731
    groups = [[r for r in rows if part(r) == k and not r.startswith("garbage")] for k in range(3)]
    (parts / "a.csv").write_text("\n".join([header, "garbage,line", *groups[0]]) + "\n")
    with zipfile.ZipFile(parts / "b.zip", "w") as z:
        z.writestr("b.csv", "\n".join([header, *groups[1]]) + "\n")
    (tmp_path / "c.csv").write_text("\n".join([header, *groups[2]]) + "\n")
    import pyarrow.csv as pcsv

    table = pcsv.read_csv(
        tmp_path / "c.csv", convert_options=pcsv.ConvertOptions(column_types={"BaseDateTime": pa.string()})
    )
    pq.write_table(table, parts / "c.parquet")
    out = tmp_path / "out"
    summary = prepare_dataset(parts, out, max_len=None, buckets=4, chunk_bytes=4096, workers=workers, **RULES)
    expected = load_tracks(day, **RULES)
    _assert_same_reports(_tracks_as_rows(expected), _prepared_as_rows(out))
    assert _summary_dict(summary.load) == _summary_dict(expected.summary)
    assert summary.files == 3


def test_windows_are_track_windows(tmp_path: Path) -> None:
    """Windows of <= max_len reports cut each track as window_bounds does."""
    from torchsde_lti.data import window_bounds

    src = _ais_csv(tmp_path / "d.csv", 30, seed=2)
    summary = prepare_dataset(src, tmp_path / "out", max_len=16, buckets=2)
    tracks = load_tracks(src)
    owner, a, b = window_bounds(tracks.lengths, 16)
    assert summary.windows == len(owner)
    lengths = sorted(_windows(tmp_path / "out").column("length").to_pylist())
    assert lengths == sorted((b - a).tolist())


def test_resume_after_a_kill_gives_the_same_dataset(tmp_path: Path) -> None:
    """A run killed (SIGKILL) after its first finished task, started again, gives the dataset of an
    uninterrupted run; the finished tasks are not redone."""
    src = tmp_path / "src"
    src.mkdir()
    for k in range(6):
        _ais_csv(src / f"AIS_{k}.csv", 25, seed=10 + k)
    whole = prepare_dataset(src, tmp_path / "whole", max_len=32, buckets=5)
    out = tmp_path / "killed"
    code = (
        "from torchsde_lti.data.prepare import prepare_dataset\n"
        f"prepare_dataset({str(src)!r}, {str(out)!r}, max_len=32, buckets=5)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code])
    manifest = out / "_manifest" / "scatter"
    deadline = time.monotonic() + 120
    while proc.poll() is None and time.monotonic() < deadline and not (manifest.is_dir() and any(manifest.iterdir())):
        time.sleep(0.002)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = sorted(p.name for p in manifest.iterdir())
    assert not (out / "summary.json").exists() and len(done) >= 1  # (stopped in the scatter, or in the gather)
    stamps = {p.name: p.stat().st_mtime_ns for p in manifest.iterdir()}
    resumed = prepare_dataset(src, out, max_len=32, buckets=5)
    assert {p: (manifest / p).stat().st_mtime_ns for p in done} == {p: stamps[p] for p in done}  # not redone
    assert resumed.as_dict()["load"] == whole.as_dict()["load"] | {"source": resumed.load.source}
    for b in range(5):
        name = f"bucket={b:05d}.parquet"
        _assert_same_table(pq.read_table(out / "windows" / name), pq.read_table(tmp_path / "whole" / "windows" / name))


def test_resume_refuses_other_settings(tmp_path: Path) -> None:
    src = _ais_csv(tmp_path / "d.csv", 10, seed=3)
    prepare_dataset(src, tmp_path / "out", max_len=16)
    with pytest.raises(ValueError, match="max_len"):
        prepare_dataset(src, tmp_path / "out", max_len=32)
    with pytest.raises(ValueError, match="rules"):
        prepare_dataset(src, tmp_path / "out", max_len=16, v_max=10.0)


def test_sources_and_arguments_are_checked(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="no trajectory file"):
        find_sources(tmp_path / "AIS_*.csv")
    src = _ais_csv(tmp_path / "d.csv", 3, seed=4)
    assert find_sources([str(tmp_path / "*.csv"), src]) == [src.resolve()]
    for bad in ({"max_len": 1}, {"workers": 0}, {"buckets": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            prepare_dataset(src, tmp_path / "out", **bad)


def test_reserved_file_is_refused(tmp_path: Path) -> None:
    pytest.importorskip("tracktable_data")
    with pytest.raises(ValueError, match="reserved for evaluation"):
        prepare_dataset("NYHarbor_2020_12_08.traj", tmp_path / "out")


def test_summary_json_is_strict_and_reloads(tmp_path: Path) -> None:
    from torchsde_lti.data.prepare import PreparedSummary

    src = _ais_csv(tmp_path / "d.csv", 12, seed=5)
    summary = prepare_dataset(src, tmp_path / "out")
    text = (tmp_path / "out" / "summary.json").read_text()
    assert PreparedSummary.from_dict(json.loads(text)) == summary
    assert summary.load.malformed == 1 and "garbage" in summary.load.malformed_examples[0]
    assert "d.csv" in summary.load.malformed_examples[0]
