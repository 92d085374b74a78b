"""Dividing :class:`~torchsde_lti.data.loaded_tracks.Tracks`: splits for training, validation
and testing, and windows for training.

    train, val, test = split_objects(tracks, (0.6, 0.2, 0.2), seed=0)   # object-disjoint
    parts = split_time(tracks, ["2020-12-06", "2020-12-07"])              # by the time of the first report
    windows = track_windows(train, max_len=128)                          # list of Track, metres and seconds

:func:`split_objects` keeps every track of an object in one split; :func:`split_time` groups
tracks loaded with ``cut_times`` (so that none spans a boundary) by interval;
:func:`track_windows` cuts tracks into :class:`~torchsde_lti.data.tracks.Track` windows of at
most ``max_len`` reports of near-equal length (:func:`window_bounds`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from torchsde_lti.data.loaded_tracks import Tracks
from torchsde_lti.data.rules import _instants, parse_instant
from torchsde_lti.data.tracks import Track

__all__ = ["split_objects", "split_time", "track_windows", "window_bounds"]


def split_objects(
    tracks: Tracks, fractions: Sequence[float] = (0.6, 0.2, 0.2), seed: int = 0
) -> tuple[Tracks, Tracks, Tracks]:
    """Object-disjoint (train, val, test) splits: every track of an object goes where the object goes.

    The sorted distinct object ids (K of them) are permuted with ``seed`` and cut into
    val = round(f_val K), test = round(f_test K) (at most what val leaves), train = the rest.
    A split with a positive share must receive an object: a ValueError says when K is too small
    for the shares (2 objects and (0.34, 0.33, 0.33) leave train empty); a share of 0 gives an
    empty split.

    Args:
        tracks: the tracks to split.
        fractions: (train, val, test) shares of the objects, non-negative, summing to 1.
        seed: the permutation's seed.

    Returns:
        tuple[Tracks, Tracks, Tracks]: train, val and test.

    Raises:
        ValueError: for fractions that are not 3 shares summing to 1, and for a split with a
            positive share that receives no object (naming it, K and the fractions).
    """
    if len(fractions) != 3 or any(f < 0 for f in fractions) or not math.isclose(sum(fractions), 1.0):
        raise ValueError(f"fractions must be 3 non-negative numbers summing to 1, got {list(fractions)}")
    ids, owner = np.unique(tracks.object_id, return_inverse=True)
    k = len(ids)
    perm = np.random.default_rng(seed).permutation(k)
    n_val = min(round(fractions[1] * k), k)
    n_test = min(round(fractions[2] * k), k - n_val)  # (both rounded up: they may exceed K together)
    n_train = k - n_val - n_test
    for name, share, n in zip(("train", "val", "test"), fractions, (n_train, n_val, n_test)):
        if share > 0 and n == 0:
            raise ValueError(
                f"split_objects: {k} objects cannot fill the splits of fractions {list(fractions)}: the {name} split "
                f"(share {share}) would get none (val = round({fractions[1]} x {k}) = {n_val}, test = "
                f"round({fractions[2]} x {k}) = {n_test}, train the rest); load more objects, or give {name} a "
                "share of 0 to leave it empty"
            )
    parts = (perm[:n_train], perm[n_train : n_train + n_val], perm[n_train + n_val :])
    out = []
    for part in parts:
        chosen = np.zeros(k, dtype=bool)
        chosen[part] = True
        out.append(tracks.subset(np.flatnonzero(chosen[owner])))
    return out[0], out[1], out[2]


def split_time(tracks: Tracks, boundaries: Sequence[str | np.datetime64]) -> list[Tracks]:
    """Tracks grouped by the interval of their first report: [-inf, b1), [b1, b2), ..., [bk, inf).

    Args:
        tracks: tracks loaded with ``cut_times=boundaries``, so that none spans a boundary.
        boundaries: increasing instants (ISO 8601 strings or datetime64).

    Returns:
        list[Tracks]: k + 1 groups, in time order.

    Raises:
        TypeError: for a single string or instant in place of a sequence.
        ValueError: for a boundary that is not an instant (naming it), boundaries that do not
            increase, or a track spanning one.
    """
    instants = [parse_instant(b, f"boundaries[{i}]") for i, b in enumerate(_instants("boundaries", boundaries))]
    cuts = np.array([(b - tracks.t0).astype("timedelta64[us]").astype(np.int64) / 1e6 for b in instants])
    if np.any(np.diff(cuts) <= 0):
        raise ValueError(f"boundaries must increase, got {list(map(str, boundaries))}")
    first_t, last_t = tracks.t[tracks.offsets[:-1]], tracks.t[tracks.offsets[1:] - 1]
    bins = np.searchsorted(cuts, first_t, side="right")
    if np.any(bins != np.searchsorted(cuts, last_t, side="right")):
        raise ValueError("some tracks span a split boundary: load them with cut_times=boundaries")
    return [tracks.subset(np.flatnonzero(bins == k)) for k in range(len(cuts) + 1)]


def window_bounds(lengths: np.ndarray, max_len: int | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut tracks of ``lengths`` into ceil(L / max_len) windows of near-equal length (<= max_len).

    Args:
        lengths: (K,) track lengths.
        max_len: the longest window (>= 2); None = one window per track.

    Returns:
        tuple[ndarray, ndarray, ndarray]: (track index, start, stop) per window, start/stop relative
        to the track.
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    if max_len is None:
        n = np.ones_like(lengths)
    else:
        if int(max_len) < 2:
            raise ValueError(f"max_len must be >= 2 or None, got {max_len}")
        n = -(-lengths // int(max_len))
    owner = np.repeat(np.arange(len(lengths)), n)
    j = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    L, k = lengths[owner], n[owner]
    return owner, (j * L) // k, ((j + 1) * L) // k


def track_windows(
    tracks: Tracks, max_len: int | None = None, center: bool = True, dtype: torch.dtype = torch.float32
) -> list[Track]:
    """Training windows as :class:`~torchsde_lti.data.tracks.Track` s (:func:`window_bounds`).

    Args:
        tracks: the tracks to cut.
        max_len: the longest window (reports); None = whole tracks.
        center: subtract each window's first report from its positions (kept in ``origin``).
        dtype: of the returned tensors, a floating-point dtype (TypeError otherwise: an integer
            dtype would truncate positions to whole metres).

    Returns:
        list[Track]: per window y (T, d) positions, dt (T,) seconds from the previous report
        (dt[0] = 0: the prior sits at the first report), t (T,) seconds since ``tracks.t0``,
        vel (T, 2) and sog (T,) where the file has SOG/COG, and track_id, the track's index in
        ``tracks`` (``tracks.object_id[track_id]`` is the object).
    """
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(
            f"track_windows: dtype must be a floating-point torch.dtype (torch.float32, ...), got {dtype!r}"
        )
    owner, a, b = window_bounds(tracks.lengths, max_len)
    a = a + tracks.offsets[owner]
    b = b + tracks.offsets[owner]
    as_t = lambda x: torch.as_tensor(np.ascontiguousarray(x, dtype=np.float64)).to(dtype)  # noqa: E731
    pos64 = np.ascontiguousarray(tracks.pos, dtype=np.float64)  # (centred in float64, then cast)
    t = as_t(tracks.t)
    vel = as_t(tracks.vel) if tracks.vel is not None else None
    sog = as_t(tracks.sog) if tracks.sog is not None else None
    dt_all = np.concatenate([[0.0], np.diff(tracks.t)])
    dt_all[a] = 0.0
    dt = as_t(dt_all)
    out = []
    for k, (i, j) in enumerate(zip(a.tolist(), b.tolist())):
        origin = pos64[i] if center else np.zeros_like(pos64[i])
        out.append(
            Track(
                y=torch.as_tensor(pos64[i:j] - origin).to(dtype),
                dt=dt[i:j],
                t=t[i:j],
                vel=None if vel is None else vel[i:j],
                sog=None if sog is None else sog[i:j],
                origin=torch.tensor(origin, dtype=dtype),
                track_id=torch.tensor(int(owner[k]), dtype=torch.int64),
            )
        )
    return out
