"""A ν per mode in the IMM (``tl.StudentT(dof)`` with dof (M,)): each mode Roth et al.'s Student-t
filter with its own degrees of freedom, the modes mixed in their covariances ``ν_i/(ν_i − 2) P_i``.

Against values computed elsewhere: a whole sequence is a plain numpy per-mode t IMM (mixing,
joint t update, scipy's multivariate t for each mode's predictive); the online step is the
sequence filter; gradients through the per-mode ν by gradcheck; the evaluation's mixture density
is scipy's and its Monte Carlo level draws each component with its own ν; a scalar ν keeps its
meaning (shared), and a ν per mode is refused where it has none.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats
from scipy.special import logsumexp

import torchsde_lti as tl
from torchsde_lti.evaluation import hpd_level, mixture_log_prob
from torchsde_lti.evaluation.student_t import t_draws, t_hpd_level
from torchsde_lti.filters import StudentTNoise, kalman_filter
from torchsde_lti.filters.imm import combine, imm_filter

F64 = torch.float64
H2 = [[1.0, 0, 0, 0], [0, 0, 1.0, 0]]
NU = [2.7, 6.0, 30.0]


def _models(dtype=F64):
    return [
        tl.models.moored(k=0.08, q=0.02, dim=2, dtype=dtype),
        tl.models.integrated_ou(0.7, 2.0, dim=2, dtype=dtype),
        tl.models.constant_velocity(dim=2, q=0.5, dtype=dtype),
    ]


def _imm(noise, dtype=F64, M=3):
    rates = torch.tensor([[0.0, 0.1, 0.05], [0.2, 0.0, 0.1], [0.1, 0.3, 0.0]], dtype=dtype)[:M, :M]
    R = torch.tensor([[[0.3, 0.1], [0.1, 0.5]], [[2.0, 0.0], [0.0, 1.5]], [[1.0, -0.2], [-0.2, 0.8]]], dtype=dtype)
    return tl.IMMFilter(_models(dtype)[:M], torch.tensor(H2, dtype=dtype), R[:M], rates,
                        P0=10 * torch.eye(4, dtype=dtype), mode_prob0=torch.full((M,), 1 / M, dtype=dtype),
                        noise=noise)  # fmt: skip


def _data(B=3, T=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    dt = torch.rand(B, T, generator=g, dtype=F64) + 0.2
    y = (2 * torch.randn(B, T, 2, generator=g, dtype=F64)).cumsum(1)
    y[0, 2, 1] = math.nan  # one missing component
    y[1, 3] = math.nan  # a missing report
    y[2, 5] += 40.0  # an outlier
    return y, dt


def _reference(y, A, Q, H, R, Pi, m0, P0, p0, nu):
    """A plain numpy IMM of one series with a Student-t filter per mode, mode j with ν_j (float64):
    mixing of the modes' covariances r_i P_i (r = ν/(ν−2)) returned to mode j's scale (÷ r_j),
    each mode's prediction and joint t update (posterior scale (ν_j + Δ²)/(ν_j + d) P⁺ with ν_j + d
    dof, matched back to ν_j in its covariance), ℓ_j = scipy's multivariate t log density."""
    M = len(nu)
    r = nu / (nu - 2)
    mu, m, P = p0.copy(), np.repeat(m0[None], M, 0), np.repeat(P0[None], M, 0)
    lls, probs, means, covs = [], [], [], []
    for k in range(len(y)):
        c = mu @ Pi[k]
        w = mu[:, None] * Pi[k] / c[None, :]
        mm = np.einsum("ij,in->jn", w, m)
        PP = np.stack([sum(w[i, j] * (r[i] * P[i] + np.outer(m[i] - mm[j], m[i] - mm[j])) for i in range(M)) / r[j]
                       for j in range(M)])  # fmt: skip
        ell = np.zeros(M)
        newm, newP = np.empty_like(m), np.empty_like(P)
        o = ~np.isnan(y[k])
        for j in range(M):
            mp, Pp = A[k, j] @ mm[j], A[k, j] @ PP[j] @ A[k, j].T + Q[k, j]
            if not o.any():
                newm[j], newP[j] = mp, Pp
                continue
            Ho, Ro = H[o], R[j][np.ix_(o, o)]
            S = Ho @ Pp @ Ho.T + Ro
            e = y[k][o] - Ho @ mp
            ell[j] = stats.multivariate_t(loc=np.zeros(o.sum()), shape=S, df=nu[j]).logpdf(e)
            K = Pp @ Ho.T @ np.linalg.inv(S)
            d2, d = e @ np.linalg.solve(S, e), o.sum()
            newm[j] = mp + K @ e
            newP[j] = (
                (nu[j] + d2) / (nu[j] + d) * (Pp - K @ S @ K.T) * (nu[j] + d) / (nu[j] + d - 2) * (nu[j] - 2) / nu[j]
            )
        joint = np.log(c) + ell
        total = logsumexp(joint)
        mu, m, P = np.exp(joint - total), newm, newP
        lls.append(total if o.any() else 0.0)
        probs.append(mu)
        means.append(m)
        covs.append(P)
    return np.array(lls), np.array(probs), np.array(means), np.array(covs)


def test_sequence_equals_a_plain_numpy_per_mode_t_imm():
    imm = _imm(tl.StudentT(NU))
    y, dt = _data()
    with torch.no_grad():
        out = imm(y, dt)
        d, Pi = imm.discretize(dt)
    nu = np.array(NU)
    for b in range(y.shape[0]):
        args = (y[b], d.A[b], d.Q[b], imm.H, imm.R, Pi[b], imm.m0, imm.P0, imm.mode_prob0)
        lls, probs, means, covs = _reference(*(x.detach().numpy() for x in args), nu)
        np.testing.assert_allclose(out.step_log_likelihood[b].numpy(), lls, rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(out.mode_probabilities[b].numpy(), probs, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(out.mode_mean[b].numpy(), means, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(out.mode_cov[b].numpy(), covs, rtol=1e-10, atol=1e-10)
        # the combined output is the mixture's covariance Σ μ_j (r_j P_j + (m_j − x)(m_j − x)ᵀ)
        x = np.einsum("tj,tjn->tn", probs, means)
        dev = means - x[:, None]
        r = nu / (nu - 2)
        cov = np.einsum("tj,tjab->tab", probs, r[:, None, None] * covs + dev[..., :, None] * dev[..., None, :])
        np.testing.assert_allclose(out.mean[b].numpy(), x, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(out.cov[b].numpy(), cov, rtol=1e-10, atol=1e-10)


def test_step_likelihood_is_the_mixture_of_each_modes_multivariate_t():
    imm = _imm(tl.StudentT(NU))
    y, dt = _data(seed=1)
    with torch.no_grad():
        out = imm(y, dt)
    H = torch.tensor(H2, dtype=F64)
    for b, k in ((2, 5), (0, 6), (1, 1)):
        c = out.pred_mode_probabilities[b, k].numpy()
        mu = (out.mode_pred_mean[b, k] @ H.mT).numpy()
        S = out.mode_innovation_cov[b, k].numpy()
        want = np.log(sum(c[j] * stats.multivariate_t(mu[j], S[j], df=NU[j]).pdf(y[b, k].numpy()) for j in range(3)))
        assert float(out.step_log_likelihood[b, k]) == pytest.approx(want, rel=1e-12)
        # ... and the evaluation's mixture density with a ν per component is the same number
        got = mixture_log_prob(y[b, k][None], out.pred_mode_probabilities[b, k][None], torch.as_tensor(mu)[None],
                               out.mode_innovation_cov[b, k][None], torch.tensor(NU, dtype=F64))  # fmt: skip
        assert float(got) == pytest.approx(want, rel=1e-12)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_online_step_equals_the_sequence_filter(dtype):
    imm = _imm(tl.StudentT(NU), dtype=dtype)
    y, dt = (x.to(dtype) for x in _data(seed=2))
    tol = 1e-11 if dtype == F64 else 2e-4
    with torch.no_grad():
        out = imm(y, dt)
        state = imm.initial_state(3)
        for k in range(y.shape[1]):
            state, step = imm.step(state, y[:, k], dt[:, k])
            torch.testing.assert_close(step.log_likelihood, out.step_log_likelihood[:, k], rtol=tol, atol=tol)
            torch.testing.assert_close(state.mode_prob, out.mode_probabilities[:, k], rtol=tol, atol=tol)
            torch.testing.assert_close(state.mode_cov, out.mode_cov[:, k], rtol=tol, atol=tol * 10)
            torch.testing.assert_close(step.cov, out.cov[:, k], rtol=tol, atol=tol * 10)
        # prediction and forecast mix per mode as the cycle does: a zero horizon is the state itself
        fc = imm.forecast(out, torch.zeros(1, dtype=dtype))
        torch.testing.assert_close(fc.cov[:, 0], out.cov[:, -1], rtol=tol, atol=tol * 10)
        torch.testing.assert_close(fc.mode_cov[:, 0], out.mode_cov[:, -1], rtol=tol, atol=tol * 10)


def test_equal_dofs_per_mode_equal_the_shared_dof_and_one_mode_is_the_kalman_filter():
    y, dt = _data(seed=3)
    with torch.no_grad():
        a, b = _imm(tl.StudentT(4.5))(y, dt), _imm(tl.StudentT([4.5] * 3))(y, dt)
        for f in ("step_log_likelihood", "mode_probabilities", "mode_mean", "mode_cov", "mean", "pred_mean"):
            torch.testing.assert_close(getattr(b, f), getattr(a, f), rtol=1e-12, atol=1e-12)
        # the combined output: the shared filter's is a scale matrix, the per-mode one's a covariance
        torch.testing.assert_close(b.cov, 4.5 / 2.5 * a.cov, rtol=1e-12, atol=1e-12)
        one = _imm(tl.StudentT([3.5]), M=1)(y, dt)
        kf = tl.KalmanFilter(_models()[0], torch.tensor(H2, dtype=F64), _imm(None, M=1).R[0],
                             P0=10 * torch.eye(4, dtype=F64), noise=tl.StudentT(3.5))  # fmt: skip
        ref = kf(y, dt)
        torch.testing.assert_close(one.step_log_likelihood, ref.step_log_likelihood, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(one.mode_cov[..., 0, :, :], ref.cov, rtol=1e-12, atol=1e-12)


def test_gradcheck_through_the_per_mode_dof():
    imm = _imm(None)
    y, dt = _data(T=6, seed=4)
    with torch.no_grad():
        d, Pi = imm.discretize(dt)
    m0, P0, p0 = imm.m0.detach(), imm.P0.detach(), imm.mode_prob0.detach()

    def f(nu, R, yy):
        R = 0.5 * (R + R.mT)  # (gradcheck perturbs one entry at a time)
        out = imm_filter(yy, d.A, d.Q, imm.H.detach(), R, Pi, m0, P0, p0, noise=StudentTNoise(nu, per_mode=True))
        return out.log_likelihood, out.cov[..., -1, :, :]

    nu = torch.tensor(NU, dtype=F64, requires_grad=True)
    R = imm.R.detach().clone().requires_grad_(True)
    yy = torch.nan_to_num(y).requires_grad_(True)
    assert torch.autograd.gradcheck(f, (nu, R, yy), eps=1e-6, atol=1e-6, rtol=1e-5)
    # each mode's ν has its own gradient through the module's parameter
    t = _imm(tl.StudentT(NU))
    (-t(y, dt).log_likelihood.sum()).backward()
    grad = t.noise.parametrizations.dof.original.grad
    assert grad.shape == (3,) and bool(torch.isfinite(grad).all()) and bool((grad != 0).all())


def test_combine_matches_the_mixture_covariance_per_mode():
    g = torch.Generator().manual_seed(5)
    p = torch.tensor([0.2, 0.5, 0.3], dtype=F64)
    m = torch.randn(3, 4, generator=g, dtype=F64)
    X = torch.randn(3, 4, 4, generator=g, dtype=F64)
    P = X @ X.mT + torch.eye(4, dtype=F64)
    nu = torch.tensor(NU, dtype=F64)
    x, C = combine(p, m, P, StudentTNoise(nu, per_mode=True))
    r = nu / (nu - 2)
    want = sum(p[j] * (r[j] * P[j] + torch.outer(m[j] - x, m[j] - x)) for j in range(3))
    torch.testing.assert_close(C, want, rtol=1e-13, atol=1e-13)


def test_level_draws_each_component_with_its_own_dof():
    """A mixture whose weight sits on one component: the Monte Carlo level is that component's
    closed-form F level with its own ν (a shared ν would give the other's)."""
    g = torch.Generator().manual_seed(6)
    N, m = 400, 2
    y = torch.randn(N, m, generator=g, dtype=F64) * 3
    mu = torch.zeros(N, 2, m, dtype=F64)
    S = torch.eye(m, dtype=F64).expand(N, 2, m, m)
    nu = torch.tensor([2.5, 40.0], dtype=F64)
    maha = (y * y).sum(-1)
    for j in (0, 1):
        w = torch.nn.functional.one_hot(torch.full((N,), j), 2).to(F64)
        mc = hpd_level(y, w, mu, S, dof=nu, samples=4000)
        exact = t_hpd_level(maha, m, float(nu[j]))
        assert float((mc - exact).abs().max()) < 0.04
    with pytest.raises(ValueError, match="pass comp"):
        t_draws(mu[:, 0], y, nu, g)


def test_module_option_shapes_repr_state_dict_and_refusals():
    imm = _imm(tl.StudentT(NU))
    assert imm.noise.dof.shape == (3,) and "dof=[2.7, 6, 30]" in repr(imm.noise)
    other = _imm(tl.StudentT([4.0, 4.0, 4.0]))
    other.load_state_dict(imm.state_dict())
    torch.testing.assert_close(other.noise.dof, torch.tensor(NU, dtype=F64))
    imm.noise.dof = torch.tensor([3.0, 4.0, 5.0], dtype=F64)
    torch.testing.assert_close(imm.noise.dof, torch.tensor([3.0, 4.0, 5.0], dtype=F64))
    with pytest.raises(ValueError, match=r"one per mode, \(3,\)"):
        _imm(tl.StudentT([4.0, 4.0]))
    with pytest.raises(ValueError, match="a KalmanFilter takes one"):
        tl.KalmanFilter(
            _models()[2], torch.tensor(H2, dtype=F64), torch.eye(2, dtype=F64), noise=tl.StudentT([4.0, 5.0])
        )
    for bad in ([[4.0, 4.0]], [4.0, 2.0], []):
        with pytest.raises(ValueError, match="dof"):
            tl.StudentT(bad)
    y, dt = _data()
    with torch.no_grad():
        d, Pi = imm.discretize(dt)
        args = (y, d.A, d.Q, imm.H, imm.R, Pi, imm.m0, imm.P0, imm.mode_prob0)
        with pytest.raises(ValueError, match="is per mode"):
            imm_filter(*args, noise=StudentTNoise(torch.tensor([4.0, 5.0], dtype=F64), per_mode=True))
        with pytest.raises(ValueError, match="is per mode"):
            kalman_filter(y, d.A[..., 0, :, :], d.Q[..., 0, :, :], imm.H, imm.R[0], imm.m0, imm.P0,
                          noise=StudentTNoise(torch.tensor([4.0, 5.0], dtype=F64), per_mode=True))  # fmt: skip
        with pytest.raises(ValueError, match="finite and > 2"):
            imm_filter(*args, noise=StudentTNoise(torch.tensor([4.0, 5.0, 1.5], dtype=F64), per_mode=True))


def test_training_through_the_config_learns_a_dof_per_mode_and_reloads(tmp_path):
    """``filter/noise=student_t_modes`` through the one training path (the tiny IMM of two modes):
    each mode's ν is a parameter that moves on its own, the run reloads with them."""
    from hydra import compose, initialize_config_dir

    from tests.training.test_imm_training import CONF, IMM_TINY
    from torchsde_lti.runs import load_run
    from torchsde_lti.training import train

    overrides = [f"output_dir={tmp_path}", *IMM_TINY, "filter/noise=student_t_modes", "filter.noise.dof=[4.0,4.0]"]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=[*overrides, "module.k_step_weight=0"])
    metrics, objects = train(cfg)
    dof = objects["module"].kf.noise.dof.detach()
    assert dof.shape == (2,) and float((dof - 4.0).abs().min()) > 1e-6 and float(dof[0]) != float(dof[1])
    assert math.isfinite(metrics["val/nll"]) and 0.0 <= metrics["val/cover2s"] <= 1.0
    run = load_run(tmp_path)
    torch.testing.assert_close(run.filter.noise.dof.detach(), dof)


@pytest.mark.slow  # torch.export of the IMM's structured scan: ≈ 20–25 s
def test_exported_program_equals_the_eager_filter():
    """The exported program (one traced cycle in torch's structured scan) takes the same route, at a
    batch equal to the number of modes (B = M = 3, which failed torch's tracing) and with missing data."""
    imm = _imm(tl.StudentT(NU))
    y, dt = _data(B=3, T=8, seed=7)
    program = torch.export.export(tl.DeployedFilter(imm).eval(), (y, dt)).module()
    ll, mean = program(y, dt)
    with torch.no_grad():
        ref = imm(y, dt)
    torch.testing.assert_close(ll, ref.log_likelihood, rtol=0, atol=1e-10)
    torch.testing.assert_close(mean, ref.mean, rtol=0, atol=1e-10)
