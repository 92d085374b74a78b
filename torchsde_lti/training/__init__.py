"""Training glue: Lightning module, metrics, callbacks, plots and the Hydra entry point.

The research evaluation (metrics of frozen filters, calibration, baselines, selection) lives in
:mod:`torchsde_lti.evaluation`; its main names are re-exported here for old imports.

The only part of the package that imports Lightning, Hydra or matplotlib.

    module.py       KalmanFilterModule: NLL loss, robust optimizer steps, logged metrics
    metrics.py      parameter errors (identifiable quantities), tables, masked Gaussian NLL
    callbacks.py    ParameterHistory, RunLog, ValidatedAt, FollowMovedRun (Lightning), BestRun (Hydra)
    plots.py        loss / parameter / track figures of a run
    checkpoints.py  read_checkpoint / load_filter_weights: clear errors for damaged files
    config.py       RunSchema (Hydra's ConfigStore) and check_config: nonsense values rejected before any work
    outputs.py      strict JSON, atomic files, the CSV log of a resumed run, the data summary
    report.py       metrics.json / results.md for a running, completed, interrupted, failed run
    signals.py      SIGTERM / SIGINT recorded around Lightning's own handling: report, exit 128 + signal
    train.py        train(cfg) behind @hydra.main (``python -m torchsde_lti.train``)
"""

from torchsde_lti.evaluation import (  # moved to torchsde_lti.evaluation; re-exported for old imports
    EvalRecords,
    ModelSelection,
    calibrate_filter,
    evaluate_filter,
    evaluate_models,
    fit_cov_scale,
    hpd_level,
    paired_bootstrap,
    select_model,
    tune_cv,
    validation_selection,
)
from torchsde_lti.training.callbacks import BestRun, FollowMovedRun, ParameterHistory, RunLog, ValidatedAt
from torchsde_lti.training.checkpoints import (
    CheckpointError,
    load_filter_weights,
    read_checkpoint,
)
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
