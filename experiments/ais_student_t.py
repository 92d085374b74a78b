"""Gaussian vs Student-t observation noise (issue 39 item 2): each train set's best single, on VALIDATION splits.

    python experiments/ais_student_t.py --train --sets us ny   # the t runs (the one training path) -> outputs/tails/<name>-t
    python experiments/ais_student_t.py --sets us ny           # score -> results/ais_student_t.{md,json}
    python experiments/ais_student_t.py --imm --train --sets us ny   # the one-step IMM's t versions (ν shared / per mode)
    python experiments/ais_student_t.py --imm --sets us ny           # -> results/ais_student_t_imm.{md,json}

The Gaussian model is the shipped best single of each train set (``results/ais_selection.json``,
selected on validation); its t version is trained by ``python -m torchsde_lti.train`` with the
same overrides plus ``filter/noise=student_t module.k_step_weight=0`` (the k-step term of the
training loss is a Gaussian density: the t filter is trained on its exact one-step predictive
alone) and loaded by ``torchsde_lti.runs.load_run`` (best checkpoint on val/nll). Both are scored with
``torchsde_lti.evaluation`` on the validation split of every listed set (never a reserved file):
NLL all / moving, 2σ (86.5 % HPD) coverage of the predictive each filter has (the t's from the F
distribution), forecast RMSE at 5 / 10 / 15 min, and the paired vessel bootstrap (t − Gaussian).
Coverage is reported uncalibrated (cov_scale 1, the question being whether it travels without a
per-set recalibration) and, for the Gaussian, with its card's calibration (fitted on its own
train set's validation split).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

import torchsde_lti as tl
from torchsde_lti.evaluation import evaluate_filter, paired_bootstrap, predictive_dof, summary
from torchsde_lti.runs import load_run

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import ais_study  # noqa: E402  (the study's sets, splits and runs)

RESULTS = HERE / "results"
T_OVERRIDES = ["filter/noise=student_t", "module.k_step_weight=0"]
#: The like-for-like Gaussian: the same training loss as the t's (no k-step term).
G0_OVERRIDES = ["module.k_step_weight=0"]
VARIANTS = {"t": T_OVERRIDES, "g0": G0_OVERRIDES}
#: ``--imm``: the t versions of each set's shipped one-step Gaussian IMM (``ais-<set>-imm-1step``,
#: trained on the one-step loss alone), by its card's command + these: one ν shared by the modes
#: (``t``) or a ν per mode (``tm``).
IMM_VARIANTS = {"tm": ["filter/noise=student_t_modes"], "t": ["filter/noise=student_t"]}
METRICS = ("nll", "nll_moving", "cover2s", "cover2s_moving", "fc_rmse_5", "fc_rmse_10", "fc_rmse_15")


def best_single(train_set: str) -> str:
    return str(json.loads(ais_study.SELECTION.read_text())[train_set]["best_single"])


def imm_name(train_set: str) -> str:
    return f"ais-{train_set}-imm-1step"


def train(sets: list[str], runs: Path, imm: bool = False) -> None:
    """The t version of each set's best single (the study's overrides + :data:`T_OVERRIDES`) and
    its like-for-like Gaussian (+ :data:`G0_OVERRIDES`), as ``<runs>/<name>-t`` and ``-g0``;
    ``imm``: the :data:`IMM_VARIANTS` of each set's one-step IMM (its card's command), as
    ``<runs>/<name>-t`` and ``-tm``."""
    for s in sets:
        name = imm_name(s) if imm else best_single(s)
        base = tl.pretrained.card(name).command.split()[3:] if imm else [*ais_study.RUNS[s][name], "plots=false"]
        for variant, extra in (IMM_VARIANTS if imm else VARIANTS).items():
            run = runs / f"{name}-{variant}"
            if ais_study.completed(run):
                continue
            cmd = [sys.executable, "-m", "torchsde_lti.train", *base, *extra, f"hydra.run.dir={run}"]
            print("$", " ".join(cmd[1:]), flush=True)
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
            print(f"  {time.perf_counter() - t0:.0f} s", flush=True)


def score(sets: list[str], runs: Path, samples: int) -> dict[str, Any]:
    models: dict[str, tuple[str, Any, Any, Any]] = {}
    for s in sets:
        name = best_single(s)
        pre = tl.pretrained.load(name)
        t_filter = load_run(runs / f"{name}-t").filter
        g0 = runs / f"{name}-g0"
        models[s] = (name, pre, t_filter, load_run(g0).filter if g0.is_dir() else None)
    out: dict[str, Any] = {"cells": {}, "dof": {}}
    for s, (_, _, t_filter, _) in models.items():
        out["dof"][s] = float(predictive_dof(t_filter))  # type: ignore[arg-type]
    for e in sets:
        t0 = time.perf_counter()
        val = ais_study.set_tracks(e, "val")
        for s, (name, pre, t_filter, g0_filter) in models.items():
            g = evaluate_filter(pre.filter, val, samples=samples)
            gc = evaluate_filter(pre.filter, val, samples=samples, cov_scale=pre.card.cov_scale)
            t = evaluate_filter(t_filter, val, samples=samples)
            out["cells"][f"{s}->{e}"] = {
                "model": name,
                "gaussian": summary(g),
                "gaussian_calibrated": summary(gc),
                "cov_scale": pre.card.cov_scale,
                "student_t": summary(t),
                "t_minus_gaussian": paired_bootstrap(t, g, metrics=METRICS),
            }
            if g0_filter is not None:  # the Gaussian trained with the t's loss (no k-step term)
                g0 = evaluate_filter(g0_filter, val, samples=samples)
                out["cells"][f"{s}->{e}"]["gaussian_one_step"] = summary(g0)
                out["cells"][f"{s}->{e}"]["t_minus_gaussian_one_step"] = paired_bootstrap(t, g0, metrics=METRICS)
        print(f"[{e} val] {len(val)} tracks, {val.num_reports} reports, {time.perf_counter() - t0:.0f} s", flush=True)
    return out


def score_imm(sets: list[str], runs: Path, samples: int) -> dict[str, Any]:
    """``--imm``: each set's one-step Gaussian IMM (shipped; uncalibrated and with its card's
    calibration), its shared-ν t (``<runs>/<name>-t``) and its ν-per-mode t (``-tm``) on every
    validation split; paired vessel bootstraps tm − G and tm − t."""
    models = {s: (tl.pretrained.load(imm_name(s)), *(load_run(runs / f"{imm_name(s)}-{v}").filter for v in ("t", "tm")))
              for s in sets}  # fmt: skip
    out: dict[str, Any] = {"cells": {}, "dof": {}}
    for s, (_, t_filter, tm_filter) in models.items():
        out["dof"][s] = {v: predictive_dof(f).tolist() for v, f in (("t", t_filter), ("tm", tm_filter))}  # type: ignore[union-attr,arg-type]
    for e in sets:
        t0 = time.perf_counter()
        val = ais_study.set_tracks(e, "val")
        for s, (pre, t_filter, tm_filter) in models.items():
            rec = {
                "g": evaluate_filter(pre.filter, val, samples=samples),
                "gc": evaluate_filter(pre.filter, val, samples=samples, cov_scale=pre.card.cov_scale),
                "t": evaluate_filter(t_filter, val, samples=samples),
                "tm": evaluate_filter(tm_filter, val, samples=samples),
            }
            cell: dict[str, Any] = {"model": imm_name(s), "cov_scale": pre.card.cov_scale}
            cell.update({k: summary(r) for k, r in rec.items()})
            cell["tm_minus_g"] = paired_bootstrap(rec["tm"], rec["g"], metrics=METRICS)
            cell["tm_minus_t"] = paired_bootstrap(rec["tm"], rec["t"], metrics=METRICS)
            out["cells"][f"{s}->{e}"] = cell
        print(f"[{e} val] {len(val)} tracks, {val.num_reports} reports, {time.perf_counter() - t0:.0f} s", flush=True)
    return out


def markdown_imm(res: dict[str, Any], cmd: str, seconds: float, load: str) -> str:
    """The ``--imm`` tables: one row per train → validation cell and model (G, G·c, t, tm)."""
    dofs = "; ".join(
        f"{s}: shared {float(d['t']):.2f}, per mode " + " / ".join(f"{v:.2f}" for v in d["tm"])
        for s, d in res["dof"].items()
    )
    lines = [
        "# One-step IMMs: Gaussian vs Student-t with one ν vs a ν per mode, validation splits",
        "",
        f"Command: `{cmd}` ({seconds:.0f} s; load average {load}, 2 shared cores). Models: the shipped"
        " `ais-<set>-imm-1step` (G; G·c with its card's calibration c) and its t versions trained by the"
        f" card's command + `{' '.join(IMM_VARIANTS['t'])}` (t) or `{' '.join(IMM_VARIANTS['tm'])}` (tm)."
        f" Learned ν (modes moored / manoeuvring / underway): {dofs}. Coverage: share of reports in the"
        " 86.5 % HPD region of the one-step predictive (target 84–89 %), uncalibrated except G·c.",
        "",
        "| train → val set | filter | NLL | NLL mov. | cover | cover mov. | RMSE 5 (m) | RMSE 10 (m) | RMSE 15 (m) |",
        "|---|---|" + "---:|" * 7,
    ]
    for cell, r in res["cells"].items():
        for k, label in (("g", "G"), ("gc", "G·c"), ("t", "t (one ν)"), ("tm", "tm (ν per mode)")):
            x = r[k]
            lines.append(
                f"| {cell} | {label} | {x['nll']:.3f} | {x['nll_moving']:.3f} | {100 * x['cover2s']:.1f} % "
                f"| {100 * x['cover2s_moving']:.1f} % | {x['fc_rmse_5']:.0f} | {x['fc_rmse_10']:.0f} | {x['fc_rmse_15']:.0f} |"
            )
    lines += [
        "",
        "Paired vessel bootstrap (95 % intervals): Δ = tm − G and tm − t.",
        "",
        "| train → val set | Δ | NLL | NLL mov. | cover (pp) | cover mov. (pp) | RMSE 5 (m) | RMSE 10 (m) | RMSE 15 (m) |",
        "|---|---|" + "---:|" * 7,
    ]
    for cell, r in res["cells"].items():
        for k, label in (("tm_minus_g", "tm − G"), ("tm_minus_t", "tm − t")):
            d = r[k]
            cov = {m: {q: 100 * v for q, v in d[m].items()} for m in ("cover2s", "cover2s_moving")}
            lines.append(
                f"| {cell} | {label} | {_interval(d['nll'], 3)} | {_interval(d['nll_moving'], 3)} "
                f"| {_interval(cov['cover2s'], 1)} | {_interval(cov['cover2s_moving'], 1)} "
                f"| {_interval(d['fc_rmse_5'], 0)} | {_interval(d['fc_rmse_10'], 0)} | {_interval(d['fc_rmse_15'], 0)} |"
            )
    return "\n".join(lines) + "\n"


def _interval(x: dict[str, float], digits: int) -> str:
    """A paired difference and its interval: ``+d [lo, hi]``."""
    return f"{x['delta']:+.{digits}f} [{x['lo']:+.{digits}f}, {x['hi']:+.{digits}f}]"


def markdown(res: dict[str, Any], cmd: str, seconds: float, load: str) -> str:
    lines = [
        "# Gaussian vs Student-t observation noise: best single per train set, validation splits",
        "",
        f"Command: `{cmd}` ({seconds:.0f} s; load average {load}, 2 shared cores). t runs:"
        f" the study's overrides + `{' '.join(T_OVERRIDES)}`. Learned ν: "
        + ", ".join(f"{s} {v:.2f}" for s, v in res["dof"].items())
        + ". Coverage: share of reports in the 86.5 % HPD region of the one-step predictive"
        " (target 84–89 %); G = Gaussian uncalibrated, G·c = with its card's calibration c,"
        " t = Student-t uncalibrated. Δ = t − G (paired vessel bootstrap 95 % interval).",
        "",
        "| train → val set | model | NLL G | NLL t | Δ NLL [95 %] | NLL mov. G | NLL mov. t "
        "| cover G | cover G·c | cover t | cover mov. G·c | cover mov. t | RMSE 5 G | RMSE 5 t | RMSE 15 G | RMSE 15 t |",
        "|---|---|" + "---:|" * 14,
    ]
    for cell, r in res["cells"].items():
        g, gc, t, d = r["gaussian"], r["gaussian_calibrated"], r["student_t"], r["t_minus_gaussian"]["nll"]
        lines.append(
            f"| {cell} | {r['model']} | {g['nll']:.3f} | {t['nll']:.3f} | {_interval(d, 3)} "
            f"| {g['nll_moving']:.3f} | {t['nll_moving']:.3f} "
            f"| {100 * g['cover2s']:.1f} % | {100 * gc['cover2s']:.1f} % | {100 * t['cover2s']:.1f} % "
            f"| {100 * gc['cover2s_moving']:.1f} % | {100 * t['cover2s_moving']:.1f} % "
            f"| {g['fc_rmse_5']:.0f} | {t['fc_rmse_5']:.0f} | {g['fc_rmse_15']:.0f} | {t['fc_rmse_15']:.0f} |"
        )
    g0_cells = {c: r for c, r in res["cells"].items() if "gaussian_one_step" in r}
    if g0_cells:
        lines += [
            "",
            "Like for like: the Gaussian G1 retrained with the t's loss (`module.k_step_weight=0`, one-step NLL"
            " only); Δ = t − G1 with the paired vessel bootstrap 95 % interval.",
            "",
            "| train → val set | NLL G1 | Δ NLL | cover G1 | cover mov. G1 | RMSE 5 G1 | RMSE 15 G1 "
            "| Δ RMSE 5 (m) | Δ RMSE 10 (m) | Δ RMSE 15 (m) |",
            "|---|" + "---:|" * 9,
        ]
        for cell, r in g0_cells.items():
            g1, d = r["gaussian_one_step"], r["t_minus_gaussian_one_step"]
            lines.append(
                f"| {cell} | {g1['nll']:.3f} | {_interval(d['nll'], 3)} | {100 * g1['cover2s']:.1f} % "
                f"| {100 * g1['cover2s_moving']:.1f} % | {g1['fc_rmse_5']:.0f} | {g1['fc_rmse_15']:.0f} "
                f"| {_interval(d['fc_rmse_5'], 0)} | {_interval(d['fc_rmse_10'], 0)} | {_interval(d['fc_rmse_15'], 0)} |"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", action="store_true", help="train the missing t runs first")
    parser.add_argument("--imm", action="store_true", help="the one-step IMMs: Gaussian, shared ν, ν per mode")
    parser.add_argument("--runs", default="outputs/tails", help="the t runs, <runs>/<name>-t")
    parser.add_argument("--sets", nargs="*", default=["us", "ny"], help="train sets (and validation sets)")
    parser.add_argument("--samples", type=int, default=500, help="Monte Carlo draws of a mixture HPD test")
    parser.add_argument("--out", default=str(RESULTS / "ais_student_t"), help="results file stem")
    args = parser.parse_args(argv)
    runs = Path(args.runs)
    if args.train:
        train(args.sets, runs, args.imm)
        return {}
    t0 = time.perf_counter()
    with torch.no_grad():
        res = (score_imm if args.imm else score)(args.sets, runs, args.samples)
    seconds = time.perf_counter() - t0
    load = " ".join(Path("/proc/loadavg").read_text().split()[:3])
    cmd = "python experiments/ais_student_t.py " + " ".join(sys.argv[1:] if argv is None else argv)
    stem = args.out + ("_imm" if args.imm else "")
    text = (markdown_imm if args.imm else markdown)(res, cmd.strip(), seconds, load)
    Path(stem + ".json").write_text(json.dumps(res, indent=1))
    Path(stem + ".md").write_text(text)
    print(text)
    return res


if __name__ == "__main__":
    main()
