"""A Stone Soup tracker's cost per scan with the LTISDE-backed transition model
(:func:`torchsde_lti.interop.stonesoup_transition_model`) against Stone Soup's own closed-form
constant velocity (``CombinedLinearGaussianTransitionModel`` of two ``ConstantVelocity``).

Workload: K tracks of the 2-D constant-velocity model (q = 1.3, positions observed with a
correlated R), 40 scans at irregular times (gaps uniform in [0.5, 5] s: every track of a scan has
the same gap, as in a tracker), a ``KalmanPredictor`` predict and a ``KalmanUpdater`` update of
every track per scan. The figure per model is the median over scans of the CPU time of a scan,
then the median over rounds, the two models alternating (:func:`_timing.interleaved_s`); the
means of the two runs are compared at the end (they must agree to rounding). The backed model
discretises the first track's gap of a scan and reuses it for the others (its cache of the last
gaps); Stone Soup's model evaluates its closed form at every call.

    PYTHONPATH=$PWD python experiments/bench_stonesoup.py            # K = 1, 10, 100
    PYTHONPATH=$PWD python experiments/bench_stonesoup.py --save     # experiments/results/bench_stonesoup.md
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from stonesoup.models.measurement.linear import LinearGaussian
from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
from stonesoup.predictor.kalman import KalmanPredictor
from stonesoup.types.detection import Detection
from stonesoup.types.hypothesis import SingleHypothesis
from stonesoup.types.state import GaussianState
from stonesoup.updater.kalman import KalmanUpdater

import torchsde_lti as tl
from torchsde_lti.interop import stonesoup_transition_model

Q, SCANS = 1.3, 40
R = np.array([[0.5, 0.1], [0.1, 0.3]])


def tracker(model: object, tracks: int, gaps: np.ndarray, reports: np.ndarray) -> tuple[float, np.ndarray]:
    """(median CPU seconds of a scan, final means (tracks, 4)) of ``tracks`` tracks predicted and
    updated with ``model`` at every scan."""
    measurement = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=R)
    predictor, updater = KalmanPredictor(model), KalmanUpdater(measurement)
    t = datetime.datetime(2024, 1, 1)
    states = [GaussianState(np.zeros((4, 1)), 10.0 * np.eye(4), timestamp=t) for _ in range(tracks)]
    per_scan = []
    for s, gap in enumerate(gaps):
        t = t + datetime.timedelta(seconds=float(gap))
        start = time.process_time()
        for k in range(tracks):
            prior = predictor.predict(states[k], timestamp=t)
            report = Detection(reports[s, k][:, None], timestamp=t, measurement_model=measurement)
            states[k] = updater.update(SingleHypothesis(prior, report))
        per_scan.append(time.process_time() - start)
    return statistics.median(per_scan), np.stack([np.asarray(x.state_vector, dtype=float)[:, 0] for x in states])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tracks", type=int, nargs="+", default=[1, 10, 100])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--save", action="store_true", help="write experiments/results/bench_stonesoup.md")
    args = parser.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _timing import interleaved_s, machine_line, saved

    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    gaps = np.round(rng.uniform(0.5, 5.0, SCANS), 3)
    sde = tl.models.constant_velocity(dim=2, q=Q, dtype=torch.float64)
    with saved("bench_stonesoup.md") if args.save else contextlib.nullcontext():
        print(
            f"Stone Soup predict + update per scan, 2-D constant velocity, {SCANS} irregular scans ({machine_line()})\n"
        )
        print(
            "| tracks per scan | backed LTISDE (ms) | Stone Soup ConstantVelocity (ms) | backed / Stone Soup | max abs mean difference |"
        )
        print("|---:|---:|---:|---:|---:|")
        for K in args.tracks:
            reports = rng.standard_normal((SCANS, K, 2)) * 3.0

            def backed() -> float:
                return tracker(stonesoup_transition_model(sde), K, gaps, reports)[0]

            def native() -> float:
                model = CombinedLinearGaussianTransitionModel([ConstantVelocity(Q), ConstantVelocity(Q)])
                return tracker(model, K, gaps, reports)[0]

            # each call times its own scans (the median scan); the two alternate, rounds' medians
            per_scan: dict[str, list[float]] = {"backed": [], "native": []}
            contestants = {"backed": backed, "native": native}
            interleaved_s({k: lambda k=k: per_scan[k].append(contestants[k]()) for k in contestants}, args.rounds, 0)
            b, n = statistics.median(per_scan["backed"]), statistics.median(per_scan["native"])
            model_b = stonesoup_transition_model(sde)
            model_n = CombinedLinearGaussianTransitionModel([ConstantVelocity(Q), ConstantVelocity(Q)])
            diff = np.abs(tracker(model_b, K, gaps, reports)[1] - tracker(model_n, K, gaps, reports)[1]).max()
            print(f"| {K} | {1e3 * b:.2f} | {1e3 * n:.2f} | {b / n:.2f} | {diff:.1e} |")


if __name__ == "__main__":
    main()
