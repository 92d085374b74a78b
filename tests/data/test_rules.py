"""CleaningRules (data.rules): every field checked, naming it; the per-report rules as data; one
rules object taken by load_tracks, prepare_tracks and TrackDataModule, keywords as shortcuts."""

from __future__ import annotations

import datetime

import numpy as np
import pytest

from torchsde_lti.data import (
    AIS_NOT_AVAILABLE,
    REPORT_RULES,
    CleaningRules,
    load_tracks,
    parse_instant,
    prepare_tracks,
    read_reports,
)

pytest.importorskip("pyarrow")
pytest.importorskip("pymap3d")


@pytest.mark.parametrize(
    ("changes", "error", "names"),
    [
        ({"columns": ["MMSI", "BaseDateTime", "LAT", "LON"]}, TypeError, "columns"),
        ({"columns": "MMSI"}, ValueError, "columns"),
        ({"columns": {"id": 0, "time": 1, "lat": 2, "lon": 2}}, ValueError, "2 is lat and lon"),
        ({"columns": {"id": "a", "time": "b", "lat": "c", "lon": "c"}}, ValueError, "'c' is lat and lon"),
        ({"columns": {"id": 0, "time": 1, "lat": 2}}, ValueError, "missing roles ['lon']"),
        ({"columns": {"id": 0, "time": 1, "lat": 2, "lon": 3, "speed": 4}}, ValueError, "unknown roles ['speed']"),
        ({"columns": {"id": 0, "time": 1, "lat": 2.5, "lon": 3}}, TypeError, "columns['lat']"),
        ({"columns": {"id": 0, "time": 1, "lat": -1, "lon": 3}}, ValueError, "columns['lat']"),
        ({"format": "xlsx"}, ValueError, "format"),
        ({"time_format": 3}, TypeError, "time_format"),
        ({"altitude_unit": "km"}, ValueError, "altitude_unit"),
        ({"dims": 4}, ValueError, "dims"),
        ({"dims": True}, ValueError, "dims"),
        ({"frame": "global"}, ValueError, "frame"),
        ({"frame": "common"}, ValueError, "reference"),
        ({"reference": (40.0, -74.0)}, ValueError, "only used with frame='common'"),
        ({"frame": "common", "reference": (91.0, 0.0)}, ValueError, "not available"),
        ({"frame": "common", "reference": (40.0, 200.0)}, ValueError, "reference longitude"),
        ({"frame": "common", "reference": (float("nan"), 0.0)}, ValueError, "reference latitude"),
        ({"frame": "common", "reference": ("40", 0.0)}, TypeError, "reference latitude"),
        ({"frame": "common", "reference": "40,-74"}, ValueError, "reference"),
        ({"course_encoding": "knots"}, ValueError, "course_encoding"),
        ({"max_gap": -1.0}, ValueError, "max_gap"),
        ({"max_gap": "1800"}, TypeError, "max_gap"),
        ({"v_max": float("inf")}, ValueError, "v_max"),
        ({"max_extent": 0.0}, ValueError, "max_extent"),
        ({"min_reports": 1}, ValueError, "min_reports"),
        ({"min_reports": 2.5}, ValueError, "min_reports"),
        ({"min_reports": "5"}, TypeError, "min_reports"),
        ({"cut_times": "2020-12-07"}, TypeError, "cut_times"),
        ({"cut_times": ["2020-12-07", "2020-13-45"]}, ValueError, "cut_times[1]"),
        ({"cut_times": ["yesterday"]}, ValueError, "cut_times[0]"),
        ({"cut_times": [20201207]}, TypeError, "cut_times[0]"),
        ({"v_maxx": 3.0}, TypeError, "v_maxx"),
    ],
)
def test_each_field_is_checked_naming_it(changes: dict, error: type, names: str) -> None:
    with pytest.raises(error, match=_literal(names)):
        CleaningRules().replace(**changes)


def _literal(text: str) -> str:
    import re

    return re.escape(text)


def test_defaults_fields_and_plain_values() -> None:
    rules = CleaningRules()
    assert len(rules.as_dict()) == 13
    assert rules.min_reports == 2 and rules.max_gap == 1800.0 and rules.cut_times == ()
    r = CleaningRules(
        columns={"id": 0, "time": 1, "lat": 3, "lon": 2, "alt": None},
        frame="common",
        reference=[40, -74],
        min_reports=5.0,
        cut_times=[np.datetime64("2020-12-07"), datetime.datetime(2020, 12, 8)],
    )
    assert r.columns == {"id": 0, "time": 1, "lat": 3, "lon": 2}  # a None column is no column
    assert r.reference == (40.0, -74.0) and r.min_reports == 5 and isinstance(r.min_reports, int)
    assert r.as_dict()["cut_times"] == ["2020-12-07", "2020-12-08T00:00:00"]
    assert r.cut_instants().tolist() == [np.datetime64("2020-12-07", "us"), np.datetime64("2020-12-08", "us")]
    assert CleaningRules.coerce(r.as_dict()) == r  # what a checkpoint stores rebuilds the same rules
    assert CleaningRules.coerce(None, v_max=3.0).v_max == 3.0
    with pytest.raises(TypeError, match="rules must be"):
        CleaningRules.coerce(["v_max", 3.0])  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("2020-12-07", "2020-12-07T00:00:00"),
        ("2020-12-07T10", "2020-12-07T10:00:00"),
        ("2020-12-07 10:30:05.25", "2020-12-07T10:30:05.250000"),
        ("2020-12-07T10:30:00Z", "2020-12-07T10:30:00"),
        ("2020-12-07T10:30:00+02:00", "2020-12-07T08:30:00"),
        ("2020-12-07T00:30:00-0130", "2020-12-07T02:00:00"),
    ],
)
def test_parse_instant_reads_iso_8601_in_utc(text: str, expected: str) -> None:
    assert parse_instant(text, "x") == np.datetime64(expected, "us")


def test_parse_instant_errors_name_the_argument() -> None:
    for bad in ("2020-02-30", "2020-12-07T25:00", "07/12/2020", "2020-12-07T10:00+25:00"):
        with pytest.raises(ValueError, match=r"split_time\[0\]"):
            parse_instant(bad, "split_time[0]")
    with pytest.raises(ValueError, match="NaT"):
        parse_instant(np.datetime64("NaT"), "b")
    aware = datetime.datetime(2020, 12, 7, 12, tzinfo=datetime.timezone(datetime.timedelta(hours=-5)))
    assert parse_instant(aware, "b") == np.datetime64("2020-12-07T17:00", "us")


def test_report_rules_as_data() -> None:
    """The sentinels and ranges are plain numbers; classify puts each bad value in one reason."""
    assert AIS_NOT_AVAILABLE == {"lat": 91.0, "lon": 181.0, "sog": 102.3, "cog": 360.0, "heading": 511.0}
    for role, sentinel in AIS_NOT_AVAILABLE.items():
        rule = REPORT_RULES[role]
        assert rule.not_available == sentinel
        masks = rule.classify(np.array([sentinel, np.float32(sentinel), np.nan, rule.low]))
        assert masks[f"{role}_not_available"].tolist() == [True, True, False, False]
        assert masks[f"{role}_missing"].tolist() == [False, False, True, False]
        assert not masks[f"{role}_out_of_range"].any()
    lon = REPORT_RULES["lon"].classify(np.array([180.0, -180.0, 181.0, 200.0, -180.5]))
    assert lon["lon_out_of_range"].tolist() == [False, False, False, True, True]
    cog = REPORT_RULES["cog"].classify(np.array([359.9, 360.0, 360.5, -0.1]))
    assert cog["cog_not_available"].tolist() == [False, True, False, False]
    assert cog["cog_out_of_range"].tolist() == [False, False, True, True]
    sog = REPORT_RULES["sog"].valid(np.array([0.0, 102.2, np.float32(102.2), 102.3, 150.0, -1.0]))
    assert sog.tolist() == [True, True, True, False, False, False]
    assert REPORT_RULES["lat"].drops_report and not REPORT_RULES["sog"].drops_report


def _csv(tmp_path, rows: list[str]):  # noqa: ANN001, ANN202
    path = tmp_path / "ais.csv"
    path.write_text("MMSI,BaseDateTime,LAT,LON,SOG,COG\n" + "\n".join(rows) + "\n")
    return path


def _rows(mmsi: int = 1, n: int = 6, lat: float = 40.0, lon: float = -74.0) -> list[str]:
    return [f"{mmsi},2020-06-30T00:{i:02d}:00,{lat + 0.001 * i},{lon},5.0,90.0" for i in range(n)]


def test_the_three_callers_take_one_rules_object(tmp_path) -> None:  # noqa: ANN001
    from torchsde_lti.data.modules import TrackDataModule

    path = _csv(tmp_path, _rows(1) + _rows(2) + _rows(3) + _rows(4) + _rows(5))
    rules = CleaningRules(max_gap=600.0, v_max=35.0, min_reports=3)
    by_object = load_tracks(path, rules=rules)
    by_keywords = load_tracks(path, max_gap=600.0, v_max=35.0, min_reports=3)
    by_mapping = load_tracks(path, rules={"max_gap": 600.0, "v_max": 35.0, "min_reports": 3})
    prepared = prepare_tracks(read_reports(path), rules=rules)
    for other in (by_keywords, by_mapping, prepared):
        assert other.summary.rules == by_object.summary.rules == rules.as_dict()
        np.testing.assert_array_equal(other.pos, by_object.pos)
    assert load_tracks(path, rules=rules, min_reports=7 - 1).summary.rules["min_reports"] == 6  # keyword wins
    with pytest.raises(TypeError, match="max_gapp"):
        load_tracks(path, max_gapp=3.0)

    dm = TrackDataModule(str(path), rules=rules, fractions=(0.6, 0.2, 0.2))
    assert dm.rules == rules
    assert TrackDataModule(str(path)).rules.min_reports == 5  # the DataModule's default
    hp = dict(dm.hparams)
    again = TrackDataModule(**hp)  # a checkpoint's hyperparameters rebuild the same module
    assert again.rules == rules and dict(again.hparams) == hp
    timed = TrackDataModule(str(path), split="time", boundaries=["2020-06-30T00:03:00"], min_reports=2)
    assert timed.rules.cut_times == ("2020-06-30T00:03:00",)
    assert TrackDataModule(**dict(timed.hparams)).rules.cut_times == ("2020-06-30T00:03:00",)
    with pytest.raises(TypeError, match=r"data\.boundaries"):
        TrackDataModule(str(path), split="time", boundaries="2020-06-30T00:03:00")
    with pytest.raises(ValueError, match=r"data\.boundaries\[0\]"):
        TrackDataModule(str(path), split="time", boundaries=["2020-06-31"])
