"""Parameter-recovery studies: simulate from a known motion model, learn it back from a wrong start.

    python experiments/recovery.py                      # cv, integrated_ou, singer, hurwitz, msd
    python experiments/recovery.py --studies cv singer  # a subset
    python experiments/recovery.py --quick              # smaller data (minutes, for a smoke check)

Each study composes ``conf/train.yaml`` with ``experiment=recovery_<model>`` (1000 tracks x
200 irregular steps, 10 % missing; msd = mass-spring-damper with known force inputs, L-BFGS) and runs the same :func:`torchsde_lti.train.train` as the
main job. Reported per study: true vs learned values, relative errors, wall time, and a check
that no logged metric was NaN. For the free 4x4 Hurwitz F the transition behaviour is
compared, ``‖expm(F dt) − expm(F* dt)‖ / ‖expm(F* dt)‖`` at several dt (F itself is only
identifiable through the transitions the data show). Writes
``experiments/results/recovery.md`` (run directories, plots and checkpoints under ``outputs/recovery/<study>/``).
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from torchsde_lti.training import format_table, train

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
RESULTS = ROOT / "experiments" / "results"
STUDIES = ("cv", "integrated_ou", "singer", "hurwitz", "msd")
DTS = (0.1, 0.5, 1.0, 2.0, 5.0)


def _nan_metrics(run_dir: Path) -> list[str]:
    """Names of logged metrics (CSV logger) that were NaN at any epoch."""
    path = run_dir / "csv" / "metrics.csv"
    bad: set[str] = set()
    if path.exists():
        with path.open() as f:
            for row in csv.DictReader(f):
                for k, v in row.items():
                    if v not in ("", None) and math.isnan(float(v)):
                        bad.add(k)
    return sorted(bad)


def _transition_errors(module: object, truth: dict) -> list[tuple[float, float]]:
    F = module.kf.sde.F.detach().to(torch.float64)  # type: ignore[attr-defined]
    F_true = truth["sde"].F.detach().to(torch.float64)
    out = []
    for dt in DTS:
        A, A_true = torch.linalg.matrix_exp(F * dt), torch.linalg.matrix_exp(F_true * dt)
        out.append((dt, float(torch.linalg.matrix_norm(A - A_true) / torch.linalg.matrix_norm(A_true))))
    return out


def run_study(name: str, quick: bool = False) -> dict:
    """Run one study; returns {"name", "wall", "table", "nan", "transition", "metrics"}."""
    out_dir = ROOT / "outputs" / "recovery" / name  # git-ignored run directories
    overrides = [f"experiment=recovery_{name}", f"output_dir={out_dir}", "trainer.enable_progress_bar=false"]
    if quick:
        overrides += ["data.num_tracks.train=200", "data.T=100", "data.T_min=100", "data.batch_size=50"]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    start = time.perf_counter()
    metrics, objects = train(cfg)
    wall = time.perf_counter() - start
    truth = objects["datamodule"].truth
    transition = _transition_errors(objects["module"], truth) if "F" in cfg.model.compare else []
    return {
        "name": name,
        "wall": wall,
        "table": metrics["table"],
        "nan": _nan_metrics(out_dir),
        "transition": transition,
        "metrics": metrics,
        "data": f"{cfg.data.num_tracks.train} train tracks x {cfg.data.T} steps, "
        f"p_missing {cfg.data.p_missing}, noise {cfg.data.noise}, {cfg.trainer.max_epochs} epochs",
    }


def report(results: list[dict]) -> str:
    lines = [
        "# Parameter recovery",
        "",
        "Command: `python experiments/recovery.py` (measured on 2 shared CPU cores; wall time",
        "includes simulation, training, validation and test).",
        "",
    ]
    for r in results:
        worst = max((row["rel_error"] for row in r["table"]), default=math.nan)
        lines += [
            f"## {r['name']}",
            "",
            f"Data: {r['data']}. Wall time {r['wall']:.0f} s. Largest relative error {100 * worst:.2f} %. "
            f"NaN in logged metrics: {', '.join(r['nan']) if r['nan'] else 'none'}.",
            "",
            format_table(r["table"]),
            "",
        ]
        if r["transition"]:
            lines += ["| dt | ‖expm(F dt) − expm(F* dt)‖ / ‖expm(F* dt)‖ |", "|---:|---:|"]
            lines += [f"| {dt:g} | {100 * e:.2f} % |" for dt, e in r["transition"]]
            lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--studies", nargs="+", default=list(STUDIES), choices=STUDIES)
    parser.add_argument("--quick", action="store_true", help="smaller data for a smoke check")
    parser.add_argument("--out", type=Path, default=RESULTS / "recovery.md")
    parser.add_argument("--append", action="store_true", help="append the new sections to --out")
    args = parser.parse_args()
    previous = args.out.read_text().rstrip() + "\n\n" if args.append and args.out.exists() else ""
    results = []
    for name in args.studies:
        r = run_study(name, quick=args.quick)
        results.append(r)
        text = report(results)
        if previous:  # keep the earlier sections, drop the repeated header
            text = previous + text.split("\n", 5)[5].lstrip("\n")
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
        print(text)


if __name__ == "__main__":
    main()
