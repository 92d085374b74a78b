"""Track simulation, dt samplers, padding and the SimulatedTracks DataModule.

Oracles are closed forms written out here (DESIGN.md §2: CV transition and noise, zero-order
hold input gain), not the library's own discretisation.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchsde_lti as tl
from torchsde_lti import models
from torchsde_lti.data import (
    BurstDt,
    EpochShuffleSampler,
    ExponentialDt,
    RegularDt,
    Track,
    collate_tracks,
    isotropic_covariance,
    pad_tracks,
    selection_matrix,
    simulate,
    simulate_tracks,
    unpad_tracks,
)
from torchsde_lti.data.modules import SimulatedTracks


def _cv_closed_form(dt: float, q: float) -> tuple[torch.Tensor, torch.Tensor]:
    A = torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=torch.float64)
    Q = q * torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], dtype=torch.float64)
    return A, Q


def test_simulate_one_step_matches_closed_form_moments() -> None:
    """x_0 = A m0 + q_0 with q_0 ~ N(0, q [[dt³/3, dt²/2], [dt²/2, dt]]) exactly."""
    dt, q, N = 0.7, 2.0, 40_000
    sde = models.constant_velocity(dim=1, q=q)
    H = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    R = torch.tensor([[0.09]], dtype=torch.float64)
    m0 = torch.tensor([1.0, 2.0], dtype=torch.float64)
    x, y = simulate(
        sde, H, R, torch.full((N, 1), dt), m0=m0, P0=torch.zeros(2, 2, dtype=torch.float64),
        generator=torch.Generator().manual_seed(3),
    )  # fmt: skip
    A, Q = _cv_closed_form(dt, q)
    x0 = x[:, 0]
    mean = x0.mean(0)
    cov = torch.cov(x0.T)
    se = (torch.diagonal(Q) / N).sqrt()
    assert torch.all((mean - A @ m0).abs() < 5 * se)
    # sample covariance: relative error ~ sqrt(2/N) ≈ 0.7 %
    assert torch.allclose(cov, Q, rtol=0.04, atol=0.0)
    v = (y - x @ H.mT)[:, 0, 0]
    assert abs(float(v.var()) / 0.09 - 1) < 0.04
    assert x.dtype == torch.float64 and x.shape == (N, 1, 2) and y.shape == (N, 1, 1)


def test_simulate_multi_step_propagates_covariance() -> None:
    """After k regular steps from a fixed start: cov = Σ_j A^j Q A^jᵀ (closed-form A, Q)."""
    dt, q, N, T = 0.3, 1.5, 30_000, 4
    sde = models.constant_velocity(dim=1, q=q)
    H = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    x, _ = simulate(
        sde, H, torch.eye(1, dtype=torch.float64), torch.full((N, T), dt),
        m0=torch.zeros(2, dtype=torch.float64), P0=torch.zeros(2, 2, dtype=torch.float64),
        generator=torch.Generator().manual_seed(11),
    )  # fmt: skip
    A, Q = _cv_closed_form(dt, q)
    P = torch.zeros(2, 2, dtype=torch.float64)
    for _ in range(T):
        P = A @ P @ A.T + Q
    assert torch.allclose(torch.cov(x[:, -1].T), P, rtol=0.05)


def test_simulate_control_input_zero_order_hold() -> None:
    """With (almost) no noise: x_0 = A m0 + G u, G = [dt²/2, dt]ᵀ for acceleration input."""
    dt = 0.4
    F = torch.tensor([[0.0, 1.0], [0.0, 0.0]], dtype=torch.float64)
    L = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    B = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    sde = tl.LTISDE(F, L, torch.tensor([[1e-14]], dtype=torch.float64), B=B, learn=())
    u = torch.tensor([[[2.0]], [[-1.0]]], dtype=torch.float64)  # (N=2, T=1, p=1)
    m0 = torch.tensor([1.0, 0.5], dtype=torch.float64)
    x, _ = simulate(
        sde, torch.tensor([[1.0, 0.0]], dtype=torch.float64), torch.zeros(1, 1, dtype=torch.float64),
        torch.full((2, 1), dt), m0=m0, P0=torch.zeros(2, 2, dtype=torch.float64), u=u,
    )  # fmt: skip
    G = torch.tensor([dt**2 / 2, dt], dtype=torch.float64)
    expected = torch.stack([torch.tensor([1.0 + 0.5 * dt, 0.5]) + G * float(ui) for ui in u[:, 0, 0]])
    assert torch.allclose(x[:, 0], expected.to(torch.float64), atol=1e-6)


def test_simulate_rejects_bad_input() -> None:
    sde = models.constant_velocity(dim=1, q=1.0)
    H = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    kw = {"m0": torch.zeros(2), "P0": torch.eye(2)}
    with pytest.raises(ValueError, match="dt"):
        simulate(sde, H, torch.eye(1), torch.full((3,), 0.1), **kw)
    with pytest.raises(ValueError, match="dt"):
        simulate(sde, H, torch.eye(1), -torch.ones(2, 3), **kw)
    with pytest.raises(ValueError, match="R"):
        simulate(sde, H, torch.eye(2), torch.ones(2, 3), **kw)
    with pytest.raises(ValueError, match="u given"):
        simulate(sde, H, torch.eye(1), torch.ones(2, 3), u=torch.zeros(2, 3, 1), **kw)


def test_simulate_rejects_mismatched_state_dim_and_indefinite_noise() -> None:
    sde = models.constant_velocity(dim=1, q=1.0)  # n = 2
    H3 = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"m0 has shape \(3,\).*state dimension 2"):  # not a RuntimeError from expand
        simulate(sde, H3, torch.eye(1), torch.ones(2, 3), m0=torch.zeros(3), P0=torch.eye(3))
    with pytest.raises(ValueError, match="H"):
        simulate_tracks(sde, H3, torch.eye(1), 2, 3)
    H = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    kw = {"m0": torch.zeros(2), "P0": torch.eye(2)}
    with pytest.raises(ValueError, match="R"):  # would be clamped to zero noise silently
        simulate(sde, H, -torch.eye(1), torch.ones(2, 3), **kw)
    with pytest.raises(ValueError, match="P0"):
        simulate(sde, H, torch.eye(1), torch.ones(2, 3), m0=torch.zeros(2), P0=torch.tensor([[1.0, 2.0], [2.0, 1.0]]))


def test_dt_samplers() -> None:
    g = torch.Generator().manual_seed(0)
    assert torch.equal(RegularDt(0.25)((3, 4), g), torch.full((3, 4), 0.25, dtype=torch.float64))
    e = ExponentialDt(mean=0.5, min_dt=0.1)((200, 500), g)
    assert float(e.min()) >= 0.1
    assert abs(float(e.mean()) - 0.5) < 0.01  # se = 0.4 / sqrt(1e5) ≈ 0.0013
    b = BurstDt(burst_dt=0.1, gap_dt=5.0, p_gap=0.2)((200, 500), g)
    assert abs(float(b.mean()) - (0.8 * 0.1 + 0.2 * 5.0)) < 0.05
    assert abs(float((b > 1.0).double().mean()) - 0.2 * math.exp(-1 / 5.0)) < 0.01
    with pytest.raises(ValueError, match="mean"):
        ExponentialDt(mean=-1.0)
    with pytest.raises(ValueError, match="dt"):
        RegularDt(0.0)
    with pytest.raises(ValueError, match="p_gap"):
        BurstDt(p_gap=1.5)


def test_simulate_tracks_padding_missing_and_seed() -> None:
    sde = models.integrated_ou(k=0.5, q=1.0, dim=2)
    H = models.position_observation(sde)
    R = isotropic_covariance(0.3, 2)
    kw = dict(dt_sampler=ExponentialDt(0.2), T_min=5, p_missing=0.3, seed=7)
    tr = simulate_tracks(sde, H, R, 400, 20, **kw)
    assert tr.y.shape == (400, 20, 2) and tr.dt.shape == (400, 20) and tr.x.shape == (400, 20, 4)
    assert int(tr.lengths.min()) >= 5 and int(tr.lengths.max()) <= 20
    assert torch.equal(tr.mask.sum(1), tr.lengths)
    pad = ~tr.mask
    assert bool(pad.any())
    assert bool((tr.dt[pad] == 0).all()) and bool(torch.isnan(tr.y[pad]).all())
    assert bool((tr.dt[tr.mask] > 0).all())
    # the state does not move over padding (dt = 0: A = I, Q = 0)
    last = tr.x[torch.arange(400), tr.lengths - 1]
    assert torch.allclose(tr.x[:, -1], last)
    frac_missing = float(torch.isnan(tr.y[tr.mask][:, 0]).double().mean())
    assert abs(frac_missing - 0.3) < 0.03
    again = simulate_tracks(sde, H, R, 400, 20, **kw)
    assert torch.equal(tr.x, again.x) and torch.equal(tr.dt, again.dt)
    assert torch.equal(torch.isnan(tr.y), torch.isnan(again.y))
    other = simulate_tracks(sde, H, R, 400, 20, **{**kw, "seed": 8})
    assert not torch.equal(tr.x, other.x)


def test_padding_contributes_nothing_to_likelihood() -> None:
    """Filtering a padded batch gives each track's own log-likelihood, computed unpadded."""
    sde = models.constant_velocity(dim=2, q=0.7).to(torch.float64)
    H = models.position_observation(sde)
    R = isotropic_covariance(0.5, 2)
    tr = simulate_tracks(sde, H, R, 6, 15, T_min=4, p_missing=0.2, seed=1)
    kf = tl.KalmanFilter(sde, H, R, m0=torch.zeros(4, dtype=torch.float64), P0=torch.eye(4, dtype=torch.float64))
    batch = kf(tr.y, tr.dt).log_likelihood
    for i in range(6):
        n = int(tr.lengths[i])
        single = kf(tr.y[i : i + 1, :n], tr.dt[i : i + 1, :n]).log_likelihood
        assert torch.allclose(batch[i], single[0], rtol=1e-10, atol=1e-10)


def test_pad_and_collate() -> None:
    tracks = [
        Track(y=torch.randn(3, 2), dt=torch.rand(3) + 0.1, x=torch.randn(3, 4)),
        Track(y=torch.randn(5, 2), dt=torch.rand(5) + 0.1, x=torch.randn(5, 4)),
    ]
    b = pad_tracks(tracks)
    assert b.y.shape == (2, 5, 2) and b.mask.tolist() == [[True] * 3 + [False] * 2, [True] * 5]
    assert bool(torch.isnan(b.y[0, 3:]).all()) and bool((b.dt[0, 3:] == 0).all())
    assert torch.equal(b.x[0, 4], tracks[0].x[-1])
    assert b.u is None and b.lengths.tolist() == [3, 5]
    b7 = pad_tracks(tracks, length=7)
    items = unpad_tracks(b7)
    assert [int(it.dt.shape[0]) for it in items] == [3, 5] and torch.equal(items[1].x, tracks[1].x)
    c = collate_tracks(items)  # pads to the longest track of the batch
    assert c.y.shape == (2, 5, 2)
    assert torch.equal(torch.isnan(c.y), torch.isnan(b.y))
    with pytest.raises(ValueError, match="track 1"):
        pad_tracks(tracks, length=4)
    with pytest.raises(ValueError, match="all tracks or none"):
        pad_tracks([tracks[0], Track(y=torch.randn(2, 2), dt=torch.rand(2))])


def test_epoch_shuffle_sampler_depends_only_on_seed_and_epoch() -> None:
    s1, s2 = EpochShuffleSampler(50, seed=3), EpochShuffleSampler(50, seed=3)
    s1.set_epoch(4)
    s2.set_epoch(4)
    assert list(s1) == list(s2) and sorted(s1) == list(range(50))
    s2.set_epoch(5)
    assert list(s1) != list(s2)


def test_selection_matrix() -> None:
    H = selection_matrix([0, 2], 4)
    assert H.tolist() == [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
    with pytest.raises(ValueError, match="indices"):
        selection_matrix([5], 4)


def _dm(**kw: object) -> SimulatedTracks:
    sde = models.constant_velocity(dim=2, q=1.0)
    args = dict(
        sde=sde, H=models.position_observation(sde), noise=0.5,
        num_tracks={"train": 10, "val": 4, "test": 3}, T=12, T_min=6, batch_size=4, seed=0,
    )  # fmt: skip
    args.update(kw)
    return SimulatedTracks(**args)  # type: ignore[arg-type]


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_datamodule_splits_and_batches(dtype: str) -> None:
    dm = _dm(dtype=dtype)
    dm.setup("fit")
    assert [len(dm.dataset(s)) for s in ("train", "val", "test")] == [10, 4, 3]
    batches = list(dm.train_dataloader())
    assert len(batches) == 3
    b = batches[0]
    assert {k for k, v in b._asdict().items() if v is not None} == {"y", "dt", "mask", "x", "lengths"}
    assert b.y.dtype == getattr(torch, dtype) and b.mask.dtype == torch.bool
    assert b.y.shape[:2] == b.dt.shape == b.mask.shape and b.y.shape[-1] == 2
    assert torch.allclose(dm.R, 0.25 * torch.eye(2, dtype=torch.float64))
    # the splits are different tracks
    assert not torch.equal(dm.tracks["train"].x[:3], dm.tracks["val"].x[:3])


def test_datamodule_batch_size_null_is_a_whole_split_per_batch() -> None:
    """data.batch_size=null (accepted by the config check, as by TrackDataModule): one batch a split."""
    dm = _dm(batch_size=None)
    dm.setup("fit")
    assert [len(list(loader)) for loader in (dm.train_dataloader(), dm.val_dataloader())] == [1, 1]
    assert next(iter(dm.train_dataloader())).y.shape[0] == 10


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"noise": -0.1}, "noise"),
        ({"T": 1}, "T"),
        ({"T_min": 1}, "T_min"),
        ({"p_missing": 1.0}, "p_missing"),
        ({"num_tracks": {"train": 0, "val": 1, "test": 1}}, "num_tracks"),
        ({"dtype": "float16"}, "dtype"),
        ({"batch_size": 0}, "batch_size"),
    ],
)
def test_datamodule_rejects_bad_values(kw: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        _dm(**kw)


# --------------------------------------------------------------------------- length bucketing


def _bucket_loader(lengths: list[int], batch_size: int, seed: int = 0, **kw):
    from torch.utils.data import DataLoader

    from torchsde_lti.data import BucketBatchSampler, TrackDataset

    tracks = [Track(y=torch.zeros(n, 2), dt=torch.ones(n), track_id=torch.tensor(i)) for i, n in enumerate(lengths)]
    sampler = BucketBatchSampler(EpochShuffleSampler(len(tracks), seed), lengths, batch_size, seed=seed, **kw)
    return DataLoader(TrackDataset(tracks), batch_sampler=sampler, collate_fn=collate_tracks)


def test_bucket_batches_cover_every_item_with_little_padding() -> None:
    from torchsde_lti.data import padding_waste

    g = torch.Generator().manual_seed(0)
    lengths = (torch.randint(5, 128, (2000,), generator=g)).tolist()
    loader = _bucket_loader(lengths, 64)
    sampler = loader.batch_sampler
    batches = list(sampler)
    assert len(batches) == len(sampler) == math.ceil(2000 / 64)
    assert sorted(i for b in batches for i in b) == list(range(2000))
    waste = padding_waste(batches, lengths)
    plain = padding_waste([list(range(k, min(k + 64, 2000))) for k in range(0, 2000, 64)], lengths)
    assert waste < 0.05 < plain  # random batches of uniform lengths waste ~33 %
    sampler.sampler.set_epoch(1)
    assert list(sampler) != batches and list(sampler) == list(sampler)  # a function of (seed, epoch)
    capped = _bucket_loader(lengths, 64, max_waste=0.1, shuffle=False).batch_sampler
    per_batch = [padding_waste([b], lengths) for b in capped]
    assert max(per_batch) <= 0.1 and sorted(i for b in capped for i in b) == list(range(2000))
    assert all(len(b) <= 64 for b in capped) and len(capped) == len(list(capped))


def test_bucket_sampler_shards_by_track_under_ddp() -> None:
    """Lightning injects its DistributedSampler into the bucketing batch sampler (as it does under
    trainer=ddp): each process buckets its own, disjoint shard, with the same number of batches."""
    from lightning.fabric.utilities.data import _replace_dunder_methods, _set_sampler_epoch
    from lightning.fabric.utilities.distributed import DistributedSamplerWrapper
    from lightning.pytorch.utilities.data import _update_dataloader
    from torch.utils.data import BatchSampler, DataLoader

    lengths = (torch.randint(5, 128, (1001,), generator=torch.Generator().manual_seed(1))).tolist()
    with _replace_dunder_methods(DataLoader, "dataset"), _replace_dunder_methods(BatchSampler):
        loader = _bucket_loader(lengths, 32, seed=3)
    shards, counts = [], []
    for rank in (0, 1):
        dist = DistributedSamplerWrapper(loader.batch_sampler.sampler, num_replicas=2, rank=rank, shuffle=True, seed=3)
        ddp = _update_dataloader(loader, dist)
        _set_sampler_epoch(ddp, 2)
        assert type(ddp.batch_sampler).__name__ == "BucketBatchSampler" and ddp.batch_sampler.sampler is dist
        batches = list(ddp.batch_sampler)
        counts.append(len(batches))
        shards.append([int(i) for b in ddp for i in b.track_id])
    assert counts[0] == counts[1] == math.ceil(501 / 32)
    both = set(shards[0]) & set(shards[1])
    assert len(both) <= 1  # DistributedSampler repeats one item to make 1001 split evenly
    assert set(shards[0]) | set(shards[1]) == set(range(1001))


def test_track_has_the_fields_of_a_batch_without_mask_and_lengths() -> None:
    from torchsde_lti.data import Track, TrackBatch

    assert Track._fields == tuple(f for f in TrackBatch._fields if f not in ("mask", "lengths"))
    assert Track(y=torch.zeros(2, 1), dt=torch.zeros(2)).u is None
