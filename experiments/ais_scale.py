"""A year of AIS, measured: out-of-core preparation and streamed training of synthetic national AIS.

    python experiments/ais_synthetic.py --out /work/tmp/ais --days 8                    # ~52 M reports, 4.6 GB
    python experiments/ais_scale.py prepare /work/tmp/ais/AIS_2024_01_01.csv --out /work/tmp/p1
    python experiments/ais_scale.py prepare '/work/tmp/ais/AIS_*.csv' --out /work/tmp/p8
    python experiments/ais_scale.py train /work/tmp/p1                                  # one epoch
    python experiments/ais_scale.py train /work/tmp/p8 --batches 200                    # RSS on all of it
    python experiments/ais_scale.py ddp /work/tmp/p1 --batches 60                       # 2 processes vs 1

Every job runs as a fresh command (``python -m torchsde_lti.prepare`` / ``... .train``) under
``nice -n 10``; the table row gives its wall time, its throughput and the peak resident memory of
its whole process tree (workers and DDP processes summed, sampled every 0.2 s from /proc: the RSS
sum, which counts the pages of torch & co. shared by several processes once per process, and the
PSS sum, which counts them once), with
the load average (``uptime``) before and after: the machine is shared with other sessions, so a
load above the number of cores means every wall-clock figure is slowed by others' work. The
throughput per core is therefore given from CPU time (user + system seconds of the job and all
its processes, sampled from /proc): reports per CPU-second, what one core does when it is the
job's alone. Rows are appended
to ``--results`` (Markdown).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return out


_TICK = os.sysconf("SC_CLK_TCK")


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of ``pid`` so far (/proc/<pid>/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICK


def _tree_memory(pid: int, cpu: dict[int, float] | None = None) -> tuple[int, int]:
    """(resident bytes, proportional set size bytes) of ``pid`` and all its descendants: the RSS sum
    counts a library page shared by k processes k times, the PSS sum once."""
    rss = pss = 0
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            if cpu is not None:
                cpu[p] = _cpu_seconds(p)
            for line in Path(f"/proc/{p}/smaps_rollup").read_text().splitlines():
                if line.startswith("Rss:"):
                    rss += int(line.split()[1]) * 1024
                elif line.startswith("Pss:"):
                    pss += int(line.split()[1]) * 1024
        except OSError:
            continue
        todo += _children(p)
    return rss, pss


def measure(cmd: list[str], env: dict[str, str] | None = None) -> dict[str, float]:
    """Run ``cmd`` (niced); wall seconds, peak RSS of its process tree (MiB), load before/after."""
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen(["nice", "-n", "10", *cmd], env={**os.environ, **(env or {})})
    peak = [0, 0]
    cpu: dict[int, float] = {}  # pid -> its CPU seconds at the last sample (the tree's forkserver workers too)
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            peak[:] = [max(a, b) for a, b in zip(peak, _tree_memory(proc.pid, cpu))]
            stop.wait(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    code = proc.wait()
    stop.set()
    sampler.join()
    if code:
        raise SystemExit(f"{shlex.join(cmd)} failed with exit code {code}")
    return {
        "wall": time.perf_counter() - t0,
        "cpu": sum(cpu.values()),  # (sampled every 0.2 s: a process's last 0.2 s may be missed)
        "rss_mib": peak[0] / 2**20,
        "pss_mib": peak[1] / 2**20,
        "load0": load0,
        "load1": os.getloadavg()[0],
    }


def _append(results: Path, header: str, row: str) -> None:
    new = not results.exists()
    with open(results, "a") as fh:
        if new:
            fh.write(header)
        fh.write(row + "\n")
    print(row, flush=True)


def prepare(args: argparse.Namespace) -> None:
    """Prepare ``source`` into ``--out`` (fresh) with ``--workers`` processes."""
    out = Path(args.out)
    if out.exists():
        raise SystemExit(f"{out} exists: give a new folder")
    cmd = [sys.executable, "-m", "torchsde_lti.prepare", f"source={args.source}", f"out={out}"]
    cmd += [f"workers={args.workers}", f"max_len={args.max_len}"]
    r = measure(cmd)
    summary = json.loads((out / "summary.json").read_text())
    load = summary["load"]
    # scatter / gather split: the last scatter manifest entry's time
    start = (out / "_manifest" / "plan.json").stat().st_mtime
    scattered = max(p.stat().st_mtime for p in (out / "_manifest" / "scatter").glob("*.json"))
    gathered = max(p.stat().st_mtime for p in (out / "_manifest" / "gather").glob("*.json"))
    size = sum(p.stat().st_size for p in (out / "windows").glob("*.parquet"))
    rows = load["rows"]
    header = (
        "| input | reports read | kept | windows | buckets | workers | wall s | scatter s | gather s | "
        "reports/s | reports per CPU-second | peak RSS / PSS MiB | dataset MB | load before / after |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---|\n"
    )
    row = (
        f"| {args.label or args.source} | {rows:,} | {load['reports']:,} | {summary['windows']:,} | {summary['buckets']} | "
        f"{args.workers} | {r['wall']:.0f} | {scattered - start:.0f} | {gathered - scattered:.0f} | "
        f"{rows / r['wall']:,.0f} | {rows / r['cpu']:,.0f} | {r['rss_mib']:.0f} / {r['pss_mib']:.0f} | "
        f"{size / 1e6:.0f} | "
        f"{r['load0']:.1f} / {r['load1']:.1f} |"
    )
    _append(Path(args.results), header, row)
    if not args.keep_scatter:
        import shutil

        shutil.rmtree(out / "_scatter", ignore_errors=True)


def _train_cmd(root: str, run: Path, batches: int | None, ddp: bool, epochs: int, workers: int) -> list[str]:
    cmd = [sys.executable, "-m", "torchsde_lti.train", "experiment=ais_us_coastal", "data=stream", f"data.root={root}"]
    cmd += [f"trainer.max_epochs={epochs}", "test=false", "plots=false", f"hydra.run.dir={run}"]
    cmd += ["trainer.enable_progress_bar=false", "+trainer.limit_val_batches=0", f"data.num_workers={workers}"]
    cmd += ["+callbacks.timer._target_=bench_tracks_scale.EpochTimer", f"+callbacks.timer.out={run}/timing"]
    if batches:
        cmd.append(f"+trainer.limit_train_batches={batches}")
    if ddp:
        cmd.append("trainer=ddp")
    return cmd


def _epochs(run: Path) -> list[list[dict[str, float]]]:
    """Per rank: the EpochTimer's epochs."""
    return [json.loads(p.read_text()) for p in sorted((run / "timing").glob("rank*.json"))]


def train(args: argparse.Namespace) -> None:
    """One streamed epoch (or ``--batches`` of it) on a prepared dataset."""
    with tempfile.TemporaryDirectory(dir=os.environ.get("TMPDIR")) as tmp:
        run = Path(tmp) / "run"
        cmd = _train_cmd(args.root, run, args.batches, False, 1, args.workers)
        r = measure(cmd, env={"PYTHONPATH": str(HERE)})
        e = _epochs(run)[0][-1]
    secs = e["seconds"]
    header = (
        "| dataset | batches | windows | reports | epoch s | reports/s | reports per CPU-second | peak RSS / PSS MiB | "
        "load before / after |\n|---|---:|---:|---:|---:|---:|---:|---:|---|\n"
    )
    row = (
        f"| {args.label or args.root} | {args.batches or 'all'} | {int(e['windows']):,} | {int(e['reports']):,} | "
        f"{secs:.0f} | {e['reports'] / secs:,.0f} | {e['reports'] / e['cpu_seconds']:,.0f} | "
        f"{r['rss_mib']:.0f} / {r['pss_mib']:.0f} | "
        f"{r['load0']:.1f} / {r['load1']:.1f} |"
    )
    _append(Path(args.results), header, row)


def ddp(args: argparse.Namespace) -> None:
    """DDP with 2 processes vs 1 process: reports per second in the second epoch (wall clock and
    CPU time), interleaved pairs, medians."""
    ratios, cpu_ratios, loads = [], [], []
    for _ in range(args.repeat):
        rates, cpus = {}, {}
        for mode in (False, True):
            with tempfile.TemporaryDirectory(dir=os.environ.get("TMPDIR")) as tmp:
                run = Path(tmp) / "run"
                r = measure(_train_cmd(args.root, run, args.batches, mode, 2, 0), env={"PYTHONPATH": str(HERE)})
                loads.append((r["load0"] + r["load1"]) / 2)
                ranks = [ep[-1] for ep in _epochs(run)]
            wall = max(e["seconds"] for e in ranks)
            cpu = max(e["cpu_seconds"] for e in ranks)
            reports = sum(e["reports"] for e in ranks)
            rates[mode], cpus[mode] = reports / wall, reports / cpu
        ratios.append(rates[True] / rates[False])
        cpu_ratios.append(cpus[True] / cpus[False])
    header = "| what | 2 processes vs 1 | load (median) |\n|---|---:|---|\n"
    _append(
        Path(args.results),
        header,
        f"| DDP speed-up, reports/s, wall clock (median of {args.repeat} pairs) | {statistics.median(ratios):.2f}x | {statistics.median(loads):.1f} |",
    )
    _append(
        Path(args.results),
        "",
        f"| ... from each process's CPU time (the speed-up with a free core per process) | {statistics.median(cpu_ratios):.2f}x | |",
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="job", required=True)
    a = sub.add_parser("prepare")
    a.add_argument("source")
    a.add_argument("--out", required=True)
    a.add_argument("--workers", type=int, default=2)
    a.add_argument("--max-len", dest="max_len", type=int, default=128)
    a.add_argument("--keep-scatter", dest="keep_scatter", action="store_true")
    b = sub.add_parser("train")
    b.add_argument("root")
    b.add_argument("--batches", type=int, default=None)
    b.add_argument("--workers", type=int, default=0, help="DataLoader workers")
    c = sub.add_parser("ddp")
    c.add_argument("root")
    c.add_argument("--batches", type=int, default=60)
    c.add_argument("--repeat", type=int, default=3)
    for s in (a, b, c):
        s.add_argument("--label", default=None)
        s.add_argument("--results", default=str(HERE / "results" / "ais_scale_runs.md"))
    args = p.parse_args()
    {"prepare": prepare, "train": train, "ddp": ddp}[args.job](args)


if __name__ == "__main__":
    main()
