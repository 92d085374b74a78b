"""Streamed training over a prepared dataset (torchsde_lti.data.stream, stream_module).

Oracles: the prepared windows themselves (every window of a split exactly once per epoch, over
ranks and workers, before and after a resume) and ``track_windows`` (the batches' content)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from torch.utils.data import DataLoader

from torchsde_lti.data import load_tracks, track_windows
from torchsde_lti.data.prepare import prepare_dataset
from torchsde_lti.data.stream import WindowStream, object_split

from .test_prepare import _ais_csv


@pytest.fixture(scope="module")
def prepared(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("stream")
    for k in range(3):
        _ais_csv(root / f"AIS_{k}.csv", 40, seed=20 + k, day=f"2024-01-0{k + 1}")
    out = root / "prepared"
    prepare_dataset(sorted(root.glob("*.csv")), out, max_len=16, buckets=4, row_group_windows=37)
    return out


def _all_rows(out: Path) -> int:
    return sum(pq.ParquetFile(f).metadata.num_rows for f in (out / "windows").glob("*.parquet"))


def _seen(loader: DataLoader) -> list[int]:
    return [int(i) for batch in loader for i in batch.track_id.tolist()]


@pytest.mark.parametrize("workers", [0, 2])
def test_splits_partition_the_windows_and_each_is_seen_once(prepared: Path, workers: int) -> None:
    """train, val, test are disjoint by object and cover every window; an epoch of each (one rank,
    ``workers`` DataLoader workers) yields each of its windows exactly once."""
    seen = {}
    for split in ("train", "val", "test"):
        ds = WindowStream(prepared, split, batch_size=8, pool_batches=3, buffer_windows=50, seed=1)
        got = _seen(DataLoader(ds, batch_size=None, num_workers=workers))
        assert len(got) == len(set(got)) == len(ds.member)
        assert set(got) == set(ds.member.tolist())
        seen[split] = {ds.object_id(i) for i in got}
    assert not (seen["train"] & seen["val"]) and not (seen["train"] & seen["test"]) and not (seen["val"] & seen["test"])
    assert sum(len(WindowStream(prepared, s).member) for s in ("train", "val", "test")) == _all_rows(prepared)


def test_ranks_share_an_epoch_evenly(prepared: Path) -> None:
    """R ranks: disjoint, equal shares (training: N // R each, same batch count), all of them
    together every window but the N mod R left over; evaluation: every window once."""
    for world in (2, 3):
        parts = [WindowStream(prepared, "train", batch_size=8, rank=r, world_size=world) for r in range(world)]
        for p in parts:
            p.set_position(epoch=2)
        rows = [np.concatenate(p.batches()) for p in parts]
        n = len(parts[0].member)
        assert all(len(r) == n // world for r in rows) and len({len(p) for p in parts}) == 1
        union = np.concatenate(rows)
        assert len(np.unique(union)) == len(union) == n - n % world
        evals = [
            WindowStream(prepared, "val", shuffle=False, even=False, rank=r, world_size=world) for r in range(world)
        ]
        every = np.concatenate([np.concatenate(e.batches()) for e in evals])
        assert sorted(every.tolist()) == sorted(evals[0].member.tolist())


def test_epochs_are_shuffled_and_reproducible(prepared: Path) -> None:
    ds = WindowStream(prepared, "train", batch_size=8, seed=3)
    a, b, a2 = (np.concatenate(ds.batches(e)) for e in (0, 1, 0))
    np.testing.assert_array_equal(a, a2)
    assert not np.array_equal(a, b) and sorted(a.tolist()) == sorted(b.tolist())
    other = np.concatenate(WindowStream(prepared, "train", batch_size=8, seed=4).batches(0))
    assert not np.array_equal(a, other)


@pytest.mark.parametrize("workers", [0, 2])
def test_a_resumed_epoch_continues_the_same_plan(prepared: Path, workers: int) -> None:
    """Stopped after k batches and resumed at batch k (any worker count), the epoch yields the
    uninterrupted epoch's batches k, k+1, ... in order: no window repeated or skipped."""
    ds = WindowStream(prepared, "train", batch_size=8, pool_batches=2, seed=5)
    ds.set_position(epoch=1)
    whole = [b.track_id.tolist() for b in DataLoader(ds, batch_size=None, num_workers=workers)]
    k = len(whole) // 3
    ds.set_position(epoch=1, skip=k)
    rest = [b.track_id.tolist() for b in DataLoader(ds, batch_size=None, num_workers=workers)]
    assert rest == whole[k:]


def test_batches_hold_the_windows_of_track_windows(tmp_path: Path) -> None:
    """One file prepared with one bucket: the streamed windows are track_windows' windows
    (positions centred on the first report, dt, velocities), matched by object and time steps."""
    src = _ais_csv(tmp_path / "d.csv", 20, seed=7, faults=False)
    prepare_dataset(src, tmp_path / "out", max_len=12, buckets=1)
    tracks = load_tracks(src)
    expected = track_windows(tracks, max_len=12, center=True, dtype=torch.float64)
    ds = WindowStream(tmp_path / "out", "train", fractions=(1.0, 0.0, 0.0), batch_size=4, dtype=torch.float64)
    got = {}
    for batch in DataLoader(ds, batch_size=None):
        for i in range(batch.y.shape[0]):
            n = int(batch.lengths[i])
            key = (int(ds.object_id(int(batch.track_id[i]))), n, *np.round(batch.dt[i, :n].numpy(), 3).tolist())
            got[key] = (batch.y[i, :n], batch.dt[i, :n], batch.vel[i, :n])
    assert len(got) == len(expected)
    for w in expected:
        key = (int(tracks.object_id[int(w.track_id)]), int(w.dt.shape[0]), *np.round(w.dt.numpy(), 3).tolist())
        y, dt, vel = got[key]
        torch.testing.assert_close(y, w.y, rtol=0, atol=1e-9)
        torch.testing.assert_close(dt, w.dt, rtol=0, atol=1e-6)
        torch.testing.assert_close(vel, w.vel, rtol=0, atol=1e-9, equal_nan=True)


def test_object_split_is_a_seeded_partition() -> None:
    ids = np.arange(100_000, 120_000)
    s = object_split(ids, (0.6, 0.2, 0.2), seed=0)
    share = np.bincount(s, minlength=3) / len(ids)
    np.testing.assert_allclose(share, [0.6, 0.2, 0.2], atol=0.015)
    assert (object_split(ids, (0.6, 0.2, 0.2), 0) == s).all() and (object_split(ids, (0.6, 0.2, 0.2), 1) != s).any()
    text = object_split(ids.astype(str), (0.5, 0.5, 0.0), seed=2)
    assert set(np.unique(text).tolist()) == {0, 1}
    with pytest.raises(ValueError, match="fractions"):
        object_split(ids, (0.5, 0.2, 0.2), 0)


def test_arguments_are_checked(prepared: Path, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="torchsde_lti.prepare"):
        WindowStream(tmp_path, "train")
    with pytest.raises(ValueError, match="split"):
        WindowStream(prepared, "validation")
    with pytest.raises(ValueError, match="batch_size"):
        WindowStream(prepared, "train", batch_size=0)
    with pytest.raises(ValueError, match="rank"):
        WindowStream(prepared, "train", rank=2, world_size=2)


# ---------------------------------------------------------------------------- through Lightning
class _Recorder:
    """A LightningModule that records the windows (track_id) of every training batch by epoch."""

    @staticmethod
    def make(log: list) -> object:
        import lightning.pytorch as pl

        class Recorder(pl.LightningModule):
            def __init__(self) -> None:
                super().__init__()
                self.w = torch.nn.Parameter(torch.zeros(()))

            def training_step(self, batch, batch_idx):  # noqa: ANN001, ANN202
                log.append((self.current_epoch, batch.track_id.tolist()))
                return (self.w - 1.0) ** 2 * batch.y.shape[0]

            def configure_optimizers(self):  # noqa: ANN202
                return torch.optim.SGD(self.parameters(), lr=0.01)

        return Recorder()


def test_resume_mid_epoch_through_a_checkpoint_sees_every_window_once(prepared: Path, tmp_path: Path) -> None:
    """A run stopped mid-epoch (max_steps) with a step checkpoint, resumed from it: each epoch's
    training windows, over both runs, are the split's windows, each exactly once."""
    import lightning.pytorch as pl
    from lightning.pytorch.callbacks import ModelCheckpoint

    from torchsde_lti.data.stream_module import StreamDataModule

    def trainer(**kw: object) -> pl.Trainer:
        ckpt = ModelCheckpoint(dirpath=tmp_path, filename="step", every_n_train_steps=5, save_top_k=-1)
        return pl.Trainer(
            accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False,
            limit_val_batches=0, callbacks=[ckpt], **kw,
        )  # fmt: skip

    dm = lambda: StreamDataModule(str(prepared), batch_size=8, pool_batches=2, seed=9)  # noqa: E731
    log: list = []
    trainer(max_steps=5).fit(_Recorder.make(log), datamodule=dm())
    assert len(log) == 5
    trainer(max_epochs=2).fit(_Recorder.make(log), datamodule=dm(), ckpt_path=str(tmp_path / "step.ckpt"))
    member = WindowStream(prepared, "train", seed=9).member
    for epoch in (0, 1):
        seen = Counter(i for e, ids in log if e == epoch for i in ids)
        assert set(seen.values()) == {1} and sorted(seen) == sorted(member.tolist())


# ---------------------------------------------------------------------------- the one training path
def test_prepare_and_train_through_hydra(tmp_path: Path) -> None:
    """``python -m torchsde_lti.prepare source=... out=...`` then ``python -m torchsde_lti.train
    data=stream data.root=...`` (configs composed as the commands compose them)."""
    from hydra import compose, initialize_config_dir

    from torchsde_lti.prepare import prepare
    from torchsde_lti.training.train import config_path, train

    src = _ais_csv(tmp_path / "AIS_2024_01_01.csv", 40, seed=30)
    out = tmp_path / "prepared"
    with initialize_config_dir(config_dir=config_path(), version_base="1.3"):
        summary = prepare(
            compose("prepare", overrides=[f"source={src}", f"out={out}", "max_len=32", "rules.v_max=null"])
        )
        assert summary.load.rules["v_max"] is None and summary.load.rules["min_reports"] == 5
        cfg = compose(
            "train",
            overrides=[
                "experiment=ais_us_coastal", "data=stream", f"data.root={out}", "data.batch_size=16",
                "trainer.max_epochs=1", "test=true", "plots=false", f"output_dir={tmp_path / 'run'}",
            ],
        )  # fmt: skip
    metrics, objects = train(cfg)
    assert metrics["status"] == "completed" and np.isfinite(metrics["val/nll"])
    dm = objects["datamodule"]
    assert dm.summary.prepared.windows == summary.windows
    assert '"prepared": {' in (tmp_path / "run" / "metrics.json").read_text()


def test_datamodule_without_a_prepared_dataset_says_how_to_make_one(tmp_path: Path) -> None:
    from torchsde_lti.data.stream_module import StreamDataModule

    dm = StreamDataModule(str(tmp_path / "nothing"))  # (built by Hydra before any data is read)
    with pytest.raises(FileNotFoundError, match="no prepared dataset.*python -m torchsde_lti.prepare"):
        dm.setup("fit")
    with pytest.raises(ValueError, match="dtype"):
        StreamDataModule(str(tmp_path), dtype="float16")
    with pytest.raises(ValueError, match="fractions"):
        StreamDataModule(str(tmp_path), fractions=(0.5, 0.5, 0.5))
