"""Reading training checkpoints with errors that say what is wrong with the file.

A run writes two Lightning checkpoints (``conf/callbacks/default.yaml``):

* ``<run>/checkpoints/last.ckpt``: the state at the end of the last completed epoch —
  the weights the run reports (``results.md``, ``metrics.json``) and the point a resumed
  run continues from;
* ``<run>/checkpoints/best.ckpt``: the epoch with the lowest ``val/nll``.

Both hold plain containers and tensors only, so they load with
``torch.load(weights_only=True)``. :func:`read_checkpoint` does that and turns every way a
file can be unusable (missing, empty, truncated, random bytes, another kind of file, Python
objects) into a :class:`CheckpointError` naming the file — never a bare ``EOFError`` /
``OSError`` or advice to disable ``weights_only``.
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

from torchsde_lti.nn.parametrizations import floor_state_keys

__all__ = ["CheckpointError", "check_state_dict", "load_filter_weights", "read_checkpoint"]

_ZIP_MAGIC = b"PK\x03\x04"
#: what Lightning writes into every training checkpoint that :meth:`Trainer.fit` resumes from
RESUME_KEYS = ("state_dict", "epoch", "global_step", "loops", "optimizer_states")


class CheckpointError(ValueError):
    """A checkpoint file that cannot be used: unreadable, damaged, or not what was asked for."""


def _damage(path: Path) -> str:
    """Why ``torch.load`` could not read ``path``: a short description from the file's bytes."""
    size = path.stat().st_size
    if size == 0:
        return "empty file (0 bytes)"
    with path.open("rb") as f:
        head = f.read(len(_ZIP_MAGIC))
    if head != _ZIP_MAGIC:
        return f"not a checkpoint (not a torch.save archive: {size} bytes that do not start like one)"
    if not zipfile.is_zipfile(path):
        return f"truncated ({size} bytes: the archive ends before its index)"
    return f"corrupted ({size} bytes: an archive whose records do not read back)"


def read_checkpoint(
    path: str | Path, *, require: Iterable[str] = ("state_dict",), name: str = "ckpt_path"
) -> dict[str, Any]:
    """Load a checkpoint with ``torch.load(weights_only=True)`` on the CPU and check its keys.

    Args:
        path: the file.
        require: top-level keys the checkpoint must hold (``RESUME_KEYS`` to resume training).
        name: the argument or config key the path came from, named in the errors.

    Returns:
        The checkpoint dict.

    Raises:
        FileNotFoundError: no such file (or a directory).
        CheckpointError: "cannot read checkpoint <path>: empty file / truncated / not a
            checkpoint / holds Python objects ...", or a dict without the required keys.
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
    except pickle.UnpicklingError as err:
        if zipfile.is_zipfile(path) and "global" in str(err).lower():
            raise CheckpointError(
                f"cannot read checkpoint {path}: it holds Python objects other than tensors and plain "
                "containers, which training checkpoints never do (not a checkpoint of this package)"
            ) from None
        raise CheckpointError(f"cannot read checkpoint {path}: {_damage(path)}") from None
    except (EOFError, OSError, RuntimeError, KeyError, ValueError, TypeError, AttributeError, IndexError, MemoryError):
        # torch.load reports damage in many ways: EOFError (empty), OSError EINVAL (truncated
        # archive), RuntimeError (miniz), KeyError / ValueError (bytes read as a legacy pickle)
        raise CheckpointError(f"cannot read checkpoint {path}: {_damage(path)}") from None
    if not isinstance(ckpt, Mapping):
        raise CheckpointError(
            f"cannot read checkpoint {path}: not a checkpoint (it holds a {type(ckpt).__name__}, "
            "not the dict Lightning writes)"
        )
    missing = [k for k in require if k not in ckpt]
    if missing:
        raise CheckpointError(
            f"cannot read checkpoint {path}: not a training checkpoint (missing {', '.join(map(repr, missing))}; "
            f"it holds {', '.join(map(repr, list(ckpt)[:8])) or 'nothing'})"
        )
    if "state_dict" in ckpt and not isinstance(ckpt["state_dict"], Mapping):
        raise CheckpointError(
            f"cannot read checkpoint {path}: its 'state_dict' is a {type(ckpt['state_dict']).__name__}, not a dict"
        )
    return dict(ckpt)


def check_state_dict(path: str | Path, saved: Mapping[str, Any], module: nn.Module, *, prefix: str = "") -> None:
    """Raise :class:`CheckpointError` unless ``saved`` has exactly the keys and shapes of
    ``module.state_dict()`` (keys of ``saved`` read without ``prefix``).

    Names the missing, unexpected and mis-shaped entries: a checkpoint of another model
    (``model=cv`` resumed with ``model=singer``) fails here, before any training. The floors of
    the positive parametrisations (:func:`~torchsde_lti.nn.parametrizations.floor_state_keys`)
    may be missing: checkpoints saved before they were saved load without them.
    """
    own = module.state_dict()
    theirs = {k.removeprefix(prefix): v for k, v in saved.items() if k.startswith(prefix)}
    missing = sorted(set(own) - set(theirs) - floor_state_keys(module))
    unexpected = sorted(set(theirs) - set(own))
    shapes = sorted(
        f"{k} {tuple(theirs[k].shape)} vs {tuple(own[k].shape)}"
        for k in set(own) & set(theirs)
        if isinstance(theirs[k], torch.Tensor) and theirs[k].shape != own[k].shape
    )
    if missing or unexpected or shapes:
        parts = [
            f"missing {missing[:5]}" if missing else "",
            f"unexpected {unexpected[:5]}" if unexpected else "",
            f"shapes (checkpoint vs model) {shapes[:5]}" if shapes else "",
        ]
        raise CheckpointError(
            f"checkpoint {path} holds a different model from the one configured: " + "; ".join(p for p in parts if p)
        )


def load_filter_weights(kf: nn.Module, path: str | Path) -> nn.Module:
    """Load the filter weights of a training checkpoint into ``kf`` (in place; returns it).

    ``kf`` is the filter the run trained, rebuilt with the same model and shapes (its
    parameters live under ``kf.`` in the checkpoint's ``state_dict``). Raises
    :class:`CheckpointError` for a damaged file or one that holds another model.
    """
    ckpt = read_checkpoint(path, name="path")
    check_state_dict(path, ckpt["state_dict"], kf, prefix="kf.")
    kf.load_state_dict({k.removeprefix("kf."): v for k, v in ckpt["state_dict"].items() if k.startswith("kf.")})
    return kf
