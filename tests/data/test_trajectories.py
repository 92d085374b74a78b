"""load_tracks / prepare_tracks: local frames against geodesics on real tracks, every cleaning
rule on reports built here, splits and windows.

Oracles: Karney's geodesics (pyproj.Geod, WGS84) for distances; hand-built report sequences
whose expected counts are written out; plain loops for windows.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from torchsde_lti.data import (
    Reports,
    load_tracks,
    locate_file,
    prepare_tracks,
    split_objects,
    split_time,
    track_windows,
    window_bounds,
)

pyproj = pytest.importorskip("pyproj", reason="pyproj (test extra) gives the reference geodesics")
GEOD = pyproj.Geod(ellps="WGS84")


def _lines(name: str, ids: set[str], tmp_path: Path) -> Path:
    """The trajectory lines of ``ids`` from a shipped .traj file: a small slice for the tests."""
    out = tmp_path / f"slice_{name}"
    with open(locate_file(name)) as fh:
        keep = [line for line in fh if any(f",{i}," in line[:200] for i in ids)]
    out.write_text("".join(keep))
    return out


def _check_geodesics(tracks, i: int) -> tuple[float, float]:
    """Largest relative error of (step lengths, distances from the origin) of track i vs geodesics."""
    d = tracks.track(i)
    lat, lon, pos = d["lat"], d["lon"], d["pos"][:, :2]
    _, _, step = GEOD.inv(lon[:-1], lat[:-1], lon[1:], lat[1:])
    ours = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    moved = step > 10.0  # 5-decimal positions: ~1 m quantisation, relative errors meaningless below
    _, _, radial = GEOD.inv(np.full_like(lon, lon[0]), np.full_like(lat, lat[0]), lon, lat)
    far = radial > 10.0
    return (
        float(np.max(np.abs(ours[moved] - step[moved]) / step[moved])),
        float(np.max(np.abs(np.linalg.norm(pos, axis=1)[far] - radial[far]) / radial[far])),
    )


@pytest.fixture(scope="module")
def coastal(tmp_path_factory) -> object:
    pytest.importorskip("tracktable_data")
    # Los Angeles / Long Beach (the file's first line), the westernmost Aleutian track (-173.6 E,
    # 52 N) and the northernmost track (Valdez, 60.3 N): no track of this file crosses 180 degrees
    # or goes above 70 N, so those two cases come from the flights below and a synthetic track.
    path = _lines(
        "US_coastal_2020_06_30.traj", {"367697580", "367569470", "367563580"}, tmp_path_factory.mktemp("coastal")
    )
    return load_tracks(path)


def test_local_frames_match_geodesics_on_real_ship_tracks(coastal) -> None:
    seen = set()
    for i in range(len(coastal)):
        lat, lon = coastal.track(i)["lat"], coastal.track(i)["lon"]
        place = (
            "LA"
            if lon.mean() < -117 and lat.mean() < 34
            else "Aleutians"
            if lon.mean() < -170
            else "Alaska 60N"
            if lat.mean() > 60
            else "?"
        )
        seen.add(place)
        step_err, radial_err = _check_geodesics(coastal, i)
        assert step_err < 1e-3 and radial_err < 1e-3, (place, step_err, radial_err)
        np.testing.assert_allclose(coastal.pos[coastal.offsets[i]], [0.0, 0.0], atol=1e-9)  # its own origin
    assert {"LA", "Aleutians", "Alaska 60N"} <= seen


def test_local_frames_across_the_antimeridian_and_near_the_pole(tmp_path: Path) -> None:
    pytest.importorskip("tracktable_data")
    # SampleTrajectories.traj: Shanghai -> Los Angeles crosses 180 degrees (longitudes unwrapped
    # beyond 180 in the file), Newark -> Chengdu flies over 88.7 N
    tracks = load_tracks(_lines("SampleTrajectories.traj", {"TSTSHALAX0", "TSTEWRCTU0"}, tmp_path))
    crossing = polar = 0
    for i in range(len(tracks)):
        lat, lon = tracks.track(i)["lat"], tracks.track(i)["lon"]
        crossing += np.ptp(lon) > 180  # lon normalised to [-180, 180): a jump means a crossing
        polar += lat.max() > 70
        step_err, radial_err = _check_geodesics(tracks, i)
        assert step_err < 1e-3 and radial_err < 1e-3, (tracks.object_id[i], lat.max(), step_err)
        # no track leaves max_extent = 250 km around its own origin
        assert np.linalg.norm(tracks.track(i)["pos"], axis=1).max() < 250_500
    assert crossing >= 1 and polar >= 5
    assert tracks.summary.extent_splits > 0


def test_synthetic_bering_strait_ship_across_180() -> None:
    """A ship at 10 m/s due west through 180 degrees at 65.8 N, one report a minute for 4 h."""
    n = 240
    lons, lats, _ = GEOD.fwd(np.full(n, -179.0), np.full(n, 65.8), np.full(n, 270.0), np.arange(n) * 600.0)
    times = np.datetime64("2020-06-30T00:00:00", "us") + np.arange(n) * np.timedelta64(60, "s")
    rep = Reports(np.full(n, 7, dtype=np.int64), times, lats, lons, None, None, None, None, n, 0, (), "synthetic")
    tracks = prepare_tracks(rep, v_max=20.0)
    assert len(tracks) == 1 and tracks.num_reports == n and tracks.summary.jump_reports_dropped == 0
    assert tracks.lon.min() < -179 and tracks.lon.max() > 178  # it crossed
    step_err, radial_err = _check_geodesics(tracks, 0)
    # 144 km from the origin at the end: tangent-plane foreshortening (144/6371)²/2 = 2.6e-4
    assert step_err < 3e-4 and radial_err < 1e-4
    steps = np.linalg.norm(np.diff(tracks.pos, axis=0), axis=1)
    np.testing.assert_allclose(steps, 600.0, rtol=3e-4)  # 10 m/s for 60 s, across the antimeridian
    # heading west: the first step points west in the origin's frame
    assert tracks.pos[1, 0] < -599 and abs(tracks.pos[1, 1]) < 1.0


def _reports(
    times_s: list[float],
    lat: list[float],
    lon: list[float],
    ids: list[int] | None = None,
    alt: list[float] | None = None,
) -> Reports:
    n = len(times_s)
    t = np.datetime64("2020-06-30T00:00:00", "us") + (np.asarray(times_s) * 1e6).astype("timedelta64[us]")
    return Reports(
        np.asarray(ids if ids is not None else [1] * n, dtype=np.int64),
        t,
        np.asarray(lat, float),
        np.asarray(lon, float),
        None if alt is None else np.asarray(alt, float),
        None,
        None,
        None,
        n,
        0,
        (),
        "hand-built",
    )


DEG = 1.0 / 111_195.0  # degrees of latitude per metre (sphere of the mean radius), enough for thresholds


def test_rules_count_everything() -> None:
    # object 1: 0..9 every 10 s moving 50 m north per step; a repeat at t=20; a spike at t=40
    # (5 km off); a 1-hour gap before t=4000; a teleport (100 km) at t=4100 continuing from there
    t = [0, 10, 20, 20, 30, 40, 50, 60, 4000, 4010, 4100, 4110, 4120]
    lat = [0.0, 50, 100, 100, 150, 5000, 250, 300, 350, 400, 100_000, 100_050, 100_100]
    lat = [40.0 + x * DEG for x in lat]
    ids = [1] * len(t)
    # object 2: one invalid position, then two reports (too short for min_reports=3)
    t += [0, 10, 20]
    lat += [95.0, 40.0, 40.0001]
    ids += [2, 2, 2]
    rep = _reports(t, lat, [-74.0] * len(t), ids)
    tracks = prepare_tracks(rep, v_max=50.0, max_gap=1800.0, min_reports=3)
    s = tracks.summary
    assert (s.invalid_positions, s.repeated_timestamps, s.jump_reports_dropped, s.jump_splits, s.gap_splits) == (
        1,
        1,
        1,
        1,
        1,
    )
    # short: the 2 reports between the gap and the teleport, and object 2's 2 valid reports
    assert (s.short_tracks, s.short_reports) == (2, 4)
    assert (
        s.rows
        == s.malformed
        + s.invalid_positions
        + s.repeated_timestamps
        + s.jump_reports_dropped
        + s.short_reports
        + s.reports
    )
    assert list(tracks.lengths) == [6, 3]
    assert s.tracks == len(tracks) and s.objects == 1
    for i in range(len(tracks)):
        seg = tracks.track(i)
        assert np.all(np.diff(seg["t"]) > 0)
        assert np.all(np.linalg.norm(np.diff(seg["pos"], axis=0), axis=1) / np.diff(seg["t"]) <= 50.0)
    text = str(s)
    for phrase in ("repeated timestamps dropped", "jumps: > 50.0 m/s", "cuts at gaps: > 1800.0 s", "invalid positions"):
        assert phrase in text


def test_extent_and_time_cuts_and_common_frame() -> None:
    # 600 km due north at 100 m/s, one report every 100 s (10 km)
    n = 61
    rep = _reports(list(np.arange(n) * 100.0), list(10.0 + np.arange(n) * 10_000 * DEG), [20.0] * n)
    local = prepare_tracks(rep, max_extent=250_000.0)
    assert local.summary.extent_splits == 2 and len(local) == 3
    assert np.linalg.norm(local.pos, axis=1).max() <= 250_000.0
    cut = prepare_tracks(rep, max_extent=None, cut_times=["2020-06-30T00:50:00"])
    assert cut.summary.time_cuts == 1 and list(cut.lengths) == [30, 31]
    before, after = split_time(cut, ["2020-06-30T00:50:00"])
    assert before.num_reports == 30 and after.num_reports == 31
    with pytest.raises(ValueError, match="span a split boundary"):
        split_time(prepare_tracks(rep, max_extent=None), ["2020-06-30T00:50:00"])
    common = prepare_tracks(rep, frame="common", reference=(10.0, 20.0))
    assert len(common) == 1 and np.allclose(common.pos[0], 0.0, atol=1e-6)
    with pytest.raises(ValueError, match="reference"):
        prepare_tracks(rep, frame="common")


def test_altitude_gives_3d_tracks() -> None:
    rep = _reports([0, 10, 20], [40.0, 40.001, 40.002], [-74.0] * 3, alt=[1000.0, 1010.0, 1030.0])
    tracks = prepare_tracks(rep)
    assert tracks.dims == 3
    np.testing.assert_allclose(tracks.pos[:, 2], [0.0, 10.0, 30.0])  # altitude above the origin's
    assert prepare_tracks(rep, dims=2).dims == 2
    flat = rep._replace(alt=np.zeros(3))
    assert prepare_tracks(flat).dims == 2  # an all-zero altitude column carries no altitude
    with pytest.raises(ValueError, match="altitude"):
        prepare_tracks(rep._replace(alt=None), dims=3)


def test_split_objects_disjoint_reproducible() -> None:
    rep = _reports(
        list(range(300)), [40.0] * 300, [-74.0 + 1e-4 * k for k in range(300)], ids=[k // 3 for k in range(300)]
    )
    tracks = prepare_tracks(rep, min_reports=3)
    a = split_objects(tracks, (0.6, 0.2, 0.2), seed=0)
    b = split_objects(tracks, (0.6, 0.2, 0.2), seed=0)
    ids = [set(p.object_id.tolist()) for p in a]
    assert [len(i) for i in ids] == [60, 20, 20] and not (ids[0] & ids[1] or ids[0] & ids[2] or ids[1] & ids[2])
    assert all(np.array_equal(x.object_id, y.object_id) for x, y in zip(a, b))
    assert sum(p.num_reports for p in a) == tracks.num_reports
    with pytest.raises(ValueError, match="fractions"):
        split_objects(tracks, (0.5, 0.6, 0.1))
    # val and test both rounded up past K (no train): still disjoint, every object once
    for k in (3, 7):
        few = prepare_tracks(
            _reports(list(range(3 * k)), [40.0] * (3 * k), [-74.0] * (3 * k), ids=[i // 3 for i in range(3 * k)]),
            min_reports=3,
        )
        parts = [set(p.object_id.tolist()) for p in split_objects(few, (0.0, 0.5, 0.5), seed=0)]
        assert sum(map(len, parts)) == k and set().union(*parts) == set(few.object_id.tolist()), parts


@pytest.mark.parametrize("max_len", [None, 2, 3, 7, 128])
def test_windows_cover_tracks_exactly(max_len: int | None) -> None:
    lengths = np.array([2, 5, 9, 130, 7])
    owner, start, stop = window_bounds(lengths, max_len)
    for i, L in enumerate(lengths):
        pieces = sorted(zip(start[owner == i], stop[owner == i]))
        assert pieces[0][0] == 0 and pieces[-1][1] == L
        assert all(p[1] == q[0] for p, q in zip(pieces, pieces[1:]))
        sizes = [b - a for a, b in pieces]
        assert max(sizes) - min(sizes) <= 1 and (max_len is None or max(sizes) <= max_len)


def test_track_windows_centred_with_dt(coastal) -> None:
    wins = track_windows(coastal, max_len=50, dtype=torch.float64)
    assert sum(int(w.dt.shape[0]) for w in wins) == coastal.num_reports
    for w in wins:
        i = int(w.track_id)
        k0 = int(np.searchsorted(coastal.t[coastal.offsets[i] : coastal.offsets[i + 1]], float(w.t[0])))
        a = coastal.offsets[i] + k0
        T = w.dt.shape[0]
        assert float(w.dt[0]) == 0.0 and torch.all(w.y[0] == 0)
        np.testing.assert_allclose(w.dt[1:].numpy(), np.diff(coastal.t[a : a + T]))
        np.testing.assert_allclose((w.y + w.origin).numpy(), coastal.pos[a : a + T], atol=1e-9)


def test_float32_windows_are_centred_in_float64(coastal) -> None:
    """Positions far from the frame's origin (a common frame) are centred before the cast: the
    float32 windows equal the float64 ones to float32 rounding of the centred values."""
    import dataclasses

    shifted = dataclasses.replace(coastal, pos=coastal.pos + 1.5e6)
    w32 = track_windows(shifted, max_len=50, dtype=torch.float32)
    w64 = track_windows(shifted, max_len=50, dtype=torch.float64)
    for a, b in zip(w32, w64):
        err = (a.y.double() - b.y).abs().max()
        assert float(err) <= 1e-6 * max(1.0, float(b.y.abs().max()))


def test_names_of_trajectories_still_import_from_it() -> None:
    """Tracks and LoadSummary (data.loaded_tracks) and the splits and windows (data.splits) live
    in their own modules; data.trajectories still exports every name it did."""
    import torchsde_lti.data as data
    import torchsde_lti.data.loaded_tracks as loaded_tracks
    import torchsde_lti.data.splits as splits
    import torchsde_lti.data.trajectories as trajectories

    moved = [*loaded_tracks.__all__, *splits.__all__]
    assert set(moved) | {"load_tracks", "prepare_tracks"} == set(trajectories.__all__)
    for name in trajectories.__all__:
        assert getattr(trajectories, name) is getattr(data, name)
