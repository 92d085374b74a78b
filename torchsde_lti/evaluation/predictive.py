r"""The predictive distributions every score is computed from, and the batching of whole tracks.

    model = frozen_copy(kf)                        # float64, eval mode: the caller's module unchanged
    pred = one_step_predictive(model, tracks)      # {"y", "w", "mu", "S", "index"}: reports k >= 2
    batch_predictive(kf, out, u)                   # the same mixture from a filter's output on one batch
    mixture_log_prob(y, w, mu, S)                  # log Σ_j w_j N(y; mu_j, S_j)
    masked_gaussian_nll(r, S, observed)            # -log N(r; 0, S) of the observed coordinates
    predictive_dof(model)                          # ν of a Student-t filter (None: Gaussian)

The one-step predictive of a report y_k given y_<k is a Gaussian mixture
``Σ_j w_j N(mu_j, S_j)`` over the M modes of an IMM (M = 1 for a Kalman filter): weights the
predicted mode probabilities, means ``H m_j^-``, covariances the innovation covariances. The
first report of a track holds the prior and is not scored. A filter with
``noise=tl.StudentT(ν)`` has the mixture ``Σ_j w_j St(mu_j, S_j, ν)`` instead (S_j the t's
scale matrices; :mod:`~torchsde_lti.evaluation.student_t`): every function that takes a
predictive takes its ``dof`` (None: Gaussian).

The bottom module of :mod:`torchsde_lti.evaluation`: calibration, scores, the baseline and the
selection all build on it (so none of them imports another in a cycle).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterator
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchsde_lti.core.linalg import sym
from torchsde_lti.data.loaded_tracks import Tracks
from torchsde_lti.data.splits import track_windows
from torchsde_lti.data.tracks import TrackBatch, pad_tracks
from torchsde_lti.evaluation.student_t import mixture_t_log_prob
from torchsde_lti.filters.noise import StudentTNoise
from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import KalmanFilter

__all__ = [
    "Model",
    "PredictiveBatch",
    "batch_predictive",
    "frozen_copy",
    "masked_gaussian_nll",
    "mixture_log_prob",
    "one_step_predictive",
    "predictive_batches",
    "predictive_dof",
]

#: A position-observing filter the evaluation scores.
Model = KalmanFilter | IMMFilter


class PredictiveBatch(NamedTuple):
    """One padded batch of whole tracks with the filter's output and one-step predictive.

    batch: the :class:`~torchsde_lti.data.TrackBatch` (B, T); report_index: (B, T) flat report index
    into the tracks (-1 at padding); out: the filter's output; w: (B, T, M) predictive mode
    weights; mu: (B, T, M, m) predictive means of y; S: (B, T, M, m, m) their covariances;
    scored: (B, T) bool, the reports that are scored (observed, not a track's first).
    """

    batch: TrackBatch
    report_index: np.ndarray
    out: Any
    w: Tensor
    mu: Tensor
    S: Tensor
    scored: Tensor


def predictive_dof(model: Model) -> Tensor | None:
    """ν (float64, no gradient) of a filter with ``noise=tl.StudentT``: 0-dim for one ν, (M,) for
    an IMM with a ν per mode (one per mixture component); None for a Gaussian filter."""
    noise = model.noise.model()
    return noise.dof.detach().to(torch.float64) if isinstance(noise, StudentTNoise) else None


def mixture_log_prob(x: Tensor, w: Tensor, mu: Tensor, S: Tensor, dof: Tensor | float | None = None) -> Tensor:
    """log Σ_j w_j N(x; mu_j, S_j) of points x (N, S, m) or (N, m).

    Args:
        x: (N, m) or (N, S, m) points (S draws per row).
        w: (N, M) weights; mu: (N, M, m) means; S: (N, M, m, m) covariances (SPD).
        dof: None (Gaussian) or ν: the mixture of Student-t's ``Σ_j w_j St(x; mu_j, S_j, ν)``
            (S_j scale matrices, :func:`~torchsde_lti.evaluation.student_t.mixture_t_log_prob`).

    Returns:
        (N,) or (N, S) log densities. Elementwise over the m × m entries of the inverse
        (no batched small solves: those dominate otherwise).
    """
    if dof is not None:
        return mixture_t_log_prob(x, w, mu, S, dof)
    squeeze = x.dim() == 2
    if squeeze:
        x = x.unsqueeze(1)
    m = x.shape[-1]
    L = torch.linalg.cholesky(S)
    Sinv = torch.cholesky_inverse(L).unsqueeze(1)  # (N, 1, M, m, m)
    logdet = 2.0 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1).unsqueeze(1)  # (N, 1, M)
    d = x.unsqueeze(-2) - mu.unsqueeze(1)  # (N, S, M, m)
    quad = sum(d[..., i] * Sinv[..., i, j] * d[..., j] for i in range(m) for j in range(m))
    comp = -0.5 * (quad + logdet + m * math.log(2 * math.pi))
    out = torch.logsumexp(comp + torch.log(w.clamp_min(1e-300)).unsqueeze(1), -1)
    return out.squeeze(1) if squeeze else out


def masked_gaussian_nll(r: Tensor, S: Tensor, observed: Tensor) -> Tensor:
    """Σ over observed coordinates of the Gaussian NLL of residual r under N(0, S).

    Missing coordinates are marginalised out exactly: their rows/columns of S are replaced by
    the identity and their residuals by 0, which leaves logdet and the quadratic form of the
    observed block unchanged.

    Args:
        r: (..., m) residuals (NaN allowed where not observed); S: (..., m, m) covariances;
            observed: (..., m) bool.

    Returns:
        (...) the NLL, zero where nothing is observed.
    """
    obs = observed.to(r.dtype)
    r = torch.where(observed, r, torch.zeros_like(r))
    both = obs.unsqueeze(-1) * obs.unsqueeze(-2)
    eye = torch.eye(r.shape[-1], dtype=r.dtype, device=r.device)
    C = torch.linalg.cholesky(sym(S * both + eye * (1.0 - obs).unsqueeze(-1)))
    z = torch.linalg.solve_triangular(C, r.unsqueeze(-1), upper=False).squeeze(-1)
    logdet = 2.0 * torch.log(torch.diagonal(C, dim1=-2, dim2=-1)).sum(-1)
    return 0.5 * ((z * z).sum(-1) + logdet + obs.sum(-1) * math.log(2.0 * math.pi))


def frozen_copy(model: Model) -> Model:
    """A float64 copy of ``model`` in eval mode, for scoring: the caller's module keeps its
    dtype and training mode."""
    return copy.deepcopy(model).to(torch.float64).eval()


def batch_predictive(kf: KalmanFilter | IMMFilter, out: Any, u: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """The one-step predictive of y from a filter's output, a mixture over modes.

    Args:
        kf: the filter; out: its output on a batch; u: (..., T, p) inputs or None.

    Returns:
        Weights (..., T, M), means (..., T, M, m) (``H_j m⁻_j``, plus the feedthrough D u of a
        KalmanFilter) and covariances (..., T, M, m, m) (``S_j``); M = 1 for a KalmanFilter.
    """
    if isinstance(kf, IMMFilter):
        mu = (kf.H @ out.mode_pred_mean.unsqueeze(-1)).squeeze(-1)  # H shared (m, n) or per mode (M, m, n)
        return out.pred_mode_probabilities, mu, out.mode_innovation_cov
    pred = out.pred_mean @ kf.H.mT
    Du = kf.feedthrough(u)
    pred = pred if Du is None else pred + Du
    return torch.ones_like(pred[..., :1]), pred.unsqueeze(-2), out.innovation_cov.unsqueeze(-3)


def _one_step(model: Model, batch: TrackBatch) -> tuple[Any, Tensor, Tensor, Tensor]:
    """Filter output and the one-step predictive of y (:func:`batch_predictive`)."""
    out = model(batch.y, batch.dt, mask=batch.mask)
    return (out, *batch_predictive(model, out))


def _forecast(model: Model, out: Any, b: Tensor, k: Tensor, lead: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Predictive of y at t_k + lead from the filtered state at (b, k): weights (P, M), means, covs."""
    if isinstance(model, IMMFilter):
        mix = model.forecast(
            (out.mode_probabilities[b, k], out.mode_mean[b, k], out.mode_cov[b, k]), lead.unsqueeze(-1)
        )
        return mix.mode_probabilities[:, 0], mix.mode_obs_mean[:, 0], mix.mode_obs_cov[:, 0]
    fc = model.forecast((out.mean[b, k], out.cov[b, k]), lead.unsqueeze(-1))
    return torch.ones(len(b), 1, dtype=lead.dtype), fc.obs_mean[:, :1], fc.obs_cov[:, :1]


def _batches(tracks: Tracks, max_steps: int) -> tuple[list[TrackBatch], list[np.ndarray]]:
    """Whole tracks (float64, centred) as padded batches of <= max_steps (B x T) each, sorted by
    length, and the flat report indices of each batch (B, T; -1 at padding)."""
    windows = track_windows(tracks, None, center=True, dtype=torch.float64)
    lengths = np.diff(tracks.offsets)
    order = np.argsort(lengths, kind="stable")
    groups: list[list[int]] = []
    cur: list[int] = []
    for i in order:
        if cur and (len(cur) + 1) * lengths[i] > max_steps:
            groups.append(cur)
            cur = []
        cur.append(int(i))
    if cur:
        groups.append(cur)
    batches, index = [], []
    for g in groups:
        batches.append(pad_tracks([windows[i] for i in g]))
        T = int(lengths[g].max())
        idx = np.full((len(g), T), -1, dtype=np.int64)
        for r, i in enumerate(g):
            idx[r, : lengths[i]] = np.arange(tracks.offsets[i], tracks.offsets[i + 1])
        index.append(idx)
    return batches, index


def predictive_batches(model: Model, tracks: Tracks, max_steps: int = 50_000) -> Iterator[PredictiveBatch]:
    """The one-step predictive of whole tracks, batch by batch (call it under ``torch.no_grad()``
    to score without gradients).

    Args:
        model: a frozen position-observing filter (:func:`frozen_copy`).
        tracks: whole tracks (:func:`~torchsde_lti.data.load_tracks`).
        max_steps: B x T of a padded batch.

    Yields:
        :class:`PredictiveBatch`, tracks sorted by length.
    """
    batches, index = _batches(tracks, max_steps)
    for batch, idx in zip(batches, index):
        out, w, mu, S = _one_step(model, batch)
        scored = batch.mask.clone()
        scored[:, 0] = False
        yield PredictiveBatch(batch, idx, out, w, mu, S, scored)


def one_step_predictive(model: Model, tracks: Tracks, max_steps: int = 50_000) -> dict[str, Tensor]:
    """The one-step predictive of every report k >= 2 of every track (float64, no gradients).

    Args:
        model: a position-observing :class:`~torchsde_lti.KalmanFilter` or :class:`~torchsde_lti.IMMFilter`.
        tracks: whole tracks (:func:`~torchsde_lti.data.load_tracks`).
        max_steps: B x T of a padded batch.

    Returns:
        {"y": (N, m), "w": (N, M), "mu": (N, M, m), "S": (N, M, m, m), "index": (N,) flat report
        index into ``tracks``}, in the order of :func:`~torchsde_lti.evaluation.evaluate_filter`.
    """
    parts: dict[str, list[Tensor]] = {k: [] for k in ("y", "w", "mu", "S", "index")}
    with torch.no_grad():
        for p in predictive_batches(frozen_copy(model), tracks, max_steps):
            m = p.scored
            parts["y"].append(p.batch.y[m])
            parts["w"].append(p.w[m])
            parts["mu"].append(p.mu[m])
            parts["S"].append(p.S[m])
            parts["index"].append(torch.as_tensor(p.report_index[m.numpy()]))
    return {k: torch.cat(v) for k, v in parts.items()}
