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
    max_rounds: int = 200,
    log: Callable[[str], None] | None = None,
) -> tuple[float, float, dict[tuple[float, float], float]]:
    """Constant velocity with (q, R = r² I) minimising the mean one-step NLL on ``tracks``.

    Refine first, then walk, in (log q, log r):

    1. the coarse grid ``q_grid`` × ``r_grid`` (log steps Δq, Δr: their smallest spacings);
    2. ``refine`` times: halve the steps and score the 5 × 5 box of ±2 steps (±1 coarser step,
       beyond the grid's edge too) around the best point so far;
    3. at the final steps (Δq, Δr) / 2^refine: score the 3 × 3 neighbours of the best point
       so far, move to the best, until the best point is lower than all 8 of its neighbours,
       i.e. an interior optimum at the final resolution.

    Refining before walking matters: at a coarse q off the valley floor the NLL can keep
    falling as r → 0 (a harbour day of the NY week: at q = 0.1 m²/s³ the optimum r is 0, at
    q = 0.056 it is 15 m), and extending a coarse grid there walks into the R → 0 basin.
    Each point is one batched filter run; points are cached.

    Args:
        tracks: the tracks (whole), scored from their second report.
        q_grid, r_grid: the coarse grid (m²/s³, m), at least one value each, positive.
        diffuse_variance: the CV filter's prior variance at a track's first report.
        max_steps: B x T of a padded batch; refine: halvings of the coarse steps (>= 0).
        max_rounds: the most walking rounds at the final steps.
        log: called with one line describing the result.

    Returns:
        (q, r_std, {(q, r): mean NLL per scored report} of every point scored).

    Raises:
        ValueError: when no track has a second report (nothing to score), for an empty or
            non-positive grid, or when the walk has not stopped at an interior optimum after
            ``max_rounds`` rounds (the table so far is in the message's count).
    """
    if len(q_grid) == 0 or len(r_grid) == 0 or min(q_grid) <= 0 or min(r_grid) <= 0:
        raise ValueError(f"q_grid and r_grid must hold positive values, got {list(q_grid)} and {list(r_grid)}")
    if refine < 0:
        raise ValueError(f"refine must be >= 0, got {refine}")
    batches, _ = _batches(tracks, max_steps)
    if not any(bool(b.mask[:, 1:].any()) for b in batches):
        raise ValueError("tune_cv needs tracks with at least two reports: the first report of a track is not scored")
    table: dict[tuple[float, float], float] = {}
    by_log: dict[tuple[float, float], float] = {}

    def point(lq: float, lr: float) -> tuple[float, float]:
        return round(float(lq), 9), round(float(lr), 9)  # one key per point, whatever steps reached it

    def score(lq: float, lr: float) -> float:
        key = point(lq, lr)
        if key not in by_log:
            q, r = float(10 ** key[0]), float(10 ** key[1])
            kf = cv_filter(q, r, diffuse_variance)
            tot, cnt = 0.0, 0
            with torch.no_grad():
                for batch in batches:
                    m = batch.mask.clone()
                    m[:, 0] = False
                    ll = kf(batch.y, batch.dt, mask=batch.mask).step_log_likelihood
                    tot += float(-(ll * m).sum())
                    cnt += int(m.sum())
            by_log[key] = table[(q, r)] = tot / max(cnt, 1)
        return by_log[key]

    def best_of(points: list[tuple[float, float]]) -> tuple[float, float]:
        return min(points, key=lambda p: score(*p))

    qs, rs = np.log10(np.asarray(q_grid, float)), np.log10(np.asarray(r_grid, float))
    dq = float(np.diff(np.unique(qs)).min()) if len(np.unique(qs)) > 1 else 1.0
    dr = float(np.diff(np.unique(rs)).min()) if len(np.unique(rs)) > 1 else 0.5
    best = best_of([point(a, c) for a in qs for c in rs])
    for _ in range(refine):  # refine first: halve the steps, score the box of +-2 steps around the best
        dq, dr = dq / 2, dr / 2
        box = [point(best[0] + i * dq, best[1] + j * dr) for i in range(-2, 3) for j in range(-2, 3)]
        best = best_of([best, *box])
    for _ in range(max_rounds):  # then walk at the final steps until the best is interior
        around = [point(best[0] + i * dq, best[1] + j * dr) for i in (-1, 0, 1) for j in (-1, 0, 1)]
        moved = best_of(around)
        if moved == best or score(*moved) >= score(*best):
            break
        best = moved
    else:
        raise ValueError(
            f"tune_cv: no interior optimum after {max_rounds} rounds at steps of {dq:.3g} / {dr:.3g} decades "
            f"({len(table)} points scored, last q={10 ** best[0]:.4g}, r={10 ** best[1]:.4g}); widen the grid"
        )
    q, r = float(10 ** best[0]), float(10 ** best[1])  # the table's key of the best point
    if log is not None:
        log(f"cv oracle: q={q:.4g}, r={r:.4g} m ({len(table)} grid points, interior at the final steps)")
    return q, r, table
