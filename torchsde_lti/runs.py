"""A trained run, rebuilt from its directory (``tl.load_run(run_dir)``), and its filter run over
tracks read from a file (:func:`track_states`: what ``torchsde-lti filter`` / ``smooth`` write).

A run of ``python -m torchsde_lti.train`` (or ``torchsde-lti train``) leaves in its directory

    .hydra/config.yaml          the composed config (Hydra's; a run Hydra did not start has only:)
    config.yaml                 the resolved config (train writes it in every run)
    checkpoints/best.ckpt       the epoch with the lowest val/nll (Lightning)
    checkpoints/last.ckpt       the end of the last completed epoch
    metrics.json                the run's card: status, metrics, learned values (strict JSON)

:func:`load_run` reads those files only: the filter is instantiated from the config's
``filter`` node (the same ``_target_`` the run built), cast to the run's ``dtype`` and given the
checkpoint's ``kf.`` weights (``torch.load(weights_only=True)``, strict keys and shapes); it
needs Hydra's ``instantiate`` and torch, not Lightning.

:func:`track_states` runs the filter (or the smoother) over every track of a
:class:`~torchsde_lti.data.Tracks` (:func:`~torchsde_lti.data.load_tracks`: CSV, Parquet,
``.traj``), batched by length, and returns one row per report: the state's mean and covariance,
the observed position it implies in the track's frame and, from that frame's origin, its
latitude and longitude.
"""

from __future__ import annotations

import dataclasses
import json
import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from torchsde_lti.data import CleaningRules, Tracks, load_tracks, pad_tracks, track_windows
from torchsde_lti.nn import IMMFilter, KalmanFilter

__all__ = ["CHECKPOINTS", "Run", "load_run", "read_tracks", "track_states"]

#: The checkpoints a run writes, by name (``<run>/checkpoints/<name>.ckpt``).
CHECKPOINTS = ("best", "last")


class Run(NamedTuple):
    """A trained run (:func:`load_run`).

    filter: the trained :class:`~torchsde_lti.KalmanFilter` or :class:`~torchsde_lti.IMMFilter`,
        in eval mode and the run's dtype.
    config: the run's resolved config (``.hydra/config.yaml``, ``output_dir`` = the run directory).
    card: ``metrics.json`` (status, metrics, tables, ...) plus ``"checkpoint"`` (the file loaded)
        and ``"learned"`` ({name: value} of that checkpoint's table); ``{}``-based when the run
        wrote no ``metrics.json``.
    run_dir: the run directory.
    checkpoint: the checkpoint file loaded.
    """

    filter: KalmanFilter | IMMFilter
    config: DictConfig
    card: dict[str, Any]
    run_dir: Path
    checkpoint: Path


def _config(run_dir: Path) -> DictConfig:
    path = next((p for p in (run_dir / ".hydra" / "config.yaml", run_dir / "config.yaml") if p.is_file()), None)
    if path is None:
        raise FileNotFoundError(
            f"run_dir: {run_dir} is not a run directory (no .hydra/config.yaml, no config.yaml); give the "
            "directory a training run wrote, e.g. outputs/<date>/<time>"
        )
    cfg = OmegaConf.load(path)
    if not isinstance(cfg, DictConfig) or cfg.get("filter") is None:
        raise ValueError(f"{path}: not a training config (no 'filter' node)")
    cfg.output_dir = str(run_dir)  # ${hydra:runtime.output_dir} resolves only inside Hydra's run
    try:
        OmegaConf.resolve(cfg)
    except Exception as err:  # noqa: BLE001 - an interpolation only the run's Hydra could resolve
        raise ValueError(f"{path}: cannot resolve the run's config: {err}") from None
    return cfg


def _checkpoint_file(run_dir: Path, checkpoint: str | os.PathLike[str]) -> Path:
    if str(checkpoint) in CHECKPOINTS:
        path = run_dir / "checkpoints" / f"{checkpoint}.ckpt"
        if not path.is_file():
            others = sorted(p.stem for p in (run_dir / "checkpoints").glob("*.ckpt"))
            raise FileNotFoundError(f"checkpoint: {path} does not exist (the run wrote {others or 'no checkpoint'})")
        return path
    path = Path(checkpoint)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint: no such file {path} (or give one of {CHECKPOINTS})")
    return path


def _weights(path: Path) -> dict[str, torch.Tensor]:
    """The filter's weights (``kf.`` entries) of a training checkpoint."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - every way torch.load reports a damaged file
        raise ValueError(f"checkpoint {path}: cannot read it ({type(err).__name__}: {err})") from None
    state = ckpt.get("state_dict") if isinstance(ckpt, Mapping) else None
    if not isinstance(state, Mapping):
        raise ValueError(f"checkpoint {path}: not a training checkpoint (no 'state_dict')")
    weights = {k.removeprefix("kf."): v for k, v in state.items() if k.startswith("kf.")}
    if not weights:
        raise ValueError(f"checkpoint {path}: holds no filter weights (no 'kf.' entries in its state_dict)")
    return weights


def _prior(weights: Mapping[str, torch.Tensor], dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """The prior arguments a filter needs to take these weights: a run may build its filter with
    its data's prior (simulated data: ``m0``, ``P0``), which the config's filter node does not
    hold. The values are placeholders of the saved shapes; ``load_state_dict`` sets them."""
    prior = {}
    if "m0" in weights:
        prior["m0"] = torch.zeros(weights["m0"].shape, dtype=dtype)
    P0 = weights.get("P0", weights.get("parametrizations.P0.original"))
    if P0 is not None:
        n = int(P0.shape[-1])
        prior["P0"] = torch.eye(n, dtype=dtype).expand(P0.shape).clone()
    return prior


def _card(run_dir: Path, checkpoint: Path) -> dict[str, Any]:
    path = run_dir / "metrics.json"
    card: dict[str, Any] = {}
    if path.is_file():
        card = json.loads(path.read_text())
    name = checkpoint.resolve()
    best = card.get("best") or {}
    if best.get("checkpoint") and (run_dir / best["checkpoint"]).resolve() == name:
        rows = best.get("table") or []
    elif (card.get("reported") or {}).get("checkpoint") and (
        run_dir / card["reported"]["checkpoint"]
    ).resolve() == name:
        rows = card.get("table") or []
    else:
        rows = []
    learned = {r["name"]: r["learned"] for r in rows if r.get("learned") is not None}
    return {**card, "checkpoint": str(checkpoint), "learned": learned}


def load_run(run_dir: str | os.PathLike[str], checkpoint: str | os.PathLike[str] = "best") -> Run:
    """Rebuild the trained filter of a run directory, with its config and card.

    Args:
        run_dir: the directory a training run wrote (``outputs/<date>/<time>``; a sweep's
            ``multirun/<date>/<time>/<n>``).
        checkpoint: ``"best"`` (lowest val/nll, default), ``"last"`` (the final epoch), or the
            path of a checkpoint file of this run.

    Returns:
        :class:`Run`: ``filter`` (eval mode, the run's dtype), ``config``, ``card``, ``run_dir``,
        ``checkpoint``.

    Raises:
        FileNotFoundError: no ``.hydra/config.yaml`` in ``run_dir``, or no such checkpoint.
        ValueError: an unreadable checkpoint, or one whose weights do not fit the configured
            filter (missing / unexpected keys, other shapes: torch's strict ``load_state_dict``).
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run_dir: no such directory {run_dir}")
    cfg = _config(run_dir)
    path = _checkpoint_file(run_dir, checkpoint)
    card = _card(run_dir, path)
    if card.get("status") not in (None, "completed"):
        warnings.warn(f"run {run_dir} is {card['status']!r} (see its results.md): loading {path}", stacklevel=2)
    from hydra.utils import instantiate

    from torchsde_lti.nn.parametrizations import reset_default_floors

    dtype = getattr(torch, str(cfg.get("dtype", "float64")))
    weights = _weights(path)
    kf = instantiate(cfg.filter, **_prior(weights, dtype))
    if not isinstance(kf, (KalmanFilter, IMMFilter)):
        raise TypeError(
            f"{run_dir}: the config's filter node builds a {type(kf).__name__}, not a KalmanFilter or IMMFilter"
        )
    kf = kf.to(dtype)
    reset_default_floors(kf, dtype)  # the floors the run trained with (a checkpoint's own replace them)
    try:
        kf.load_state_dict(weights)
    except RuntimeError as err:
        raise ValueError(f"checkpoint {path} does not fit the run's configured filter: {err}") from None
    kf.eval()
    return Run(kf, cfg, card, run_dir, path)


def read_tracks(run: Run, source: str | os.PathLike[str], **overrides: Any) -> Tracks:
    """Tracks of ``source`` read and cleaned as the run's data were.

    A run trained on real tracks (``data._target_`` a TrackDataModule) names how its files are
    read and cleaned: ``data.rules`` (None: the module's default, ``min_reports=5``) and the
    :class:`~torchsde_lti.data.CleaningRules` fields beside it (``data.columns``,
    ``course_encoding``, ``max_gap``, ``v_max``, ``min_reports``, ``max_extent``, ...); the same
    rules apply here, except the cut times of a split in time. A run on simulated data names
    none: :func:`~torchsde_lti.data.load_tracks`'s defaults apply. ``overrides``: any
    CleaningRules field, over both.

    Returns:
        :class:`~torchsde_lti.data.Tracks` (with ``.summary`` counting what every rule removed).

    Raises:
        TypeError: an override that is no CleaningRules field.
    """
    accepted = {f.name for f in dataclasses.fields(CleaningRules)} - {"cut_times"}
    unknown = sorted(set(overrides) - accepted)
    if unknown:
        raise TypeError(f"read_tracks: unknown load_tracks arguments {unknown} (accepted: {sorted(accepted)})")
    data = run.config.get("data") or {}
    rules: dict[str, Any] = {}
    if str(data.get("_target_", "")).endswith("TrackDataModule"):
        node = OmegaConf.to_container(data, resolve=True)
        assert isinstance(node, dict)
        base = node.get("rules")
        base = {"min_reports": 5} if base is None else dict(base)  # TrackDataModule's default without rules
        rules = {k: v for k, v in {**base, **node}.items() if k in accepted}
    return load_tracks(source, **{**rules, **overrides})


def _observed_position(kf: KalmanFilter | IMMFilter, result: Any) -> Tensor:
    """(B, T, m) the observation the state implies, H m (an IMM: Σ_j μ_j H_j m_j)."""
    H_all = kf.H
    if isinstance(kf, IMMFilter) and isinstance(H_all, Tensor) and H_all.dim() == 3 and hasattr(result, "mode_mean"):
        per_mode = (H_all @ result.mode_mean.unsqueeze(-1)).squeeze(-1)  # (B, T, M, m)
        return (result.mode_probabilities.unsqueeze(-1) * per_mode).sum(-2)
    H = kf.modes()[0].H
    return result.mean @ H.mT


def _state_rows(kf: KalmanFilter | IMMFilter, chunk: list[Any], smooth: bool, dtype: torch.dtype) -> dict[str, Tensor]:
    """One padded batch of tracks through the filter (or the smoother): per step (B, T, ...)."""
    batch = pad_tracks(chunk)
    with torch.no_grad():
        out = kf(batch.y.to(dtype), batch.dt.to(dtype))
        if smooth:
            smoother = getattr(kf, "smooth", None)
            if smoother is None:
                raise ValueError(
                    f"smooth: the run's {type(kf).__name__.removeprefix('Parametrized')} has no smoother; use filter"
                )
            out = smoother(out)
    rows = {"mean": out.mean, "cov": out.cov, "position": _observed_position(kf, out), "mask": batch.mask}
    if getattr(out, "mode_probabilities", None) is not None:
        rows["mode_probabilities"] = out.mode_probabilities
    return rows


def track_states(run: Run, tracks: Tracks, *, smooth: bool = False, batch_size: int = 256) -> dict[str, np.ndarray]:
    """The run's filtered (or smoothed) state at every report of ``tracks``, as columns.

    Each track is filtered whole from its first report (where the prior sits), positions
    relative to that report (as the run trained: ``data.center``), in the run's dtype; tracks
    are batched by length (``batch_size`` per call, padding as in training).

    Args:
        run: a :class:`Run` (:func:`load_run`).
        tracks: the tracks (:func:`read_tracks` reads them as the run's data were).
        smooth: the RTS smoother's states (a KalmanFilter) instead of the filter's.
        batch_size: tracks per filter call.

    Returns:
        Columns of N rows (one per report, track by track, time-sorted): ``id`` (the object),
        ``track`` (its index in ``tracks``), ``time`` (datetime64[us]), ``t`` (s since the file's
        first report); ``mean_<i>`` (state i, positions relative to the track's first report)
        and ``cov_<i>_<j>`` (i <= j); ``east``, ``north`` (and ``altitude`` in 3-D): the
        position H m in the track's frame (m); ``lat``, ``lon`` of that position (degrees; for
        2-D or 3-D frames, from the frame's origin); an IMM adds ``prob_<mode>`` (its mode
        probabilities).
    """
    if not isinstance(tracks, Tracks):
        raise TypeError(
            f"tracks must be torchsde_lti.data.Tracks (load_tracks / read_tracks), got {type(tracks).__name__}"
        )
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    kf = run.filter
    dtype = getattr(torch, str(run.config.get("dtype", "float64")))
    center = bool((run.config.get("data") or {}).get("center", True))
    windows = track_windows(tracks, None, center, torch.float64)  # whole tracks, in order
    order = np.argsort(tracks.lengths, kind="stable")
    parts: dict[str, list[np.ndarray]] = {}
    for start in range(0, len(order), int(batch_size)):
        idx = order[start : start + int(batch_size)]
        rows = _state_rows(kf, [windows[i] for i in idx], smooth, dtype)
        mask = rows.pop("mask")
        for b, i in enumerate(idx.tolist()):
            L = int(mask[b].sum())
            parts.setdefault("index", []).append(np.full(L, i))
            origin = windows[i].origin.numpy()
            for key, value in rows.items():
                v = value[b, :L].detach().to(torch.float64).numpy()
                parts.setdefault(key, []).append(v + origin if key == "position" else v)
    flat = {k: np.concatenate(v) for k, v in parts.items()}
    report = np.argsort(flat["index"], kind="stable")  # back to the file's track order
    flat = {k: v[report] for k, v in flat.items()}
    return _columns(run, tracks, flat)


def _geodetic(east: np.ndarray, north: np.ndarray, lat0: np.ndarray, lon0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lat, lon) of the point at height 0 whose east/north in the frame at (lat0, lon0) are
    (east, north): the inverse of :func:`~torchsde_lti.data.frames.local_positions` (which
    projects reports to height 0 and keeps east and north). The frame's "up" of that point is
    the curvature drop (about -d²/2R), found by three fixed-point steps from 0 (each shrinks
    the error by ~θ², θ the point's angle from the origin)."""
    import pymap3d

    up = np.zeros_like(east)
    for _ in range(3):
        lat, lon, h = pymap3d.enu2geodetic(east, north, up, lat0, lon0, 0.0)
        up = up - h
    lat, lon, _ = pymap3d.enu2geodetic(east, north, up, lat0, lon0, 0.0)
    return np.asarray(lat), (np.asarray(lon) + 180.0) % 360.0 - 180.0


def _columns(run: Run, tracks: Tracks, flat: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    track = flat["index"]
    columns: dict[str, np.ndarray] = {
        "id": tracks.object_id[track],
        "track": track,
        "time": tracks.t0 + (tracks.t * 1e6).round().astype("timedelta64[us]"),
        "t": tracks.t,
    }
    mean, cov = flat["mean"], flat["cov"]
    n = mean.shape[-1]
    columns.update({f"mean_{i}": mean[:, i] for i in range(n)})
    columns.update({f"cov_{i}_{j}": cov[:, i, j] for i in range(n) for j in range(i, n)})
    position = flat["position"]
    for k, name in enumerate(("east", "north", "altitude")[: position.shape[-1]]):
        columns[name] = position[:, k]
    if position.shape[-1] >= 2 and tracks.dims == position.shape[-1]:
        origin = tracks.origin[track]
        columns["lat"], columns["lon"] = _geodetic(position[:, 0], position[:, 1], origin[:, 0], origin[:, 1])
    if "mode_probabilities" in flat:
        names = getattr(run.filter, "mode_names", None) or [str(j) for j in range(flat["mode_probabilities"].shape[-1])]
        columns.update({f"prob_{name}": flat["mode_probabilities"][:, j] for j, name in enumerate(names)})
    return columns
