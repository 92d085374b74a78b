r"""Functional Kalman filtering and RTS smoothing on per-step discrete matrices.

Inference is kept apart from models (as in dynamax): these are pure functions of the
discrete-time state-space model

    x_k = A_k x_{k-1} + G_k u_k + q_k,    q_k ~ N(0, Q_k),     x_{-1} ~ N(m0, P0)
    y_k = H_k x_k + D u_k + r_k,          r_k ~ N(0, R_k),     k = 0 … T-1

(D, the feedthrough of known inputs, is optional: ``D u`` is subtracted from y during the
input preparation, so every filter variant sees ``y − D u``.)

(the prior sits *before* step 0: step k first predicts with A_k, Q_k, then updates with
y_k; pass A_0 = I, Q_0 = 0 to put the prior at the first observation).
:class:`torchsde_lti.KalmanFilter` builds (A_k, Q_k, G_k) from an SDE and calls them.
Shapes and missing-data rules: :mod:`torchsde_lti.filters.inputs`.

- :func:`kalman_filter` (``kalman``), ``algorithm=`` one of :data:`ALGORITHMS`: the Joseph-form
  loop (``sequential``), the Cholesky-factor loop (``square_root``: Givens predict and update,
  PSD by construction), the associative scan (``scan``: O(log T) depth) or ``"auto"``
  (:func:`choose_algorithm`); all on one batch-last layout (``layout``);
- :func:`rts_smoother` (``smoothers``), ``algorithm="sequential"`` or ``"scan"`` (or ``"auto"``);
- :func:`imm_filter` (``imm``): interacting multiple models over a bank of per-mode matrices;
- :func:`imm_smoother` (``imm_smoother``): Kim's (1994) fixed-interval smoother over an IMM result;
- :func:`kalman_step`, :func:`imm_step` (``online``): one report per live track, the loops' own steps;
- :class:`GaussianNoise`, :class:`StudentTNoise` (``noise``): the observation-noise model every
  filter above takes as ``noise=`` (a Student-t: Roth et al.'s heavy-tailed filter).
"""

from torchsde_lti.filters.imm import IMMPrediction, IMMResult, imm_filter, imm_predict
from torchsde_lti.filters.imm_forecast import imm_forecast
from torchsde_lti.filters.imm_online import IMMState, IMMStep, imm_predict_state, imm_step
from torchsde_lti.filters.imm_smoother import IMMSmootherResult, imm_smoother
from torchsde_lti.filters.kalman import ALGORITHMS, choose_algorithm, kalman_filter
from torchsde_lti.filters.noise import GaussianNoise, NoiseModel, StudentTNoise
from torchsde_lti.filters.online import KalmanState, KalmanStep, kalman_predict, kalman_step
from torchsde_lti.filters.results import FilterResult, SmootherResult
from torchsde_lti.filters.scan import associative_scan
from torchsde_lti.filters.smoothers import SMOOTHER_ALGORITHMS, rts_smoother

__all__ = [
    "ALGORITHMS",
    "FilterResult",
    "GaussianNoise",
    "IMMPrediction",
    "IMMResult",
    "IMMSmootherResult",
    "IMMState",
    "IMMStep",
    "KalmanState",
    "KalmanStep",
    "NoiseModel",
    "SMOOTHER_ALGORITHMS",
    "SmootherResult",
    "StudentTNoise",
    "associative_scan",
    "choose_algorithm",
    "imm_filter",
    "imm_forecast",
    "imm_predict",
    "imm_predict_state",
    "imm_smoother",
    "imm_step",
    "kalman_predict",
    "kalman_step",
    "kalman_filter",
    "rts_smoother",
]
