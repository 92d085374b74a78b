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
:mod:`torchsde_lti.evaluation` (Lightning-free; it imports nothing from here).
"""

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
    "FollowMovedRun",
    "KalmanFilterModule",
    "RunCard",
    "RunInterrupted",
    "RunLog",
    "config_path",
    "format_table",
    "load_filter_weights",
    "main",
    "plot_run",
    "read_checkpoint",
    "restart_learner",
    "train",
]
