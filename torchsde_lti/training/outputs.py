"""What a run writes: strict JSON, atomic files, the metrics CSV of a resumed run, the data summary.

Every JSON file the package writes goes through :func:`write_json`: non-finite floats become
``null`` (``json.dumps(..., allow_nan=False)`` then holds: no bare ``NaN`` / ``Infinity``),
tensors, NumPy values, NamedTuples, dataclasses and paths become plain JSON, and the file is
replaced atomically (written next to the target, then renamed), so a reader never sees half a
file — not even when the run is killed while writing.

``metrics.json`` of a run (``schema_version`` :data:`SCHEMA_VERSION`) is built by
:mod:`torchsde_lti.training.train`; its keys are listed in that module's docstring.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["SCHEMA_VERSION", "continue_csv_log", "data_summary", "to_jsonable", "write_json", "write_text"]

#: version of the layout of ``metrics.json`` (bumped when a key changes meaning or moves)
SCHEMA_VERSION = 1


def to_jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON values; NaN and ±inf (floats, tensors, arrays) become None.

    Mappings (keys as strings), sequences, NamedTuples, dataclasses, tensors and arrays
    (as nested lists), NumPy / torch scalars, paths; anything else by its ``str``.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, int):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (torch.Tensor, np.ndarray, np.generic)):
        value = obj.detach().cpu().tolist() if isinstance(obj, torch.Tensor) else obj.tolist()
        return to_jsonable(value)
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "_asdict"):  # NamedTuple
        return to_jsonable(obj._asdict())
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(dataclasses.asdict(obj))
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_jsonable(v) for v in obj]
    return str(obj)


def _replace_atomically(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")  # same directory: os.replace is atomic
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_json(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as strict JSON (:func:`to_jsonable`; NaN/inf as null), atomically."""
    _replace_atomically(Path(path), json.dumps(to_jsonable(obj), indent=2, allow_nan=False) + "\n")


def write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    _replace_atomically(Path(path), text)


def data_summary(datamodule: Any) -> Any:
    """The datamodule's own summary, as JSON values, or None when it offers none.

    Reads ``datamodule.summary`` (an attribute, or a method called without arguments);
    whatever it holds (a dict, a string, a NamedTuple, ...) goes through :func:`to_jsonable`.
    """
    summary = getattr(datamodule, "summary", None)
    if callable(summary):
        summary = summary()
    return None if summary is None else to_jsonable(summary)


def _epoch(row: Mapping[str, str]) -> int | None:
    try:
        return int(float(row.get("epoch") or ""))
    except ValueError:
        return None


def continue_csv_log(logger: Any, last_epoch: int) -> int:
    """Keep the rows of epochs ``<= last_epoch`` in a CSVLogger's ``metrics.csv``, for a run
    resumed into its own directory from a checkpoint of epoch ``last_epoch``.

    Lightning's CSV writer deletes an existing ``metrics.csv`` when it starts; this reads the
    file first, lets the writer start, writes the kept rows back and tells the writer their
    header, so the resumed run appends after them. Dropped: the rows of epochs the checkpoint
    does not hold (an interrupted epoch, which the resumed run logs again) and the test rows
    of an earlier run (it tests again). Call before anything is logged. Returns the number
    of rows kept.
    """
    from lightning.pytorch.loggers import CSVLogger

    if not isinstance(logger, CSVLogger):
        return 0
    path = Path(logger.log_dir) / "metrics.csv"
    if not path.is_file():
        return 0
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        header = list(reader.fieldnames or [])
        rows = list(reader)
    tests = [k for k in header if k.startswith("test/")]
    kept = [r for r in rows if (e := _epoch(r)) is not None and e <= last_epoch and not any(r.get(k) for k in tests)]
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*Experiment logs directory .* exists and is not empty")
        writer = logger.experiment  # starts the writer, which removes the old file
    with path.open("w", newline="") as f:
        out = csv.DictWriter(f, fieldnames=header)
        out.writeheader()
        out.writerows(kept)
    writer.metrics_keys = header  # later saves append under this header (rewritten if new keys appear)
    return len(kept)
