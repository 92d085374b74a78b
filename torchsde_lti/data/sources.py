"""Reading trajectory files into columns of reports: tracktable ``.traj``, CSV and Parquet.

One reader per format, one result type (:class:`Reports`: numpy arrays, one entry per
report) and one rule for what cannot be read: a malformed line (``.traj``) or row (CSV,
Parquet) is skipped and COUNTED, with the first few examples kept for the summary.

- ``.traj`` (tracktable's trajectory text format): one trajectory per line,
  ``*T*[, uuid], domain, N, n_props, (name, type, value) * n_props, *P*, domain, dim,
  has_id, has_time, k, (name, type) * k`` followed by N points ``id, time, lon, lat, k values``.
  A point property named ``altitude`` becomes the altitude column. Parsed with ``str.split``
  and numpy (the lines have no fixed width, so no CSV engine reads them); the file's own
  segmentation is kept (``segment`` = line number).
- CSV and Parquet through pyarrow (one pass, malformed rows counted). Columns are
  named per role (``columns={"id": ..., "time": ..., "lat": ..., "lon": ..., "alt": ...,
  "sog": ..., "cog": ...}``, header names or 0-based positions); without ``columns`` the
  MarineCadastre AIS header (:data:`AIS_COLUMNS`) is recognised. Leading ``#`` lines
  (tracktable's point files) are skipped. Times: ISO 8601 strings, each row read on its own
  (``Z`` or a ``±hh[:mm]`` offset converted to UTC, a time without one taken as UTC, fractions
  finer than the microsecond truncated), a ``time_format`` for anything else, numbers (seconds
  since 1970-01-01 UTC) or Parquet timestamps (converted to UTC, truncated to the microsecond).

Files are found by path, or by file name among the example files of the optional package
``tracktable-data`` (located with ``importlib.util.find_spec``: its modules are never
imported, since ``tracktable_data.data`` sets ``sys.tracebacklimit = 0`` and configures the
root logger at import).
"""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from torchsde_lti.data.csv_header import (
    check_header,
    first_line,
    first_line_is_header,
    leading_comment_lines,
    split_line,
)
from torchsde_lti.data.rules import ROLES, CleaningRules
from torchsde_lti.data.values import column_numbers, column_times

__all__ = ["AIS_COLUMNS", "RESERVED_FOR_EVALUATION", "ROLES", "Reports", "locate_file", "read_reports"]

#: MarineCadastre AIS column names (BaseDateTime ISO 8601 UTC, LAT/LON degrees, SOG knots, COG degrees).
AIS_COLUMNS: dict[str, str] = {
    "id": "MMSI",
    "time": "BaseDateTime",
    "lat": "LAT",
    "lon": "LON",
    "sog": "SOG",
    "cog": "COG",
}
#: tracktable-data files kept for evaluation only: never train, tune or select models on them.
RESERVED_FOR_EVALUATION = ("NYHarbor_2020_12_08.traj", "VirginiaBeach_2020_06_04_to_06_filtered.traj")
# their content as tracktable-data 1.7.3.1 ships it, (size in bytes, sha256): a copy under another name is refused too
_RESERVED_CONTENT = {
    "NYHarbor_2020_12_08.traj": (446_635, "b23de3fd5442a941eb1a025308681d60cb086ab1bd0151a26b2726ea820aee5c"),
    "VirginiaBeach_2020_06_04_to_06_filtered.traj": (
        1_951_886,
        "610f8e8cf09180e2db28dccc34d421aa8cb5e620c0c97c5bce8561456c287a6f",
    ),
}
_EXAMPLES = 3  # malformed examples kept


class Reports(NamedTuple):
    """All readable reports of one file, in file order; N = number of reports.

    object_id: (N,) int64 or str; time: (N,) datetime64[us] (UTC where the file says so);
    lat, lon: (N,) float64 degrees as read; alt: (N,) metres or None; sog: (N,) knots or None;
    cog: (N,) degrees or None; heading: (N,) degrees or None (true heading); segment: (N,) int64 (a ``.traj`` line) or None (one track per id);
    rows: lines (``.traj``: points of the readable lines, plus one per malformed line) read;
    malformed: lines or rows skipped because a field could not be parsed; malformed_examples: the
    first few of them with the reason; path: the file read; columns: role -> the column's name in
    the file (None: ``.traj``, whose points are lon, lat); decoded: values converted from the
    file format's own convention, counted by name (``"lon_unwrapped"``: a ``.traj`` longitude
    outside [-180, 180), tracktable's unwrapped longitudes, mapped into it).
    """

    object_id: np.ndarray
    time: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    alt: np.ndarray | None
    sog: np.ndarray | None
    cog: np.ndarray | None
    segment: np.ndarray | None
    rows: int
    malformed: int
    malformed_examples: tuple[str, ...]
    path: str
    heading: np.ndarray | None = None
    columns: dict[str, str] | None = None
    decoded: dict[str, int] = {}  # noqa: RUF012 - a NamedTuple's default, never mutated


def _example_dirs() -> list[Path]:
    """Folders of tracktable-data's example files, found without importing the package."""
    spec = importlib.util.find_spec("tracktable_data")
    if spec is None or not spec.submodule_search_locations:
        return []
    return [Path(p) for p in spec.submodule_search_locations]


def locate_file(name: str | os.PathLike[str]) -> Path:
    """The file ``name``: an existing path, else a file of that name shipped by ``tracktable-data``.

    Args:
        name: a path, or the bare name of a shipped file.

    Returns:
        Path: the file found.

    Raises:
        FileNotFoundError: naming the path tried, the package folder searched, and the
            closest shipped file names.
    """
    path = Path(name).expanduser()
    if path.is_file():
        return path
    roots = _example_dirs()
    shipped = {p.name: p for root in roots for p in sorted(root.rglob("*")) if p.is_file() and p.suffix != ".py"}
    if path.name in shipped and path.parent == Path("."):
        return shipped[path.name]
    where = (
        f"tracktable-data's files under {', '.join(map(str, roots))}"
        if roots
        else "tracktable-data's files (package not installed: pip install 'torchsde_lti[data]')"
    )
    import difflib

    close = difflib.get_close_matches(path.name, list(shipped), n=3, cutoff=0.5)
    hint = f"; did you mean {', '.join(close)}?" if close else ""
    raise FileNotFoundError(f"no trajectory file {str(name)!r}: looked at {path.resolve()} and among {where}{hint}")


def read_reports(
    source: str | os.PathLike[str],
    columns: Mapping[str, str | int] | str | None = None,
    *,
    format: str | None = None,
    time_format: str | None = None,
    altitude_unit: str = "m",
) -> Reports:
    """Read every parseable report of a trajectory file (see the module docstring).

    Args:
        source: a path, or a file name shipped by tracktable-data (:func:`locate_file`).
        columns: for CSV / Parquet, role -> column (header name or 0-based position) for the roles
            in :data:`ROLES`; ``"ais"`` or None (recognised from the header) for MarineCadastre AIS.
        format: "traj", "csv" or "parquet"; default from the file suffix.
        time_format: strptime format of the time column when it is not ISO 8601.
        altitude_unit: "m" or "ft" (converted to metres).

    Returns:
        Reports: numpy columns, one entry per readable report, with the malformed ones counted.

    Raises:
        FileNotFoundError: for no such file (:func:`locate_file`).
        TypeError: for an argument of the wrong type (naming it), a column of booleans or
            timestamps for a number (naming the file and the column).
        ValueError: for a file that cannot be read (empty, not CSV text, not Parquet), columns
            that are not in it (the role, the position and the file's column count), a data
            line where the header should be, and a file of which no row reads (each column that
            did not, with a row and its value); every message starts with the file's path.
    """
    if not isinstance(source, (str, os.PathLike)):
        raise TypeError(f"source must be a path (str or os.PathLike), got {type(source).__name__} {source!r}")
    checked = CleaningRules(columns=columns, format=format, time_format=time_format, altitude_unit=altitude_unit)
    columns = checked.columns
    path = locate_file(source)
    fmt = (checked.format or path.suffix.lstrip(".")).lower()
    if fmt == "traj":
        if columns not in (None, "ais"):
            raise ValueError(f"columns are fixed by the .traj format; got columns={columns!r} for {path}")
        reports = _read_traj(path)
    elif fmt in ("csv", "parquet", "pq"):
        reports = _read_table(path, "parquet" if fmt == "pq" else fmt, columns, time_format)
    else:
        raise ValueError(f"unknown trajectory format {fmt!r} of {path}: use format='traj', 'csv' or 'parquet'")
    if reports.alt is not None and altitude_unit == "ft":
        reports = reports._replace(alt=reports.alt * 0.3048)
    return reports


# ---------------------------------------------------------------------------- .traj
def _traj_header(fields: list[str]) -> tuple[int, int, list[str], list[str]]:
    """(index of the first point field, N points, point property names, their type codes)."""
    if not fields or fields[0] != "*T*":
        raise ValueError("line does not start with *T*")
    i = 1 if fields[2].isdigit() else 2  # `*T*, domain, N` (old) or `*T*, uuid, domain, N`
    n_points, n_props = int(fields[i + 1]), int(fields[i + 2])
    i += 3 + 3 * n_props
    if fields[i] != "*P*":
        raise ValueError(f"expected *P* after {n_props} trajectory properties, got {fields[i]!r}")
    domain, dim, has_id, has_time, k = fields[i + 1], fields[i + 2], fields[i + 3], fields[i + 4], int(fields[i + 5])
    if domain not in ("terrestrial", "generic") or dim != "2":
        raise ValueError(f"expected 2-D longitude/latitude points, got domain {domain!r} of dimension {dim}")
    if (has_id, has_time) != ("1", "1"):
        raise ValueError("expected points with an object id and a timestamp")
    names = [fields[i + 6 + 2 * p] for p in range(k)]
    types = [fields[i + 7 + 2 * p] for p in range(k)]
    return i + 6 + 2 * k, n_points, names, types


def _traj_points(fields: list[str], start: int, n: int, types: list[str]) -> list[list[str]]:
    """The N points as columns of strings [ids, times, lons, lats, *values]."""
    width = 4 + len(types)
    body = fields[start:]
    if body and body[-1] == "" and len(body) == n * width + 1:  # a trailing comma
        body = body[:-1]
    if len(body) == n * width:
        return [body[c::width] for c in range(width)]
    # a string value containing commas (vessel names): it runs until the next point's id and time
    if not types or types[-1] != "2":
        raise ValueError(f"{len(body)} point fields, expected {n} x {width}")
    obj, rows, j = body[0], [], 0
    for _ in range(n):
        row = body[j : j + width - 1]
        j += width - 1
        stop = j
        while stop < len(body) and not (
            body[stop] == obj
            and stop + 1 < len(body)
            and body[stop + 1][:2].isdigit()
            and len(body[stop + 1]) >= 19
            and body[stop + 1][4] == "-"
        ):
            stop += 1
        rows.append(row + [",".join(body[j:stop])])
        j = stop
    if j < len(body) and not (j == len(body) - 1 and body[-1] == ""):
        raise ValueError(f"{len(body) - j} fields left after {n} points")
    return [list(col) for col in zip(*rows)] if rows else [[] for _ in range(width)]


def _read_traj(path: Path) -> Reports:
    ids: list[np.ndarray] = []
    times: list[np.ndarray] = []
    lonlat: list[np.ndarray] = []
    alts: list[np.ndarray | None] = []  # None: a line without an altitude property
    segs: list[np.ndarray] = []
    examples: list[str] = []
    malformed, lines, points = 0, 0, 0
    with open(path, encoding="utf-8-sig", errors="replace") as fh:
        for number, line in enumerate(fh, start=1):
            if not line.strip():
                continue
            lines += 1
            try:
                fields = line.rstrip("\r\n").split(",")
                start, n, names, types = _traj_header(fields)
                cols = _traj_points(fields, start, n, types)
                if len(set(cols[0])) > 1:
                    raise ValueError("points of one trajectory carry different object ids")
                when = np.array(cols[1], dtype="datetime64[us]")
                ll = np.array([cols[2], cols[3]], dtype=np.float64).T
                alt = np.array(cols[4 + names.index("altitude")], dtype=np.float64) if "altitude" in names else None
            except (ValueError, IndexError) as err:
                malformed += 1
                if len(examples) < _EXAMPLES:
                    examples.append(f"line {number}: {err}")
                continue
            points += n
            ids.append(np.array(cols[0], dtype=str))
            times.append(when)
            lonlat.append(ll)
            alts.append(alt)
            segs.append(np.full(n, number, dtype=np.int64))
    if not ids:
        raise ValueError(
            f"{path}: no trajectory could be read ({lines} lines, {malformed} malformed: {'; '.join(examples)})"
        )
    object_id = np.concatenate(ids)
    object_id = _object_ids(object_id, np.ones(len(object_id), dtype=bool))
    ll = np.concatenate(lonlat)
    # tracktable writes a trajectory's longitudes unwrapped (continuous across the antimeridian: 190,
    # -200): the format's convention, decoded into [-180, 180) here and counted
    lon = ll[:, 0]
    unwrapped = np.isfinite(lon) & ((lon < -180.0) | (lon >= 180.0))
    lon = np.where(unwrapped, (lon + 180.0) % 360.0 - 180.0, lon)
    alt = None
    if any(a is not None for a in alts):  # altitude when any line has it, NaN at the points of the lines without
        alt = np.concatenate([np.full(len(t), np.nan) if a is None else a for a, t in zip(alts, times)])
    return Reports(
        object_id,
        np.concatenate(times),
        ll[:, 1].copy(),
        lon,
        alt,
        None,
        None,
        np.concatenate(segs),
        points + malformed,  # (a malformed line counts as one row, as in malformed)
        malformed,
        tuple(examples),
        str(path),
        decoded={"lon_unwrapped": int(unwrapped.sum())} if unwrapped.any() else {},
    )


# ---------------------------------------------------------------------------- CSV / Parquet
def _resolve_columns(
    columns: Mapping[str, str | int] | str | None, header: list[str] | None, path: Path, first: str
) -> dict[str, str | int]:
    """role -> column of a CSV / Parquet file, checked against its ``header`` (None: a CSV read
    by position without a header line, ``first`` its first data line)."""
    if columns is None or columns == "ais":
        if header is not None and set(AIS_COLUMNS.values()) <= set(header):
            return dict(AIS_COLUMNS)
        if columns == "ais":
            raise ValueError(
                f"{path}: columns='ais' needs the header columns {sorted(AIS_COLUMNS.values())}, found {header}"
            )
        raise ValueError(
            f"{path}: not the MarineCadastre AIS header {sorted(AIS_COLUMNS.values())}; name the "
            f"columns, e.g. columns={{'id': ..., 'time': ..., 'lat': ..., 'lon': ...}} "
            f"(header names or 0-based positions); header found: {header}"
        )
    cols = dict(columns) if isinstance(columns, Mapping) else {}  # (checked by CleaningRules)
    fields = header if header is not None else split_line(first)
    for role, c in cols.items():
        if isinstance(c, int) and c >= len(fields):
            where = f"not in the header {header}" if header is not None else "out of range"
            raise ValueError(
                f"{path}: columns[{role!r}]={c} is {where}: the file has {len(fields)} columns "
                f"(0-based positions 0 to {len(fields) - 1}); its first {'header' if header else 'data'} line: "
                f"{first[:120]!r}"
            )
        if isinstance(c, str) and c not in fields:
            raise ValueError(
                f"{path}: columns[{role!r}]={c!r} is not in the header {header} (names or 0-based positions)"
            )
    return cols


def _read_table(
    path: Path, fmt: str, columns: Mapping[str, str | int] | str | None, time_format: str | None
) -> Reports:
    try:
        import pyarrow as pa
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ModuleNotFoundError(
            "reading CSV / Parquet trajectories needs pyarrow: pip install 'torchsde_lti[data]'"
        ) from err
    try:
        if fmt == "parquet":
            table, names, bad = _parquet_table(path, columns)
        else:
            table, names, bad = _csv_table(path, columns)
    except (pa.ArrowException, UnicodeDecodeError) as err:  # (the file's path is not in pyarrow's message)
        raise ValueError(f"{path}: cannot be read as {fmt.upper()}: {err}") from err
    return _table_reports(table, names, bad, path, time_format)


def _parquet_table(path: Path, columns: Mapping[str, str | int] | str | None) -> tuple[Any, dict[str, str], list[str]]:
    """(table of the used columns, role -> column name, no malformed rows) of a Parquet file."""
    import pyarrow.parquet as pq

    header = pq.read_schema(path).names
    cols = _resolve_columns(columns, header, path, ",".join(header))
    names = {role: (header[c] if isinstance(c, int) else c) for role, c in cols.items()}
    return pq.read_table(path, columns=sorted(set(names.values()))), names, []


def _csv_table(path: Path, columns: Mapping[str, str | int] | str | None) -> tuple[Any, dict[str, str], list[str]]:
    """(table of the used columns, role -> column name, examples of malformed rows) of a CSV:
    leading ``#`` lines skipped; columns by header name, or by position (a header line above
    them, recognised by text at the latitude or longitude position, skipped)."""
    import pyarrow as pa
    import pyarrow.csv as pcsv

    comments = leading_comment_lines(path)
    skip = len(comments)
    first = first_line(path, skip)
    if not first.strip():
        raise ValueError(f"{path}: no data: the file is empty" + (f" after {skip} '#' comment lines" if skip else ""))
    if any(ord(ch) < 32 and ch != "\t" for ch in first):
        raise ValueError(f"{path}: not a CSV text file: its first line holds control characters ({first[:40]!r})")
    by_position = isinstance(columns, Mapping) and all(isinstance(v, int) for v in columns.values())
    if by_position and isinstance(columns, Mapping) and first_line_is_header(first, columns):
        skip += 1  # positions above a header line: the header is not a row
        first = first_line(path, skip)
    header = None if by_position else split_line(first)
    if header is not None:
        check_header(path, header, comments, recognising=not isinstance(columns, Mapping))
    cols = _resolve_columns(columns, header, path, first)
    # positions: pyarrow's generated names without a header, the header's names with one
    names = {role: (c if isinstance(c, str) else f"f{c}" if header is None else header[c]) for role, c in cols.items()}
    bad: list[str] = []

    def handler(row: object) -> str:
        if len(bad) < _EXAMPLES:
            bad.append(
                f"{getattr(row, 'text', '')[:80]!r}: {getattr(row, 'actual_columns', '?')} fields, "
                f"expected {getattr(row, 'expected_columns', '?')}"
            )
        else:
            bad.append("")
        return "skip"

    read = pcsv.ReadOptions(skip_rows=skip, autogenerate_column_names=by_position)
    string_cols = {names["id"]: pa.string(), names["time"]: pa.string()}
    convert = pcsv.ConvertOptions(
        include_columns=sorted(set(names.values())), column_types=string_cols, strings_can_be_null=True
    )
    table = pcsv.read_csv(
        path, read_options=read, parse_options=pcsv.ParseOptions(invalid_row_handler=handler), convert_options=convert
    )
    return table, names, bad


def _table_reports(table: Any, names: dict[str, str], bad: list[str], path: Path, time_format: str | None) -> Reports:
    """Reports of a table: rows whose id, time, latitude or longitude does not read are skipped
    and counted (an error naming the column, a row and its value when no row reads)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    n = table.num_rows
    ok = np.ones(n, dtype=bool)
    reasons: dict[str, np.ndarray] = {}
    values: dict[str, np.ndarray] = {}
    for role in ("lat", "lon", "alt", "sog", "cog", "heading"):
        if role in names:
            values[role], valid = column_numbers(table[names[role]].combine_chunks(), role, names[role], path)
            if role in ("lat", "lon"):
                reasons[role] = ~valid
                ok &= valid
    time, valid = column_times(table[names["time"]].combine_chunks(), time_format)
    reasons["time"] = ~valid
    ok &= valid
    raw_id = pc.cast(table[names["id"]].combine_chunks(), pa.string())
    id_ok = np.asarray(raw_id.is_valid().to_numpy(zero_copy_only=False), dtype=bool)
    id_ok &= np.asarray(raw_id.fill_null("").to_numpy(zero_copy_only=False), dtype=str) != ""
    reasons["id"] = ~id_ok
    ok &= id_ok
    if not ok.any():
        _no_readable_row(table, names, reasons, bad, path, time_format)
    object_id = _object_ids(np.asarray(raw_id.fill_null("").to_numpy(zero_copy_only=False), dtype=str), ok)
    examples = [b for b in bad if b][:_EXAMPLES]
    for role, mask in reasons.items():
        for r in np.flatnonzero(mask)[: max(0, _EXAMPLES - len(examples))]:
            examples.append(_unreadable(table, names, role, int(r)))
    keep = np.flatnonzero(ok)
    take = (lambda a: a[keep]) if not ok.all() else (lambda a: a)  # noqa: E731
    return Reports(
        take(object_id),
        take(time),
        take(values["lat"]),
        take(values["lon"]),
        take(values["alt"]) if "alt" in values else None,
        take(values["sog"]) if "sog" in values else None,
        take(values["cog"]) if "cog" in values else None,
        None,
        n + len(bad),
        int((~ok).sum()) + len(bad),
        tuple(examples),
        str(path),
        take(values["heading"]) if "heading" in values else None,
        {role: str(name) for role, name in names.items()},
    )


def _unreadable(table: Any, names: dict[str, str], role: str, row: int) -> str:
    """'data row r: <role> column <name> unreadable: <value>' (r 1-based, after the header)."""
    value = table[names[role]][row].as_py()
    return f"data row {row + 1}: {role} column {names[role]!r} unreadable: {'empty' if value in (None, '') else repr(value)}"


def _no_readable_row(
    table: Any,
    names: dict[str, str],
    reasons: dict[str, np.ndarray],
    bad: list[str],
    path: Path,
    time_format: str | None,
) -> None:
    """Raise the ValueError for a file of which no row reads, saying which columns did not."""
    n = table.num_rows
    if n == 0:
        why = f"{len(bad)} rows with the wrong number of fields, e.g. {bad[0]}" if bad else "a header and no data rows"
        raise ValueError(f"{path}: no report can be read: the file has {why}")
    parts = []
    for role in ("id", "time", "lat", "lon"):
        failed = reasons[role]
        if failed.any():
            how = ""
            if role == "time":
                how = (
                    f" with time_format={time_format!r}"
                    if time_format is not None
                    else " (ISO 8601, or numbers: seconds since 1970-01-01 UTC, within ±292,000 years; "
                    "else give time_format)"
                )
            what = "is empty" if role == "id" else "does not read"
            parts.append(
                f"the {role} column {names[role]!r} {what}{how} in {int(failed.sum())} of {n} rows, e.g. "
                + _unreadable(table, names, role, int(np.flatnonzero(failed)[0]))
            )
    raise ValueError(f"{path}: no report can be read: " + "; ".join(parts))


def _object_ids(ids: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """int64 when every readable id is an integer (MMSI) and distinct ids stay distinct ("007"
    and "7" do not), else the strings (call signs)."""
    if not ok.any():
        return ids
    try:
        as_int = np.where(ok, ids, "0").astype(np.int64)
    except (ValueError, OverflowError):
        return ids
    return as_int if len(np.unique(as_int[ok])) == len(np.unique(ids[ok])) else ids
