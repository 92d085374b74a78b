"""Validation once, at the public boundary: the modules' ``validate_args`` (per instance, with a
class default as in torch.distributions) and inner calls that never check again."""

from __future__ import annotations

import pytest
import torch

import torchsde_lti as tl
import torchsde_lti.core.validation as core_validation
import torchsde_lti.filters.inputs as filter_inputs
import torchsde_lti.nn.kalman as nn_kalman
from torchsde_lti.data import TrackBatch
from torchsde_lti.training.module import KalmanFilterModule

F64 = torch.float64


def _filter(model: str = "cv", **kw: object) -> tl.KalmanFilter:
    sde = {
        "cv": tl.models.constant_velocity(dim=2, q=0.7, dtype=F64),
        "matern": tl.models.matern(1.5, lengthscale=0.8, variance=1.3, dtype=F64),
    }[model]
    H = tl.models.position_observation(sde) if model == "cv" else torch.tensor([[1.0, 0.0]], dtype=F64)
    return tl.KalmanFilter(sde, H, 0.4 * torch.eye(H.shape[0], dtype=F64), **kw)


def _data(kf: tl.KalmanFilter, B: int = 3, T: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return torch.randn(B, T, kf.obs_dim, generator=g, dtype=F64), torch.rand(B, T, generator=g, dtype=F64) + 0.1


@pytest.fixture
def value_checks(monkeypatch: pytest.MonkeyPatch) -> dict[str, list]:
    """Records every fused module check and every validate_args the core and filter
    functions see (``checks_values`` is where each of them decides to check values)."""
    seen: dict[str, list] = {"fused": [], "inner": []}
    fused = nn_kalman.check_values

    def spy_fused(*args: object, **kwargs: object) -> None:
        seen["fused"].append(1)
        fused(*args, **kwargs)

    def spy_inner(validate_args: bool) -> bool:
        seen["inner"].append(validate_args)
        return validate_args and not core_validation.tracing()

    monkeypatch.setattr(nn_kalman, "check_values", spy_fused)
    for module in (core_validation, filter_inputs):
        monkeypatch.setattr(module, "checks_values", spy_inner)
    import torchsde_lti.core.stationary as stationary

    monkeypatch.setattr(stationary, "checks_values", spy_inner)
    return seen


@pytest.mark.parametrize("model", ["cv", "matern"])  # diffuse prior; stationary prior (recomputed per call)
@pytest.mark.parametrize("algorithm", ["sequential", "scan", "square_root"])
def test_forward_checks_once_and_inner_calls_never(value_checks: dict[str, list], model: str, algorithm: str) -> None:
    kf = _filter(model, algorithm=algorithm)
    y, dt = _data(kf)
    value_checks["fused"].clear()
    value_checks["inner"].clear()
    out = kf(y, dt)
    (-out.log_likelihood.sum()).backward()
    kf.smooth(out)
    assert value_checks["fused"] == [1]  # y, dt and every parameter, in one test
    assert value_checks["inner"] and not any(value_checks["inner"])  # discretisation, prior, filter: unchecked


@pytest.mark.filterwarnings(r"ignore:You are trying to `self.log\(\)`")
def test_training_step_checks_once_and_discretises_once(
    value_checks: dict[str, list], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A training step with the k-step loss and inputs: one value check, one discretisation
    (the k-step loss reuses the filter's A, Q and G u instead of discretising again)."""
    sde = tl.models.mass_spring_damper(m=1.5, k=2.0, c=0.4, q=0.7, dtype=F64)
    kf = tl.KalmanFilter(sde, sde.C, 0.1 * torch.eye(1, dtype=F64), P0=torch.eye(2, dtype=F64))
    module = KalmanFilterModule(kf, k_step=2, k_step_weight=0.5)
    calls = []
    original = nn_kalman.discretize_steps
    monkeypatch.setattr(nn_kalman, "discretize_steps", lambda *a, **k: (calls.append(1), original(*a, **k))[1])
    monkeypatch.setattr(tl.LTISDE, "forward", lambda *a, **k: pytest.fail("the SDE was discretised again"))
    g = torch.Generator().manual_seed(1)
    y, dt, u = (
        torch.randn(4, 9, 1, generator=g, dtype=F64),
        torch.rand(4, 9, generator=g, dtype=F64),
        torch.randn(4, 9, 1, generator=g, dtype=F64),
    )
    mask = torch.ones(4, 9, dtype=torch.bool)
    mask[2, 6:] = False  # padding
    batch = TrackBatch(y=y, dt=dt, mask=mask, lengths=mask.sum(-1), u=u)
    value_checks["fused"].clear()
    value_checks["inner"].clear()
    loss = module.training_step(batch, 0)
    loss.backward()
    assert calls == [1] and value_checks["fused"] == [1] and not any(value_checks["inner"])


def test_k_step_loss_with_inputs_is_the_filters_step_likelihood_at_k_1() -> None:
    """k = 1 with inputs: the one-step-ahead score from the filtered state, pushed with the
    filter's own A, Q and G u, is the prediction-error decomposition of the filter."""
    sde = tl.models.mass_spring_damper(m=1.5, k=2.0, c=0.4, q=0.7, dtype=F64)
    kf = tl.KalmanFilter(sde, sde.C, 0.1 * torch.eye(1, dtype=F64), P0=torch.eye(2, dtype=F64))
    module = KalmanFilterModule(kf, k_step=1, k_step_weight=1.0)
    g = torch.Generator().manual_seed(2)
    y, dt, u = (
        torch.randn(3, 12, 1, generator=g, dtype=F64),
        torch.rand(3, 12, generator=g, dtype=F64) + 0.1,
        torch.randn(3, 12, 1, generator=g, dtype=F64),
    )
    y[1, 4] = float("nan")
    out = kf(y, dt, u=u)
    got = module.k_step_nll(out, y, ~torch.isnan(y))
    torch.testing.assert_close(got, -out.step_log_likelihood[..., 1:].sum(), rtol=1e-10, atol=1e-10)


def test_validate_args_false_skips_value_checks_not_shape_checks() -> None:
    kf = _filter(validate_args=False)
    y, dt = _data(kf)
    out = kf(y, -dt)  # negative steps: not checked, the result is whatever the math gives
    assert out.mean.shape == (3, 8, 4)
    with pytest.raises(ValueError, match="dt must have shape"):
        kf(y, dt[..., :-1])
    checked = _filter()
    with pytest.raises(ValueError, match="dt must be non-negative"):
        checked(y, -dt)


def test_class_default_and_instance_override(monkeypatch: pytest.MonkeyPatch) -> None:
    """None follows the class default (read at call time, as torch.distributions); an explicit
    value overrides it; the layers, SDEs and IMM filters take the same switch."""
    follows, checked = _filter(), _filter(validate_args=True)
    y, dt = _data(follows)
    monkeypatch.setattr(tl.KalmanFilter, "default_validate_args", False)
    assert follows.validate_args is False and checked.validate_args is True
    follows(y, -dt)
    with pytest.raises(ValueError, match="dt must be non-negative"):
        checked(y, -dt)
    follows.validate_args = True
    with pytest.raises(ValueError, match="dt must be non-negative"):
        follows(y, -dt)
    F = torch.tensor([[-1.0]], dtype=F64)
    with pytest.raises(ValueError, match="dt must be non-negative"):
        tl.Transition()(F, -1.0)
    assert tl.Transition(validate_args=False)(F, -1.0).shape == (1, 1)
    sde = tl.models.ornstein_uhlenbeck(1.0, 1.0, dtype=F64, validate_args=False)
    assert sde.validate_args is False and sde(torch.tensor(-1.0, dtype=F64)).A.shape == (1, 1)
    with pytest.raises(ValueError, match="dt must be non-negative"):
        tl.models.ornstein_uhlenbeck(1.0, 1.0, dtype=F64)(torch.tensor(-1.0, dtype=F64))
    assert tl.models.ornstein_uhlenbeck(1.0, 1.0, dtype=F64).to_free().validate_args is True


def test_imm_filter_algorithms_and_checks() -> None:
    cv = tl.models.constant_velocity(dim=1, q=0.5, dtype=F64)
    ou = tl.models.integrated_ou(k=0.5, q=0.5, dtype=F64)
    args = (
        [cv, ou],
        torch.tensor([[1.0, 0.0]], dtype=F64),
        0.2 * torch.eye(1, dtype=F64),
        torch.tensor([[0.0, 0.1], [0.1, 0.0]], dtype=F64),
    )
    for algorithm in ("scan", "square_root", "parallel"):
        with pytest.raises(
            ValueError, match=rf"IMMFilter has the algorithms \('auto', 'sequential'\), got algorithm='{algorithm}'"
        ):
            tl.IMMFilter(*args, algorithm=algorithm)
    imm = tl.IMMFilter(*args, algorithm="sequential")
    y, dt = torch.randn(2, 7, 1, dtype=F64), torch.rand(2, 7, dtype=F64)
    assert imm(y, dt).log_likelihood.shape == (2,)
    with pytest.raises(ValueError, match="dt must be non-negative"):
        imm(y, -dt)
    y[0, 2, 0] = float("inf")
    with pytest.raises(ValueError, match="y contains Inf"):
        imm(y, dt)
    assert tl.IMMFilter(*args, validate_args=False)(y.nan_to_num(posinf=0.0), -dt).mean.shape == (2, 7, 2)
    for bad in ([float("nan"), 1.0], [-0.5, 1.5], [0.5, 0.6], [float("inf"), 0.0]):
        with pytest.raises(ValueError, match="mode_prob0 must be a probability vector"):
            tl.IMMFilter(*args, mode_prob0=torch.tensor(bad, dtype=F64))


def test_prior_is_a_method_of_the_model() -> None:
    """prior_covariance(): P∞ for a Hurwitz F, ValueError otherwise (the filter then starts
    diffuse), a shaped model's steady-state start; the filter recomputes it every call."""
    ou = tl.models.ornstein_uhlenbeck(0.5, 2.0, dtype=F64)
    torch.testing.assert_close(ou.prior_covariance(), torch.tensor([[2.0]], dtype=F64))  # q / (2 θ)
    cv = tl.models.constant_velocity(dim=1, dtype=F64)
    with pytest.raises(ValueError, match="Hurwitz"):
        cv.prior_covariance()
    assert tl.KalmanFilter(cv, torch.tensor([[1.0, 0.0]], dtype=F64), torch.eye(1, dtype=F64)).prior_mode == "diffuse"
    kf = tl.KalmanFilter(ou, torch.eye(1, dtype=F64), torch.eye(1, dtype=F64))
    assert kf.prior_mode == "model"
    ou.theta = 0.25
    torch.testing.assert_close(kf.initial_state().cov, torch.tensor([[4.0]], dtype=F64))
    with torch.no_grad():
        ou.parametrizations.theta.original.fill_(float("nan"))
    with pytest.raises(ValueError, match="contains NaN or Inf"):
        kf(torch.zeros(1, 3, 1, dtype=F64), torch.ones(1, 3, dtype=F64))


def test_one_public_name_per_model() -> None:
    """tl.models exports the factory functions only; each returns an LTISDE."""
    import inspect

    for name in tl.models.__all__:
        assert inspect.isfunction(getattr(tl.models, name)), name
    assert not [n for n in dir(tl.models) if not n.startswith("_") and inspect.isclass(getattr(tl.models, n))]
    assert isinstance(tl.models.singer(0.5, 1.0, dim=2), tl.LTISDE)


@pytest.mark.parametrize("size", [3, 400])  # on Python floats (≤ PYTHON_CHECK_MAX_VALUES in all); as tensors
def test_fused_check_names_the_bad_tensor_on_both_paths(size: int) -> None:
    """check_values: the same verdicts whether the values are read to the host (a live track's
    step) or reduced as tensors (a batch): NaN/Inf in a finite argument, a negative or NaN dt,
    Inf in y fail, naming the argument; NaN in y (missing data) passes."""
    from torchsde_lti.nn._validate import check_values

    def call(F: torch.Tensor, dt: torch.Tensor, y: torch.Tensor) -> None:
        check_values(finite=[("F", F), ("L", None)], nonnegative=[("dt", dt)], no_inf=[("y", y)])

    F, dt, y = torch.zeros(2, 2, dtype=F64), torch.ones(size, dtype=F64), torch.zeros(size, 2, dtype=F64)
    y[0, 1] = float("nan")
    call(F, dt, y)
    for field, index, value, message in (
        ("F", (1, 0), float("nan"), "F contains NaN or Inf"),
        ("F", (0, 1), float("-inf"), "F contains NaN or Inf"),
        ("dt", (size - 1,), -1e-300, "dt must be non-negative"),
        ("dt", (0,), float("nan"), "dt contains NaN or Inf"),
        ("y", (size - 1, 0), float("inf"), "y contains Inf"),
    ):
        args = {"F": F.clone(), "dt": dt.clone(), "y": y.clone()}
        args[field][index] = value
        with pytest.raises(ValueError, match=message):
            call(**args)


def test_a_nearly_singular_observation_noise_is_named_when_the_likelihood_is_not_finite() -> None:
    """R formed from a factor with a tiny pivot under a unit off-diagonal (positive definite
    on paper, singular in float32): the error names R, not the observations."""
    import torchsde_lti as tl
    from torchsde_lti.nn._validate import NonFiniteLikelihoodError

    dtype = torch.float32
    kf = tl.KalmanFilter(
        tl.models.constant_velocity(dim=1, q=1.0, dtype=dtype), torch.eye(2, dtype=dtype), torch.eye(2, dtype=dtype)
    )
    kf.parametrizations.R.original.data = torch.tensor([[-10.0, 0.0], [1.0, -10.0]], dtype=dtype)
    g = torch.Generator().manual_seed(0)
    y, dt = torch.randn(3, 20, 2, generator=g), torch.full((3, 20), 0.5)
    with pytest.raises(NonFiniteLikelihoodError, match="observation noise R is nearly singular"):
        kf(y, dt)


@pytest.mark.parametrize("online", [False, True])
@pytest.mark.parametrize("imm", [False, True])
def test_matrix_exp_whose_Q_overflows_is_refused_with_a_value_error(imm: bool, online: bool) -> None:
    """method="matrix_exp" over a long gap: Van Loan's block overflows and Q is not finite. A
    checked KalmanFilter raised a LAPACK error (eigvalsh of Inf), an IMMFilter returned NaN."""
    f64 = torch.float64
    slow = tl.models.singer(alpha=0.6, q=2.0, dim=1, dtype=f64)
    H, R = tl.models.position_observation(slow), torch.eye(1, dtype=f64)
    if imm:
        rates = torch.tensor([[0.0, 0.1], [0.1, 0.0]], dtype=f64)
        fast = tl.models.singer(alpha=2.0, q=1.0, dim=1, dtype=f64)
        model = tl.IMMFilter([slow, fast], H, R, rates, method="matrix_exp")
    else:
        model = tl.KalmanFilter(slow, H, R, method="matrix_exp")
    with pytest.raises(ValueError, match="matrix_exp"):
        if online:
            model.step(model.initial_state(1), torch.zeros(1, 1, dtype=f64), torch.tensor([2000.0], dtype=f64))
        else:
            model(torch.zeros(1, 3, 1, dtype=f64), torch.tensor([[1.0, 2000.0, 1.0]], dtype=f64))
    if not imm:  # a forecast over the same gap (it returned NaN covariances)
        out = model(torch.zeros(1, 3, 1, dtype=f64), torch.ones(1, 3, dtype=f64))
        with pytest.raises(ValueError, match="matrix_exp"):
            model.forecast(out, torch.tensor([2000.0], dtype=f64))
