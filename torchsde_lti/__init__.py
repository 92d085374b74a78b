"""torchsde_lti: exact, batched, differentiable continuous-time linear SDEs for PyTorch.

Notation (Särkkä & Solin): continuous-time F, L, Qc, B; discrete-time A, Q (= Qd), G;
observations y = H x + v, v ~ N(0, R).
"""

from torchsde_lti.discretization import (
    Discrete,
    discretize,
    process_noise,
    propagate,
    transition_matrix,
    zero_order_hold,
)
from torchsde_lti.stationary import stationary_covariance
from torchsde_lti.sde import LTISDE, SDEMatrices
from torchsde_lti import models, parametrizations
from torchsde_lti.filtering import (
    FilterResult,
    SmootherResult,
    kalman_filter,
    parallel_kalman_filter,
    parallel_rts_smoother,
    rts_smoother,
)
from torchsde_lti.kalman import Forecast, KalmanFilter
from torchsde_lti.nn.imm import IMMFilter

__all__ = [
    "FilterResult",
    "Forecast",
    "KalmanFilter",
    "IMMFilter",
    "SmootherResult",
    "kalman_filter",
    "parallel_kalman_filter",
    "parallel_rts_smoother",
    "rts_smoother",
    "LTISDE",
    "SDEMatrices",
    "models",
    "parametrizations",
    "Discrete",
    "discretize",
    "process_noise",
    "propagate",
    "stationary_covariance",
    "transition_matrix",
    "zero_order_hold",
]

__version__ = "0.1.0"
