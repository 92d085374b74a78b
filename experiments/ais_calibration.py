"""Why does the 2σ coverage of the moving-ships models miss? A diagnosis on VALIDATION data only.

    python experiments/ais_calibration.py        # -> experiments/results/ais_calibration.md

For every model card of experiments/ais_study.py (both sets), on the set's validation split (the
national day's val vessels; 6 Dec of the NY week): the coverage of the one-step predictive's HPD
regions at several levels (a calibration curve: a calibrated predictive covers each level's share),
overall and on moving / moored 1-h windows; the 2σ coverage by the report's position-derived speed
and, for an IMM, by the mode the filter predicts (largest predictive weight); and the same after the
card's calibration (``calibration.cov_scale``). Never the hold-outs.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

import torchsde_lti as tl

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ais_study  # noqa: E402

from torchsde_lti.evaluation import (  # noqa: E402
    NOMINAL_2SIGMA,
    hpd_level,
    moving_reports,  # noqa: E402
    one_step_predictive,
)

LEVELS = (0.5, 0.8, NOMINAL_2SIGMA, 0.95, 0.99)
SPEEDS = (0.0, 0.25, 1.0, 3.0, 6.0, 10.0, np.inf)


def diagnose(set_name: str, samples: int = 500) -> list[str]:
    val = ais_study.set_tracks(set_name, "val")
    moving = moving_reports(val.t, val.pos[:, :2], val.offsets)
    speed = np.full(val.num_reports, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        speed[1:] = np.linalg.norm(np.diff(val.pos[:, :2], axis=0), axis=1) / np.diff(val.t)
    lines = [f"## {set_name}: validation split ({len(val)} tracks, {val.num_reports} reports)", ""]
    for name in ais_study.RUNS[set_name]:
        t0 = time.perf_counter()
        model, card = tl.pretrained.load(name)
        p = one_step_predictive(model, val)
        idx = p["index"].numpy()
        mv, sp = moving[idx], speed[idx]
        c = card.cov_scale
        lev = hpd_level(p["y"], p["w"], p["mu"], p["S"], samples=samples).numpy()
        lev_c = hpd_level(p["y"], p["w"], p["mu"], p["S"], c, samples=samples).numpy()
        lines += [
            f"### {name} ({len(idx)} reports, {mv.sum()} in moving windows; c = {' / '.join(f'{x:.4f}' for x in sorted(set(c)))})",
            "",
        ]
        lines += ["| HPD level | all | moving | moored | all, calibrated | moving, calibrated |", "|---|" + "---:|" * 5]
        for a in LEVELS:
            cells = [np.mean(x[s] <= a) for x in (lev,) for s in (slice(None), mv, ~mv)]
            cells += [np.mean(lev_c[s] <= a) for s in (slice(None), mv)]
            lines.append(f"| {100 * a:.1f} % | " + " | ".join(f"{100 * v:.1f} %" for v in cells) + " |")
        lines += ["", "| step speed (m/s) | reports | in 2σ | in 2σ, calibrated |", "|---|---:|---:|---:|"]
        for lo, hi in zip(SPEEDS[:-1], SPEEDS[1:]):
            s = (sp >= lo) & (sp < hi)
            lines.append(
                f"| [{lo:g}, {hi:g}) | {s.sum()} | {100 * np.mean(lev[s] <= NOMINAL_2SIGMA):.1f} % | "
                f"{100 * np.mean(lev_c[s] <= NOMINAL_2SIGMA):.1f} % |"
            )
        if p["w"].shape[-1] > 1:
            dom = p["w"].argmax(-1).numpy()
            lines += [
                "",
                "| predicted mode | reports | share moving | in 2σ | in 2σ, calibrated |",
                "|---|---:|---:|---:|---:|",
            ]
            for j, mode in enumerate(card.filter.get("mode_names") or range(p["w"].shape[-1])):
                s = dom == j
                lines.append(
                    f"| {mode} | {s.sum()} | {100 * mv[s].mean():.0f} % | {100 * np.mean(lev[s] <= NOMINAL_2SIGMA):.1f} % "
                    f"| {100 * np.mean(lev_c[s] <= NOMINAL_2SIGMA):.1f} % |"
                )
        lines += ["", f"({time.perf_counter() - t0:.0f} s)", ""]
        print(f"[{set_name}] {name}: {time.perf_counter() - t0:.0f} s", flush=True)
    return lines


def main() -> None:
    torch.set_num_threads(1)
    start = time.perf_counter()
    lines = [
        "# Calibration of the moving-ships models on VALIDATION data",
        "",
        "Command: `python experiments/ais_calibration.py` (the shipped cards, `tl.pretrained`; validation "
        "splits only: the national day's val vessels, 6 Dec of the NY week). HPD level a: the share of reports "
        "inside the a highest-density region of the one-step predictive (Monte Carlo for a mixture); "
        "calibrated = with the card's covariance scale c. A calibrated predictive covers a at every level.",
        "",
    ]
    for s in ("us", "ny"):
        lines += diagnose(s)
    load = os.getloadavg()
    lines.append(
        f"Runtime {time.perf_counter() - start:.0f} s on {os.cpu_count()} cores (load average {load[0]:.1f}, "
        f"{load[1]:.1f}, {load[2]:.1f}: shared machine)."
    )
    out = Path(__file__).resolve().parent / "results" / "ais_calibration.md"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
