"""Parameter recovery: what a filter learned and how far it is from a known true model.

Torch only (no Lightning): usable on any pair of models.

* :func:`parameter_errors` compares the quantities the data determine: named scalars of
  structured models, ``expm(F dt)`` where F itself is identifiable, and for a free F seen
  through fewer observations than states the observed autocovariance
  ``H e^{Fτ} P∞ Hᵀ`` (:func:`observed_autocovariance`), which every state basis shares.
* :func:`filter_values`: what a :class:`~torchsde_lti.KalmanFilter` or an
  :class:`~torchsde_lti.IMMFilter` learned, mode by mode (``kf.modes()``), with an IMM's
  switching chain; :func:`flat_values` as named floats.
* :func:`filter_errors` / :func:`parameter_table`: a filter against a simulated truth
  ``{"sde", "R", "H"}``, as errors and as the rows of a true-vs-learned table.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from torchsde_lti.core.stationary import stationary_covariance
from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import KalmanFilter
from torchsde_lti.nn.noise import StudentT
from torchsde_lti.nn.parametrizations import IntegratorChain
from torchsde_lti.nn.sde import LTISDE

__all__ = [
    "filter_errors",
    "filter_values",
    "flat_values",
    "identifiability_note",
    "learned_values",
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
    """Names of the learned 0-dim parameters of a motion model (``q``, ``k``, ``parts.0.q``, ...),
    read from ``named_parameters`` (``parametrizations.q.original`` -> ``q``)."""
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
    """A model's interpretable values, detached: the named scalars (``names`` or the model's
    own), then the matrices ``F`` (n, n), ``Qc`` (s, s) and, if given, ``R`` (m, m)."""
    out = {
        name: torch.as_tensor(_resolve(sde, name)).detach()
        for name in (names if names is not None else _scalar_names(sde))
    }
    mats = sde.matrices()
    out.update(F=mats.F.detach(), Qc=mats.Qc.detach())
    if R is not None:
        out["R"] = R.detach()
    return out


def _rel(a: Tensor, b: Tensor) -> float:
    """Relative Frobenius error ‖a − b‖ / ‖b‖ (absolute when b = 0)."""
    a, b = a.detach().to(torch.float64), b.detach().to(torch.float64)
    den, num = torch.linalg.vector_norm(b), torch.linalg.vector_norm(a - b)
    return float(num / den) if float(den) > 0 else float(num)


def same_model(learned: LTISDE, truth: LTISDE) -> bool:
    """Whether learner and truth are the same kind of model, so their named scalars pair up."""

    def kind(m: nn.Module) -> str:
        return type(m).__name__.removeprefix("Parametrized")

    return kind(learned) == kind(truth) and learned.matrices().F.shape[-2:] == truth.matrices().F.shape[-2:]


def raw_f_identifiable(sde: LTISDE, H: Tensor | None) -> bool:
    """Whether the data determine F itself (not only up to a change of state basis).

    True for structured models (named scalars fix the basis), a fixed structure such as
    :class:`~torchsde_lti.nn.parametrizations.IntegratorChain`, and a free F observed through
    an H of full column rank. A free F seen through fewer observations than states is
    determined only up to ``T F T⁻¹`` (with ``H T⁻¹``, ``T L``): raw-F errors mean nothing there.
    """
    if _scalar_names(sde):
        return True
    param = getattr(getattr(sde, "parametrizations", None), "F", None)
    if param is not None and any(isinstance(p, IntegratorChain) for p in param):
        return True
    return H is None or int(torch.linalg.matrix_rank(H.detach().to(torch.float64))) >= sde.state_dim


def observed_autocovariance(sde: LTISDE, H: Tensor, lags: Sequence[float]) -> Tensor:
    """Stationary autocovariance of the observed signal, ``H e^{F τ} P∞ Hᵀ`` at each lag.

    P∞ solves ``F P∞ + P∞ Fᵀ + L Qc Lᵀ = 0``; invariant under a change of state basis.

    Returns:
        (len(lags), m, m) in float64.

    Raises:
        ValueError: F is not Hurwitz (from ``stationary_covariance``).
    """
    F, L, Qc = (x.detach().to(torch.float64) for x in sde.matrices()[:3])
    P = stationary_covariance(F, L, Qc)
    H = H.detach().to(torch.float64)
    return torch.stack([H @ torch.linalg.matrix_exp(F * float(t)) @ P @ H.mT for t in lags])


def _autocov_error(learned: LTISDE, truth: LTISDE, H: Tensor, H_true: Tensor, lags: Sequence[float]) -> float | None:
    """``max_τ ‖C(τ) − C*(τ)‖ / ‖C*(0)‖`` (None: the truth has no stationary autocovariance;
    inf: the learned F is not Hurwitz yet)."""
    try:
        C_true = observed_autocovariance(truth, H_true, lags)
    except ValueError:
        return None
    try:
        C = observed_autocovariance(learned, H, lags)
    except ValueError:
        return math.inf
    return float((torch.linalg.matrix_norm(C - C_true) / torch.linalg.matrix_norm(C_true[0])).max())


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
    * ``F`` identifiable (:func:`raw_f_identifiable`): ``expmF`` =
      ``max_dt ‖expm(F dt) − expm(F* dt)‖ / ‖expm(F* dt)‖`` over ``dts``;
    * ``F`` not identifiable (free F, H of lower rank than the state, or another state size
      than the truth's): ``autocov`` = ``max_τ ‖C(τ) − C*(τ)‖ / ‖C*(0)‖`` over ``lags`` of the
      observed autocovariance (inf while the learned F is not Hurwitz); no raw F or Qc error;
    * ``R`` (if given with ``R_true``): relative Frobenius error.

    Args:
        learned, truth: the models; R, R_true: (m, m) observation noises; names: the scalars
            to pair (default: the learner's own); compare: which of "F", "Qc" to compare;
            dts, lags: the steps and lags of the matrix errors; H, H_true: (m, n) observations.

    Returns:
        {name: relative error}.
    """
    errors: dict[str, float] = {}
    names = list(names) if names is not None else _scalar_names(learned)
    mine, theirs = learned.matrices(), truth.matrices()
    same_shape = mine.F.shape[-2:] == theirs.F.shape[-2:] and mine.Qc.shape[-2:] == theirs.Qc.shape[-2:]
    for name in names if same_model(learned, truth) else ():  # a learner of another kind: nothing to pair
        errors[name] = _rel(torch.as_tensor(_resolve(learned, name)), torch.as_tensor(_resolve(truth, name)))
    identifiable = same_shape and raw_f_identifiable(learned, H)
    if "F" in compare and not identifiable and H is not None:
        autocov = _autocov_error(learned, truth, H, H if H_true is None else H_true, lags)
        if autocov is not None:
            errors["autocov"] = autocov
    elif not names and "Qc" in compare and identifiable:
        errors["Qc"] = _rel(mine.Qc, theirs.Qc)
    if "F" in compare and identifiable:
        F, F_true = mine.F.detach().to(torch.float64), theirs.F.detach().to(torch.float64)
        errors["expmF"] = max(_rel(torch.linalg.matrix_exp(F * t), torch.linalg.matrix_exp(F_true * t)) for t in dts)
    if R is not None and R_true is not None:
        errors["R"] = _rel(R, R_true)
    return errors


def filter_values(kf: KalmanFilter | IMMFilter, names: Sequence[str] | None = None) -> dict[str, Tensor]:
    """What a filter learned, detached: :func:`learned_values` of each of ``kf.modes()``.

    One mode (a ``KalmanFilter``): ``learned_values(sde, R, names)``. Several (an ``IMMFilter``):
    every key prefixed by the mode's name (``"moored/k"``), plus the switching chain as scalars,
    ``"rate[a->b]"`` = Λ_ab (1/time) for each ordered pair and ``"mode_prob0[a]"``. A learned
    Student-t ν (``noise=tl.StudentT(dof, learn=True)``) as ``"dof"``, or per mode
    ``"<mode>/dof"`` for an IMM with a ν per mode.
    """
    modes = kf.modes()
    if len(modes) == 1:
        out = learned_values(modes[0].sde, modes[0].R, names)
    else:
        out = {}
        for mode in modes:
            out.update({f"{mode.name}/{k}": v for k, v in learned_values(mode.sde, mode.R, names).items()})
        assert isinstance(kf, IMMFilter)  # only it has several modes
        rates, p0 = kf.rates.detach(), kf.mode_prob0.detach()
        labels = [mode.name for mode in modes]
        out.update(
            {f"rate[{a}->{b}]": rates[i, j] for i, a in enumerate(labels) for j, b in enumerate(labels) if i != j}
        )
        out.update({f"mode_prob0[{a}]": p0[i] for i, a in enumerate(labels)})
    noise = kf.noise
    if isinstance(noise, StudentT) and noise.learn:
        dof = noise.dof.detach()
        out.update({"dof": dof} if dof.dim() == 0 else {f"{m.name}/dof": dof[i] for i, m in enumerate(modes)})
    return out


def _split(name: str) -> tuple[str, str]:
    """``"moored/R"`` -> (``"moored/"``, ``"R"``); ``"R"`` -> (``""``, ``"R"``)."""
    prefix, _, base = name.rpartition("/")
    return (f"{prefix}/" if prefix else ""), base


def flat_values(values: Mapping[str, Tensor]) -> dict[str, float]:
    """Scalars as they are; R and (without named scalars) Qc by their diagonals (``R[0]``, ...),
    per mode for the prefixed keys of :func:`filter_values`; F is left out."""
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


def filter_errors(
    kf: KalmanFilter | IMMFilter,
    truth: Mapping[str, Any] | None,
    names: Sequence[str] | None = None,
    compare: Sequence[str] = ("F", "Qc", "R"),
) -> dict[str, float]:
    """:func:`parameter_errors` of a single-model filter against ``truth`` ({"sde", "R", "H"});
    {} without a truth, and for several modes (the truth is one model)."""
    modes = kf.modes()
    if truth is None or truth.get("sde") is None or len(modes) != 1:
        return {}
    mode = modes[0]
    R_true = truth.get("R") if "R" in compare else None
    return parameter_errors(
        mode.sde, truth["sde"], R=mode.R if R_true is not None else None, R_true=R_true,
        names=names, compare=compare, H=mode.H, H_true=truth.get("H"),
    )  # fmt: skip


def identifiability_note(kf: KalmanFilter | IMMFilter) -> str:
    """'' when every mode's F is identifiable, else a sentence saying why not."""
    hidden = [mode for mode in kf.modes() if not raw_f_identifiable(mode.sde, mode.H)]
    if not hidden:
        return ""
    m, n = hidden[0].H.shape[-2:]
    return (
        f"F is free and observed through H ({m}x{n}, rank < {n}): F and Qc are determined only up to a "
        "change of state basis, so they are compared through the observed autocovariance "
        "H e^{F tau} P_inf H^T (`autocov`), not entrywise."
    )


def parameter_table(
    kf: KalmanFilter | IMMFilter,
    truth: Mapping[str, Any] | None,
    names: Sequence[str] | None = None,
    compare: Sequence[str] = ("F", "Qc", "R"),
) -> list[dict[str, Any]]:
    """Rows {"name", "true", "learned", "rel_error"} of every learned quantity.

    Named scalars (an IMM's switching rates and initial mode probabilities too) and the diagonal
    of every R by value (``true`` and ``rel_error`` NaN without a truth); the matrix errors of
    :func:`filter_errors` (``expmF``, ``autocov``, ``Qc``, ``R``) by error only, except against
    a zero truth (``data.noise=0``: R = 0), which has no relative error: that row gives the
    learned matrix's Frobenius norm. Only a single-model filter is paired with a truth.
    """
    errors = filter_errors(kf, truth, names, compare)
    learned = filter_values(kf, names)
    true: dict[str, Any] = {}
    if truth and len(kf.modes()) == 1:
        paired = same_model(kf.modes()[0].sde, truth["sde"])
        true = learned_values(truth["sde"], truth.get("R"), names if paired else [])
        true = true if paired else {k: v for k, v in true.items() if k == "R"}
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
        if name in true and not bool(torch.as_tensor(true[name]).any()):  # a zero truth: no relative error
            norm = float(torch.linalg.vector_norm(learned[name].double())) if name in learned else math.nan
            rows.append({"name": f"{name} (matrix, ‖·‖_F)", "true": 0.0, "learned": norm, "rel_error": math.nan})
        else:
            rows.append({"name": f"{name} (matrix)", "true": math.nan, "learned": math.nan, "rel_error": errors[name]})
    return rows
