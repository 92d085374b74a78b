"""One column's values, read with pyarrow: numbers (coordinates, speeds) and times.

Used by the CSV / Parquet reader (:mod:`torchsde_lti.data.sources`): each function takes one
pyarrow array and returns numpy values with an ``ok`` mask, so that a value that does not read
makes its row unreadable (counted by the reader) without touching the others.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from torchsde_lti.data.rules import ISO_8601

__all__ = ["NUMBER", "column_numbers", "column_times"]

#: A decimal number, as text (a regular expression).
NUMBER = r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$"


def column_numbers(arr: Any, role: str, column: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(values float64, ok mask): nulls and unparsable strings are not ok.

    Raises:
        TypeError: for a column that holds neither numbers nor text (booleans, timestamps...),
            naming the role, the column and the file.
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    if pa.types.is_dictionary(arr.type):
        arr = arr.dictionary_decode()
    if pa.types.is_string(arr.type) or pa.types.is_large_string(arr.type):
        ok = pc.fill_null(pc.match_substring_regex(pc.utf8_trim_whitespace(arr), NUMBER), False)
        arr = pc.cast(pc.if_else(ok, arr, pa.scalar("nan")), pa.float64())
    elif pa.types.is_integer(arr.type) or pa.types.is_floating(arr.type) or pa.types.is_decimal(arr.type):
        ok = pc.is_valid(arr)
        arr = pc.cast(arr, pa.float64())
    elif pa.types.is_null(arr.type):  # (a CSV column with no value at all)
        ok = pa.array(np.zeros(len(arr), dtype=np.bool_))
        arr = pa.array(np.full(len(arr), np.nan))
    else:
        raise TypeError(f"{path}: the {role} column {column!r} holds {arr.type} values, not numbers")
    return np.asarray(arr.to_numpy(zero_copy_only=False), dtype=np.float64), np.asarray(
        ok.to_numpy(zero_copy_only=False), dtype=bool
    )


def _epoch_seconds(seconds: Any) -> Any:
    """Seconds since 1970-01-01 UTC (a float64 arrow array) as a timestamp[us] array, rounded to
    the microsecond; NaN, ±inf and values beyond the int64 range of microseconds are null."""
    import pyarrow as pa
    import pyarrow.compute as pc

    us = pc.round(pc.multiply(seconds, 1e6))
    valid = pc.and_(pc.is_finite(us), pc.less(pc.abs(us), 9.2e18))
    us = pc.if_else(valid, us, pa.scalar(None, pa.float64()))
    return pc.cast(pc.cast(us, pa.int64()), pa.timestamp("us"))


def _iso_8601(arr: Any) -> Any:
    """Each string of ``arr`` read alone as an ISO 8601 date-time (:data:`ISO_8601`): a
    timestamp[us] array in UTC, null where a string is not one (the other rows still read).

    A fraction finer than the microsecond is truncated (as Parquet ns timestamps are); ``Z`` and a
    ``±hh[[:]mm]`` offset are converted to UTC; a time without a zone is taken as written (UTC).
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    parts = pc.extract_regex(pc.cast(arr, pa.string()), ISO_8601)  # null where the regex fails
    part = {name: pc.struct_field(parts, name) for name in ("date", "hour", "minute", "second", "fraction", "zone")}
    default = lambda name: pc.if_else(pc.equal(part[name], ""), "00", part[name])  # noqa: E731
    clock = pc.binary_join_element_wise(default("hour"), default("minute"), default("second"), ":")
    wall = pc.binary_join_element_wise(part["date"], clock, "T")
    try:  # Arrow's cast checks the calendar (no 30 February), for all rows or none
        seconds = pc.cast(wall, pa.timestamp("s"))
    except pa.ArrowInvalid:  # row by row: strptime rolls 30 February into March, so read it back
        fmt = "%Y-%m-%dT%H:%M:%S"
        seconds = pc.strptime(wall, format=fmt, unit="s", error_is_null=True)
        seconds = pc.if_else(pc.equal(pc.strftime(seconds, format=fmt), wall), seconds, pa.scalar(None, seconds.type))
    fraction = pc.utf8_slice_codeunits(pc.utf8_rpad(part["fraction"], 6, "0"), 0, 6)
    zone = part["zone"]  # "", "Z", "+hh", "+hhmm" or "+hh:mm"
    digits = pc.utf8_rpad(pc.replace_substring(pc.utf8_slice_codeunits(zone, 1, 6), ":", ""), 4, "0")  # hhmm
    hours = pc.cast(pc.utf8_slice_codeunits(digits, 0, 2), pa.int64())
    minutes = pc.cast(pc.utf8_slice_codeunits(digits, 2, 4), pa.int64())
    offset = pc.multiply(pc.add(pc.multiply(hours, 60), minutes), 60_000_000)
    offset = pc.if_else(pc.starts_with(zone, "-"), pc.negate(offset), offset)
    offset = pc.if_else(pc.and_(pc.less(hours, 24), pc.less(minutes, 60)), offset, pa.scalar(None, pa.int64()))
    us = pc.add(pc.multiply(pc.cast(seconds, pa.int64()), 1_000_000), pc.cast(fraction, pa.int64()))
    return pc.cast(pc.subtract(us, offset), pa.timestamp("us"))


def column_times(arr: Any, time_format: str | None) -> tuple[np.ndarray, np.ndarray]:
    """(datetime64[us], ok mask) from strings, numbers (seconds since the epoch) or timestamps.

    Strings: ``time_format`` (strptime) when given, else ISO 8601 or numbers (seconds since the
    epoch), whichever reads more rows. Arrow's cast reads a clean ISO 8601 column in one call;
    when one row fails it, each row is read alone (:func:`_iso_8601`, the same readings), so a
    row that does not read is not ok and the others are unaffected.
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    if pa.types.is_timestamp(arr.type):
        # (finer units truncated to the microsecond)
        us = pa.timestamp("us", tz=arr.type.tz) if arr.type.tz else pa.timestamp("us")
        out = pc.cast(arr, us, safe=False)
    elif pa.types.is_integer(arr.type) or pa.types.is_floating(arr.type):
        out = _epoch_seconds(pc.cast(arr, pa.float64()))
    elif time_format is not None:
        out = pc.strptime(pc.cast(arr, pa.string()), format=time_format, unit="us", error_is_null=True)
    else:
        arr = pc.cast(arr, pa.string())
        for target in (pa.timestamp("us"), pa.timestamp("us", tz="UTC")):  # a clean column: one call
            try:
                out = pc.cast(arr, target)
                break
            except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
                continue
        else:  # some row fails Arrow's cast (which reads all rows or none): each row alone
            # CSV columns arrive as strings: numbers are seconds since the epoch
            numeric = pc.fill_null(pc.match_substring_regex(pc.utf8_trim_whitespace(arr), NUMBER), False)
            epoch = _epoch_seconds(pc.cast(pc.if_else(numeric, arr, pa.scalar(None, pa.string())), pa.float64()))
            out = min((_iso_8601(arr), epoch), key=lambda a: a.null_count)
    ok = np.asarray(pc.is_valid(out).to_numpy(zero_copy_only=False), dtype=bool)
    values = out.cast(pa.int64()).to_numpy(zero_copy_only=False)
    return np.where(ok, np.nan_to_num(values.astype(np.float64)), 0).astype(np.int64).astype("datetime64[us]"), ok
