"""The ``torchsde-lti`` command (also ``python -m torchsde_lti``): train, filter, smooth, evaluate, export.

    torchsde-lti train model=singer data.noise=1.0            # = python -m torchsde_lti.train ...
    torchsde-lti filter outputs/<date>/<time> tracks.csv -o states.parquet
    torchsde-lti smooth outputs/<date>/<time> tracks.csv -o smoothed.csv
    torchsde-lti evaluate outputs/<date>/<time> held_out.csv
    torchsde-lti export outputs/<date>/<time> -o filter.pt2

``train`` (and ``prepare``, where the package has :mod:`torchsde_lti.prepare`) hand their
arguments to the Hydra entry point unchanged; the others rebuild the trained filter of a run
directory with :func:`~torchsde_lti.runs.load_run`. Built on :mod:`argparse` (the standard
library): five subcommands with a few options each need no dependency.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import runpy
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["main"]

_RUN_HELP = "a run directory (outputs/<date>/<time>, with .hydra/config.yaml and checkpoints/)"
_FORMATS = {".csv": "csv", ".parquet": "parquet", ".pq": "parquet"}

_EXAMPLES = {
    "train": """examples:
  torchsde-lti train                                        # the main job (conf/train.yaml)
  torchsde-lti train model=singer data.noise=1.0            # any Hydra override
  torchsde-lti train experiment=ais_us_coastal data.source=my_tracks.csv
  torchsde-lti train --multirun model=cv,singer             # a sweep
  torchsde-lti train --cfg job                              # print the composed config, run nothing
The arguments go to `python -m torchsde_lti.train` unchanged; its own help: torchsde-lti train --help-hydra""",
    "prepare": """examples:
  torchsde-lti prepare source='raw/*.csv' out=prepared/
The arguments go to `python -m torchsde_lti.prepare` unchanged.""",
    "filter": """examples:
  torchsde-lti filter outputs/2026-01-01/12-00-00 tracks.csv -o states.csv
  torchsde-lti filter RUN tracks.parquet -o states.parquet --checkpoint last
  torchsde-lti filter RUN tracks.csv -o states.csv --columns id=ship,time=ts,lat=lat,lon=lon
One row per report: id, track, time, t, mean_<i>, cov_<i>_<j> (i <= j), east, north (m, the
track's frame), lat, lon; an IMM adds prob_<mode>. The file is read and cleaned with the run's
data rules (data.columns, max_gap, ...), or load_tracks' defaults for a run on simulated data.""",
    "smooth": """examples:
  torchsde-lti smooth outputs/2026-01-01/12-00-00 tracks.csv -o smoothed.parquet
The columns of `filter`, from the smoother (every report seen) instead of the filter: the RTS
smoother of a Kalman filter run, the IMM smoother (imm.smooth) of an IMM run.""",
    "evaluate": """examples:
  torchsde-lti evaluate outputs/2026-01-01/12-00-00 held_out.csv
  torchsde-lti evaluate RUN held_out.traj -o evaluation.json
Per report: the one-step predictive NLL (nats per report; all, moving and moored windows), the
share of reports inside the 2-sigma region (0.865 when calibrated), and the forecast RMSE (m)
at 5, 10 and 15 min.""",
    "export": """examples:
  torchsde-lti export outputs/2026-01-01/12-00-00 -o filter.pt2
  torchsde-lti export RUN -o filter_aoti.pt2 --package --batch 64 --length 100
Default: a torch.export program (tl.DeployedFilter, to run as it is) with a dynamic
batch and length: torch.export.load(path).module()(y, dt) -> (log_likelihood, mean). --package:
an AOTInductor package (tl.compile_package; needs a C++ compiler) for one (batch, length);
tl.load_package(path) runs it.""",
}


def _parser() -> argparse.ArgumentParser:
    import torchsde_lti

    parser = argparse.ArgumentParser(
        prog="torchsde-lti",
        description="Train learned motion models and run trained ones over tracks.",
        epilog="Each command has its own --help with examples.",
    )
    parser.add_argument("--version", action="version", version=f"torchsde_lti {torchsde_lti.__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, summary: str) -> argparse.ArgumentParser:
        return commands.add_parser(
            name,
            help=summary,
            description=summary,
            epilog=_EXAMPLES[name],
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )

    train = command("train", "train a motion model (the Hydra job python -m torchsde_lti.train)")
    train.add_argument("overrides", nargs="*", help="Hydra overrides and flags (--multirun, --cfg job, ...), passed on")
    if _has_prepare():
        prepare = command("prepare", "prepare raw track files out of core (python -m torchsde_lti.prepare)")
        prepare.add_argument("overrides", nargs="*", help="Hydra overrides, passed on")

    for name, summary in (
        ("filter", "run a trained filter over the tracks of a CSV / Parquet / .traj file"),
        ("smooth", "run a trained filter's smoother (RTS, or the IMM smoother) over the tracks of a file"),
    ):
        sub = command(name, summary)
        sub.add_argument("run", help=_RUN_HELP)
        sub.add_argument("tracks", help="the tracks: a CSV, Parquet or .traj file (as data.load_tracks reads)")
        sub.add_argument("-o", "--output", required=True, help="the states: a .csv or .parquet file")
        _checkpoint_option(sub)
        _columns_option(sub)
        sub.add_argument("--batch-size", type=int, default=256, help="tracks per filter call (default 256)")

    evaluate = command("evaluate", "score a trained filter on held-out tracks (NLL, 2-sigma coverage, forecast RMSE)")
    evaluate.add_argument("run", help=_RUN_HELP)
    evaluate.add_argument("tracks", help="held-out tracks: a CSV, Parquet or .traj file")
    evaluate.add_argument("-o", "--output", help="also write the scores to this JSON file")
    _checkpoint_option(evaluate)
    _columns_option(evaluate)

    export = command("export", "export a trained filter for serving (torch.export / AOTInductor)")
    export.add_argument("run", help=_RUN_HELP)
    export.add_argument("-o", "--output", required=True, help="the program or package file (.pt2)")
    _checkpoint_option(export)
    export.add_argument("--package", action="store_true", help="build an AOTInductor package (tl.compile_package)")
    export.add_argument("--batch", type=int, default=8, help="tracks of the example input (--package: of every call)")
    export.add_argument(
        "--length", type=int, default=32, help="reports of the example input (--package: of every call)"
    )
    return parser


def _has_prepare() -> bool:
    """Whether the package has the out-of-core preparation entry point (``torchsde_lti.prepare``)."""
    return importlib.util.find_spec("torchsde_lti.prepare") is not None


def _checkpoint_option(sub: argparse.ArgumentParser) -> None:
    sub.add_argument(
        "--checkpoint", default="best", help="best (lowest val/nll, default), last, or a checkpoint file of the run"
    )


def _columns_option(sub: argparse.ArgumentParser) -> None:
    sub.add_argument(
        "--columns",
        help="role=column pairs for the file's columns (id, time, lat, lon; alt, sog, cog), e.g. "
        "id=MMSI,time=BaseDateTime,lat=LAT,lon=LON (default: the run's data.columns, else the AIS header)",
    )


def _columns(text: str | None) -> dict[str, Any]:
    if text is None:
        return {}
    pairs = [p.split("=", 1) for p in text.split(",") if p.strip()]
    if not pairs or any(len(p) != 2 or not p[0].strip() or not p[1].strip() for p in pairs):
        raise ValueError(f"--columns must be role=column pairs separated by commas, got {text!r}")
    return {"columns": {k.strip(): v.strip() for k, v in pairs}}


def _hand_over(module: str, prog: str, args: Sequence[str]) -> int:
    """Run ``python -m <module> <args>`` in this process (Hydra reads ``sys.argv``)."""
    args = ["--help" if a == "--help-hydra" else a for a in args]
    argv = sys.argv
    sys.argv = [prog, *args]
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as stop:
        code = stop.code
        return code if isinstance(code, int) else (0 if code is None else 1)
    finally:
        sys.argv = argv
    return 0


def _write_table(columns: dict[str, Any], path: Path) -> None:
    fmt = _FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"--output {path}: give a .csv or .parquet file")
    import pyarrow as pa

    table = pa.table(columns)
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "csv":
        import pyarrow.csv

        pyarrow.csv.write_csv(table, path)
    else:
        import pyarrow.parquet

        pyarrow.parquet.write_table(table, path)


def _states(args: argparse.Namespace, smooth: bool) -> int:
    from torchsde_lti.runs import load_run, read_tracks, track_states

    run = load_run(args.run, args.checkpoint)
    tracks = read_tracks(run, args.tracks, **_columns(args.columns))
    print(tracks.summary, file=sys.stderr)
    columns = track_states(run, tracks, smooth=smooth, batch_size=args.batch_size)
    _write_table(columns, Path(args.output))
    kind = "smoothed" if smooth else "filtered"
    print(f"{len(columns['t'])} {kind} states of {len(tracks)} tracks -> {args.output}", file=sys.stderr)
    return 0


def _unit(score: str) -> str:
    """The unit of an ``evaluate`` score (training.evaluation.summary's names)."""
    if score.startswith("nll"):
        return "nats per report"
    if "cover2s" in score:
        return "share inside the 2σ region (0.865 when calibrated)"
    if score == "rmse1":
        return "m (one-step prediction)"
    if score.startswith("fc_rmse_"):
        return f"m (forecast {score.removeprefix('fc_rmse_')} min ahead)"
    return "count"


def _evaluate(args: argparse.Namespace) -> int:
    from torchsde_lti.evaluation.scores import evaluate_filter, summary
    from torchsde_lti.runs import load_run, read_tracks

    run = load_run(args.run, args.checkpoint)
    tracks = read_tracks(run, args.tracks, **_columns(args.columns))
    print(tracks.summary, file=sys.stderr)
    scores = summary(evaluate_filter(run.filter, tracks))
    scores = {k: v for k, v in scores.items() if not (isinstance(v, float) and math.isnan(v))}  # (not computed)
    lines = ["| score | value | unit |", "|---|---:|---|"]
    lines += [f"| {name} | {value:.6g} | {_unit(name)} |" for name, value in scores.items()]
    print(f"{run.run_dir} ({run.checkpoint.name}) on {args.tracks}:\n\n" + "\n".join(lines))
    if args.output:
        plain = {k: (v if math.isfinite(v) else None) for k, v in scores.items()}
        Path(args.output).write_text(json.dumps({"run": str(run.run_dir), "tracks": args.tracks, **plain}, indent=2))
    return 0


def _export(args: argparse.Namespace) -> int:
    import torch
    from torch.export import Dim

    import torchsde_lti as tl
    from torchsde_lti.runs import load_run

    run = load_run(args.run, args.checkpoint)
    kf = run.filter
    dtype = next(kf.parameters()).dtype
    m = int(kf.modes()[0].H.shape[-2])
    example = (torch.zeros(args.batch, args.length, m, dtype=dtype), torch.ones(args.batch, args.length, dtype=dtype))
    if args.package:
        program = torch.export.export(tl.DeployedFilter(kf), example)
        tl.compile_package(program, args.output)
        print(f"AOTInductor package for ({args.batch}, {args.length}) inputs -> {args.output}", file=sys.stderr)
        return 0
    B, T = Dim("B", max=1_000_000), Dim("T", max=1_000_000)
    program = torch.export.export(
        tl.DeployedFilter(kf), example, dynamic_shapes={"y": {0: B, 1: T}, "dt": {0: B, 1: T}}
    )
    torch.export.save(program, args.output)
    print(f"torch.export program (dynamic batch and length) -> {args.output}", file=sys.stderr)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``); returns the exit status.

    Bad input (a missing file, a run directory without a config, an unknown column) is
    reported on stderr in one line, with status 2.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    passed_on = argv[:1] == ["train"] or (argv[:1] == ["prepare"] and _has_prepare())
    if passed_on and argv[1:2] not in (["-h"], ["--help"]):  # (argparse would take Hydra's flags as its own)
        return _hand_over(f"torchsde_lti.{argv[0]}", f"torchsde-lti {argv[0]}", argv[1:])
    args = _parser().parse_args(argv)
    handlers = {
        "filter": lambda a: _states(a, smooth=False),
        "smooth": lambda a: _states(a, smooth=True),
        "evaluate": _evaluate,
        "export": _export,
    }
    try:
        return int(handlers[args.command](args))
    except (FileNotFoundError, ValueError, TypeError) as err:
        print(f"torchsde-lti {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
