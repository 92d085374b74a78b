"""The online API (issue 21): ``initial_state``, ``step``, ``predict`` of KalmanFilter and
IMMFilter, run report by report, equal the sequence filters over random series with missing
reports (NaN and mask) to 1e-12 in float64; tracks join and leave by indexing the state."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsde_lti as tl

F64 = torch.float64
H2 = [[1.0, 0, 0, 0], [0, 0, 1.0, 0]]


def _series(B: int, T: int, seed: int, dtype: torch.dtype = F64) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    y = torch.randn(B, T, 2, generator=g, dtype=dtype).cumsum(1)
    dt = torch.rand(B, T, generator=g, dtype=dtype) * 2.0
    dt[:, 0] = 0.0
    y[torch.rand(B, T, 2, generator=g) < 0.15] = float("nan")  # missing components
    mask = torch.rand(B, T, generator=g) > 0.15  # missing reports
    return y, dt, mask


def _kf(dtype: torch.dtype = F64, model: str = "cv") -> tl.KalmanFilter:
    """A two-axis tracker observing the positions: constant velocity (F nilpotent: the online
    step's terminating series), integrated OU or Singer (F not nilpotent: core's discretisation)."""
    if model == "cv":
        sde = tl.models.constant_velocity(dim=2, q=0.8, dtype=dtype)
    elif model == "iou":
        sde = tl.models.integrated_ou(0.7, 0.5, dim=2, dtype=dtype)
    else:
        sde = tl.models.singer(0.8, 0.5, dim=2, dtype=dtype)
    n = sde.state_dim
    m0 = torch.zeros(n, dtype=dtype)
    m0[[0, n // 2, n // 2 + 1]] = torch.tensor([0.5, -0.5, 0.1], dtype=dtype)
    R = torch.tensor([[0.3, 0.1], [0.1, 0.5]], dtype=dtype)
    return tl.KalmanFilter(
        sde,
        torch.eye(n, dtype=dtype)[[0, n // 2]],  # (H2 for the 4-state models)
        R,
        P0=20 * torch.eye(n, dtype=dtype),
        m0=m0,
        algorithm="sequential",
    )


@pytest.mark.parametrize("B", [1, 6, 300])
@pytest.mark.parametrize("model", ["cv", "iou", "singer"])
def test_kalman_step_equals_sequence_filter(model, B):
    """One step for every batch size (one track, a few, many), for a nilpotent F (cv: its
    terminating series) and F that are not (iou, Singer: the doubling's series)."""
    kf = _kf(model=model)
    y, dt, mask = _series(B, 40, seed=1)
    with torch.no_grad():
        ref = kf(y, dt, mask=mask)
        state = kf.initial_state((B,))
        for k in range(y.shape[1]):
            state, out = kf.step(state, y[:, k], dt[:, k], mask=mask[:, k])
            for got, want in (
                (state.mean, ref.mean[:, k]),
                (state.cov, ref.cov[:, k]),
                (out.pred_mean, ref.pred_mean[:, k]),
                (out.pred_cov, ref.pred_cov[:, k]),
                (out.innovation, ref.innovation[:, k]),
                (out.innovation_cov, ref.innovation_cov[:, k]),
                (out.log_likelihood, ref.step_log_likelihood[:, k]),
                (out.observed, ref.observed[:, k]),
            ):
                torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


def test_kalman_step_without_missing_reports():
    """Every report present, float64 and float32."""
    for dtype, tol in ((F64, 1e-12), (torch.float32, 2e-3)):
        kf = _kf(dtype)
        y, dt, _ = _series(4, 25, seed=8, dtype=dtype)
        y = torch.nan_to_num(y)
        with torch.no_grad():
            ref = kf(y, dt)
            state = kf.initial_state(4)
            for k in range(25):
                state, out = kf.step(state, y[:, k], dt[:, k])
                torch.testing.assert_close(state.cov, ref.cov[:, k], rtol=0, atol=tol)
                torch.testing.assert_close(out.log_likelihood, ref.step_log_likelihood[:, k], rtol=0, atol=tol)
            torch.testing.assert_close(state.mean, ref.mean[:, -1], rtol=0, atol=tol)


def test_kalman_step_float32_and_per_component_mask():
    kf = _kf(torch.float32)
    y, dt, _ = _series(3, 20, seed=2, dtype=torch.float32)
    mask = torch.rand(3, 20, 2, generator=torch.Generator().manual_seed(3)) > 0.3
    with torch.no_grad():
        ref = kf(y, dt, mask=mask)
        state = kf.initial_state(3)
        for k in range(20):
            state, _ = kf.step(state, y[:, k], dt[:, k], mask=mask[:, k])
        assert state.mean.dtype == torch.float32
        torch.testing.assert_close(state.mean, ref.mean[:, -1], rtol=1e-4, atol=1e-4)


def test_predict_equals_forecast_and_missing_report():
    kf = _kf()
    state = kf.initial_state((4,))
    dt = torch.tensor([0.0, 0.5, 1.0, 3.0], dtype=F64)
    with torch.no_grad():
        pred = kf.predict(state, dt)
        fc = kf.forecast((state.mean, state.cov), dt.unsqueeze(-1))
        torch.testing.assert_close(pred.mean, fc.mean[:, 0], rtol=0, atol=1e-12)
        torch.testing.assert_close(pred.cov, fc.cov[:, 0], rtol=0, atol=1e-12)
        # a missing report is a pure prediction with zero log-likelihood
        new, out = kf.step(state, torch.full((4, 2), float("nan"), dtype=F64), dt)
        torch.testing.assert_close(new.cov, pred.cov, rtol=0, atol=1e-12)
        assert bool((out.log_likelihood == 0).all())


def test_tracks_join_and_leave_by_indexing():
    kf = _kf()
    y, dt, _ = _series(5, 12, seed=4)
    y = torch.nan_to_num(y)
    with torch.no_grad():
        ref = kf(y, dt)
        ref_late = kf(y[:2, 6:], dt[:2, 6:])  # two tracks starting at step 6
        state = kf.initial_state((5,))
        for k in range(6):
            state, _ = kf.step(state, y[:, k], dt[:, k])
        keep = torch.tensor([True, False, True, True, False])
        state = state.select(keep)  # tracks 1 and 4 leave
        state = tl.KalmanState.cat([state, kf.initial_state((2,))])  # two new tracks join
        y_now = torch.cat([y[keep, 6:], y[:2, 6:]])
        dt_now = torch.cat([dt[keep, 6:], dt[:2, 6:]])
        for k in range(6):
            state, _ = kf.step(state, y_now[:, k], dt_now[:, k])
        torch.testing.assert_close(state.mean[:3], ref.mean[keep, -1], rtol=0, atol=1e-12)
        torch.testing.assert_close(state.mean[3:], ref_late.mean[:, -1], rtol=0, atol=1e-12)
        # the generic form for any state NamedTuple
        sub = type(state)(*(t[[0, 4]] for t in state))
        torch.testing.assert_close(sub.cov, state.cov[[0, 4]])


def test_step_gating_statistic_is_chi_square():
    kf = _kf()
    state = kf.initial_state(())
    state, _ = kf.step(state, torch.tensor([0.1, 0.2], dtype=F64), 0.0)
    _, out = kf.step(state, torch.tensor([0.5, -0.1], dtype=F64), 1.0)
    e, S = out.innovation, out.innovation_cov
    d2 = e @ torch.linalg.solve(S, e)
    expected_ll = -0.5 * (d2 + torch.logdet(2 * torch.pi * S))
    torch.testing.assert_close(out.log_likelihood, expected_ll, rtol=0, atol=1e-12)


def test_step_gradients_float64():
    kf = _kf()
    y = torch.tensor([[0.3, -0.2], [1.0, 0.4]], dtype=F64)
    dt = torch.tensor([0.4, 1.3], dtype=F64, requires_grad=True)
    state = kf.initial_state(2)

    def f(dt_: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
        new, out = kf.step(tl.KalmanState(mean, state.cov), y, dt_)
        return out.log_likelihood.sum() + new.mean.sum()

    assert torch.autograd.gradcheck(f, (dt, state.mean.detach().clone().requires_grad_(True)))
    kf.step(state, y, dt)[1].log_likelihood.sum().backward()  # R is learned (the default learn)
    grads = [p.grad for p in kf.parameters() if p.requires_grad]
    assert grads and all(g is not None and bool(torch.isfinite(g).all()) for g in grads)


def test_step_validates_arguments():
    kf = _kf()
    state = kf.initial_state(2)
    with pytest.raises(ValueError, match="y must have shape"):
        kf.step(state, torch.zeros(2, 3, dtype=F64), torch.ones(2, dtype=F64))
    with pytest.raises(ValueError, match="dt"):
        kf.step(state, torch.zeros(2, 2, dtype=F64), torch.tensor([1.0, -1.0], dtype=F64))
    with pytest.raises(ValueError, match="state must be"):
        kf.step(tl.KalmanState(state.mean[:, :3], state.cov), torch.zeros(2, 2, dtype=F64), 1.0)
    with pytest.raises(TypeError, match="KalmanState"):
        kf.step(state.mean, torch.zeros(2, 2, dtype=F64), 1.0)
    kf.validate_args = False  # the hot loop: no value checks (no host sync for them)
    kf.step(state, torch.zeros(2, 2, dtype=F64), torch.tensor([1.0, 2.0], dtype=F64))


def _imm(dtype: torch.dtype = F64) -> tl.IMMFilter:
    cv = tl.models.constant_velocity(dim=2, q=0.5, dtype=dtype)
    iou = tl.models.integrated_ou(1.5, 0.05, dim=2, dtype=dtype)
    return tl.IMMFilter(
        [cv, iou],
        torch.tensor(H2, dtype=dtype),
        0.4 * torch.eye(2, dtype=dtype),
        torch.tensor([[0.0, 0.2], [0.4, 0.0]], dtype=dtype),
        P0=30 * torch.eye(4, dtype=dtype),
        mode_prob0=torch.tensor([0.3, 0.7], dtype=dtype),
    )


def test_imm_step_equals_sequence_filter():
    imm = _imm()
    y, dt, mask = _series(5, 40, seed=5)
    with torch.no_grad():
        ref = imm(y, dt, mask=mask)
        state = imm.initial_state((5,))
        for k in range(y.shape[1]):
            state, out = imm.step(state, y[:, k], dt[:, k], mask=mask[:, k])
            for got, want in (
                (state.mode_prob, ref.mode_probabilities[:, k]),
                (state.mode_mean, ref.mode_mean[:, k]),
                (state.mode_cov, ref.mode_cov[:, k]),
                (out.mean, ref.mean[:, k]),
                (out.cov, ref.cov[:, k]),
                (out.pred_mode_prob, ref.pred_mode_probabilities[:, k]),
                (out.mode_innovation, ref.mode_innovation[:, k]),
                (out.mode_innovation_cov, ref.mode_innovation_cov[:, k]),
                (out.log_likelihood, ref.step_log_likelihood[:, k]),
                (out.observed, ref.observed[:, k]),
            ):
                torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


def test_imm_predict_equals_forecast_and_indexing():
    imm = _imm()
    y, dt, _ = _series(3, 8, seed=6)
    with torch.no_grad():
        state = imm.initial_state(3)
        for k in range(8):
            state, _ = imm.step(state, y[:, k], dt[:, k])
        h = torch.tensor([0.5, 1.0, 2.0], dtype=F64)
        pred = imm.predict(state, h)  # the filter's own prediction (mixing once, then the modes)
        fc = imm.forecast(tuple(state), h.unsqueeze(-1))  # the exact moments of the switching SDE
        torch.testing.assert_close(pred.mode_prob, fc.mode_probabilities[:, 0], rtol=0, atol=1e-12)
        mean = (pred.mode_prob.unsqueeze(-1) * pred.mode_mean).sum(-2)
        torch.testing.assert_close(mean, fc.mean[:, 0], rtol=0.02, atol=0.02)  # switches within h: a little apart
        two = tl.IMMState.cat([state.select([0]), state.select(slice(2, 3))])
        torch.testing.assert_close(two.mode_mean, state.mode_mean[[0, 2]])
    with pytest.raises(ValueError, match="no inputs"):
        imm.step(state, y[:, 0], dt[:, 0], u=torch.zeros(3, 1, dtype=F64))


def test_step_with_inputs_and_feedthrough_equals_sequence_filter():
    """u enters G u (the SDE's B) and y = H x + D u, as in the sequence filter."""
    sde = tl.models.constant_velocity(dim=1, q=0.3, dtype=F64)
    sde = tl.LTISDE(sde.F, sde.L, sde.Qc, B=torch.tensor([[0.5], [1.0]], dtype=F64))
    kf = tl.KalmanFilter(
        sde,
        torch.tensor([[1.0, 0.0]], dtype=F64),
        torch.tensor([[0.2]], dtype=F64),
        P0=5 * torch.eye(2, dtype=F64),
        D=torch.tensor([[0.3]], dtype=F64),
        algorithm="sequential",
    )
    g = torch.Generator().manual_seed(7)
    y = torch.randn(2, 15, 1, generator=g, dtype=F64)
    u = torch.randn(2, 15, 1, generator=g, dtype=F64)
    dt = torch.rand(2, 15, generator=g, dtype=F64)
    with torch.no_grad():
        ref = kf(y, dt, u=u)
        state = kf.initial_state(2)
        for k in range(15):
            state, out = kf.step(state, y[:, k], dt[:, k], u=u[:, k])
            torch.testing.assert_close(out.log_likelihood, ref.step_log_likelihood[:, k], rtol=0, atol=1e-12)
        torch.testing.assert_close(state.mean, ref.mean[:, -1], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="u must have shape"):
        kf.step(state, y[:, 0], dt[:, 0], u=torch.zeros(2, 3, dtype=F64))


def test_step_follows_parameter_changes_without_gradients():
    """The online calls evaluate the model once per parameter version under no_grad: an
    in-place optimiser-style update or a new R is seen by the next step."""
    kf = _kf()
    state = kf.initial_state(2)
    y = torch.tensor([[0.3, -0.2], [1.0, 0.4]], dtype=F64)
    dt = torch.tensor([0.4, 1.3], dtype=F64)
    with torch.no_grad():
        before = kf.step(state, y, dt)[1].log_likelihood
        assert torch.equal(kf.step(state, y, dt)[1].log_likelihood, before)  # cached model, same values
        for p in kf.parameters():
            p.mul_(1.5)
        after = kf.step(state, y, dt)[1].log_likelihood
        kf.R = torch.tensor([[2.0, 0.0], [0.0, 3.0]], dtype=F64)
        again = kf.step(state, y, dt)[1]
    with torch.enable_grad():
        want = kf.step(state, y, dt)[1]
    assert not torch.allclose(after, before)
    torch.testing.assert_close(again.innovation_cov, want.innovation_cov.detach(), rtol=0, atol=1e-12)
    torch.testing.assert_close(again.log_likelihood, want.log_likelihood.detach(), rtol=0, atol=1e-12)


def test_imm_step_follows_parameter_changes_without_gradients():
    imm = _imm()
    state = imm.initial_state(2)
    y = torch.tensor([[0.3, -0.2], [1.0, 0.4]], dtype=F64)
    dt = torch.tensor([0.4, 1.3], dtype=F64)
    with torch.no_grad():
        before = imm.step(state, y, dt)[1].log_likelihood
        for p in imm.parameters():
            p.mul_(1.3)
        after = imm.step(state, y, dt)[1].log_likelihood
    want = imm.step(state, y, dt)[1].log_likelihood.detach()  # evaluated afresh (gradients on)
    assert not torch.allclose(after, before)
    torch.testing.assert_close(after, want, rtol=0, atol=1e-12)


def _cv_closed_form(dt: float, q: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The textbook constant-velocity A, Q (one axis, state [x, v]): [[1, dt], [0, 1]] and
    q [[dt³/3, dt²/2], [dt²/2, dt]]."""
    A = torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=F64)
    Q = q * torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], dtype=F64)
    return A, Q


def test_terminating_series_equals_closed_form_and_van_loan():
    """The online step's closed-form discretisation of a nilpotent F (formed once per
    parameter version) equals the textbook constant-velocity A, Q and torch.matrix_exp of
    Van Loan's block (core's method="matrix_exp") for integrator chains of order 1-3, with an
    input matrix B and for F = 0; dt of any shape (0-dim, a batch, 0 and large gaps)."""
    from torchsde_lti.core.discretization import discretize
    from torchsde_lti.nn._online import model_series

    cv = tl.models.constant_velocity(dim=1, q=0.7, dtype=F64).matrices()
    series = model_series(*cv)
    assert series is not None
    for h in (0.0, 0.3, 1.7, 250.0):
        A, Q, G = series(torch.tensor(h, dtype=F64))
        A_want, Q_want = _cv_closed_form(h, 0.7)
        assert G is None and A.shape == Q.shape == (2, 2)
        torch.testing.assert_close(A, A_want, rtol=1e-14, atol=0)
        torch.testing.assert_close(Q, Q_want, rtol=1e-13, atol=1e-300)
    g = torch.Generator().manual_seed(4)
    B_in = torch.randn(4, 2, generator=g, dtype=F64)
    models = [  # (matrices, F's nilpotency index: the terminating series; None: the doubling's series)
        (tl.models.constant_acceleration(dim=2, q=0.4, dtype=F64).matrices(), 3),
        (tl.models.integrated_wiener(order=3, dim=1, q=1.3, dtype=F64).matrices(), 3),
        (tl.LTISDE(cv.F.new_tensor([[0.0, 2.0], [0.0, 0.0]]), cv.L, cv.Qc, B_in[:2]).matrices(), 2),
        (
            tl.LTISDE(
                torch.zeros(4, 4, dtype=F64), torch.eye(4, dtype=F64), 0.5 * torch.eye(4, dtype=F64), B_in
            ).matrices(),
            1,
        ),
        (tl.LTISDE(cv.F.new_tensor([[0.0, 2.0], [0.0, 0.0]]), cv.L, cv.Qc, B_in[:2]).matrices(), None),
    ]
    few = torch.rand(3, 5, generator=g, dtype=F64) * 4.0  # batch-first results
    few[0, 0] = 0.0
    many = torch.rand(2, 100, generator=g, dtype=F64) * 4.0
    for mats, _ in models:  # (the structural index: the series finds it itself)
        series = model_series(*mats)
        assert series is not None
        for dt in (few, many):
            A, Q, G = series(dt)
            want = discretize(*mats[:3], dt, B=mats.B, method="matrix_exp")
            n = mats.F.shape[-1]
            assert A.shape == Q.shape == (*dt.shape, n, n)
            torch.testing.assert_close(A, want.A, rtol=1e-12, atol=1e-12)
            torch.testing.assert_close(Q, want.Q, rtol=1e-12, atol=1e-12)
            if mats.B is None:
                assert G is None
            else:
                torch.testing.assert_close(G, want.G, rtol=1e-12, atol=1e-12)


def test_model_series_of_one_parameter_set():
    """A nilpotent F: its terminating series; any other F (Singer, OU): the doubling's series
    terms (SharedSeries), whose steps equal core's discretize to rounding and, where the Van
    Loan block is benign (dt ≤ 4), scipy's expm of it; a batch of parameters: None (core's
    discretisation then)."""
    import scipy.linalg

    from torchsde_lti.core.discretization import SharedSeries, discretize
    from torchsde_lti.nn._online import model_series

    dt = torch.tensor([0.0, 1e-5, 0.03, 0.7, 4.0, 60.0], dtype=F64)
    for sde in (tl.models.singer(0.5, 1.0, dim=2, dtype=F64), tl.models.ornstein_uhlenbeck(0.5, 1.0, dtype=F64)):
        mats = sde.matrices()
        with torch.no_grad():
            series = model_series(*mats)
            assert isinstance(series, SharedSeries)
            A, Q, _ = series(dt)
            ref = discretize(mats.F, mats.L, mats.Qc, dt)
        torch.testing.assert_close(A, ref.A, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(Q, ref.Q, rtol=1e-12, atol=1e-14)
        n = mats.F.shape[-1]
        F, W = mats.F.detach().numpy(), (mats.L @ mats.Qc @ mats.L.mT).detach().numpy()
        for k, h in enumerate(dt.tolist()[:-1]):
            E = scipy.linalg.expm(np.block([[F, W], [np.zeros((n, n)), -F.T]]) * h)
            np.testing.assert_allclose(A[k].numpy(), E[:n, :n], rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(Q[k].numpy(), E[:n, n:] @ E[:n, :n].T, rtol=1e-8, atol=1e-12)
    cv = tl.models.constant_velocity(dim=1, dtype=F64).matrices()
    with torch.no_grad():
        series = model_series(*cv)
        assert isinstance(series, SharedSeries) and bool(series.nilpotent)
    assert model_series(cv.F.expand(3, 2, 2), cv.L, cv.Qc, None) is None


def test_structural_series_for_integrator_chains():
    """Integrator chains (integrated_wiener: constant velocity, acceleration) fix F's
    nilpotency by their structure, so a traced program forms the series without reading F's
    values; the structural series equals the one found from the values. Other models: not structurally nilpotent."""
    from torchsde_lti.core.discretization import discretization_series
    from torchsde_lti.core.linalg import noise_covariance
    from torchsde_lti.nn._online import model_series

    for sde, order in (
        (tl.models.constant_velocity(dim=2, q=0.3, dtype=F64), 2),
        (tl.models.constant_acceleration(dim=1, q=2.0, dtype=F64), 3),
        (tl.models.integrated_wiener(order=1, dim=2, dtype=F64), 1),
    ):
        assert sde.structural_nilpotency() == order
        mats = sde.matrices()
        with torch.no_grad():
            by_values = discretization_series(mats.F, noise_covariance(mats.L, mats.Qc), None)
        by_structure = model_series(*mats)
        assert by_values is not None and by_structure is not None
        dt = torch.tensor([0.0, 0.4, 3.0], dtype=F64)
        for got, want in zip(by_structure(dt), by_values(dt)):
            torch.testing.assert_close(got, want, rtol=0, atol=0)
    for sde in (tl.models.singer(0.5, 1.0, dtype=F64), tl.models.ornstein_uhlenbeck(0.5, 1.0, dtype=F64)):
        assert sde.structural_nilpotency() is None
    cv = tl.models.constant_velocity(dim=1, dtype=F64).matrices()
    assert tl.LTISDE(cv.F, cv.L, cv.Qc).structural_nilpotency() is None  # a free F may be trained away from nilpotent


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_series_keeps_a_finite_transition_over_gaps_beyond_the_float_range_of_its_powers(dtype) -> None:
    """A constant-acceleration model over gaps whose x^5 overflows float32: A (exact, finite)
    equals core's, never inf · 0 = NaN (Q's exact entries overflow there); every batch size
    (joint and scalar layouts)."""
    from torchsde_lti.nn._online import model_series

    sde = tl.models.constant_acceleration(dim=1, q=1.0, dtype=dtype)
    m = sde.matrices()
    for b in (1, 300):
        dt = torch.logspace(6, 12, b, dtype=dtype) if b > 1 else torch.tensor([1e9], dtype=dtype)
        with torch.no_grad():
            series = model_series(*m)
            assert series is not None
            A, _, _ = series(dt)
            ref = tl.discretize(m.F, m.L, m.Qc, dt, validate_args=False)
        assert bool(A.isfinite().all())
        torch.testing.assert_close(A, ref.A, rtol=1e-6, atol=0)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_imm_step_many_tracks_long_gaps_equals_sequence_filter(dtype):
    """The IMM step with each mode's series (integrated OU: doubling over long gaps; constant
    velocity: its terminating series) over 80 tracks whose gaps reach 50 equals the sequence
    filter (core's discretisation of the whole bank), in float32 and float64."""
    imm = _imm(dtype)
    y, dt, mask = _series(80, 12, seed=9, dtype=dtype)
    dt = dt * torch.logspace(-2, 1.7, 12, dtype=dtype)
    tol = 1e-10 if dtype == F64 else 2e-3
    with torch.no_grad():
        ref = imm(y, dt, mask=mask)
        state = imm.initial_state(80)
        for k in range(12):
            state, out = imm.step(state, y[:, k], dt[:, k], mask=mask[:, k])
            torch.testing.assert_close(out.log_likelihood, ref.step_log_likelihood[:, k], rtol=tol, atol=tol)
        torch.testing.assert_close(state.mode_prob, ref.mode_probabilities[:, -1], rtol=tol, atol=tol)
        torch.testing.assert_close(out.mean, ref.mean[:, -1], rtol=tol, atol=tol * 10)


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_kalman_step_of_a_batch_equals_a_loop_over_its_tracks(dtype):
    """batch = loop: one step of B × C tracks equals the step of each track alone (values and
    gradients), with per-track, shared and broadcast A, Q, a second batch dimension, inputs,
    missing components and a mask."""
    online = tl.filters.online
    g = torch.Generator().manual_seed(11)
    B, C, n, m = 5, 3, 4, 2

    def spd(*shape: int) -> torch.Tensor:
        X = torch.randn(*shape, generator=g, dtype=F64)
        return (X @ X.mT / shape[-1] + 0.5 * torch.eye(shape[-1], dtype=F64)).to(dtype)

    mean = torch.randn(B, C, n, generator=g, dtype=F64).to(dtype)
    cov = spd(B, C, n, n)
    y = torch.randn(B, C, m, generator=g, dtype=F64).to(dtype)
    y[2, 1, 0] = float("nan")
    y[4] = float("nan")
    mask = torch.rand(B, C, generator=g) > 0.2
    cases = {
        "per track": (torch.randn(B, C, n, n, generator=g, dtype=F64).to(dtype) / 2, spd(B, C, n, n)),
        "shared": (torch.randn(n, n, generator=g, dtype=F64).to(dtype) / 2, spd(n, n)),
        "broadcast": (torch.randn(1, C, n, n, generator=g, dtype=F64).to(dtype) / 2, spd(B, 1, n, n)),
    }
    H, R = torch.randn(m, n, generator=g, dtype=F64).to(dtype), spd(C, m, m)
    c = torch.randn(B, 1, n, generator=g, dtype=F64).to(dtype)
    tol = 1e-12 if dtype == F64 else 1e-5
    for name, (A, Q) in cases.items():
        for extra in ({}, {"c": c, "mask": mask}):
            A_ = A.clone().requires_grad_(True)
            state, out = online.kalman_step(tl.KalmanState(mean, cov), y, A_, Q, H, R, **extra)
            (grad,) = torch.autograd.grad(out.log_likelihood.sum() + state.cov.sum(), A_)
            for b in range(B):
                for j in range(C):

                    def one(x: torch.Tensor, event: int) -> torch.Tensor:
                        full = x.expand(B, C, *x.shape[x.dim() - event :]) if x.dim() > event else x
                        return full[b, j] if x.dim() > event else x

                    kw = {k: one(v, 1 if k == "c" else 0) for k, v in extra.items()}
                    A1 = one(A, 2).detach().clone().requires_grad_(True)
                    s1, o1 = online.kalman_step(
                        tl.KalmanState(mean[b, j], cov[b, j]), y[b, j], A1, one(Q, 2), H, R[j], **kw
                    )
                    (g1,) = torch.autograd.grad(o1.log_likelihood + s1.cov.sum(), A1)
                    for got, want in zip((*s1, *o1), (*state, *out)):
                        torch.testing.assert_close(got, want[b, j], rtol=0, atol=tol, msg=name)
                    if name == "per track":  # (its own gradient)
                        torch.testing.assert_close(g1, grad[b, j], rtol=0, atol=tol, msg=name)


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_kalman_step_shared_observation_model_equals_masked_path(dtype):
    """The scalar updates of one (H, R) for every track with every report observed (one
    whitening of all reports) equal the general masked path (an all-True mask): values
    and gradients, per-track and shared A, Q, with and without an input term."""
    online = tl.filters.online
    g = torch.Generator().manual_seed(12)
    B, n, m = 9, 4, 2

    def spd(*shape: int) -> torch.Tensor:
        X = torch.randn(*shape, generator=g, dtype=F64)
        return (X @ X.mT / shape[-1] + 0.5 * torch.eye(shape[-1], dtype=F64)).to(dtype)

    mean = torch.randn(B, n, generator=g, dtype=F64).to(dtype)
    cov, y = spd(B, n, n), torch.randn(B, m, generator=g, dtype=F64).to(dtype)
    H, R = torch.randn(m, n, generator=g, dtype=F64).to(dtype), spd(m, m)
    c = torch.randn(B, n, generator=g, dtype=F64).to(dtype)
    A_cases = {"per track": (torch.randn(B, n, n, generator=g, dtype=F64).to(dtype), spd(B, n, n))}
    A_cases["shared"] = (torch.randn(n, n, generator=g, dtype=F64).to(dtype), spd(n, n))
    tol = 1e-12 if dtype == F64 else 1e-5
    for name, (A, Q) in A_cases.items():
        for extra in ({}, {"c": c}):
            runs = []
            for mask in (None, torch.ones(B, dtype=torch.bool)):
                A_ = A.clone().requires_grad_(True)
                state, out = online.kalman_step(tl.KalmanState(mean, cov), y, A_, Q, H, R, mask=mask, **extra)
                (grad,) = torch.autograd.grad(out.log_likelihood.sum() + state.cov.sum() + out.innovation_cov.sum(), A_)
                runs.append((*state, *out, grad))
            for got, want in zip(runs[0], runs[1]):
                assert got.shape == want.shape and got.dtype == want.dtype, name
                torch.testing.assert_close(got, want, rtol=0, atol=tol, msg=name)


def test_initial_state_broadcasts_with_a_parameter_batch_and_checks_batch_shape() -> None:
    """A model with a parameter batch (3 OU rates) starts 3 tracks per shape element (the
    sequence filter broadcasts the same way); the online steps from that state equal the
    sequence filter; a negative or non-broadcasting batch_shape is a ValueError naming it."""
    ou = tl.models.ornstein_uhlenbeck(torch.tensor([0.5, 1.0, 2.0], dtype=F64), 1.0)
    kf = tl.KalmanFilter(ou, torch.tensor([[1.0]], dtype=F64), torch.tensor([[0.3]], dtype=F64))
    assert [tuple(t.shape) for t in kf.initial_state()] == [(3, 1), (3, 1, 1)]
    state = kf.initial_state((2, 1))
    assert [tuple(t.shape) for t in state] == [(2, 3, 1), (2, 3, 1, 1)]
    g = torch.Generator().manual_seed(4)
    y, dt = torch.randn(2, 1, 4, 1, generator=g, dtype=F64), torch.rand(2, 1, 4, generator=g, dtype=F64)
    out = kf(y, dt)
    with torch.no_grad():
        for k in range(4):
            state, step = kf.step(state, y[:, :, k], dt[:, :, k])
            torch.testing.assert_close(state.mean, out.mean[..., k, :].detach(), rtol=0, atol=1e-12)
    for bad in (-1, (2, -3), (2,), "ab", 1.5):
        with pytest.raises(ValueError, match="batch_shape"):
            kf.initial_state(bad)  # type: ignore[arg-type]
    imm = _imm()
    with pytest.raises(ValueError, match="batch_shape"):
        imm.initial_state(-2)
    assert imm.initial_state((4,)).mode_cov.shape == (4, 2, 4, 4)


def test_predict_and_forecast_check_the_state_like_step() -> None:
    """predict and forecast (KalmanFilter and IMMFilter) name mismatched batches in a
    ValueError, convert a state of another dtype, and refuse a NaN state with value checks on."""
    kf, imm = _kf(), _imm()
    state, istate = kf.initial_state(3), imm.initial_state(3)
    dt2, dtK = torch.rand(2, dtype=F64), torch.rand(2, 4, dtype=F64)
    for call in (
        lambda: kf.predict(state, dt2),
        lambda: kf.forecast(state, dtK),
        lambda: imm.predict(istate, dt2),
        lambda: imm.forecast(istate, dtK),
    ):
        with pytest.raises(ValueError, match=r"batch shapes do not broadcast: state\.mode_prob|state\.mean"):
            call()
    f32 = tl.KalmanState(*(t.float() for t in state))
    want = kf.forecast(state, 1.5)
    got = kf.forecast(f32, 1.5)
    assert got.mean.dtype == F64
    torch.testing.assert_close(got.cov, want.cov, rtol=1e-6, atol=1e-6)
    assert imm.forecast(tl.IMMState(*(t.float() for t in istate)), 1.5).mean.dtype == F64
    bad = tl.KalmanState(state.mean.clone(), state.cov)
    bad.mean[0, 0] = float("nan")
    for call in (lambda: kf.predict(bad, 1.0), lambda: kf.forecast(bad, 1.0)):
        with pytest.raises(ValueError, match="mean contains NaN"):
            call()
    ibad = tl.IMMState(istate.mode_prob, istate.mode_mean.clone(), istate.mode_cov)
    ibad.mode_mean[0, 0, 0] = float("nan")
    for call in (lambda: imm.predict(ibad, 1.0), lambda: imm.forecast(ibad, 1.0)):
        with pytest.raises(ValueError, match="state.mode_mean contains NaN"):
            call()


def test_float32_step_where_the_prior_dwarfs_r_raises_as_the_sequence_filter() -> None:
    """A float32 update whose prior dwarfs R (gaps up to e^9, R = 1e-4) cancels: covariances with
    eigenvalues -100x the largest, NaN log-likelihoods. Online = sequence: the float32 step
    raises the sequence filter's NonFiniteLikelihoodError (naming float64), where it once
    widened itself to float64 (and so differed from the sequence filter); in float64 the
    steps equal the sequence filter."""
    g = torch.Generator().manual_seed(0)
    B, T = 64, 150
    dt, y = torch.exp(3 * torch.randn(B, T, generator=g)), 10 * torch.randn(B, T, 1, generator=g)

    def make(dtype: torch.dtype) -> tl.KalmanFilter:
        sde = tl.models.singer(5.0, 2.0, dim=1, dtype=dtype)
        H = tl.models.position_observation(sde)
        return tl.KalmanFilter(
            sde, H, 1e-4 * torch.eye(1, dtype=dtype), P0=1e4 * torch.eye(3, dtype=dtype), algorithm="sequential"
        )

    with torch.no_grad():
        kf = make(torch.float32)
        with pytest.raises(tl.NonFiniteLikelihoodError, match="float64"):
            kf(y, dt)
        state = kf.initial_state((B,))
        with pytest.raises(tl.NonFiniteLikelihoodError, match="float64"):
            for t in range(T):
                state, _ = kf.step(state, y[:, t], dt[:, t])
        kf64 = make(torch.float64)
        ref = kf64(y.double(), dt.double())
        state, total = kf64.initial_state((B,)), torch.zeros(B, dtype=torch.float64)
        for t in range(T):
            state, out = kf64.step(state, y[:, t].double(), dt[:, t].double())
            total += out.log_likelihood
    torch.testing.assert_close(total, ref.log_likelihood, rtol=1e-10, atol=0)


def test_exported_imm_saves_loads_and_deploys() -> None:
    """torch.export of an IMMFilter (IMMResult out) with a dynamic batch AND T (the cycle as
    torch's structured scan: T was fixed to the example's) saves and loads, runs at three
    (B, T) shapes, T = 1 included, and DeployedFilter takes an IMMFilter (it raised
    TypeError): all equal eager."""
    import io

    from torch.export import Dim

    torch._dynamo.reset()  # (the scan's body is traced by dynamo: no frames cached by earlier exports)
    imm = _imm()
    y, dt, _ = _series(3, 12, seed=2)
    B, T = Dim("B", max=10_000), Dim("T", max=10_000)
    # exported in grad mode (the parameters require grad: torch's scan then traced the cycle
    # through autograd, where its einsums failed)
    ep = torch.export.export(imm, (y, dt), dynamic_shapes={"y": {0: B, 1: T}, "dt": {0: B, 1: T}})
    with torch.no_grad():
        buffer = io.BytesIO()
        torch.export.save(ep, buffer)
        buffer.seek(0)
        program = torch.export.load(buffer).module()
        for b, t, seed in ((3, 12, 2), (1, 1, 3), (5, 40, 4)):
            y, dt, _ = _series(b, t, seed=seed)
            ref = imm(y, dt)
            out = program(y, dt)
            torch.testing.assert_close(out.log_likelihood, ref.log_likelihood, rtol=0, atol=1e-10)
            torch.testing.assert_close(out.mean, ref.mean, rtol=0, atol=1e-10)
            torch.testing.assert_close(out.mode_probabilities, ref.mode_probabilities, rtol=0, atol=1e-12)
        ll, mean = tl.DeployedFilter(imm)(y, dt)
    torch.testing.assert_close(ll, ref.log_likelihood, rtol=0, atol=0)
    torch.testing.assert_close(mean, ref.mean, rtol=0, atol=0)
    with pytest.raises(ValueError, match="IMMFilter has no inputs"):
        tl.DeployedFilter(imm)(y, dt, torch.zeros(3, 12, 1, dtype=F64))


@pytest.mark.parametrize("B", [10, 200])
def test_step_with_a_covariance_batch_of_fewer_dims_than_the_tracks(B):
    """kf.step with a state whose covariance is shared (cov (n, n), mean (B, n)) and with reports
    of an extra batch dim (y (2, B, m)): each equals the step of the state with its covariance
    expanded, stepped slice by slice (beyond 128 tracks the first raised and the second gave
    means off by up to 1.8)."""
    kf = _kf()
    g = torch.Generator().manual_seed(B)
    mean = torch.randn(B, 4, generator=g, dtype=F64)
    cov = torch.eye(4, dtype=F64) + 0.1
    y = torch.randn(2, B, 2, generator=g, dtype=F64)
    with torch.no_grad():
        shared, shared_out = kf.step(tl.KalmanState(mean, cov), y[0], 0.5)
        full, full_out = kf.step(tl.KalmanState(mean, cov.expand(B, 4, 4).clone()), y[0], 0.5)
        torch.testing.assert_close(shared.mean, full.mean, rtol=0, atol=1e-12)
        torch.testing.assert_close(shared.cov.expand(B, 4, 4), full.cov, rtol=0, atol=1e-12)
        torch.testing.assert_close(shared_out.log_likelihood, full_out.log_likelihood, rtol=0, atol=1e-12)
        both, both_out = kf.step(tl.KalmanState(mean, cov.expand(B, 4, 4).clone()), y, 0.5)
        for i in range(2):
            one, one_out = kf.step(tl.KalmanState(mean, cov.expand(B, 4, 4).clone()), y[i], 0.5)
            torch.testing.assert_close(both.mean[i], one.mean, rtol=0, atol=1e-12)
            torch.testing.assert_close(both.cov.expand(2, B, 4, 4)[i], one.cov, rtol=0, atol=1e-12)
            torch.testing.assert_close(both_out.log_likelihood[i], one_out.log_likelihood, rtol=0, atol=1e-12)
