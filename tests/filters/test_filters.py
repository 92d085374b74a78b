"""Tests of the functional filter/smoother against plain numpy references and oracles.

The numpy reference below is the textbook filter (joint update on the observed components,
explicit solve, standard covariance update) written independently of torchsde_lti.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
import scipy.linalg
import scipy.stats
import torch

from tests.reference import cv_matrices, numpy_kalman_filter, numpy_rts, random_problem, reference_batch, to_torch
from torchsde_lti.filters import FilterResult, kalman_filter, rts_smoother

F64 = torch.float64
# the two algorithms named, so that every test says which one it checks
sequential_kf = functools.partial(kalman_filter, algorithm="sequential")
scan_kf = functools.partial(kalman_filter, algorithm="scan")
sequential_rts = functools.partial(rts_smoother, algorithm="sequential")
scan_rts = functools.partial(rts_smoother, algorithm="scan")


# ----------------------------------------------------------------------------------------
# filter == numpy reference
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("fn", [sequential_kf, scan_kf], ids=["sequential", "scan"])
def test_filter_matches_numpy_reference(fn):
    rng = np.random.default_rng(0)
    d = random_problem(rng)
    ref = reference_batch(d)
    t = to_torch(d)
    out = fn(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], G=t["G"], u=t["u"])
    np.testing.assert_allclose(out.mean.numpy(), ref["mean"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.cov.numpy(), ref["cov"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.pred_mean.numpy(), ref["pred_mean"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.pred_cov.numpy(), ref["pred_cov"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.step_log_likelihood.numpy(), ref["ll"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.log_likelihood.numpy(), ref["ll"].sum(-1), rtol=0, atol=1e-9)
    # innovations: y - H m⁻ where observed, 0 elsewhere; S = H P⁻ Hᵀ + R
    v_ref = np.where(np.isnan(d["y"]), 0.0, d["y"] - ref["pred_mean"] @ d["H"].T)
    np.testing.assert_allclose(out.innovation.numpy(), v_ref, atol=1e-9)
    S_ref = d["H"] @ ref["pred_cov"] @ d["H"].T + d["R"]
    np.testing.assert_allclose(out.innovation_cov.numpy(), S_ref, atol=1e-9)
    assert out.observed.numpy().tolist() == (~np.isnan(d["y"])).tolist()


def test_cv_irregular_dt_with_controls_matches_reference():
    rng = np.random.default_rng(1)
    B, T = 4, 30
    dt = rng.exponential(0.5, size=(B, T))
    dt[:, 0] = 0.0
    A, Q, G = cv_matrices(dt, q=0.7)
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    R = np.array([[0.3, 0.05], [0.05, 0.2]])
    y = rng.standard_normal((B, T, 2)) * 3
    y[rng.random((B, T)) < 0.2] = np.nan
    y[1, 4, 0] = np.nan
    u = rng.standard_normal((B, T, 2))
    d = dict(y=y, A=A, Q=Q, H=H, R=R, m0=np.zeros((B, 4)), P0=np.tile(4 * np.eye(4), (B, 1, 1)), G=G, u=u)
    ref = reference_batch(d)
    t = to_torch(d)
    out = sequential_kf(
        t["y"],
        t["A"],
        t["Q"],
        t["H"],
        t["R"],
        torch.zeros(4, dtype=F64),
        4 * torch.eye(4, dtype=F64),
        G=t["G"],
        u=t["u"],
    )
    np.testing.assert_allclose(out.mean.numpy(), ref["mean"], atol=1e-9)
    np.testing.assert_allclose(out.cov.numpy(), ref["cov"], atol=1e-9)
    np.testing.assert_allclose(out.step_log_likelihood.numpy(), ref["ll"], atol=1e-9)


def test_time_varying_H_and_R_match_reference():
    rng = np.random.default_rng(21)
    d = random_problem(rng, batch=(2,), T=8)
    Hs = rng.standard_normal((2, 8, 2, 4))
    W = rng.standard_normal((8, 2, 2))
    Rs = W @ np.swapaxes(W, -1, -2) + 0.3 * np.eye(2)
    t = to_torch(d)
    out = sequential_kf(t["y"], t["A"], t["Q"], torch.as_tensor(Hs), torch.as_tensor(Rs), t["m0"], t["P0"])
    for b in range(2):
        m, P = d["m0"][b], d["P0"][b]
        for k in range(8):
            m = d["A"][b, k] @ m
            P = d["A"][b, k] @ P @ d["A"][b, k].T + d["Q"][b, k]
            S_full = Hs[b, k] @ P @ Hs[b, k].T + Rs[k]
            np.testing.assert_allclose(out.innovation_cov[b, k].numpy(), S_full, atol=1e-9)
            o = ~np.isnan(d["y"][b, k])
            if o.any():
                Ho, So = Hs[b, k][o], S_full[np.ix_(o, o)]
                v = d["y"][b, k][o] - Ho @ m
                K = np.linalg.solve(So, Ho @ P).T
                m, P = m + K @ v, P - K @ So @ K.T
            np.testing.assert_allclose(out.mean[b, k].numpy(), m, atol=1e-9)
            np.testing.assert_allclose(out.cov[b, k].numpy(), P, atol=1e-9)


def test_mask_equals_nan():
    rng = np.random.default_rng(2)
    d = random_problem(rng, missing=False)
    t = to_torch(d)
    mask = torch.ones(t["y"].shape, dtype=torch.bool)
    mask[0, 3, 1] = False
    mask[2, 4, :] = False
    y_nan = t["y"].clone()
    y_nan[~mask] = float("nan")
    args = (t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"])
    a = sequential_kf(y_nan, *args)
    b = sequential_kf(t["y"], *args, mask=mask)
    step_mask = torch.ones(t["y"].shape[:-1], dtype=torch.bool)
    step_mask[2, 4] = False
    y_step = t["y"].clone()
    y_step[2, 4] = float("nan")
    c = sequential_kf(y_step, *args, mask=step_mask)
    d_ = sequential_kf(y_step, *args)
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(a.log_likelihood, b.log_likelihood, rtol=0, atol=1e-12)
    torch.testing.assert_close(c.mean, d_.mean, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------------------
# independent oracle: dense joint Gaussian of the stacked observations
# ----------------------------------------------------------------------------------------


def test_log_likelihood_equals_dense_joint_gaussian():
    rng = np.random.default_rng(3)
    T, n, m = 4, 3, 2
    d = random_problem(rng, batch=(1,), T=T, n=n, m=m, p=1, missing=False)
    y = d["y"][0]
    y[1, 0] = np.nan
    y[2, :] = np.nan
    A, Q, c = d["A"][0], d["Q"][0], (d["G"][0] @ d["u"][0][..., None])[..., 0]
    m0, P0, H, R = d["m0"][0], d["P0"][0], d["H"], d["R"]
    # x = M z with z = [x_{-1}, q_0, ..., q_{T-1}] ~ N([m0, 0...], blkdiag(P0, Q_k)), plus means of c.
    Phi = [np.eye(n)]
    mean_x, cols = [], []
    mk = m0
    lin = np.eye(n)
    blocks_x = np.zeros((T * n, (T + 1) * n))
    for k in range(T):
        mk = A[k] @ mk + c[k]
        mean_x.append(mk)
        lin = A[k] @ lin
        blocks_x[k * n : (k + 1) * n, :n] = lin
        for j in range(k + 1):
            prod = np.eye(n)
            for i in range(j + 1, k + 1):
                prod = A[i] @ prod
            blocks_x[k * n : (k + 1) * n, (j + 1) * n : (j + 2) * n] = prod
    del Phi, cols
    Sz = scipy.linalg.block_diag(P0, *Q)
    Sx = blocks_x @ Sz @ blocks_x.T
    Hb = scipy.linalg.block_diag(*([H] * T))
    Sy = Hb @ Sx @ Hb.T + scipy.linalg.block_diag(*([R] * T))
    my = Hb @ np.concatenate(mean_x)
    yf = y.reshape(-1)
    o = ~np.isnan(yf)
    dense = scipy.stats.multivariate_normal(mean=my[o], cov=Sy[np.ix_(o, o)]).logpdf(yf[o])
    t = to_torch(d)
    yt = torch.as_tensor(y[None])
    for fn in (sequential_kf, scan_kf):
        out = fn(yt, t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], G=t["G"], u=t["u"])
        assert abs(float(out.log_likelihood[0]) - dense) < 1e-9


# ----------------------------------------------------------------------------------------
# smoother
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("smoother", [sequential_rts, scan_rts], ids=["sequential", "scan"])
def test_rts_matches_numpy_and_shrinks_covariance(smoother):
    rng = np.random.default_rng(4)
    d = random_problem(rng, batch=(2,), T=15)
    t = to_torch(d)
    out = sequential_kf(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], G=t["G"], u=t["u"])
    sm = smoother(out)
    for b in range(2):
        ms, Ps = numpy_rts(
            out.mean[b].numpy(), out.cov[b].numpy(), out.pred_mean[b].numpy(), out.pred_cov[b].numpy(), d["A"][b]
        )
        np.testing.assert_allclose(sm.mean[b].numpy(), ms, atol=1e-9)
        np.testing.assert_allclose(sm.cov[b].numpy(), Ps, atol=1e-9)
    gap = torch.linalg.eigvalsh(out.cov - sm.cov)
    assert float(gap.min()) > -1e-10
    torch.testing.assert_close(sm.mean[..., -1, :], out.mean[..., -1, :])


@pytest.mark.parametrize("smoother", [sequential_rts, scan_rts], ids=["sequential", "scan"])
@pytest.mark.parametrize("n", [4, 6])
def test_rts_with_singular_predicted_covariances_matches_pseudo_inverse_reference(smoother, n):
    """A prior with zero variances and steps with dt = 0 (A = I, Q = 0) leave P⁻ singular:
    the smoother takes a generalised inverse, the reference the pseudo-inverse (the smoothed
    moments are the same under any); n = 6 takes the solves' LAPACK path."""
    rng = np.random.default_rng(7)
    T, m = 6, 2
    A = np.stack([np.eye(n)] * 2 + [np.eye(n) + 0.3 * rng.standard_normal((n, n)) for _ in range(T - 2)])
    Q = np.zeros((T, n, n))
    for k in range(2, T):
        C = rng.standard_normal((n, n))
        Q[k] = C @ C.T / n + 0.1 * np.eye(n)
    P0 = np.diag([0.0, 1.0, 0.0, 2.0] + [0.5] * (n - 4))
    H = rng.standard_normal((m, n))
    R = 0.2 * np.eye(m)
    y = rng.standard_normal((T, m))
    out = sequential_kf(*(torch.tensor(x) for x in (y, A, Q, H, R, np.zeros(n), P0)))
    sm = smoother(out)
    mean, cov, pm, pc = (x.numpy() for x in (out.mean, out.cov, out.pred_mean, out.pred_cov))
    assert np.linalg.matrix_rank(pc[1]) < n  # singular predicted covariances
    ms, Ps = mean.copy(), cov.copy()
    for k in range(T - 2, -1, -1):
        E = cov[k] @ A[k + 1].T @ np.linalg.pinv(pc[k + 1], rcond=1e-12, hermitian=True)
        ms[k] = mean[k] + E @ (ms[k + 1] - pm[k + 1])
        Ps[k] = cov[k] + E @ (Ps[k + 1] - pc[k + 1]) @ E.T
    np.testing.assert_allclose(sm.mean.numpy(), ms, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sm.cov.numpy(), Ps, rtol=0, atol=1e-9)
    assert float(torch.linalg.eigvalsh(sm.cov).min()) > -1e-10


def test_smoother_explicit_A_Q_equal_stored():
    rng = np.random.default_rng(5)
    d = random_problem(rng, batch=(2,), T=6, missing=False)
    t = to_torch(d)
    out = sequential_kf(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"])
    a = sequential_rts(out)
    b = sequential_rts(out, t["A"], t["Q"])
    torch.testing.assert_close(a.mean, b.mean)


@pytest.mark.parametrize("smoother", [sequential_rts, scan_rts], ids=["sequential", "scan"])
def test_smoother_refuses_explicit_A_Q_the_filter_could_not_have_used(smoother):
    """A, Q passed to the smoother take the filter's shapes: time axis absent, 1 or T, batch
    broadcasting to the result's; anything else is a ValueError naming them (T − 1 steps too)."""
    rng = np.random.default_rng(5)
    d = random_problem(rng, batch=(3,), T=5, missing=False)
    t = to_torch(d)
    out = sequential_kf(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"])
    A, Q = t["A"], t["Q"]  # (3, 5, n, n)
    n = A.shape[-1]
    bad = {
        "A": [A[:1].expand(4, 5, n, n), A[0, :2], A[0, 1:], A.unsqueeze(0).expand(2, 3, 5, n, n)],
        "Q": [Q[:1].expand(4, 5, n, n), Q[0, :2]],
    }
    for name, shapes in bad.items():
        for x in shapes:
            with pytest.raises(ValueError, match=rf"\b{name}\b.*\({', '.join(map(str, x.shape[:-2]))}"):
                smoother(out, **{name: x})
    # accepted: a time axis of 1 (the same as that matrix at every step) or none, a batch of 1
    const = smoother(out, A[:, 1:2], Q).mean
    torch.testing.assert_close(smoother(out, A[:, 1:2].expand(3, 5, n, n), Q).mean, const)
    torch.testing.assert_close(smoother(out, A[0, 1], Q[:1]).mean, smoother(out, A[:1, 1:2], Q).mean)


# ----------------------------------------------------------------------------------------
# NEES on data simulated from the true model
# ----------------------------------------------------------------------------------------


def test_nees_is_chi_square():
    g = torch.Generator().manual_seed(7)
    B, T, n = 400, 25, 4
    dt = torch.rand(B, T, generator=g, dtype=F64) * 2.0 + 0.01
    A, Q, _ = (torch.as_tensor(x) for x in cv_matrices(dt.numpy(), q=0.5))
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64)
    R = torch.tensor([[0.4, 0.1], [0.1, 0.3]], dtype=F64)
    m0 = torch.zeros(n, dtype=F64)
    P0 = torch.diag(torch.tensor([10.0, 1.0, 10.0, 1.0], dtype=F64))
    chol = lambda M: torch.linalg.cholesky(M + 1e-300 * torch.eye(M.shape[-1], dtype=F64))  # noqa: E731
    x = m0 + (chol(P0) @ torch.randn(B, n, 1, generator=g, dtype=F64))[..., 0]
    xs, ys = [], []
    for k in range(T):
        x = (A[:, k] @ x[..., None])[..., 0] + (chol(Q[:, k]) @ torch.randn(B, n, 1, generator=g, dtype=F64))[..., 0]
        xs.append(x)
        ys.append((H @ x[..., None])[..., 0] + (chol(R) @ torch.randn(B, 2, 1, generator=g, dtype=F64))[..., 0])
    xs, ys = torch.stack(xs, 1), torch.stack(ys, 1)
    ys[:, 3] = float("nan")  # a missing step for everybody
    out = sequential_kf(ys, A, Q, H, R, m0, P0)
    err = xs - out.mean
    nees = (err * torch.linalg.solve(out.cov, err[..., None])[..., 0]).sum(-1)  # (B, T)
    # At each step, Σ_b NEES ~ χ²(n B) exactly (independent tracks). Bonferroni over T steps.
    lo, hi = scipy.stats.chi2.ppf([1e-4 / T, 1 - 1e-4 / T], n * B)
    total = nees.sum(0).numpy()
    assert np.all(total > lo) and np.all(total < hi), (total / B, lo / B, hi / B)
    # normalised innovation squared likewise (m = 2 per observed step)
    S = out.innovation_cov
    v = out.innovation
    nis = (v * torch.linalg.solve(S, v[..., None])[..., 0]).sum(-1)
    obs_steps = [k for k in range(T) if k != 3]
    lo, hi = scipy.stats.chi2.ppf([1e-4 / T, 1 - 1e-4 / T], 2 * B)
    tot = nis[:, obs_steps].sum(0).numpy()
    assert np.all(tot > lo) and np.all(tot < hi)


# ----------------------------------------------------------------------------------------
# gradients, batching, shapes
# ----------------------------------------------------------------------------------------


def test_gradcheck_all_inputs():
    rng = np.random.default_rng(8)
    d = random_problem(rng, batch=(1,), T=5, n=3, m=2, p=1)
    t = to_torch(d)
    y = t["y"]

    def f(A, Wq, H, Wr, m0, W0, G, u):
        Q = Wq @ Wq.mT
        R = Wr @ Wr.mT + 0.5 * torch.eye(2, dtype=F64)
        P0 = W0 @ W0.mT + torch.eye(3, dtype=F64)
        out = sequential_kf(y, A, Q, H, R, m0, P0, G=G, u=u)
        return out.log_likelihood, out.mean, out.cov

    Wq = torch.as_tensor(rng.standard_normal((1, 5, 3, 3)) * 0.3)
    Wr = torch.as_tensor(rng.standard_normal((2, 2)))
    W0 = torch.as_tensor(rng.standard_normal((1, 3, 3)))
    inputs = [t["A"], Wq, t["H"], Wr, t["m0"], W0, t["G"], t["u"]]
    inputs = [x.clone().requires_grad_(True) for x in inputs]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6)


def test_gradient_wrt_symmetric_inputs_is_symmetric_and_the_same_for_every_algorithm():
    """Q, R, P0 are used as their symmetric parts: d loglik / dQ (and of R, P0, and through the
    smoother) is the same symmetric matrix from every algorithm, so an SGD step on a directly
    learned Q keeps it symmetric (the scan and square-root filters used to differ from the loop
    by an antisymmetric part, and the next call refused the stepped Q)."""
    rng = np.random.default_rng(11)
    d = random_problem(rng, batch=(2,), T=7, n=3, m=2, missing=True)
    t = to_torch(d)
    Q0, R0, P00 = ((x + x.mT) / 2 for x in (t["Q"][0, 0], t["R"], t["P0"][0]))  # exactly symmetric
    B, T, n = 2, 7, 3
    grads = {}
    for algorithm in ("sequential", "scan", "square_root"):
        for smoother in ("sequential", "scan"):
            Q, R, P0 = (x.clone().requires_grad_(True) for x in (Q0, R0, P00))
            # Q as a broadcast view of the shared matrix, R shared, P0 per track
            out = kalman_filter(
                t["y"],
                t["A"],
                Q.expand(B, T, n, n),
                H=t["H"],
                R=R,
                m0=t["m0"],
                P0=P0.expand(B, n, n),
                algorithm=algorithm,
            )
            sm = rts_smoother(out, algorithm=smoother)
            loss = out.log_likelihood.sum() + (sm.mean**2).sum() + sm.cov.sum()
            grads[algorithm, smoother] = torch.autograd.grad(loss, (Q, R, P0))
    ref = grads["sequential", "sequential"]
    for key, g in grads.items():
        for name, gx, rx in zip(("Q", "R", "P0"), g, ref):
            torch.testing.assert_close(gx, gx.mT, rtol=0, atol=1e-12, msg=f"{key} d/d{name} not symmetric")
            torch.testing.assert_close(gx, rx, rtol=1e-10, atol=1e-10, msg=f"{key} d/d{name} differs")
    # one SGD step on a directly learned Q with the default algorithm; the next call accepts it
    Q = torch.nn.Parameter(Q0.clone())
    opt = torch.optim.SGD([Q], lr=1e-4)
    for _ in range(2):
        opt.zero_grad()
        loss = -kalman_filter(t["y"], t["A"], Q, t["H"], R0, t["m0"], P00).log_likelihood.sum()
        loss.backward()
        opt.step()
        assert torch.equal(Q, Q.mT)


def test_a_shared_matrix_passed_as_a_broadcast_view_is_symmetrised_once():
    """Q, R, P0 shared by the tracks and passed as broadcast views (B, T, n, n) are symmetrised
    (and laid out) at their own extent, not B·T times: the prepared Q, R, P0 keep a batch of 1."""
    from torchsde_lti.filters.inputs import FilterInputs, prepare_inputs

    t = to_torch(random_problem(np.random.default_rng(3), batch=(4,), T=5, missing=False))
    X = torch.randn(4, 4, dtype=F64)
    Q, R, P0 = (
        (X @ X.mT).expand(4, 5, 4, 4),
        (0.5 * torch.eye(2, dtype=F64)).expand(4, 5, 2, 2),
        torch.eye(4, dtype=F64),
    )
    prep = prepare_inputs(FilterInputs(t["y"], t["A"], Q, t["H"], R, t["m0"], P0.expand(4, 4, 4)))
    assert prep.Q.shape == (5, 4, 4, 1) and prep.R.shape[-1] == 1 and prep.P0.shape == (4, 4, 1)
    torch.testing.assert_close(prep.Q[2, :, :, 0], (X @ X.mT + (X @ X.mT).mT) / 2, rtol=0, atol=0)


def test_gradients_finite_for_fully_missing_track():
    rng = np.random.default_rng(9)
    d = random_problem(rng, batch=(2,), T=6, missing=False)
    t = to_torch(d)
    y = t["y"].clone()
    y[1] = float("nan")
    y.requires_grad_(True)
    A = t["A"].clone().requires_grad_(True)
    Q = t["Q"].clone().requires_grad_(True)
    R = t["R"].clone().requires_grad_(True)
    H = t["H"].clone().requires_grad_(True)
    for fn in (sequential_kf, scan_kf):
        out = fn(y, A, Q, H, R, t["m0"], t["P0"])
        assert float(out.step_log_likelihood[1].detach().abs().max()) == 0.0
        loss = out.log_likelihood.sum() + out.mean.sum() + sequential_rts(out).mean.sum()
        grads = torch.autograd.grad(loss, (y, A, Q, R, H))
        for g in grads:
            assert torch.isfinite(g).all()
        assert float(grads[0][1].abs().max()) == 0.0


def test_batched_equals_loop_and_leading_dims():
    rng = np.random.default_rng(10)
    d = random_problem(rng, batch=(2, 3), T=7)
    t = to_torch(d)
    out = sequential_kf(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], G=t["G"], u=t["u"])
    assert out.mean.shape == (2, 3, 7, 4) and out.cov.shape == (2, 3, 7, 4, 4)
    assert out.log_likelihood.shape == (2, 3) and out.step_log_likelihood.shape == (2, 3, 7)
    sm = sequential_rts(out)
    assert sm.cov.shape == (2, 3, 7, 4, 4)
    for i in range(2):
        for j in range(3):
            single = sequential_kf(
                t["y"][i, j],
                t["A"][i, j],
                t["Q"][i, j],
                t["H"],
                t["R"],
                t["m0"][i, j],
                t["P0"][i, j],
                G=t["G"][i, j],
                u=t["u"][i, j],
            )
            torch.testing.assert_close(out.mean[i, j], single.mean, rtol=0, atol=1e-12)
            torch.testing.assert_close(out.cov[i, j], single.cov, rtol=0, atol=1e-12)
            torch.testing.assert_close(out.log_likelihood[i, j], single.log_likelihood, rtol=0, atol=1e-12)
            torch.testing.assert_close(sm.mean[i, j], sequential_rts(single).mean, rtol=0, atol=1e-12)


@pytest.mark.parametrize("algorithm", ["sequential", "square_root", "scan"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_empty_batch_gives_empty_results(algorithm, dtype):
    """Zero tracks (a tracker or a loader with nothing to pass): empty results, every algorithm
    (the sequential one's -1 reshapes were ambiguous for zero elements)."""
    A, Q, _ = (torch.as_tensor(x, dtype=dtype) for x in cv_matrices(np.ones(5), 0.5, axes=1))
    H = torch.tensor([[1.0, 0.0]], dtype=dtype)
    y = torch.zeros(0, 5, 1, dtype=dtype)
    out = kalman_filter(y, A, Q, H, 0.25 * torch.eye(1, dtype=dtype), torch.zeros(2, dtype=dtype),
                        torch.eye(2, dtype=dtype), algorithm=algorithm)  # fmt: skip
    assert out.mean.shape == (0, 5, 2) and out.cov.shape == (0, 5, 2, 2) and out.log_likelihood.shape == (0,)
    assert rts_smoother(out).cov.shape == (0, 5, 2, 2)


def test_shared_grid_broadcasts_over_tracks():
    """A, Q without a track axis and y (B, T, m): the covariance path is shared."""
    rng = np.random.default_rng(11)
    T = 9
    dt = rng.exponential(1.0, size=T)
    A, Q, _ = cv_matrices(dt)
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    R = 0.5 * np.eye(2)
    y = rng.standard_normal((5, T, 2))
    tA, tQ, tH, tR = (torch.as_tensor(x) for x in (A, Q, H, R))
    out = sequential_kf(torch.as_tensor(y), tA, tQ, tH, tR, torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64))
    assert out.cov.shape == (5, T, 4, 4)
    for b in range(5):
        ref = numpy_kalman_filter(y[b], A, Q, H, R, np.zeros(4), np.eye(4))
        np.testing.assert_allclose(out.mean[b].numpy(), ref["mean"], atol=1e-10)
        np.testing.assert_allclose(out.step_log_likelihood[b].numpy(), ref["ll"], atol=1e-10)


@pytest.mark.parametrize("T", [1, 2, 7, 16])
def test_scan_equals_sequential(T):
    rng = np.random.default_rng(12 + T)
    d = random_problem(rng, batch=(2, 3), T=T, missing=T > 7)
    t = to_torch(d)
    args = (t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"])
    a = sequential_kf(*args, G=t["G"], u=t["u"])
    b = scan_kf(*args, G=t["G"], u=t["u"])
    for name in ("mean", "cov", "pred_mean", "pred_cov", "innovation", "innovation_cov", "step_log_likelihood"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=1e-9, msg=name)
    sa, sb = sequential_rts(a), scan_rts(a)
    torch.testing.assert_close(sa.mean, sb.mean, rtol=0, atol=1e-9)
    torch.testing.assert_close(sa.cov, sb.cov, rtol=0, atol=1e-9)


def test_float32_matches_float64():
    rng = np.random.default_rng(13)
    d = random_problem(rng, batch=(3,), T=10)
    t64, t32 = to_torch(d), to_torch(d, torch.float32)
    a = sequential_kf(*(t64[k] for k in ("y", "A", "Q", "H", "R", "m0", "P0")))
    b = sequential_kf(*(t32[k] for k in ("y", "A", "Q", "H", "R", "m0", "P0")))
    assert b.mean.dtype == torch.float32 and b.log_likelihood.dtype == torch.float32
    torch.testing.assert_close(b.mean.double(), a.mean, rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(b.log_likelihood.double(), a.log_likelihood, rtol=1e-4, atol=1e-3)


# ----------------------------------------------------------------------------------------
# float32 robustness: stiff model, wildly irregular dt, 1e4 steps
# ----------------------------------------------------------------------------------------


def test_float32_psd_over_10k_steps_stiff_irregular():
    """Stiff model (time scales 1e3 s … 0.5 ms), dt log-uniform in [1e-6, 1e3], precise sensors.

    With these settings a float32 filter with the standard update P − K S Kᵀ loses
    definiteness (torch-kf without Joseph: 29 of 10⁴ filtered covariances fail Cholesky);
    here every filtered and predicted covariance must stay exactly symmetric and admit a
    float32 Cholesky factorisation.
    """
    import torchsde_lti as tl

    rng = np.random.default_rng(14)
    T = 10_000
    dt = 10.0 ** rng.uniform(-6, 3, size=T)
    F = scipy.linalg.block_diag(np.array([[0.0, 1.0], [-1e3, -2e3]]), np.array([[-1e-3, 1.0], [0.0, -5e2]]))
    d = tl.discretize(
        torch.as_tensor(F),
        torch.eye(4, dtype=F64),
        torch.diag(torch.tensor([0.0, 1e4, 0.0, 1e4], dtype=F64)),
        torch.as_tensor(dt),
    )
    f32 = torch.float32
    A, Q = d.A.to(f32), d.Q.to(f32)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=f32)
    R = 1e-6 * torch.eye(2, dtype=f32)
    y = torch.as_tensor(rng.standard_normal((2, T, 2)), dtype=f32)
    y[0, torch.as_tensor(rng.random(T) < 0.3)] = float("nan")
    y[1, torch.as_tensor(rng.random(T) < 0.1), 1] = float("nan")
    out = sequential_kf(y, A, Q, H, R, torch.zeros(4, dtype=f32), 1e2 * torch.eye(4, dtype=f32))
    for P in (out.cov, out.pred_cov):
        assert torch.isfinite(P).all()
        assert torch.equal(P, P.mT)
        assert int((torch.linalg.cholesky_ex(P).info != 0).sum()) == 0
        eig = torch.linalg.eigvalsh(P.double()).amin(-1)
        assert float(eig.min()) >= 0.0
    assert torch.isfinite(out.log_likelihood).all()


# ----------------------------------------------------------------------------------------
# bad input
# ----------------------------------------------------------------------------------------


def _ok():
    rng = np.random.default_rng(15)
    return to_torch(random_problem(rng, batch=(2,), T=5, missing=False))


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda t: t.update(y=t["y"][..., :1]), "rows"),
        (lambda t: t.update(H=t["H"][:, :3]), "H must have 4 columns"),
        (lambda t: t.update(A=t["A"][..., :4, :, :]), "time axis"),
        (lambda t: t.update(R=t["R"] + torch.tensor([[0.0, 1.0], [0.0, 0.0]], dtype=F64)), "R must be symmetric"),
        (lambda t: t.update(R=-t["R"]), "R must be positive"),
        (lambda t: t.update(m0=t["m0"][..., :3]), "m0"),
        (lambda t: t.update(P0=t["P0"][..., :3, :3]), "P0"),
        (lambda t: t.update(G=None), "G and u"),
        (lambda t: t.update(u=t["u"][..., :1]), "u must have shape"),
        (lambda t: t.update(y=t["y"][..., :0, :]), "at least one step"),
    ],
)
def test_bad_input_raises(change, match):
    t = _ok()
    change(t)
    with pytest.raises(ValueError, match=match):
        sequential_kf(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], G=t["G"], u=t["u"])


@pytest.mark.parametrize("algorithm", ["sequential", "square_root", "scan", "auto"])
@pytest.mark.parametrize("inf", [float("inf"), -float("inf")])
def test_inf_in_y_raises(algorithm, inf):
    """±Inf in y is refused as by imm_filter and the modules (NaN marks missing data)."""
    t = _ok()
    args = (t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"])
    y = t["y"].clone()
    y[1, 2, 0] = inf
    with pytest.raises(ValueError, match=r"y contains Inf.*mark missing values with NaN or mask"):
        kalman_filter(y, *args, algorithm=algorithm)
    y[1, 2, 0] = float("nan")
    assert torch.isfinite(kalman_filter(y, *args, algorithm=algorithm).log_likelihood).all()


def test_bad_mask_raises():
    t = _ok()
    with pytest.raises(ValueError, match="mask"):
        sequential_kf(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], mask=torch.ones(2, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="mask"):
        sequential_kf(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"], mask=torch.ones(2, 5))


def test_mask_of_both_forms_when_T_equals_m():
    """With T == m == B a (B, T) mask also fits (T, m): refused with a ValueError that names
    both ways to write it; the unambiguous forms read as the online step reads them."""
    g = torch.Generator().manual_seed(2)
    B = T = m = 2
    y = torch.randn(B, T, m, generator=g, dtype=F64)
    A, Q = torch.eye(2, dtype=F64).expand(T, 2, 2), 0.1 * torch.eye(2, dtype=F64).expand(T, 2, 2)
    H, R, m0, P0 = (
        torch.eye(2, dtype=F64),
        0.3 * torch.eye(2, dtype=F64),
        torch.zeros(2, dtype=F64),
        torch.eye(2, dtype=F64),
    )
    per_step = torch.tensor([[True, False], [False, True]])
    with pytest.raises(ValueError, match=r"ambiguous.*\(\.\.\., 2, 1\)"):
        sequential_kf(y, A, Q, H, R, m0, P0, mask=per_step)
    y_nan = y.clone()
    y_nan[~per_step] = float("nan")
    want = sequential_kf(y_nan, A, Q, H, R, m0, P0)
    got = sequential_kf(y, A, Q, H, R, m0, P0, mask=per_step[..., None])
    torch.testing.assert_close(got.log_likelihood, want.log_likelihood, rtol=0, atol=1e-12)
    # with y's number of dimensions: per component
    per_component = torch.tensor([[[True, False], [True, True]], [[False, True], [True, False]]])
    y_nan = y.clone()
    y_nan[~per_component] = float("nan")
    got = sequential_kf(y, A, Q, H, R, m0, P0, mask=per_component)
    torch.testing.assert_close(
        got.log_likelihood, sequential_kf(y_nan, A, Q, H, R, m0, P0).log_likelihood, rtol=0, atol=1e-12
    )


def test_result_is_namedtuple():
    t = _ok()
    out = sequential_kf(t["y"], t["A"], t["Q"], t["H"], t["R"], t["m0"], t["P0"])
    assert isinstance(out, FilterResult)


@pytest.mark.parametrize("algorithm", ["sequential", "scan", "square_root"])
def test_shared_grid_passed_expanded_equals_shared(algorithm):
    """A, Q of one time grid passed as a broadcast view (B, T, n, n) (``A.expand(B, …)``): the
    same results and gradients as (T, n, n); a batch that does not broadcast is still refused."""
    kw = to_torch(random_problem(np.random.default_rng(5), batch=(6,), T=7, missing=False))
    A0, Q0 = kw["A"][0].clone().requires_grad_(), kw["Q"][0].clone().requires_grad_()
    args = dict(y=kw["y"], H=kw["H"], R=kw["R"], m0=kw["m0"][0], P0=kw["P0"][0], algorithm=algorithm)
    shared = kalman_filter(A=A0, Q=Q0, **args)
    expanded = kalman_filter(A=A0.expand(6, 7, 4, 4), Q=Q0.expand(6, 7, 4, 4), **args)
    for name in ("log_likelihood", "mean", "cov", "innovation_cov"):
        torch.testing.assert_close(getattr(expanded, name), getattr(shared, name), rtol=1e-14, atol=1e-14)
    g_shared = torch.autograd.grad(shared.log_likelihood.sum(), [A0, Q0])
    g_expanded = torch.autograd.grad(expanded.log_likelihood.sum(), [A0, Q0])
    for a, b in zip(g_expanded, g_shared):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="do not broadcast"):
        kalman_filter(A=A0.expand(5, 7, 4, 4), Q=Q0, **args)
