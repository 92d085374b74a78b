r"""Research evaluation of frozen filters on held-out tracks: metrics, calibration, baselines, selection.

No Lightning, no Hydra: torch, numpy and the package's data layer only.

    predictive.py   the one-step predictive (a Gaussian mixture over modes) of whole tracks,
                    batched; mixture densities; ``frozen_copy`` (float64, eval)
    student_t.py    the Student-t predictive of a filter with noise=tl.StudentT: densities,
                    HPD levels (F distribution), draws
    calibration.py  HPD levels of a predictive mixture, a covariance inflation fitted on
                    validation tracks (``calibrate_filter``), or adapted per track online
                    (``OnlineScale``)
    scores.py       NLL (all / moving / moored windows), 2σ coverage, forecast RMSE at horizons,
                    per-vessel sums and the paired vessel bootstrap (``evaluate_filter``)
    baseline.py     the constant-velocity baseline (``cv_filter``) and its grid oracle (``tune_cv``)
    selection.py    model selection on validation summaries (``select_model``, ``validation_selection``)
    figures.py      figures of a filter on a batch of tracks: a map with 2σ ellipses, mode
                    probabilities, forecast error against lead time (``track_figures``; matplotlib)
    history_figures.py  loss and learned values per epoch of a training history (``history_figures``)
    batch_scores.py the k-step-ahead predictive NLLs (Kalman, IMM), the one-step predictive and
                    the 2σ coverage counts of one padded batch (the training module's loss and scores)
    recovery.py     learned values of a filter and their errors against a known true model
                    (``parameter_errors``, ``parameter_table``; imports no other module here)

The modules import downwards only (student_t ← predictive ← calibration ← scores ← baseline, selection,
batch_scores; recovery and figures import no other module here, history_figures only those two).

    recs = evaluate_filter(kf, tracks, cov_scale=calibrate_filter(kf, val_tracks))
    summary(recs)["nll_moving"]; paired_bootstrap(recs, evaluate_filter(cv_filter(q, r), tracks))
"""

from torchsde_lti.evaluation.baseline import cv_filter, tune_cv
from torchsde_lti.evaluation.batch_scores import coverage_counts, imm_k_step_nll, kalman_k_step_nll
from torchsde_lti.evaluation.calibration import (
    NOMINAL_2SIGMA,
    OnlineScale,
    calibrate_filter,
    fit_cov_scale,
    fit_mode_scales,
    hpd_level,
    online_scales,
    scale_vector,
)
from torchsde_lti.evaluation.figures import track_figures
from torchsde_lti.evaluation.history_figures import history_figures
from torchsde_lti.evaluation.predictive import (
    Model,
    PredictiveBatch,
    batch_predictive,
    frozen_copy,
    masked_gaussian_nll,
    mixture_log_prob,
    one_step_predictive,
    predictive_batches,
    predictive_dof,
)
from torchsde_lti.evaluation.recovery import (
    filter_errors,
    filter_values,
    flat_values,
    identifiability_note,
    learned_values,
    observed_autocovariance,
    parameter_errors,
    parameter_table,
    raw_f_identifiable,
    same_model,
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
    "EvalRecords",
    "HORIZONS",
    "Model",
    "ModelSelection",
    "NOMINAL_2SIGMA",
    "OnlineScale",
    "PredictiveBatch",
    "batch_predictive",
    "calibrate_filter",
    "coverage_counts",
    "cv_filter",
    "evaluate_filter",
    "evaluate_models",
    "filter_errors",
    "filter_values",
    "fit_cov_scale",
    "fit_mode_scales",
    "flat_values",
    "forecast_pairs",
    "frozen_copy",
    "history_figures",
    "hpd_inside",
    "hpd_level",
    "identifiability_note",
    "imm_k_step_nll",
    "kalman_k_step_nll",
    "learned_values",
    "masked_gaussian_nll",
    "mixture_log_prob",
    "moving_reports",
    "observed_autocovariance",
    "one_step_predictive",
    "online_scales",
    "paired_bootstrap",
    "parameter_errors",
    "parameter_table",
    "predictive_batches",
    "predictive_dof",
    "raw_f_identifiable",
    "same_model",
    "scale_vector",
    "select_model",
    "summary",
    "track_figures",
    "tune_cv",
    "validation_selection",
    "vessel_sums",
]
