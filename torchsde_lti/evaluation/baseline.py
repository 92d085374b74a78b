"""The constant-velocity baseline: a fixed CV filter, and its noise tuned on a grid (the CV oracle).

    kf = cv_filter(q, r_std)                    # constant velocity in 2-D, R = r_std² I, nothing learned
    q, r_std, table = tune_cv(tracks)           # (q, r) of the lowest mean one-step NLL on ``tracks``

:func:`tune_cv` scores each grid point by the mean one-step NLL of whole tracks, batched as
:func:`~torchsde_lti.evaluation.evaluate_filter` batches them. Tuned on the very
tracks it is then scored on (``cv_oracle`` of ``experiments/ais_study.py``), it is an
in-sample oracle for the constant-velocity model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from torchsde_lti.data.loaded_tracks import Tracks
from torchsde_lti.evaluation.predictive import _batches
from torchsde_lti.nn.kalman import KalmanFilter

__all__ = ["cv_filter", "tune_cv"]


def cv_filter(q: float, r_std: float, diffuse_variance: float = 100.0) -> KalmanFilter:
    """Constant velocity in 2-D (state [x, vx, y, vy]), isotropic R = r_std² I, float64, nothing learned."""
    from torchsde_lti.models import constant_velocity, position_observation

    sde = constant_velocity(dim=2, q=torch.tensor(float(q), dtype=torch.float64))
    return KalmanFilter(
        sde,
        position_observation(sde),
        float(r_std) ** 2 * torch.eye(2, dtype=torch.float64),
        learn=(),
        diffuse_variance=diffuse_variance,
        unique_dt=True,
    )


def tune_cv(
    tracks: Tracks,
    q_grid: Sequence[float] = tuple(10.0 ** np.arange(-4.0, 0.1, 1.0)),
    r_grid: Sequence[float] = (3.0, 10.0, 30.0, 100.0),
    diffuse_variance: float = 100.0,
    max_steps: int = 100_000,
    refine: int = 2,
    log: Callable[[str], None] | None = None,
) -> tuple[float, float, dict[tuple[float, float], float]]:
    """Constant velocity with (q, R = r² I) minimising the mean one-step NLL on ``tracks``.

    A log-spaced grid over q and r, extended by a factor of the grid step beyond any edge
    where the optimum lies until the optimum is inside, then refined ``refine`` times
    (halving the log step around the optimum). Returns (q, r_std, {(q, r): mean NLL}).
    ValueError when no track has a second report (nothing to score).
    """
    batches, _ = _batches(tracks, max_steps)
    if not any(bool(b.mask[:, 1:].any()) for b in batches):
        raise ValueError("tune_cv needs tracks with at least two reports: the first report of a track is not scored")
    table: dict[tuple[float, float], float] = {}

    def score(q: float, r: float) -> float:
        key = (float(q), float(r))
        if key not in table:
            kf = cv_filter(q, r, diffuse_variance)
            tot, cnt = 0.0, 0
            with torch.no_grad():
                for batch in batches:
                    m = batch.mask.clone()
                    m[:, 0] = False
                    ll = kf(batch.y, batch.dt, mask=batch.mask).step_log_likelihood
                    tot += float(-(ll * m).sum())
                    cnt += int(m.sum())
            table[key] = tot / max(cnt, 1)
        return table[key]

    qs, rs = np.log10(np.asarray(q_grid, float)), np.log10(np.asarray(r_grid, float))
    dq = float(np.diff(qs).min()) if len(qs) > 1 else 1.0
    dr = float(np.diff(rs).min()) if len(rs) > 1 else 0.5
    for _ in range(20):  # extend until the optimum is inside
        vals = np.array([[score(10**a, 10**c) for c in rs] for a in qs])
        i, j = np.unravel_index(np.argmin(vals), vals.shape)
        grow = False
        if i == 0:
            qs, grow = np.concatenate([[qs[0] - dq], qs]), True
        elif i == len(qs) - 1:
            qs, grow = np.concatenate([qs, [qs[-1] + dq]]), True
        if j == 0:
            rs, grow = np.concatenate([[rs[0] - dr], rs]), True
        elif j == len(rs) - 1:
            rs, grow = np.concatenate([rs, [rs[-1] + dr]]), True
        if not grow:
            break
    bq, br = qs[i], rs[j]
    for _ in range(refine):
        dq, dr = dq / 2, dr / 2
        cand = [(bq + a * dq, br + c * dr) for a in (-1, 0, 1) for c in (-1, 0, 1)]
        bq, br = min(cand, key=lambda p: score(10 ** p[0], 10 ** p[1]))
    if log is not None:
        log(f"cv oracle: q={10**bq:.4g}, r={10**br:.4g} m ({len(table)} grid points)")
    return float(10**bq), float(10**br), table
