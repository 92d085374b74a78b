"""What a run writes: strict JSON, files replaced atomically, the CSV log of a resumed run.

Every JSON file of a run goes through :func:`write_json`: non-finite floats become ``null`` (no
bare ``NaN`` / ``Infinity``), tensors, NumPy values, NamedTuples, dataclasses and paths plain
JSON; the file is written next to the target and renamed over it, so a reader never sees half a
file, not even when the run is killed while writing.
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

__all__ = ["continue_csv_log", "data_summary", "to_jsonable", "write_json", "write_text"]


def to_jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON values, NaN and ±inf (floats, tensors, arrays) as None: mappings
    (keys as strings), sequences and sets, NamedTuples, dataclasses, tensors and arrays (nested
    lists), NumPy / torch scalars; anything else by its ``str``."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    if isinstance(obj, torch.Tensor):
        return to_jsonable(obj.detach().cpu().tolist())
    if isinstance(obj, (np.ndarray, np.generic)):
        return to_jsonable(obj.tolist())
    if hasattr(obj, "_asdict"):  # NamedTuple
        obj = obj._asdict()
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        obj = dataclasses.asdict(obj)
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_jsonable(v) for v in obj]
    return str(obj)


def write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (a temporary file in the same directory, renamed)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_json(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as strict JSON (:func:`to_jsonable`), atomically."""
    write_text(path, json.dumps(to_jsonable(obj), indent=2, allow_nan=False) + "\n")


def data_summary(datamodule: Any) -> Any:
    """The datamodule's ``summary`` (an attribute, or a method called without arguments) as JSON
    values, or None when it offers none."""
    summary = getattr(datamodule, "summary", None)
    summary = summary() if callable(summary) else summary
    return None if summary is None else to_jsonable(summary)


def continue_csv_log(logger: Any, last_epoch: int) -> int:
    """Keep the rows of epochs ``<= last_epoch`` in a CSVLogger's ``metrics.csv``, for a run
    resumed into its own directory from a checkpoint of epoch ``last_epoch``; returns how many.

    Lightning's CSV writer (2.x) deletes an existing ``metrics.csv`` when it starts: this reads
    the file first, lets the writer start, writes the kept rows back and gives the writer their
    header, so the resumed run appends after them. Dropped: the rows of an interrupted epoch
    (logged again) and an earlier process's test rows (it tests again). Call before any logging.
    """
    from lightning.pytorch.loggers import CSVLogger

    path = Path(logger.log_dir) / "metrics.csv" if isinstance(logger, CSVLogger) else None
    if path is None or not path.is_file():
        return 0
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        header, rows = list(reader.fieldnames or []), list(reader)
    tests = [k for k in header if k.startswith("test/")]
    kept = [r for r in rows if r.get("epoch") and int(float(r["epoch"])) <= last_epoch and not any(r[k] for k in tests)]
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*Experiment logs directory .* exists and is not empty")
        writer = logger.experiment  # starts the writer, which removes the old file
    with path.open("w", newline="") as f:
        out = csv.DictWriter(f, fieldnames=header)
        out.writeheader()
        out.writerows(kept)
    writer.metrics_keys = header  # later saves append under this header (rewritten if new keys appear)
    return len(kept)
