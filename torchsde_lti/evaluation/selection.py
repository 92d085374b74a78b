r"""Model selection on a VALIDATION split: the rule, and the rule on every model's evaluation.

    sel = validation_selection(models, val_tracks)   # evaluate_filter + summary of every model, then the rule
    sel = select_model(val_summaries, singles=[...])  # the rule alone, on VALIDATION summaries only
    sel.best, sel.best_single, sel.reason              # ModelSelection

Model selection (:func:`select_model`, :func:`validation_selection`) judges on a VALIDATION
split what the hold-out judges: the best single model is the single-mode model of lowest
validation NLL; the best model is the candidate (a multi-mode model) of lowest validation NLL
among those whose validation forecast RMSE is <= the best single's at every horizon; when
none qualifies, the lowest validation NLL of all (and the selection says so).

The summaries are those of :mod:`torchsde_lti.evaluation.scores`
(:func:`~torchsde_lti.evaluation.summary` of
:func:`~torchsde_lti.evaluation.evaluate_filter`), so the validation split is scored
exactly as the hold-out is.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from typing import Any, NamedTuple

from torchsde_lti.data.loaded_tracks import Tracks
from torchsde_lti.evaluation.predictive import Model
from torchsde_lti.evaluation.scores import HORIZONS, _key, evaluate_filter, summary
from torchsde_lti.nn.kalman import KalmanFilter

__all__ = ["ModelSelection", "select_model", "validation_selection"]


class ModelSelection(NamedTuple):
    """The outcome of :func:`select_model`.

    best: the selected model; best_single: the single-mode model of lowest validation NLL;
    candidates: the models the rule chose among (every model not in ``singles``);
    qualified: the candidates whose validation forecast RMSE is <= best_single's at every
    horizon (in the order given); fallback: True when no candidate qualified and ``best`` is
    the lowest validation NLL of all models; reason: the decision in words; table: the
    validation summaries the rule read ({model: {metric: value}}, as given).
    """

    best: str
    best_single: str
    candidates: tuple[str, ...]
    qualified: tuple[str, ...]
    fallback: bool
    reason: str
    table: dict[str, dict[str, float]]


def select_model(
    val: Mapping[str, Mapping[str, float]],
    singles: Collection[str],
    horizons: Sequence[float] = HORIZONS,
    nll_key: str = "nll",
) -> ModelSelection:
    r"""The model selection rule, on VALIDATION summaries (never the hold-out's).

    With :math:`\mathrm{NLL}_v(m)` and :math:`\mathrm{RMSE}_v(m, h)` the validation NLL per report
    and forecast RMSE at horizon h of model m (:func:`summary` on the validation split, the
    same reports for every model):

    - best single :math:`s^* = \arg\min_{m \in \text{singles}} \mathrm{NLL}_v(m)`;
    - qualified :math:`Q = \{c \notin \text{singles} : \mathrm{RMSE}_v(c, h) \le
      \mathrm{RMSE}_v(s^*, h)\ \forall h\}` (a NaN RMSE does not qualify);
    - best :math:`= \arg\min_{c \in Q} \mathrm{NLL}_v(c)`; when Q is empty (or there are no
      candidates), the fallback :math:`\arg\min_m \mathrm{NLL}_v(m)` over all models.

    So the selected model is not worse than the best single model on validation forecasts
    (what the hold-out judges besides the NLL), and among those the likeliest.

    Args:
        val: {model: summary} with ``nll_key`` and ``fc_rmse_<min>`` for every horizon (e.g.
            ``{"fc_rmse_5": ...}`` for 300 s), e.g. :func:`summary` of :func:`evaluate_filter`
            on the validation tracks.
        singles: the single-mode models (at least one of ``val``).
        horizons: forecast horizons (s) to check; nll_key: the NLL metric to rank by.

    Returns:
        :class:`ModelSelection`. Ties go to the model listed first in ``val``.
    """
    names = list(val)
    if not names:
        raise ValueError("val must hold at least one model's validation summary, got none")
    unknown = [s for s in singles if s not in val]
    if unknown:
        raise ValueError(f"singles must name models of val {names}, got unknown {unknown}")
    single = [n for n in names if n in set(singles)]
    if not single:
        raise ValueError(f"singles must name at least one model of val {names}, got none")
    keys = [nll_key, *(f"fc_rmse_{_key(h)}" for h in horizons)]
    for n in names:
        missing = [k for k in keys if k not in val[n]]
        if missing:
            raise ValueError(f"val[{n!r}] lacks {missing} (needs {keys})")

    def nll(n: str) -> float:
        v = float(val[n][nll_key])
        return v if math.isfinite(v) else math.inf

    best_single = min(single, key=nll)
    candidates = tuple(n for n in names if n not in set(single))
    ref = {h: float(val[best_single][f"fc_rmse_{_key(h)}"]) for h in horizons}
    qualified = tuple(c for c in candidates if all(float(val[c][f"fc_rmse_{_key(h)}"]) <= ref[h] for h in horizons))
    table = {n: {k: float(v) for k, v in val[n].items()} for n in names}
    horizon_s = "/".join(_key(h) for h in horizons)
    if qualified:
        best = min(qualified, key=nll)
        reason = (
            f"{best}: lowest validation {nll_key} among the candidates whose validation forecast RMSE at "
            f"{horizon_s} min is <= the best single's ({best_single}): {list(qualified)} of {list(candidates)}"
        )
        return ModelSelection(best, best_single, candidates, qualified, False, reason, table)
    best = min(names, key=nll)
    reason = (
        f"FALLBACK: no candidate of {list(candidates)} has a validation forecast RMSE at {horizon_s} min <= the "
        f"best single's ({best_single}); {best}: the lowest validation {nll_key} of all models"
    )
    return ModelSelection(best, best_single, candidates, (), True, reason, table)


def validation_selection(
    models: Mapping[str, Model],
    tracks: Tracks,
    singles: Collection[str] | None = None,
    cov_scale: Mapping[str, float | Sequence[float]] | None = None,
    horizons: Sequence[float] = HORIZONS,
    **kwargs: Any,
) -> ModelSelection:
    """:func:`select_model` on :func:`summary` of :func:`evaluate_filter` of every model on the
    VALIDATION ``tracks`` (the same reports for every model).

    Args:
        models: {name: frozen filter}; singles: the single-mode models (default: every
            :class:`~torchsde_lti.KalmanFilter` of ``models``; the candidates are the rest).
        cov_scale: {name: the calibrated predictive's covariance scale} (default 1.0: the
            filter's own predictive); the NLL ranks the predictive that is evaluated.
        horizons: forecast horizons (s); kwargs: more arguments of :func:`evaluate_filter`.
    """
    if singles is None:
        singles = [n for n, m in models.items() if isinstance(m, KalmanFilter)]
    scale = dict(cov_scale or {})
    val = {
        n: summary(evaluate_filter(m, tracks, horizons=horizons, cov_scale=scale.get(n, 1.0), **kwargs))
        for n, m in models.items()
    }
    return select_model(val, singles, horizons)
