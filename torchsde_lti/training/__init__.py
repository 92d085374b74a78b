"""Training glue: Lightning module, metrics, callbacks, plots and the Hydra entry point.

The only part of the package that imports Lightning, Hydra or matplotlib.

    module.py       KalmanFilterModule: NLL loss, robust optimizer steps, logged metrics
    metrics.py      parameter errors (identifiable quantities), tables, masked Gaussian NLL
    evaluation.py   frozen filters on held-out tracks: NLL (moving / moored windows), HPD coverage,
                    forecast RMSE, paired vessel bootstrap (no Lightning)
    baseline.py     the constant-velocity baseline (cv_filter) and its CV grid oracle (tune_cv)
    selection.py    model selection on validation (select_model, validation_selection)
    calibration.py  HPD levels of a predictive mixture, a scalar covariance inflation fitted on
                    validation tracks (calibrate_filter), the one-step predictive of a filter
    callbacks.py    ParameterHistory, RunLog, ValidatedAt, FollowMovedRun (Lightning), BestRun (Hydra)
    plots.py        loss / parameter / track figures of a run
    checkpoints.py  read_checkpoint / load_filter_weights: clear errors for damaged files
    config.py       RunSchema (Hydra's ConfigStore) and check_config: nonsense values rejected before any work
    outputs.py      strict JSON, atomic files, the CSV log of a resumed run, the data summary
    report.py       metrics.json / results.md for a running, completed, interrupted, failed run
    signals.py      SIGTERM / SIGINT recorded around Lightning's own handling: report, exit 128 + signal
    train.py        train(cfg) behind @hydra.main (``python -m torchsde_lti.train``)
"""

from torchsde_lti.training.baseline import tune_cv
from torchsde_lti.training.calibration import calibrate_filter, fit_cov_scale, hpd_level
from torchsde_lti.training.callbacks import BestRun, FollowMovedRun, ParameterHistory, RunLog, ValidatedAt
from torchsde_lti.training.checkpoints import (
    CheckpointError,
    load_filter_weights,
    read_checkpoint,
)
from torchsde_lti.training.evaluation import EvalRecords, evaluate_filter, evaluate_models, paired_bootstrap
from torchsde_lti.training.metrics import (
    format_table,
    learned_values,
    masked_gaussian_nll,
    observed_autocovariance,
    parameter_errors,
    parameter_table,
    raw_f_identifiable,
)
from torchsde_lti.training.module import KalmanFilterModule
from torchsde_lti.training.plots import plot_run
from torchsde_lti.training.selection import ModelSelection, select_model, validation_selection
from torchsde_lti.training.signals import RunInterrupted
from torchsde_lti.training.train import config_path, main, restart_learner, train

__all__ = [
    "BestRun",
    "CheckpointError",
    "EvalRecords",
    "FollowMovedRun",
    "KalmanFilterModule",
    "ModelSelection",
    "ParameterHistory",
    "RunInterrupted",
    "RunLog",
    "ValidatedAt",
    "calibrate_filter",
    "config_path",
    "evaluate_filter",
    "evaluate_models",
    "fit_cov_scale",
    "format_table",
    "hpd_level",
    "learned_values",
    "load_filter_weights",
    "main",
    "masked_gaussian_nll",
    "observed_autocovariance",
    "paired_bootstrap",
    "parameter_errors",
    "parameter_table",
    "plot_run",
    "raw_f_identifiable",
    "read_checkpoint",
    "restart_learner",
    "select_model",
    "train",
    "tune_cv",
    "validation_selection",
]
