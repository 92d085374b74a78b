"""The allocator's share of a large discretisation call: glibc's defaults against raised trim
and mmap thresholds, each in fresh processes, alternating (docs/how-to/threads.md).

One parameter set (a random stable F, n = 4, float64), B = 1e5 steps uniform in [0, 10),
forward without gradients, 1 thread: the median wall time of 10 calls after one warm-up call
and the median minor page faults per call (``getrusage``).

    python experiments/bench_allocator.py --rounds 4
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time

import torch
from _timing import machine_line

#: The environment of the second contestant: freed large blocks stay in the process's heap.
RAISED = {"MALLOC_MMAP_THRESHOLD_": "33554432", "MALLOC_TRIM_THRESHOLD_": "4294967296"}


def measure() -> dict[str, float]:
    import torchsde_lti as tl

    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    F = torch.randn(4, 4, generator=g, dtype=torch.float64) - 3.0 * torch.eye(4, dtype=torch.float64)
    eye = torch.eye(4, dtype=torch.float64)
    dt = 10.0 * torch.rand(100_000, generator=g, dtype=torch.float64)
    times, faults = [], []
    with torch.no_grad():
        for _ in range(11):
            f0, t0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt, time.perf_counter()
            tl.discretize(F, eye, eye, dt)
            times.append(time.perf_counter() - t0)
            faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
    return {"ms": 1e3 * statistics.median(times[1:]), "faults": statistics.median(faults[1:])}


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--measure", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure()))
        return
    runs: dict[str, list[dict[str, float]]] = {"glibc defaults": [], "raised thresholds": []}
    for _ in range(args.rounds):
        for name, extra in (("glibc defaults", {}), ("raised thresholds", RAISED)):
            env = {k: v for k, v in os.environ.items() if k not in RAISED} | extra
            out = subprocess.run(
                [sys.executable, __file__, "--measure"], env=env, capture_output=True, text=True, check=True
            )
            runs[name].append(json.loads(out.stdout.strip().splitlines()[-1]))
    torch.set_num_threads(1)  # (the measuring processes run at 1 thread; the line reports it)
    print(machine_line())
    print("| allocator | ms per call (rounds) | median | minor faults per call |")
    print("|---|---|---:|---:|")
    for name, rs in runs.items():
        ms = [r["ms"] for r in rs]
        print(
            f"| {name} | {', '.join(f'{x:.0f}' for x in ms)} | {statistics.median(ms):.0f} | "
            f"{statistics.median(r['faults'] for r in rs):.0f} |"
        )


if __name__ == "__main__":
    main()
