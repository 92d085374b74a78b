"""Hostile inputs to the training side: damaged checkpoints (read_checkpoint, load_filter_weights,
train's ckpt_path), nonsense configs (train(cfg) before any work), values the JSON writer must
make strict, and two real CLI runs. Every config or checkpoint error must come before any work:
no checkpoints, no metrics.json."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import pickle
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf, open_dict

import torchsde_lti as tl
from tests.hostile.harness import Case, Finite, Raises, params, run_case
from tests.training.helpers import load_strict_json
from torchsde_lti.training import CheckpointError, load_filter_weights, read_checkpoint, train
from torchsde_lti.training.outputs import write_json

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
TINY = ["experiment=tiny", "test=false", "trainer.max_epochs=1"]
NO_ADVICE = r"weights_only"  # never tell the user to turn weights_only off


GROUPS = {"model", "truth", "data", "filter", "trainer", "logger", "callbacks", "experiment"}


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("train", overrides=list(overrides))


class Context:
    """Files and a fresh output directory per call, made once per module.

    :meth:`cfg` applies value overrides (``key=value``, ``+key=value``, ``~key``, parsed by
    Hydra's own override parser) to one composed tiny config: composing anew per case would
    cost a fifth of a second each; group overrides (``model=singer``) are composed.
    """

    def __init__(self, root: Path, good: Path) -> None:
        self.root, self.good, self._n = root, good, 0
        self.files = _damaged_files(root / "damaged", good)
        self.base = _compose("output_dir=unset", *TINY)

    def out_dir(self) -> Path:
        self._n += 1
        return self.root / f"run{self._n}"

    def cfg(self, *overrides: str, out: Path | None = None):
        out = out or self.out_dir()
        parsed = OverridesParser.create().parse_overrides(list(overrides))
        if any(o.key_or_group in GROUPS for o in parsed):
            return _compose(f"output_dir={out}", *TINY, *overrides)
        cfg = copy.deepcopy(self.base)
        with open_dict(cfg):
            cfg.output_dir = str(out)
            for o in parsed:
                if o.is_delete():
                    parent, _, leaf = o.key_or_group.rpartition(".")
                    del (OmegaConf.select(cfg, parent) if parent else cfg)[leaf]
                else:
                    OmegaConf.update(cfg, o.key_or_group, o.value(), merge=True, force_add=o.is_add())
        return cfg

    def train_before_work(self, *overrides: str) -> Any:
        """train(cfg); when it raises, assert it did so before any work, and re-raise."""
        out = self.out_dir()
        try:
            return train(self.cfg(*overrides, out=out))
        except BaseException:
            assert not (out / "checkpoints").exists() and not (out / "metrics.json").exists(), "work was done"
            raise


def _damaged_files(where: Path, good: Path) -> dict[str, Path]:
    where.mkdir(parents=True)
    data = good.read_bytes()
    raw: dict[str, bytes] = {
        "empty": b"",
        "truncated-half": data[: len(data) // 2],
        "truncated-10-bytes": data[:10],
        "truncated-last-byte": data[:-1],
        "random-bytes": np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes(),
        "text": b"epoch: 3\nstate_dict: {}\n" * 20,
        "json": json.dumps({"state_dict": {}, "epoch": 1}).encode(),
        "raw-pickle": pickle.dumps({"state_dict": {}, "epoch": 1}),
    }
    files = {k: where / f"{k}.ckpt" for k in raw}
    for k, v in raw.items():
        files[k].write_bytes(v)
    saved: dict[str, Any] = {
        "tensor": torch.zeros(3),
        "no-state-dict": {"epoch": 1, "weights": torch.zeros(2)},
        "weights-only": {"state_dict": torch.load(good, weights_only=True)["state_dict"]},
        "python-object": {"state_dict": {}, "obj": _Opaque()},
    }
    for k, v in saved.items():
        files[k] = where / f"{k}.ckpt"
        torch.save(v, files[k])
    files["directory"] = where / "a-directory.ckpt"
    files["directory"].mkdir()
    files["missing"] = where / "missing.ckpt"
    return files


class _Opaque:
    """A Python object, which a training checkpoint never holds."""


@pytest.fixture(scope="module")
def ctx(tmp_path_factory: pytest.TempPathFactory) -> Context:
    root = tmp_path_factory.mktemp("hostile_training")
    train(_compose(f"output_dir={root / 'good'}", *TINY))
    return Context(root, root / "good" / "checkpoints" / "last.ckpt")


def _filter() -> tl.KalmanFilter:
    """The filter the tiny run trains (integrated OU, 2-D) — for load_filter_weights."""
    sde = tl.models.integrated_ou(k=2.0, q=0.2, dim=2, dtype=torch.float64)
    return tl.KalmanFilter(
        sde,
        tl.models.position_observation(sde),
        torch.eye(2, dtype=torch.float64),
        P0=torch.eye(4, dtype=torch.float64),
    )


def _singer_filter() -> tl.KalmanFilter:
    sde = tl.models.singer(alpha=0.5, q=1.0, dim=2, dtype=torch.float64)
    return tl.KalmanFilter(sde, tl.models.position_observation(sde), torch.eye(2, dtype=torch.float64))


# --------------------------------------------------------------------------- damaged checkpoints

DAMAGE = {  # kind: what the message must say
    "empty": r"cannot read checkpoint .*empty\.ckpt: empty file",
    "truncated-half": r"cannot read checkpoint .*: truncated",
    "truncated-10-bytes": r"cannot read checkpoint .*: truncated",
    "truncated-last-byte": r"cannot read checkpoint .*: truncated",
    "random-bytes": r"cannot read checkpoint .*: not a checkpoint",
    "text": r"cannot read checkpoint .*: not a checkpoint",
    "json": r"cannot read checkpoint .*: not a checkpoint",
    "raw-pickle": r"cannot read checkpoint .*: not a checkpoint",
    "tensor": r"cannot read checkpoint .*: not a checkpoint \(it holds a Tensor",
    "no-state-dict": r"cannot read checkpoint .*: not a training checkpoint \(missing 'state_dict'",
    "python-object": r"cannot read checkpoint .*: it holds Python objects",
}


def _entry_points(kind: str, match: str) -> list[Case]:
    return [
        Case(f"read-{kind}", lambda c: read_checkpoint(c.files[kind]), Raises(CheckpointError, match, NO_ADVICE)),
        Case(
            f"load-weights-{kind}",
            lambda c: load_filter_weights(_filter(), c.files[kind]),
            Raises(CheckpointError, match, NO_ADVICE),
        ),
        Case(
            f"train-ckpt-{kind}",
            lambda c: c.train_before_work(f"ckpt_path={c.files[kind]}"),
            Raises(CheckpointError, match, NO_ADVICE),
        ),
    ]


CHECKPOINT_CASES = [
    *(case for kind, match in DAMAGE.items() for case in _entry_points(kind, match)),
    Case(
        "read-missing",
        lambda c: read_checkpoint(c.files["missing"]),
        Raises(FileNotFoundError, r"ckpt_path: no such checkpoint file: .*missing\.ckpt"),
    ),
    Case(
        "read-directory", lambda c: read_checkpoint(c.files["directory"]), Raises(FileNotFoundError, r"is not a file")
    ),
    Case("read-None", lambda c: read_checkpoint(None), Raises(TypeError, r"ckpt_path must be a path")),
    Case("read-int", lambda c: read_checkpoint(3), Raises(TypeError, r"ckpt_path must be a path")),
    Case(
        "read-good",
        lambda c: read_checkpoint(c.good)["epoch"],
        Finite(lambda epoch: epoch == 0 or pytest.fail(str(epoch))),
    ),
    Case(
        "load-weights-missing",
        lambda c: load_filter_weights(_filter(), c.files["missing"]),
        Raises(FileNotFoundError, r"path: no such checkpoint file"),
    ),
    Case("load-weights-good", lambda c: load_filter_weights(_filter(), c.good), Finite(lambda kf: _trained(kf))),
    Case(
        "load-weights-other-model",
        lambda c: load_filter_weights(_singer_filter(), c.good),
        Raises(CheckpointError, r"holds a different model.*missing.*alpha", NO_ADVICE),
    ),
    Case(
        "train-ckpt-missing",
        lambda c: c.train_before_work(f"ckpt_path={c.files['missing']}"),
        Raises(FileNotFoundError, r"ckpt_path: no such checkpoint file"),
    ),
    Case(
        "train-ckpt-directory",
        lambda c: c.train_before_work(f"ckpt_path={c.files['directory']}"),
        Raises(FileNotFoundError, r"ckpt_path: .* is not a file"),
    ),
    Case(
        "train-ckpt-weights-only",
        lambda c: c.train_before_work(f"ckpt_path={c.files['weights-only']}"),
        Raises(
            CheckpointError,
            r"not a training checkpoint \(missing 'epoch', 'global_step', 'loops', 'optimizer_states'",
            NO_ADVICE,
        ),
    ),
    Case(
        "train-ckpt-other-model",
        lambda c: c.train_before_work("model=singer", f"ckpt_path={c.good}"),
        Raises(CheckpointError, r"holds a different model from the one configured.*missing", NO_ADVICE),
    ),
]


def _trained(kf: tl.KalmanFilter) -> None:
    assert not torch.equal(kf.sde.k, _filter().sde.k)  # the trained k, not the start


# --------------------------------------------------------------------------- nonsense configs


def _bad(key: str, value: str, match: str | None = None, error: type[BaseException] = ValueError) -> Case:
    pattern = match or re.escape(key.lstrip("+"))
    return Case(f"config-{key}={value}", lambda c: c.train_before_work(f"{key}={value}"), Raises(error, pattern))


CONFIG_CASES = [
    _bad("trainer.max_epochs", "-1", r"trainer\.max_epochs must be an integer >= 1 \(-1 means 'train forever'"),
    _bad("trainer.max_epochs", "0"),
    _bad("trainer.max_epochs", "-5"),
    _bad("trainer.max_epochs", "2.5"),
    _bad("trainer.max_epochs", "null"),
    _bad("trainer.max_epochs", "ten"),
    _bad("+trainer.max_steps", "0", r"trainer\.max_steps"),
    _bad("+trainer.min_epochs", "5", r"trainer\.min_epochs \(5\) must be <= trainer\.max_epochs \(1\)"),
    _bad("module.optimizer.lr", "0"),
    _bad("module.optimizer.lr", "-0.1"),
    _bad("module.optimizer.lr", "nan"),
    _bad("module.optimizer.lr", "inf"),
    _bad("module.optimizer.lr", "fast"),
    _bad("+module.optimizer.weight_decay", "-1", r"module\.optimizer\.weight_decay"),
    _bad("+module.optimizer.eps", "0", r"module\.optimizer\.eps"),
    _bad("module.scheduler.T_max", "0"),
    _bad("module.scheduler.eta_min", "-1"),
    _bad("trainer.gradient_clip_val", "-1"),  # Lightning clips; a negative value would flip the gradients
    _bad("module.k_step", "-1", r"config module .*k_step must be >= 0"),
    _bad("data.batch_size", "0"),
    _bad("data.batch_size", "-3"),
    _bad("data.batch_size", "2.5"),
    _bad("data.noise", "-0.5", r"config data .*data\.noise"),
    _bad("data.noise", "nan", r"config data .*data\.noise"),
    _bad("data.T", "1", r"config data .*data\.T"),
    _bad("data.T_min", "50", r"config data .*data\.T_min"),
    _bad("data.p_missing", "1.0", r"config data .*data\.p_missing"),
    _bad("data.num_tracks.train", "0", r"config data .*data\.num_tracks\.train"),
    _bad("data.init_std", "0", r"config data .*data\.init_std"),
    _bad("+data.bogus", "1", r"config data .*bogus", TypeError),
    _bad("model.init.q", "-1", r"config .*q must be positive"),
    _bad("dtype", "float16"),
    _bad("dtype", "int64"),
    _bad("seed", "-1"),
    _bad("seed", "1.5"),
    _bad("seed", "1099511627776"),
    _bad("num_threads", "-2"),
    _bad("init_jitter", "-1"),
    _bad("init_jitter", "nan"),
    _bad("restart", "-1"),
    _bad("test", "maybe"),
    _bad("plots", "3"),
    _bad("ckpt_path", "123", r"ckpt_path must be null or the path"),
    _bad("+trainer.fast_dev_run", "-1", r"config trainer .*fast_dev_run"),
    _bad("trainer.accelerator", "abacus", r"config trainer .*abacus"),
    Case(
        "config-no-module-node",
        lambda c: c.train_before_work("~module"),
        Raises(ValueError, r"config is missing the 'module' node"),
    ),
]


# --------------------------------------------------------------------------- strict JSON


class _Pair(NamedTuple):
    a: float
    b: Any


def _written(obj: Any) -> Callable[[Context], Any]:
    def call(c: Context) -> Any:
        path = c.out_dir() / "x.json"
        write_json(path, obj)
        return load_strict_json(path)

    return call


def _equals(expected: Any):
    return lambda got: got == expected or pytest.fail(f"{got!r} != {expected!r}")


JSON_CASES = [
    Case(
        "json-nan-inf",
        _written({"a": math.nan, "b": math.inf, "c": -math.inf, "d": 1.5}),
        Finite(_equals({"a": None, "b": None, "c": None, "d": 1.5})),
    ),
    Case(
        "json-tensor-with-nan",
        _written({"t": torch.tensor([1.0, math.nan, math.inf])}),
        Finite(_equals({"t": [1.0, None, None]})),
    ),
    Case("json-tensor-0d", _written(torch.tensor(2.5, dtype=torch.float64)), Finite(_equals(2.5))),
    Case(
        "json-numpy",
        _written({"x": np.float64("nan"), "y": np.arange(3), "z": np.float32(0.5)}),
        Finite(_equals({"x": None, "y": [0, 1, 2], "z": 0.5})),
    ),
    Case(
        "json-namedtuple-path-set",
        _written(_Pair(math.nan, [Path("/a/b"), {3}])),
        Finite(_equals({"a": None, "b": ["/a/b", [3]]})),
    ),
    Case("json-non-string-keys", _written({1: "x", (2, 3): math.inf}), Finite(_equals({"1": "x", "(2, 3)": None}))),
    Case("json-bool-and-none", _written([True, False, None, 0]), Finite(_equals([True, False, None, 0]))),
    Case("json-object", _written({"o": _Opaque}), Finite(lambda got: "Opaque" in got["o"] or pytest.fail(str(got)))),
    Case("json-huge-int", _written({"n": 2**80}), Finite(_equals({"n": 2**80}))),
]


ALL = CHECKPOINT_CASES + CONFIG_CASES + JSON_CASES


@pytest.mark.parametrize("case", params(ALL))
def test_training(case: Case, ctx: Context) -> None:
    run_case(dataclasses.replace(case, call=lambda: case.call(ctx)))


def test_every_json_a_run_writes_is_strict(ctx: Context) -> None:
    """A run whose table holds NaN (no truth for R's off-diagonal, nothing learned yet) and a sweep summary."""
    from torchsde_lti.training import BestRun

    out = ctx.root / "good"
    found = sorted(out.rglob("*.json"))
    assert found, "the run wrote no JSON"
    for path in found:
        load_strict_json(path)
    summary = load_strict_json(out / "metrics.json")
    assert summary["schema_version"] == 1 and summary["status"] == "completed"
    assert any(row["true"] is None for row in summary["table"])  # NaN cells became null
    sweep = ctx.root / "sweep"
    for i, value in enumerate([1.0, math.nan]):
        write_json(sweep / str(i) / "metrics.json", {"status": "completed", "metrics": {"val/nll": value}})
    (sweep / "2").mkdir()
    write_json(sweep / "2" / "metrics.json", {"status": "interrupted", "metrics": {"val/nll": -5.0}})
    BestRun().on_multirun_end(_SweepConfig(sweep))
    best = load_strict_json(sweep / "best_run.json")
    assert best["value"] == 1.0 and len(best["runs"]) == 1  # NaN and interrupted runs do not compete


class _SweepConfig:
    def __init__(self, sweep: Path) -> None:
        self.hydra = type("H", (), {"sweep": type("S", (), {"dir": str(sweep)})()})()


def test_a_run_that_fails_says_so(ctx: Context) -> None:
    """An error during training (here a monitor that is never logged) leaves metrics.json 'failed'."""
    out = ctx.out_dir()
    with pytest.raises(Exception, match="val/bogus"):
        train(ctx.cfg("callbacks.best.monitor=val/bogus", out=out))
    summary = load_strict_json(out / "metrics.json")
    assert summary["status"] == "failed" and "val/bogus" in summary["error"]
    assert "FAILED" in (out / "results.md").read_text()


# --------------------------------------------------------------------------- the CLI


def test_cli_damaged_last_checkpoint_fails_clearly_and_leaves_the_run_alone(ctx: Context) -> None:
    """``ckpt_path=<run>/checkpoints/last.ckpt`` truncated: the CLI exits non-zero naming the file and
    the damage (no bare OSError, no advice about weights_only), before touching the run's results."""
    import shutil

    run = ctx.root / "cli-run"
    shutil.copytree(ctx.root / "good", run)
    last = run / "checkpoints" / "last.ckpt"
    last.write_bytes(last.read_bytes()[:-100])
    before = (run / "metrics.json").read_bytes()
    proc = subprocess.run(
        [sys.executable, "-m", "torchsde_lti.train", *TINY, f"ckpt_path={last}"],
        cwd=ctx.root,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
        capture_output=True,
        text=True,
        timeout=240,
    )
    output = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert re.search(rf"cannot read checkpoint {re.escape(str(last))}: truncated", output), output[-3000:]
    assert "weights_only" not in output and "OSError" not in output and "EOFError" not in output
    assert (run / "metrics.json").read_bytes() == before
