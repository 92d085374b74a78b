r"""Shipped trained filters: their cards, loading by name, older cards upgraded, the card's check.

A *card* (``files/<name>.json``) says what a shipped filter is: the filter's configuration (the
Hydra node of ``python -m torchsde_lti.train``, ``_target_`` and arguments), its weights
(``files/<name>.pt``, a ``state_dict`` of that filter), the data it was trained on and how it was
split, the command that trained it, what it learned, its covariance calibration (fitted on the
validation split), and its *validation record*: metrics of the calibrated predictive on a small
fixed slice of the validation split that ships with it (``files/<slice>.npz``), with the
tolerance to which :func:`check` must reproduce them.

Cards carry a ``format`` number; a card of an older format is upgraded when it is read
(:data:`FORMAT` is the current one): format 0 is the study card of
``experiments/ais_study.py`` before cards were shipped (no name, no validation record, model
options the factories no longer take, listed in :data:`REMOVED_OPTIONS`).
"""

from __future__ import annotations

import copy
import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from torchsde_lti.data.loaded_tracks import LoadSummary, Tracks
from torchsde_lti.evaluation import evaluate_filter, summary
from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import KalmanFilter

__all__ = [
    "FILES",
    "FORMAT",
    "REMOVED_OPTIONS",
    "VALIDATION_METRICS",
    "ModelCard",
    "Pretrained",
    "card",
    "check",
    "load",
    "load_card",
    "names",
    "read_card",
    "save_validation_tracks",
    "validation_metrics",
    "validation_tracks",
]

#: The folder of the shipped cards, weights and validation slices (package data).
FILES = Path(__file__).resolve().parent / "files"
#: The card format this version writes; older ones are upgraded when read.
FORMAT = 1
#: Keyword options a model factory once took and no longer does: ``_target_`` -> names, dropped
#: from older cards (``conf/model/cv.yaml`` set an unused ``k`` until constant_velocity refused it).
REMOVED_OPTIONS: dict[str, tuple[str, ...]] = {"torchsde_lti.models.constant_velocity": ("k",)}


@dataclass(frozen=True)
class ModelCard:
    """What a shipped filter is (module docstring).

    name: the name :func:`load` takes; description: one line; format: of the card;
    library_version: ``torchsde_lti.__version__`` that wrote the weights; filter: the filter's
    configuration ({"_target_": ..., ...}); weights: the state-dict file (next to the card);
    data: {"source", "loader" (load_tracks arguments), "split", "trained_on",
    "checkpoint_chosen_on", "held_out", ...}; command: the training command; learned: {name:
    value} of the weights; calibration: {"cov_scale": [c_j], "fitted_on", ...}; training: what
    the run recorded ({"val_nll_per_scalar", "epoch", "wall_time_s"}); validation:
    {"tracks": slice file, "object_ids", "split", "metrics": {metric: value}, "tolerance":
    {metric: (rel, abs)}, "samples", "seed"} (empty for a card without one); folder: where the
    card was read.
    """

    name: str
    description: str
    format: int
    library_version: str
    filter: dict[str, Any]
    weights: str
    data: dict[str, Any]
    command: str
    learned: dict[str, float] = field(default_factory=dict)
    calibration: dict[str, Any] = field(default_factory=dict)
    training: dict[str, Any] = field(default_factory=dict)
    validation: dict[str, Any] = field(default_factory=dict)
    folder: Path | None = None

    @property
    def cov_scale(self) -> list[float]:
        """The calibrated predictive's covariance scale per mode ([1.0] without a calibration)."""
        c = self.calibration.get("cov_scale", [1.0])
        return [float(x) for x in (c if isinstance(c, list) else [c])]

    def as_dict(self) -> dict[str, Any]:
        """The card as JSON-ready values (without ``folder``)."""
        return {k: copy.deepcopy(getattr(self, k)) for k in self.__dataclass_fields__ if k != "folder"}


class Pretrained(NamedTuple):
    """A loaded shipped filter: ``filter`` (float64, eval mode, its weights) and its ``card``."""

    filter: KalmanFilter | IMMFilter
    card: ModelCard


def names() -> list[str]:
    """The names of the shipped filters, sorted (each loads with :func:`load`)."""
    return sorted(p.stem for p in FILES.glob("*.json"))


def _card_path(name: str) -> Path:
    if not isinstance(name, str) or not (FILES / f"{name}.json").is_file():
        raise ValueError(f"no shipped filter named {name!r}: tl.pretrained.names() lists {names()}")
    return FILES / f"{name}.json"


def card(name: str) -> ModelCard:
    """The card of the shipped filter ``name`` (ValueError listing the names for an unknown one)."""
    return read_card(_card_path(name))


def _drop_removed_options(node: Any) -> Any:
    """``node`` with the options of :data:`REMOVED_OPTIONS` taken out of every ``_target_`` node."""
    if isinstance(node, Mapping):
        gone = REMOVED_OPTIONS.get(str(node.get("_target_", "")), ())
        return {k: _drop_removed_options(v) for k, v in node.items() if k not in gone}
    if isinstance(node, list):
        return [_drop_removed_options(v) for v in node]
    return node


def _upgrade(raw: dict[str, Any], path: Path) -> dict[str, Any]:
    """A card of any known format as the current one."""
    fmt = raw.get("format", 0)
    if not isinstance(fmt, int) or fmt < 0 or fmt > FORMAT:
        raise ValueError(f"{path}: card format {fmt!r} is not one this version reads (0 .. {FORMAT})")
    if fmt == 0:  # experiments/ais_study.py's card before cards were shipped
        loader = raw.get("data_config", {})
        data = dict(raw.get("data", {}))
        data["loader"] = {k: loader[k] for k in ("max_gap", "v_max", "min_reports", "max_extent") if k in loader}
        raw = {
            "name": raw.get("model", path.stem),
            "description": f"{raw.get('model', path.stem)} trained on the {raw.get('set', '?')} set (format-0 card)",
            "format": FORMAT,
            "library_version": raw.get("library_version", "0.1.0"),
            "filter": raw["filter"],
            "weights": raw["weights"],
            "data": data,
            "command": raw.get("command", ""),
            "learned": raw.get("learned", {}),
            "calibration": raw.get("calibration", {}),
            "training": {k: raw[k] for k in ("val_nll_per_scalar", "epoch", "wall_time_s") if k in raw},
            "validation": {},
        }
    raw = dict(raw)
    raw["filter"] = _drop_removed_options(raw["filter"])
    return raw


def read_card(path: str | os.PathLike[str]) -> ModelCard:
    """The card in ``path`` (a JSON file of any known format; older ones upgraded).

    Raises:
        ValueError: naming the file, for a card that is not JSON, lacks a field or has an
            unknown format.
    """
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a readable card ({err})") from None
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: a card is a JSON object, got {type(raw).__name__}")
    try:
        up = _upgrade(raw, path)
        required = ("name", "description", "format", "library_version", "filter", "weights", "data", "command")
        fields = {k: up[k] for k in required} | {k: up[k] for k in ModelCard.__dataclass_fields__ if k in up}
        return ModelCard(**fields, folder=path.parent)
    except KeyError as err:
        raise ValueError(f"{path}: the card lacks the field {err.args[0]!r}") from None


def load_card(path: str | os.PathLike[str], dtype: torch.dtype = torch.float64) -> Pretrained:
    """The filter of the card in ``path`` with its weights (next to the card), in eval mode.

    Args:
        path: a card file (any known format: older ones are upgraded).
        dtype: of the filter (float64 as validated; float32 for speed).

    Returns:
        :class:`Pretrained` (filter, card).

    Raises:
        ValueError: for an unreadable card, a filter that is not a KalmanFilter / IMMFilter, or
            weights that do not fit the filter (naming the files).
    """
    from hydra.utils import instantiate  # the training entry point's instantiation (Hydra is a dependency)
    from omegaconf import OmegaConf

    c = read_card(path)
    kf = instantiate(OmegaConf.create(c.filter))
    if not isinstance(kf, (KalmanFilter, IMMFilter)):
        raise ValueError(f"{path}: the card's filter must be a KalmanFilter or IMMFilter, got {type(kf).__name__}")
    kf = kf.to(torch.float64)
    weights = Path(path).parent / c.weights
    try:
        state = torch.load(weights, map_location="cpu", weights_only=True)
        kf.load_state_dict(state)
    except (OSError, RuntimeError, ValueError) as err:
        raise ValueError(f"{weights}: the weights of card {c.name!r} do not load: {err}") from None
    return Pretrained(kf.to(dtype).eval(), c)


def load(name: str, dtype: torch.dtype = torch.float64) -> Pretrained:
    """The shipped filter ``name`` (:func:`names`), ready to run: weights loaded, eval mode.

    Example::

        kf, card = tl.pretrained.load("ais-us-imm")   # kf: IMMFilter (float64), card: ModelCard
        out = kf(y, dt)                               # y (..., T, 2) east/north metres, dt (..., T) s

    The calibrated predictive scales every mode's covariance by ``card.cov_scale`` (as
    :func:`torchsde_lti.evaluation.evaluate_filter` does with ``cov_scale=``).

    Args:
        name: one of :func:`names`.
        dtype: of the filter.

    Returns:
        :class:`Pretrained` (filter, card).

    Raises:
        ValueError: for an unknown name (listing the names).
    """
    return load_card(_card_path(name), dtype)


# ---------------------------------------------------------------------------- validation slices


def save_validation_tracks(tracks: Tracks, path: str | os.PathLike[str]) -> None:
    """Write ``tracks`` (positions, times, ids) as a validation slice (``.npz``) :func:`validation_tracks` reads."""
    np.savez_compressed(
        path,
        object_id=np.asarray(tracks.object_id),
        offsets=tracks.offsets.astype(np.int64),
        t=tracks.t.astype(np.float64),
        pos=tracks.pos.astype(np.float64),
        lat=tracks.lat.astype(np.float64),
        lon=tracks.lon.astype(np.float64),
        origin=tracks.origin.astype(np.float64),
        t0=np.asarray(str(tracks.t0)),
        source=np.asarray(os.path.basename(tracks.summary.source)),
    )


def validation_tracks(c: ModelCard) -> Tracks:
    """The validation slice of card ``c`` (shipped with it) as :class:`~torchsde_lti.data.Tracks`.

    Raises:
        ValueError: for a card without a validation record.
    """
    if not c.validation or c.folder is None:
        raise ValueError(f"card {c.name!r} has no validation record (a format-0 card, or one read without a folder)")
    path = c.folder / c.validation["tracks"]
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    offsets = arrays["offsets"]
    fields: dict[str, Any] = {f: 0 for f in LoadSummary.__dataclass_fields__}
    fields.update(
        source=str(arrays["source"]),
        malformed_examples=(),
        frame="local",
        rules={},
        dims=int(arrays["pos"].shape[-1]),
        objects=len(np.unique(arrays["object_id"])),
        tracks=len(offsets) - 1,
        reports=int(offsets[-1]),
        rows=int(offsets[-1]),
    )
    return Tracks(
        object_id=arrays["object_id"],
        offsets=offsets,
        t=arrays["t"],
        pos=arrays["pos"],
        lat=arrays["lat"],
        lon=arrays["lon"],
        alt=None,
        vel=None,
        sog=None,
        origin=arrays["origin"],
        t0=np.datetime64(str(arrays["t0"]), "us"),
        frame="local",
        summary=LoadSummary(**fields),
    )


#: The metrics of a validation record, and their default tolerance (relative, absolute).
VALIDATION_METRICS: dict[str, tuple[float, float]] = {
    "nll": (1e-6, 1e-9),
    "nll_moving": (1e-6, 1e-9),
    "cover2s": (0.0, 0.01),
    "rmse1": (1e-6, 1e-9),
    "fc_rmse_5": (1e-6, 1e-9),
    "fc_rmse_10": (1e-6, 1e-9),
    "fc_rmse_15": (1e-6, 1e-9),
}


def validation_metrics(model: KalmanFilter | IMMFilter, c: ModelCard, tracks: Tracks) -> dict[str, float]:
    """The validation record's metrics of ``model`` on ``tracks`` (the calibrated predictive)."""
    samples, seed = int(c.validation.get("samples", 500)), int(c.validation.get("seed", 0))
    res = summary(evaluate_filter(model, tracks, cov_scale=c.cov_scale, samples=samples, seed=seed))
    return {k: float(res[k]) for k in VALIDATION_METRICS}


def check(name: str | Pretrained) -> dict[str, dict[str, float | bool]]:
    """Recompute a shipped filter's validation record on its shipped slice.

    Args:
        name: a shipped name, or a :class:`Pretrained` (e.g. from :func:`load_card`).

    Returns:
        {metric: {"card": value, "now": value, "ok": within the card's tolerance}}.

    Raises:
        ValueError: for a card without a validation record.
    """
    pre = load(name) if isinstance(name, str) else name
    c = pre.card
    tracks = validation_tracks(c)
    now = validation_metrics(pre.filter, c, tracks)
    tol = {k: tuple(v) for k, v in c.validation.get("tolerance", VALIDATION_METRICS).items()}
    out: dict[str, dict[str, float | bool]] = {}
    for k, expected in c.validation["metrics"].items():
        rel, abs_ = tol.get(k, VALIDATION_METRICS.get(k, (1e-6, 1e-9)))
        got = now[k]
        both_nan = math.isnan(expected) and math.isnan(got)
        ok = both_nan or abs(got - expected) <= abs_ + rel * abs(expected)
        out[k] = {"card": float(expected), "now": got, "ok": bool(ok)}
    return out
