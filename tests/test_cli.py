"""The ``torchsde-lti`` command and ``tl.load_run``: train -> load_run -> filter / smooth a CSV ->
the states the in-process filter gives; every subcommand's help, errors and outputs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from torchsde_lti.cli import main
from torchsde_lti.runs import _geodetic, load_run, read_tracks, track_states

pytest.importorskip("pyarrow")
pytest.importorskip("pymap3d")
import pyarrow.csv  # noqa: E402
import pyarrow.parquet  # noqa: E402
import pymap3d  # noqa: E402

CONF = Path(__file__).resolve().parents[1] / "conf"


def _write_ais_csv(path: Path, tracks: int = 5, reports: int = 12, seed: int = 0) -> Path:
    """A MarineCadastre-style CSV of ``tracks`` ships moving near New York, irregular reports."""
    rng = np.random.default_rng(seed)
    lines = ["MMSI,BaseDateTime,LAT,LON,SOG,COG"]
    for k in range(tracks):
        t = np.cumsum(rng.integers(5, 90, reports))
        lat = 40.6 + 0.01 * k + 1e-5 * t * rng.uniform(0.5, 1.5) + 1e-5 * rng.standard_normal(reports)
        lon = -74.0 - 0.01 * k + 2e-5 * t * rng.uniform(0.5, 1.5) + 1e-5 * rng.standard_normal(reports)
        for ti, la, lo in zip(t, lat, lon):
            stamp = np.datetime64("2020-06-30T00:00:00") + np.timedelta64(int(ti), "s")
            lines.append(f"{366000000 + k},{stamp},{la:.6f},{lo:.6f},5.0,45.0")
    # one single-report ship: dropped by the loader, and counted
    lines.append("366999999,2020-06-30T00:00:00,40.70,-74.00,0.0,0.0")
    path.write_text("\n".join(lines) + "\n")
    return path


def _train(run_dir: Path, *overrides: str) -> None:
    cmd = [sys.executable, "-m", "torchsde_lti", "train", "experiment=tiny", f"hydra.run.dir={run_dir}", *overrides]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]


@pytest.fixture(scope="module")
def cv_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny constant-velocity run, trained by the command (``python -m torchsde_lti train``)."""
    run_dir = tmp_path_factory.mktemp("cv_run")
    _train(run_dir, "model=cv", "truth=cv")
    return run_dir


@pytest.fixture(scope="module")
def imm_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run_dir = tmp_path_factory.mktemp("imm_run")
    _train(run_dir, "model=imm", "filter=imm", "truth=cv", "test=false")
    return run_dir


@pytest.fixture(scope="module")
def csv_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_ais_csv(tmp_path_factory.mktemp("tracks") / "tracks.csv")


# --------------------------------------------------------------------------- load_run


def test_load_run_rebuilds_the_best_checkpoint_in_eval_mode(cv_run: Path) -> None:
    run = load_run(cv_run)
    card = json.loads((cv_run / "metrics.json").read_text())
    assert isinstance(run.filter, tl.KalmanFilter) and not run.filter.training
    assert run.checkpoint == cv_run / "checkpoints" / "best.ckpt"
    assert run.card["status"] == "completed" and run.card["metrics"] == card["metrics"]
    assert run.config.model.name == "cv" and run.config.output_dir == str(cv_run)
    assert all(p.dtype == torch.float64 for p in run.filter.parameters())
    # the weights are the checkpoint's, and the card's learned values are that checkpoint's table
    saved = torch.load(run.checkpoint, weights_only=True)["state_dict"]
    for key, value in run.filter.state_dict().items():
        torch.testing.assert_close(value, saved[f"kf.{key}"], rtol=0, atol=0)
    best = {r["name"]: r["learned"] for r in card["best"]["table"] if r["learned"] is not None}
    assert run.card["learned"] == best
    R = run.filter.R.detach()
    assert run.card["learned"]["R[0,0]"] == pytest.approx(float(R[0, 0]), rel=1e-12)


def test_load_run_rebuilds_a_run_trained_in_process(tmp_path: Path) -> None:
    """train(cfg) called from Python (no Hydra run, no .hydra/) writes the resolved config.yaml:
    load_run rebuilds the run's filter, which gives the trained module's outputs exactly."""
    from hydra import compose, initialize_config_dir

    from torchsde_lti.training import train

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=[f"output_dir={tmp_path}", "experiment=tiny", "model=cv", "truth=cv"])
    _, objects = train(cfg)
    assert not (tmp_path / ".hydra").exists() and (tmp_path / "config.yaml").is_file()
    run = load_run(tmp_path, checkpoint="last")  # the final weights: the trained module's
    trained = objects["module"].kf.eval()
    y = torch.randn(3, 9, 2, dtype=torch.float64).cumsum(1)
    dt = torch.rand(3, 9, dtype=torch.float64) + 0.1
    with torch.no_grad():
        got, expected = run.filter(y, dt), trained(y, dt)
    torch.testing.assert_close(got.mean, expected.mean, rtol=0, atol=0)
    torch.testing.assert_close(got.cov, expected.cov, rtol=0, atol=0)
    assert run.config.model.name == "cv" and run.card["status"] == "completed"


def test_load_run_last_and_float32(tmp_path: Path) -> None:
    _train(tmp_path, "model=cv", "truth=cv", "dtype=float32", "test=false")
    run = load_run(tmp_path, checkpoint="last")
    assert run.checkpoint.name == "last.ckpt"
    assert all(p.dtype == torch.float32 for p in run.filter.parameters())


def test_load_run_errors_name_the_problem(cv_run: Path, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="run_dir: no such directory"):
        load_run(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError, match=r"not a run directory \(no .hydra/config.yaml, no config.yaml\)"):
        load_run(tmp_path)
    with pytest.raises(FileNotFoundError, match="checkpoint: no such file"):
        load_run(cv_run, checkpoint=tmp_path / "x.ckpt")
    broken = tmp_path / "broken.ckpt"
    broken.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="cannot read it"):
        load_run(cv_run, checkpoint=broken)


def test_load_run_refuses_another_models_checkpoint(cv_run: Path, imm_run: Path) -> None:
    with pytest.raises(ValueError, match="does not fit the run's configured filter"):
        load_run(cv_run, checkpoint=imm_run / "checkpoints" / "best.ckpt")


# --------------------------------------------------------------------------- filter / smooth


def _in_process(run_dir: Path, csv: Path, smooth: bool) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each track's (mean, cov), from the loaded filter called on that track alone."""
    run = load_run(run_dir)
    tracks = tl.data.load_tracks(csv)
    out = []
    for i in range(len(tracks)):
        tr = tracks.track(i)
        y = torch.as_tensor(tr["pos"] - tr["pos"][0])[None]
        dt = torch.as_tensor(np.diff(tr["t"], prepend=tr["t"][0]))[None]
        with torch.no_grad():
            res = run.filter(y, dt)
            res = run.filter.smooth(res) if smooth else res
        out.append((res.mean[0].numpy(), res.cov[0].numpy()))
    return out


@pytest.mark.parametrize("command, suffix", [("filter", ".csv"), ("smooth", ".parquet")])
def test_filter_and_smooth_write_the_in_process_states(
    cv_run: Path, csv_file: Path, tmp_path: Path, command: str, suffix: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / f"states{suffix}"
    # batch size 2: several padded batches of unequal lengths, reordered back
    assert main([command, str(cv_run), str(csv_file), "-o", str(out), "--batch-size", "2"]) == 0
    assert "tracks < 2 reports dropped (reports)        1 (1)" in capsys.readouterr().err  # counted, not silent
    table = (pyarrow.csv.read_csv(out) if suffix == ".csv" else pyarrow.parquet.read_table(out)).to_pydict()
    expected = _in_process(cv_run, csv_file, smooth=command == "smooth")
    assert len(table["t"]) == sum(len(m) for m, _ in expected) == 5 * 12
    track = np.asarray(table["track"])
    for i, (mean, cov) in enumerate(expected):
        rows = track == i
        got_mean = np.stack([np.asarray(table[f"mean_{k}"])[rows] for k in range(4)], -1)
        np.testing.assert_allclose(got_mean, mean, rtol=1e-10, atol=1e-9)
        for a in range(4):
            for b in range(a, 4):
                np.testing.assert_allclose(
                    np.asarray(table[f"cov_{a}_{b}"])[rows], cov[:, a, b], rtol=1e-10, atol=1e-12
                )
    assert set(table["id"]) == {366000000 + k for k in range(5)}


def test_positions_and_lat_lon_are_in_the_tracks_frame(cv_run: Path, csv_file: Path) -> None:
    run = load_run(cv_run)
    tracks = read_tracks(run, csv_file)
    cols = track_states(run, tracks)
    # east/north: H m (state 0 and 2) in the track's own frame (the first report is its origin)
    np.testing.assert_allclose(cols["east"], cols["mean_0"], atol=1e-6)
    np.testing.assert_allclose(cols["north"], cols["mean_2"], atol=1e-6)
    origin = tracks.origin[cols["track"]]
    e, n, _ = pymap3d.geodetic2enu(cols["lat"], cols["lon"], 0.0, origin[:, 0], origin[:, 1], 0.0)
    np.testing.assert_allclose(e, cols["east"], atol=1e-6)
    np.testing.assert_allclose(n, cols["north"], atol=1e-6)
    # filtered positions stay near the reports (metres, not degrees)
    assert np.abs(cols["east"] - tracks.pos[:, 0]).max() < 50.0
    assert (np.diff(cols["time"].astype("int64")) != 0).all()


@pytest.mark.parametrize("lat0, lon0", [(40.7, -74.0), (70.0, 179.5), (-33.9, 151.2)])
def test_geodetic_inverts_the_local_frame_far_from_its_origin(lat0: float, lon0: float) -> None:
    """The inverse of data.frames.local_positions (height-0 projection): pymap3d's forward map
    of the recovered point gives the east/north back, 200 km out and across the antimeridian."""
    angles = np.linspace(0, 2 * np.pi, 9)
    east, north = 2e5 * np.cos(angles), 2e5 * np.sin(angles)
    lat, lon = _geodetic(east, north, np.full(9, lat0), np.full(9, lon0))
    e, n, _ = pymap3d.geodetic2enu(lat, lon, 0.0, lat0, lon0, 0.0)
    np.testing.assert_allclose(e, east, atol=1e-5)
    np.testing.assert_allclose(n, north, atol=1e-5)
    assert ((lon >= -180) & (lon < 180)).all()


def test_imm_filter_writes_mode_probabilities(imm_run: Path, csv_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "imm.csv"
    assert main(["filter", str(imm_run), str(csv_file), "-o", str(out)]) == 0
    table = pyarrow.csv.read_csv(out).to_pydict()
    probs = np.stack([np.asarray(table["prob_moored"]), np.asarray(table["prob_underway"])], -1)
    np.testing.assert_allclose(probs.sum(-1), 1.0, atol=1e-12)
    # the IMM smoother (IMMFilter.smooth): smoothed mode probabilities
    smoothed = tmp_path / "imm_smoothed.csv"
    assert main(["smooth", str(imm_run), str(csv_file), "-o", str(smoothed)]) == 0
    table = pyarrow.csv.read_csv(smoothed).to_pydict()
    probs = np.stack([np.asarray(table["prob_moored"]), np.asarray(table["prob_underway"])], -1)
    np.testing.assert_allclose(probs.sum(-1), 1.0, atol=1e-12)


def test_columns_option_reads_other_headers(cv_run: Path, csv_file: Path, tmp_path: Path) -> None:
    renamed = tmp_path / "renamed.csv"
    renamed.write_text(csv_file.read_text().replace("MMSI,BaseDateTime,LAT,LON", "ship,when,la,lo", 1))
    out = tmp_path / "s.csv"
    cols = "id=ship,time=when,lat=la,lon=lo,sog=SOG,cog=COG"
    assert main(["filter", str(cv_run), str(renamed), "-o", str(out), "--columns", cols]) == 0
    assert pyarrow.csv.read_csv(out).num_rows == 60


def test_bad_input_is_one_line_and_status_2(cv_run: Path, csv_file: Path, tmp_path: Path, capsys) -> None:
    assert main(["filter", str(tmp_path), str(csv_file), "-o", str(tmp_path / "s.csv")]) == 2
    assert "no .hydra/config.yaml" in capsys.readouterr().err
    assert main(["filter", str(cv_run), str(csv_file), "-o", str(tmp_path / "s.json")]) == 2
    assert "give a .csv or .parquet file" in capsys.readouterr().err
    assert main(["filter", str(cv_run), str(tmp_path / "none.csv"), "-o", str(tmp_path / "s.csv")]) == 2
    assert main(["filter", str(cv_run), str(csv_file), "-o", str(tmp_path / "s.csv"), "--columns", "id"]) == 2
    assert "role=column pairs" in capsys.readouterr().err


# --------------------------------------------------------------------------- evaluate, export, help


def test_evaluate_prints_scores_with_units(cv_run: Path, csv_file: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "scores.json"
    assert main(["evaluate", str(cv_run), str(csv_file), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| nll |" in text and "nats per report" in text and "| cover2s |" in text
    scores = json.loads(out.read_text())
    assert scores["vessels"] == 5 and np.isfinite(scores["nll"])


def test_export_traces_the_runs_filter_with_a_dynamic_batch_and_length(
    cv_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The wiring, without the tracing (tens of seconds; the slow test below runs it whole)."""
    calls = []
    monkeypatch.setattr(torch.export, "export", lambda *a, **k: calls.append((a, k)) or "program")
    monkeypatch.setattr(torch.export, "save", lambda program, path: calls.append((program, path)))
    assert main(["export", str(cv_run), "-o", str(tmp_path / "kf.pt2"), "--batch", "3", "--length", "7"]) == 0
    (module, example), options = calls[0]
    assert isinstance(module, tl.DeployedFilter)
    assert example[0].shape == (3, 7, 2) and example[0].dtype == torch.float64
    assert set(options["dynamic_shapes"]) == {"y", "dt"}
    assert calls[1] == ("program", str(tmp_path / "kf.pt2"))
    y, dt = torch.randn(2, 9, 2, dtype=torch.float64).cumsum(1), torch.rand(2, 9, dtype=torch.float64)
    torch.testing.assert_close(module(y, dt)[0], load_run(cv_run).filter(y, dt).log_likelihood)


@pytest.mark.slow
def test_export_gives_a_program_with_the_filters_values(cv_run: Path, tmp_path: Path) -> None:
    path = tmp_path / "kf.pt2"
    assert main(["export", str(cv_run), "-o", str(path), "--batch", "2", "--length", "4"]) == 0
    program = torch.export.load(path).module()
    kf = load_run(cv_run).filter
    for B, T in ((1, 5), (3, 40)):  # a dynamic batch and length
        y = torch.randn(B, T, 2, dtype=torch.float64).cumsum(1)
        dt = torch.rand(B, T, dtype=torch.float64) + 0.1
        ll, mean = program(y, dt)
        torch.testing.assert_close(ll, kf(y, dt).log_likelihood, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("command", ["train", "filter", "smooth", "evaluate", "export"])
def test_every_command_has_help_with_examples(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        main([command, "--help"])
    assert stop.value.code == 0
    text = capsys.readouterr().out
    assert "examples:" in text and f"torchsde-lti {command}" in text


def test_python_dash_m_and_train_pass_hydra_flags_through(tmp_path: Path) -> None:
    res = subprocess.run(
        [sys.executable, "-m", "torchsde_lti", "train", "model=cv", "--cfg", "job"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert "name: cv" in res.stdout  # Hydra printed the composed config; nothing ran
    res = subprocess.run([sys.executable, "-m", "torchsde_lti", "--help"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and "filter" in res.stdout and "export" in res.stdout


def test_the_package_is_typed() -> None:
    assert (Path(tl.__file__).parent / "py.typed").is_file()


def test_a_real_data_run_reads_files_with_its_own_rules(cv_run: Path, csv_file: Path, tmp_path: Path) -> None:
    """A run trained on real tracks names how its files are read (data.columns, min_reports, ...):
    filter / smooth read a new file the same way, with no option given."""
    import shutil

    from omegaconf import OmegaConf

    run_dir = tmp_path / "run"
    shutil.copytree(cv_run, run_dir)
    cfg = OmegaConf.load(run_dir / ".hydra" / "config.yaml")
    cfg.data = {
        "_target_": "torchsde_lti.data.modules.TrackDataModule",
        "source": "unused.csv",
        "columns": {"id": "ship", "time": "when", "lat": "la", "lon": "lo"},
        "min_reports": 13,  # every test track has 12 reports: all dropped, and counted
        "center": True,
    }
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")
    renamed = tmp_path / "renamed.csv"
    renamed.write_text(csv_file.read_text().replace("MMSI,BaseDateTime,LAT,LON", "ship,when,la,lo", 1))
    run = load_run(run_dir)
    with pytest.raises(ValueError, match="no track of >= 13 reports is left"):
        track_states(run, read_tracks(run, renamed))
    tracks = read_tracks(run, renamed, min_reports=2)  # an argument of load_tracks overrides the run's
    assert len(tracks) == 5 and tracks.summary.as_dict()
    with pytest.raises(TypeError, match="unknown load_tracks arguments"):
        read_tracks(run, renamed, colums={})
