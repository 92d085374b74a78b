"""``torch.compile(kf)``: the first call's time with a cold inductor cache (issue 19's target:
≤ 60 s at B = 1, T = 200), and the log-likelihood against eager.

Run it with a fresh cache directory (the FX graph cache is switched off here)::

    TORCHINDUCTOR_CACHE_DIR=$(mktemp -d) PYTHONPATH=$PWD python experiments/probe_compile_cold.py  # -> results/probe_compile_cold.txt
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import torch
import torch._inductor.config as inductor_config

sys.path.insert(0, str(Path(__file__).parent))
from _timing import machine_line, saved  # noqa: E402
from bench_deploy import data, make_filter  # noqa: E402


def main() -> None:
    inductor_config.fx_graph_cache = False
    torch.set_num_threads(1)
    kf = make_filter()
    y, dt = data(1, 200, 0)
    compiled = torch.compile(kf)
    t0 = time.perf_counter()
    out = compiled(y, dt)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    compiled(y, dt)
    second = time.perf_counter() - t0
    err = float((out.log_likelihood - kf(y, dt).log_likelihood).detach().abs().max())
    print(
        f"{machine_line()}: torch.compile(kf) first call (B = 1, T = 200, "
        f"cold cache) {first:.1f} s, second call {second * 1e3:.1f} ms, |log-likelihood − eager| {err:.1e}"
    )


if __name__ == "__main__":
    with saved("probe_compile_cold.txt"):
        main()
