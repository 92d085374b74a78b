"""The IMM smoother's time next to the IMM forward filter: 2,000 tracks x 50 reports, 3 modes.

    python experiments/imm_smoother_speed.py [--tracks 2000] [--steps 50] [--repeats 7]

The shipped ``ais-us-imm`` (3 modes, n = 4, m = 2) on synthetic random-walk tracks with
irregular gaps (20-200 s) and 10 % missing reports. Forward and smoother are timed alternately
(paired, no gradients, float64 and float32), at 1 and 2 intra-op threads; medians of the
repeats. Writes experiments/results/imm_smoother_speed.md with the command and the load average.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import torch

import torchsde_lti as tl


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", type=int, default=2000)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    g = torch.Generator().manual_seed(0)
    B, T = args.tracks, args.steps
    y = (30.0 * torch.randn(B, T, 2, generator=g, dtype=torch.float64)).cumsum(1)
    y[torch.rand(B, T, generator=g) < 0.1] = float("nan")
    dt = 20.0 + 180.0 * torch.rand(B, T, generator=g, dtype=torch.float64)
    rows = []
    for dtype in (torch.float64, torch.float32):
        imm = tl.pretrained.load("ais-us-imm").filter.to(dtype)
        yd, dtd = y.to(dtype), dt.to(dtype)
        for threads in (1, 2):
            torch.set_num_threads(threads)  # (an experiment script owns its process)
            fwd, smo = [], []
            with torch.no_grad():
                out = imm(yd, dtd)
                imm.smooth(out)  # warm-up
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    out = imm(yd, dtd)
                    t1 = time.perf_counter()
                    imm.smooth(out)
                    t2 = time.perf_counter()
                    fwd.append(t1 - t0)
                    smo.append(t2 - t1)
            f, s = statistics.median(fwd), statistics.median(smo)
            rows.append((str(dtype).removeprefix("torch."), threads, f, s, s / f))
            print(rows[-1], flush=True)
    load = os.getloadavg()
    lines = [
        "# IMM smoother vs IMM forward filter",
        "",
        f"`python experiments/imm_smoother_speed.py --tracks {B} --steps {T} --repeats {args.repeats}`: "
        f"`ais-us-imm` (3 modes, n = 4), {B} tracks x {T} reports, no gradients, medians of {args.repeats} "
        f"paired repeats. Load average at the end: {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} "
        "(a shared 2-core machine: other sessions ran meanwhile).",
        "",
        "| dtype | threads | forward (s) | smoother (s) | smoother / forward |",
        "|---|---:|---:|---:|---:|",
        *(f"| {d} | {th} | {f:.3f} | {s:.3f} | {r:.2f} |" for d, th, f, s, r in rows),
        "",
    ]
    out_path = Path(__file__).parent / "results" / "imm_smoother_speed.md"
    out_path.write_text("\n".join(lines))
    print(out_path.read_text())


if __name__ == "__main__":
    main()
