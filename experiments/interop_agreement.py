"""Agreement and cost of the issue-13 features, printed as a small table.

    PYTHONPATH=$PWD python experiments/interop_agreement.py   # writes experiments/results/interop_agreement.txt

Agreement (float64, max abs deviation over an irregular 200-step track with missing steps):
Stone Soup KalmanPredictor/KalmanUpdater with the LTISDE-backed transition model vs
tl.KalmanFilter; filterpy with set_filterpy_step vs tl.KalmanFilter; the shaping block of
propagate from seed 003's start vs P∞ (float32 and float64); the built transfer function's
H(jω) vs scipy.signal.freqs. Cost: median over 5 repeats of one Stone Soup predict+update
step with the backed model and with Stone Soup's own CombinedLinearGaussianTransitionModel
of two ConstantVelocity models (closed form), same track.
"""

from __future__ import annotations

import datetime
import sys
import time
from pathlib import Path

import numpy as np
import scipy.signal
import torch
from filterpy.kalman import KalmanFilter as FilterpyKF
from stonesoup.models.measurement.linear import LinearGaussian
from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
from stonesoup.predictor.kalman import KalmanPredictor
from stonesoup.types.detection import Detection
from stonesoup.types.hypothesis import SingleHypothesis
from stonesoup.types.state import GaussianState
from stonesoup.updater.kalman import KalmanUpdater

import torchsde_lti as tl
from torchsde_lti.interop import set_filterpy_step, stonesoup_transition_model

F64 = torch.float64


def stonesoup_run(transition, measurement, m0, P0, dt, y):
    predictor, updater = KalmanPredictor(transition), KalmanUpdater(measurement)
    t = datetime.datetime(2024, 1, 1)
    state = GaussianState(m0[:, None], P0, timestamp=t)
    means, covs = [], []
    start = time.perf_counter()
    for k in range(len(dt)):
        t = t + datetime.timedelta(seconds=float(dt[k]))
        state = predictor.predict(state, timestamp=t)
        if not np.isnan(y[k]).any():
            state = updater.update(
                SingleHypothesis(state, Detection(y[k][:, None], timestamp=t, measurement_model=measurement))
            )
        means.append(np.asarray(state.state_vector, dtype=float)[:, 0])
        covs.append(np.asarray(state.covar, dtype=float))
    return np.array(means), np.array(covs), (time.perf_counter() - start) / len(dt)


def main() -> None:
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    T = 200
    dt = np.round(rng.uniform(0.05, 2.5, size=T), 6)
    y = rng.standard_normal((T, 2)) * 3.0
    y[rng.random(T) < 0.1] = np.nan
    R = np.array([[0.5, 0.1], [0.1, 0.3]])
    rows = []

    # Stone Soup, constant velocity (so the closed-form Stone Soup model is a like-for-like cost reference)
    q = 1.3
    sde = tl.models.constant_velocity(dim=2, q=q, dtype=F64)
    H = tl.models.position_observation(sde)
    m0, P0 = np.zeros(4), 10.0 * np.eye(4)
    out = tl.KalmanFilter(sde, H, torch.tensor(R), m0=torch.tensor(m0), P0=torch.tensor(P0))(
        torch.tensor(y), torch.tensor(dt)
    )
    meas = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=R)
    backed, native = [], []
    for _ in range(5):
        mb, cb, tb = stonesoup_run(stonesoup_transition_model(sde), meas, m0, P0, dt, y)
        native_model = CombinedLinearGaussianTransitionModel([ConstantVelocity(q), ConstantVelocity(q)])
        mn, cn, tn = stonesoup_run(native_model, meas, m0, P0, dt, y)
        backed.append(tb)
        native.append(tn)
    ref_m, ref_c = out.mean.detach().numpy(), out.cov.detach().numpy()
    rows.append(("Stone Soup (backed CV) vs tl.KalmanFilter: mean", np.abs(mb - ref_m).max()))
    rows.append(("Stone Soup (backed CV) vs tl.KalmanFilter: cov", np.abs(cb - ref_c).max()))
    rows.append(("Stone Soup (native CV) vs tl.KalmanFilter: mean", np.abs(mn - ref_m).max()))

    # filterpy with inputs (mass-spring-damper: B present)
    msd = tl.models.mass_spring_damper(m=1.5, k=2.0, c=0.4, q=0.7, dtype=F64)
    u = rng.standard_normal((T, 1))
    y1 = y[:, :1]
    out2 = tl.KalmanFilter(
        msd, msd.C, torch.tensor([[0.2]], dtype=F64), m0=torch.zeros(2, dtype=F64), P0=torch.eye(2, dtype=F64)
    )(torch.tensor(y1), torch.tensor(dt), u=torch.tensor(u))
    fp = FilterpyKF(dim_x=2, dim_z=1, dim_u=1)
    fp.x, fp.P, fp.H, fp.R = np.zeros((2, 1)), np.eye(2), msd.C.numpy().copy(), np.array([[0.2]])
    dev_m = dev_c = 0.0
    for k in range(T):
        set_filterpy_step(fp, msd, float(dt[k]))
        fp.predict(u=u[k][:, None])
        if not np.isnan(y1[k]).any():
            fp.update(y1[k][:, None])
        dev_m = max(dev_m, np.abs(fp.x[:, 0] - out2.mean[k].detach().numpy()).max())
        dev_c = max(dev_c, np.abs(fp.P - out2.cov[k].detach().numpy()).max())
    rows.append(("filterpy + set_filterpy_step (MSD, inputs) vs tl: mean", dev_m))
    rows.append(("filterpy + set_filterpy_step (MSD, inputs) vs tl: cov", dev_c))

    # shaping block from seed 003's start
    for dtype in (torch.float32, F64):
        system = tl.models.mass_spring_damper(m=2.0, k=3.0, c=0.8, dtype=dtype)
        shaping = tl.models.matern(1.5, lengthscale=1.5, variance=0.7, dtype=dtype)
        model = tl.models.shaped(system, shaping, C=torch.tensor([[1.0, 0.0]], dtype=dtype))
        tau = 1.0 / float(-torch.linalg.eigvals(model.F.detach().double()).real.max())
        _, P = model.propagate(
            torch.zeros(4, dtype=dtype), model.prior_covariance(), torch.linspace(0, 10 * tau, 201, dtype=dtype)
        )
        err = (P[:, 2:, 2:] - shaping.stationary_covariance()).abs().max().item()
        rows.append((f"shaping block |P_ff(t) - P_inf_f|, t in [0, 10 tau], {dtype}", err))

    # transfer function frequency response
    num, den = [3.0, 0.0, 1.0, 2.0], [1.5, 2.0, 4.0, 1.0]
    tf = tl.models.from_transfer_function(num, den, dtype=F64)
    F, B, C, D = (x.detach().numpy() for x in (tf.F, tf.B, tf.C, tf.D))
    w = np.logspace(-2, 2, 20)
    _, h_ref = scipy.signal.freqs(num, den, worN=w)
    h = np.array([(C @ np.linalg.solve(1j * wk * np.eye(3) - F, B) + D)[0, 0] for wk in w])
    rows.append(("from_transfer_function H(jw) vs scipy.signal.freqs (max rel)", np.abs(h / h_ref - 1).max()))

    width = max(len(r[0]) for r in rows)
    for name, value in rows:
        print(f"{name:<{width}}  {value:.2e}")
    print(
        f"Stone Soup predict+update per step, backed LTISDE CV: {1e6 * np.median(backed):.0f} us "
        f"(median of 5; native CombinedLinearGaussian CV: {1e6 * np.median(native):.0f} us)"
    )


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _timing import saved

    with saved("interop_agreement.txt"):
        main()
