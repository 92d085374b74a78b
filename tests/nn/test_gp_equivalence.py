"""A Matérn-3/2 SDE + KalmanFilter on sorted irregular times equals scikit-learn's exact GP
log marginal likelihood (issue 10): the state-space form of a GP is exact, not approximate."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsde_lti as tl

sklearn_gp = pytest.importorskip("sklearn.gaussian_process")
kernels = pytest.importorskip("sklearn.gaussian_process.kernels")


@pytest.mark.parametrize("algorithm", ["auto", "sequential", "scan"])
def test_matern32_kalman_log_likelihood_equals_sklearn_exact_gp(algorithm):
    rng = np.random.default_rng(0)
    N, ell, var, noise = 300, 0.7, 1.9, 0.05
    t = np.sort(rng.uniform(0.0, 60.0, N))
    y = np.sin(t) + 0.3 * rng.standard_normal(N)
    kernel = kernels.ConstantKernel(var) * kernels.Matern(length_scale=ell, nu=1.5) + kernels.WhiteKernel(noise)
    gp = sklearn_gp.GaussianProcessRegressor(kernel=kernel, optimizer=None, normalize_y=False, alpha=0.0)
    gp.fit(t[:, None], y)
    exact = gp.log_marginal_likelihood_value_

    sde = tl.models.matern(1.5, lengthscale=ell, variance=var, dtype=torch.float64)
    H = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    # default prior: the stationary covariance P∞ (the GP prior at the first time, dt[0] = 0)
    kf = tl.KalmanFilter(sde, H, torch.tensor([[noise]], dtype=torch.float64), algorithm=algorithm)
    assert kf.prior_mode == "model"
    dt = torch.as_tensor(np.diff(t, prepend=t[0]))
    out = kf(torch.as_tensor(y)[:, None], dt)
    assert abs(float(out.log_likelihood.detach()) - exact) < 1e-8, (float(out.log_likelihood.detach()), exact)
