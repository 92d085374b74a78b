"""Why the exported sequence program, run in Python (``ep.module()``), is slower than eager
``kf(y, dt)``: the same algorithm in both, timed side by side.

Three programs of bench_online.py's float64 constant-velocity filter, each against eager
``kf(y, dt)`` (1 thread, CPU-time medians, the two sides timed in alternation), at B = 1 and
B = 100 tracks of T = 200 reports:

- ``dynamic``: the shipped export (``DeployedFilter``, a dynamic batch and T): the loop as
  torch's structured scan, one step's graph called once per step;
- ``static, eager's algorithm``: an export with static (B, T) in which the call runs the
  algorithm eager runs (the associative scan at B = 1, the batch-last sequential loop at
  B = 100), traced whole (the loop unrolled): no higher-order operator at all;
- the count of aten operators each side dispatches per call (``torch.profiler``), top-level
  calls included.

If even the static program with eager's own algorithm is slower than eager, the gap is the
exported graph's runtime (every view, expand and decomposed op a separate aten call from
Python) and not the choice of algorithm.

    PYTHONPATH=$PWD python experiments/probe_export_runtime.py   # writes experiments/results/probe_export_runtime.md
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import torch

import torchsde_lti as tl
import torchsde_lti.filters.kalman as filters_kalman
import torchsde_lti.nn.kalman as nn_kalman
from torchsde_lti.filters.scan import prefers_scan

sys.path.insert(0, str(Path(__file__).parent))
from _timing import machine_line, paired_s, saved  # noqa: E402
from bench_online import F64, build_filter  # noqa: E402


def aten_calls(fn: object) -> int:
    """aten operators dispatched by one call of ``fn`` (every level of the call tree)."""
    from torch.profiler import profile

    with profile() as prof:
        fn()  # type: ignore[operator]
    return sum(e.count for e in prof.key_averages() if e.key.startswith("aten::"))


def export_eager_algorithm(kf: tl.KalmanFilter, y: torch.Tensor, dt: torch.Tensor) -> torch.export.ExportedProgram:
    """A static-shape export whose trace runs the algorithm eager chooses, unrolled (no
    structured scan): ``choose_algorithm`` and the loop's structured switch patched while it traces."""
    choose, run_alg = filters_kalman.choose_algorithm, filters_kalman._run_algorithm

    def eager_choice(algorithm: str, batch: int, T: int, device: torch.device) -> str:
        return "scan" if prefers_scan(batch, T, device) else "sequential"

    def unrolled(args, algorithm, chunk, validate_args, compiled_loop):  # type: ignore[no-untyped-def]
        if algorithm == "scan":
            return filters_kalman.chunked_scan(args, chunk, validate_args)
        return filters_kalman.sequential_filter(filters_kalman.prepare_inputs(args, validate_args), False)

    nn_kalman.choose_algorithm = filters_kalman.choose_algorithm = eager_choice  # type: ignore[assignment]
    filters_kalman._run_algorithm = unrolled  # type: ignore[assignment]
    try:
        with torch.no_grad():
            return torch.export.export(tl.DeployedFilter(kf).eval(), (y, dt))
    finally:
        nn_kalman.choose_algorithm = filters_kalman.choose_algorithm = choose  # type: ignore[assignment]
        filters_kalman._run_algorithm = run_alg  # type: ignore[assignment]


def main() -> None:
    torch.set_num_threads(1)
    from torch.export import Dim

    kf = build_filter(validate=False)
    T = 200
    g = torch.Generator().manual_seed(3)
    print(f"# exported program vs eager ({machine_line()})\n")
    print(
        "| B | program | export s | graph nodes | eager ms | exported ms | exported / eager time | aten calls eager / exported |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    with torch.no_grad():
        y2 = torch.randn(2, T, 2, generator=g, dtype=F64).cumsum(1)
        dt2 = 0.2 + torch.rand(2, T, generator=g, dtype=F64)
        Bd, Td = Dim("B", max=100_000), Dim("T", max=100_000)
        t0 = time.perf_counter()
        dynamic = torch.export.export(
            tl.DeployedFilter(kf).eval(), (y2, dt2), dynamic_shapes={"y": {0: Bd, 1: Td}, "dt": {0: Bd, 1: Td}}
        )
        t_dynamic = time.perf_counter() - t0
    torch._dynamo.reset()
    for b in (1, 100):
        y = torch.randn(b, T, 2, generator=g, dtype=F64).cumsum(1)
        dt = 0.2 + torch.rand(b, T, generator=g, dtype=F64)
        t0 = time.perf_counter()
        static = export_eager_algorithm(kf, y, dt)
        t_static = time.perf_counter() - t0
        for name, ep, t_export in (
            ("dynamic (shipped)", dynamic, t_dynamic),
            ("static, eager's algorithm", static, t_static),
        ):
            prog = ep.module()
            with torch.no_grad():
                ll, _ = prog(y, dt)
                assert torch.allclose(ll, kf(y, dt).log_likelihood, rtol=1e-10, atol=1e-8)
                t_e, t_x = paired_s(lambda y=y, dt=dt: kf(y, dt), lambda y=y, dt=dt, p=prog: p(y, dt), 9, warmup=1)
                n_e = aten_calls(lambda y=y, dt=dt: kf(y, dt))
                n_x = aten_calls(lambda y=y, dt=dt, p=prog: p(y, dt))
            print(
                f"| {b} | {name} | {t_export:.1f} | {len(ep.graph.nodes)} | {t_e * 1e3:.2f} | {t_x * 1e3:.2f} | "
                f"{t_x / t_e:.2f} | {n_e} / {n_x} |"
            )
    print(f"\nat the end: {machine_line()}")


if __name__ == "__main__":
    with saved("probe_export_runtime.md"):
        main()
