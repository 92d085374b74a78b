"""Training glue: Lightning module, metrics, callbacks, plots and the Hydra entry point.

The only part of the package that imports Lightning, Hydra or matplotlib.

    module.py     KalmanFilterModule: NLL loss, robust optimizer steps, logged metrics
    metrics.py    parameter errors (identifiable quantities), tables, masked Gaussian NLL
    callbacks.py  ParameterHistory (Lightning), BestRun (Hydra, best of a multirun)
    plots.py      loss / parameter / track figures of a run
    train.py      train(cfg) behind @hydra.main (``python -m torchsde_lti.train``)
"""

from torchsde_lti.training.callbacks import BestRun, ParameterHistory
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
from torchsde_lti.training.train import config_path, main, restart_learner, train

__all__ = [
    "BestRun",
    "KalmanFilterModule",
    "ParameterHistory",
    "config_path",
    "format_table",
    "learned_values",
    "main",
    "masked_gaussian_nll",
    "observed_autocovariance",
    "parameter_errors",
    "parameter_table",
    "plot_run",
    "raw_f_identifiable",
    "restart_learner",
    "train",
]
