"""The RTS smoother (filters/smoothers.py, KalmanFilter.smooth) where its gain is extreme: a
velocity that decays without noise (the shipped ``moored`` mode, F = −k on the velocity, no
velocity noise) over long gaps, where the gain ``E_k = P_k Aᵀ (P⁻_{k+1})⁻¹`` carries e^{k dt}.

References computed another way: the joint Gaussian of all states, conditioned on all reports
(mpmath at 60 digits, never inverting a state covariance), and the one-mode IMM smoother (a
backward information filter in square-root form, filters/imm_smoother.py)."""

from __future__ import annotations

import copy
import itertools
import math
from pathlib import Path

import mpmath
import pytest
import torch

import torchsde_lti as tl

D64 = torch.float64
ALGORITHMS = ("sequential", "scan")


def _moored(k: float, q: float, dts: list[float], dim: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """A, Q (T, 2·dim, 2·dim) of ``dx = v dt + dβ``, ``dv = −k v dt`` per axis (closed form)."""
    T, n = len(dts), 2 * dim
    A, Q = torch.zeros(T, n, n, dtype=D64), torch.zeros(T, n, n, dtype=D64)
    for i, dt in enumerate(dts):
        for a in range(dim):
            p, v = 2 * a, 2 * a + 1
            A[i, p, p] = 1.0
            A[i, p, v] = -math.expm1(-k * dt) / k
            A[i, v, v] = math.exp(-k * dt)
            Q[i, p, p] = q * dt
    return A, Q


def exact_smoother(y, A, Q, H, R, m0, P0):  # noqa: ANN001, ANN201 - float64 tensors
    """E[x_k | y] (T, n) and Cov[x_k | y] (T, n, n): the joint Gaussian of x_0 … x_{T−1} (x_0 ~
    N(m0, P0), x_k = A_k x_{k−1} + N(0, Q_k)) conditioned on every observed component of
    y_k = H x_k + N(0, R) (NaN = missing), in mpmath: only the reports' covariance is inverted."""
    mpmath.mp.dps = 60
    T, n = A.shape[0], A.shape[-1]
    mat = lambda t: mpmath.matrix(t.tolist())  # noqa: E731
    As, Qs = [mat(A[i]) for i in range(T)], [mat(Q[i]) for i in range(T)]
    mu, cov = [mat(m0.reshape(n, 1))], {(0, 0): mat(P0)}
    for k in range(1, T):
        mu.append(As[k] * mu[-1])
        for j in range(k):
            cov[k, j] = As[k] * cov[k - 1, j]
            cov[j, k] = cov[k, j].T
        cov[k, k] = As[k] * cov[k - 1, k - 1] * As[k].T + Qs[k]
    big = mpmath.zeros(n * T, n * T)
    for (i, j), c in cov.items():
        for a, b in itertools.product(range(n), range(n)):
            big[i * n + a, j * n + b] = c[a, b]
    mean = mpmath.matrix([mu[k][a] for k in range(T) for a in range(n)])
    obs = [(k, r) for k in range(T) for r in range(y.shape[-1]) if not math.isnan(float(y[k, r]))]
    Hm, Rm = mpmath.zeros(len(obs), n * T), mpmath.zeros(len(obs), len(obs))
    Y = mpmath.matrix([float(y[k, r]) for k, r in obs])
    for i, (k, r) in enumerate(obs):
        for a in range(n):
            Hm[i, k * n + a] = float(H[r, a])
        for j, (k2, r2) in enumerate(obs):
            Rm[i, j] = float(R[r, r2]) if k2 == k else 0.0
    gain = big * Hm.T * mpmath.inverse(Hm * big * Hm.T + Rm)
    post, pc = mean + gain * (Y - Hm * mean), big - gain * Hm * big
    m = torch.tensor([[float(post[k * n + a]) for a in range(n)] for k in range(T)], dtype=D64)
    P = torch.tensor(
        [[[float(pc[k * n + a, k * n + b]) for b in range(n)] for a in range(n)] for k in range(T)], dtype=D64
    )
    return m, P


def _assert_close_in_std(sm, mean: torch.Tensor, cov: torch.Tensor, rtol: float, floor: float = 0.0) -> None:  # noqa: ANN001
    """|Δmean| ≤ rtol s, |ΔP_ij| ≤ rtol s_i s_j with s = std + max(floor, sqrt(tiny)) + 8 eps |mean|:
    errors in units of the exact posterior's standard deviations, widened by what the result's
    dtype resolves (a variance below ``tiny`` underflows: after a gap of k dt = 190 the velocity's
    is 1e-410; and the rounding of the mean itself: float32 positions of 1e5 m are ±4 mm)."""
    assert torch.isfinite(sm.mean).all() and torch.isfinite(sm.cov).all()
    eps = torch.finfo(sm.mean.dtype).eps
    floor = max(floor, torch.finfo(sm.mean.dtype).tiny ** 0.5)
    std = cov.diagonal(dim1=-2, dim2=-1).sqrt() + floor + 8 * eps * mean.abs()
    err_mean = float(((sm.mean.double() - mean).abs() / std).max())
    err_cov = float(((sm.cov.double() - cov).abs() / std[..., :, None] / std[..., None, :]).max())
    assert err_mean <= rtol and err_cov <= rtol, (err_mean, err_cov)


# ------------------------------------------------------------------ against the joint Gaussian
GAPS = (10.0, 600.0, 1500.0, 20000.0)  # k dt = 0.5 … 1000: e^{−k dt} underflows float32 from ~1500, float64 at 20000


@pytest.mark.parametrize("algorithm", ALGORITHMS)
@pytest.mark.parametrize("dtype", [D64, torch.float32])
@pytest.mark.parametrize("gap", GAPS)
def test_a_decaying_velocity_over_a_long_gap_matches_the_joint_gaussian(
    gap: float, dtype: torch.dtype, algorithm: str
) -> None:
    """1-D moored (k = 0.05, q = 0.1), positions at 1e5 m observed with R = 4, the gap in the
    middle; float64 to 1e-9 std, float32 to 1e-2 std (positions of 1e5 m in float32)."""
    k, q, off = 0.05, 0.1, 1e5
    A, Q = _moored(k, q, [0.0, 1.0, 1.0, gap, 1.0, 1.0, 2.0])
    H, R = torch.tensor([[1.0, 0.0]], dtype=D64), torch.tensor([[4.0]], dtype=D64)
    m0, P0 = torch.tensor([off, 1.0], dtype=D64), torch.diag(torch.tensor([100.0, 4.0], dtype=D64))
    y = off + torch.tensor([[0.3], [2.1], [3.9], [60.0], [float("nan")], [60.5], [61.2]], dtype=D64)
    mean, cov = exact_smoother(y, A, Q, H, R, m0, P0)
    c = lambda t: t.to(dtype)  # noqa: E731
    out = tl.kalman_filter(c(y), c(A), c(Q), c(H), c(R), c(m0), c(P0))
    sm = tl.rts_smoother(out, algorithm=algorithm)
    rtol = 1e-9 if dtype == D64 else 1e-2
    _assert_close_in_std(sm, mean, cov, rtol)


@pytest.mark.parametrize("dtype", [D64, torch.float32])
@pytest.mark.parametrize("seed", range(6))
def test_random_gaps_and_tracks_in_2d_match_the_joint_gaussian(seed: int, dtype: torch.dtype) -> None:
    """2-D moored with correlated R, gaps from 1 s to 2 h, positions at 2e4 or 1e6 m, a missing
    component: both algorithms."""
    g = torch.Generator().manual_seed(seed)
    k, off = (0.026, 0.8, 0.1)[seed % 3], (2e4, 1e6)[seed % 2]
    choices = torch.tensor([1.0, 10.0, 60.0, 600.0, 3600.0, 7200.0], dtype=D64)
    dts = [0.0, *choices[torch.randint(len(choices), (6,), generator=g)].tolist()]
    A, Q = _moored(k, 0.05, dts, dim=2)
    H = tl.models.position_observation(tl.models.moored(dim=2, dtype=D64))
    R = torch.tensor([[9.0, 3.0], [3.0, 16.0]], dtype=D64)
    m0 = torch.tensor([off, 0.5, -off, -0.2], dtype=D64)
    P0 = torch.diag(torch.tensor([400.0, 4.0, 400.0, 4.0], dtype=D64))
    y = m0[[0, 2]] + 5.0 * torch.randn(len(dts), 2, generator=g, dtype=D64).cumsum(0)
    y[3, 1] = float("nan")
    mean, cov = exact_smoother(y, A, Q, H, R, m0, P0)
    c = lambda t: t.to(dtype)  # noqa: E731
    out = tl.kalman_filter(c(y), c(A), c(Q), c(H), c(R), c(m0), c(P0))
    rtol = 1e-9 if dtype == D64 else 1e-1  # float32 positions of 1e6 m: ±0.06 m (8 eps |mean| = 1 m)
    for algorithm in ALGORITHMS:
        _assert_close_in_std(tl.rts_smoother(out, algorithm=algorithm), mean, cov, rtol)


def test_gradients_through_a_long_gap() -> None:
    """float64 gradcheck of the smoothed moments with respect to the reports and Q's scale across a
    gap with e^{k dt} = 2e4 in the gain."""
    A, Q = _moored(0.05, 0.1, [0.0, 1.0, 200.0, 1.0])
    H, R = torch.tensor([[1.0, 0.0]], dtype=D64), torch.tensor([[4.0]], dtype=D64)
    m0, P0 = torch.tensor([0.0, 1.0], dtype=D64), torch.diag(torch.tensor([100.0, 4.0], dtype=D64))

    def smoothed(y: torch.Tensor, s: torch.Tensor, algorithm: str) -> tuple[torch.Tensor, torch.Tensor]:
        sm = tl.rts_smoother(tl.kalman_filter(y, A, Q * s, H, R, m0, P0), algorithm=algorithm)
        return sm.mean, sm.cov

    y = torch.tensor([[0.3], [2.1], [30.0], [31.0]], dtype=D64, requires_grad=True)
    s = torch.tensor(1.5, dtype=D64, requires_grad=True)
    for algorithm in ALGORITHMS:
        assert torch.autograd.gradcheck(lambda y, s: smoothed(y, s, algorithm), (y, s))  # noqa: B023


# ------------------------------------------------------------------ the shipped model, real tracks
def _national_day_lines(lines: int = 12) -> str:
    """The first ``lines`` tracks of the national day's file (not a reserved file)."""
    data = pytest.importorskip("tracktable_data")
    path = Path(data.__file__).parent / "python_example_data" / "US_coastal_2020_06_30.traj"
    with open(path) as fh:
        text = "".join(itertools.islice(fh, lines))
    return text


@pytest.fixture(scope="module")
def national_day(tmp_path_factory: pytest.TempPathFactory) -> tuple[torch.Tensor, torch.Tensor]:
    """(y (B, T, 2), dt (B, T)) of those tracks, cut at no gap, padded at the end with missing
    reports and dt = 0 (A = I, Q = 0: the padding carries the last state unchanged)."""
    out = tmp_path_factory.mktemp("national") / "slice.traj"
    out.write_text(_national_day_lines())
    windows = tl.data.track_windows(tl.data.load_tracks(out, rules=tl.data.CleaningRules(max_gap=None)), max_len=None)
    T = max(len(w.y) for w in windows)
    y = torch.full((len(windows), T, 2), float("nan"), dtype=D64)
    dt = torch.zeros(len(windows), T, dtype=D64)
    for i, w in enumerate(windows):
        y[i, : len(w.y)], dt[i, : len(w.y)] = torch.as_tensor(w.y, dtype=D64), torch.as_tensor(w.dt, dtype=D64)
    return y, dt


def test_shipped_moored_mode_on_national_day_tracks_equals_the_information_smoother(
    national_day: tuple[torch.Tensor, torch.Tensor],
) -> None:
    """``ais-us-imm``'s moored mode as a KalmanFilter on 12 real tracks (11–68 reports, gaps up to
    19 min, vessels at 0.001–7.8 m/s): kf.smooth is finite and equals the one-mode IMM smoother
    (backward information filter) to 1e-8 std in float64; float32 to 5e-2 std (floor 1 cm, 1 cm/s)."""
    shipped = tl.pretrained.load("ais-us-imm").filter.double()
    mode = shipped.modes()[shipped.mode_names.index("moored")]
    P0 = shipped.P0.detach()
    P0 = P0[0] if P0.dim() == 3 else P0
    one = tl.IMMFilter([copy.deepcopy(mode.sde)], mode.H, mode.R.detach(), torch.zeros(1, 1, dtype=D64), P0=P0)
    y, dt = national_day
    with torch.no_grad():
        ref = one.smooth(one(y, dt))
    for dtype, rtol, floor in ((D64, 1e-8, 0.0), (torch.float32, 5e-2, 1e-2)):
        kf = tl.KalmanFilter(
            copy.deepcopy(mode.sde).to(dtype), mode.H.to(dtype), mode.R.detach().to(dtype), P0=P0.to(dtype)
        )
        with torch.no_grad():
            sm = kf.smooth(kf(y.to(dtype), dt.to(dtype)))
        _assert_close_in_std(sm, ref.mean, ref.cov, rtol, floor)


# ------------------------------------------------------------------ one-mode IMM smoother = RTS
@pytest.mark.parametrize("dtype", [D64, torch.float32])
def test_one_mode_imm_smoother_equals_kf_smooth_for_the_moored_model(dtype: torch.dtype) -> None:
    """The moored model (k = 0.8) over gaps of up to 100 s (e^{k dt} = 5e34) in a batch of tracks
    with their own gaps: IMMFilter([moored]).smooth == KalmanFilter(moored).smooth."""
    g = torch.Generator().manual_seed(1)
    sde = tl.models.moored(k=0.8, q=0.05, dim=2, dtype=dtype)
    H = tl.models.position_observation(sde)
    R = torch.tensor([[1.0, 0.2], [0.2, 0.7]], dtype=dtype)
    P0 = 4.0 * torch.eye(4, dtype=dtype)
    imm = tl.IMMFilter([sde], H, R, torch.zeros(1, 1, dtype=dtype), P0=P0)
    kf = tl.KalmanFilter(sde, H, R, P0=P0)
    y = torch.randn(3, 12, 2, generator=g, dtype=dtype).cumsum(1)
    dt = torch.tensor([0.5, 3.0, 100.0], dtype=dtype)[torch.randint(3, (3, 12), generator=g)]
    y[1, 4] = float("nan")
    with torch.no_grad():
        a, b = imm.smooth(imm(y, dt)), kf.smooth(kf(y, dt))
    assert torch.equal(a.mode_probabilities, torch.ones_like(a.mode_probabilities))
    rtol = 1e-10 if dtype == D64 else 1e-3
    _assert_close_in_std(b, a.mean.double(), a.cov.double(), rtol)
    _assert_close_in_std(b, a.mode_mean[..., 0, :].double(), a.mode_cov[..., 0, :, :].double(), rtol)
