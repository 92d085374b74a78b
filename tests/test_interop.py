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
        np.testing.assert_allclose(np.asarray(state.state_vector, dtype=float)[:, 0], out.mean[k].detach().numpy(),
                                   atol=1e-9, rtol=0)
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
