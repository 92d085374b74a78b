"""Summarise a Hydra --multirun sweep of the main job into one table and one plot.

    python -m torchsde_lti.train --multirun model=cv,integrated_ou,singer data.noise=0.1,1.0
    python experiments/collect_sweep.py multirun/<date>/<time>

Reads every run directory of the sweep (``.hydra/overrides.yaml`` and the ``metrics.json``
that :func:`torchsde_lti.train.train` writes) and writes ``summary.md`` (one row per run:
overrides, val/nll, test/nll, largest relative parameter error, per-parameter errors, wall
time) and ``summary.png`` (largest parameter error per run) into the sweep directory.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import yaml


def collect(sweep_dir: Path) -> list[dict]:
    """One record per completed run: {"run", "overrides", "model", "noise", "metrics", "param_errors", "wall_time"}
    (metrics.json's keys; runs whose ``status`` is not "completed" are skipped)."""
    rows = []
    for run in sorted(sweep_dir.iterdir(), key=lambda p: (len(p.name), p.name)):
        metrics_file = run / "metrics.json"
        if not (run.is_dir() and metrics_file.exists()):
            continue
        overrides_file = run / ".hydra" / "overrides.yaml"
        overrides = yaml.safe_load(overrides_file.read_text()) if overrides_file.exists() else []
        m = json.loads(metrics_file.read_text())
        if m.get("status", "completed") != "completed":  # interrupted, failed or still running: no results
            print(f"skipping {run.name}: status {m['status']}")
            continue
        rows.append({"run": run.name, "overrides": " ".join(overrides or []), **m})
    return rows


def _fmt(x: float | None, pct: bool = False) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return ""
    return f"{100 * x:.2f} %" if pct else f"{x:.4g}"


def _seconds(x: float | None) -> str:
    return f"{x:.1f}" if isinstance(x, (int, float)) else ""


def summary_table(rows: list[dict]) -> str:
    lines = [
        "| run | overrides | val/nll | test/nll | max param error | per-parameter errors | wall (s) |",
        "|---|---|---:|---:|---:|---|---:|",
    ]
    for r in rows:
        errs = {k: v for k, v in r.get("param_errors", {}).items() if v is not None}  # null: not finite
        worst = max(errs.values()) if errs else None
        per = ", ".join(f"{k} {100 * v:.1f}%" for k, v in errs.items())
        met = r.get("metrics", {})
        lines.append(
            f"| {r['run']} | {r['overrides']} | {_fmt(met.get('val/nll'))} | {_fmt(met.get('test/nll'))} | "
            f"{_fmt(worst, pct=True)} | {per} | {_seconds(r.get('wall_time'))} |"
        )
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [r["overrides"] or r["run"] for r in rows]
    worst = [
        max((v for v in r["param_errors"].values() if v is not None), default=math.nan) * 100
        if r.get("param_errors")
        else math.nan
        for r in rows
    ]
    fig, ax = plt.subplots(figsize=(max(5, 0.9 * len(rows) + 2), 4))
    if any(w > 0 for w in worst):  # (NaN compares False) a truth to compare with
        ax.bar(range(len(rows)), worst)
        ax.set_ylabel("largest relative parameter error (%)")
        ax.set_yscale("log")
    else:  # real data: no truth, the validation NLL
        ax.bar(range(len(rows)), [(r.get("metrics") or {}).get("val/nll", math.nan) for r in rows])
        ax.set_ylabel("val/nll")
    ax.set_xticks(range(len(rows)), labels, rotation=30, ha="right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweep_dir", type=Path, help="the Hydra sweep directory (hydra.sweep.dir)")
    parser.add_argument("--out", type=Path, default=None, help="also write the table here (markdown)")
    args = parser.parse_args()
    rows = collect(args.sweep_dir)
    if not rows:
        raise SystemExit(f"no finished runs (metrics.json) under {args.sweep_dir}")
    text = f"# Sweep {args.sweep_dir}\n\n{summary_table(rows)}\n"
    (args.sweep_dir / "summary.md").write_text(text)
    plot(rows, args.sweep_dir / "summary.png")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
