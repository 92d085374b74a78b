"""Learned motion models vs a tuned constant-velocity filter on real AIS ship tracks.

    python experiments/ais_study.py            # ~ a few minutes on 2 CPU cores

Data: one hour of AIS reports in New York Harbor (``torchsde_lti.data.ais``, needs the optional
package tracktable-data), vessels split 60/20/20 into train/val/test with seed 0, positions
in a local east/north frame (metres), each track centred on its first report.

Models (all exact-discretisation Kalman filters over the irregular report times, observing
position with noise R, a full 2x2 covariance when learned):

- ``cv (grid)``: the practitioner's baseline, constant velocity with isotropic R; q and
  R chosen by grid search on the VALIDATION vessels' predictive NLL;
- ``cv``: constant velocity, q and R learned;
- ``integrated_ou``: velocity with drag k (dv = -k v dt + dβ), k, q, R learned;
- ``singer``: acceleration with drag alpha, alpha, q, R learned;
- ``hurwitz_drag``: coupled 2-D velocity dynamics dv = F_v v dt + dβ with a learned 2x2
  Hurwitz-stable F_v (can rotate and damp) and a full learned Qc, R.

Learned models maximise the Kalman-filter likelihood of the TRAINING vessels (full batch,
L-BFGS, float64). The prior sits at each track's first report: x0 ~ N(0, P0) with P0 =
diag(100 m, 5 m/s, 0.1 m/s^2)^2 per axis (shared by all models); since the tracks are
centred on that report, its own likelihood term is left out of training and evaluation:
every NLL is of reports 2..T given the earlier ones.

Test metrics (test vessels only): one-step predictive NLL per 2-D report (nats), one-step
position RMSE (m, Euclidean), share of reports inside the predictive 2σ ellipse (86.5 %
for a calibrated Gaussian), forecast RMSE at 1, 5, 10 min (from every filtered state with
>= 2 reports seen to the report whose lead time is nearest the horizon, within ±25 %),
and RMSE of the filtered velocity against the SOG/COG velocity (m/s), for all reports and
for reports with SOG >= 2 kn.

Writes experiments/results/ais.md, ais_map.png, ais_horizon.png (and ais_metrics.json).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import torch
from torch import Tensor

import torchsde_lti as tl
from torchsde_lti.data import TrackBatch, ais
from torchsde_lti.core.validation import validation
from torchsde_lti.filters import FilterResult, kalman_filter
from torchsde_lti.nn.parametrizations import IntegratorChain

HORIZONS_MIN = (1.0, 5.0, 10.0)
CURVE_MIN = (1.0, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0)
P0_STD = (100.0, 5.0, 0.1)  # per axis: position (m), velocity (m/s), acceleration (m/s^2)
CHI2_2SIGMA = 4.0  # Mahalanobis² of the 2σ ellipse in 2-D; P(chi2_2 <= 4) = 1 - e^-2
Q_GRID = 10.0 ** np.arange(-5.0, 0.01, 0.5)  # baseline grid for q, m²/s³, half decades
R_STD_GRID = np.array([2.0, 3.0, 5.0, 7.0, 10.0, 15.0, 20.0, 30.0, 50.0])  # baseline grid for sqrt(R), m


class Spec(NamedTuple):
    """A motion model: its SDE, the per-axis order of its state (2: [p, v], 3: [p, v, a])."""

    name: str
    build: Callable[[], tl.LTISDE]
    order: int
    about: str


def _f64(x: float) -> Tensor:
    return torch.tensor(x, dtype=torch.float64)


def hurwitz_drag() -> tl.LTISDE:
    """[x, vx, y, vy] with dx = v dt, dv = F_v v dt + dβ, F_v (2, 2) Hurwitz, Qc (2, 2) full."""
    F = torch.tensor([[0, 1, 0, 0], [0, -0.01, 0, 0], [0, 0, 0, 1], [0, 0, 0, -0.01]], dtype=torch.float64)
    L = torch.tensor([[0, 0], [1, 0], [0, 0], [0, 1]], dtype=torch.float64)
    sde = tl.LTISDE(F, L, 0.01 * torch.eye(2, dtype=torch.float64), learn=("F", "Qc"),
                    F_constraint=IntegratorChain(order=2, dim=2, drag="hurwitz"))
    sde.position_indices = (0, 2)
    return sde


SPECS = [
    Spec("cv", lambda: tl.models.constant_velocity(dim=2, q=_f64(0.01)), 2, "q, R"),
    Spec("integrated_ou", lambda: tl.models.integrated_ou(k=_f64(0.01), q=_f64(0.01), dim=2), 2, "k, q, R"),
    Spec("singer", lambda: tl.models.singer(alpha=_f64(0.02), q=_f64(1e-4), dim=2), 3, "alpha, q, R"),
    Spec("hurwitz_drag", hurwitz_drag, 2, "F_v (2x2 Hurwitz), Qc (2x2), R"),
]


def make_filter(sde: tl.LTISDE, order: int, R: Tensor, learn_R: bool = True) -> tl.KalmanFilter:
    """Position-observing filter with the shared prior N(0, diag(P0_STD[:order])^2 per axis)."""
    H = tl.models.position_observation(sde)
    n = H.shape[-1]
    var = torch.tensor([s**2 for s in P0_STD[:order]] * (n // order), dtype=torch.float64)
    return tl.KalmanFilter(sde, H, R, m0=torch.zeros(n, dtype=torch.float64), P0=torch.diag(var),
                           learn=("R",) if learn_R else ())


def velocity_readout(kf: tl.KalmanFilter) -> Tensor:
    """(2, n) selecting the velocity components: one past each position component."""
    H = kf.H.detach()
    return torch.roll(H, shifts=1, dims=-1)


def run_filter(kf: tl.KalmanFilter, batch: TrackBatch) -> FilterResult:
    """``kf(batch.y, batch.dt, mask=batch.mask)`` with each DISTINCT dt discretised once.

    AIS times have 1 s resolution, so the ~9k steps of the training split share ~160
    distinct dt; discretising those (U, n, n) and gathering is the same computation as the
    filter's own batched ``sde(dt, series=True)`` (checked in :func:`main`) but cheaper: one
    likelihood + gradient on the training split took 0.064 s instead of 0.14 s (integrated
    OU) and 0.083 s instead of 0.26 s (Singer), 1 thread. Everything else is
    ``tl.KalmanFilter``'s: its prior, H, R, and the functional filter it calls.
    """
    uniq, inv = torch.unique(batch.dt, return_inverse=True)
    d = kf.sde(uniq)  # A, Q: (U, n, n)
    m0, P0 = kf.initial_state()
    with validation(False):  # as in KalmanFilter.forward: matrices are valid by construction
        return kalman_filter(batch.y, d.A[inv], d.Q[inv], kf.H, kf.R, m0, P0, mask=batch.mask)


def vessel_nll(kf: tl.KalmanFilter, batch: TrackBatch) -> tuple[np.ndarray, np.ndarray]:
    """Per vessel: summed -log p(y_k | y_<k) over reports 2..T, and the number of them. (B,), (B,)."""
    with torch.no_grad():
        out = run_filter(kf, batch)
    m = batch.mask[:, 1:]
    return (-(out.step_log_likelihood[:, 1:] * m).sum(1)).numpy(), m.sum(1).numpy()


def paired_bootstrap(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], n_boot: int = 4000,
                     seed: int = 0) -> tuple[float, float, float, float]:
    """NLL-per-report difference a - b resampling VESSELS: (estimate, 2.5 %, 97.5 %, P(diff >= 0))."""
    (sa, n), (sb, _) = a, b
    diff = sa - sb
    est = diff.sum() / n.sum()
    idx = np.random.default_rng(seed).integers(0, len(n), size=(n_boot, len(n)))
    boot = diff[idx].sum(1) / n[idx].sum(1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return float(est), float(lo), float(hi), float((boot >= 0).mean())


def predictive_nll(out: object, batch: TrackBatch) -> Tensor:
    """Mean over reports 2..T of -log p(y_k | y_<k) (nats per 2-D report), a scalar."""
    m = batch.mask[:, 1:]
    return -(out.step_log_likelihood[:, 1:] * m).sum() / m.sum()


def fit(kf: tl.KalmanFilter, batch: TrackBatch, max_iter: int) -> dict[str, float]:
    """Maximise the training likelihood with full-batch L-BFGS (strong Wolfe line search)."""
    params = [p for p in kf.parameters() if p.requires_grad]
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=max_iter, history_size=20,
                            line_search_fn="strong_wolfe", tolerance_grad=1e-7, tolerance_change=1e-10)
    evals = 0

    def closure() -> Tensor:
        nonlocal evals
        evals += 1
        opt.zero_grad()
        loss = predictive_nll(run_filter(kf, batch), batch)
        loss.backward()
        return loss

    start = time.perf_counter()
    opt.step(closure)
    with torch.no_grad():
        final = float(predictive_nll(run_filter(kf, batch), batch))
    return {"train_nll": final, "evals": evals, "seconds": time.perf_counter() - start}


def grid_search_cv(val: TrackBatch, q_grid: np.ndarray, r_grid: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Validation NLL of constant velocity over q x R_std; returns best q, best R std, table."""
    table = np.empty((len(q_grid), len(r_grid)))
    with torch.no_grad():
        for i, q in enumerate(q_grid):
            for j, r in enumerate(r_grid):
                kf = make_filter(tl.models.constant_velocity(dim=2, q=_f64(q)), 2,
                                 r**2 * torch.eye(2, dtype=torch.float64), learn_R=False)
                table[i, j] = float(predictive_nll(run_filter(kf, val), val))
    i, j = np.unravel_index(np.argmin(table), table.shape)
    return float(q_grid[i]), float(r_grid[j]), table


def forecast_pairs(batch: TrackBatch, horizon: float, tol: float = 0.25) -> tuple[Tensor, Tensor, Tensor]:
    """Origins (b, k), k >= 1, and targets j: the report with lead t_j - t_k nearest ``horizon``.

    Returns index tensors b, k, j (N,) of the pairs with |lead - horizon| <= tol * horizon.
    """
    t, mask = batch.t, batch.mask
    lead = t[:, None, :] - t[:, :, None]  # (B, K origins, J targets)
    T = t.shape[1]
    later = torch.arange(T)[None, :] > torch.arange(T)[:, None]
    ok = later[None] & mask[:, None, :] & mask[:, :, None]
    ok[:, 0, :] = False  # origin needs >= 2 reports seen
    gap = torch.where(ok, (lead - horizon).abs(), torch.full_like(lead, math.inf))
    best, j = gap.min(dim=-1)
    sel = best <= tol * horizon
    b, k = sel.nonzero(as_tuple=True)
    return b, k, j[b, k]


def evaluate(kf: tl.KalmanFilter, batch: TrackBatch, curve_min: tuple[float, ...]) -> dict[str, float]:
    """All test metrics of the module docstring for one filter on one batch."""
    with torch.no_grad():
        out = run_filter(kf, batch)
        m = batch.mask.clone()
        m[:, 0] = False
        res: dict[str, float] = {"nll": float(predictive_nll(out, batch)), "reports": int(m.sum())}
        e = out.innovation[m]  # (N, 2) y - H m⁻
        S = out.innovation_cov[m]
        res["rmse1"] = float(e.pow(2).sum(-1).mean().sqrt())
        maha = (e.unsqueeze(-2) @ torch.linalg.solve(S, e.unsqueeze(-1))).squeeze(-1).squeeze(-1)
        res["cover2s"] = float((maha <= CHI2_2SIGMA).double().mean())
        under = batch.sog >= 2.0
        mu = m & under
        res["nll_underway"] = float(-(out.step_log_likelihood * mu).sum() / mu.sum())
        res["reports_underway"] = int(mu.sum())
        ms = m & ~under
        res["nll_slow"] = float(-(out.step_log_likelihood * ms).sum() / ms.sum())
        enorm = out.innovation.norm(dim=-1)
        res["med_err_slow"] = float(enorm[ms].median())
        res["med_err_underway"] = float(enorm[mu].median())
        # velocity vs SOG/COG
        Hv = velocity_readout(kf)
        v = out.mean @ Hv.mT
        good = m & torch.isfinite(batch.vel).all(-1)
        dv = (v - batch.vel)[good]
        res["vel_rmse"] = float(dv.pow(2).sum(-1).mean().sqrt())
        gu = good & under
        res["vel_rmse_underway"] = float((v - batch.vel)[gu].pow(2).sum(-1).mean().sqrt())
        # forecasts
        for h in curve_min:
            b, k, j = forecast_pairs(batch, 60.0 * h)
            res[f"fc_n_{h:g}"] = int(len(b))
            if len(b) == 0:  # no report near this lead time (e.g. 30 s: reports come every >= 60 s)
                res[f"fc_rmse_{h:g}"] = res[f"fc_cover2s_{h:g}"] = math.nan
                continue
            lead = batch.t[b, j] - batch.t[b, k]
            fc = kf.forecast((out.mean[b, k], out.cov[b, k]), lead.unsqueeze(-1))
            err = fc.obs_mean[:, 0] - batch.y[b, j]
            res[f"fc_rmse_{h:g}"] = float(err.pow(2).sum(-1).mean().sqrt())
            d = err.unsqueeze(-1)
            mh = (d.mT @ torch.linalg.solve(fc.obs_cov[:, 0], d)).squeeze()
            res[f"fc_cover2s_{h:g}"] = float((mh <= CHI2_2SIGMA).double().mean())
    return res


def describe(kf: tl.KalmanFilter) -> str:
    """Learned values in physical units."""
    sde, parts = kf.sde, []
    names = [n.split(".")[1] for n, _ in sde.named_parameters() if n.startswith("parametrizations.")]
    for name in names:
        val = getattr(sde, name).detach()
        if val.numel() == 1:
            parts.append(f"{name}={float(val):.3g}")
    if "F" in names:
        Fv = sde.F.detach()[[1, 3]][:, [1, 3]]
        ev = torch.linalg.eigvals(Fv)
        parts.append("eig(F_v)=" + ", ".join(f"{complex(e).real:.2e}{complex(e).imag:+.2e}j" for e in ev))
    if "Qc" in names:
        Qc = sde.Qc.detach()
        parts.append(f"Qc=[[{Qc[0, 0]:.3g}, {Qc[0, 1]:.3g}], [{Qc[1, 0]:.3g}, {Qc[1, 1]:.3g}]]")
    R = kf.R.detach()
    parts.append(f"R=[[{R[0, 0]:.3g}, {R[0, 1]:.3g}], [{R[1, 0]:.3g}, {R[1, 1]:.3g}]] m²")
    return ", ".join(parts)


def plot_map(path: Path, tracks: list[ais.AISTrack], batch: TrackBatch, filters: dict[str, tl.KalmanFilter]) -> None:
    """Test tracks (grey), with one-step predictions and 2σ ellipses for a few underway vessels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    sog = batch.sog.numpy()
    moving = np.argsort(-(sog * batch.mask.numpy()).sum(1) / batch.mask.numpy().sum(1))[:4]
    fig = plt.figure(figsize=(15, 9.5))
    grid = fig.add_gridspec(2, 3)
    ax0 = fig.add_subplot(grid[:, 0])
    axes = [ax0] + [fig.add_subplot(grid[r, c]) for r in range(2) for c in (1, 2)][: len(moving)]
    for tr in tracks:
        ax0.plot(tr.pos[:, 0] / 1e3, tr.pos[:, 1] / 1e3, "-", color="0.6", lw=0.8)
        ax0.plot(tr.pos[0, 0] / 1e3, tr.pos[0, 1] / 1e3, ".", color="0.3", ms=3)
    ax0.set_title(f"{len(tracks)} test vessels (east/north km)")
    ax0.set_aspect("equal")
    colors = ["C3", "C0", "C2", "C1", "C4"]
    with torch.no_grad():
        outs = {name: run_filter(kf, batch) for name, kf in filters.items()}
    for c, (ax, i) in enumerate(zip(axes[1:], moving)):
        T = int(batch.lengths[i])
        org = batch.origin[i].numpy()
        y = batch.y[i, :T].numpy() + org
        ax0.plot(y[:, 0] / 1e3, y[:, 1] / 1e3, "-", color=f"C{c + 5}", lw=2)
        ax.plot(y[:, 0], y[:, 1], "k.-", lw=0.8, ms=4, label="AIS reports", zorder=5)
        for (name, out), col in zip(outs.items(), colors):
            pm = (out.pred_mean[i, 1:T] @ filters[name].H.mT).numpy() + org
            S = out.innovation_cov[i, 1:T].numpy()
            ax.plot(pm[:, 0], pm[:, 1], "x", color=col, ms=5, label=f"{name}: one-step prediction")
            for p, s in zip(pm, S):
                w, V = np.linalg.eigh(s)
                ang = math.degrees(math.atan2(V[1, 1], V[0, 1]))
                ax.add_patch(Ellipse(p, 4 * math.sqrt(w[1]), 4 * math.sqrt(w[0]), angle=ang,
                                     fill=False, color=col, lw=0.7, alpha=0.7))
        ax.set_title(f"MMSI {int(batch.track_id[i])}, median SOG {np.median(sog[i, :T]):.1f} kn")
        ax.set_aspect("equal")
        ax.set_xlabel("east (m)")
        ax.set_ylabel("north (m)")
    axes[1].legend(fontsize=7, loc="best")
    fig.suptitle("One-step predictions with 2σ ellipses (predictive covariance H P⁻ Hᵀ + R)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_horizon(path: Path, results: dict[str, dict[str, float]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    styles = ["o-", "s--", "^:", "v-.", "D-"]
    for (name, r), st in zip(results.items(), styles):
        ax.plot(CURVE_MIN, [r[f"fc_rmse_{h:g}"] for h in CURVE_MIN], st, label=name, alpha=0.8, mfc="none")
    ax.set_title("forecast error vs horizon (curves on top of each other: near-equal errors)", fontsize=8)
    ax.set_xlabel("forecast horizon (min)")
    ax.set_ylabel("position RMSE on test vessels (m)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def fit_all(data: ais.AISData, seed: int, max_iter: int, verbose: bool = True) -> tuple[
        dict[str, tl.KalmanFilter], dict[str, dict[str, object]], list[TrackBatch], list[list[ais.AISTrack]]]:
    """Split vessels with ``seed``, grid-tune the baseline on val, train the learned models on train."""
    idx = ais.split_vessels(len(data.tracks), seed=seed)
    split_tracks = [[data.tracks[i] for i in ix] for ix in idx]
    batches = [ais.ais_batch(s, center=True, dtype=torch.float64) for s in split_tracks]
    train, val, _ = batches
    filters: dict[str, tl.KalmanFilter] = {}
    info: dict[str, dict[str, object]] = {}
    t0 = time.perf_counter()
    q_best, r_best, table = grid_search_cv(val, Q_GRID, R_STD_GRID)
    filters["cv (grid)"] = make_filter(tl.models.constant_velocity(dim=2, q=_f64(q_best)), 2,
                                       r_best**2 * torch.eye(2, dtype=torch.float64), learn_R=False)
    info["cv (grid)"] = {"learned": f"grid: q={q_best:.3g} m²/s³, R={r_best:g}² m² I ({table.size} points)",
                         "seconds": time.perf_counter() - t0, "q": q_best, "r_std": r_best}
    if verbose:
        print(f"[seed {seed}] grid search: q={q_best:.3g}, R std={r_best} ({time.perf_counter() - t0:.1f} s)",
              flush=True)
    for spec in SPECS:
        torch.manual_seed(0)
        kf = make_filter(spec.build(), spec.order, 10.0**2 * torch.eye(2, dtype=torch.float64))
        stats = fit(kf, train, max_iter)
        filters[spec.name] = kf
        info[spec.name] = {**stats, "learned": describe(kf)}
        if verbose:
            print(f"[seed {seed}] {spec.name}: {stats} {describe(kf)}", flush=True)
    return filters, info, batches, split_tracks


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default=str(Path(__file__).parent / "results"))
    parser.add_argument("--seed", type=int, default=0, help="vessel split seed of the main table")
    parser.add_argument("--robustness-seeds", type=int, nargs="*", default=[1, 2, 3, 4],
                        help="further vessel splits: test NLL only")
    parser.add_argument("--max-iter", type=int, default=100, help="L-BFGS function evaluations per model")
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    torch.set_num_threads(1)  # small batched matrices: one intra-op thread is fastest
    start = time.perf_counter()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)

    data = ais.load_ais()
    dts = ais.dt_summary(data.tracks)
    print(f"data: {data.counts}\ndt: {dts}", flush=True)
    filters, info, (train, val, test), split_tracks = fit_all(data, args.seed, args.max_iter)

    results: dict[str, dict[str, float]] = {}
    per_vessel: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, kf in filters.items():
        with torch.no_grad():
            val_nll = float(predictive_nll(run_filter(kf, val), val))
            # the distinct-dt shortcut must reproduce the library's own forward pass
            ref = kf(val.y, val.dt, mask=val.mask).step_log_likelihood
            gap = float((ref - run_filter(kf, val).step_log_likelihood).abs().max())
            if not gap < 1e-6:
                raise RuntimeError(f"{name}: run_filter differs from KalmanFilter.forward by {gap:.3g}")
        results[name] = {"val_nll": val_nll, **evaluate(kf, test, CURVE_MIN)}
        per_vessel[name] = vessel_nll(kf, test)
    base = per_vessel["cv (grid)"]
    paired = {name: paired_bootstrap(pv, base) for name, pv in per_vessel.items() if name != "cv (grid)"}

    robust: dict[int, dict[str, tuple[float, float]]] = {
        args.seed: {k: (r["val_nll"], r["nll"]) for k, r in results.items()}
    }
    for seed in args.robustness_seeds:
        f_s, _, (_, val_s, test_s), _ = fit_all(data, seed, args.max_iter, verbose=False)
        with torch.no_grad():
            robust[seed] = {k: (float(predictive_nll(run_filter(kf, val_s), val_s)),
                                float(predictive_nll(run_filter(kf, test_s), test_s))) for k, kf in f_s.items()}
        scores = ", ".join(f"{k}: {v[0]:.3f}, {v[1]:.3f}" for k, v in robust[seed].items())
        print(f"[seed {seed}] (val, test) NLL: {scores}", flush=True)
    runtime = time.perf_counter() - start

    shown = {k: filters[k] for k in ("cv (grid)", best_learned(results))}
    plot_map(out_dir / "ais_map.png", split_tracks[2], test, shown)
    plot_horizon(out_dir / "ais_horizon.png", results)
    notes = interpretation(results, filters, dts)
    md = report(data, dts, [len(s) for s in split_tracks], results, paired, robust, info, runtime, args, notes)
    (out_dir / "ais.md").write_text(md)
    (out_dir / "ais_metrics.json").write_text(json.dumps({"results": results, "paired": paired, "robustness": robust,
                                                          "counts": data.counts, "dt": dts,
                                                          "runtime_s": runtime}, indent=1))
    print(md)
    print(f"total {time.perf_counter() - start:.1f} s")
    return results


def interpretation(results: dict[str, dict[str, float]], filters: dict[str, tl.KalmanFilter],
                   dts: dict[str, float]) -> list[str]:
    """Measured facts behind the table, as markdown bullet points."""
    base, best = results["cv (grid)"], results[best_learned(results)]
    name = best_learned(results)
    lines = [
        f"- Slow reports (SOG < 2 kn, {base['reports'] - base['reports_underway']} of {base['reports']}): "
        f"NLL {base['nll_slow']:.3f} (baseline) vs {best['nll_slow']:.3f} ({name}); underway reports: "
        f"{base['nll_underway']:.3f} vs {best['nll_underway']:.3f}. The learned drag helps on moving vessels "
        "(velocity decorrelates over minutes, so long gaps are not extrapolated linearly), while the "
        "baseline's smaller R, chosen on the validation vessels, suits the moored ones.",
        f"- Every model here is linear-Gaussian, so its predictive covariance does not depend on the data: "
        f"the same ellipse must cover moored vessels (median one-step error {base['med_err_slow']:.1f} m) and "
        f"vessels under way, up to 30 kn ferries (median {base['med_err_underway']:.0f} m). "
        "That heteroscedasticity, not the choice of dynamics, dominates the NLL (≈ 12 nats per report "
        "for all models); regime-switching (IMM) or per-vessel noise would be the next step.",
    ]
    sg = filters.get("singer")
    if sg is not None:
        alpha, qs = float(sg.sde.alpha.detach()), float(sg.sde.q.detach())
        cvq = float(filters["cv"].sde.q.detach())
        if alpha * dts["median"] > 10:
            lines.append(
                f"- Singer learned alpha = {alpha:.3g} /s (1/alpha = {1 / alpha:.2g} s, far below the median gap "
                f"{dts['median']:.0f} s): its acceleration is white on the reporting time scale, so it reduces to "
                f"constant velocity with q = q_singer / alpha² = {qs / alpha**2:.4g} (learned cv: q = {cvq:.4g}) "
                "and gives the same numbers.")
    return lines


def best_learned(results: dict[str, dict[str, float]]) -> str:
    """Learned model with the lowest VALIDATION NLL (the test set does not choose it)."""
    return min((k for k in results if k != "cv (grid)"), key=lambda k: results[k]["val_nll"])


def report(data: ais.AISData, dts: dict[str, float], sizes: list[int], results: dict[str, dict[str, float]],
           paired: dict[str, tuple[float, float, float, float]], robust: dict[int, dict[str, tuple[float, float]]],
           info: dict[str, dict[str, object]], runtime: float, args: argparse.Namespace, notes: list[str]) -> str:
    c = data.counts
    hz = " | ".join(f"fc RMSE {h:g} min (m)" for h in HORIZONS_MIN)
    lines = [
        "# AIS study: learned motion models vs tuned constant velocity (NY Harbor, 2020-06-30 00:00-01:00)",
        "",
        "Command: `python experiments/ais_study.py` "
        f"(seed {args.seed}, L-BFGS max {args.max_iter} evaluations per model); runtime {runtime:.0f} s.",
        "",
        f"Data: {c['rows']} reports, {c['vessels_all']} vessels; dropped {c['exact_duplicates']} exact duplicates, "
        f"{c['repeated_timestamps']} repeated (MMSI, time) reports and {c['vessels_dropped_short']} vessels with < 5 "
        f"reports ({c['reports_dropped_short']} reports). Kept {c['vessels']} vessels, {c['reports']} reports; "
        f"split train/val/test = {sizes[0]}/{sizes[1]}/{sizes[2]} vessels. Report gaps dt (s): "
        f"min {dts['min']:.0f}, 5 % {dts['p05']:.0f}, median {dts['median']:.0f}, 95 % {dts['p95']:.0f}, "
        f"max {dts['max']:.0f} (n = {dts['n']}).",
        "",
        "Test vessels, reports 2..T of each track given the earlier ones "
        f"({next(iter(results.values()))['reports']} reports, "
        f"{next(iter(results.values()))['reports_underway']} with SOG >= 2 kn):",
        "",
        f"| model | val NLL | test NLL / report | NLL, SOG>=2 kn | 1-step RMSE (m) | in 2σ (86.5 %) | {hz} "
        "| vel. RMSE vs SOG/COG (m/s) | vel. RMSE, SOG>=2 kn |",
        "|---|" + "---:|" * (7 + len(HORIZONS_MIN)),
    ]
    for name, r in results.items():
        fc = " | ".join(f"{r[f'fc_rmse_{h:g}']:.0f}" for h in HORIZONS_MIN)
        lines.append(
            f"| {name} | {r['val_nll']:.3f} | {r['nll']:.3f} | {r['nll_underway']:.3f} | {r['rmse1']:.1f} | "
            f"{100 * r['cover2s']:.1f} % | {fc} | {r['vel_rmse']:.2f} | {r['vel_rmse_underway']:.2f} |"
        )
    base = results["cv (grid)"]
    best = best_learned(results)
    gap = results[best]["nll"] - base["nll"]
    lines += [
        "",
        f"Forecast pairs per horizon: " + ", ".join(f"{h:g} min: {base[f'fc_n_{h:g}']}" for h in HORIZONS_MIN) + ".",
        "",
        f"Best learned model by validation NLL: **{best}**; test NLL {results[best]['nll']:.3f} vs "
        f"{base['nll']:.3f} for the tuned baseline ({'better' if gap < 0 else 'NOT better'} by {abs(gap):.3f} "
        "nats per report).",
        "",
        *notes,
        "",
        "Paired difference to the baseline in test NLL per report (negative = learned model better), "
        "95 % interval and P(diff >= 0) from 4000 bootstrap resamples of the test VESSELS:",
        "",
        "| model | Δ NLL / report | 95 % interval | P(Δ >= 0) |",
        "|---|---:|---:|---:|",
        *[f"| {k} | {v[0]:+.3f} | [{v[1]:+.3f}, {v[2]:+.3f}] | {v[3]:.3f} |" for k, v in paired.items()],
        "",
        "Where the NLL comes from (test, per report; |e| = one-step innovation norm):",
        "",
        "| model | SOG < 2 kn: NLL | median abs(e) (m) | SOG >= 2 kn: NLL | median abs(e) (m) |",
        "|---|---:|---:|---:|---:|",
        *[f"| {k} | {r['nll_slow']:.3f} | {r['med_err_slow']:.1f} | {r['nll_underway']:.3f} | "
          f"{r['med_err_underway']:.1f} |" for k, r in results.items()],
        "",
        "Other vessel splits (same recipe, seeds " + ", ".join(str(k) for k in robust if k != args.seed)
        + "): test NLL per report; the learned model is the one with the best validation NLL.",
        "",
        "| split seed | cv (grid) | " + " | ".join(k for k in results if k != "cv (grid)")
        + " | best by val | Δ best - baseline |",
        "|---|" + "---:|" * (len(results) + 2),
    ]
    for seed, r in robust.items():
        learned = {k: v for k, v in r.items() if k != "cv (grid)"}
        pick = min(learned, key=lambda k: learned[k][0])
        lines.append(f"| {seed} | " + " | ".join(f"{v[1]:.3f}" for v in r.values())
                     + f" | {pick} | {learned[pick][1] - r['cv (grid)'][1]:+.3f} |")
    lines += [
        "",
        "Learned / chosen parameters (SI units: m, s):",
        "",
    ]
    for name, d in info.items():
        extra = f" ({d['evals']} evaluations, {d['seconds']:.1f} s)" if "evals" in d else ""
        about = next((f" (learns {sp.about})" for sp in SPECS if sp.name == name), "")
        lines.append(f"- {name}{about}: {d['learned']}{extra}")
    lines += ["", "Plots: `ais_map.png` (test tracks; one-step predictions with 2σ ellipses for the four fastest "
              "test vessels), `ais_horizon.png` (forecast RMSE vs horizon).", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
