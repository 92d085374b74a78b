"""torch.export of a KalmanFilter (issue 10, item 5): the exported program, saved and loaded
with torch.export.save/load, gives the eager log-likelihood and filtered means to 1e-10
(float64), also in a fresh process where Lightning and Hydra cannot be imported."""

from __future__ import annotations

import io
import subprocess
import sys
import textwrap

import pytest
import torch

import torchsde_lti as tl

F64 = torch.float64


def _data(B: int, T: int, m: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    y = torch.randn(B, T, m, generator=g, dtype=F64).cumsum(1)
    y[0, 3, 0] = float("nan")  # missing component: masked path inside the exported graph
    dt = torch.rand(B, T, generator=g, dtype=F64) * 3.0 + 1e-3
    return y, dt


def _filters() -> dict[str, tl.KalmanFilter]:
    cv = tl.models.constant_velocity(dim=2, q=0.8, dtype=F64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64)
    R = 0.3 * torch.eye(2, dtype=F64)
    matern = tl.models.matern(1.5, lengthscale=0.7, variance=2.0, dtype=F64)  # stationary prior, doubling
    return {
        "cv-scan": tl.KalmanFilter(cv, H, R, P0=50 * torch.eye(4, dtype=F64)),  # auto: scan (B = 2)
        "cv-loop": tl.KalmanFilter(cv, H, R, P0=50 * torch.eye(4, dtype=F64), algorithm="sequential"),
        "matern": tl.KalmanFilter(matern, torch.tensor([[1.0, 0.0]], dtype=F64), torch.tensor([[0.1]], dtype=F64)),
    }


@pytest.mark.parametrize("name", ["cv-scan", "cv-loop"])  # "matern": the subprocess test
def test_exported_filter_saved_and_loaded_matches_eager(name, tmp_path):
    kf = _filters()[name]
    m = kf.obs_dim
    B, T = 2, 12
    module = tl.DeployedFilter(kf).eval()
    ep = torch.export.export(module, _data(B, T, m, seed=0))
    path = tmp_path / f"{name}.pt2"
    torch.export.save(ep, path)
    loaded = torch.export.load(path).module()
    y, dt = _data(B, T, m, seed=1)  # new tracks, same shapes
    ll, mean = loaded(y, dt)
    with torch.no_grad():
        ref = kf(y, dt)
    torch.testing.assert_close(ll, ref.log_likelihood, rtol=0, atol=1e-10)
    torch.testing.assert_close(mean, ref.mean, rtol=0, atol=1e-10)


def test_exported_filter_runs_without_lightning_or_hydra(tmp_path):
    kf = _filters()["matern"]
    y, dt = _data(2, 12, 1, seed=0)
    ep = torch.export.export(tl.DeployedFilter(kf).eval(), (y, dt))
    path = tmp_path / "kf.pt2"
    torch.export.save(ep, path)
    torch.save((y, dt), tmp_path / "data.pt")
    with torch.no_grad():
        expected = kf(y, dt).log_likelihood
    script = textwrap.dedent(f"""
        import sys, importlib.abc
        class Block(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("lightning", "pytorch_lightning", "hydra", "omegaconf"):
                    raise ImportError("blocked: " + name)
        sys.meta_path.insert(0, Block())
        import torch
        import torchsde_lti  # the core imports without them too
        prog = torch.export.load({str(path)!r}).module()
        y, dt = torch.load({str(tmp_path / "data.pt")!r})
        ll, _ = prog(y, dt)
        assert not any(k.split(".")[0] in ("lightning", "hydra") for k in sys.modules)
        print(repr(ll.tolist()))
    """)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    got = torch.tensor(eval(run.stdout.strip().splitlines()[-1]), dtype=F64)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-10)


@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-11), (torch.float32, 5e-4)])
def test_traced_doubling_equals_eager(dtype, rtol):
    """The traced discretisation (static graph: all series terms, masked doublings) equals
    the eager one, for per-element F, a shared F and an input matrix, dt over 6 decades
    (relative to each matrix: float32 A decayed to 1e-16 after ~10 doublings differs by 1e-4)."""
    from torchsde_lti.core._doubling import per_element_doubling
    from torchsde_lti.core.discretization import doubling
    from torchsde_lti.core.validation import sde_inputs

    g = torch.Generator().manual_seed(0)
    n, N = 3, 300
    M = torch.randn(N, n, n, generator=g, dtype=F64)
    F = M - (torch.linalg.eigvals(M).real.amax(-1) + 0.5)[:, None, None] * torch.eye(n, dtype=F64)
    dt = torch.logspace(-3, 3, N, dtype=F64)
    for F_case in (F, F[0]):
        inp = sde_inputs(
            F_case.to(dtype),
            torch.eye(n, dtype=dtype),
            torch.eye(n, dtype=dtype),
            dt.to(dtype),
            B=torch.ones(n, 1, dtype=dtype),
        )
        eager = doubling(inp)
        traced = per_element_doubling(inp)  # (core's traced schedule: tests/core/test_doubling_paths.py)
        for a, b in zip(eager, traced):
            floor = torch.finfo(dtype).tiny ** 0.5  # entries that underflow in one path: absolute
            scale = a.flatten(-2).norm(dim=-1).clamp_min(floor)[..., None, None]
            assert float(((a - b).abs() / scale).max()) < rtol


@pytest.mark.slow  # builds C++ kernels: ≈ 20–60 s each
@pytest.mark.parametrize("name", ["cv-scan", "matern"])
def test_aoti_package_matches_eager(name, tmp_path):
    """exported program → AOTInductor package → load → run equals eager to 1e-10 (float64);
    for Matérn (F not nilpotent: the doubling in a while_loop) also when every gap is too short
    to halve (a loop of no iteration once gave wrong values)."""
    kf = _filters()[name].eval()
    m = kf.obs_dim
    ep = torch.export.export(tl.DeployedFilter(kf), _data(2, 12, m, seed=0))
    path = torch._inductor.aoti_compile_and_package(ep, package_path=str(tmp_path / "kf_aoti.pt2"))
    runner = torch._inductor.aoti_load_package(path)
    y, dt = _data(2, 12, m, seed=1)
    for gaps in (dt, torch.full_like(dt, 0.02)):
        ll, mean = runner(y, gaps)
        with torch.no_grad():
            ref = kf(y, gaps)
        torch.testing.assert_close(ll, ref.log_likelihood, rtol=0, atol=1e-10)
        torch.testing.assert_close(mean, ref.mean, rtol=0, atol=1e-10)


@pytest.mark.slow  # inductor compiles the whole scan: ≈ 20–60 s
def test_compiled_forced_scan_matches_eager():
    """torch.compile(KalmanFilter(algorithm="scan")) traces the associative scan whole (the
    doubling's while_loop without a gradient) and equals eager to 1e-10."""
    cv = tl.models.constant_velocity(dim=2, q=0.8, dtype=F64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64)
    kf = tl.KalmanFilter(cv, H, 0.3 * torch.eye(2, dtype=F64), P0=50 * torch.eye(4, dtype=F64), algorithm="scan")
    compiled = torch.compile(kf)
    y, dt = _data(2, 12, 2, seed=1)
    with torch.no_grad():
        out, ref = compiled(y, dt), kf(y, dt)
    torch.testing.assert_close(out.log_likelihood, ref.log_likelihood, rtol=0, atol=1e-10)
    torch.testing.assert_close(out.mean, ref.mean, rtol=0, atol=1e-10)


@pytest.mark.slow  # compiles one step of the loop: ≈ 5–20 s
def test_compiled_default_runs_the_loop_as_a_structured_scan_and_matches_eager():
    """torch.compile(kf) with algorithm="auto" runs the loop as torch's structured scan (never
    the scan traced whole), equal to eager with and without gradients; the functional
    kalman_filter under torch.compile does the same."""
    import torchsde_lti.filters.sequential as sequential

    cv = tl.models.constant_velocity(dim=2, q=0.8, dtype=F64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64)
    kf = tl.KalmanFilter(cv, H, 0.3 * torch.eye(2, dtype=F64), P0=50 * torch.eye(4, dtype=F64))
    y, dt = _data(1, 30, 2, seed=1)
    calls = []
    original = sequential._run_compiled_loop
    sequential._run_compiled_loop = lambda *a: (calls.append(1), original(*a))[1]
    try:
        compiled = torch.compile(kf)
        with torch.no_grad():
            out, ref = compiled(y, dt), kf(y, dt)
        torch.testing.assert_close(out.log_likelihood, ref.log_likelihood, rtol=0, atol=1e-10)
        torch.testing.assert_close(out.mean, ref.mean, rtol=0, atol=1e-10)
        (g_c,) = torch.autograd.grad(compiled(y, dt).log_likelihood.sum(), kf.parametrizations.R.original)
        (g_e,) = torch.autograd.grad(kf(y, dt).log_likelihood.sum(), kf.parametrizations.R.original)
        torch.testing.assert_close(g_c, g_e, rtol=1e-9, atol=1e-10)
        d = cv(dt, series=True)
        args = (H, 0.3 * torch.eye(2, dtype=F64), torch.zeros(4, dtype=F64), 50 * torch.eye(4, dtype=F64))
        fn = torch.compile(lambda y, A, Q: tl.kalman_filter(y, A, Q, *args).log_likelihood)
        with torch.no_grad():
            torch.testing.assert_close(
                fn(y, d.A, d.Q), tl.kalman_filter(y, d.A, d.Q, *args).log_likelihood, rtol=0, atol=1e-10
            )
    finally:
        sequential._run_compiled_loop = original
    assert len(calls) == 3  # the module (no grad, grad) and the function: the loop each time


def _cv_filter() -> tl.KalmanFilter:
    cv = tl.models.constant_velocity(dim=2, q=0.8, dtype=F64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64)
    return tl.KalmanFilter(cv, H, torch.tensor([[0.3, 0.1], [0.1, 0.4]], dtype=F64), P0=50 * torch.eye(4, dtype=F64))


def test_export_the_module_itself_with_dynamic_batch_and_time():
    """torch.export.export(kf, ...) on the KalmanFilter (FilterResult out) with torch.export.Dim
    for the batch and T: ONE program, run at three (B, T) shapes, equals eager."""
    from torch.export import Dim

    torch._dynamo.reset()  # the structured scan's body is traced by dynamo: no frames cached by earlier exports
    kf = _cv_filter()
    B, T = Dim("B", max=100_000), Dim("T", max=100_000)
    ep = torch.export.export(kf, _data(3, 5, 2, seed=0), dynamic_shapes={"y": {0: B, 1: T}, "dt": {0: B, 1: T}})
    # the program saves and loads (FilterResult registered for serialisation: it raised NotImplementedError)
    buffer = io.BytesIO()
    torch.export.save(ep, buffer)
    buffer.seek(0)
    prog = torch.export.load(buffer).module()
    for b, t in ((1, 7), (4, 20), (50, 3)):
        g = torch.Generator().manual_seed(b + t)
        y = torch.randn(b, t, 2, generator=g, dtype=F64).cumsum(1)
        y[0, 1, 0] = float("nan")  # missing data inside the program
        dt = torch.rand(b, t, generator=g, dtype=F64) * 3.0
        out = prog(y, dt)
        assert isinstance(out, tl.FilterResult)
        with torch.no_grad():
            ref = kf(y, dt)
        torch.testing.assert_close(out.log_likelihood, ref.log_likelihood, rtol=0, atol=1e-10)
        torch.testing.assert_close(out.mean, ref.mean, rtol=0, atol=1e-10)
        torch.testing.assert_close(out.innovation_cov, ref.innovation_cov, rtol=0, atol=1e-10)


def _step_args(b: int, seed: int) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    mean = torch.randn(b, 4, generator=g, dtype=F64)
    cov = 2.0 * torch.eye(4, dtype=F64).expand(b, 4, 4).contiguous()
    y = torch.randn(b, 2, generator=g, dtype=F64)
    y[0, 1] = float("nan")  # a missing component
    return mean, cov, y, torch.rand(b, generator=g, dtype=F64) * 3.0


def _exported_step(kf: tl.KalmanFilter) -> torch.export.ExportedProgram:
    from torch.export import Dim

    B = Dim("B", max=1_000_000)
    with torch.no_grad():  # an inference program (no grad-mode switches inside to serialise)
        return torch.export.export(tl.OnlineStep(kf).eval(), _step_args(3, 0), dynamic_shapes=({0: B},) * 4)


def test_exported_online_step_any_number_of_tracks(tmp_path):
    """OnlineStep exported once with a dynamic batch, saved and loaded, runs 1, 7 and 1000
    tracks (each its own dt) and equals the eager step."""
    kf = _cv_filter()
    path = tmp_path / "step.pt2"
    torch.export.save(_exported_step(kf), path)
    prog = torch.export.load(path).module()
    for b in (1, 7, 1000):
        args = _step_args(b, seed=b)
        got = prog(*args)
        with torch.no_grad():
            state, out = kf.step(tl.KalmanState(args[0], args[1]), args[2], args[3])
        for x, ref in zip(got, (state.mean, state.cov, out.innovation, out.innovation_cov, out.log_likelihood)):
            torch.testing.assert_close(x, ref, rtol=0, atol=1e-10)


@pytest.mark.parametrize("model", ["singer", "constant_acceleration"])
def test_exported_online_step_of_larger_models(model):
    """The exported step of a 6-state model (products through bmm while traced: above the
    fused-product bound; Singer's F is not nilpotent, constant acceleration's is) equals the
    eager step, NaN report components included."""
    from torch.export import Dim

    kw = {"alpha": 0.5, "q": 0.7} if model == "singer" else {}
    sde = getattr(tl.models, model)(dim=2, dtype=F64, **kw)
    kf = tl.KalmanFilter(
        sde, tl.models.position_observation(sde), 0.3 * torch.eye(2, dtype=F64), P0=torch.eye(6, dtype=F64)
    )
    g = torch.Generator().manual_seed(5)

    def args(b: int) -> tuple[torch.Tensor, ...]:
        y = torch.randn(b, 2, generator=g, dtype=F64)
        y[0, 0] = float("nan")
        cov = torch.eye(6, dtype=F64).expand(b, 6, 6).contiguous()
        return torch.randn(b, 6, generator=g, dtype=F64), cov, y, torch.rand(b, generator=g, dtype=F64) * 2.0

    with torch.no_grad():
        ep = torch.export.export(tl.OnlineStep(kf).eval(), args(3), dynamic_shapes=({0: Dim("B", max=10_000)},) * 4)
        prog = ep.module()
        for b in (1, 9):
            a = args(b)
            state, out = kf.step(tl.KalmanState(a[0], a[1]), a[2], a[3])
            for x, ref in zip(
                prog(*a), (state.mean, state.cov, out.innovation, out.innovation_cov, out.log_likelihood)
            ):
                torch.testing.assert_close(x, ref, rtol=0, atol=1e-10)


def test_online_step_is_a_snapshot_of_the_filter():
    """OnlineStep holds the model's matrices evaluated when it is built: its exported program
    reads none of the filter's parameters (no parametrisation runs per call), and a later
    change of the filter does not reach it (a new OnlineStep sees it)."""
    kf = _cv_filter()
    ep = _exported_step(kf)
    params = set(ep.graph_signature.inputs_to_parameters)
    used = [n.name for n in ep.graph.nodes if n.op == "placeholder" and n.name in params and n.users]
    assert params and not used
    step = tl.OnlineStep(kf)
    args = _step_args(5, seed=3)
    before = step(*args)
    with torch.no_grad():
        for p in kf.parameters():
            p.add_(0.3)
    after = step(*args)
    for x, y in zip(before, after):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    fresh = tl.OnlineStep(kf)(*args)
    reloaded = tl.OnlineStep(_cv_filter())
    reloaded.load_state_dict(step.state_dict())  # kf's changed weights: the snapshot follows them
    for x, y in zip(reloaded(*args), fresh):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    with torch.no_grad():
        state, out = kf.step(tl.KalmanState(args[0], args[1]), args[2], args[3])
    assert not torch.allclose(fresh[4], before[4])
    for x, ref in zip(fresh, (state.mean, state.cov, out.innovation, out.innovation_cov, out.log_likelihood)):
        torch.testing.assert_close(x, ref, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_aoti_packaged_online_step(tmp_path):
    """The exported step through AOTInductor (compiles C++: slow), built by compile_package and
    loaded by load_package (and by torch's own loader), gives the eager step at 1 and 500 tracks."""
    kf = _cv_filter()
    path = tl.compile_package(_exported_step(kf), tmp_path / "step_aoti.pt2")
    packaged = tl.load_package(path)
    stock = torch._inductor.aoti_load_package(path)
    for b in (1, 500):
        args = _step_args(b, seed=10 + b)
        with torch.no_grad():
            state, out = kf.step(tl.KalmanState(args[0], args[1]), args[2], args[3])
        refs = (state.mean, state.cov, out.innovation, out.innovation_cov, out.log_likelihood)
        for got in (packaged(*args), stock(*args)):
            assert isinstance(got, tuple) and len(got) == 5
            for x, ref in zip(got, refs):
                torch.testing.assert_close(x, ref, rtol=0, atol=1e-9)
    # the recorded signature: a wrong dtype, rank or count is a ValueError naming the input
    mean, cov, y, dt = _step_args(2, seed=1)
    with pytest.raises(ValueError, match=r"dt must be a 1-dim torch.float64 tensor on cpu, got \(2\) torch.float32"):
        packaged(mean, cov, y, dt.float())
    with pytest.raises(ValueError, match=r"cov must be a 3-dim torch.float64"):
        packaged(mean, cov[0], y, dt)
    with pytest.raises(ValueError, match=r"takes 4 tensors \(mean, cov, y, dt\), got 3"):
        packaged(mean, cov, y)
    # sizes: tracks that disagree between inputs, a fixed size that differs (torch's own loader
    # reads past the end of y here, or returns garbage)
    with pytest.raises(ValueError, match=r"y \(3, 2\) and mean \(2, 4\) must agree in the program's dynamic dim"):
        packaged(mean, cov, torch.zeros(3, 2, dtype=F64), torch.ones(3, dtype=F64))
    with pytest.raises(
        ValueError, match=r"cov must have size 4 in dim 1 \(the program's fixed size\), got \(2, 3, 4\)"
    ):
        packaged(mean, cov[:, 1:], y, dt)
    # views: the state of kf.initial_state is expanded (stride 0), a transposed mean is not contiguous
    state = kf.initial_state((3,))
    assert state.cov.stride(0) == 0
    y3, dt3 = torch.randn(3, 2, dtype=F64), torch.full((3,), 0.5, dtype=F64)
    mean_t = torch.randn(4, 3, dtype=F64).mT
    with torch.no_grad():
        for m in (state.mean, mean_t):
            ref_state, ref_out = kf.step(tl.KalmanState(m, state.cov), y3, dt3)
            got = packaged(m, state.cov, y3, dt3)
            torch.testing.assert_close(got[0], ref_state.mean, rtol=0, atol=1e-9)
            torch.testing.assert_close(got[4], ref_out.log_likelihood, rtol=0, atol=1e-9)


def test_package_functions_reject_bad_arguments(tmp_path):
    """compile_package takes an ExportedProgram; load_package a file that exists."""
    with pytest.raises(TypeError, match="program must be a torch.export.ExportedProgram, got OnlineStep"):
        tl.compile_package(tl.OnlineStep(_cv_filter()), tmp_path / "x.pt2")
    with pytest.raises(ValueError, match="path must name an AOTInductor package file"):
        tl.load_package(tmp_path / "missing.pt2")


@pytest.mark.slow  # builds C++ kernels: ≈ 20–60 s
def test_aoti_packaged_online_step_of_a_model_that_is_not_nilpotent(tmp_path):
    """Singer (F not nilpotent: the program doubles over each gap's halvings in a while_loop)
    through AOTInductor equals the eager step for short gaps (no track needs a halving: a loop
    of no iteration, which once gave wrong values), long gaps and a mix."""
    from torch.export import Dim

    sde = tl.models.singer(dim=2, alpha=0.5, q=0.7, dtype=F64)
    kf = tl.KalmanFilter(
        sde, tl.models.position_observation(sde), 0.3 * torch.eye(2, dtype=F64), P0=torch.eye(6, dtype=F64)
    )
    g = torch.Generator().manual_seed(7)

    def args(b: int, dt: torch.Tensor) -> tuple[torch.Tensor, ...]:
        cov = torch.eye(6, dtype=F64).expand(b, 6, 6).contiguous()
        return torch.randn(b, 6, generator=g, dtype=F64), cov, torch.randn(b, 2, generator=g, dtype=F64), dt

    with torch.no_grad():
        ep = torch.export.export(
            tl.OnlineStep(kf).eval(), args(3, torch.rand(3, dtype=F64)), dynamic_shapes=({0: Dim("B", max=10_000)},) * 4
        )
    run = tl.load_package(tl.compile_package(ep, tmp_path / "singer_step.pt2"))
    for dt in (
        torch.full((1,), 0.05, dtype=F64),
        torch.full((4,), 0.05, dtype=F64),
        torch.full((2,), 30.0, dtype=F64),
        torch.tensor([0.0, 0.01, 0.7, 5.0, 80.0], dtype=F64),
    ):
        a = args(dt.numel(), dt)
        with torch.no_grad():
            state, out = kf.step(tl.KalmanState(a[0], a[1]), a[2], a[3])
        for x, ref in zip(run(*a), (state.mean, state.cov, out.innovation, out.innovation_cov, out.log_likelihood)):
            torch.testing.assert_close(x, ref, rtol=1e-9, atol=1e-9)


def test_deployed_filter_and_online_step_take_the_inputs_u():
    """A model with an input matrix B: the deployed sequence program (eager and exported with
    dynamic B, T) and the online step equal ``kf(y, dt, u=u)`` (inputs were silently 0 before)."""
    from torch.export import Dim

    sde = tl.models.mass_spring_damper(m=1.0, k=2.0, c=0.5, q=0.1, dtype=F64)
    kf = tl.KalmanFilter(
        sde, torch.tensor([[1.0, 0.0]], dtype=F64), 0.01 * torch.eye(1, dtype=F64), P0=torch.eye(2, dtype=F64)
    )
    g = torch.Generator().manual_seed(0)
    y = torch.randn(3, 12, 1, generator=g, dtype=F64)
    dt = torch.full((3, 12), 0.1, dtype=F64)
    u = torch.randn(3, 12, 1, generator=g, dtype=F64)
    with torch.no_grad():
        want = kf(y, dt, u=u)
        assert not torch.allclose(kf(y, dt).log_likelihood, want.log_likelihood)  # u matters here
        deployed = tl.DeployedFilter(kf)
        b, t = Dim("b"), Dim("t")
        ep = torch.export.export(deployed, (y, dt, u), dynamic_shapes=({0: b, 1: t}, {0: b, 1: t}, {0: b, 1: t}))
        for got in (deployed(y, dt, u), ep.module()(y[:2, :7], dt[:2, :7], u[:2, :7])):
            n = got[0].shape[0]
            ref = want if n == 3 else kf(y[:2, :7], dt[:2, :7], u=u[:2, :7])
            torch.testing.assert_close(got[0], ref.log_likelihood, rtol=0, atol=1e-10)
        step, state = tl.OnlineStep(kf), kf.initial_state(3)
        mean, cov = state.mean.contiguous(), state.cov.contiguous()
        for k in range(12):
            mean, cov, *_ = step(mean, cov, y[:, k], dt[:, k], u[:, k])
        torch.testing.assert_close(mean, want.mean[:, -1], rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "dtype, model", [(torch.float64, "cv"), (torch.float32, "cv"), (torch.float64, "integrated_ou")]
)
def test_exported_program_any_batch_and_time(dtype, model):
    """DeployedFilter(kf) exported ONCE with a dynamic batch and T: the program
    runs the default loop (torch's structured scan, any T); at every shape it equals the eager
    filter (missing components included), T = 1 and a long T included. Integrated OU: an F that
    is not nilpotent (the traced doubling in the program)."""
    from torch.export import Dim

    torch._dynamo.reset()
    if model == "cv":
        sde = tl.models.constant_velocity(dim=2, q=0.8, dtype=dtype)
    else:
        sde = tl.models.integrated_ou(k=0.5, q=1.0, dim=2, dtype=dtype)
    kf = tl.KalmanFilter(
        sde,
        torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=dtype),
        0.3 * torch.eye(2, dtype=dtype),
        P0=50 * torch.eye(4, dtype=dtype),
    )
    B, T = Dim("B", max=100_000), Dim("T", max=100_000)
    y0, dt0 = _data(2, 6, 2, seed=0)
    with torch.no_grad():
        ep = torch.export.export(
            tl.DeployedFilter(kf).eval(),
            (y0.to(dtype), dt0.to(dtype)),
            dynamic_shapes={"y": {0: B, 1: T}, "dt": {0: B, 1: T}},
        )
    prog = ep.module()
    atol = 1e-9 if dtype == torch.float64 else 2e-2
    for b, t in ((1, 1), (1, 37), (3, 130), (40, 9), (0, 5)):  # (B = 0: inside the Dim's range)
        y, dt = (x.to(dtype) for x in _data(b, t, 2, seed=b + t)) if t > 3 and b else _short(b, t, dtype)
        with torch.no_grad():
            ref = kf(y, dt)
        ll, mean = prog(y, dt)
        torch.testing.assert_close(ll, ref.log_likelihood, rtol=1e-6 if dtype == torch.float32 else 0, atol=atol)
        torch.testing.assert_close(mean, ref.mean, rtol=1e-5 if dtype == torch.float32 else 0, atol=atol)


def _short(b: int, t: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(b * 10 + t)
    return torch.randn(b, t, 2, generator=g, dtype=dtype), torch.rand(b, t, generator=g, dtype=dtype) + 0.1


def test_exported_online_step_run_as_it_is():
    """OnlineStep(kf) exported with a dynamic batch and run as it is (``ep.module()``): the
    online step is one implementation (the sequence loop's step); the program equals the eager
    step at 1, 7 and 300 tracks."""
    from torch.export import Dim

    kf = _cv_filter()
    with torch.no_grad():
        ep = torch.export.export(tl.OnlineStep(kf).eval(), _step_args(3, 0), dynamic_shapes=({0: Dim("B")},) * 4)
    prog = ep.module()
    for b in (1, 7, 300):
        args = _step_args(b, seed=b)
        with torch.no_grad():
            state, out = kf.step(tl.KalmanState(args[0], args[1]), args[2], args[3])
        for x, ref in zip(prog(*args), (state.mean, state.cov, out.innovation, out.innovation_cov, out.log_likelihood)):
            torch.testing.assert_close(x, ref, rtol=0, atol=1e-10)


def test_package_signature_of_programs_with_unbounded_sizes():
    """compile_package records each dynamic size's range: a program with a Dim("B") without
    max= (and the deploy page's static-shape sequence program, whose structured scan creates an
    unbounded size) failed with "'Infinity' object has no attribute '_mpf_'" (torch's unbounded
    marker converted with int()); the range is now [lowest, None]."""
    from torch.export import Dim

    from torchsde_lti.nn.deploy import _ranges

    sde = tl.models.integrated_ou(k=0.5, q=1.0, dim=2, dtype=F64)
    kf = tl.KalmanFilter(sde, tl.models.position_observation(sde), torch.eye(2, dtype=F64), P0=torch.eye(4, dtype=F64))
    example = (torch.zeros(2, 30, 2, dtype=F64), torch.ones(2, 30, dtype=F64))
    static = torch.export.export(tl.DeployedFilter(kf.eval()), example)  # (the deploy page's program)
    assert list(_ranges(static).values()) == [[1, None]]
    with torch.no_grad():
        step = torch.export.export(
            tl.OnlineStep(_cv_filter()).eval(), _step_args(3, 0), dynamic_shapes=({0: Dim("B")},) * 4
        )
    assert [bounds[1] for bounds in _ranges(step).values()] == [None]


@pytest.mark.slow
def test_compile_package_of_the_deploy_pages_static_program(tmp_path):
    """The deploy page's static-shape program through compile_package and load_package (compiles
    C++: slow) equals eager."""
    sde = tl.models.integrated_ou(k=0.5, q=1.0, dim=2, dtype=F64)
    kf = tl.KalmanFilter(sde, tl.models.position_observation(sde), torch.eye(2, dtype=F64), P0=torch.eye(4, dtype=F64))
    kf.eval()
    example = (torch.zeros(2, 30, 2, dtype=F64), torch.ones(2, 30, dtype=F64))
    run = tl.load_package(tl.compile_package(torch.export.export(tl.DeployedFilter(kf), example), tmp_path / "kf.pt2"))
    y, dt = _data(2, 30, 2, seed=1)
    ll, mean = run(y, dt)
    torch.testing.assert_close(ll, kf(y, dt).log_likelihood.detach(), rtol=0, atol=1e-9)


def test_deploy_modules_warn_that_runtime_has_no_effect():
    """runtime= is accepted for compatibility only: a DeprecationWarning that says it has no
    effect, and the module is the one built without it (same outputs)."""
    kf = _cv_filter()
    args = _step_args(3, 0)
    with pytest.warns(DeprecationWarning, match="runtime has no effect"):
        deployed = tl.DeployedFilter(kf, runtime="eager")
    with pytest.warns(DeprecationWarning, match="runtime has no effect"):
        step = tl.OnlineStep(kf, runtime="inductor")
    assert not hasattr(deployed, "runtime") and not hasattr(step, "runtime")
    y, dt = _data(2, 6, 2, seed=0)
    with torch.no_grad():
        for got, want in zip(deployed(y, dt), tl.DeployedFilter(kf)(y, dt)):
            torch.testing.assert_close(got, want, rtol=0, atol=0)
        for got, want in zip(step(*args), tl.OnlineStep(kf)(*args)):
            torch.testing.assert_close(got, want, rtol=0, atol=0)


def test_exported_program_forced_scan_and_a_report_batch_smaller_than_dt():
    """algorithm="scan" forced (one scan over any T while exporting, no chunks: the chunking
    specialised B and T) and, in the auto program, reports y (1, T, m) shared
    by dt (B, T): the branches read the batch from the prior mean, which has the whole batch."""
    from torch.export import Dim

    torch._dynamo.reset()
    kf = _cv_filter()
    B, T = Dim("B", max=10_000), Dim("T", max=10_000)
    y0, dt0 = _data(2, 6, 2, seed=0)
    with torch.no_grad():
        forced = tl.KalmanFilter(kf.sde, kf.H, kf.R, P0=kf.P0, algorithm="scan")
        programs = {
            "scan": torch.export.export(
                tl.DeployedFilter(forced),
                (y0, dt0),
                dynamic_shapes={"y": {0: B, 1: T}, "dt": {0: B, 1: T}},
            ).module(),
            "shared y": torch.export.export(
                tl.DeployedFilter(kf), (y0[:1], dt0), dynamic_shapes={"y": {1: T}, "dt": {0: B, 1: T}}
            ).module(),
        }
        for b, t in ((1, 9), (5, 33), (30, 4)):
            y, dt = _data(b, t, 2, seed=b * t)
            ll, mean = programs["scan"](y, dt)
            ref = forced(y, dt)
            torch.testing.assert_close(ll, ref.log_likelihood, rtol=0, atol=1e-9)
            torch.testing.assert_close(mean, ref.mean, rtol=0, atol=1e-9)
            ll, mean = programs["shared y"](y[:1], dt)
            ref = kf(y[:1], dt)
            assert ll.shape == (b,)
            torch.testing.assert_close(ll, ref.log_likelihood, rtol=0, atol=1e-9)
            torch.testing.assert_close(mean, ref.mean, rtol=0, atol=1e-9)


@pytest.mark.parametrize("dynamic", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_imm_with_a_batch_equal_to_its_number_of_modes_exports(dynamic):
    """DeployedFilter of an IMM with an R per mode, exported (in grad mode: its parameters require
    grad) at an example batch B equal to its number of modes M (= 2): B and M then share one symbol
    in the scan's traced cycle, and the online step's ``H @ P⁻ @ Hᵀ`` (a matmul folding the two
    batch dims into one of size B·M) failed torch's tracing with "s*((s**2)//s) is not tracked with
    proxy" (experiments/export_scan_matmul.py: torch alone); S is now the sequence filter's own
    multiply-adds. The program gives the eager values at that batch and, dynamic, at others."""
    from torch.export import Dim

    torch._dynamo.reset()
    cv = tl.models.constant_velocity(dim=1, q=0.5, dtype=F64)
    iou = tl.models.integrated_ou(1.5, 0.05, dim=1, dtype=F64)
    R = torch.tensor([[[0.4]], [[2.0]]], dtype=F64)  # (M, m, m): one R per mode
    imm = tl.IMMFilter([cv, iou], torch.tensor([[1.0, 0.0]], dtype=F64), R, torch.tensor([[0.0, 0.2], [0.4, 0.0]],
                       dtype=F64), P0=30 * torch.eye(2, dtype=F64), mode_prob0=torch.tensor([0.3, 0.7], dtype=F64))  # fmt: skip
    y, dt = _data(2, 5, 1, seed=3)
    shapes = {"y": {0: Dim("B"), 1: Dim("T")}, "dt": {0: Dim("B"), 1: Dim("T")}} if dynamic else None
    program = torch.export.export(tl.DeployedFilter(imm).eval(), (y, dt), dynamic_shapes=shapes).module()
    for b, t in ((2, 5), (3, 7), (1, 4)) if dynamic else ((2, 5),):
        y, dt = _data(b, t, 1, seed=b + t)
        ll, mean = program(y, dt)
        with torch.no_grad():
            ref = imm(y, dt)
        torch.testing.assert_close(ll, ref.log_likelihood, rtol=0, atol=1e-12)
        torch.testing.assert_close(mean, ref.mean, rtol=0, atol=1e-12)
