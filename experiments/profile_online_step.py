"""Where one online step's time goes (B = 1, constant velocity in 2-D, float64, 1 thread).

Eager: torch.profiler's top-level aten calls and the CPU time of each part of ``kf.step``
(the per-version cache's key, the closed-form discretisation of the one gap of the nilpotent
CV model, ``filters.kalman_step``), and of what the step does not run each time (the model's
matrices, once per parameter version; core's discretisation, which a model whose F has no
closed form takes).
AOTInductor: the whole step's package, a package of ``filters.kalman_step`` alone (A, Q
given: no discretisation inside), each called through the package's Python wrapper and
through its C++ loader directly (``.loader.run``), against filterpy's predict + update, all
timed in alternation with filterpy (CPU time, medians).

    PYTHONPATH=$PWD python experiments/profile_online_step.py   # writes experiments/results/profile_online_step.md
"""

from __future__ import annotations

import collections
import os
import sys
import tempfile
from pathlib import Path

import torch
from torch.export import Dim
from torch.profiler import profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import median_s, paired_s  # noqa: E402
from bench_online import (  # noqa: E402
    build_filter,
    discretize,
    filterpy_filter,
    filterpy_step,
    step_args,
)

import torchsde_lti as tl  # noqa: E402
from torchsde_lti.nn import model_version  # noqa: E402
from torchsde_lti.nn._online import model_series, series_step  # noqa: E402


class UpdateOnly(torch.nn.Module):
    """``filters.kalman_step`` with A, Q as inputs (the filter update without the discretisation)."""

    def __init__(self, H: torch.Tensor, R: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("H", H)
        self.register_buffer("R", R)

    def forward(self, mean, cov, y, A, Q):  # noqa: ANN001, ANN201
        st, out = tl.filters.kalman_step(tl.KalmanState(mean, cov), y, A, Q, self.H, self.R)
        return st.mean, st.cov, out.innovation, out.innovation_cov, out.log_likelihood


def top_level_calls(fn) -> tuple[int, list[tuple[str, int]]]:  # noqa: ANN001
    with profile() as p:
        fn()
    tops = [e.name for e in p.events() if e.cpu_parent is None]
    return len(tops), collections.Counter(tops).most_common(8)


def main() -> None:
    torch.set_num_threads(1)
    load = os.getloadavg()[0]
    kf = build_filter(validate=False)
    mean, cov, y, dt = step_args(1, 0)
    state = tl.KalmanState(mean, cov)
    lines = ["# One online step, B = 1: where the time goes (experiments/profile_online_step.py)", ""]
    with torch.no_grad():
        mats = kf.sde.matrices()
        d = discretize(mats.F, mats.L, mats.Qc, dt, validate_args=False)
        series = model_series(*mats)
        assert series is not None  # constant velocity: F² = 0
        A, Q, _ = series_step(series, dt)
        H, R = kf.H.detach().clone(), kf.R.detach().clone()
        parts = {
            "kf.step": lambda: kf.step(state, y, dt),
            "model_version(kf) (cache key)": lambda: model_version(kf),
            "closed-form series (1 gap; the step's)": lambda: series_step(series, dt),
            "filters.kalman_step": lambda: tl.filters.kalman_step(state, y, A, Q, H, R),
            "sde.matrices() (once per version)": lambda: kf.sde.matrices(),
            "core discretize (1 gap; F without closed form)": lambda: discretize(
                mats.F, mats.L, mats.Qc, dt, validate_args=False
            ),
        }
        lines += [
            f"torch {torch.__version__}, 1 thread, float64, CPU-time medians; load average {load:.1f} on "
            f"{os.cpu_count()} cores (shared machine).",
            "",
            "| eager part | CPU time | top-level aten calls | most frequent |",
            "|---|---:|---:|---|",
        ]
        for name, fn in parts.items():
            t = median_s(fn, 201, inner=5)
            n, common = top_level_calls(fn)
            lines.append(f"| {name} | {t * 1e6:.0f} µs | {n} | {', '.join(f'{k} {v}' for k, v in common[:5])} |")

        # B = 1000 tracks, each with its own dt: the same parts (the scalar updates of the
        # sequence loop run for more than SMALL_BATCH tracks)
        mB, cB, yB, dtB = step_args(1000, 2)
        stB = tl.KalmanState(mB, cB)
        AB, QB, _ = series_step(series, dtB)
        lines += [
            "",
            "| eager part, B = 1000 (own dt) | CPU time | top-level aten calls | most frequent |",
            "|---|---:|---:|---|",
        ]
        for name, fn in {
            "kf.step": lambda: kf.step(stB, yB, dtB),
            "closed-form series (1000 gaps)": lambda: series_step(series, dtB),
            "filters.kalman_step (scalar Joseph updates)": lambda: tl.filters.kalman_step(stB, yB, AB, QB, H, R),
        }.items():
            t = median_s(fn, 51, inner=2)
            n, common = top_level_calls(fn)
            lines.append(f"| {name} | {t * 1e6:.0f} µs | {n} | {', '.join(f'{k} {v}' for k, v in common[:5])} |")

    workdir = Path(tempfile.mkdtemp(prefix="profile_online_"))
    B = Dim("B", max=1_000_000)
    with torch.no_grad():
        ep_step = torch.export.export(tl.OnlineStep(kf).eval(), step_args(3, 1), dynamic_shapes=({0: B},) * 4)
        m3, c3, y3, dt3 = step_args(3, 1)
        d3 = discretize(mats.F, mats.L, mats.Qc, dt3, validate_args=False)
        ep_upd = torch.export.export(
            UpdateOnly(H, R).eval(), (m3, c3, y3, d3.A.contiguous(), d3.Q.contiguous()), dynamic_shapes=({0: B},) * 5
        )
    run_step = torch._inductor.aoti_load_package(
        torch._inductor.aoti_compile_and_package(ep_step, package_path=str(workdir / "step.pt2"))
    )
    run_upd = torch._inductor.aoti_load_package(
        torch._inductor.aoti_compile_and_package(ep_upd, package_path=str(workdir / "update.pt2"))
    )
    upd_args = [mean, cov, y, d.A.contiguous(), d.Q.contiguous()]
    step_list = [mean, cov, y, dt]
    fp = filterpy_filter()
    z, h = y[0].numpy()[:, None], float(dt[0])
    rows = {
        "AOTI step (discretisation + update), Python wrapper": lambda: run_step(*step_list),
        "AOTI step, C++ loader (.loader.run)": lambda: run_step.loader.run(step_list),
        "AOTI update alone (A, Q given), Python wrapper": lambda: run_upd(*upd_args),
        "AOTI update alone, C++ loader (.loader.run)": lambda: run_upd.loader.run(upd_args),
    }
    lines += [
        "",
        "| AOTInductor | its CPU time | filterpy predict+update (same pairs) | ratio |",
        "|---|---:|---:|---:|",
    ]
    for name, fn in rows.items():
        t, t_fp = paired_s(fn, lambda: filterpy_step(fp, z, h), 201, inner=20)
        lines.append(f"| {name} | {t * 1e6:.1f} µs | {t_fp * 1e6:.1f} µs | {t / t_fp:.2f}× |")
    lines.append("")
    text = "\n".join(lines)
    print(text)
    out = Path(__file__).parent / "results" / "profile_online_step.md"
    out.write_text(text)


if __name__ == "__main__":
    main()
