"""evaluation.scores: the one evaluation of frozen filters (moving windows, HPD coverage,
forecast RMSE, paired vessel bootstrap), with the CV oracle (evaluation.baseline) and the model
selection on validation (evaluation.selection), on small synthetic tracks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from torchsde_lti import models
from torchsde_lti.data import ExponentialDt, simulate_tracks
from torchsde_lti.data.loaded_tracks import LoadSummary, Tracks
from torchsde_lti.evaluation.baseline import cv_filter, tune_cv
from torchsde_lti.evaluation.scores import (
    NOMINAL_2SIGMA,
    EvalRecords,
    evaluate_filter,
    forecast_pairs,
    hpd_inside,
    mixture_log_prob,
    moving_reports,
    paired_bootstrap,
    summary,
)
from torchsde_lti.evaluation.selection import select_model, validation_selection


def make_tracks(object_id: list[int], times: list[np.ndarray], positions: list[np.ndarray]) -> Tracks:
    """Tracks from per-track times (s) and positions (T, 2) m (no lat/lon: zeros)."""
    lengths = [len(t) for t in times]
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    N = int(offsets[-1])
    fields = {f: 0 for f in LoadSummary.__dataclass_fields__}
    fields.update(source="synthetic", malformed_examples=(), frame="local", rules={}, dims=2)
    return Tracks(
        np.asarray(object_id, dtype=np.int64),
        offsets,
        np.concatenate(times).astype(np.float64),
        np.concatenate(positions).astype(np.float64),
        np.zeros(N),
        np.zeros(N),
        None,
        None,
        None,
        np.zeros((len(times), 3)),
        np.datetime64("2020-01-01T00:00:00", "us"),
        "local",
        LoadSummary(**fields),
    )


def simulated_cv(q: float, r: float, num: int, T: int, seed: int, mean_dt: float = 60.0) -> Tracks:
    """Constant-velocity tracks observed with noise r² I: one vessel per track."""
    sde = tl.models.constant_velocity(dim=2, q=torch.tensor(q, dtype=torch.float64))
    H = tl.models.position_observation(sde)
    P0 = torch.diag(torch.tensor([1e-6, 25.0, 1e-6, 25.0], dtype=torch.float64))
    b = simulate_tracks(
        sde,
        H,
        r**2 * torch.eye(2, dtype=torch.float64),
        num,
        T,
        dt_sampler=ExponentialDt(mean_dt, min_dt=5.0),
        P0=P0,
        seed=seed,
    )
    t = torch.cumsum(b.dt, dim=1).numpy()
    return make_tracks(list(range(num)), [t[i] for i in range(num)], [b.y[i].numpy() for i in range(num)])


def test_mixture_log_prob_matches_torch_distributions() -> None:
    g = torch.Generator().manual_seed(0)
    w = torch.tensor([[0.3, 0.7]], dtype=torch.float64)
    mu = torch.randn(1, 2, 2, generator=g, dtype=torch.float64)
    A = torch.randn(1, 2, 2, 2, generator=g, dtype=torch.float64)
    S = A @ A.mT + 0.5 * torch.eye(2, dtype=torch.float64)
    x = torch.randn(1, 2, generator=g, dtype=torch.float64)
    want = math.log(
        sum(
            float(w[0, j]) * math.exp(float(torch.distributions.MultivariateNormal(mu[0, j], S[0, j]).log_prob(x[0])))
            for j in range(2)
        )
    )
    assert float(mixture_log_prob(x, w, mu, S)[0]) == pytest.approx(want, rel=1e-12)


def test_hpd_of_a_gaussian_is_the_2sigma_ellipse_and_mixture_coverage_is_nominal() -> None:
    g = torch.Generator().manual_seed(1)
    N = 3000
    S1 = torch.tensor([[4.0, 1.0], [1.0, 2.0]], dtype=torch.float64).expand(N, 1, 2, 2)
    y = torch.randn(N, 2, generator=g, dtype=torch.float64) @ torch.linalg.cholesky(S1[0, 0]).mT
    inside = hpd_inside(y, torch.ones(N, 1, dtype=torch.float64), torch.zeros(N, 1, 2, dtype=torch.float64), S1)
    maha = (y.unsqueeze(-2) @ torch.linalg.solve(S1[:, 0], y.unsqueeze(-1))).reshape(-1)
    assert torch.equal(inside, maha <= 4.0)
    assert float(inside.double().mean()) == pytest.approx(NOMINAL_2SIGMA, abs=0.02)
    # a two-component mixture (narrow + wide, like moored + underway): draws from it land inside
    # its Monte Carlo HPD region at the nominal rate
    w = torch.tensor([0.6, 0.4], dtype=torch.float64).expand(N, 2)
    mu = torch.tensor([[0.0, 0.0], [30.0, 0.0]], dtype=torch.float64).expand(N, 2, 2)
    S = torch.stack([torch.eye(2), 400.0 * torch.eye(2)]).double().expand(N, 2, 2, 2)
    comp = torch.multinomial(w[0], N, replacement=True, generator=g)
    z = torch.randn(N, 2, generator=g, dtype=torch.float64)
    ym = mu[0][comp] + z * torch.tensor([1.0, 20.0], dtype=torch.float64)[comp, None]
    cover = float(hpd_inside(ym, w, mu, S, samples=400, seed=3).double().mean())
    assert cover == pytest.approx(NOMINAL_2SIGMA, abs=0.025)
    # the same mixture, a component written twice, is still the same Gaussian: same region (up to MC)
    n = 500
    two = hpd_inside(
        y[:n],
        torch.full((n, 2), 0.5, dtype=torch.float64),
        torch.zeros(n, 2, 2, dtype=torch.float64),
        S1[:n].expand(n, 2, 2, 2),
        samples=2000,
    )
    assert float((two == inside[:n]).double().mean()) > 0.97


def test_moving_windows_by_the_median_position_speed() -> None:
    # track 0: 2 m/s for the first hour, then still; track 1: 0.5 m/s throughout (moored by the rule)
    t0 = np.arange(0.0, 7200.0, 60.0)
    x0 = np.where(t0 < 3600.0, 2.0 * t0, 2.0 * 3600.0)
    t1 = np.arange(0.0, 3000.0, 100.0)
    tr = make_tracks([7, 8], [t0, t1], [np.stack([x0, 0 * t0], -1), np.stack([0.5 * t1, 0 * t1], -1)])
    mv = moving_reports(tr.t, tr.pos, tr.offsets)
    n0 = len(t0)
    assert mv[:n0][t0 < 3600].all() and not mv[:n0][t0 >= 3600].any()
    assert not mv[n0:].any()
    assert moving_reports(tr.t, tr.pos, tr.offsets, moving_speed=0.4)[n0:].all()


def test_forecast_rmse_and_nll_match_a_hand_computation() -> None:
    tr = simulated_cv(0.01, 5.0, num=3, T=40, seed=2)
    kf = cv_filter(0.02, 6.0)
    rec = evaluate_filter(kf, tr, horizons=(300.0,))
    res = summary(rec)
    sq, nll, n_fc = [], [], 0
    for i in range(len(tr)):
        a, b = tr.offsets[i], tr.offsets[i + 1]
        t, y = torch.as_tensor(tr.t[a:b]), torch.as_tensor(tr.pos[a:b]) - torch.as_tensor(tr.pos[a])
        dt = torch.cat([torch.zeros(1, dtype=torch.float64), torch.diff(t)])
        with torch.no_grad():
            out = kf(y, dt)
        nll += (-out.step_log_likelihood[1:]).tolist()
        for k in range(1, len(t)):
            leads = t[k + 1 :] - t[k]
            if leads.numel() == 0:
                continue
            j = int(torch.argmin((leads - 300.0).abs()))
            if abs(float(leads[j]) - 300.0) > 75.0:
                continue
            with torch.no_grad():
                fc = kf.forecast((out.mean[k], out.cov[k]), leads[j : j + 1])
            sq.append(float(((fc.obs_mean[0] - y[k + 1 + j]) ** 2).sum()))
            n_fc += 1
    assert res["fc_n_5"] == n_fc > 10
    assert res["fc_rmse_5"] == pytest.approx(math.sqrt(np.mean(sq)), rel=1e-9)
    assert res["nll"] == pytest.approx(np.mean(nll), rel=1e-9)
    assert res["reports"] == len(nll) and res["vessels"] == 3


def test_coverage_of_the_true_model_is_nominal() -> None:
    q, r = 0.02, 4.0
    tr = simulated_cv(q, r, num=40, T=80, seed=5)
    res = summary(
        evaluate_filter(cv_filter(q, r, diffuse_variance=25.0), tr, horizons=(300.0,), forecast_coverage=True)
    )
    assert res["cover2s"] == pytest.approx(NOMINAL_2SIGMA, abs=0.02)
    assert res["fc_cover2s_5"] == pytest.approx(NOMINAL_2SIGMA, abs=0.03)
    # a model far too confident under-covers
    bad = summary(evaluate_filter(cv_filter(q / 100, r / 4), tr, horizons=(300.0,)))
    assert bad["cover2s"] < 0.6


def _records(nll: np.ndarray, vessel: np.ndarray, V: int) -> EvalRecords:
    n = nll.size
    return EvalRecords(vessel, nll, np.arange(n) % 2 == 0, np.ones(n, bool), np.ones(n), {}, V)


def test_paired_bootstrap_interval_covers_the_true_difference() -> None:
    true, hits = 0.3, 0
    for rep in range(40):
        rng = np.random.default_rng(rep)
        V = 40
        vessel = np.repeat(np.arange(V), rng.integers(5, 30, V))
        base = rng.normal(10.0, 2.0, vessel.size)
        effect = true + rng.normal(0.0, 0.5, V)  # vessel-level differences: reports are not independent
        a, b = _records(base + effect[vessel], vessel, V), _records(base, vessel, V)
        d = paired_bootstrap(a, b, metrics=["nll"], n_boot=400, seed=rep)["nll"]
        assert d["lo"] <= d["delta"] <= d["hi"]
        assert d["delta"] == pytest.approx(float(np.mean(effect[vessel])), rel=1e-12)
        # effect per vessel is i.i.d. with mean `true`; weights by report count keep it unbiased
        hits += d["lo"] <= true <= d["hi"]
    assert hits >= 33  # nominal 95 % of 40 (binomial: P(< 34) ~ 1 %)
    # identical models: zero difference, a zero-width interval
    z = paired_bootstrap(b, b, n_boot=100)
    assert all(v["delta"] == 0.0 and v["lo"] == 0.0 == v["hi"] for k, v in z.items() if math.isfinite(v["delta"]))
    with pytest.raises(ValueError, match="same reports"):
        paired_bootstrap(a, _records(base[:-1], vessel[:-1], V))


def test_forecast_pairs_pick_the_nearest_lead_within_tolerance() -> None:
    t = torch.tensor([[0.0, 100.0, 290.0, 420.0, 700.0]], dtype=torch.float64)
    batch = tl.data.TrackBatch(
        torch.zeros(1, 5, 2), torch.zeros(1, 5), torch.ones(1, 5, dtype=torch.bool), torch.tensor([5]), t=t
    )
    b, k, j = forecast_pairs(batch, 300.0)
    # from 100: 420 (lead 320); from 290: nearest 700 (lead 410, off by > 25 %): none; from 420: 700 (280);
    # never from the first report (k = 0)
    assert list(zip(k.tolist(), j.tolist())) == [(1, 3), (3, 4)] and b.tolist() == [0, 0]


def test_cv_oracle_grid_extends_until_the_optimum_is_inside() -> None:
    tr = simulated_cv(0.01, 3.0, num=20, T=60, seed=7)
    q, r, table = tune_cv(tr, q_grid=(1e2, 1e3), r_grid=(100.0, 300.0), refine=1)
    assert 0.002 < q < 0.05 and 1.5 < r < 6.0
    best = min(table.values())
    assert best == pytest.approx(table[(q, r)])
    qs = sorted({k[0] for k in table})
    assert qs[0] < q < qs[-1]


def harbour_tracks() -> Tracks:
    """Five vessels of the NY harbour on 7 Dec 2020 (NYHarbor_2020_12_first_week.traj, tracktable-data;
    the ny_week set's test split, per-track local east/north metres and seconds from each track's
    first report): moored ones with positions quantised to ~0.84 m, and ships under way."""
    from pathlib import Path

    data = np.load(Path(__file__).parent / "data" / "ny_harbour_2020_12_07_five_vessels.npz")
    off = data["offsets"]
    times = [data["t"][a:b] for a, b in zip(off[:-1], off[1:])]
    positions = [data["pos"][a:b] for a, b in zip(off[:-1], off[1:])]
    return make_tracks(data["object_id"].tolist(), times, positions)


def test_cv_oracle_refines_before_it_walks_and_stops_at_an_interior_optimum() -> None:
    """On a harbour day the coarse grid's optimum (q = 0.1) sits where the NLL keeps falling as
    R -> 0: walking at the coarse steps never stops (the old grid extension ended at r = 6e-7 m).
    Refining first finds the valley floor (q ~ 0.056) and an interior r of metres, with a lower NLL
    than any R -> 0 point scored."""
    tr = harbour_tracks()
    with pytest.raises(ValueError, match="no interior optimum"):
        tune_cv(tr, refine=0, max_rounds=6)  # the walk at the coarse steps heads for R -> 0
    q, r, table = tune_cv(tr)
    assert 5.0 < r < 60.0 and 0.02 < q < 0.2
    assert table[(q, r)] == min(table.values())
    r_to_0 = summary(evaluate_filter(cv_filter(q, 1e-6), tr))["nll"]  # the boundary R -> 0 at the same q
    assert table[(q, r)] < r_to_0 - 0.01
    dq, dr = 0.25, math.log10(3.0) / 4  # the final steps: the coarse grid's (1 decade, 0.477) / 2^refine
    for i in (-1, 0, 1):  # every neighbour at the final steps was scored, and is worse
        for j in (-1, 0, 1):
            if i or j:
                nq, nr = q * 10 ** (i * dq), r * 10 ** (j * dr)
                (value,) = [v for (a, b), v in table.items() if abs(a / nq - 1) < 1e-6 and abs(b / nr - 1) < 1e-6]
                assert value > table[(q, r)]


def wiggly_tracks(num: int, T: int, seed: int, q: float = 1e-3, sig: float = 60.0, tau: float = 300.0) -> Tracks:
    """Constant-velocity tracks (q) plus a slow Ornstein-Uhlenbeck wiggle of the position (std sig m,
    time constant tau s) and 3 m white noise, reported every ~15 s: a filter that tracks the wiggle
    (high q, small R) has the better one-step NLL, one that averages it out the better forecasts."""
    rng = np.random.default_rng(seed)
    times, positions = [], []
    for _ in range(num):
        dt = rng.exponential(10.0, T - 1) + 5.0
        x, v, w = np.zeros(2), rng.normal(0.0, 3.0, 2), rng.normal(0.0, sig, 2)
        pos = [x + w + 3.0 * rng.normal(size=2)]
        for d in dt:
            L = np.linalg.cholesky(q * np.array([[d**3 / 3, d**2 / 2], [d**2 / 2, d]]))
            e = L @ rng.normal(size=(2, 2))  # (x, v) increments of both axes
            x, v = x + v * d + e[0], v + e[1]
            phi = math.exp(-d / tau)
            w = phi * w + sig * math.sqrt(1 - phi**2) * rng.normal(size=2)
            pos.append(x + w + 3.0 * rng.normal(size=2))
        times.append(np.concatenate([[0.0], np.cumsum(dt)]))
        positions.append(np.stack(pos))
    return make_tracks(list(range(num)), times, positions)


def _cv_imm(q1: float, q2: float, r: float) -> tl.IMMFilter:
    f64 = torch.float64
    a, b = (models.constant_velocity(dim=2, q=torch.tensor(q, dtype=f64)) for q in (q1, q2))
    rates = torch.tensor([[0.0, 1e-3], [1e-3, 0.0]], dtype=f64)
    return tl.IMMFilter(
        [a, b], models.position_observation(a), r**2 * torch.eye(2, dtype=f64), rates, diffuse_variance=100.0
    )


def test_selection_picks_the_forecast_qualified_candidate_not_the_lowest_nll() -> None:
    tr = wiggly_tracks(8, 120, seed=0)
    ms = {
        "cv_smooth": cv_filter(0.1, 60.0),  # the best single (lower NLL than cv_rough)
        "cv_rough": cv_filter(1.0, 60.0),
        "imm_track": _cv_imm(0.01, 0.1, 10.0),  # tracks the wiggle: lowest NLL, worse forecasts
        "imm_smooth": _cv_imm(1e-3, 3e-3, 60.0),  # averages it out: better forecasts
    }
    sel = validation_selection(ms, tr, cov_scale={"cv_rough": 2.0}, samples=20)
    v = sel.table
    # the premise: one-step NLL alone would pick imm_track, whose forecasts lose to the best single
    assert min(v, key=lambda n: v[n]["nll"]) == "imm_track"
    assert all(v["imm_track"][f"fc_rmse_{h}"] > v["cv_smooth"][f"fc_rmse_{h}"] for h in (5, 10, 15))
    assert all(v["imm_smooth"][f"fc_rmse_{h}"] <= v["cv_smooth"][f"fc_rmse_{h}"] for h in (5, 10, 15))
    assert sel.best_single == "cv_smooth" and sel.candidates == ("imm_track", "imm_smooth")
    assert sel.best == "imm_smooth" and sel.qualified == ("imm_smooth",) and not sel.fallback
    # the table is evaluate_filter's summary on these tracks, of the calibrated predictive where a scale is given
    rough = summary(evaluate_filter(ms["cv_rough"], tr, samples=20, cov_scale=2.0))
    assert v["cv_rough"]["nll"] == pytest.approx(rough["nll"], rel=1e-12)
    # without a qualified candidate: the lowest NLL of all, flagged
    del ms["imm_smooth"]
    fb = select_model({n: v[n] for n in ms}, ["cv_smooth", "cv_rough"])
    assert fb.best == "imm_track" and fb.fallback and fb.qualified == () and "FALLBACK" in fb.reason


def test_select_model_rule_on_given_summaries() -> None:
    def row(nll: float, *fc: float) -> dict[str, float]:
        return {"nll": nll, "fc_rmse_5": fc[0], "fc_rmse_10": fc[1], "fc_rmse_15": fc[2]}

    val = {
        "s1": row(6.0, 100.0, 200.0, 300.0),
        "s2": row(5.0, 110.0, 190.0, 310.0),  # best single (lowest NLL of the singles), not the best forecasts
        "a": row(4.0, 100.0, 190.0, 311.0),  # lowest NLL, worse than s2 at 15 min
        "b": row(4.5, 110.0, 190.0, 310.0),  # ties s2 everywhere: qualifies (<=)
        "c": row(4.2, math.nan, 100.0, 100.0),  # no 5-min pairs: does not qualify
        "d": row(4.8, 50.0, 50.0, 50.0),
    }
    sel = select_model(val, ["s1", "s2"])
    assert (sel.best, sel.best_single, sel.qualified, sel.fallback) == ("b", "s2", ("b", "d"), False)
    assert sel.candidates == ("a", "b", "c", "d")
    # only some horizons checked: a qualifies on 5 and 10 min
    assert select_model(val, ["s1", "s2"], horizons=(300.0, 600.0)).best == "a"
    # only singles: nothing to choose among, the lowest NLL
    only = select_model({k: val[k] for k in ("s1", "s2")}, ["s1", "s2"])
    assert only.best == "s2" and only.fallback
    with pytest.raises(ValueError, match="singles"):
        select_model(val, [])
    with pytest.raises(ValueError, match="singles"):
        select_model(val, ["nope"])
    with pytest.raises(ValueError, match="lacks"):
        select_model({"s1": {"nll": 1.0}}, ["s1"])


def test_evaluation_modules_import_downwards_only() -> None:
    """The subpackage has no import cycle (issue 40: calibration and evaluation imported each
    other): each module imports only modules before it in recovery, figures, history_figures,
    student_t, predictive, calibration, scores, baseline / selection, batch_scores, at any depth
    (function-level imports included); the k-step NLL that moved out of the training module is
    still importable from there, the same object."""
    import ast
    from pathlib import Path

    import torchsde_lti.evaluation as ev
    import torchsde_lti.training.module as training_module

    order = ["recovery", "figures", "history_figures", "student_t", "predictive", "calibration", "scores"]
    order += ["baseline", "selection", "batch_scores"]
    folder = Path(ev.__file__).parent
    assert sorted(p.stem for p in folder.glob("*.py") if p.stem != "__init__") == sorted(order)
    for rank, name in enumerate(order):
        tree = ast.parse((folder / f"{name}.py").read_text())
        imported = {
            node.module.split(".")[2]
            for node in ast.walk(tree)
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("torchsde_lti.evaluation.")
        }
        later = imported & set(order[rank:]) - {name}
        if name in ("baseline", "selection"):
            later -= {"baseline", "selection"} - {name}
            assert not ({"baseline", "selection"} & imported), f"{name} imports {imported}"
        assert not later, f"evaluation.{name} imports later modules {sorted(later)}"
    assert training_module.imm_k_step_nll is ev.imm_k_step_nll


def test_a_horizon_without_pairs_summarises_as_nan_and_bootstraps() -> None:
    """One 9-minute track: 5- and 10-minute forecast pairs, none at 15 minutes. The summary
    says NaN and 0 pairs at 15 minutes, and the bootstrap runs (both raised a numpy casting
    error from the empty horizon's float vessel array)."""
    t = np.arange(10) * 60.0
    tracks = make_tracks([1], [t], [np.stack([2 * t, 0 * t], -1)])
    rec = evaluate_filter(cv_filter(0.01, 10.0), tracks)
    assert rec.fc[900.0][0].dtype == np.int64 and rec.fc[900.0][0].size == 0
    s = summary(rec)
    assert s["fc_n_15"] == 0 and math.isnan(s["fc_rmse_15"]) and s["fc_n_5"] == 5
    paired_bootstrap(rec, rec)


def test_tune_cv_refuses_tracks_with_nothing_to_score() -> None:
    """Single-report tracks: the first report of a track is not scored, so no grid point has a
    score (each was 0.0, a meaningless optimum)."""
    t = [np.array([0.0]), np.array([5.0])]
    tracks = make_tracks([1, 2], t, [np.zeros((1, 2)), np.ones((1, 2))])
    with pytest.raises(ValueError, match="at least two reports"):
        tune_cv(tracks)


def test_scoring_leaves_the_callers_model_as_it_was() -> None:
    """evaluate_filter and one_step_predictive score a float64 eval-mode copy: the caller's
    float32 module in training mode stays so (both converted it in place)."""
    from torchsde_lti.evaluation.calibration import one_step_predictive

    t = np.arange(12) * 30.0
    tracks = make_tracks([1], [t], [np.stack([3 * t, t], -1)])
    model = cv_filter(0.01, 10.0).float().train()
    evaluate_filter(model, tracks)
    one_step_predictive(model, tracks)
    assert model.training and all(p.dtype == torch.float32 for p in model.parameters())
