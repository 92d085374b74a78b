"""Every shell command of README.md and docs/ (its ```bash blocks), run with tiny settings.

The Python blocks run through pytest-markdown-docs; this runs the shell ones, each as a
subprocess, as a user would type it, with its placeholders filled and made tiny:

- a training command (``python -m torchsde_lti.train ...``, ``torchsde-lti train ...``,
  ``make run``) keeps every override it has and gets a run directory under tmp; without an
  ``experiment=`` it also gets ``experiment=tiny trainer.max_epochs=1 plots=true`` (the plot step
  runs: ``model=cv truth=singer`` used to crash there), with one ``+trainer.fast_dev_run=true
  plots=false`` (a batch of training and validation) and a sweep of at most two trials; a
  shipped trajectory file over 2 MB is replaced by a slice of it (its first trajectories and a
  few after the data's first split instant);
- outputs (``-o FILE``) go to tmp; placeholders: ``/path/to/...csv``, ``/tmp/my_tracks.csv`` -> small files written here;
  ``outputs/<date>/<time>`` -> a tiny run made here (the resume command resumes it);
  ``multirun/<date>/<time>`` -> a tiny sweep; ``<same overrides>`` -> nothing; the scale page's
  ``source=data/...`` -> two small zipped MarineCadastre days written here and its ``prepared/...``
  folders -> tmp (the prepare commands run first, the stream training reads what they wrote);
- the commands that cannot run here are in :data:`NOT_RUN`, each with the reason, and
  :data:`EXPECTED_FAILURES` holds documented commands that fail today (with the issue).

A new ```bash command in the docs runs here as soon as it is written; one that cannot run must
be added to :data:`NOT_RUN` with its reason.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r"^```(?:bash|sh|shell)\n(.*?)^```", re.S | re.M)

#: Commands (regular expressions) not run here, and why.
NOT_RUN: dict[str, str] = {
    r"^make test\b": "the test suite itself, which runs this test",
    r"^pip install\b": "installs packages: the suite runs in the environment `make` installed",
    r"hydra/launcher=slurm": "needs a Slurm cluster (tests/training/test_real_data.py composes the launcher config)",
    r"trainer=ddp": "two DDP processes: tests/training/test_train.py::test_ddp_two_cpu_processes_gloo runs trainer=ddp",
    r"^python experiments/ais_(study|calibration)\.py": "the AIS study: hours of training and evaluation on the full "
    "data (tests/evaluation run its evaluation code on small tracks)",
    r"data=stream .*ckpt_path=": "resumes the stream run from a mid-epoch checkpoint, which fast_dev_run does not write: "
    "tests/data/test_stream.py::test_resume_mid_epoch_through_a_checkpoint_sees_every_window_once resumes one",
    r"^torchsde-lti export\b": "tens of seconds of torch.export tracing: tests/test_cli.py::"
    "test_export_gives_a_program_with_the_filters_values runs it (marked slow) and the wiring test runs always",
}
#: Documented commands that fail today (regular expression -> reason); they run, strict xfail.
EXPECTED_FAILURES: dict[str, str] = {}
#: Shipped files larger than this are sliced for the tiny runs.
SLICE_ABOVE = 2_000_000
TIMEOUT = 1800  # the whole plan, in one process


def _commands() -> list[tuple[str, str]]:
    """(page:line, command) of every shell command, continuation lines joined, comments dropped
    (``<same overrides>``: none)."""
    found = []
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        for block in FENCE.finditer(text):
            line = text[: block.start()].count("\n") + 2
            for k, raw in enumerate(block.group(1).replace("\\\n", " ").splitlines()):
                tokens = shlex.split(raw.replace("<same overrides>", ""), comments=True)
                if tokens:
                    found.append((f"{page.relative_to(ROOT)}:{line + k}", shlex.join(tokens)))
    return found


COMMANDS = _commands()


def _reason(command: str, table: dict[str, str]) -> str | None:
    return next((why for pattern, why in table.items() if re.search(pattern, command)), None)


# --------------------------------------------------------------------------- placeholders


def _write_ais(path: Path, vessels: int = 12, reports: int = 15) -> Path:
    """A MarineCadastre CSV of ships moving near New York, one day, irregular reports."""
    rng = np.random.default_rng(0)
    rows = ["MMSI,BaseDateTime,LAT,LON,SOG,COG,Heading"]
    for k in range(vessels):
        t = np.cumsum(rng.integers(10, 120, reports))
        lat = 40.55 + 0.01 * k + 1e-5 * t + 2e-5 * rng.standard_normal(reports)
        lon = -74.05 + 2e-5 * t + 2e-5 * rng.standard_normal(reports)
        for ti, la, lo in zip(t, lat, lon):
            stamp = np.datetime64("2020-12-01T08:00:00") + np.timedelta64(int(ti), "s")
            rows.append(f"{367000000 + k},{stamp},{la:.6f},{lo:.6f},,,")
    path.write_text("\n".join(rows) + "\n")
    return path


def _write_flights(path: Path, flights: int = 12, reports: int = 15) -> Path:
    """Flights with the columns the page names: callsign, ts, lat, lon, alt (feet)."""
    rng = np.random.default_rng(1)
    rows = ["callsign,ts,lat,lon,alt"]
    for k in range(flights):
        t = np.cumsum(rng.integers(5, 30, reports))
        for ti in t:
            stamp = np.datetime64("2020-06-30T12:00:00") + np.timedelta64(int(ti), "s")
            rows.append(f"TL{k:03d},{stamp},{39.0 + 0.002 * ti:.6f},{-77.0 + 0.003 * ti:.6f},{30000 + 5 * ti}")
    path.write_text("\n".join(rows) + "\n")
    return path


def _write_marine_cadastre_days(folder: Path, days: tuple[str, ...] = ("2022-06-01", "2022-06-02")) -> Path:
    """``folder`` with one zipped MarineCadastre day file per day (``AIS_2022_06_01.zip``, ...)."""
    import zipfile

    folder.mkdir(parents=True, exist_ok=True)
    for day in days:
        name = f"AIS_{day.replace('-', '_')}"
        csv = _write_ais(folder / f"{name}.csv", vessels=8, reports=40)
        with zipfile.ZipFile(folder / f"{name}.zip", "w") as archive:
            archive.write(csv, csv.name)
        csv.unlink()
    return folder


def _slice(name: str, tmp: Path, after: str | None, first: int = 40, extra: int = 15) -> Path:
    """The first ``first`` trajectory lines of a shipped .traj file (and ``extra`` lines with ``after``)."""
    from torchsde_lti.data import locate_file

    lines = locate_file(name).read_text().splitlines(keepends=True)
    picked = lines[:first] + ([ln for ln in lines[first:] if after in ln[:400]][:extra] if after else [])
    out = tmp / f"slice_{name}"
    out.write_text("".join(picked))
    return out


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Files the commands name, and (made when first needed) a tiny run and a tiny sweep."""
    tmp = tmp_path_factory.mktemp("docs_commands")
    return {
        "tmp": tmp,
        "ais": _write_ais(tmp / "my_tracks.csv"),
        "flights": _write_flights(tmp / "flights.csv"),
        "data": _write_marine_cadastre_days(tmp / "data"),
    }


def _python(tokens: list[str]) -> list[str]:
    """The command's argv with this interpreter for ``python`` and ``torchsde-lti``."""
    if tokens[0] == "python":
        return [sys.executable, *tokens[1:]]
    if tokens[0] == "torchsde-lti":
        return [sys.executable, "-m", "torchsde_lti", *tokens[1:]]
    return tokens


def _fill(token: str, ws: dict[str, Path]) -> str:
    """A placeholder of the docs made real (the run and the sweep are made first by the driver)."""
    token = token.replace("/path/to/my_tracks.csv", str(ws["ais"])).replace("/tmp/my_tracks.csv", str(ws["ais"]))
    token = token.replace("/path/to/flights.csv", str(ws["flights"]))
    for key in ("source=", "out=", "data.root="):  # the scale page's raw files and prepared folders
        for folder, there in (("data/", ws["data"]), ("prepared/", ws["tmp"] / "prepared")):
            if token.startswith(key + folder):
                token = f"{key}{there}/{token[len(key + folder) :]}"
    token = token.replace("outputs/<date>/<time>", str(ws["run"]))
    return token.replace("multirun/<date>/<time>", str(ws["sweep"]))


def _source_slice(overrides: list[str], ws: dict[str, Path]) -> list[str]:
    """``data.source=<slice>`` where the composed config's source is a large shipped file."""
    from hydra import compose, initialize_config_dir

    import torchsde_lti.training  # noqa: F401 - registers the config schema (train_schema) with Hydra

    plain = [
        o for o in overrides if not o.startswith(("hydra", "-", "+trainer")) and not re.search(r",|range\(|choice\(", o)
    ]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=plain)
    source = cfg.data.get("source")
    if not source or Path(str(source)).is_absolute():
        return []
    from torchsde_lti.data import locate_file

    if locate_file(str(source)).stat().st_size <= SLICE_ABOVE:
        return []
    bounds = cfg.data.get("boundaries") or []
    after = str(bounds[0])[:10] if cfg.data.get("split") == "time" and bounds else None
    return [f"data.source={_slice(str(source), ws['tmp'], after)}"]


def _tiny(args: list[str], ws: dict[str, Path], run_dir: Path, sweep: Path | None = None) -> list[str]:
    """Training arguments made tiny (module docstring)."""
    args = [a for a in args if not a.startswith(("hydra.run.dir=", "hydra.sweep.dir="))]
    extra = [f"hydra.run.dir={run_dir}", f"hydra.sweep.dir={sweep or run_dir.with_name(run_dir.name + '_sweep')}"]
    experiment = next((a.split("=", 1)[1] for a in args if a.startswith("experiment=")), None)
    if experiment is None:
        extra += ["experiment=tiny", "trainer.max_epochs=1", "plots=true"]
    else:
        extra += ["+trainer.fast_dev_run=true", "plots=false"]
        if not any(a.startswith("data.source=") for a in args):
            extra += _source_slice([a for a in args if "=" in a and not a.startswith("-")], ws)
    if "-m" in args or "--multirun" in args:
        extra += ["hydra.sweeper.n_trials=2"] if experiment in ("search", "search_imm") else []
        args = [re.sub(r"range\((\d+)\)", "range(2)", a) for a in args]
    return [*args, *extra]


def _executable(command: str, ws: dict[str, Path], index: int) -> list[str]:
    """The argv actually run for a documented command."""
    tokens = [_fill(t, ws) for t in shlex.split(command)]
    run_dir = ws["tmp"] / f"run{index}"
    for k in range(len(tokens) - 1):  # outputs go to tmp, not into the checkout
        if tokens[k] in ("-o", "--output", "--json"):
            tokens[k + 1] = str(ws["tmp"] / f"out{index}_{Path(tokens[k + 1]).name}")
    if tokens[:2] == ["make", "run"]:
        recipe = (ROOT / "Makefile").read_text().split("\nrun:", 1)[1].split("\n")[1].strip()
        assert recipe == "$(PY) -m torchsde_lti.train", f"make run's recipe changed: {recipe!r}; update this test"
        tokens = ["python", "-m", "torchsde_lti.train", *tokens[2:]]
    argv = _python(tokens)
    for head in (["-m", "torchsde_lti.train"], ["-m", "torchsde_lti", "train"]):
        if argv[1 : 1 + len(head)] == head:
            return [*argv[: 1 + len(head)], *_tiny(argv[1 + len(head) :], ws, run_dir)]
    return argv


def drive(plan_file: str) -> None:
    """Run every argv of the plan (a JSON list of {"argv", "log"}) in THIS process, one after the
    other, as ``python -m <module>`` / ``python <script>`` would (runpy), each one's output into
    its log and its exit status into the plan's ``rc``. One process: the imports (torch,
    Lightning, Hydra: seconds each time) are paid once."""
    import json
    import runpy
    import traceback

    from hydra.core.global_hydra import GlobalHydra

    plan = json.loads(Path(plan_file).read_text())
    for step in plan:
        argv = step["argv"]
        saved = os.dup(1), os.dup(2), sys.argv
        with open(step["log"], "w") as log:
            os.dup2(log.fileno(), 1)
            os.dup2(log.fileno(), 2)
            try:
                if argv[1] == "-m":
                    sys.argv = [argv[2], *argv[3:]]
                    runpy.run_module(argv[2], run_name="__main__", alter_sys=True)
                else:
                    sys.argv = argv[1:]
                    runpy.run_path(argv[1], run_name="__main__")
                step["rc"] = 0
            except SystemExit as stop:
                step["rc"] = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
            except BaseException:  # noqa: BLE001 - reported as the command's failure
                traceback.print_exc()
                step["rc"] = 1
            finally:
                sys.stdout.flush()
                sys.stderr.flush()
                os.dup2(saved[0], 1)
                os.dup2(saved[1], 2)
                sys.argv = saved[2]
                GlobalHydra.instance().clear()
        Path(plan_file).write_text(json.dumps(plan))


@pytest.fixture(scope="module")
def results(workspace: dict[str, Path]) -> dict[str, dict]:
    """Every runnable command, run by :func:`drive` in one subprocess: where -> {argv, log, rc}."""
    import json

    ws = workspace
    ws["run"], ws["sweep"] = ws["tmp"] / "main_run", ws["tmp"] / "sweep"
    setup = [
        ("setup: the tiny run", [sys.executable, "-m", "torchsde_lti.train", *_tiny([], ws, ws["run"])]),
        ("setup: the tiny sweep", [sys.executable, "-m", "torchsde_lti.train", "-m", "model=cv,integrated_ou",
                                   *_tiny([], ws, ws["tmp"] / "unused", sweep=ws["sweep"])]),
    ]  # fmt: skip
    runnable = [(w, _executable(c, ws, i)) for i, (w, c) in enumerate(COMMANDS) if _reason(c, NOT_RUN) is None]
    plan = [
        {"where": w, "argv": argv, "log": str(ws["tmp"] / f"log{i}.txt")}
        for i, (w, argv) in enumerate(setup + runnable)
    ]
    plan_file = ws["tmp"] / "plan.json"
    plan_file.write_text(json.dumps(plan))
    code = f"from tests.test_docs_commands import drive; drive({str(plan_file)!r})"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, timeout=TIMEOUT, check=False)
    done = {step["where"]: step for step in json.loads(plan_file.read_text())}
    for name, _ in setup:
        assert done[name].get("rc") == 0, Path(done[name]["log"]).read_text()[-3000:]
    return done


@pytest.mark.parametrize("where, command", COMMANDS, ids=[f"{w} {c[:60]}" for w, c in COMMANDS])
def test_documented_command_runs(where: str, command: str, results: dict[str, dict]) -> None:
    why = _reason(command, NOT_RUN)
    if why is not None:
        pytest.skip(f"not run here: {why}")
    step = results[where]
    assert "rc" in step, f"{where}: `{command}` did not finish (the driver stopped before it: see {step['log']})"
    if _reason(command, EXPECTED_FAILURES) is not None:
        assert step["rc"] != 0, f"{where}: `{command}` passes now: remove it from EXPECTED_FAILURES"
        pytest.xfail(_reason(command, EXPECTED_FAILURES))
    log = Path(step["log"]).read_text()
    assert step["rc"] == 0, f"{where}: `{command}` ran as {shlex.join(step['argv'])}:\n{log[-4000:]}"


def test_every_exception_names_a_documented_command() -> None:
    """No stale entry: each pattern of NOT_RUN and EXPECTED_FAILURES matches a command of the docs."""
    for table in (NOT_RUN, EXPECTED_FAILURES):
        for pattern in table:
            assert any(re.search(pattern, c) for _, c in COMMANDS), f"no documented command matches {pattern!r}"


def test_the_docs_have_shell_commands() -> None:
    assert len(COMMANDS) >= 20
    assert any(c.startswith("make run") for _, c in COMMANDS)
