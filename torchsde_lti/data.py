"""Track data: exact simulation from an LTI SDE, padding, and a LightningDataModule.

Time convention (the Kalman filter's): the prior ``x_{-1} ~ N(m0, P0)`` sits at t0;
step k advances over ``dt[..., k]`` and then observes,

    x_k = A(dt_k) x_{k-1} + G(dt_k) u_k + q_k,   q_k ~ N(0, Qd(dt_k))
    y_k = H x_k + v_k,                           v_k ~ N(0, R)

with the exact discretisation ``sde(dt) -> tl.Discrete(A, Q, G)`` (zero-order hold on u).

Batch format (what :class:`~torchsde_lti.lightning_module.KalmanFilterModule` consumes,
and what any other LightningDataModule must yield to plug into ``conf/data``): a dict

    y    (B, T, m)  observations; NaN = missing (a whole row, or single coordinates)
    dt   (B, T)     step lengths; dt[:, 0] is the time from t0 to the first observation
    mask (B, T)     bool, True on real steps, False on padding
    u    (B, T, p)  optional control inputs, held over the step that ends at t_k
    x    (B, T, n)  optional true states (simulated data only)

Padding: a padded step has ``dt = 0`` (so A = I, Qd = 0, G = 0: the state does not move),
``y = NaN`` (no update, no log-likelihood term) and ``u = 0``. A Kalman filter therefore
carries its last filtered state through the padding unchanged and the padding contributes
exactly nothing to the likelihood, whether or not ``mask`` is passed on.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, NamedTuple

import torch
from lightning.pytorch import LightningDataModule
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, Sampler

from torchsde_lti.core.validation import check_symmetric_psd

__all__ = [
    "BurstDt",
    "EpochShuffleSampler",
    "ExponentialDt",
    "RegularDt",
    "SimulatedTracks",
    "TrackDataset",
    "Tracks",
    "collate_tracks",
    "isotropic_covariance",
    "pad_tracks",
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
    """``std**2 * I_dim`` in float64: a noise covariance from a standard deviation."""
    if not std >= 0:
        raise ValueError(f"std must be non-negative, got {std}")
    if int(dim) < 1:
        raise ValueError(f"dim must be >= 1, got {dim}")
    return float(std) ** 2 * torch.eye(int(dim), dtype=torch.float64)


def selection_matrix(indices: Sequence[int], n: int) -> Tensor:
    """Observation matrix H (len(indices), n) picking state coordinates ``indices`` (float64)."""
    idx = [int(i) for i in indices]
    if not idx or any(not 0 <= i < int(n) for i in idx):
        raise ValueError(f"indices must be a non-empty list of state indices in [0, {n}), got {idx}")
    H = torch.zeros(len(idx), int(n), dtype=torch.float64)
    H[torch.arange(len(idx)), torch.tensor(idx)] = 1.0
    return H


def _psd_sqrt(S: Tensor) -> Tensor:
    """A square root ``W`` with ``W Wᵀ = S`` for symmetric PSD, possibly singular ``S`` (..., k, k)."""
    w, V = torch.linalg.eigh(0.5 * (S + S.mT))
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


class Tracks(NamedTuple):
    """A padded set of tracks (see the module docstring for the padding convention).

    y (N, T, m) with NaN = missing; dt (N, T); mask (N, T) bool; x (N, T, n);
    u (N, T, p) or None; lengths (N,) int64.
    """

    y: Tensor
    dt: Tensor
    mask: Tensor
    x: Tensor
    u: Tensor | None
    lengths: Tensor

    def as_dict(self) -> dict[str, Tensor]:
        out = {"y": self.y, "dt": self.dt, "mask": self.mask, "x": self.x}
        if self.u is not None:
            out["u"] = self.u
        return out


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
) -> Tracks:
    """Simulate ``num_tracks`` tracks of length ``T_min..T`` (uniform), padded to T.

    ``dt_sampler(shape, generator) -> dt`` draws the step lengths (default
    ``ExponentialDt(0.1)``); each real step loses its whole observation with probability
    ``p_missing``; ``control_std`` draws i.i.d. N(0, control_std²) inputs per step.
    Everything is reproducible from ``seed``. Returned tensors are float64.
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
    return Tracks(y=y, dt=dt, mask=mask, x=x, u=u, lengths=lengths)


# --------------------------------------------------------------------------- padding / batching


def pad_tracks(tracks: Sequence[Mapping[str, Tensor]], length: int | None = None) -> dict[str, Tensor]:
    """Pad variable-length tracks into one batch.

    Each track is a mapping with ``y`` (T_i, m), ``dt`` (T_i,) and optionally ``u``
    (T_i, p), ``x`` (T_i, n). Returns the batch dict of the module docstring, padded to
    ``length`` (default: the longest track) with y = NaN, dt = 0, u = 0, x = last state.
    """
    if len(tracks) == 0:
        raise ValueError("tracks must not be empty")
    T = max(int(t["dt"].shape[0]) for t in tracks) if length is None else int(length)
    out: dict[str, list[Tensor]] = {"y": [], "dt": [], "mask": []}
    keys = [k for k in ("u", "x") if k in tracks[0]]
    for k in keys:
        out[k] = []
    for i, t in enumerate(tracks):
        Ti = int(t["dt"].shape[0])
        if Ti > T or t["y"].shape[0] != Ti:
            raise ValueError(f"track {i}: y {tuple(t['y'].shape)} and dt {tuple(t['dt'].shape)} must share T <= {T}")
        pad = T - Ti
        out["y"].append(torch.cat([t["y"], t["y"].new_full((pad, t["y"].shape[-1]), math.nan)]))
        out["dt"].append(torch.cat([t["dt"], t["dt"].new_zeros(pad)]))
        out["mask"].append(torch.arange(T) < Ti)
        if "u" in keys:
            out["u"].append(torch.cat([t["u"], t["u"].new_zeros(pad, t["u"].shape[-1])]))
        if "x" in keys:
            out["x"].append(torch.cat([t["x"], t["x"][-1:].expand(pad, -1)]))
    return {k: torch.stack(v) for k, v in out.items()}


def collate_tracks(items: Sequence[Mapping[str, Tensor]]) -> dict[str, Tensor]:
    """Collate equal-length padded tracks (a list of dicts) and trim trailing all-padding steps."""
    batch = {k: torch.stack([it[k] for it in items]) for k in items[0]}
    T = int(batch["mask"].any(0).nonzero().max()) + 1 if bool(batch["mask"].any()) else 1
    T = max(T, 1)
    return {k: (v[:, :T] if v.dim() >= 2 else v) for k, v in batch.items()}


class TrackDataset(Dataset):
    """Tracks stored as padded tensors with a leading track dimension; item i is a dict."""

    def __init__(self, tensors: Mapping[str, Tensor]) -> None:
        sizes = {k: v.shape[0] for k, v in tensors.items()}
        if len(set(sizes.values())) != 1:
            raise ValueError(f"all tensors need the same number of tracks, got {sizes}")
        self.tensors = dict(tensors)
        self._len = next(iter(sizes.values()))

    def __len__(self) -> int:
        return self._len

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        return {k: v[i] for k, v in self.tensors.items()}


class EpochShuffleSampler(Sampler[int]):
    """Random permutation that depends only on (seed, epoch), so a resumed run sees the
    same batches as an uninterrupted one (Lightning calls ``set_epoch`` every epoch)."""

    def __init__(self, n: int, seed: int = 0) -> None:
        self.n, self.seed, self.epoch = int(n), int(seed), 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __iter__(self) -> Iterator[int]:
        g = torch.Generator().manual_seed(self.seed * 100_003 + self.epoch)
        return iter(torch.randperm(self.n, generator=g).tolist())

    def __len__(self) -> int:
        return self.n


# --------------------------------------------------------------------------- DataModule


class SimulatedTracks(LightningDataModule):
    """Tracks simulated exactly from a known LTISDE, split into train/val/test.

    Args:
        sde: the true LTISDE (simulated in float64; the original is left untouched).
        H: (m, n) observation matrix (e.g. ``tl.models.position_observation(sde)``).
        noise: observation noise standard deviation σ; R = σ² I (must be >= 0).
        num_tracks: {"train": .., "val": .., "test": ..} tracks per split.
        T: steps per track (>= 2); T_min: shortest track (default T: all equal).
        dt: a dt sampler (``RegularDt``, ``ExponentialDt``, ``BurstDt`` or any
            ``f(shape, generator) -> Tensor``).
        p_missing: probability that a step's observation is missing.
        control_std: i.i.d. Gaussian control inputs (needs ``sde.B``); None = no inputs.
        init_std: prior standard deviation of every state coordinate at t0 (m0 = 0).
        batch_size: tracks per batch; seed: simulation and shuffling seed;
        dtype: "float64" or "float32" for the batches.

    Attributes after construction: ``truth`` = {"sde", "R"} (for parameter errors),
    ``m0`` (n,) and ``P0`` (n, n), the prior shared with the filter.
    """

    def __init__(
        self,
        sde: torch.nn.Module,
        H: Tensor,
        noise: float = 0.5,
        num_tracks: Mapping[str, int] | None = None,
        T: int = 100,
        T_min: int | None = None,
        dt: Any = None,
        p_missing: float = 0.0,
        control_std: float | None = None,
        init_std: float = 1.0,
        batch_size: int = 64,
        seed: int = 0,
        dtype: str = "float64",
    ) -> None:
        super().__init__()
        if not (isinstance(noise, (int, float)) and noise >= 0 and math.isfinite(noise)):
            raise ValueError(f"data.noise (observation noise std) must be a finite number >= 0, got {noise!r}")
        if int(T) < 2:
            raise ValueError(f"data.T (steps per track) must be >= 2, got {T}")
        if T_min is not None and not 2 <= int(T_min) <= int(T):
            raise ValueError(f"data.T_min must satisfy 2 <= T_min <= T = {T}, got {T_min}")
        if not 0 <= p_missing < 1:
            raise ValueError(f"data.p_missing must be in [0, 1), got {p_missing}")
        if not init_std > 0:
            raise ValueError(f"data.init_std must be positive, got {init_std}")
        if int(batch_size) < 1:
            raise ValueError(f"data.batch_size must be >= 1, got {batch_size}")
        if dtype not in ("float32", "float64"):
            raise ValueError(f"data.dtype must be 'float32' or 'float64', got {dtype!r}")
        splits = {"train": 200, "val": 50, "test": 50} if num_tracks is None else dict(num_tracks)
        for k in ("train", "val", "test"):
            if int(splits.get(k, 0)) < 1:
                raise ValueError(f"data.num_tracks.{k} must be >= 1, got {splits.get(k)}")
        self.sde = sde
        self.H = torch.as_tensor(H, dtype=torch.float64).detach()
        m, n = self.H.shape
        self.noise, self.T, self.T_min = float(noise), int(T), T_min
        self.num_tracks = {k: int(splits[k]) for k in ("train", "val", "test")}
        self.dt_sampler = ExponentialDt(0.1) if dt is None else dt
        self.p_missing, self.control_std = float(p_missing), control_std
        self.batch_size, self.seed, self.dtype = int(batch_size), int(seed), getattr(torch, dtype)
        self.R = isotropic_covariance(self.noise, m)
        self.m0 = torch.zeros(n, dtype=torch.float64)
        self.P0 = float(init_std) ** 2 * torch.eye(n, dtype=torch.float64)
        self.truth = {"sde": sde, "R": self.R}
        self.tracks: dict[str, Tracks] = {}

    def _simulate(self, split: str) -> Tracks:
        offset = {"train": 0, "val": 1, "test": 2}[split]
        return simulate_tracks(
            self.sde, self.H, self.R, self.num_tracks[split], self.T,
            dt_sampler=self.dt_sampler, T_min=self.T_min, p_missing=self.p_missing,
            control_std=self.control_std, m0=self.m0, P0=self.P0,
            seed=self.seed * 1_000_003 + offset,
        )  # fmt: skip

    def setup(self, stage: str | None = None) -> None:
        """Simulate all three splits once (deterministic, so every DDP rank agrees)."""
        for split in ("train", "val", "test"):
            if split not in self.tracks:
                self.tracks[split] = self._simulate(split)

    def dataset(self, split: str) -> TrackDataset:
        if split not in self.tracks:
            self.setup()
        d = self.tracks[split].as_dict()
        return TrackDataset({k: (v.to(self.dtype) if v.is_floating_point() else v) for k, v in d.items()})

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        ds = self.dataset(split)
        sampler = EpochShuffleSampler(len(ds), self.seed) if shuffle else None
        return DataLoader(ds, batch_size=self.batch_size, sampler=sampler, collate_fn=collate_tracks)

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False)
