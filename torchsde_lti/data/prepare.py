"""Out-of-core preparation: many raw trajectory files -> cleaned, windowed tracks in a Parquet dataset.

    summary = prepare_dataset("AIS_2024_*.csv", "prepared/", max_len=128, workers=2)
    print(summary)                       # the loader's counted summary, summed over every file

The same reading (:func:`~torchsde_lti.data.read_reports`) and the same cleaning rules
(:func:`~torchsde_lti.data.prepare_tracks`) as :func:`~torchsde_lti.data.load_tracks`, in
memory bounded independently of the data's size, in two passes of independent tasks run by a
pool of ``workers`` processes:

1. **scatter** (a task per input file): the file is read ``chunk_bytes`` at a time (CSV, the CSV
   inside a zip, ``.traj`` lines; Parquet row groups), each chunk with ``read_reports``, and
   its reports are appended to ``B`` Parquet files by a hash of the object id (MMSI): bucket b
   holds every report of about 1/B of the objects, from every file. ``B`` is chosen from the
   inputs' size (about ``bucket_reports`` reports a bucket) and fixed in the plan. (The chunks:
   :mod:`torchsde_lti.data.chunks`.)
2. **gather** (a task per bucket): a bucket's reports, in the files' order, are cleaned into
   tracks with ``prepare_tracks``, exactly as ``load_tracks`` cleans one file, cut into windows of at most
   ``max_len`` reports (:func:`~torchsde_lti.data.window_bounds`) and written as
   ``windows/bucket=BBBBB.parquet``, one row per window.

A task's outputs are written under temporary names and published by a rename, then recorded in
``_manifest/`` (the plan, one entry per scattered file and per gathered bucket), so a killed
run resumes where it stopped and gives the same dataset; ``summary.json`` is written last (the
:class:`~torchsde_lti.data.LoadSummary` counts summed over the buckets; ``rows`` and
``malformed`` over the files). Since an object's reports all land in one bucket, each bucket is
cleaned like a file of its own: the counts add up, objects included, and preparing ONE file gives
the tracks ``load_tracks`` gives (tested on the national day).

Per-chunk reading: a chunk of one file is read on its own, so what ``read_reports`` decides per
file (integer or text ids, ISO 8601 or epoch seconds when a time column mixes them) is decided
per chunk; a malformed row's example names the file and the chunk's first line.

A window row (``windows/*.parquet``): ``object_id``, ``bucket``, ``track`` (its index in the
bucket), ``length`` (T), ``time`` (T,) int64 microseconds since 1970 UTC, ``lat``, ``lon`` (T,)
degrees, ``east``, ``north`` [, ``up``] (T,) metres in the track's frame, ``origin_lat``,
``origin_lon``, ``origin_alt`` (the frame's origin), and where the files have SOG/COG
``vel_east``, ``vel_north`` (T,) m/s and ``sog`` (T,) knots (NaN: unavailable).
"""

from __future__ import annotations

import dataclasses
import glob
import hashlib
import json
import math
import os
import shutil
import zipfile
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torchsde_lti.data.chunks import report_chunks
from torchsde_lti.data.loaded_tracks import LoadSummary, Tracks, _ranges
from torchsde_lti.data.rules import CleaningRules
from torchsde_lti.data.sources import Reports, locate_file
from torchsde_lti.data.splits import window_bounds
from torchsde_lti.data.trajectories import prepare_tracks

__all__ = ["PREPARED_FORMAT", "PreparedSummary", "find_sources", "prepare_dataset"]

#: Version of the prepared dataset's layout (in ``_manifest/plan.json`` and ``summary.json``).
PREPARED_FORMAT = 1
_SUFFIXES = (".csv", ".zip", ".traj", ".parquet", ".pq")
_EXAMPLES = 3
_BUFFER_REPORTS = 500_000  # reports a scatter task buffers before writing (~30 MB as columns)
_BYTES_PER_REPORT = {".csv": 85, ".zip": 85, ".traj": 45, ".parquet": 0, ".pq": 0}  # 0: rows from the metadata


@dataclass(frozen=True)
class PreparedSummary:
    """What :func:`prepare_dataset` read, removed and kept, and what it wrote.

    ``load`` is the loader's :class:`~torchsde_lti.data.LoadSummary` over all the files (its
    ``source`` names the inputs); ``files``: input files; ``buckets``: B; ``windows``: rows
    written; ``max_len``; ``out``: the dataset's folder.
    """

    load: LoadSummary
    files: int
    buckets: int
    windows: int
    max_len: int | None
    out: str

    def as_dict(self) -> dict[str, Any]:
        """Plain Python values (JSON-ready)."""
        return {
            "format": PREPARED_FORMAT,
            "load": self.load.as_dict(),
            "files": self.files,
            "buckets": self.buckets,
            "windows": self.windows,
            "max_len": self.max_len,
            "out": self.out,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PreparedSummary:
        load = dict(d["load"])
        load["malformed_examples"] = tuple(load["malformed_examples"])
        known = {f.name for f in dataclasses.fields(LoadSummary)}
        return cls(
            LoadSummary(**{k: v for k, v in load.items() if k in known}),
            int(d["files"]),
            int(d["buckets"]),
            int(d["windows"]),
            d["max_len"],
            str(d["out"]),
        )

    def __str__(self) -> str:
        return (
            f"{self.load}\n  prepared: {self.windows} windows of <= {self.max_len or 'all'} reports from "
            f"{self.files} files in {self.buckets} buckets under {self.out}"
        )


# ---------------------------------------------------------------------------- inputs and plan
def find_sources(source: str | os.PathLike[str] | Sequence[str | os.PathLike[str]]) -> list[Path]:
    """The input files of ``source``: a file, a directory (its trajectory files, recursively), a
    glob pattern, or a list of those; sorted, without duplicates.

    Args:
        source: as above (or the name of a file shipped by tracktable-data); trajectory files end
            in .csv, .zip (a CSV inside), .traj, .parquet or .pq.

    Returns:
        list[Path]: the files, resolved.

    Raises:
        FileNotFoundError: when ``source`` names no trajectory file (naming it).
        ValueError: for a file reserved for evaluation.
    """
    from torchsde_lti.data.modules import _reserved_file

    items = [source] if isinstance(source, (str, os.PathLike)) else list(source)
    found: set[Path] = set()
    for item in items:
        text = os.path.expanduser(str(item))
        path = Path(text)
        if path.is_dir():
            matches = [p for p in path.rglob("*") if p.is_file() and p.suffix.lower() in _SUFFIXES]
        elif path.is_file():
            matches = [path]
        else:
            matches = [Path(p) for p in glob.glob(text, recursive=True) if Path(p).is_file()]
            matches = [p for p in matches if p.suffix.lower() in _SUFFIXES]
        if not matches and not glob.has_magic(text):
            matches = [locate_file(text)]  # a file shipped by tracktable-data (FileNotFoundError says where it looked)
        if not matches:
            raise FileNotFoundError(f"source={str(item)!r}: no trajectory file ({', '.join(_SUFFIXES)}) there")
        found.update(p.resolve() for p in matches)
    files = sorted(found)
    for f in files:
        reserved = _reserved_file(f)
        if reserved is not None:
            raise ValueError(f"source: {f} is {reserved}, reserved for evaluation (never train, tune or select on it)")
    return files


def _file_key(path: Path) -> str:
    """A name for the file's scattered parts: its path, size and modification time, hashed."""
    st = path.stat()
    return hashlib.sha1(f"{path}\0{st.st_size}\0{st.st_mtime_ns}".encode()).hexdigest()[:16]


def _estimated_reports(path: Path) -> int:
    suffix = path.suffix.lower()
    if suffix in (".parquet", ".pq"):
        import pyarrow.parquet as pq

        return int(pq.ParquetFile(path).metadata.num_rows)
    size = path.stat().st_size
    if suffix == ".zip":
        with zipfile.ZipFile(path) as z:
            size = sum(i.file_size for i in z.infolist())
    return max(1, size // _BYTES_PER_REPORT[suffix])


def _plan(
    files: list[Path], rules: dict[str, Any], max_len: int | None, buckets: int | None, bucket_reports: int
) -> dict[str, Any]:
    """The dataset's plan: its inputs, settings and number of buckets (fixed once written)."""
    if buckets is None:
        buckets = max(1, math.ceil(sum(_estimated_reports(f) for f in files) / bucket_reports))
    return {
        "format": PREPARED_FORMAT,
        "files": [{"path": str(f), "key": _file_key(f), "size": f.stat().st_size} for f in files],
        "rules": rules,
        "max_len": max_len,
        "buckets": int(buckets),
    }


# ---------------------------------------------------------------------------- scatter
_ARRAY_FIELDS = ("object_id", "time", "lat", "lon", "alt", "sog", "cog", "heading", "segment")


def _bucket_of(object_id: np.ndarray, buckets: int) -> np.ndarray:
    """(N,) bucket of each object id: a multiplicative hash of integer ids (MMSI), CRC-32 of text ids."""
    if object_id.dtype.kind in "iu":
        mixed = object_id.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
        return ((mixed >> np.uint64(32)) % np.uint64(buckets)).astype(np.int64)
    import zlib

    uniq, inverse = np.unique(object_id.astype(str), return_inverse=True)
    codes = np.array([zlib.crc32(u.encode()) for u in uniq.tolist()], dtype=np.int64)
    return (codes % buckets)[inverse]


def _scatter_file(task: dict[str, Any]) -> dict[str, Any]:
    """Pass 1 for one file: its reports, chunk by chunk, into its part of every bucket.

    A bucket's reports are buffered across chunks and written out (a Parquet file each time,
    no writer held open) when the buffers hold more than :data:`_BUFFER_REPORTS` reports (the
    largest buffer first) and at the file's end: memory does not grow with the number of buckets.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    path, key, out = Path(task["path"]), task["key"], Path(task["out"])
    buckets, reading = int(task["buckets"]), task["reading"]
    tmp = out / "_tmp" / key
    if tmp.exists():  # an earlier attempt at this file was stopped: remove whatever of it was published
        shutil.rmtree(tmp)
        for stale in (out / "_scatter").glob(f"bucket=*/{key}-*.parquet"):
            stale.unlink()
    tmp.mkdir(parents=True)
    pending: dict[int, list[Any]] = {}
    sizes: dict[int, int] = {}
    parts: dict[int, int] = {}  # bucket -> files written
    rows = malformed = reports = 0
    examples: list[str] = []
    decoded: dict[str, int] = {}
    columns: dict[str, str] | None = None
    schema = None

    def flush(b: int) -> None:
        pq.write_table(pa.concat_tables(pending.pop(b)), tmp / f"{b}-{parts.get(b, 0):06d}.parquet")
        parts[b] = parts.get(b, 0) + 1
        sizes.pop(b)

    for rep in report_chunks(path, tmp, int(task["chunk_bytes"]), reading):
        rows += rep.rows
        malformed += rep.malformed
        columns = columns or rep.columns
        for name, count in rep.decoded.items():
            decoded[name] = decoded.get(name, 0) + int(count)
        examples += list(rep.malformed_examples)[: max(0, _EXAMPLES - len(examples))]
        if len(rep.time) == 0:
            continue
        reports += len(rep.time)
        table = _reports_table(rep)
        if schema is None:
            schema = table.schema
        elif table.schema != schema:  # (text ids in a chunk after integer ones, say)
            raise ValueError(f"{path}: a chunk read as {table.schema} after {schema} in an earlier chunk")
        bucket = _bucket_of(rep.object_id, buckets)
        order = np.argsort(bucket, kind="stable")
        sorted_b = bucket[order]
        edges = np.flatnonzero(np.diff(sorted_b)) + 1
        for a, z in zip(np.concatenate([[0], edges]), np.concatenate([edges, [len(order)]])):
            b = int(sorted_b[a])
            # a copy of the bucket's rows (a slice would keep the whole chunk alive while it waits)
            pending.setdefault(b, []).append(table.take(pa.array(order[a:z])))
            sizes[b] = sizes.get(b, 0) + int(z - a)
        while sum(sizes.values()) > _BUFFER_REPORTS:
            flush(max(sizes, key=lambda k: sizes[k]))
    for b in sorted(pending):
        flush(b)
    for b, n in parts.items():  # publish: rename into the buckets
        folder = out / "_scatter" / f"bucket={b:05d}"
        folder.mkdir(parents=True, exist_ok=True)
        for k in range(n):
            os.replace(tmp / f"{b}-{k:06d}.parquet", folder / f"{key}-{k:06d}.parquet")
    shutil.rmtree(tmp, ignore_errors=True)
    entry = {"path": str(path), "key": key, "rows": rows, "malformed": malformed, "examples": examples}
    entry |= {"reports": reports, "buckets": sorted(parts), "columns": columns, "decoded": decoded}
    _write_json(out / "_manifest" / "scatter" / f"{key}.json", entry)
    return entry


def _reports_table(rep: Reports) -> Any:
    """The array fields of ``rep`` as a pyarrow table (times as int64 microseconds)."""
    import pyarrow as pa

    cols: dict[str, Any] = {}
    for name in _ARRAY_FIELDS:
        v = getattr(rep, name, None)
        if v is None:
            continue
        if name == "time":
            v = v.astype("datetime64[us]").astype(np.int64)
        cols[name] = pa.array(v.astype(str) if v.dtype.kind == "U" else v)
    return pa.table(cols)


# ---------------------------------------------------------------------------- gather
def _gather_bucket(task: dict[str, Any]) -> dict[str, Any]:
    """Pass 2 for one bucket: clean its reports into tracks, cut windows, write them."""
    import pyarrow.parquet as pq

    out, b = Path(task["out"]), int(task["bucket"])
    folder = out / "_scatter" / f"bucket={b:05d}"
    parts = [p for key in task["keys"] for p in sorted(folder.glob(f"{key}-*.parquet"))]  # the files' order
    name = f"{task['source']} (bucket {b} of {task['buckets']})"
    entry: dict[str, Any] = {"bucket": b, "windows": 0, "counts": None}
    if parts:
        table = _concat([pq.read_table(p) for p in parts])
        rep = _table_reports(table, name, task["columns"])
        rules = CleaningRules.coerce(task["rules"])
        try:
            tracks = prepare_tracks(rep, rules=rules)
        except ValueError as err:
            if "no report has a valid position" not in str(err) and "no track of" not in str(err):
                raise
            tracks = None  # (no track left in this bucket: counted below)
            entry["counts"] = _empty_counts(rep, rules)
        if tracks is not None:
            windows = _windows_table(tracks, task["max_len"], b)
            target = out / "windows" / f"bucket={b:05d}.parquet"
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = target.with_name(f".{target.name}.tmp")
            pq.write_table(windows, tmp, row_group_size=int(task["row_group_windows"]), compression="zstd")
            os.replace(tmp, target)
            entry["windows"] = windows.num_rows
            entry["counts"] = tracks.summary.as_dict()
            entry["dims"] = tracks.dims
    _write_json(out / "_manifest" / "gather" / f"{b:05d}.json", entry)
    return entry


def _concat(tables: list[Any]) -> Any:
    import pyarrow as pa

    if len({t.schema.field("object_id").type for t in tables}) > 1:  # integer ids in some files, text in others
        tables = [
            t.set_column(t.schema.get_field_index("object_id"), "object_id", t["object_id"].cast(pa.string()))
            for t in tables
        ]
    return pa.concat_tables(tables, promote_options="default")


def _table_reports(table: Any, name: str, columns: dict[str, str] | None) -> Reports:
    """A bucket's scattered reports as :class:`Reports` (one report a row, nothing malformed; the
    values the reader decoded are counted by the scatter, per file)."""
    cols = {}
    for field_name in _ARRAY_FIELDS:
        if field_name in table.column_names:
            arr = table[field_name].to_numpy()
            cols[field_name] = arr.astype(str) if arr.dtype == object else arr
    cols["time"] = cols["time"].astype("datetime64[us]")
    n = table.num_rows
    values: dict[str, Any] = {f: cols.get(f) for f in _ARRAY_FIELDS}
    return Reports(**values, rows=n, malformed=0, malformed_examples=(), path=name, columns=columns, decoded={})


def _empty_counts(rep: Reports, rules: CleaningRules) -> dict[str, Any]:
    """The counts of a bucket that keeps no track: its invalid positions by reason, the rest of
    its reports counted as in short tracks (a few objects whose every track is too short)."""
    from torchsde_lti.data.trajectories import _valid_positions

    dims = rules.dims or (3 if rep.alt is not None and bool(np.any(np.isfinite(rep.alt) & (rep.alt != 0))) else 2)
    valid, invalid = _valid_positions(rep, dims)
    return {
        "empty": True,
        "invalid": invalid,
        "invalid_positions": int((~valid).sum()),
        "short_reports": int(valid.sum()),
    }


def _windows_table(tracks: Tracks, max_len: int | None, bucket: int) -> Any:
    """One row per window (the module docstring's columns), list columns without a Python loop."""
    import pyarrow as pa

    owner, a, b = window_bounds(tracks.lengths, max_len)
    a = a + tracks.offsets[owner]
    b = b + tracks.offsets[owner]
    lengths = (b - a).astype(np.int64)
    offsets = pa.array(np.concatenate([[0], np.cumsum(lengths)]).astype(np.int32))
    rows = _ranges(a, lengths)
    t0 = tracks.t0.astype("datetime64[us]").astype(np.int64)
    time = t0 + np.round(tracks.t[rows] * 1e6).astype(np.int64)

    def listed(values: np.ndarray) -> Any:
        return pa.ListArray.from_arrays(offsets, pa.array(np.ascontiguousarray(values)))

    cols: dict[str, Any] = {
        "object_id": pa.array(
            tracks.object_id[owner].astype(str) if tracks.object_id.dtype.kind == "U" else tracks.object_id[owner]
        ),
        "bucket": pa.array(np.full(len(owner), bucket, dtype=np.int32)),
        "track": pa.array(owner.astype(np.int64)),
        "length": pa.array(lengths.astype(np.int32)),
        "time": listed(time),
        "lat": listed(tracks.lat[rows]),
        "lon": listed(tracks.lon[rows]),
        "east": listed(tracks.pos[rows, 0]),
        "north": listed(tracks.pos[rows, 1]),
    }
    if tracks.dims == 3:
        cols["up"] = listed(tracks.pos[rows, 2])
    cols["origin_lat"] = pa.array(tracks.origin[owner, 0])
    cols["origin_lon"] = pa.array(tracks.origin[owner, 1])
    cols["origin_alt"] = pa.array(tracks.origin[owner, 2])
    if tracks.vel is not None:
        cols["vel_east"] = listed(tracks.vel[rows, 0])
        cols["vel_north"] = listed(tracks.vel[rows, 1])
    if tracks.sog is not None:
        cols["sog"] = listed(tracks.sog[rows])
    return pa.table(cols)


# ---------------------------------------------------------------------------- the summary
def _merge(
    files: list[dict[str, Any]], buckets: list[dict[str, Any]], source: str, rules: dict[str, Any]
) -> LoadSummary:
    """One LoadSummary: rows and malformed over the files, every other count over the buckets."""
    kept = [b["counts"] for b in buckets if b["counts"] and "empty" not in b["counts"]]
    empty = [b["counts"] for b in buckets if b["counts"] and "empty" in b["counts"]]
    if not kept:
        raise ValueError(f"{source}: no track is left after cleaning ({sum(e['rows'] for e in files)} reports read)")
    counts: dict[str, Any] = {}
    for field in dataclasses.fields(LoadSummary):
        values = [k[field.name] for k in kept + empty if field.name in k]
        if field.type in ("int", int) and field.name != "dims":
            counts[field.name] = int(sum(values))
        elif values and all(isinstance(v, dict) and all(isinstance(x, int) for x in v.values()) for v in values):
            names = dict.fromkeys(name for v in values for name in v)
            counts[field.name] = {name: sum(v.get(name, 0) for v in values) for name in names}
        elif values:
            counts[field.name] = values[0]
    counts["rows"] = int(sum(e["rows"] for e in files))
    counts["malformed"] = int(sum(e["malformed"] for e in files))
    counts["malformed_examples"] = tuple(x for e in files for x in e["examples"])[:_EXAMPLES]
    counts["decoded"] = {}
    for entry in files:
        for name, count in entry["decoded"].items():
            counts["decoded"][name] = counts["decoded"].get(name, 0) + int(count)
    counts["source"] = source
    return LoadSummary(**counts)


def _write_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(obj, indent=1, default=str) + "\n")
    os.replace(tmp, path)


def _read_json(path: Path) -> Any:
    return json.loads(path.read_text())


# ---------------------------------------------------------------------------- the job
def prepare_dataset(
    source: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    *,
    rules: CleaningRules | Mapping[str, Any] | None = None,
    max_len: int | None = 128,
    workers: int = 1,
    buckets: int | None = None,
    bucket_reports: int = 500_000,
    chunk_bytes: int = 16 << 20,
    row_group_windows: int = 1024,
    keep_scatter: bool = False,
    **changes: Any,
) -> PreparedSummary:
    """Prepare ``source`` into the Parquet dataset ``out`` (see the module docstring); resumes an
    unfinished preparation of the same inputs and settings into ``out``.

    Args:
        source: a file, a directory, a glob pattern or a list of them (:func:`find_sources`).
        out: the dataset's folder (created).
        rules: the reading and cleaning rules (:class:`~torchsde_lti.data.CleaningRules` or a
            mapping of its fields), as :func:`~torchsde_lti.data.load_tracks` takes them.
        max_len: the longest window (reports); None = whole tracks.
        workers: processes of the pool (1: in this process).
        buckets: B, the number of object buckets; None = about ``bucket_reports`` reports each.
        bucket_reports: reports per bucket when ``buckets`` is None (the gather's memory grows
            with it: about 0.5 kB a report at its peak, so 500 k reports ~ 250 MB a worker).
        chunk_bytes: bytes of a file read at once by the scatter (a scatter worker's memory grows
            by roughly 20x this, measured on a MarineCadastre-format day).
        row_group_windows: windows per Parquet row group (the streaming reader's unit).
        keep_scatter: keep the bucketed reports (``_scatter/``) after the gather.
        **changes: fields of :class:`~torchsde_lti.data.CleaningRules` replacing those of
            ``rules`` (``v_max=35.0``, ``min_reports=5``...).

    Returns:
        PreparedSummary: also written to ``out/summary.json``.

    Raises:
        ValueError: ``out`` holds a preparation of other inputs or settings (naming what differs),
            or bad settings (TypeError / ValueError naming them, as ``load_tracks`` raises them).
    """
    checked = CleaningRules.coerce(rules, **changes)
    if max_len is not None and int(max_len) < 2:
        raise ValueError(f"max_len must be >= 2 or None, got {max_len}")
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if buckets is not None and int(buckets) < 1:
        raise ValueError(f"buckets must be >= 1 or None, got {buckets}")
    out = Path(out).expanduser().resolve()
    files = find_sources(source)
    plain = checked.as_dict()
    plan_path = out / "_manifest" / "plan.json"
    plan = _plan(files, plain, None if max_len is None else int(max_len), buckets, int(bucket_reports))
    if plan_path.is_file():
        old = _read_json(plan_path)
        differs = [k for k in ("format", "files", "rules", "max_len") if old.get(k) != plan[k]]
        if buckets is not None and old.get("buckets") != plan["buckets"]:
            differs.append("buckets")
        if differs:
            raise ValueError(
                f"out={str(out)!r} holds a preparation with other {', '.join(differs)}; "
                "prepare into a new folder (or delete it)"
            )
        plan = old
        summary_path = out / "summary.json"
        if summary_path.is_file():
            return PreparedSummary.from_dict(_read_json(summary_path))
    else:
        _write_json(plan_path, plan)
    source_name = ", ".join(map(str, [source] if isinstance(source, (str, os.PathLike)) else source))
    reading = checked.reading
    common = {"out": str(out), "buckets": plan["buckets"]}
    scatter = [
        {**common, "path": f["path"], "key": f["key"], "reading": reading, "chunk_bytes": int(chunk_bytes)}
        for f in plan["files"]
        if not (out / "_manifest" / "scatter" / f"{f['key']}.json").is_file()
    ]
    with _pool(int(workers)) as run:
        run(_scatter_file, scatter)
        file_entries = [_read_json(out / "_manifest" / "scatter" / f"{f['key']}.json") for f in plan["files"]]
        columns = next((f["columns"] for f in file_entries if f["columns"]), None)
        gather = [
            {**common, "bucket": b, "rules": plain, "max_len": plan["max_len"], "source": source_name}
            | {
                "row_group_windows": int(row_group_windows),
                "columns": columns,
                "keys": [f["key"] for f in plan["files"]],
            }
            for b in range(plan["buckets"])
            if not (out / "_manifest" / "gather" / f"{b:05d}.json").is_file()
        ]
        run(_gather_bucket, gather)
    bucket_entries = [_read_json(out / "_manifest" / "gather" / f"{b:05d}.json") for b in range(plan["buckets"])]
    load = _merge(file_entries, bucket_entries, source_name, plain)
    summary = PreparedSummary(
        load, len(files), plan["buckets"], sum(b["windows"] for b in bucket_entries), plan["max_len"], str(out)
    )
    _write_json(out / "summary.json", summary.as_dict())
    if not keep_scatter:
        shutil.rmtree(out / "_scatter", ignore_errors=True)
    shutil.rmtree(out / "_tmp", ignore_errors=True)
    return summary


class _pool:
    """``run(fn, tasks)``: every task, in this process (1 worker) or a pool of processes (started
    by ``forkserver`` or ``spawn``: a script that calls :func:`prepare_dataset` with ``workers > 1``
    needs the ``if __name__ == "__main__":`` guard, as any multiprocessing program)."""

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self.executor: ProcessPoolExecutor | None = None

    def __enter__(self) -> Any:
        if self.workers > 1:
            import multiprocessing

            # forkserver: workers forked from a fresh server that imported this module once (no
            # threads of this process inherited, the imported libraries' pages shared); else spawn
            methods = multiprocessing.get_all_start_methods()
            context = multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
            if context.get_start_method() == "forkserver":
                context.set_forkserver_preload([__name__])
            self.executor = ProcessPoolExecutor(self.workers, mp_context=context)

        def run(fn: Any, tasks: list[dict[str, Any]]) -> list[Any]:
            if self.executor is None:
                return [fn(t) for t in tasks]
            return list(self.executor.map(fn, tasks))

        return run

    def __exit__(self, *exc: object) -> None:
        if self.executor is not None:
            self.executor.shutdown(cancel_futures=True)
