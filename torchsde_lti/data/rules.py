"""The cleaning rules as data: one :class:`CleaningRules` for every path that turns reports into tracks.

:func:`~torchsde_lti.data.load_tracks`, :func:`~torchsde_lti.data.prepare_tracks`,
:class:`~torchsde_lti.data.modules.TrackDataModule` and an out-of-core preparation all take
``rules=CleaningRules(...)`` (their keyword arguments are shortcuts that replace fields of it),
so the 13 settings are defined, defaulted and validated once, here.

Two kinds of rule:

- **per-report rules** (:data:`REPORT_RULES`): each a :class:`ValueRule` on one column: a valid
  range and AIS's "not available" value, as plain numbers, so that any engine (numpy here;
  polars, DuckDB or pyarrow in a preparation) can apply them to a column on its own
  (:meth:`ValueRule.classify` is the numpy version). A report whose latitude or longitude fails
  is dropped; a speed, course or heading that fails becomes unavailable (NaN), the report kept.
  Either way it is counted by name (``"lat_not_available"``, ``"lon_out_of_range"``,
  ``"sog_not_available"``, ...): nothing is wrapped, clamped or dropped unseen.
- **per-track rules** (repeated timestamps, cuts at ``cut_times`` and at gaps over ``max_gap``,
  implausible jumps over ``v_max``, cuts at ``max_extent``, tracks shorter than ``min_reports``)
  need a track's reports in time order; their settings are fields of :class:`CleaningRules` and
  :func:`~torchsde_lti.data.prepare_tracks` applies them (the order is in
  :mod:`torchsde_lti.data.trajectories`).

Instants (``cut_times``, split boundaries) are ISO 8601 strings (``2020-12-07``,
``2020-12-07T00:00:00``, with ``Z`` or a ``±hh:mm`` offset converted to UTC, none = UTC) or
``numpy.datetime64`` / :class:`datetime.datetime` values (:func:`parse_instant`).
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import numbers
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "AIS_NOT_AVAILABLE",
    "REPORT_RULES",
    "ROLES",
    "CleaningRules",
    "ValueRule",
    "parse_instant",
]

#: The roles a column can play; id, time, lat and lon are required.
ROLES = ("id", "time", "lat", "lon", "alt", "sog", "cog", "heading")
_REQUIRED_ROLES = ("id", "time", "lat", "lon")
#: AIS's "not available" value of each field (ITU-R M.1371: lat 91°, lon 181°, SOG 102.3 kn,
#: COG 360°, true heading 511°).
AIS_NOT_AVAILABLE: dict[str, float] = {"lat": 91.0, "lon": 181.0, "sog": 102.3, "cog": 360.0, "heading": 511.0}

_FORMATS = ("traj", "csv", "parquet", "pq")
_COURSE_ENCODINGS = ("ais", "ais_int12", "degrees")
# a date-time in ISO 8601, in named parts (a blank around it, a lower-case t and a comma before the fraction allowed)
ISO_8601 = (
    r"^\s*(?P<date>\d{4}-\d{2}-\d{2})"
    r"(?:[Tt ](?P<hour>\d{2})(?::(?P<minute>\d{2})(?::(?P<second>\d{2})(?:[.,](?P<fraction>\d+))?)?)?)?"
    r"\s*(?P<zone>Z|[+-]\d{2}(?::?\d{2})?)?\s*$"
)


@dataclass(frozen=True)
class ValueRule:
    """The rule for one column's values, as data any engine can apply.

    A value v of column ``role`` is, in this order:

    - ``missing`` when it is not finite (NaN, ±inf);
    - ``not_available`` when |v − not_available| <= ``tolerance`` (AIS's sentinel, if any);
    - ``out_of_range`` when v < low, or v > high (v >= high when ``high_open``);
    - valid otherwise.

    Attributes:
        role: the column's role (:data:`ROLES`).
        low, high: the valid range; high_open: whether ``high`` itself is outside it.
        not_available: AIS's "not available" value, or None.
        tolerance: how close to ``not_available`` counts as it (half the field's resolution,
            so a float32 copy of the sentinel is still recognised).
        drops_report: True: a report with an invalid value is dropped (positions); False: the
            value becomes unavailable (NaN) and the report is kept (speed, course, heading).
    """

    role: str
    low: float
    high: float
    high_open: bool
    not_available: float | None
    tolerance: float
    drops_report: bool

    def classify(self, values: np.ndarray) -> dict[str, np.ndarray]:
        """Boolean masks of the invalid values, by reason, each value in at most one.

        Args:
            values: (N,) the column, float64.

        Returns:
            dict[str, ndarray]: ``"{role}_missing"``, ``"{role}_not_available"`` (only with a
            sentinel) and ``"{role}_out_of_range"``, each (N,) bool.
        """
        v = np.asarray(values, dtype=np.float64)
        missing = ~np.isfinite(v)
        out = {f"{self.role}_missing": missing}
        seen = missing
        if self.not_available is not None:
            sentinel = ~seen & (np.abs(v - self.not_available) <= self.tolerance)
            out[f"{self.role}_not_available"] = sentinel
            seen = seen | sentinel
        with np.errstate(invalid="ignore"):
            above = v >= self.high if self.high_open else v > self.high
            out[f"{self.role}_out_of_range"] = ~seen & ((v < self.low) | above)
        return out

    def valid(self, values: np.ndarray) -> np.ndarray:
        """(N,) bool: the values that pass (:meth:`classify` finds nothing)."""
        bad = np.zeros(np.shape(values), dtype=bool)
        for mask in self.classify(values).values():
            bad |= mask
        return ~bad


#: The per-report rules, by role. Positions: a report without a valid latitude and longitude is
#: dropped. Speed (knots; AIS: 102.2 = "102.2 or more"), course (degrees in [0, 360)) and true
#: heading (degrees in [0, 360)): an invalid value becomes unavailable, the report is kept. With
#: ``course_encoding="degrees"`` (not AIS) a course is taken modulo 360 and only a negative speed
#: is invalid.
REPORT_RULES: dict[str, ValueRule] = {
    "lat": ValueRule("lat", -90.0, 90.0, False, AIS_NOT_AVAILABLE["lat"], 1e-6, True),
    "lon": ValueRule("lon", -180.0, 180.0, False, AIS_NOT_AVAILABLE["lon"], 1e-6, True),
    "sog": ValueRule("sog", 0.0, 102.2 + 1e-6, False, AIS_NOT_AVAILABLE["sog"], 0.05, False),
    "cog": ValueRule("cog", 0.0, 360.0, True, AIS_NOT_AVAILABLE["cog"], 0.05, False),
    "heading": ValueRule("heading", 0.0, 360.0, True, AIS_NOT_AVAILABLE["heading"], 0.5, False),
}


def parse_instant(value: object, argument: str) -> np.datetime64:
    """One instant as ``datetime64[us]`` in UTC.

    Args:
        value: an ISO 8601 string (``Z`` or ``±hh[:mm]`` converted to UTC; none = UTC), a
            ``numpy.datetime64`` or a :class:`datetime.datetime` (an aware one converted to UTC,
            a naive one taken as UTC).
        argument: the argument's name, for the error (e.g. ``"cut_times[1]"``).

    Returns:
        numpy.datetime64: microseconds since 1970-01-01 UTC.

    Raises:
        TypeError: for another type, naming ``argument``.
        ValueError: for a string that is not an ISO 8601 date-time, or an impossible date,
            naming ``argument`` and the value.
    """
    if isinstance(value, np.datetime64):
        if np.isnat(value):
            raise ValueError(f"{argument} is NaT (not a time)")
        return value.astype("datetime64[us]")
    if isinstance(value, datetime.datetime):
        if value.tzinfo is not None:
            value = value.astimezone(datetime.timezone.utc).replace(tzinfo=None)
        return np.datetime64(value, "us")
    if isinstance(value, datetime.date):
        return np.datetime64(value, "D").astype("datetime64[us]")
    if not isinstance(value, str):
        raise TypeError(f"{argument} must be an ISO 8601 string or a datetime64, got {type(value).__name__} {value!r}")
    match = re.match(ISO_8601, value)
    if match is None:
        raise ValueError(f"{argument}={value!r} is not an ISO 8601 date-time (e.g. '2020-12-07T00:00:00', UTC)")
    part = match.groupdict()
    wall = f"{part['date']}T{part['hour'] or '00'}:{part['minute'] or '00'}:{part['second'] or '00'}"
    try:
        when = datetime.datetime.fromisoformat(wall)
    except ValueError as err:
        raise ValueError(f"{argument}={value!r} is not a valid date-time: {err}") from None
    us = np.datetime64(when, "us") + np.timedelta64(int((part["fraction"] or "0").ljust(6, "0")[:6]), "us")
    zone = part["zone"] or ""
    if zone not in ("", "Z"):
        digits = zone[1:].replace(":", "").ljust(4, "0")
        hours, minutes = int(digits[:2]), int(digits[2:])
        if hours >= 24 or minutes >= 60:
            raise ValueError(f"{argument}={value!r}: the UTC offset {zone!r} is not a valid offset")
        offset = np.timedelta64((hours * 60 + minutes) * 60_000_000, "us")
        us = us - offset if zone.startswith("+") else us + offset
    return us


def _number(name: str, value: object, *, allow_none: bool = True) -> float | None:
    """A positive finite number (or None), else TypeError / ValueError naming ``name``."""
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a positive number{' or None' if allow_none else ''}, got {value!r}")
    if not (math.isfinite(float(value)) and float(value) > 0):
        raise ValueError(f"{name} must be a positive number{' or None' if allow_none else ''}, got {value!r}")
    return float(value)


def _columns(value: object) -> dict[str, str | int] | str | None:
    """``columns`` checked: None, "ais" or a mapping role -> header name / 0-based position."""
    if value is None:
        return None
    if isinstance(value, str):
        if value != "ais":
            raise ValueError(f"columns must be a mapping role -> column, 'ais' or None, got {value!r}")
        return value
    if not isinstance(value, Mapping):
        raise TypeError(
            "columns must be a mapping role -> column (header name or 0-based position), e.g. "
            f"{{'id': 'MMSI', 'time': 'BaseDateTime', 'lat': 'LAT', 'lon': 'LON'}}, 'ais' or None; "
            f"got {type(value).__name__} {value!r}"
        )
    cols: dict[str, str | int] = {}
    for role, column in value.items():
        if column is None:
            continue
        if isinstance(column, bool) or not isinstance(column, (str, numbers.Integral)):
            raise TypeError(
                f"columns[{role!r}] must be a header name or a 0-based position, got {type(column).__name__} {column!r}"
            )
        if isinstance(column, numbers.Integral) and int(column) < 0:
            raise ValueError(f"columns[{role!r}]={column}: positions are 0-based, >= 0")
        cols[str(role)] = int(column) if isinstance(column, numbers.Integral) else str(column)
    unknown = sorted(set(cols) - set(ROLES))
    missing = sorted(set(_REQUIRED_ROLES) - set(cols))
    if unknown or missing:
        raise ValueError(f"columns: unknown roles {unknown} / missing roles {missing}; roles are {ROLES}, got {cols}")
    by_column: dict[str | int, list[str]] = {}
    for role, column in cols.items():
        by_column.setdefault(column, []).append(role)
    shared = {column: roles for column, roles in by_column.items() if len(roles) > 1}
    if shared:
        raise ValueError(
            "columns: one column for several roles: "
            + "; ".join(f"{column!r} is {' and '.join(roles)}" for column, roles in shared.items())
        )
    return cols


def _instants(name: str, value: object) -> tuple[str, ...]:
    """A sequence of instants, each checked by :func:`parse_instant`, kept as strings."""
    if value is None:
        return ()
    if isinstance(value, (str, bytes, np.datetime64, datetime.date)):
        raise TypeError(
            f"{name} must be a sequence of instants, not a single {type(value).__name__}: write {name}=[{value!r}]"
        )
    if not isinstance(value, Sequence) and not isinstance(value, np.ndarray):
        raise TypeError(f"{name} must be a sequence of ISO 8601 instants, got {type(value).__name__} {value!r}")
    out = []
    for i, v in enumerate(value):
        parse_instant(v, f"{name}[{i}]")
        out.append(v.isoformat() if isinstance(v, datetime.date) else str(v))
    return tuple(out)


@dataclass(frozen=True)
class CleaningRules:
    """How reports are read and cleaned into tracks: the one settings object of the data path.

    Reading (:func:`~torchsde_lti.data.read_reports`):

    Attributes:
        columns: CSV / Parquet role -> column (header name or 0-based position) for the roles in
            :data:`ROLES` (id, time, lat, lon required; alt, sog, cog, heading optional); None or
            ``"ais"``: the MarineCadastre AIS header. One column plays one role.
        format: "traj", "csv" or "parquet" (None: the file's suffix).
        time_format: strptime format of the time column when it is not ISO 8601.
        altitude_unit: "m" or "ft".

    Cleaning (:func:`~torchsde_lti.data.prepare_tracks`; the per-report rules are
    :data:`REPORT_RULES`):

    Attributes:
        dims: 2 or 3 (east, north, altitude); None = 3 when the file has a non-zero altitude.
        frame: "local" (each track's own origin, its first report) or "common" (``reference``).
        reference: (lat, lon[, alt]) of the common frame (degrees in range, metres), only with
            ``frame="common"``.
        course_encoding: SOG/COG conventions: "ais" (:data:`REPORT_RULES`), "ais_int12" (also
            decodes a COG stored as a signed 12-bit field: negative v -> v + 409.6), "degrees"
            (not AIS: any COG taken modulo 360, a negative SOG unavailable).
        max_gap: cut tracks at gaps longer than this (s); None = never.
        v_max: implied speed (m/s) above which a jump is implausible; None = no check.
        min_reports: drop tracks with fewer reports (an integer >= 2).
        max_extent: cut tracks leaving this radius (m) around their origin (local frames only);
            None = never.
        cut_times: instants at which every track is cut (:func:`parse_instant`), so that a split
            in time keeps each part in its own frame.

    Every field is checked when the object is made (or :meth:`replace` d): TypeError or
    ValueError naming the field.
    """

    columns: Mapping[str, str | int] | str | None = None
    format: str | None = None
    time_format: str | None = None
    altitude_unit: str = "m"
    dims: int | None = None
    frame: str = "local"
    reference: tuple[float, ...] | None = None
    course_encoding: str = "ais"
    max_gap: float | None = 1800.0
    v_max: float | None = None
    min_reports: int = 2
    max_extent: float | None = 250_000.0
    cut_times: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        put = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        put("columns", _columns(self.columns))
        if self.format is not None:
            if not isinstance(self.format, str) or self.format.lower() not in _FORMATS:
                raise ValueError(f"format must be 'traj', 'csv', 'parquet' or None, got {self.format!r}")
            put("format", self.format.lower())
        if self.time_format is not None and not isinstance(self.time_format, str):
            raise TypeError(f"time_format must be a strptime format string or None, got {self.time_format!r}")
        if self.altitude_unit not in ("m", "ft"):
            raise ValueError(f"altitude_unit must be 'm' or 'ft', got {self.altitude_unit!r}")
        if self.dims is not None and (isinstance(self.dims, bool) or self.dims not in (2, 3)):
            raise ValueError(f"dims must be 2, 3 or None, got {self.dims!r}")
        if self.frame not in ("local", "common"):
            raise ValueError(f"frame must be 'local' or 'common', got {self.frame!r}")
        put("reference", self._reference())
        if self.course_encoding not in _COURSE_ENCODINGS:
            raise ValueError(f"course_encoding must be one of {_COURSE_ENCODINGS}, got {self.course_encoding!r}")
        for name in ("max_gap", "v_max", "max_extent"):
            put(name, _number(name, getattr(self, name)))
        m = self.min_reports
        if isinstance(m, bool) or not isinstance(m, numbers.Real):
            raise TypeError(f"min_reports must be an integer >= 2, got {m!r}")
        if float(m) != int(m) or int(m) < 2:
            raise ValueError(f"min_reports must be an integer >= 2 (a track needs a time step), got {m!r}")
        put("min_reports", int(m))
        put("cut_times", _instants("cut_times", self.cut_times))

    def _reference(self) -> tuple[float, ...] | None:
        ref = self.reference
        if self.frame == "local":
            if ref is not None:
                raise ValueError(f"reference={ref!r} is only used with frame='common' (frame is 'local')")
            return None
        if isinstance(ref, (str, bytes)) or not isinstance(ref, (Sequence, np.ndarray)) or len(ref) not in (2, 3):
            raise ValueError(f"frame='common' needs reference=(lat, lon[, alt]), got {ref!r}")
        values: list[float] = []
        for name, v in zip(("latitude", "longitude", "altitude"), ref):
            if isinstance(v, bool) or not isinstance(v, numbers.Real):
                raise TypeError(f"reference {name} must be a number, got {v!r}")
            if not math.isfinite(float(v)):
                raise ValueError(f"reference {name} must be finite, got {v!r}")
            values.append(float(v))
        for role, v in zip(("lat", "lon"), values):
            rule = REPORT_RULES[role]
            if not rule.valid(np.array([v]))[0]:
                raise ValueError(
                    f"reference {'latitude' if role == 'lat' else 'longitude'} {v!r} is outside "
                    f"[{rule.low:g}, {rule.high:g}] degrees"
                    + (f" ({v:g} is AIS's 'not available')" if v == rule.not_available else "")
                )
        return tuple(values)

    def replace(self, **changes: Any) -> CleaningRules:
        """A copy with ``changes`` (field -> value), checked like a new object.

        Raises:
            TypeError: for a name that is not a field, naming it and the fields.
        """
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise TypeError(
                f"unknown cleaning rule(s) {unknown}; the rules are {[f.name for f in dataclasses.fields(self)]}"
            )
        return dataclasses.replace(self, **changes)

    @classmethod
    def coerce(cls, rules: CleaningRules | Mapping[str, Any] | None, **changes: Any) -> CleaningRules:
        """``rules`` (an object, a mapping of fields such as a Hydra node, or None = the defaults)
        with ``changes`` applied: how the loaders accept ``rules=`` and their keyword shortcuts."""
        if rules is None:
            base = cls()
        elif isinstance(rules, CleaningRules):
            base = rules
        elif isinstance(rules, Mapping):
            base = cls().replace(**{str(k): v for k, v in rules.items()})
        else:
            raise TypeError(f"rules must be a CleaningRules, a mapping of its fields or None, got {rules!r}")
        return base.replace(**changes) if changes else base

    def cut_instants(self) -> np.ndarray:
        """(K,) ``cut_times`` as sorted datetime64[us] in UTC."""
        return np.sort(
            np.array(
                [parse_instant(c, f"cut_times[{i}]") for i, c in enumerate(self.cut_times)], dtype="datetime64[us]"
            )
        )

    def as_dict(self) -> dict[str, Any]:
        """Plain Python values (JSON-ready, and what checkpoints store)."""
        return {
            "columns": dict(self.columns) if isinstance(self.columns, Mapping) else self.columns,
            "format": self.format,
            "time_format": self.time_format,
            "altitude_unit": self.altitude_unit,
            "dims": self.dims,
            "frame": self.frame,
            "reference": None if self.reference is None else list(self.reference),
            "course_encoding": self.course_encoding,
            "max_gap": self.max_gap,
            "v_max": self.v_max,
            "min_reports": self.min_reports,
            "max_extent": self.max_extent,
            "cut_times": list(self.cut_times),
        }

    @property
    def reading(self) -> dict[str, Any]:
        """The reading fields as keyword arguments of :func:`~torchsde_lti.data.read_reports`."""
        return {
            "columns": self.columns,
            "format": self.format,
            "time_format": self.time_format,
            "altitude_unit": self.altitude_unit,
        }
