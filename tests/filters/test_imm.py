"""IMM filter (filters/imm.py, nn/imm.py): vs KalmanFilter, vs filterpy's IMMEstimator, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from torchsde_lti.filters.imm import imm_filter
from torchsde_lti.nn.parametrizations import Generator

D64 = torch.float64


def _bank(dtype: torch.dtype = D64) -> list[tl.LTISDE]:
    cv = tl.models.constant_velocity(dim=2, q=torch.tensor(0.3, dtype=dtype))
    ou = tl.models.integrated_ou(k=torch.tensor(0.5, dtype=dtype), q=torch.tensor(2.0, dtype=dtype), dim=2)
    return [cv, ou]


def _data(B: int = 3, T: int = 9, dtype: torch.dtype = D64, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    y = torch.randn(B, T, 2, generator=g, dtype=dtype).cumsum(1)
    dt = 0.2 + 2.0 * torch.rand(B, T, generator=g, dtype=dtype)
    return y, dt


def _imm(models: list[tl.LTISDE], rates: torch.Tensor, **kw: object) -> tl.IMMFilter:
    dtype = models[0].dtype
    H = tl.models.position_observation(models[0])
    R = torch.tensor([[1.0, 0.2], [0.2, 0.7]], dtype=dtype)
    return tl.IMMFilter(models, H, R, rates, P0=4.0 * torch.eye(4, dtype=dtype), **kw)


def test_one_mode_equals_kalman_filter() -> None:
    sde = _bank()[1]
    y, dt = _data()
    y[1, 3] = float("nan")
    imm = _imm([sde], torch.zeros(1, 1, dtype=D64), learn=("R",))
    kf = tl.KalmanFilter(sde, imm.H, imm.R.detach(), P0=imm.P0.detach())
    a, b = imm(y, dt), kf(y, dt)
    torch.testing.assert_close(a.step_log_likelihood, b.step_log_likelihood, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(a.mean, b.mean, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(a.cov, b.cov, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(a.pred_mean, b.pred_mean, rtol=1e-12, atol=1e-10)
    assert torch.equal(a.mode_probabilities, torch.ones_like(a.mode_probabilities))


@pytest.mark.parametrize("mode", [0, 1])
def test_no_switching_known_mode_equals_that_filter(mode: int) -> None:
    models = _bank()
    y, dt = _data()
    p0 = torch.zeros(2, dtype=D64)
    p0[mode] = 1.0
    imm = _imm(models, torch.zeros(2, 2, dtype=D64), mode_prob0=p0, learn=())
    kf = tl.KalmanFilter(models[mode], imm.H, imm.R, P0=imm.P0)
    a, b = imm(y, dt), kf(y, dt)
    torch.testing.assert_close(a.log_likelihood, b.log_likelihood, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(a.mean, b.mean, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(a.mode_probabilities[..., mode], torch.ones_like(a.mode_probabilities[..., 0]))


def test_regular_dt_equals_filterpy_imm_estimator() -> None:
    filterpy = pytest.importorskip("filterpy.kalman")
    from scipy.linalg import expm

    models = _bank()
    h = 0.7
    T = 25
    rates = torch.tensor([[0.0, 0.15], [0.4, 0.0]], dtype=D64)
    p0 = torch.tensor([0.3, 0.7], dtype=D64)
    imm = _imm(models, rates, mode_prob0=p0)
    y, _ = _data(B=1, T=T, seed=3)
    y = 3.0 * y[0]
    dt = torch.full((T,), h, dtype=D64)
    out = imm(y, dt)
    Pi = expm(imm.rates.detach().numpy() * h)
    d = [tl.discretize(s.F, s.L, s.Qc, h) for s in models]
    H, R, P0 = imm.H.numpy(), imm.R.detach().numpy(), imm.P0.detach().numpy()
    fs = []
    for dm in d:
        f = filterpy.KalmanFilter(dim_x=4, dim_z=2)
        f.F, f.Q = dm.A.detach().numpy(), dm.Q.detach().numpy()
        f.H, f.R, f.P, f.x = H.copy(), R.copy(), P0.copy(), np.zeros((4, 1))
        fs.append(f)
    est = filterpy.IMMEstimator(fs, p0.numpy().copy(), Pi)
    for k in range(T):
        est.predict()
        cbar = est.cbar.copy()
        est.update(y[k].numpy().reshape(2, 1))
        ll = np.log(cbar @ est.likelihood)
        np.testing.assert_allclose(out.step_log_likelihood[k].item(), ll, rtol=0, atol=1e-8)
        np.testing.assert_allclose(out.mode_probabilities[k].detach().numpy(), est.mu, rtol=0, atol=1e-8)
        np.testing.assert_allclose(out.mean[k].detach().numpy(), est.x.ravel(), rtol=0, atol=1e-8)
        np.testing.assert_allclose(out.cov[k].detach().numpy(), est.P, rtol=1e-8, atol=1e-8)
        for j in range(2):
            np.testing.assert_allclose(out.mode_mean[k, j].detach().numpy(), fs[j].x.ravel(), rtol=0, atol=1e-8)


def test_batched_equals_loop() -> None:
    imm = _imm(_bank(), torch.tensor([[0.0, 0.1], [0.3, 0.0]], dtype=D64))
    y, dt = _data(B=4)
    y[2, 4:] = float("nan")
    out = imm(y, dt)
    for b in range(4):
        one = imm(y[b], dt[b])
        torch.testing.assert_close(out.step_log_likelihood[b], one.step_log_likelihood, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out.mode_probabilities[b], one.mode_probabilities, rtol=1e-12, atol=1e-12)


def test_unique_dt_matches_plain_path() -> None:
    models = _bank()
    rates = torch.tensor([[0.0, 0.1], [0.3, 0.0]], dtype=D64)
    y, dt = _data()
    dt = torch.round(dt * 2) / 2
    a = _imm(models, rates)(y, dt)
    b = _imm(models, rates, unique_dt=True)(y, dt)
    torch.testing.assert_close(a.step_log_likelihood, b.step_log_likelihood, rtol=1e-13, atol=1e-12)


def test_gradcheck_F_Qc_R_rates() -> None:
    y, dt = _data(B=2, T=4)
    y[0, 1] = float("nan")
    H = tl.models.position_observation(_bank()[0])
    P0 = 4.0 * torch.eye(4, dtype=D64)

    def ll(Fv: torch.Tensor, qc: torch.Tensor, Rf: torch.Tensor, raw: torch.Tensor) -> torch.Tensor:
        F = torch.zeros(4, 4, dtype=D64)
        F = F.index_put((torch.tensor([0, 2]), torch.tensor([1, 3])), torch.ones(2, dtype=D64))
        F = F.index_put((torch.tensor([1, 1, 3, 3]), torch.tensor([1, 3, 1, 3])), Fv.reshape(-1))
        L = torch.tensor([[0, 0], [1, 0], [0, 0], [0, 1]], dtype=D64)
        Qc = qc @ qc.mT + 0.1 * torch.eye(2, dtype=D64)
        mo = tl.models.moored(k=torch.tensor(0.8, dtype=D64), q=torch.tensor(0.05, dtype=D64)).matrices()
        Fs = torch.stack([F, mo.F])
        Ws = torch.stack([L @ Qc @ L.mT, mo.L @ mo.Qc @ mo.L.mT])
        d = tl.discretize(Fs, torch.eye(4, dtype=D64), Ws, dt.unsqueeze(-1))
        Lam = Generator().to(dtype=D64)(raw)
        Pi = torch.matrix_exp(Lam * dt[..., None, None])
        R = Rf @ Rf.mT + 0.5 * torch.eye(2, dtype=D64)
        p0 = torch.tensor([0.6, 0.4], dtype=D64)
        return imm_filter(y, d.A, d.Q, H, R, Pi, torch.zeros(4, dtype=D64), P0, p0).log_likelihood

    args = (
        torch.tensor([[-0.3, 0.1], [-0.05, -0.2]], dtype=D64, requires_grad=True),
        torch.tensor([[0.5, 0.0], [0.2, 0.4]], dtype=D64, requires_grad=True),
        torch.tensor([[0.8, 0.0], [0.1, 0.6]], dtype=D64, requires_grad=True),
        torch.tensor([[0.0, -1.0], [0.5, 0.0]], dtype=D64, requires_grad=True),
    )
    assert torch.autograd.gradcheck(ll, args)


def test_module_gradients_reach_every_parameter() -> None:
    imm = _imm(_bank(), torch.tensor([[0.0, 0.1], [0.3, 0.0]], dtype=D64), learn=("R", "rates", "mode_prob0"))
    y, dt = _data()
    imm(y, dt).log_likelihood.sum().backward()
    for name, p in imm.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


def test_missing_steps_and_all_missing_track_finite_gradients() -> None:
    imm = _imm(_bank(), torch.tensor([[0.0, 0.1], [0.3, 0.0]], dtype=D64), learn=("R", "rates"))
    y, dt = _data()
    y[0, 2:5] = float("nan")
    y[1] = float("nan")
    y[2, 3, 0] = float("nan")  # one component only
    mask = torch.ones(3, 9, dtype=torch.bool)
    mask[2, 7] = False
    out = imm(y, dt, mask=mask)
    assert torch.isfinite(out.mean).all() and torch.isfinite(out.cov).all()
    assert float(out.log_likelihood[1].detach()) == 0.0
    assert torch.all(out.step_log_likelihood[0, 2:5] == 0)
    # a fully missing step keeps the predicted mode probabilities
    torch.testing.assert_close(out.mode_probabilities[0, 2], out.pred_mode_probabilities[0, 2])
    out.log_likelihood.sum().backward()
    for name, p in imm.named_parameters():
        assert torch.isfinite(p.grad).all(), name


def test_float32_runs_and_agrees_with_float64() -> None:
    rates = torch.tensor([[0.0, 0.1], [0.3, 0.0]])
    y, dt = _data()
    out64 = _imm(_bank(D64), rates.double())(y, dt)
    out32 = _imm(_bank(torch.float32), rates.float())(y.float(), dt.float())
    assert out32.log_likelihood.dtype == torch.float32
    torch.testing.assert_close(out32.log_likelihood.double(), out64.log_likelihood, rtol=1e-4, atol=1e-3)
    torch.testing.assert_close(out32.mode_probabilities.double(), out64.mode_probabilities, rtol=1e-3, atol=1e-4)


def test_forecast_no_switching_matches_kalman_forecast() -> None:
    models = _bank()
    imm = _imm(models, torch.zeros(2, 2, dtype=D64), mode_prob0=torch.tensor([0.0, 1.0], dtype=D64), learn=())
    kf = tl.KalmanFilter(models[1], imm.H, imm.R, P0=imm.P0)
    y, dt = _data()
    h = torch.tensor([1.0, 5.0], dtype=D64)
    a, b = imm.forecast(imm(y, dt), h), kf.forecast(kf(y, dt), h)
    torch.testing.assert_close(a.obs_mean, b.obs_mean, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(a.obs_cov, b.obs_cov, rtol=1e-12, atol=1e-10)


def test_generator_parametrisation() -> None:
    gen = Generator().to(dtype=D64)
    raw = torch.tensor([[3.0, -800.0, 900.0], [1.0, 0.0, 2.0], [-5.0, 5.0, 7.0]], dtype=D64)
    lam = gen(raw)
    assert torch.isfinite(lam).all()
    off = ~torch.eye(3, dtype=torch.bool)
    assert (lam[off] > 0).all()
    torch.testing.assert_close(lam.sum(-1), torch.zeros(3, dtype=D64), rtol=0, atol=1e-12)
    rates = torch.tensor([[0.0, 0.1, 0.02], [0.3, 0.0, 1.0], [0.5, 0.01, 0.0]], dtype=D64)
    back = gen(gen.right_inverse(rates))
    torch.testing.assert_close(back[off], rates[off])
    imm = _imm(_bank(), rates[:2, :2])
    imm.rates = torch.tensor([[0.0, 0.25], [0.5, 0.0]], dtype=D64)
    torch.testing.assert_close(imm.rates, torch.tensor([[-0.25, 0.25], [0.5, -0.5]], dtype=D64))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"rates": torch.zeros(3, 3, dtype=D64)}, "rates"),
        ({"rates": torch.tensor([[0.0, -1.0], [1.0, 0.0]], dtype=D64)}, "rates"),
        ({"R": torch.eye(3, dtype=D64)}, "R"),
        ({"H": torch.ones(2, 5, dtype=D64)}, "H"),
        ({"mode_prob0": torch.tensor([0.5, 0.6], dtype=D64)}, "mode_prob0"),
        ({"P0": torch.eye(3, dtype=D64)}, "P0"),
    ],
)
def test_bad_module_arguments_raise(kwargs: dict, match: str) -> None:
    models = _bank()
    args = {
        "H": tl.models.position_observation(models[0]),
        "R": torch.eye(2, dtype=D64),
        "rates": torch.tensor([[0.0, 0.1], [0.3, 0.0]], dtype=D64),
        **kwargs,
    }
    with pytest.raises(ValueError, match=match):
        tl.IMMFilter(models, args.pop("H"), args.pop("R"), args.pop("rates"), **args)


def test_bad_call_arguments_raise() -> None:
    imm = _imm(_bank(), torch.tensor([[0.0, 0.1], [0.3, 0.0]], dtype=D64))
    y, dt = _data()
    with pytest.raises(ValueError, match="dt"):
        imm(y, dt[:, :-1])
    with pytest.raises(ValueError, match="dt"):
        imm(y, -dt)
    with pytest.raises(ValueError, match="y"):
        imm(y[..., :1], dt)
    with pytest.raises(ValueError, match="mask"):
        imm(y, dt, mask=torch.ones(3, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="models"):
        tl.IMMFilter(
            [_bank()[0], tl.models.constant_acceleration(dim=2, q=torch.tensor(1.0, dtype=D64))],
            torch.eye(2, 4, dtype=D64),
            torch.eye(2, dtype=D64),
            torch.zeros(2, 2, dtype=D64),
            learn=(),
        )
    A = torch.eye(4, dtype=D64).expand(9, 2, 4, 4)
    H = torch.eye(2, 4, dtype=D64)
    with pytest.raises(ValueError, match="Pi"):
        imm_filter(
            y,
            A,
            0 * A,
            H,
            torch.eye(2, dtype=D64),
            torch.ones(9, 2, 2, dtype=D64),
            torch.zeros(4, dtype=D64),
            torch.eye(4, dtype=D64),
            torch.tensor([0.5, 0.5], dtype=D64),
        )
    with pytest.raises(ValueError, match="A"):
        imm_filter(
            y,
            torch.eye(4, dtype=D64).expand(9, 3, 4, 4),
            0 * A,
            H,
            torch.eye(2, dtype=D64),
            torch.eye(2, dtype=D64),
            torch.zeros(4, dtype=D64),
            torch.eye(4, dtype=D64),
            torch.tensor([0.5, 0.5], dtype=D64),
        )


def test_subnormal_mode_probability_through_zero_dt_padding_has_finite_gradients() -> None:
    """A subnormal mode weight c_j (a posterior that underflowed, kept through zero-dt padding
    steps where Pi = I) used to reach the mixing division ``joint / c``, whose backward
    ``joint / c²`` overflowed: NaN gradients (seen as skipped L-BFGS steps on AIS)."""
    import torchsde_lti as tl
    from torchsde_lti import models

    moored = models.moored(k=1.0, q=1e-3, dim=1, dtype=D64)
    underway = models.integrated_ou(k=0.01, q=1.0, dim=1, dtype=D64)
    H = models.position_observation(underway)
    R = torch.stack([1e-2 * torch.eye(1), 1.0 * torch.eye(1)]).to(D64)
    tiny = 1e-310  # subnormal in float64
    imm = tl.IMMFilter(
        [moored, underway],
        H,
        R,
        torch.tensor([[0.0, 1e-3], [1e-3, 0.0]], dtype=D64),
        m0=torch.zeros(2, dtype=D64),
        P0=torch.eye(2, dtype=D64),
        mode_prob0=torch.tensor([tiny, 1.0 - tiny], dtype=D64),
        learn=("R", "rates", "P0"),
    )
    y = torch.tensor([[math.nan], [math.nan], [0.5], [1.0]], dtype=D64)
    dt = torch.tensor([0.0, 0.0, 1.0, 1.0], dtype=D64)
    out = imm(y, dt)
    (-out.log_likelihood).backward()
    assert bool(torch.isfinite(out.log_likelihood))
    for name, p in imm.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name


def test_module_discretises_each_mode_once_as_its_kalman_filter_does(monkeypatch) -> None:
    """IMMFilter: each mode's series and the chain's formed once a call (not the bank broadcast
    to every (gap, mode) element), the same route for every batch size; each mode's A, Q equal
    a KalmanFilter's of that mode (the shared plumbing) and core's per-element discretize, and
    Pi equals torch.matrix_exp(Λ dt)."""
    import torchsde_lti.nn._online as nn_online
    import torchsde_lti.nn.imm as nn_imm

    f64 = torch.float64
    cv = tl.models.constant_velocity(dim=2, q=0.3, dtype=f64)
    iou = tl.models.integrated_ou(0.5, 1.0, dim=2, dtype=f64)
    H = tl.models.position_observation(cv)
    imm = tl.IMMFilter([cv, iou], H, torch.eye(2, dtype=f64), torch.ones(2, 2, dtype=f64))
    g = torch.Generator().manual_seed(0)
    y = torch.randn(5, 12, 2, generator=g, dtype=f64).cumsum(1)
    dt = torch.rand(5, 12, generator=g, dtype=f64) * 3.0
    calls = []
    for module in (nn_online, nn_imm):
        series = module.discretization_series
        monkeypatch.setattr(module, "discretization_series", lambda *a, _s=series, **k: calls.append(1) or _s(*a, **k))
    imm(y, dt)
    assert len(calls) == 3  # two modes and the chain
    with torch.no_grad():
        d, Pi = imm.discretize(dt)
        for j, sde in enumerate((cv, iou)):
            kf = tl.KalmanFilter(sde, H, torch.eye(2, dtype=f64))
            d_kf = kf._discretize(dt, series_layout=False)
            torch.testing.assert_close(d.A[..., j, :, :], d_kf.A, rtol=0, atol=0)
            # the same route; the modes ride as a batch dim of the products, so Q agrees to rounding
            torch.testing.assert_close(d.Q[..., j, :, :], d_kf.Q, rtol=1e-14, atol=1e-15)
            m = sde.matrices()
            ref = tl.discretize(m.F, m.L, m.Qc, dt, method="matrix_exp")
            torch.testing.assert_close(d.A[..., j, :, :], ref.A, rtol=1e-10, atol=1e-12)
            torch.testing.assert_close(d.Q[..., j, :, :], ref.Q, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(Pi, torch.matrix_exp(imm.rates * dt[..., None, None]), rtol=1e-10, atol=1e-12)
