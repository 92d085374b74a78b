"""Real trajectories at scale: load + prepare the national AIS day, memory vs reports, one training
epoch through the one path, and DDP throughput.

    python experiments/bench_tracks_scale.py          # ≈ 10 min; writes experiments/results/bench_tracks_scale.md

1. Load + prepare ``US_coastal_2020_06_30.traj`` (1,395 trajectories, 236k reports) exactly as
   ``experiment=ais_us_coastal`` does (``TrackDataModule.setup``: parse, clean, frames, vessel split,
   windows, bucketing), in a fresh process: wall seconds (after imports) and the process's peak RSS.
2. Memory vs reports: the same on the first 1/8, 1/4, 1/2 of the file's lines and on 2 and 4 copies
   of it (ids shifted): resident memory after setup minus before, per report, and a linear fit.
3. One training epoch: ``python -m torchsde_lti.train experiment=ais_us_coastal`` on (nearly) the
   whole day (``data.fractions=[0.98,0.02,0]``), float64 and float32 states, batches of 64
   windows of <= 128 reports, one thread; the second epoch's training time (no validation).
4. DDP: the same with ``trainer=ddp`` (2 CPU processes, gloo, one thread each) vs one process at
   one thread: windows (tracks) per second in the second epoch.

Every figure is the median of ``--repeat`` runs; the machine may be shared, so the table says
the load average seen. Timing callback: :class:`EpochTimer` (this file, passed by ``_target_``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import lightning.pytorch as pl

from torchsde_lti.training.outputs import write_json

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DAY = "US_coastal_2020_06_30.traj"


class EpochTimer(pl.Callback):
    """Per training epoch: seconds from its start to its last batch's end, windows and reports seen
    by this process; written to ``<out>/rank<r>.json`` when training ends."""

    def __init__(self, out: str) -> None:
        self.out = Path(out)
        self.epochs: list[dict[str, float]] = []

    def on_train_epoch_start(self, trainer: pl.Trainer, module: pl.LightningModule) -> None:
        now, cpu = time.perf_counter(), time.process_time()
        self.epochs.append({"start": now, "end": now, "cpu_start": cpu, "cpu_end": cpu, "windows": 0, "reports": 0})

    def on_train_batch_end(
        self, trainer: pl.Trainer, module: pl.LightningModule, outputs: object, batch: object, batch_idx: int
    ) -> None:
        e = self.epochs[-1]
        e["end"], e["cpu_end"] = time.perf_counter(), time.process_time()
        e["windows"] += int(batch.y.shape[0])
        e["reports"] += int(batch.mask.sum())

    def on_train_end(self, trainer: pl.Trainer, module: pl.LightningModule) -> None:
        self.out.mkdir(parents=True, exist_ok=True)
        rows = [
            {
                "seconds": e["end"] - e["start"],
                "cpu_seconds": e["cpu_end"] - e["cpu_start"],
                "windows": e["windows"],
                "reports": e["reports"],
            }
            for e in self.epochs
        ]
        (self.out / f"rank{trainer.global_rank}.json").write_text(json.dumps(rows))


SETUP = r"""
import json, sys, time
def status_mb(key):  # VmRSS now, VmHWM the peak (unlike ru_maxrss, not inherited from the parent across exec)
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) / 1024
rss_mb = lambda: status_mb("VmRSS")
from torchsde_lti.data.modules import TrackDataModule
import pymap3d, pyarrow  # noqa: F401  (imports counted before the clock starts)
before = rss_mb()
start = time.perf_counter()
dm = TrackDataModule(sys.argv[1], v_max=35.0, min_reports=5, max_len=128, batch_size=64)
dm.setup()
wall = time.perf_counter() - start
print(json.dumps({"seconds": wall, "reports_read": dm.tracks.summary.rows, "reports": dm.tracks.num_reports,
                  "windows": sum(len(w) for w in dm.windows.values()), "rss_before_mb": before,
                  "rss_after_mb": rss_mb(), "peak_rss_mb": status_mb("VmHWM"),
                  **{f"waste_{k}": v["padding_waste"] for k, v in dm.summary.splits.items()}}))
"""


def setup_run(path: Path) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-c", SETUP, str(path)], capture_output=True, text=True, env=env, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def scaled_files(folder: Path) -> list[tuple[str, Path]]:
    """The first 1/8, 1/4, 1/2 of the day's lines, the day, and 2 and 4 copies (object ids shifted)."""
    from torchsde_lti.data import locate_file

    lines = locate_file(DAY).read_text().splitlines(keepends=True)
    out = []
    for label, k in (("1/8 day", 8), ("1/4 day", 4), ("1/2 day", 2)):
        p = folder / f"day_{k}.traj"
        p.write_text("".join(lines[: len(lines) // k]))
        out.append((label, p))
    out.append(("1 day", locate_file(DAY)))
    for copies in (2, 4):
        p = folder / f"day_x{copies}.traj"
        with open(p, "w") as fh:
            for c in range(copies):
                for line in lines:
                    f = line.split(",", 12)  # shift the object id of every point: prefix the copy number
                    fh.write(line.replace(f",{f[11]},", f",{c}{f[11]},") if c else line)
        out.append((f"{copies} days", p))
    return out


def train_run(tmp: Path, label: str, overrides: list[str]) -> dict[str, float]:
    """One `python -m torchsde_lti.train` run; the second epoch of EpochTimer (all ranks combined)."""
    out = tmp / "".join(c if c.isalnum() else "_" for c in label)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), str(HERE), os.environ.get("PYTHONPATH", "")]),
        "PYTHONWARNINGS": "ignore",
    }
    cmd = [
        sys.executable,
        "-m",
        "torchsde_lti.train",
        "experiment=ais_us_coastal",
        "trainer.max_epochs=2",
        "test=false",
        "plots=false",
        "data.fractions=[0.98,0.02,0.0]",
        "num_threads=1",
        "+callbacks.timer._target_=bench_tracks_scale.EpochTimer",
        f"+callbacks.timer.out={out / 'timer'}",
        f"hydra.run.dir={out / 'run'}",
        *overrides,
    ]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp)
    if proc.returncode != 0:
        raise RuntimeError(f"{label} failed:\n{proc.stderr[-3000:]}")
    ranks = [json.loads(p.read_text()) for p in sorted((out / "timer").glob("rank*.json"))]
    epoch = [r[-1] for r in ranks]
    seconds = max(e["seconds"] for e in epoch)
    cpu_seconds = max(e["cpu_seconds"] for e in epoch)  # the busiest process's own CPU time
    windows, reports = sum(e["windows"] for e in epoch), sum(e["reports"] for e in epoch)
    return {
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "windows": windows,
        "reports": reports,
        "tracks_per_s": windows / seconds,
        "reports_per_s": reports / seconds,
        "processes": len(ranks),
        "first_epoch_s": max(r[0]["seconds"] for r in ranks),
        "wall_s": time.perf_counter() - start,
    }


def median_of(runs: list[dict[str, float]]) -> dict[str, float]:
    return {k: statistics.median(r[k] for r in runs) for k in runs[0] if isinstance(runs[0][k], (int, float))}


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", default=str(HERE / "results" / "bench_tracks_scale.md"))
    parser.add_argument("--only-training", action="store_true", help="skip the load and memory measurements")
    args = parser.parse_args(argv)
    from torchsde_lti.data import locate_file

    load_before = os.getloadavg()
    results: dict[str, object] = {"cpus": os.cpu_count()}
    lines = ["# Real trajectories at scale (the national AIS day)", ""]
    memory: list[tuple[str, dict[str, float]]] = []
    train: dict[str, dict[str, float]] = {}
    ratios: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        if not args.only_training:
            day = median_of([setup_run(locate_file(DAY)) for _ in range(args.repeat)])
            results["day"] = day
            print("load + prepare:", day, flush=True)
            for label, path in scaled_files(tmp):
                r = median_of([setup_run(path) for _ in range(max(1, args.repeat - 1))])
                memory.append((label, r))
                print(label, r, flush=True)
            import numpy as np

            x = np.array([r["reports_read"] for _, r in memory], dtype=float)
            y = np.array([r["rss_after_mb"] - r["rss_before_mb"] for _, r in memory])
            slope, icpt = np.polyfit(x, y, 1)
            r2 = 1 - ((y - (slope * x + icpt)) ** 2).sum() / ((y - y.mean()) ** 2).sum()
            results["memory"] = {"rows": memory, "mb_per_100k_reports": slope * 1e5, "intercept_mb": icpt, "r2": r2}
        # one process and DDP alternate (ABAB...), so that both see the same load on a shared
        # machine; the speed-up is the median of the paired ratios
        for dt in ("float64", "float32"):
            one_runs, ddp_runs = [], []
            for k in range(args.repeat):
                one_runs.append(train_run(tmp, f"one {dt} {k}", [f"dtype={dt}"]))
                ddp_runs.append(train_run(tmp, f"ddp {dt} {k}", [f"dtype={dt}", "trainer=ddp"]))
                print(dt, k, one_runs[-1], ddp_runs[-1], flush=True)
            train[f"1 process, {dt}"] = median_of(one_runs)
            train[f"DDP 2 processes, {dt}"] = median_of(ddp_runs)
            ratios[dt] = statistics.median(d["tracks_per_s"] / o["tracks_per_s"] for o, d in zip(one_runs, ddp_runs))
            ratios[f"{dt} cpu"] = statistics.median(
                o["cpu_seconds"] / d["cpu_seconds"] * d["windows"] / o["windows"] for o, d in zip(one_runs, ddp_runs)
            )
        results["train"], results["ddp_speedup"] = train, ratios
    load_after = os.getloadavg()
    results["loadavg"] = [load_before, load_after]

    lines += [
        f"`python experiments/bench_tracks_scale.py --repeat {args.repeat}`; medians of {args.repeat} fresh "
        f"processes; {os.cpu_count()} CPU cores, load average {load_before[0]:.1f} before / "
        f"{load_after[0]:.1f} after (a shared machine).",
        "",
        "| what | measured | target |",
        "|---|---:|---:|",
    ]
    if memory:
        lines += [
            f"| load + prepare `{DAY}` ({int(day['reports_read'])} reports -> {int(day['windows'])} windows; "
            "parse, clean, frames, vessel split, windows, buckets) | "
            f"{day['seconds']:.2f} s | ≤ 10 s |",
            f"| peak RSS of that process (torch, Lightning, pyarrow imported) | {day['peak_rss_mb']:.0f} MB | "
            "≤ 1.5 GB |",
            f"| resident memory added by the data, per 100k reports (fit over 1/8 .. 4 days, R² "
            f"{r2:.4f}) | {slope * 1e5:.1f} MB | linear |",
            "| padding waste of the bucketed batches (train / val / test) | "
            + " / ".join(
                f"{100 * day[f'waste_{k}']:.1f} %" if f"waste_{k}" in day else "–" for k in ("train", "val", "test")
            )
            + " | ≤ 10 % |",
        ]
    for label, r in train.items():
        lines.append(
            f"| one training epoch, {label}, batches of 64 windows ≤ 128 reports "
            f"({int(r['windows'])} windows, {int(r['reports'])} reports) | {r['seconds']:.1f} s "
            f"({r['tracks_per_s']:.0f} windows/s; first epoch {r['first_epoch_s']:.1f} s) | ≤ 60 s |"
        )
    for dt in ("float64", "float32"):
        if dt in ratios:
            lines.append(
                f"| DDP speed-up, 2 processes vs 1 process at 1 thread, {dt} (windows/s, wall clock; median "
                f"of {args.repeat} paired runs) | {ratios[dt]:.2f}x | ≥ 1.6x |"
            )
            lines.append(
                f"| … the same from each process's own CPU time (1 process's CPU s / busiest DDP process's "
                f"CPU s: the speed-up when each process has a core to itself) | {ratios[dt + ' cpu']:.2f}x | |"
            )
    if not memory:
        lines += [""]
        text = "\n".join(lines) + "\n"
        print(text)
        out = Path(args.out)
        out.with_name(out.stem + "_training.md").write_text(text)  # the full table stays as it was
        return text
    lines += [
        "",
        "Memory vs reports (resident memory after setup minus before, fresh process each):",
        "",
        "| input | reports | setup (s) | + RSS (MB) | peak RSS (MB) |",
        "|---|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {label} | {int(r['reports_read'])} | {r['seconds']:.2f} | {r['rss_after_mb'] - r['rss_before_mb']:.0f}"
        f" | {r['peak_rss_mb']:.0f} |"
        for label, r in memory
    ]
    text = "\n".join(lines) + "\n"
    Path(args.out).write_text(text)
    write_json(Path(args.out).with_suffix(".json"), results)  # strict JSON: NaN / inf as null
    print(text)
    return text


if __name__ == "__main__":
    main()
