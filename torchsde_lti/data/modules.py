"""Lightning DataModules: simulated tracks from a known LTISDE, and the AIS ship tracks.

The only place in :mod:`torchsde_lti.data` that imports Lightning; both yield
:class:`~torchsde_lti.data.tracks.TrackBatch` batches through the one
:func:`~torchsde_lti.data.tracks.collate_tracks`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from lightning.pytorch import LightningDataModule
from torch import Tensor
from torch.utils.data import DataLoader

from torchsde_lti.data.ais import REFERENCE_LATLON, AISData, AISTrack, load_ais, split_vessels, to_track
from torchsde_lti.data.simulate import ExponentialDt, isotropic_covariance, simulate_tracks
from torchsde_lti.data.tracks import EpochShuffleSampler, TrackBatch, TrackDataset, collate_tracks, unpad_tracks

__all__ = ["AISDataModule", "SimulatedTracks"]


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
        self.tracks: dict[str, TrackBatch] = {}

    def _simulate(self, split: str) -> TrackBatch:
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
        batch = self.tracks[split]
        cast = {k: v.to(self.dtype) for k, v in batch._asdict().items() if isinstance(v, Tensor) and v.is_floating_point()}
        return TrackDataset(unpad_tracks(batch._replace(**cast)))

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


class AISDataModule(LightningDataModule):
    """Train / val / test vessels of the NY Harbor AIS hour as padded, masked batches.

    Each batch is a :class:`~torchsde_lti.data.tracks.TrackBatch` (y (B, T, 2) metres, dt (B, T) seconds, mask
    (B, T)). ``batch_size=None`` puts a whole split in one batch (the default: the train
    split is ~170 vessels x <= 54 reports). Shuffling of training batches uses ``seed``.
    """

    def __init__(
        self,
        path: str | None = None,
        min_reports: int = 5,
        fractions: Sequence[float] = (0.6, 0.2, 0.2),
        seed: int = 0,
        batch_size: int | None = None,
        center: bool = True,
        dtype: str = "float32",
        reference: Sequence[float] = REFERENCE_LATLON,
    ) -> None:
        super().__init__()
        # plain Python values only (no OmegaConf ListConfig), so checkpoints load with
        # torch.load(weights_only=True), as the training entry point's resume does
        self.save_hyperparameters({
            "path": None if path is None else str(path), "min_reports": int(min_reports),
            "fractions": [float(f) for f in fractions], "seed": int(seed),
            "batch_size": None if batch_size is None else int(batch_size), "center": bool(center),
            "dtype": str(dtype), "reference": [float(r) for r in reference],
        })
        self.path = path
        self.min_reports = min_reports
        self.fractions = tuple(fractions)
        self.seed = seed
        self.batch_size = batch_size
        self.center = center
        self.dtype = getattr(torch, dtype) if isinstance(dtype, str) else dtype
        self.reference = (float(reference[0]), float(reference[1]))
        self.data: AISData | None = None
        self.train_tracks: list[AISTrack] = []
        self.val_tracks: list[AISTrack] = []
        self.test_tracks: list[AISTrack] = []

    def setup(self, stage: str | None = None) -> None:
        if self.data is not None:
            return
        self.data = load_ais(self.path, self.min_reports, self.reference)
        tr, va, te = split_vessels(len(self.data.tracks), self.fractions, self.seed)
        self.train_tracks = [self.data.tracks[i] for i in tr]
        self.val_tracks = [self.data.tracks[i] for i in va]
        self.test_tracks = [self.data.tracks[i] for i in te]

    def _loader(self, tracks: list[AISTrack], shuffle: bool) -> DataLoader:
        bs = len(tracks) if self.batch_size is None else self.batch_size
        # the order depends only on (seed, epoch), so a resumed run sees the same batches
        sampler = EpochShuffleSampler(len(tracks), self.seed) if shuffle else None
        return DataLoader(
            TrackDataset([to_track(tr, self.center, self.dtype) for tr in tracks]),
            batch_size=max(bs, 1),
            sampler=sampler,
            collate_fn=collate_tracks,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_tracks, shuffle=self.batch_size is not None)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_tracks, shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.test_tracks, shuffle=False)
