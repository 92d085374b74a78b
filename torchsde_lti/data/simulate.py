"""Exact simulation of tracks from an LTI SDE (torch only), and dt samplers.

Time convention (the Kalman filter's): the prior ``x_{-1} ~ N(m0, P0)`` sits at t0;
step k advances over ``dt[..., k]`` and then observes,

    x_k = A(dt_k) x_{k-1} + G(dt_k) u_k + q_k,   q_k ~ N(0, Qd(dt_k))
    y_k = H x_k + v_k,                           v_k ~ N(0, R)

with the exact discretisation ``sde(dt) -> tl.Discrete(A, Q, G)`` (zero-order hold on u).

Batches: :class:`~torchsde_lti.data.tracks.TrackBatch`; its padding (dt = 0, y = NaN, u = 0)
contributes exactly nothing to a Kalman filter's likelihood (convention in that module).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from torchsde_lti.core.linalg import sym
from torchsde_lti.core.validation import check_symmetric_psd
from torchsde_lti.data.tracks import TrackBatch

__all__ = [
    "BurstDt",
    "ExponentialDt",
    "RegularDt",
    "diagonal_covariance",
    "isotropic_covariance",
    "selection_matrix",
    "simulate",
    "simulate_tracks",
]

# --------------------------------------------------------------------------- dt samplers


class RegularDt:
    """Regular sampling: every step lasts ``dt``."""

    def __init__(self, dt: float = 0.1) -> None:
        if not dt > 0:
            raise ValueError(f"dt must be positive, got {dt}")
        self.dt = float(dt)

    def __call__(self, shape: Sequence[int], generator: torch.Generator) -> Tensor:
        """Step lengths of shape ``shape`` (float64)."""
        return torch.full(tuple(shape), self.dt, dtype=torch.float64)

    def __repr__(self) -> str:
        return f"RegularDt(dt={self.dt})"


class ExponentialDt:
    """Poisson sampling: gaps ``dt = min_dt + Exp(mean - min_dt)``, so E[dt] = ``mean``."""

    def __init__(self, mean: float = 0.1, min_dt: float = 0.0) -> None:
        if not mean > 0:
            raise ValueError(f"mean must be positive, got {mean}")
        if not 0 <= min_dt < mean:
            raise ValueError(f"min_dt must satisfy 0 <= min_dt < mean, got min_dt={min_dt}, mean={mean}")
        self.mean = float(mean)
        self.min_dt = float(min_dt)

    def __call__(self, shape: Sequence[int], generator: torch.Generator) -> Tensor:
        e = torch.empty(tuple(shape), dtype=torch.float64).exponential_(1.0, generator=generator)
        return self.min_dt + (self.mean - self.min_dt) * e

    def __repr__(self) -> str:
        return f"ExponentialDt(mean={self.mean}, min_dt={self.min_dt})"


class BurstDt:
    """Bursty sampling: short gaps ``Exp(burst_dt)`` inside bursts; with probability
    ``p_gap`` a step is a long gap ``Exp(gap_dt)`` between bursts (mean burst length
    ``1 / p_gap`` observations)."""

    def __init__(self, burst_dt: float = 0.05, gap_dt: float = 2.0, p_gap: float = 0.1) -> None:
        if not (burst_dt > 0 and gap_dt > 0):
            raise ValueError(f"burst_dt and gap_dt must be positive, got {burst_dt}, {gap_dt}")
        if not 0 <= p_gap <= 1:
            raise ValueError(f"p_gap must be in [0, 1], got {p_gap}")
        self.burst_dt, self.gap_dt, self.p_gap = float(burst_dt), float(gap_dt), float(p_gap)

    def __call__(self, shape: Sequence[int], generator: torch.Generator) -> Tensor:
        e = torch.empty(tuple(shape), dtype=torch.float64).exponential_(1.0, generator=generator)
        gap = torch.rand(tuple(shape), dtype=torch.float64, generator=generator) < self.p_gap
        return torch.where(gap, self.gap_dt * e, self.burst_dt * e)

    def __repr__(self) -> str:
        return f"BurstDt(burst_dt={self.burst_dt}, gap_dt={self.gap_dt}, p_gap={self.p_gap})"


# --------------------------------------------------------------------------- simulation


def isotropic_covariance(std: float, dim: int) -> Tensor:
    """``std**2 * I_dim`` in float64: a noise covariance from a standard deviation.

    Args:
        std: standard deviation, non-negative.
        dim: dimension (>= 1).

    Returns:
        Tensor: (dim, dim).
    """
    if not std >= 0:
        raise ValueError(f"std must be non-negative, got {std}")
    if int(dim) < 1:
        raise ValueError(f"dim must be >= 1, got {dim}")
    return float(std) ** 2 * torch.eye(int(dim), dtype=torch.float64)


def diagonal_covariance(std: Sequence[float] | Sequence[Sequence[float]] | Tensor) -> Tensor:
    """``diag(std²)`` in float64: covariances (..., n, n) from standard deviations (..., n).

    A nested list gives a stack, e.g. per-mode covariances of an IMM:
    ``diagonal_covariance([[5, 5], [20, 20]])`` is (2, 2, 2).

    Args:
        std: (..., n) standard deviations, finite and non-negative.

    Returns:
        Tensor: (..., n, n) diagonal covariances.

    Raises:
        ValueError: for a negative, non-finite or 0-dimensional std.
    """
    s = torch.as_tensor(std, dtype=torch.float64)
    if s.dim() < 1 or s.shape[-1] < 1:
        raise ValueError(f"std must have shape (..., n) with n >= 1, got shape {tuple(s.shape)}")
    if not bool(torch.isfinite(s).all()) or bool((s < 0).any()):
        raise ValueError(f"std must be finite and non-negative, got {s.tolist()}")
    return torch.diag_embed(s**2)


def selection_matrix(indices: Sequence[int], n: int) -> Tensor:
    """Observation matrix H (len(indices), n) picking state coordinates ``indices`` (float64).

    Args:
        indices: state coordinates observed, each in [0, n).
        n: state dimension.

    Returns:
        Tensor: H (len(indices), n) of zeros and ones.
    """
    idx = [int(i) for i in indices]
    if not idx or any(not 0 <= i < int(n) for i in idx):
        raise ValueError(f"indices must be a non-empty list of state indices in [0, {n}), got {idx}")
    H = torch.zeros(len(idx), int(n), dtype=torch.float64)
    H[torch.arange(len(idx)), torch.tensor(idx)] = 1.0
    return H


def _psd_sqrt(S: Tensor) -> Tensor:
    """A square root ``W`` with ``W Wᵀ = S`` for symmetric PSD, possibly singular ``S`` (..., k, k)."""
    w, V = torch.linalg.eigh(sym(S))
    return V * w.clamp_min(0.0).sqrt().unsqueeze(-2)


def _randn(shape: Sequence[int], generator: torch.Generator) -> Tensor:
    return torch.randn(tuple(shape), dtype=torch.float64, generator=generator)


def simulate(
    sde: torch.nn.Module,
    H: Tensor,
    R: Tensor,
    dt: Tensor,
    *,
    m0: Tensor,
    P0: Tensor,
    u: Tensor | None = None,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """Sample states and observations exactly (no Euler error), in float64.

    Args:
        sde: an LTISDE; ``sde(dt)`` returns ``tl.Discrete(A, Q, G)`` batched over dt.
        H: (m, n) observation matrix. R: (m, m) observation noise covariance (PSD).
        dt: (N, T) step lengths (>= 0; 0 = padding, the state stays put).
        m0: (n,) and P0: (n, n): the prior of the state at t0.
        u: optional (N, T, p) control inputs, held over each step (needs ``sde.B``).
        generator: torch.Generator for reproducibility.

    Returns:
        x (N, T, n) true states and y (N, T, m) = H x + v (no missing values).
    """
    if generator is None:
        generator = torch.Generator().manual_seed(0)
    dt = torch.as_tensor(dt, dtype=torch.float64)
    if dt.dim() != 2:
        raise ValueError(f"dt must have shape (N, T), got shape {tuple(dt.shape)}")
    if bool((dt < 0).any()) or not bool(torch.isfinite(dt).all()):
        raise ValueError("dt must be finite and non-negative")
    N, T = dt.shape
    H = torch.as_tensor(H, dtype=torch.float64)
    R = torch.as_tensor(R, dtype=torch.float64)
    m0 = torch.as_tensor(m0, dtype=torch.float64)
    P0 = torch.as_tensor(P0, dtype=torch.float64)
    n = m0.shape[-1]
    if H.dim() != 2 or H.shape[-1] != n:
        raise ValueError(f"H must have shape (m, {n}), got shape {tuple(H.shape)}")
    m = H.shape[0]
    if R.shape != (m, m):
        raise ValueError(f"R must have shape ({m}, {m}), got shape {tuple(R.shape)}")
    if P0.shape != (n, n):
        raise ValueError(f"P0 must have shape ({n}, {n}), got shape {tuple(P0.shape)}")
    check_symmetric_psd(R, "R")  # _psd_sqrt would clamp negative eigenvalues away silently
    check_symmetric_psd(P0, "P0")
    n_sde = getattr(sde, "state_dim", n)
    if n_sde != n:
        raise ValueError(f"m0 has shape {tuple(m0.shape)} (H {tuple(H.shape)}) but the sde has state dimension {n_sde}")
    sde64 = copy.deepcopy(sde).to(torch.float64)
    with torch.no_grad():
        d = sde64(dt)  # A (N, T, n, n), Q (N, T, n, n), G (N, T, n, p) or None
        A, Q = d.A.expand(N, T, n, n), d.Q.expand(N, T, n, n)
        drive = torch.zeros(N, T, n, dtype=torch.float64)
        if u is not None:
            if d.G is None:
                raise ValueError("u given but the SDE has no input matrix B")
            u = torch.as_tensor(u, dtype=torch.float64)
            if u.shape[:2] != (N, T) or u.dim() != 3:
                raise ValueError(f"u must have shape ({N}, {T}, p), got shape {tuple(u.shape)}")
            drive = (d.G @ u.unsqueeze(-1)).squeeze(-1)
        noise = (_psd_sqrt(Q) @ _randn((N, T, n, 1), generator)).squeeze(-1) + drive
        x = torch.empty(N, T, n, dtype=torch.float64)
        state = m0 + (_psd_sqrt(P0) @ _randn((N, n, 1), generator)).squeeze(-1)
        for k in range(T):
            state = (A[:, k] @ state.unsqueeze(-1)).squeeze(-1) + noise[:, k]
            x[:, k] = state
        v = (_psd_sqrt(R) @ _randn((N, T, m, 1), generator)).squeeze(-1)
        y = x @ H.mT + v
    return x, y


def simulate_tracks(
    sde: torch.nn.Module,
    H: Tensor,
    R: Tensor,
    num_tracks: int,
    T: int,
    *,
    dt_sampler: Any = None,
    T_min: int | None = None,
    p_missing: float = 0.0,
    control_std: float | None = None,
    m0: Tensor | None = None,
    P0: Tensor | None = None,
    seed: int = 0,
) -> TrackBatch:
    """Simulate ``num_tracks`` tracks of length ``T_min..T`` (uniform), padded to T.

    Everything is reproducible from ``seed``; returned tensors are float64.

    Args:
        sde: an LTISDE (the true model).
        H: (m, n) observation matrix.
        R: (m, m) observation noise covariance.
        num_tracks: number of tracks N (>= 1).
        T: longest track (steps, >= 2).
        dt_sampler: ``dt_sampler(shape, generator) -> dt`` draws the step lengths (default
            ``ExponentialDt(0.1)``).
        T_min: shortest track (default T).
        p_missing: probability that a real step loses its whole observation (NaN), in [0, 1).
        control_std: i.i.d. N(0, control_std²) inputs per step (needs the SDE's B); None = no inputs.
        m0: (n,) prior mean (default 0).
        P0: (n, n) prior covariance.
        seed: the random seed.

    Returns:
        TrackBatch: y (N, T, m) with NaN = missing, dt (N, T), mask, lengths (N,), true states x (N, T, n).
    """
    if int(T) < 2:
        raise ValueError(f"T must be >= 2 (steps per track), got {T}")
    T = int(T)
    T_min = T if T_min is None else int(T_min)
    if not 2 <= T_min <= T:
        raise ValueError(f"T_min must satisfy 2 <= T_min <= T = {T}, got {T_min}")
    if int(num_tracks) < 1:
        raise ValueError(f"num_tracks must be >= 1, got {num_tracks}")
    if not 0 <= p_missing < 1:
        raise ValueError(f"p_missing must be in [0, 1), got {p_missing}")
    if control_std is not None and not control_std >= 0:
        raise ValueError(f"control_std must be non-negative, got {control_std}")
    N = int(num_tracks)
    g = torch.Generator().manual_seed(int(seed))
    dt_sampler = ExponentialDt(0.1) if dt_sampler is None else dt_sampler
    H = torch.as_tensor(H, dtype=torch.float64)
    n = H.shape[-1]
    m0 = torch.zeros(n, dtype=torch.float64) if m0 is None else torch.as_tensor(m0, dtype=torch.float64)
    P0 = torch.eye(n, dtype=torch.float64) if P0 is None else torch.as_tensor(P0, dtype=torch.float64)

    lengths = torch.randint(T_min, T + 1, (N,), generator=g)
    mask = torch.arange(T).unsqueeze(0) < lengths.unsqueeze(1)  # (N, T)
    dt = torch.as_tensor(dt_sampler((N, T), g), dtype=torch.float64)
    if dt.shape != (N, T) or bool((dt < 0).any()) or not bool(torch.isfinite(dt).all()):
        raise ValueError(f"dt_sampler must return finite non-negative (N, T) = ({N}, {T}) step lengths")
    dt = torch.where(mask, dt, torch.zeros_like(dt))
    u = None
    if control_std is not None:
        B = getattr(sde, "B", None)
        if B is None:
            raise ValueError("control_std given but the SDE has no input matrix B")
        u = control_std * _randn((N, T, B.shape[-1]), g) * mask.unsqueeze(-1)
    x, y = simulate(sde, H, R, dt, m0=m0, P0=P0, u=u, generator=g)
    missing = torch.rand(N, T, generator=g) < p_missing
    y = torch.where((missing | ~mask).unsqueeze(-1), torch.full_like(y, math.nan), y)
    return TrackBatch(y=y, dt=dt, mask=mask, lengths=lengths, u=u, x=x)
