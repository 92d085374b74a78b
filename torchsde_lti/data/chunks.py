"""Reading a trajectory file a chunk at a time, each chunk with :func:`~torchsde_lti.data.read_reports`.

:func:`report_chunks` yields the :class:`~torchsde_lti.data.Reports` of consecutive chunks of
about ``chunk_bytes`` of a file: whole lines of a CSV (each chunk after the first given the file's
leading ``#`` lines and its header line, so it reads as the file would), of the CSV inside a zip,
of a ``.traj`` file (segments renumbered to the file's line numbers), or Parquet record batches.
A chunk is written to a temporary file and read by ``read_reports``: the loader's own reading
(malformed rows counted, values checked), chunk by chunk, in memory set by ``chunk_bytes``. A
malformed row's example names the file and the chunk's first line (or row).
"""

from __future__ import annotations

import zipfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from torchsde_lti.data.sources import Reports, read_reports

__all__ = ["report_chunks"]


def report_chunks(path: Path, tmp: Path, chunk_bytes: int, reading: dict[str, Any]) -> Iterator[Reports]:
    """The reports of each chunk of ``path`` (the module docstring).

    Args:
        path: a CSV, zip (one CSV inside), ``.traj`` or Parquet file.
        tmp: an existing folder for the chunk files (each removed once read).
        chunk_bytes: bytes of the file per chunk (Parquet: estimated from the row groups' sizes).
        reading: ``read_reports``' keyword arguments (``CleaningRules.reading``).

    Yields:
        Reports: each chunk's, ``path`` naming the file.
    """
    if path.suffix.lower() == ".zip":
        with zipfile.ZipFile(path) as z:
            members = [i for i in z.infolist() if not i.is_dir()]
            if len(members) != 1:
                raise ValueError(f"{path}: a zipped source must hold one file, found {[m.filename for m in members]}")
            fmt = (reading.get("format") or Path(members[0].filename).suffix.lstrip(".") or "csv").lower()
            with z.open(members[0]) as fh:
                yield from _text_chunks(fh, fmt, tmp, chunk_bytes, reading, f"{path}!{members[0].filename}")
        return
    fmt = (reading.get("format") or path.suffix.lstrip(".")).lower()
    if fmt in ("parquet", "pq"):
        yield from _parquet_chunks(path, tmp, chunk_bytes, reading)
        return
    with open(path, "rb") as fh:
        yield from _text_chunks(fh, fmt, tmp, chunk_bytes, reading, str(path))


def _text_chunks(
    fh: Any, fmt: str, tmp: Path, chunk_bytes: int, reading: dict[str, Any], name: str
) -> Iterator[Reports]:
    """Chunks of whole lines. Every CSV chunk after the first starts with the file's leading
    comment lines and its header line (when it has one), so that it reads as the file would."""
    preamble = rest = b""
    if fmt == "csv":
        head = [fh.readline()]
        while head[-1].startswith(b"#"):
            head.append(fh.readline())
        preamble = b"".join(head if _has_header(head[-1], reading.get("columns")) else head[:-1])
        rest = b"".join(head)  # the first chunk is the file's own beginning
    line, k = 1, 0
    while True:
        block = fh.read(chunk_bytes)
        data = rest + block
        cut = len(data) if not block else data.rfind(b"\n") + 1
        body, rest = data[:cut], data[cut:]
        if body.strip():
            yield _read_chunk(body if k == 0 else preamble + body, fmt, tmp, reading, name, line, k)
            line += body.count(b"\n")
            k += 1
        if not block:
            return


def _has_header(first: bytes, columns: object) -> bool:
    """Whether a CSV's first non-comment line is a header: yes unless every column is given by
    position and the line has a number at the latitude position."""
    if not isinstance(columns, Mapping) or not all(isinstance(v, int) for v in columns.values() if v is not None):
        return True
    fields = first.decode("utf-8", errors="replace").strip().split(",")
    lat = columns.get("lat")
    if not isinstance(lat, int) or lat >= len(fields):
        return True
    try:
        float(fields[lat])
    except ValueError:
        return True
    return False


def _read_chunk(data: bytes, fmt: str, tmp: Path, reading: dict[str, Any], name: str, line: int, k: int) -> Reports:
    chunk = tmp / f"chunk{k}.{fmt}"
    chunk.write_bytes(data)
    try:
        rep = read_reports(chunk, **{**reading, "format": fmt})
    except ValueError as err:
        raise ValueError(f"{name} (the chunk from line {line}): {err}".replace(str(chunk), name)) from None
    finally:
        chunk.unlink(missing_ok=True)
    examples = tuple(f"{name}, chunk from line {line}: {e}" for e in rep.malformed_examples)
    segment = rep.segment + (line - 1) if rep.segment is not None else None  # .traj: the file's line numbers
    return rep._replace(malformed_examples=examples, segment=segment, path=name)


def _parquet_chunks(path: Path, tmp: Path, chunk_bytes: int, reading: dict[str, Any]) -> Iterator[Reports]:
    import pyarrow as pa
    import pyarrow.parquet as pq

    source = pq.ParquetFile(path)
    rows = max(1, chunk_bytes // max(1, _row_bytes(source)))
    first = 1
    for k, batch in enumerate(source.iter_batches(batch_size=rows)):
        chunk = tmp / f"chunk{k}.parquet"
        pq.write_table(pa.Table.from_batches([batch]), chunk)
        try:
            rep = read_reports(chunk, **{**reading, "format": "parquet"})
        except ValueError as err:
            raise ValueError(f"{path} (the chunk from row {first}): {err}".replace(str(chunk), str(path))) from None
        finally:
            chunk.unlink(missing_ok=True)
        examples = tuple(f"{path}, chunk from row {first}: {e}" for e in rep.malformed_examples)
        yield rep._replace(malformed_examples=examples, path=str(path))
        first += batch.num_rows


def _row_bytes(source: Any) -> int:
    meta = source.metadata
    return max(
        1, meta.serialized_size + sum(meta.row_group(i).total_byte_size for i in range(meta.num_row_groups))
    ) // max(1, meta.num_rows)
