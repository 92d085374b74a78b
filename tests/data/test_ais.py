"""The NY Harbor AIS hour (tracktable-data) through load_tracks and TrackDataModule, as data=ais.

Oracles are independent of the loader: a plain csv re-count of the file, finite differences of
the positions for the SOG/COG velocity, each track filtered alone for the padded batches.
"""

from __future__ import annotations

import csv
import io
import os

import numpy as np
import pytest
import torch

pytest.importorskip(
    "tracktable_data",
    reason="optional data package tracktable-data not installed (pip install -e .[data])",
)
pytest.importorskip("pyarrow", reason="CSV files are read with pyarrow (pip install -e .[data])")

from torchsde_lti.data import (  # noqa: E402
    TrackBatch,
    Tracks,
    load_tracks,
    locate_file,
    pad_tracks,
    split_objects,
    track_windows,  # noqa: E402
)
from torchsde_lti.data.modules import TrackDataModule  # noqa: E402

HOUR = "NYHarbor_2020_06_30_first_hour.csv"
JUNE = {"course_encoding": "ais_int12", "min_reports": 5}  # conf/data/ais.yaml


def june_module(**kw: object) -> TrackDataModule:
    return TrackDataModule(HOUR, **{**JUNE, **kw})


@pytest.fixture(scope="module")
def data() -> Tracks:
    return load_tracks(HOUR, **JUNE)


@pytest.fixture(scope="module")
def raw_rows() -> list[dict[str, str]]:
    with open(locate_file(HOUR), newline="") as fh:
        return list(csv.DictReader(fh))


def test_counts_match_independent_recount(data: Tracks, raw_rows: list[dict[str, str]]) -> None:
    c = data.summary
    assert c.rows == len(raw_rows) and 8000 < c.rows < 9500  # ~8.7k reports from ~300 vessels
    keys = {(r["MMSI"], r["BaseDateTime"]) for r in raw_rows}
    assert c.rows - c.repeated_timestamps == len(keys) and c.malformed == 0 and c.invalid_positions == 0
    per_vessel: dict[str, int] = {}
    for m, _ in keys:
        per_vessel[m] = per_vessel.get(m, 0) + 1
    long_enough = [n for n in per_vessel.values() if n >= 5]
    assert c.tracks == len(data) == len(long_enough) == c.objects == 283
    assert c.reports == sum(long_enough) == data.num_reports == 8658
    assert c.short_tracks == len(per_vessel) - len(long_enough)
    assert len(set(data.object_id.tolist())) == len(data)


def test_tracks_monotone_time_and_finite(data: Tracks) -> None:
    dts = []
    for i in range(len(data)):
        tr = data.track(i)
        assert np.all(np.diff(tr["t"]) > 0) and np.isfinite(tr["pos"]).all()
        assert 0.0 <= tr["t"][0] and tr["t"][-1] < 3600.0  # one hour of data
        dts.append(np.diff(tr["t"]))
    dts = np.concatenate(dts)
    assert dts.min() > 0 and 30 < np.median(dts) < 120  # median gap ~70 s


def test_sog_cog_velocity_matches_finite_differences(data: Tracks) -> None:
    diffs = []
    for i in range(len(data)):
        tr = data.track(i)
        fd = np.diff(tr["pos"], axis=0) / np.diff(tr["t"])[:, None]
        mid = 0.5 * (tr["vel"][1:] + tr["vel"][:-1])
        ok = np.isfinite(mid).all(1) & (tr["sog"][1:] > 5) & (tr["sog"][:-1] > 5)
        diffs.append(fd[ok] - mid[ok])
    d = np.concatenate(diffs)
    assert len(d) > 500
    # measured: 90th percentile 1.3 m/s, bias < 0.03 m/s; reading COG undecoded gives
    # 7.1 m/s and a 1 m/s bias, swapping east/north 13.8 m/s
    err = np.linalg.norm(d, axis=1)
    assert np.percentile(err, 50) < 0.5 and np.percentile(err, 90) < 3.0
    assert np.all(np.abs(d.mean(axis=0)) < 0.2)
    raw = load_tracks(HOUR, min_reports=5)  # COG read as plain AIS degrees: negative values unavailable
    assert raw.summary.courses_decoded == 0 and np.isnan(raw.vel).any(-1).sum() > np.isnan(data.vel).any(-1).sum()


def test_vessel_split_sizes(data: Tracks) -> None:
    parts = split_objects(data, (0.6, 0.2, 0.2), seed=0)
    assert [len(p) for p in parts] == [169, 57, 57]


def test_datamodule_padded_masked_batches(data: Tracks) -> None:
    dm = june_module(batch_size=16, seed=0)
    dm.setup("fit")
    mmsi = [set(dm.splits[s].object_id.tolist()) for s in ("train", "val", "test")]
    assert not (mmsi[0] & mmsi[1] or mmsi[0] & mmsi[2] or mmsi[1] & mmsi[2])
    assert sum(map(len, mmsi)) == data.summary.objects
    train = dm.splits["train"]
    batch = next(iter(dm.train_dataloader()))
    assert isinstance(batch, TrackBatch)
    B, T = batch.mask.shape
    assert B == 16 and batch.y.shape == (B, T, 2) and batch.dt.shape == (B, T)
    assert batch.y.dtype == torch.float32 and batch.mask.dtype == torch.bool
    assert T == int(batch.lengths.max())
    np.testing.assert_array_equal(batch.mask.sum(1).numpy(), batch.lengths.numpy())
    assert torch.equal(torch.isnan(batch.y).any(-1), ~batch.mask)
    assert torch.all(batch.dt[:, 0] == 0) and torch.all(batch.dt[~batch.mask] == 0)
    for i in range(B):
        tr = train.track(int(batch.track_id[i]))
        k = len(tr["t"])
        np.testing.assert_allclose(batch.dt[i, 1:k].numpy(), np.diff(tr["t"]), rtol=1e-6)
        np.testing.assert_allclose((batch.y[i, :k] + batch.origin[i]).double().numpy(), tr["pos"], atol=0.01)
        assert torch.all(batch.y[i, 0] == 0)
    waste = dm.summary.splits["train"]["padding_waste"]
    assert 0 <= waste < 0.25 and "padding waste" in str(dm.summary)
    full = next(iter(june_module(dtype="float64").val_dataloader()))
    assert full.y.dtype == torch.float64 and full.y.shape[0] == 57


def test_reserved_files_are_refused() -> None:
    for name in ("NYHarbor_2020_12_08.traj", "VirginiaBeach_2020_06_04_to_06_filtered.traj"):
        for spelling in (name, f"./{name}", f"{name}/", f"{name}/.", f"{name}//"):
            with pytest.raises(ValueError, match="reserved for evaluation"):
                TrackDataModule(spelling)


def test_a_link_to_a_reserved_file_is_refused(tmp_path) -> None:
    from torchsde_lti.data import locate_file

    link = tmp_path / "renamed.traj"
    link.symlink_to(locate_file("NYHarbor_2020_12_08.traj"))
    with pytest.raises(ValueError, match="reserved for evaluation"):
        TrackDataModule(str(link))


def test_a_hard_link_or_renamed_copy_of_a_reserved_file_is_refused(tmp_path, monkeypatch) -> None:
    # the names were checked only: a hard link or a copy under another name trained on the file
    import shutil

    from torchsde_lti.data import RESERVED_FOR_EVALUATION, sources

    for name in RESERVED_FOR_EVALUATION:
        shipped = locate_file(name)
        copy = shutil.copy(shipped, tmp_path / f"copy_{name}.traj")
        with pytest.raises(ValueError, match=f"is {name}, reserved for evaluation"):
            TrackDataModule(str(copy))
        try:
            os.link(shipped, tmp_path / f"hard_{name}")
        except OSError:  # another file system
            continue
        with pytest.raises(ValueError, match=f"is {name}, reserved for evaluation"):
            TrackDataModule(str(tmp_path / f"hard_{name}"))
    # the table of sizes and hashes alone (no tracktable-data found) still knows the copies
    monkeypatch.setattr(sources, "_example_dirs", lambda: [])
    for name in RESERVED_FOR_EVALUATION:
        with pytest.raises(ValueError, match="reserved for evaluation"):
            TrackDataModule(str(tmp_path / f"copy_{name}.traj"))


def test_shuffled_batches_depend_only_on_seed_and_epoch() -> None:
    # a resumed run builds a fresh loader at epoch e: it must see the batches an
    # uninterrupted run sees at epoch e (Lightning calls set_epoch before every epoch)
    from lightning.fabric.utilities.data import _set_sampler_epoch

    def order(loader, epoch: int) -> list[int]:
        _set_sampler_epoch(loader, epoch)
        return [int(m) for b in loader for m in b.track_id]

    dm = june_module(batch_size=32, seed=3)
    dm.setup()
    running = dm.train_dataloader()
    epoch0, epoch1 = order(running, 0), order(running, 1)
    assert epoch0 != epoch1 and sorted(epoch0) == sorted(epoch1)
    fresh = june_module(batch_size=32, seed=3)
    fresh.setup()
    assert order(fresh.train_dataloader(), 1) == epoch1


def test_padded_batch_likelihood_equals_per_track_filtering(data: Tracks) -> None:
    """Padding (dt = 0, y = NaN, mask False) adds nothing: batch log-likelihoods equal
    those of each track filtered alone, without padding."""
    import torchsde_lti as tl

    tracks = data.subset(range(6))
    batch = pad_tracks(track_windows(tracks, dtype=torch.float64))
    assert batch.lengths.min() < batch.mask.shape[1]
    sde = tl.models.constant_velocity(dim=2, q=torch.tensor(0.01, dtype=torch.float64))
    kf = tl.KalmanFilter(
        sde,
        tl.models.position_observation(sde),
        400.0 * torch.eye(2, dtype=torch.float64),
        P0=torch.diag(torch.tensor([1e4, 25.0, 1e4, 25.0], dtype=torch.float64)),
    )
    with torch.no_grad():
        ll = kf(batch.y, batch.dt, mask=batch.mask).log_likelihood
        for i in range(len(tracks)):
            tr = tracks.track(i)
            y = torch.as_tensor(tr["pos"] - tr["pos"][0])
            dt = torch.as_tensor(np.concatenate([[0.0], np.diff(tr["t"])]))
            assert float(kf(y, dt).log_likelihood) == pytest.approx(float(ll[i]), rel=1e-10, abs=1e-8)


def test_experiment_ais_config_trains(tmp_path) -> None:
    """`experiment=ais` composes (AIS data, ship-scale inits, model sweep) and runs end to end."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    from torchsde_lti.train import train

    conf = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[
                f"output_dir={tmp_path}",
                "experiment=ais",
                "+trainer.fast_dev_run=true",
                "plots=false",
                "module.optimizer.max_iter=3",
            ],
        )
        hcfg = compose("train", overrides=["experiment=ais"], return_hydra_config=True)
    assert cfg.data._target_ == "torchsde_lti.data.modules.TrackDataModule"
    assert set(str(hcfg.hydra.sweeper.params.model).split(",")) == {"cv", "integrated_ou", "singer"}
    metrics, objects = train(cfg)
    dm = objects["datamodule"]
    assert isinstance(dm, TrackDataModule) and len(dm.splits["train"]) == 169
    assert np.isfinite(metrics["train/nll"]) and np.isfinite(metrics["val/nll"])
    kf = objects["module"].kf
    assert kf.H.shape == (2, 4) and float(kf.sde.k.detach()) != pytest.approx(2.0)  # the drag moved off its init
    # hyperparameters are plain Python (no OmegaConf containers): checkpoints load with weights_only
    buf = io.BytesIO()
    torch.save(dict(dm.hparams), buf)
    buf.seek(0)
    assert torch.load(buf, weights_only=True)["fractions"] == [0.6, 0.2, 0.2]


def test_experiment_ais_imm_config_trains(tmp_path) -> None:
    """`experiment=ais_imm` composes (AIS data, the moored + underway IMM bank) and runs end to end."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    import torchsde_lti as tl
    from torchsde_lti.train import train

    conf = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[
                f"output_dir={tmp_path}",
                "experiment=ais_imm",
                "+trainer.fast_dev_run=true",
                "plots=false",
                "module.optimizer.max_iter=3",
            ],
        )
    assert cfg.filter._target_ == "torchsde_lti.IMMFilter" and cfg.get("truth") is None
    metrics, objects = train(cfg)
    assert len(objects["datamodule"].splits["train"]) == 169
    assert np.isfinite(metrics["train/nll"]) and np.isfinite(metrics["val/nll"])
    kf = objects["module"].kf
    assert isinstance(kf, tl.IMMFilter) and kf.mode_names == ("moored", "underway") and kf.R.shape == (2, 2, 2)
    assert float(kf.models[0].k.detach()) != pytest.approx(0.05, rel=1e-6)  # the moored drag moved off its init
    names = {r["name"] for r in metrics["table"]}
    assert {"moored/k", "underway/k", "underway/R[0,0]", "rate[moored->underway]", "mode_prob0[moored]"} <= names
