"""Training checkpoints read with errors that say what is wrong with the file.

A run writes ``<run>/checkpoints/last.ckpt`` (the end of the last completed epoch: the weights
the run reports and the point a resumed run continues from) and ``best.ckpt`` (the lowest
``val/nll``): plain containers and tensors, loaded with ``torch.load(weights_only=True)``.
torch reports a damaged file as ``EOFError``, ``OSError``, miniz's ``RuntimeError`` or an
``UnpicklingError`` that advises turning ``weights_only`` off; :func:`read_checkpoint` names the
file and the damage instead (:class:`CheckpointError`), and a checkpoint of another model fails
with torch's own list of missing, unexpected and mis-shaped entries.
"""

from __future__ import annotations

import pickle
import warnings
import zipfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

__all__ = ["RESUME_KEYS", "CheckpointError", "load_filter_weights", "load_weights", "read_checkpoint"]

#: What Lightning writes into every training checkpoint that :meth:`Trainer.fit` resumes from.
RESUME_KEYS = ("state_dict", "epoch", "global_step", "loops", "optimizer_states")


class CheckpointError(ValueError):
    """A checkpoint file that cannot be used: unreadable, damaged, or not what was asked for."""


def _damage(path: Path, err: Exception) -> str:
    """Why ``torch.load`` could not read ``path``, from the file's bytes."""
    size = path.stat().st_size
    if size == 0:
        return "empty file (0 bytes)"
    with path.open("rb") as f:
        head = f.read(4)
    if head != b"PK\x03\x04":
        return f"not a checkpoint (not a torch.save archive: {size} bytes that do not start like one)"
    if not zipfile.is_zipfile(path):
        return f"truncated ({size} bytes: the archive ends before its index)"
    if isinstance(err, pickle.UnpicklingError) and "global" in str(err).lower():
        return "it holds Python objects other than tensors and plain containers, which training checkpoints never do"
    return f"corrupted ({size} bytes: an archive whose records do not read back)"


def read_checkpoint(
    path: str | Path, *, require: Iterable[str] = ("state_dict",), name: str = "ckpt_path"
) -> dict[str, Any]:
    """Load a checkpoint with ``torch.load(weights_only=True)`` on the CPU and check its keys.

    Args:
        path: the file.
        require: top-level keys the checkpoint must hold (:data:`RESUME_KEYS` to resume training).
        name: the argument or config key the path came from, named in the errors.

    Returns:
        The checkpoint dict.

    Raises:
        TypeError: ``path`` is not a path.
        FileNotFoundError: no such file (or a directory).
        CheckpointError: "cannot read checkpoint <path>: empty file / truncated / not a checkpoint /
            it holds Python objects ...", or a dict without the required keys.
    """
    if not isinstance(path, (str, Path)) or not str(path):
        raise TypeError(f"{name} must be a path to a checkpoint file, got {path!r}")
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{name}: no such checkpoint file: {path}")
    if not path.is_file():
        raise FileNotFoundError(f"{name}: {path} is not a file (a checkpoint is a file: <run>/checkpoints/last.ckpt)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # e.g. "Detected pickle protocol 4": the error below says more
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - every way torch.load reports a damaged file
        raise CheckpointError(f"cannot read checkpoint {path}: {_damage(path, err)}") from None
    what = f"it holds a {type(ckpt).__name__}, not the dict Lightning writes"
    if isinstance(ckpt, Mapping):
        missing = [k for k in require if k not in ckpt]
        what = f"missing {', '.join(map(repr, missing))}; it holds {', '.join(map(repr, list(ckpt)[:8])) or 'nothing'}"
        if not missing:
            return dict(ckpt)
        raise CheckpointError(f"cannot read checkpoint {path}: not a training checkpoint ({what})")
    raise CheckpointError(f"cannot read checkpoint {path}: not a checkpoint ({what})")


def load_weights(module: nn.Module, state_dict: Mapping[str, Any], path: str | Path, prefix: str = "") -> None:
    """``module.load_state_dict`` (strict) of the entries of ``state_dict`` under ``prefix``; a
    checkpoint of another model raises :class:`CheckpointError` naming the file, with torch's
    list of the missing, unexpected and mis-shaped entries (the floors of the positive
    parametrisations may be missing: older checkpoints load without them)."""
    own = {k.removeprefix(prefix): v for k, v in state_dict.items() if k.startswith(prefix)}
    try:
        module.load_state_dict(own)
    except RuntimeError as err:
        raise CheckpointError(
            f"checkpoint {path} holds a different model from the one configured: {' '.join(str(err).split())}"
        ) from None


def load_filter_weights(kf: nn.Module, path: str | Path) -> nn.Module:
    """Load the filter weights (the ``kf.`` entries) of a training checkpoint into ``kf``, the
    filter the run trained rebuilt with the same model and shapes; in place, returns it.

    Raises:
        FileNotFoundError, CheckpointError: as :func:`read_checkpoint`, or a checkpoint of
            another model (:func:`load_weights`).
    """
    load_weights(kf, read_checkpoint(path, name="path")["state_dict"], path, prefix="kf.")
    return kf
