"""Large CPU calls and the memory allocator: glibc's default thresholds against a heap that
keeps its memory, for the issue-19 discretisation cells (float64, forward, 1 thread).

PyTorch's CPU tensors come from ``malloc``. glibc serves blocks above its mmap threshold
(adaptive, at most 32 MiB) with fresh ``mmap`` pages and returns freed heap tops to the OS
above its trim threshold, so a call that allocates tens of MB of temporaries can pay a
minor page fault per 4 KiB page it touches, every call. Setting ``MALLOC_MMAP_THRESHOLD_``
and ``MALLOC_TRIM_THRESHOLD_`` high keeps the pages in the heap between calls.

Each (cell, contestant, allocator) runs in its own process (the setting is read at process
start): warm-up calls, then timed calls; reported per process: median process CPU time,
median wall time and minor page faults per call (``getrusage``). Processes alternate
between the two settings over ``--rounds`` rounds; the table gives the median over rounds
and the range. Timing only, no pass/fail.

    python experiments/bench_allocator.py [--rounds 3] [--out experiments/results/bench_allocator.md]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
#: glibc settings that keep freed memory in the heap (16 GiB: above any block here)
KEEP_HEAP = {"MALLOC_MMAP_THRESHOLD_": str(1 << 34), "MALLOC_TRIM_THRESHOLD_": str(1 << 34)}
CELLS = (
    "shared F, n=2, B=1e5",
    "shared F, n=4, B=1e5",
    "per-element F, n=4, B=1e4",
)


def build(cell: str, contestant: str):  # noqa: ANN201 (a zero-argument closure)
    sys.path.insert(0, str(HERE))
    from bench_discretize import make_call, make_problem
    from bench_threads import per_element_call

    if cell.startswith("shared"):
        n = int(cell.split("n=")[1].split(",")[0])
        return make_call(contestant, make_problem(n, 100_000), 100_000, torch.float64, False)
    return per_element_call(contestant, 4, 10_000, torch.float64, False)


def child(cell: str, contestant: str, calls: int) -> None:
    torch.set_num_threads(1)
    fn = build(cell, contestant)
    for _ in range(3):
        fn()
    cpu, wall = [], []
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(calls):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / calls
    print(json.dumps({"cpu": statistics.median(cpu), "wall": statistics.median(wall), "faults": faults}))


def run_child(cell: str, contestant: str, keep_heap: bool, calls: int) -> dict[str, float]:
    env = {k: v for k, v in os.environ.items() if k not in KEEP_HEAP}
    if keep_heap:
        env.update(KEEP_HEAP)
    out = subprocess.run(
        [sys.executable, __file__, "--child", cell, contestant, "--calls", str(calls)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def fmt_range(values: list[float], scale: float, digits: int = 1) -> str:
    med = statistics.median(values) * scale
    return f"{med:.{digits}f} ({min(values) * scale:.{digits}f}–{max(values) * scale:.{digits}f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--calls", type=int, default=7)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "bench_allocator.md")
    ap.add_argument("--child", nargs=2, metavar=("CELL", "CONTESTANT"))
    args = ap.parse_args()
    if args.child:
        child(*args.child, args.calls)
        return
    results: dict[tuple[str, str, bool], list[dict[str, float]]] = {}
    load0 = os.getloadavg()[0]
    for r in range(args.rounds):
        for cell in CELLS:
            for contestant in ("default", "naive"):
                for keep in (False, True) if r % 2 == 0 else (True, False):
                    results.setdefault((cell, contestant, keep), []).append(
                        run_child(cell, contestant, keep, args.calls)
                    )
    lines = [
        "# Large calls and the allocator (experiments/bench_allocator.py)",
        "",
        f"torch {torch.__version__}, {platform.libc_ver()[0]} {platform.libc_ver()[1]}, 1 thread, float64, "
        f"forward; {args.rounds} rounds of one process per entry, {args.calls} calls each; load average "
        f"{load0:.2f} at start, {os.getloadavg()[0]:.2f} at end (2 shared cores). Median over rounds (range).",
        "",
        "| cell | contestant | glibc default: CPU ms | minor faults / call | kept heap: CPU ms | minor faults / call |",
        "|---|---|---|---|---|---|",
    ]
    for cell in CELLS:
        for contestant in ("default", "naive"):
            d, k = results[(cell, contestant, False)], results[(cell, contestant, True)]
            lines.append(
                f"| {cell} | {contestant} | {fmt_range([x['cpu'] for x in d], 1e3)} | "
                f"{fmt_range([x['faults'] for x in d], 1.0, 0)} | {fmt_range([x['cpu'] for x in k], 1e3)} | "
                f"{fmt_range([x['faults'] for x in k], 1.0, 0)} |"
            )
    lines += ["", "| cell | naive / default, glibc default | naive / default, kept heap |", "|---|---|---|"]
    for cell in CELLS:
        ratio = {
            keep: statistics.median(x["cpu"] for x in results[(cell, "naive", keep)])
            / statistics.median(x["cpu"] for x in results[(cell, "default", keep)])
            for keep in (False, True)
        }
        lines.append(f"| {cell} | {ratio[False]:.2f}× | {ratio[True]:.2f}× |")
    text = "\n".join(lines) + "\n"
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)


if __name__ == "__main__":
    main()
