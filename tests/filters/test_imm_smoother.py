"""IMM smoother (filters/imm_smoother.py, IMMFilter.smooth): equal to the RTS smoother where it
must be, and measured against the exact smoothed posterior of the switching model (the mixture
over all M^(T+1) mode histories of Kalman smoothers, a plain numpy reference written here)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from torchsde_lti.filters.imm import imm_filter
from torchsde_lti.filters.imm_smoother import imm_smoother

D64 = torch.float64


def exact_switching_smoother(y, A, Q, H, R, Pi, m0, P0, p0):  # noqa: ANN001, ANN201 - numpy arrays
    """The exact smoothed posterior of the IMM's model, by enumeration (numpy, tests only).

    y (T, m) with NaN = missing; A, Q (T, M, n, n); H (M, m, n); R (M, m, m); Pi (T, M, M);
    m0 (M, n), P0 (M, n, n), p0 (M,) the prior before step 0. Histories s_{-1}, s_0 … s_{T-1}
    (s_{-1} ~ p0 picks the prior, s_k ~ Pi_k[s_{k-1}], x_k = A_{k,s_k} x_{k-1} + q): each one a
    Kalman filter + RTS smoother, weighted by prior × likelihood. Returns the smoothed mode
    probabilities (T, M), the moment-matched mean (T, n) and cov (T, n, n), and the mode-matched
    means (T, M, n) and covs (T, M, n, n) (zeros where a mode has probability 0)."""
    T, M, n = A.shape[0], A.shape[1], A.shape[-1]
    h = np.array(list(itertools.product(range(M), repeat=T + 1)))
    with np.errstate(divide="ignore"):
        logw = np.log(p0[h[:, 0]])
        for k in range(T):
            logw = logw + np.log(Pi[k, h[:, k], h[:, k + 1]])
    keep = np.isfinite(logw)
    h, logw = h[keep], logw[keep]
    m, P = m0[h[:, 0]].copy(), P0[h[:, 0]].copy()
    fm, fP, pm, pP, As = [], [], [], [], []
    for k in range(T):
        s = h[:, k + 1]
        Ak = A[k, s]
        m = np.einsum("nab,nb->na", Ak, m)
        P = Ak @ P @ Ak.transpose(0, 2, 1) + Q[k, s]
        pm.append(m), pP.append(P), As.append(Ak)
        obs = ~np.isnan(y[k])
        if obs.any():
            Hk, Rk = H[s][:, obs, :], R[s][:, obs][:, :, obs]
            S = Hk @ P @ Hk.transpose(0, 2, 1) + Rk
            v = y[k, obs][None] - np.einsum("nab,nb->na", Hk, m)
            Si = np.linalg.inv(S)
            K = P @ Hk.transpose(0, 2, 1) @ Si
            logw = logw - 0.5 * (np.einsum("na,nab,nb->n", v, Si, v) + np.linalg.slogdet(2 * np.pi * S)[1])
            m = m + np.einsum("nab,nb->na", K, v)
            P = P - K @ S @ K.transpose(0, 2, 1)
        fm.append(m), fP.append(P)
    sm, sP = [fm[-1]], [fP[-1]]
    for k in range(T - 2, -1, -1):
        E = fP[k] @ As[k + 1].transpose(0, 2, 1) @ np.linalg.inv(pP[k + 1])
        sm.insert(0, fm[k] + np.einsum("nab,nb->na", E, sm[0] - pm[k + 1]))
        sP.insert(0, fP[k] + E @ (sP[0] - pP[k + 1]) @ E.transpose(0, 2, 1))
    w = np.exp(logw - logw.max())
    w /= w.sum()
    sm, sP = np.stack(sm, 1), np.stack(sP, 1)  # (N, T, n), (N, T, n, n)

    def moments(weights: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.einsum("n,na->a", weights, mean)
        d = mean - x
        return x, np.einsum("n,nab->ab", weights, cov + d[:, :, None] * d[:, None, :])

    prob = np.zeros((T, M))
    mode_mean, mode_cov = np.zeros((T, M, n)), np.zeros((T, M, n, n))
    mean, cov = np.zeros((T, n)), np.zeros((T, n, n))
    for k in range(T):
        mean[k], cov[k] = moments(w, sm[:, k], sP[:, k])
        for j in range(M):
            sel = h[:, k + 1] == j
            prob[k, j] = w[sel].sum()
            if prob[k, j] > 0:
                mode_mean[k, j], mode_cov[k, j] = moments(w[sel] / prob[k, j], sm[sel, k], sP[sel, k])
    return prob, mean, cov, mode_mean, mode_cov


def _bank(dtype: torch.dtype = D64) -> list[tl.LTISDE]:
    cv = tl.models.constant_velocity(dim=2, q=0.3, dtype=dtype)
    ou = tl.models.integrated_ou(k=0.5, q=2.0, dim=2, dtype=dtype)
    moored = tl.models.moored(k=0.8, q=0.05, dim=2, dtype=dtype)  # no velocity noise: contracts it
    return [cv, ou, moored]


def _matrices(models: list[tl.LTISDE], dt: torch.Tensor, rates: list[list[float]]):  # noqa: ANN202
    """A, Q (..., T, M, n, n) of every mode over every gap and Pi = expm(Λ dt) (..., T, M, M)."""
    mats = [m.matrices() for m in models]
    F = torch.stack([x.F for x in mats]).detach()
    W = torch.stack([x.L @ x.Qc @ x.L.mT for x in mats]).detach()
    d = tl.discretize(F, torch.eye(F.shape[-1], dtype=F.dtype), W, dt.unsqueeze(-1))
    Lam = torch.as_tensor(rates, dtype=dt.dtype)
    Lam = Lam - torch.diag_embed(Lam.sum(-1))
    return d.A, d.Q, torch.matrix_exp(Lam * dt[..., None, None])


def _problem(M: int, T: int, rates: list[list[float]], seed: int, per_mode_prior: bool = False):  # noqa: ANN202
    """A random short track (positions, one component missing) for the first M models of the bank."""
    g = torch.Generator().manual_seed(seed)
    models = _bank()[:M]
    y = 2.0 * torch.randn(T, 2, generator=g, dtype=D64).cumsum(0)
    y[min(2, T - 1), 1] = float("nan")
    dt = 0.2 + 2.0 * torch.rand(T, generator=g, dtype=D64)
    A, Q, Pi = _matrices(models, dt, rates)
    H = tl.models.position_observation(models[0]).expand(M, 2, 4)
    R = torch.tensor([[1.0, 0.2], [0.2, 0.7]], dtype=D64).expand(M, 2, 2)
    m0 = torch.zeros(M, 4, dtype=D64)
    P0 = 4.0 * torch.eye(4, dtype=D64).expand(M, 4, 4).clone()
    if per_mode_prior:
        m0 = m0 + torch.randn(M, 4, generator=g, dtype=D64)
        P0 = P0 * torch.linspace(0.5, 2.0, M, dtype=D64)[:, None, None]
    p0 = torch.softmax(torch.randn(M, generator=g, dtype=D64), -1)
    return y, A, Q, H, R, Pi, m0, P0, p0


def _compare(args, M: int):  # noqa: ANN001, ANN202
    """(smoother, filter, exact) on one problem: the smoother's and filter's errors vs exact."""
    y, A, Q, H, R, Pi, m0, P0, p0 = args
    out = imm_filter(y, A, Q, H, R, Pi, m0, P0, p0)
    sm = imm_smoother(out)
    ex = exact_switching_smoother(*(t.numpy() for t in (y, A, Q, H, R, Pi, m0, P0, p0)))
    return sm, out, ex


def _errors(sm, out, ex) -> dict[str, float]:  # noqa: ANN001
    prob, mean, cov, mode_mean, _ = ex
    std = np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1))  # (T, n) the exact posterior's std
    return {
        "prob": float(np.abs(sm.mode_probabilities.numpy() - prob).max()),
        "mean": float((np.abs(sm.mean.numpy() - mean) / std).max()),
        "cov": float(np.abs(sm.cov.numpy() - cov).max() / np.abs(cov).max()),
        "filter_prob": float(np.abs(out.mode_probabilities.numpy() - prob).max()),
        "filter_mean": float((np.abs(out.mean.numpy() - mean) / std).max()),
    }


# ---------------------------------------------------------------- where it must be exact
def _one_mode(sde: tl.LTISDE, dtype: torch.dtype = D64) -> tuple[tl.IMMFilter, tl.KalmanFilter]:
    H = tl.models.position_observation(sde)
    R = torch.tensor([[1.0, 0.2], [0.2, 0.7]], dtype=dtype)
    imm = tl.IMMFilter([sde], H, R, torch.zeros(1, 1, dtype=dtype), P0=4.0 * torch.eye(4, dtype=dtype))
    return imm, tl.KalmanFilter(sde, H, imm.R.detach(), P0=imm.P0.detach())


def _tracks(B: int = 3, T: int = 9, dtype: torch.dtype = D64, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    y = torch.randn(B, T, 2, generator=g, dtype=dtype).cumsum(1)
    dt = 0.2 + 2.0 * torch.rand(B, T, generator=g, dtype=dtype)  # per-track irregular gaps
    y[1, 3] = float("nan")
    y[2, 5, 0] = float("nan")
    y[0, -2:] = float("nan")
    return y, dt


@pytest.mark.parametrize("model", ["cv", "iou"])
def test_one_mode_equals_rts_smoother(model: str) -> None:
    sde = _bank()[0 if model == "cv" else 1]
    imm, kf = _one_mode(sde)
    y, dt = _tracks()
    a, b = imm.smooth(imm(y, dt)), kf.smooth(kf(y, dt))
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=1e-10)
    torch.testing.assert_close(a.cov, b.cov, rtol=0, atol=1e-10)
    torch.testing.assert_close(a.mode_mean[..., 0, :], b.mean, rtol=0, atol=1e-10)
    assert torch.equal(a.mode_probabilities, torch.ones_like(a.mode_probabilities))


def test_identical_modes_equal_rts_and_the_chain_marginals() -> None:
    """M copies of one model: the modes say nothing, so the state is the RTS smoother's and the
    smoothed mode probabilities are the chain's prior marginals p0 Pi_0 … Pi_k."""
    sde = _bank()[1]
    H = tl.models.position_observation(sde)
    R = torch.tensor([[1.0, 0.2], [0.2, 0.7]], dtype=D64)
    rates = torch.tensor([[0.0, 0.3, 0.1], [0.2, 0.0, 0.4], [0.5, 0.1, 0.0]], dtype=D64)
    p0 = torch.tensor([0.2, 0.5, 0.3], dtype=D64)
    imm = tl.IMMFilter([sde, sde, sde], H, R, rates, P0=4.0 * torch.eye(4, dtype=D64), mode_prob0=p0)
    kf = tl.KalmanFilter(sde, H, R, P0=4.0 * torch.eye(4, dtype=D64))
    y, dt = _tracks()
    out = imm(y, dt)
    a, b = imm.smooth(out), kf.smooth(kf(y, dt))
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=1e-10)
    torch.testing.assert_close(a.cov, b.cov, rtol=0, atol=1e-10)
    marginal = (p0 @ out.mode_transition[..., 0, :, :]).unsqueeze(-2)
    for k in range(1, dt.shape[-1]):
        marginal = torch.cat([marginal, (marginal[..., -1:, :] @ out.mode_transition[..., k, :, :])], -2)
    torch.testing.assert_close(a.mode_probabilities, marginal, rtol=0, atol=1e-12)


@pytest.mark.parametrize("M", [2, 3])
def test_no_switching_equals_the_exact_mixture(M: int) -> None:
    """Λ = 0: the exact posterior is the mixture of each mode's Kalman smoother weighted by its
    likelihood (per-mode priors too), and the smoother is exact."""
    args = _problem(M, T=5, rates=[[0.0] * M] * M, seed=1, per_mode_prior=True)
    sm, _, (prob, mean, cov, mode_mean, mode_cov) = _compare(args, M)
    torch.testing.assert_close(sm.mode_probabilities, torch.from_numpy(prob), rtol=0, atol=1e-10)
    torch.testing.assert_close(sm.mean, torch.from_numpy(mean), rtol=0, atol=1e-9)
    torch.testing.assert_close(sm.cov, torch.from_numpy(cov), rtol=0, atol=1e-9)
    torch.testing.assert_close(sm.mode_mean, torch.from_numpy(mode_mean), rtol=0, atol=1e-9)
    torch.testing.assert_close(sm.mode_cov, torch.from_numpy(mode_cov), rtol=0, atol=1e-9)


# ---------------------------------------------------------------- an approximation, measured
SWITCHING = {2: [[0.0, 0.2], [0.3, 0.0]], 3: [[0.0, 0.2, 0.1], [0.3, 0.0, 0.1], [0.2, 0.2, 0.0]]}


@pytest.mark.parametrize("M", [2, 3])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_switching_is_close_to_the_exact_mixture(M: int, seed: int) -> None:
    """Modes that overlap and switch about every 3–5 s on 0.2–2.2 s gaps, T = 6 (M^7 histories).
    The smoother approximates (one Gaussian per mode in the filter and in the backward message),
    so the tolerance is that of an approximation, set from what it measured on these problems
    (mode probabilities ≤ 0.121 off, means ≤ 0.20 posterior std, covariances ≤ 8 % of the
    largest entry) with a margin: 0.15, 0.3 std, 12 %. Checked against what the smoother is
    for: it is much closer to the exact smoothed posterior than the filter is (the filter's
    means are 1.7–5 std off here)."""
    sm, out, ex = _compare(_problem(M, T=6, rates=SWITCHING[M], seed=seed), M)
    e = _errors(sm, out, ex)
    assert e["prob"] < 0.15, e
    assert e["mean"] < 0.3, e
    assert e["cov"] < 0.12, e
    assert e["mean"] < 0.25 * e["filter_mean"], e


def test_well_separated_modes_are_nearly_exact() -> None:
    """A track that sits still and then moves at 3 m/s, precise reports, rare switches (1/100 s):
    the mode history is nearly certain, and the smoothed mode probabilities are within 1.3e-4 of
    the exact ones (0.12 on the overlapping problems above; the filter's are 0.92 off here), the
    covariances within 0.2 %; the means keep the forward filter's one-Gaussian-per-mode error
    (measured 0.24 posterior std). Tolerances: 1e-3, 0.5 %, 0.35 std."""
    g = torch.Generator().manual_seed(3)
    T, M = 6, 2
    cv = tl.models.constant_velocity(dim=2, q=0.05, dtype=D64)
    moored = tl.models.moored(k=0.8, q=0.001, dim=2, dtype=D64)
    dt = torch.full((T,), 1.0, dtype=D64)
    pos = torch.cat([torch.zeros(3), 3.0 * torch.arange(1, 4, dtype=D64)]).to(D64)
    y = torch.stack([pos, 0.5 * pos], -1) + 0.1 * torch.randn(T, 2, generator=g, dtype=D64)
    A, Q, Pi = _matrices([moored, cv], dt, [[0.0, 0.01], [0.01, 0.0]])
    H = tl.models.position_observation(cv).expand(M, 2, 4)
    R = 0.01 * torch.eye(2, dtype=D64).expand(M, 2, 2)
    P0 = torch.diag(torch.tensor([1.0, 0.01, 1.0, 0.01], dtype=D64)).expand(M, 4, 4)
    args = (y, A, Q, H, R, Pi, torch.zeros(M, 4, dtype=D64), P0, torch.tensor([0.5, 0.5], dtype=D64))
    sm, out, ex = _compare(args, M)
    e = _errors(sm, out, ex)
    assert e["prob"] < 1e-3 and e["cov"] < 5e-3 and e["mean"] < 0.35, e
    assert e["filter_prob"] > 0.5, e  # (what the smoother fixes: the filter's mode probabilities)


# ---------------------------------------------------------------- batch, dtypes, gradients, errors
def _switching_imm(dtype: torch.dtype = D64, **kw: object) -> tl.IMMFilter:
    models = _bank(dtype)
    H = tl.models.position_observation(models[0])
    R = torch.tensor([[1.0, 0.2], [0.2, 0.7]], dtype=dtype)
    rates = torch.tensor(SWITCHING[3], dtype=dtype)
    return tl.IMMFilter(models, H, R, rates, P0=4.0 * torch.eye(4, dtype=dtype), **kw)


def test_batched_tracks_with_their_own_gaps_equal_one_track_at_a_time() -> None:
    imm = _switching_imm()
    y, dt = _tracks(B=4, T=8)
    y[3] = float("nan")  # a track with no report at all
    sm = imm.smooth(imm(y, dt))
    for b in range(4):
        one = imm.smooth(imm(y[b], dt[b]))
        for name in ("mean", "cov", "mode_probabilities", "mode_mean", "mode_cov"):
            torch.testing.assert_close(getattr(sm, name)[b], getattr(one, name), rtol=1e-12, atol=1e-12)
    assert torch.isfinite(sm.cov).all()
    # without a report the smoother has nothing to add: it is the filter (a pure prediction)
    out = imm(y[3], dt[3])
    torch.testing.assert_close(imm.smooth(out).mean, out.mean, rtol=0, atol=1e-9)


def test_missing_reports_carry_no_information() -> None:
    """A NaN report, a masked one and a report left out of the model (H row 0 via mask) agree."""
    imm = _switching_imm()
    y, dt = _tracks(B=3, T=7)
    mask = torch.ones(3, 7, dtype=torch.bool)
    mask[0, 4] = False
    a = imm.smooth(imm(y, dt, mask=mask))
    y2 = y.clone()
    y2[0, 4] = float("nan")
    b = imm.smooth(imm(y2, dt))
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=1e-12)
    y3 = y2.clone()
    y3[0, 4] = 1e6  # a wild value where the report is masked out: not read
    c = imm.smooth(imm(y3, dt, mask=mask))
    torch.testing.assert_close(c.mean, b.mean, rtol=0, atol=1e-12)


def test_float32_agrees_with_float64_and_stays_psd() -> None:
    y, dt = _tracks(B=3, T=12)
    a = _switching_imm(D64)
    b = _switching_imm(torch.float32)
    s64 = a.smooth(a(y, dt))
    s32 = b.smooth(b(y.float(), dt.float()))
    assert s32.mean.dtype == torch.float32
    torch.testing.assert_close(s32.mean.double(), s64.mean, rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(s32.mode_probabilities.double(), s64.mode_probabilities, rtol=0, atol=1e-3)
    for cov in (s32.cov, s32.mode_cov):
        assert torch.allclose(cov, cov.mT)
        assert bool((torch.linalg.eigvalsh(cov.double()) > -1e-5 * cov.double().abs().amax((-2, -1))[..., None]).all())


def test_gradcheck_through_filter_and_smoother() -> None:
    """float64 gradcheck of the smoothed mean, covariance and mode probabilities with respect to
    the reports, the process noises, R and the chain (a tiny case: B = 1, T = 3, M = 2)."""
    g = torch.Generator().manual_seed(0)
    T, M = 3, 2
    dt = torch.tensor([0.5, 1.0, 0.7], dtype=D64)
    A, Q, _ = _matrices(_bank()[:M], dt, [[0.0, 0.3], [0.2, 0.0]])
    H = tl.models.position_observation(_bank()[0])
    y0 = torch.randn(T, 2, generator=g, dtype=D64)
    P0 = 2.0 * torch.eye(4, dtype=D64)

    def smoothed(y: torch.Tensor, q: torch.Tensor, Rf: torch.Tensor, rates: torch.Tensor):  # noqa: ANN202
        Lam = torch.stack([torch.stack([-rates[0], rates[0]]), torch.stack([rates[1], -rates[1]])])
        Pi = torch.matrix_exp(Lam * dt[:, None, None])
        R = Rf @ Rf.mT + 0.1 * torch.eye(2, dtype=D64)
        out = imm_filter(y, A, Q * q[:, None, None], H, R, Pi, torch.zeros(4, dtype=D64), P0,
                         torch.tensor([0.4, 0.6], dtype=D64))  # fmt: skip
        sm = imm_smoother(out)
        return sm.mean, sm.cov, sm.mode_probabilities, sm.mode_cov

    args = (
        y0.clone().requires_grad_(),
        torch.tensor([1.0, 0.7], dtype=D64, requires_grad=True),
        torch.tensor([[0.8, 0.0], [0.1, 0.6]], dtype=D64, requires_grad=True),
        torch.tensor([0.3, 0.2], dtype=D64, requires_grad=True),
    )
    assert torch.autograd.gradcheck(smoothed, args, fast_mode=True)


def test_bad_arguments_raise() -> None:
    imm = _switching_imm()
    y, dt = _tracks(B=3, T=7)
    out = imm(y, dt)
    with pytest.raises(TypeError, match="IMMResult"):
        imm_smoother(out[:3])  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="Pi of shape"):
        imm_smoother(out, Pi=torch.eye(2, dtype=D64))
    with pytest.raises(ValueError, match="A of shape"):
        imm_smoother(out, A=torch.eye(3, dtype=D64))
    old = out._replace(transition=None)
    with pytest.raises(ValueError, match="result has no A"):
        imm_smoother(old)
    # explicit matrices equal the stored ones
    again = imm_smoother(old, A=out.transition)
    torch.testing.assert_close(again.mean, imm.smooth(out).mean, rtol=0, atol=0)


def test_public_names() -> None:
    assert tl.imm_smoother is imm_smoother
    assert tl.filters.imm_smoother is imm_smoother
    assert tl.IMMSmootherResult._fields == ("mean", "cov", "mode_probabilities", "mode_mean", "mode_cov")
