"""Interop: a Stone Soup transition model and a filterpy helper backed by an LTISDE."""

from __future__ import annotations

import datetime
import subprocess
import sys

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from tests.reference import scipy_discretize

F64 = torch.float64


def irregular_track(rng, T=30, m=2, missing=(4, 5, 17)):
    """Gaps rounded to microseconds (what a timedelta holds) and observations with NaN steps."""
    dt = np.round(rng.uniform(0.05, 2.5, size=T), 6)
    y = rng.standard_normal((T, m)) * 3.0
    y[list(missing)] = np.nan
    return dt, y


def test_importing_the_package_imports_neither_peer():
    code = (
        "import sys, torchsde_lti, torchsde_lti.interop; "
        "assert 'stonesoup' not in sys.modules and 'filterpy' not in sys.modules, "
        "[k for k in sys.modules if k.startswith(('stonesoup', 'filterpy'))]"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_stonesoup_predictor_updater_match_kalman_filter():
    pytest.importorskip("stonesoup")
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.transition.linear import LinearGaussianTransitionModel
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import GaussianState
    from stonesoup.updater.kalman import KalmanUpdater

    from torchsde_lti.interop import LTISDETransitionModel, stonesoup_transition_model

    rng = np.random.default_rng(0)
    sde = tl.models.singer(alpha=0.6, q=2.0, dim=2, dtype=F64)  # state [x, vx, ax, y, vy, ay]
    H = tl.models.position_observation(sde)
    R = np.array([[0.5, 0.1], [0.1, 0.3]])
    dt, y = irregular_track(rng)
    m0 = np.array([1.0, 0.5, 0.0, -2.0, 0.2, 0.0])
    P0 = np.diag([4.0, 1.0, 0.5, 4.0, 1.0, 0.5])

    kf = tl.KalmanFilter(sde, H, torch.tensor(R), m0=torch.tensor(m0), P0=torch.tensor(P0))
    out = kf(torch.tensor(y), torch.tensor(dt))

    transition = stonesoup_transition_model(sde)
    assert isinstance(transition, LinearGaussianTransitionModel) and isinstance(transition, LTISDETransitionModel)
    assert transition.ndim_state == 6
    measurement = LinearGaussian(ndim_state=6, mapping=sde.position_indices, noise_covar=R)
    predictor, updater = KalmanPredictor(transition), KalmanUpdater(measurement)
    t = datetime.datetime(2024, 1, 1)
    state = GaussianState(m0[:, None], P0, timestamp=t)
    for k in range(len(dt)):
        t = t + datetime.timedelta(seconds=float(dt[k]))
        state = predictor.predict(state, timestamp=t)
        if not np.isnan(y[k]).any():
            hyp = SingleHypothesis(state, Detection(y[k][:, None], timestamp=t, measurement_model=measurement))
            state = updater.update(hyp)
        np.testing.assert_allclose(
            np.asarray(state.state_vector, dtype=float)[:, 0], out.mean[k].detach().numpy(), atol=1e-9, rtol=0
        )
        np.testing.assert_allclose(np.asarray(state.covar, dtype=float), out.cov[k].detach().numpy(), atol=1e-9, rtol=0)


def test_stonesoup_matrices_are_the_exact_discretisation_and_follow_the_parameters():
    pytest.importorskip("stonesoup")
    from torchsde_lti.interop import stonesoup_transition_model

    sde = tl.models.integrated_ou(k=0.8, q=1.5, dim=1, dtype=F64)
    transition = stonesoup_transition_model(sde)
    gap = datetime.timedelta(seconds=1.75)
    F, L, Qc = (x.detach().numpy() for x in (sde.F, sde.L, sde.Qc))
    A, Q, _ = scipy_discretize(F, L, Qc, np.asarray([1.75]), None)
    np.testing.assert_allclose(transition.matrix(time_interval=gap), A[0], atol=1e-13)
    np.testing.assert_allclose(transition.covar(time_interval=gap), Q[0], atol=1e-13)
    sde.k = 2.0  # a model trained further is picked up
    F2 = sde.F.detach().numpy()
    A2, Q2, _ = scipy_discretize(F2, L, Qc, np.asarray([1.75]), None)
    np.testing.assert_allclose(transition.matrix(time_interval=gap), A2[0], atol=1e-13)
    np.testing.assert_allclose(transition.covar(time_interval=gap), Q2[0], atol=1e-13)
    # several gaps kept at once, and an in-place (optimiser-style) update is picked up
    A3, _, _ = scipy_discretize(F2, L, Qc, np.asarray([0.5]), None)
    np.testing.assert_allclose(transition.matrix(time_interval=datetime.timedelta(seconds=0.5)), A3[0], atol=1e-13)
    np.testing.assert_allclose(transition.matrix(time_interval=gap), A2[0], atol=1e-13)
    with torch.no_grad():
        for p in sde.parameters():
            p.add_(0.3)
    A4, _, _ = scipy_discretize(sde.F.detach().numpy(), L, sde.Qc.detach().numpy(), np.asarray([1.75]), None)
    np.testing.assert_allclose(transition.matrix(time_interval=gap), A4[0], atol=1e-13)
    with pytest.raises(ValueError, match="time_interval"):
        transition.matrix(time_interval=datetime.timedelta(seconds=-1.0))
    with pytest.raises(ValueError, match="batch_shape"):
        stonesoup_transition_model(tl.models.integrated_ou(k=torch.tensor([0.5, 1.0]), q=1.0))


def test_filterpy_helper_matches_kalman_filter_with_inputs():
    filterpy_kalman = pytest.importorskip("filterpy.kalman")
    from torchsde_lti.interop import set_filterpy_step

    rng = np.random.default_rng(1)
    sde = tl.models.mass_spring_damper(m=1.5, k=2.0, c=0.4, q=0.7, dtype=F64)  # has B: force input
    dt, y = irregular_track(rng, T=25, m=1, missing=(3, 11, 12))
    u = rng.standard_normal((25, 1))
    R = np.array([[0.2]])
    m0, P0 = np.array([0.5, -0.3]), np.diag([1.0, 2.0])
    kf = tl.KalmanFilter(sde, sde.C, torch.tensor(R), m0=torch.tensor(m0), P0=torch.tensor(P0))
    out = kf(torch.tensor(y), torch.tensor(dt), u=torch.tensor(u))

    fp = filterpy_kalman.KalmanFilter(dim_x=2, dim_z=1, dim_u=1)
    fp.x, fp.P = m0[:, None].copy(), P0.copy()
    fp.H, fp.R = sde.C.numpy().copy(), R.copy()
    for k in range(len(dt)):
        set_filterpy_step(fp, sde, float(dt[k]))
        fp.predict(u=u[k][:, None])
        if not np.isnan(y[k]).any():
            fp.update(y[k][:, None])
        np.testing.assert_allclose(fp.x[:, 0], out.mean[k].detach().numpy(), atol=1e-9, rtol=0)
        np.testing.assert_allclose(fp.P, out.cov[k].detach().numpy(), atol=1e-9, rtol=0)
    with pytest.raises(ValueError, match="dim_x"):
        set_filterpy_step(filterpy_kalman.KalmanFilter(dim_x=3, dim_z=1), sde, 1.0)
    with pytest.raises(TypeError, match="filterpy KalmanFilter"):
        set_filterpy_step(object(), sde, 1.0)
    with pytest.raises(TypeError, match="sde must be an LTISDE, got ndarray"):
        set_filterpy_step(filterpy_kalman.KalmanFilter(dim_x=2, dim_z=1), np.eye(2), 1.0)


# ------------------------------------------------------------------ a multi-target tracker
def stonesoup_scenario(seed: int = 1, targets: int = 4, scans: int = 30) -> tuple[list, list]:
    """Ground truths of ``targets`` constant-velocity targets in 2-D (state [x, vx, y, vy], m and
    m/s) and the scans a sensor reports at irregular times: (time, set of detections) with
    detection probability 0.9, position noise 1 m² and uniform clutter."""
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.types.detection import Clutter, TrueDetection
    from stonesoup.types.groundtruth import GroundTruthPath, GroundTruthState

    rng = np.random.default_rng(seed)
    measurement = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=np.eye(2))
    start = datetime.datetime(2024, 1, 1)
    gaps = rng.uniform(0.5, 1.5, size=scans)
    times = [start + datetime.timedelta(seconds=float(s)) for s in np.cumsum(gaps)]
    truths = []
    for j in range(targets):
        x = np.array([60.0 * j, rng.uniform(-2, 2), rng.uniform(-50, 50), rng.uniform(-2, 2)])
        path = GroundTruthPath()
        prev = start
        for t in times:
            h = (t - prev).total_seconds()
            x = x + np.array([x[1] * h, 0.0, x[3] * h, 0.0])
            x[[1, 3]] += rng.normal(0.0, 0.05 * np.sqrt(h), size=2)
            path.append(GroundTruthState(x.copy()[:, None], timestamp=t))
            prev = t
        truths.append(path)
    scans_out = []
    for k, t in enumerate(times):
        dets = set()
        for path in truths:
            if rng.uniform() < 0.9:
                z = np.asarray(path[k].state_vector, dtype=float)[[0, 2], 0] + rng.normal(0.0, 1.0, size=2)
                dets.add(TrueDetection(z[:, None], timestamp=t, measurement_model=measurement, groundtruth_path=path))
        for _ in range(rng.poisson(2.0)):
            z = rng.uniform([-20, -80], [220, 80])
            dets.add(Clutter(z[:, None], timestamp=t, measurement_model=measurement))
        scans_out.append((t, dets))
    return truths, scans_out


def run_stonesoup_tracker(transition_model, scans: list) -> tuple[set, float]:
    """A Stone Soup multi-target tracker (Kalman predictor and updater, Mahalanobis
    hypothesiser, GNN 2-D assignment, multi-measurement initiator, covariance deleter) over
    ``scans``: (its tracks, CPU seconds per scan)."""
    import time as _time

    from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
    from stonesoup.deleter.error import CovarianceBasedDeleter
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.initiator.simple import MultiMeasurementInitiator
    from stonesoup.measures import Mahalanobis
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.tracker.simple import MultiTargetTracker
    from stonesoup.types.state import GaussianState
    from stonesoup.updater.kalman import KalmanUpdater

    measurement = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=np.eye(2))
    predictor, updater = KalmanPredictor(transition_model), KalmanUpdater(measurement)
    hypothesiser = DistanceHypothesiser(predictor, updater, measure=Mahalanobis(), missed_distance=4.0)
    associator = GNNWith2DAssignment(hypothesiser)
    deleter = CovarianceBasedDeleter(covar_trace_thresh=200.0)
    initiator = MultiMeasurementInitiator(
        prior_state=GaussianState(np.zeros((4, 1)), np.diag([1.0, 9.0, 1.0, 9.0])),
        measurement_model=measurement,
        deleter=deleter,
        data_associator=associator,
        updater=updater,
        min_points=3,
    )
    tracker = MultiTargetTracker(
        initiator=initiator, deleter=deleter, detector=scans, data_associator=associator, updater=updater
    )
    tracks: set = set()
    t0 = _time.process_time()
    for _, current in tracker:
        tracks |= current
    return tracks, (_time.process_time() - t0) / len(scans)


def fit_constant_velocity(scans: list, steps: int = 25) -> tl.LTISDE:
    """A constant-velocity model whose noise intensity q is LEARNED (Adam on the filter's
    log-likelihood) from the true detections of each target in ``scans``."""
    from stonesoup.types.detection import TrueDetection

    series: dict[int, list] = {}
    for t, dets in scans:
        for d in dets:
            if isinstance(d, TrueDetection):
                series.setdefault(id(d.groundtruth_path), []).append((t, np.asarray(d.state_vector, dtype=float)[:, 0]))
    T = min(len(s) for s in series.values())
    y = torch.tensor(np.stack([[z for _, z in s[:T]] for s in series.values()]))
    dt = torch.tensor(
        [[0.0] + [(b[0] - a[0]).total_seconds() for a, b in zip(s[: T - 1], s[1:T])] for s in series.values()]
    )
    sde = tl.models.constant_velocity(dim=2, q=1.0, dtype=F64)
    kf = tl.KalmanFilter(
        sde,
        tl.models.position_observation(sde),
        torch.eye(2, dtype=F64),
        m0=torch.cat([y[:, 0, :1], torch.zeros_like(y[:, 0, :1]), y[:, 0, 1:], torch.zeros_like(y[:, 0, :1])], -1),
        P0=torch.diag(torch.tensor([4.0, 9.0, 4.0, 9.0], dtype=F64)),
        learn=(),
    )
    opt = torch.optim.Adam(sde.parameters(), lr=0.2)
    for _ in range(steps):
        opt.zero_grad()
        (-kf(y, dt).log_likelihood.sum()).backward()
        opt.step()
    return sde


def test_stonesoup_multi_target_tracker_with_a_learned_model():
    """Stone Soup's tracker (predictor, updater, GNN associator, initiator, deleter) runs a
    4-target scenario with clutter and missed detections end to end on a learned model through
    torchsde_lti.interop, and follows every target about as well as with its own ConstantVelocity."""
    pytest.importorskip("stonesoup")
    from stonesoup.models.transition.linear import (
        CombinedLinearGaussianTransitionModel,
        ConstantVelocity,
    )

    from torchsde_lti.interop import stonesoup_transition_model

    truths, scans = stonesoup_scenario()
    sde = fit_constant_velocity(scans)
    q = float(sde.matrices().Qc[0, 0].detach())
    assert 1e-4 < q < 0.5  # learned from the data (the truth's velocity noise is 0.05² per s), moved from 1
    results = {}
    for name, model in (
        ("learned", stonesoup_transition_model(sde)),
        ("stonesoup", CombinedLinearGaussianTransitionModel([ConstantVelocity(q), ConstantVelocity(q)])),
    ):
        tracks, _ = run_stonesoup_tracker(model, scans)
        long = [tr for tr in tracks if len(tr) >= 15]
        end = scans[-1][0]
        errors = []
        for path in truths:  # each target's nearest track at the last scan
            truth = np.asarray(path[-1].state_vector, dtype=float)[[0, 2], 0]
            ends = [np.asarray(tr.state_vector, dtype=float)[[0, 2], 0] for tr in long if tr.timestamp == end]
            errors.append(min(np.linalg.norm(e - truth) for e in ends) if ends else np.inf)
        results[name] = (len(long), max(errors))
    print(results, q)
    assert results["learned"][0] >= 4 and results["learned"][1] < 3.0, results
    assert results["learned"][0] == results["stonesoup"][0], results
