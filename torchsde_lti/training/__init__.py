"""Training glue: Lightning module, callbacks, plots and the Hydra entry point; the only part of
the package that imports Lightning, Hydra or matplotlib.

    module.py       KalmanFilterModule: NLL loss, robust optimizer steps, logged metrics
    callbacks.py    RunLog, FollowMovedRun (Lightning), BestRun (Hydra)
    plots.py        loss / parameter / map / track / mode / forecast figures of a run
    checkpoints.py  read_checkpoint / load_filter_weights: errors that name the file and the damage
    config.py       RunSchema (Hydra's ConfigStore) and check_config: nonsense values rejected before any work
    outputs.py      strict JSON, atomic files, the CSV log of a resumed run
    report.py       RunCard: metrics.json / results.md of a running, completed, interrupted, failed run
    signals.py      SIGTERM / SIGINT recorded around Lightning's own handling: report, exit 128 + signal
    train.py        train(cfg) behind @hydra.main (``python -m torchsde_lti.train``)

The research evaluation (scores, calibration, baselines, selection, parameter recovery) is
:mod:`torchsde_lti.evaluation`; a few of its names are re-exported here for old imports.
"""

from torchsde_lti.evaluation import (  # re-exported for old imports
    EvalRecords,
    calibrate_filter,
    evaluate_filter,
    paired_bootstrap,
    parameter_errors,
    select_model,
    tune_cv,
)
from torchsde_lti.training.callbacks import BestRun, FollowMovedRun, RunLog
from torchsde_lti.training.checkpoints import CheckpointError, load_filter_weights, read_checkpoint
from torchsde_lti.training.module import KalmanFilterModule
from torchsde_lti.training.plots import plot_run
from torchsde_lti.training.report import RunCard, format_table
from torchsde_lti.training.signals import RunInterrupted
from torchsde_lti.training.train import config_path, main, restart_learner, train

__all__ = [
    "BestRun",
    "CheckpointError",
    "EvalRecords",
    "FollowMovedRun",
    "KalmanFilterModule",
    "RunCard",
    "RunInterrupted",
    "RunLog",
    "calibrate_filter",
    "config_path",
    "evaluate_filter",
    "format_table",
    "load_filter_weights",
    "main",
    "paired_bootstrap",
    "parameter_errors",
    "plot_run",
    "read_checkpoint",
    "restart_learner",
    "select_model",
    "train",
    "tune_cv",
]
