r"""Research evaluation of frozen filters on held-out tracks: metrics, calibration, baselines, selection.

No Lightning, no Hydra: torch, numpy and the package's data layer only.

    predictive.py   the one-step predictive (a Gaussian mixture over modes) of whole tracks,
                    batched; mixture densities; ``frozen_copy`` (float64, eval)
    student_t.py    the Student-t predictive of a filter with noise=tl.StudentT: densities,
                    HPD levels (F distribution), draws
    calibration.py  HPD levels of a predictive mixture, a covariance inflation fitted on
                    validation tracks (``calibrate_filter``)
    scores.py       NLL (all / moving / moored windows), 2σ coverage, forecast RMSE at horizons,
                    per-vessel sums and the paired vessel bootstrap (``evaluate_filter``)
    baseline.py     the constant-velocity baseline (``cv_filter``) and its grid oracle (``tune_cv``)
    selection.py    model selection on validation summaries (``select_model``, ``validation_selection``)

The modules import downwards only (student_t ← predictive ← calibration ← scores ← baseline, selection).

    recs = evaluate_filter(kf, tracks, cov_scale=calibrate_filter(kf, val_tracks))
    summary(recs)["nll_moving"]; paired_bootstrap(recs, evaluate_filter(cv_filter(q, r), tracks))
"""

from torchsde_lti.evaluation.baseline import cv_filter, tune_cv
from torchsde_lti.evaluation.calibration import (
    NOMINAL_2SIGMA,
    calibrate_filter,
    fit_cov_scale,
    fit_mode_scales,
    hpd_level,
    scale_vector,
)
from torchsde_lti.evaluation.predictive import (
    Model,
    PredictiveBatch,
    frozen_copy,
    mixture_log_prob,
    one_step_predictive,
    predictive_batches,
    predictive_dof,
)
from torchsde_lti.evaluation.scores import (
    HORIZONS,
    EvalRecords,
    evaluate_filter,
    evaluate_models,
    forecast_pairs,
    hpd_inside,
    moving_reports,
    paired_bootstrap,
    summary,
    vessel_sums,
)
from torchsde_lti.evaluation.selection import ModelSelection, select_model, validation_selection

__all__ = [
    "HORIZONS",
    "NOMINAL_2SIGMA",
    "EvalRecords",
    "Model",
    "ModelSelection",
    "PredictiveBatch",
    "calibrate_filter",
    "cv_filter",
    "evaluate_filter",
    "evaluate_models",
    "fit_cov_scale",
    "fit_mode_scales",
    "forecast_pairs",
    "frozen_copy",
    "hpd_inside",
    "hpd_level",
    "mixture_log_prob",
    "moving_reports",
    "one_step_predictive",
    "paired_bootstrap",
    "predictive_batches",
    "predictive_dof",
    "scale_vector",
    "select_model",
    "summary",
    "tune_cv",
    "validation_selection",
    "vessel_sums",
]
