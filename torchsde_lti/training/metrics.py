"""What a run reports: learned values, errors against the truth, the masked Gaussian NLL.

Torch only (no Lightning): usable on any pair of models.

* :func:`parameter_errors` compares the quantities the data determine: named scalars of
  structured models, ``expm(F dt)`` where F itself is identifiable, and for a free F seen
  through fewer observations than states the observed autocovariance
  ``H e^{Fτ} P∞ Hᵀ`` (:func:`observed_autocovariance`), which every state basis shares.
* :func:`filter_values`: what a filter learned, for a :class:`~torchsde_lti.KalmanFilter`
  and an :class:`~torchsde_lti.IMMFilter` alike: it iterates over ``kf.modes()`` (one
  :class:`~torchsde_lti.nn.FilterMode` per motion model) and, for several modes, adds the
  switching chain (``kf.rates``, ``kf.mode_prob0``).
* :func:`parameter_table` / :func:`format_table`: the true-vs-learned table of a run.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from torchsde_lti.core.linalg import sym
from torchsde_lti.core.stationary import stationary_covariance
from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import KalmanFilter
from torchsde_lti.nn.parametrizations import IntegratorChain
from torchsde_lti.nn.sde import LTISDE

__all__ = [
    "filter_values",
    "flat_values",
    "format_table",
    "learned_values",
    "masked_gaussian_nll",
    "observed_autocovariance",
    "parameter_errors",
    "parameter_table",
    "raw_f_identifiable",
    "same_model",
]


def _resolve(module: nn.Module, path: str) -> Any:
    obj: Any = module
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def _scalar_names(sde: nn.Module) -> list[str]:
    """Names of the learned scalar parameters of a motion model (``q``, ``k``, ``alpha``, ...).

    Read from ``named_parameters``: ``parametrizations.q.original`` -> ``q`` (and
    ``parts.0.parametrizations.q.original`` -> ``parts.0.q``); only 0-dim values count.
    """
    names: list[str] = []
    for raw_name, _ in sde.named_parameters():
        name = raw_name.replace("parametrizations.", "").replace(".original", "")
        try:
            value = _resolve(sde, name)
        except AttributeError:
            continue
        if isinstance(value, Tensor) and value.dim() == 0 and name not in names:
            names.append(name)
    return names


def learned_values(sde: LTISDE, R: Tensor | None = None, names: Sequence[str] | None = None) -> dict[str, Tensor]:
    """Current values of a model's interpretable parameters, detached.

    Named scalars (``names`` or the model's own list) come from ``getattr(sde, name)``;
    then the matrices ``F`` and ``Qc`` and, if given, ``R``.
    """
    out: dict[str, Tensor] = {}
    for name in names if names is not None else _scalar_names(sde):
        out[name] = torch.as_tensor(_resolve(sde, name)).detach()
    mats = sde.matrices()
    out["F"] = mats.F.detach()
    out["Qc"] = mats.Qc.detach()
    if R is not None:
        out["R"] = R.detach()
    return out


def _rel(a: Tensor, b: Tensor) -> float:
    """Relative Frobenius error ‖a − b‖ / ‖b‖ (absolute when b = 0)."""
    a, b = a.detach().to(torch.float64), b.detach().to(torch.float64)
    den = torch.linalg.vector_norm(b)
    num = torch.linalg.vector_norm(a - b)
    return float(num / den) if float(den) > 0 else float(num)


def same_model(learned: LTISDE, truth: LTISDE) -> bool:
    """Whether learner and truth are the same kind of model, so their named scalars pair up."""

    def kind(m: nn.Module) -> str:
        return type(m).__name__.removeprefix("Parametrized")

    return kind(learned) == kind(truth) and learned.matrices().F.shape[-2:] == truth.matrices().F.shape[-2:]


def raw_f_identifiable(sde: LTISDE, H: Tensor | None) -> bool:
    """Whether the data determine F itself (not only up to a change of state basis).

    True for structured models (named scalars fix the basis), for a fixed structure such as
    :class:`~torchsde_lti.nn.parametrizations.IntegratorChain`, and for a free F observed
    through an H of full column rank. A free F seen through fewer observations than states
    is determined only up to similarity transforms ``T F T⁻¹`` (with ``H T⁻¹``, ``T L``):
    every such F gives the same likelihood, so raw-F errors are meaningless there.
    """
    if _scalar_names(sde):
        return True
    param = getattr(getattr(sde, "parametrizations", None), "F", None)
    if param is not None and any(isinstance(p, IntegratorChain) for p in param):
        return True
    if H is None:
        return True
    H = H.detach().to(torch.float64)
    return int(torch.linalg.matrix_rank(H)) >= sde.state_dim


def observed_autocovariance(sde: LTISDE, H: Tensor, lags: Sequence[float]) -> Tensor:
    """Stationary autocovariance of the observed signal, ``H e^{F τ} P∞ Hᵀ`` at each lag.

    P∞ solves ``F P∞ + P∞ Fᵀ + L Qc Lᵀ = 0``; invariant under a change of state basis, so
    the data determine it whenever they determine anything. Returns (len(lags), m, m) in
    float64; ValueError (from ``stationary_covariance``) when F is not Hurwitz.
    """
    F, L, Qc = (x.detach().to(torch.float64) for x in sde.matrices()[:3])
    P = stationary_covariance(F, L, Qc)
    H = H.detach().to(torch.float64)
    return torch.stack([H @ torch.linalg.matrix_exp(F * float(t)) @ P @ H.mT for t in lags])


def parameter_errors(
    learned: LTISDE,
    truth: LTISDE,
    *,
    R: Tensor | None = None,
    R_true: Tensor | None = None,
    names: Sequence[str] | None = None,
    compare: Sequence[str] = ("F", "Qc"),
    dts: Sequence[float] = (0.1, 1.0, 5.0),
    H: Tensor | None = None,
    H_true: Tensor | None = None,
    lags: Sequence[float] = (0.0, 0.5, 1.0, 2.0, 5.0),
) -> dict[str, float]:
    """Relative errors of every learned quantity the data determine, against the truth.

    * each named scalar (``q``, ``k``, ``alpha``, ...): |learned − true| / |true|;
    * ``Qc`` (if compared, identifiable and no scalar names cover it): relative Frobenius error;
    * ``F`` (if compared and identifiable, see :func:`raw_f_identifiable`):
      ``max_dt ‖expm(F dt) − expm(F* dt)‖ / ‖expm(F* dt)‖`` over ``dts``, as ``expmF``;
    * ``F`` not identifiable (free F, H of lower rank than the state): the observed
      autocovariance ``C(τ) = H e^{Fτ} P∞ Hᵀ`` instead,
      ``max_τ ‖C(τ) − C*(τ)‖ / ‖C*(0)‖`` over ``lags``, as ``autocov`` (it covers Qc's
      effect as well; inf while the learned F is not Hurwitz). Raw F and Qc errors are
      left out: the likelihood cannot see them;
    * ``R`` (if given): relative Frobenius error.
    """
    errors: dict[str, float] = {}
    names = list(names) if names is not None else _scalar_names(learned)
    mine, theirs = learned.matrices(), truth.matrices()
    same_shape = mine.F.shape[-2:] == theirs.F.shape[-2:] and mine.Qc.shape[-2:] == theirs.Qc.shape[-2:]
    for name in names if same_model(learned, truth) else ():  # a learner of another kind: nothing to pair
        errors[name] = _rel(torch.as_tensor(_resolve(learned, name)), torch.as_tensor(_resolve(truth, name)))
    identifiable = raw_f_identifiable(learned, H)
    if not same_shape:  # e.g. model=cv truth=singer: only observation-level quantities compare
        identifiable = False
    if "F" in compare and not identifiable and H is not None:
        H_true = H if H_true is None else H_true
        try:
            C_true = observed_autocovariance(truth, H_true, lags)
        except ValueError:  # the truth has no stationary autocovariance (integrators): nothing to compare
            C_true = None
        if C_true is not None:
            try:
                C = observed_autocovariance(learned, H, lags)
            except ValueError:  # the learned F is not Hurwitz (yet): no stationary autocovariance
                errors["autocov"] = math.inf
            else:
                scale = torch.linalg.matrix_norm(C_true[0])
                errors["autocov"] = float((torch.linalg.matrix_norm(C - C_true) / scale).max())
    elif not names and "Qc" in compare and identifiable:  # (identifiable implies same_shape)
        errors["Qc"] = _rel(mine.Qc, theirs.Qc)
    if "F" in compare and identifiable:
        F, F_true = mine.F.detach().to(torch.float64), theirs.F.detach().to(torch.float64)
        errors["expmF"] = max(_rel(torch.linalg.matrix_exp(F * t), torch.linalg.matrix_exp(F_true * t)) for t in dts)
    if R is not None and R_true is not None:
        errors["R"] = _rel(R, R_true)
    return errors


def masked_gaussian_nll(r: Tensor, S: Tensor, observed: Tensor) -> Tensor:
    """Σ over observed coordinates of the Gaussian NLL of residual r under N(0, S).

    r: (..., m) residuals, S: (..., m, m), observed: (..., m) bool. Missing coordinates
    are marginalised out exactly: their rows/columns of S are replaced by the identity
    and their residuals by 0, which leaves logdet and the quadratic form of the observed
    block unchanged. Returns (...), zero where nothing is observed.
    """
    obs = observed.to(r.dtype)
    r = torch.where(observed, r, torch.zeros_like(r))
    both = obs.unsqueeze(-1) * obs.unsqueeze(-2)
    eye = torch.eye(r.shape[-1], dtype=r.dtype, device=r.device)
    S = S * both + eye * (1.0 - obs).unsqueeze(-1)
    S = sym(S)
    C = torch.linalg.cholesky(S)
    z = torch.linalg.solve_triangular(C, r.unsqueeze(-1), upper=False).squeeze(-1)
    logdet = 2.0 * torch.log(torch.diagonal(C, dim1=-2, dim2=-1)).sum(-1)
    return 0.5 * ((z * z).sum(-1) + logdet + obs.sum(-1) * math.log(2.0 * math.pi))


def filter_values(kf: KalmanFilter | IMMFilter, names: Sequence[str] | None = None) -> dict[str, Tensor]:
    """What a filter learned, detached: :func:`learned_values` of each of ``kf.modes()``.

    A single-model filter (``KalmanFilter``) gives exactly ``learned_values(sde, R, names)``.
    With several modes (``IMMFilter``) every key is prefixed by the mode's name
    (``"moored/k"``, ``"underway/R"``) and the switching chain is added as scalars:
    ``"rate[a->b]"`` = Λ_ab (1/time) for every ordered pair of modes and ``"mode_prob0[a]"``.
    ``names`` applies to each mode's model (None: each model's own list).
    """
    modes = kf.modes()
    if len(modes) == 1:
        mode = modes[0]
        return learned_values(mode.sde, mode.R, names)
    out: dict[str, Tensor] = {}
    for mode in modes:
        out.update({f"{mode.name}/{k}": v for k, v in learned_values(mode.sde, mode.R, names).items()})
    assert isinstance(kf, IMMFilter)  # only it has several modes
    rates, p0 = kf.rates.detach(), kf.mode_prob0.detach()
    labels = [mode.name for mode in modes]
    for i, a in enumerate(labels):
        for j, b in enumerate(labels):
            if i != j:
                out[f"rate[{a}->{b}]"] = rates[i, j]
    out.update({f"mode_prob0[{a}]": p0[i] for i, a in enumerate(labels)})
    return out


def _split(name: str) -> tuple[str, str]:
    """``"moored/R"`` -> (``"moored/"``, ``"R"``); ``"R"`` -> (``""``, ``"R"``)."""
    prefix, _, base = name.rpartition("/")
    return (f"{prefix}/" if prefix else ""), base


def flat_values(values: Mapping[str, Tensor]) -> dict[str, float]:
    """Scalars as they are; R and (without named scalars) Qc by their diagonals (``R[0]``, ...).

    Mode-prefixed keys of :func:`filter_values` (``"moored/R"``) are handled per mode."""
    out: dict[str, float] = {}
    with_scalars = {_split(k)[0] for k, v in values.items() if v.dim() == 0}
    for name, v in values.items():
        prefix, base = _split(name)
        if base == "Qc" and prefix in with_scalars:  # Qc is a function of the named scalars
            continue
        v = v.detach().to(torch.float64)
        if v.dim() == 0:
            out[name] = float(v)
        elif base in ("R", "Qc") and v.dim() == 2:
            out.update({f"{name}[{i}]": float(x) for i, x in enumerate(torch.diagonal(v))})
    return out


def parameter_table(module: Any, truth: dict[str, Any] | None) -> list[dict[str, Any]]:
    """Rows {"name", "true", "learned", "rel_error"} for every learned quantity.

    Named scalars (for an IMM also the switching rates and initial mode probabilities) and
    the diagonal of every R are listed by value (``true`` and ``rel_error`` NaN without a
    truth); the matrix errors (``expmF``: max over dt of ‖expm(F dt) − expm(F* dt)‖/‖expm(F* dt)‖;
    ``autocov``: the observed autocovariance, for a free F the data do not determine entrywise;
    ``Qc``, ``R``) by error only, except against a zero truth (``data.noise=0``: R = 0), which
    has no relative error: that row gives the learned matrix's Frobenius norm. Only a
    single-model filter is paired with a truth.
    """
    errors = module.parameter_errors()
    kf = module.kf
    learned = filter_values(kf, module.param_names)
    true: dict[str, Any] = {}
    if truth and len(kf.modes()) == 1:
        paired = same_model(kf.modes()[0].sde, truth["sde"])
        true = learned_values(truth["sde"], truth.get("R"), module.param_names if paired else [])
        if not paired:
            true = {k: v for k, v in true.items() if k == "R"}
    rows: list[dict[str, Any]] = []
    for name, value in learned.items():
        if value.dim() == 0:
            t = float(true[name]) if name in true else math.nan
            rows.append({"name": name, "true": t, "learned": float(value), "rel_error": errors.get(name, math.nan)})
        elif _split(name)[1] == "R" and value.dim() == 2:
            t_diag = torch.diagonal(true[name]) if name in true and "R" in errors else None
            for i, a in enumerate(torch.diagonal(value)):
                b = float(t_diag[i]) if t_diag is not None else math.nan
                err = abs(float(a) - b) / abs(b) if t_diag is not None and b != 0 else math.nan
                rows.append({"name": f"{name}[{i},{i}]", "true": b, "learned": float(a), "rel_error": err})
    for name in ("expmF", "autocov", "Qc", "R"):
        if name not in errors:
            continue
        zero = name in true and not bool(torch.as_tensor(true[name]).any())
        if zero:  # no relative error to a zero truth: the learned matrix's Frobenius norm instead
            norm = float(torch.linalg.vector_norm(learned[name].detach().double())) if name in learned else math.nan
            rows.append({"name": f"{name} (matrix, ‖·‖_F)", "true": 0.0, "learned": norm, "rel_error": math.nan})
        else:
            rows.append({"name": f"{name} (matrix)", "true": math.nan, "learned": math.nan, "rel_error": errors[name]})
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    """Markdown table of :func:`parameter_table` rows."""
    lines = ["| parameter | true | learned | rel. error |", "|---|---:|---:|---:|"]
    for r in rows:
        t = "" if math.isnan(r["true"]) else f"{r['true']:.4g}"
        v = "" if math.isnan(r["learned"]) else f"{r['learned']:.4g}"
        e = "" if math.isnan(r["rel_error"]) else f"{100 * r['rel_error']:.2f} %"
        lines.append(f"| {r['name']} | {t} | {v} | {e} |")
    return "\n".join(lines)
