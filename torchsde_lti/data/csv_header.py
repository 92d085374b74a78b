"""Where a CSV's column names are: ``#`` comment lines, the header line, and a data line taken
for one (an error that says where the names are and how to name the columns by position).

Used by the CSV reader of :mod:`torchsde_lti.data.sources`.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

from torchsde_lti.data.rules import ISO_8601
from torchsde_lti.data.values import NUMBER

__all__ = [
    "ROLE_NAMES",
    "check_header",
    "first_line",
    "first_line_is_header",
    "leading_comment_lines",
    "looks_like_data",
    "split_line",
    "suggest_columns",
]


def split_line(line: str) -> list[str]:
    """The fields of one CSV line (quotes honoured)."""
    import csv

    return next(csv.reader([line]), [])


def looks_like_data(fields: list[str]) -> bool:
    """Whether a line that should name the columns holds data: a field that is a number or an
    ISO 8601 date-time (column names are neither)."""
    return any(re.match(NUMBER, f.strip()) or re.match(ISO_8601, f) for f in fields)


# header names by role, lower case, to suggest a mapping when the names sit on a '#' line
ROLE_NAMES = {
    "id": ("mmsi", "object_id", "id", "callsign", "icao24", "vessel", "track_id"),
    "time": ("basedatetime", "timestamp", "time", "datetime", "ts", "t"),
    "lat": ("lat", "latitude"),
    "lon": ("lon", "lng", "long", "longitude"),
    "alt": ("alt", "altitude"),
    "sog": ("sog",),
    "cog": ("cog",),
    "heading": ("heading",),
}


def suggest_columns(names: list[str]) -> dict[str, int]:
    """role -> position of the names that say their role (:data:`ROLE_NAMES`); {} unless the
    required roles are all there."""
    lower = [n.strip().lower() for n in names]
    out = {role: lower.index(n) for role, known in ROLE_NAMES.items() for n in known if n in lower}
    out = {role: out[role] for role in ROLE_NAMES if role in out}
    return out if {"id", "time", "lat", "lon"} <= set(out) else {}


def check_header(path: Path, header: list[str], comments: list[str], recognising: bool) -> None:
    """Refuse a data line read as the header, saying where the names are (a ``#`` line, which
    is skipped as a comment) and how to name the columns by position instead."""
    if not looks_like_data(header):
        return
    last = comments[-1].lstrip("#").strip() if comments else ""
    names = split_line(last) if "," in last else last.split()
    suggestion = {"id": 0, "time": 1, "lat": 2, "lon": 3}
    if names and not looks_like_data(names):
        positions = ", ".join(f"{name.strip()}={i}" for i, name in enumerate(names))
        where = (
            f"the column names are on '#' comment line {len(comments)} ({comments[-1].strip()[:120]!r}), which is "
            f"skipped as a comment; the line after it (line {len(comments) + 1}), where the header should be, "
            f"holds data"
        )
        fix = f"name the columns by 0-based position (from the comment line: {positions})"
        suggestion = suggest_columns(names) or suggestion
    else:
        where = f"line {len(comments) + 1}, where the header should be, holds data: {','.join(header)[:120]!r}"
        fix = "add a header line, or name the columns by 0-based position"
    recognised = "no header recognised (not the MarineCadastre AIS header): " if recognising else ""
    raise ValueError(
        f"{path}: {recognised}{where}; {fix}, e.g. columns={suggestion} (positions read every line as data)"
    )


def leading_comment_lines(path: Path) -> list[str]:
    """The ``#`` lines at the top of a CSV (tracktable's point files)."""
    lines = []
    with open(path, encoding="utf-8-sig", errors="replace") as fh:
        for line in fh:
            if not line.startswith("#"):
                break
            lines.append(line.rstrip("\r\n"))
    return lines


def first_line(path: Path, skip: int) -> str:
    """The line after the first ``skip`` lines, without its line break ('' at the end of the file)."""
    with open(path, "rb") as fh:
        for _ in range(skip):
            fh.readline()
        first = fh.readline().rstrip(b"\r\n")
    return first.decode("utf-8-sig", errors="replace")


def first_line_is_header(first: str, columns: Mapping[str, str | int]) -> bool:
    """Whether ``first`` has text, not a number, at the latitude or longitude position of ``columns``."""
    fields = split_line(first)
    positions = [columns.get(role) for role in ("lat", "lon")]
    return any(
        isinstance(c, int) and c < len(fields) and re.match(NUMBER, fields[c].strip()) is None for c in positions
    )
