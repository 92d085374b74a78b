"""Interrupted runs: SIGTERM / SIGINT stop a run at a safe point, say so, exit non-zero, and a
resumed run (into the same directory, even twice) ends exactly where one that never stopped ends.

In-process tests signal the run from a callback at an exact batch (tests.training.helpers.SignalAt);
the CLI test runs ``python -m torchsde_lti.train`` in a subprocess, signals it from outside and
resumes it with the command its report gives (SIGINT takes the same exit path: ``128 + signal``).
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from lightning.pytorch.utilities.exceptions import SIGTERMException

from tests.training.helpers import load_strict_json
from torchsde_lti.training import RunInterrupted, train
from torchsde_lti.training.plots import epoch_rows
from torchsde_lti.training.signals import SignalGuard

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
EPOCHS = 6
COMMON = ["experiment=tiny", "test=false", f"trainer.max_epochs={EPOCHS}"]


def _cfg(out: Path, *overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("train", overrides=[f"output_dir={out}", *overrides])


def _signal_at(epoch: int, *, batch: int = 0, signum: int = signal.SIGTERM, stage: str = "train") -> list[str]:
    return [
        "+callbacks.kill._target_=tests.training.helpers.SignalAt",
        f"+callbacks.kill.epoch={epoch}",
        f"+callbacks.kill.batch={batch}",
        f"+callbacks.kill.signum={int(signum)}",
        f"+callbacks.kill.stage={stage}",
    ]


def _csv_rows(run: Path) -> list[dict[str, str]]:
    with (run / "csv" / "metrics.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _weights(run: Path) -> dict[str, torch.Tensor]:
    return torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]


def _assert_same(run: Path, reference: Path) -> None:
    a, b = _weights(reference), _weights(run)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    rows, ref_rows = _csv_rows(run), _csv_rows(reference)
    assert rows == ref_rows  # every epoch once, every logged value bit for bit
    assert sorted({int(r["epoch"]) for r in rows}) == list(range(EPOCHS))


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The run that is never interrupted."""
    run = tmp_path_factory.mktemp("reference") / "run"
    train(_cfg(run, *COMMON))
    return run


def test_interrupted_twice_then_resumed_equals_the_uninterrupted_run(tmp_path: Path, reference: Path) -> None:
    run = tmp_path / "run"
    last = run / "checkpoints" / "last.ckpt"
    # 1. SIGTERM after the first batch of epoch 2: epochs 0 and 1 are complete, epoch 2 is dropped
    with pytest.raises(RunInterrupted) as info:
        train(_cfg(run, *COMMON, *_signal_at(2)))
    assert info.value.signum == signal.SIGTERM and info.value.exit_code == 143
    assert info.value.resume_from == str(last.resolve())
    summary = load_strict_json(run / "metrics.json")
    assert summary["status"] == "interrupted" and summary["epochs"] == 2
    assert summary["interruption"]["signal"] == "SIGTERM" and summary["interruption"]["phase"] == "fit"
    assert f"ckpt_path={last.resolve()}" in summary["interruption"]["resume_command"]
    assert "INTERRUPTED by SIGTERM" in (run / "results.md").read_text()
    assert torch.load(last, weights_only=True)["epoch"] == 1
    assert {int(r["epoch"]) for r in _csv_rows(run)} == {0, 1}
    # 2. resumed in the same directory; SIGINT during the validation of epoch 4 (its only batch,
    # so epoch 4 completes and is checkpointed before the run stops)
    with pytest.raises(RunInterrupted) as info:
        train(_cfg(run, *COMMON, *_signal_at(4, signum=signal.SIGINT, stage="validation"), f"ckpt_path={last}"))
    assert info.value.signum == signal.SIGINT and info.value.exit_code == 130
    summary = load_strict_json(run / "metrics.json")
    assert summary["status"] == "interrupted" and summary["epochs"] == 5
    assert [r["epoch"] for r in summary["resumed_from"]] == [1]
    # 3. resumed to the end: the same weights, the same log, each epoch once
    _, objects = train(_cfg(run, *COMMON, f"ckpt_path={last}"))
    _assert_same(run, reference)
    summary = load_strict_json(run / "metrics.json")
    assert summary["status"] == "completed" and summary["epochs"] == EPOCHS and summary["interruption"] is None
    assert [r["epoch"] for r in summary["resumed_from"]] == [1, 4]
    # the resume point carries the best checkpoint's state after its epoch, not before it
    state = next(v for k, v in torch.load(last, weights_only=True)["callbacks"].items() if "'monitor': 'val/nll'" in k)
    assert float(state["best_model_score"]) == min(float(r["val/nll"]) for r in _csv_rows(run) if r["val/nll"])
    ref_summary = load_strict_json(reference / "metrics.json")
    assert summary["table"] == ref_summary["table"] and summary["best"] == ref_summary["best"]
    assert torch.equal(
        *(
            torch.load(r / "checkpoints" / "best.ckpt", weights_only=True)["state_dict"][
                "kf.sde.parametrizations.k.original"
            ]
            for r in (run, reference)
        )
    )
    assert [r["epoch"] for r in epoch_rows(run / "csv" / "metrics.csv")] == [float(e) for e in range(EPOCHS)]


@pytest.mark.parametrize("stage", ["train", "setup"])  # setup: before Lightning's own handler is installed
def test_interrupted_before_any_epoch_has_nothing_to_resume(tmp_path: Path, stage: str) -> None:
    run = tmp_path / "run"
    with pytest.raises(RunInterrupted) as info:
        train(_cfg(run, *COMMON, *_signal_at(0, stage=stage)))
    assert info.value.phase == "fit"
    assert info.value.resume_from is None
    summary = load_strict_json(run / "metrics.json")
    assert summary["status"] == "interrupted" and summary["epochs"] == 0
    assert summary["interruption"]["resume_checkpoint"] is None
    assert "nothing to resume" in str(info.value) and "run again" in (run / "results.md").read_text()


def test_interrupted_while_testing_resumes_to_the_same_report(tmp_path: Path) -> None:
    """A signal during the test (after the last epoch): the resumed run trains nothing, tests again,
    and reports what a run that never stopped reports (epoch metrics kept from the first process)."""
    with_test = [*COMMON[:1], f"trainer.max_epochs={EPOCHS}", "test=true"]
    train(_cfg(tmp_path / "reference", *with_test))
    run = tmp_path / "run"
    with pytest.raises(RunInterrupted) as info:
        train(_cfg(run, *with_test, *_signal_at(0, stage="test")))
    assert info.value.phase == "test"
    assert load_strict_json(run / "metrics.json")["epochs"] == EPOCHS
    train(_cfg(run, *with_test, f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}"))
    got, ref = load_strict_json(run / "metrics.json"), load_strict_json(tmp_path / "reference" / "metrics.json")
    drop = {"wall_time"}
    assert {k: v for k, v in got["metrics"].items() if k not in drop} == {
        k: v for k, v in ref["metrics"].items() if k not in drop
    }
    assert got["table"] == ref["table"] and got["best"] == ref["best"] and got["status"] == "completed"
    assert _csv_rows(run) == _csv_rows(tmp_path / "reference")


def test_interrupted_while_building_says_so(tmp_path: Path) -> None:
    run = tmp_path / "run"
    with pytest.raises(RunInterrupted) as info:
        train(_cfg(run, *COMMON, "data._target_=tests.training.helpers.SignalOnInit"))
    assert info.value.phase == "setup" and info.value.exit_code == 143
    summary = load_strict_json(run / "metrics.json")
    assert summary["status"] == "interrupted" and summary["interruption"]["phase"] == "setup" and summary["epochs"] == 0


def test_signal_guard_records_stops_between_phases_and_restores_handlers() -> None:
    before = {signum: signal.getsignal(signum) for signum in (signal.SIGTERM, signal.SIGINT)}
    with SignalGuard() as guard:
        guard.phase = "plots"
        os.kill(os.getpid(), signal.SIGTERM)  # recorded; the phase finishes its work
        time.sleep(0.01)
        assert guard.received == signal.SIGTERM and guard.received_during == "plots"
        with pytest.raises(SIGTERMException):
            guard.stop_if_received()
    with SignalGuard() as guard:  # building the data and the model: nothing to keep, stop at once
        with pytest.raises(SIGTERMException):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)  # the handler runs at the next bytecode
        assert guard.received == signal.SIGTERM and guard.received_during == "setup"
    with SignalGuard() as guard:  # Ctrl-C: recorded as SIGINT, re-sent as SIGTERM (Lightning's graceful path)
        guard.phase = "fit"
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.01)
        assert guard.received == signal.SIGINT and guard.received_during == "fit"
        with pytest.raises(KeyboardInterrupt):  # a second Ctrl-C stops at once
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)
    assert {signum: signal.getsignal(signum) for signum in before} == before


# --------------------------------------------------------------------------- the CLI


def _cli(args: list[str], cwd: Path) -> subprocess.Popen:
    env = {
        **os.environ,
        "PYTHONWARNINGS": "ignore",
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    return subprocess.Popen(
        [sys.executable, "-m", "torchsde_lti.train", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def test_cli_sigterm_exits_143_and_resumes_in_the_same_directory(tmp_path: Path, reference: Path) -> None:
    run = tmp_path / "run"
    slow = ["+callbacks.slow._target_=tests.training.helpers.Sleep", "+callbacks.slow.seconds=0.15"]
    proc = _cli([*COMMON, *slow, f"hydra.run.dir={run}"], tmp_path)
    deadline = time.monotonic() + 240
    while not (run / "checkpoints" / "last.ckpt").exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=240)
    assert proc.returncode == 143, out[-3000:]
    summary = load_strict_json(run / "metrics.json")
    assert summary["status"] == "interrupted" and 1 <= summary["epochs"] < EPOCHS
    log = (run / "train.log").read_text()
    assert "received SIGTERM" in log and "interrupted by SIGTERM" in log
    # resume exactly as results.md says: no hydra.run.dir, the run continues in its own directory
    command = summary["interruption"]["resume_command"].split()
    assert command[1:3] == ["-m", "torchsde_lti.train"]
    proc = _cli(command[3:], tmp_path)
    out, _ = proc.communicate(timeout=240)
    assert proc.returncode == 0, out[-3000:]
    assert not (tmp_path / "outputs").exists()  # no new run directory
    _assert_same(run, reference)
    summary = load_strict_json(run / "metrics.json")
    assert summary["status"] == "completed" and len(summary["resumed_from"]) == 1
    log = (run / "train.log").read_text()  # the log of both processes, the config and every epoch
    assert "resuming from" in log and "config:" in log
    assert all(f"epoch {e}/{EPOCHS - 1}:" in log for e in range(EPOCHS))  # numbered as the progress bar
    assert "`Trainer.fit` stopped" in log  # Lightning's own records reach train.log too
