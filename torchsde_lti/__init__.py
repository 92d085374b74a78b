"""torchsde_lti: exact, batched, differentiable continuous-time linear SDEs for PyTorch.

Notation (Särkkä & Solin): continuous-time F, L, Qc, B; discrete-time A, Q (= Qd), G;
observations y = H x + v, v ~ N(0, R).

Layers of the package (each imports only from the ones above it):

- :mod:`torchsde_lti.core`: torch only — validation, linear-algebra kernels, exact
  discretisation (doubling and torch.matrix_exp methods), stationary covariance, moments;
- :mod:`torchsde_lti.nn`: the Transition / VanLoanNoise layers, parametrisations,
  :class:`LTISDE`, :class:`KalmanFilter`;
- :mod:`torchsde_lti.models`: the motion-model library;
- :mod:`torchsde_lti.filters`: pure filter and smoother functions on discrete matrices;
- :mod:`torchsde_lti.data`: simulation, track batches, real trajectories (``tl.data.load_tracks``);
- :mod:`torchsde_lti.training`: Lightning module and the Hydra entry point.
"""

from torchsde_lti import data, models
from torchsde_lti.core import (
    METHODS,
    Discrete,
    discretize,
    process_noise,
    propagate,
    stationary_covariance,
    transition_matrix,
    zero_order_hold,
)
from torchsde_lti.filters import (
    FilterResult,
    SmootherResult,
    kalman_filter,
    parallel_kalman_filter,
    parallel_rts_smoother,
    rts_smoother,
)
from torchsde_lti.nn import (
    LTISDE,
    DeployedFilter,
    Discretization,
    Forecast,
    IMMFilter,
    KalmanFilter,
    SDEMatrices,
    StructuredSDE,
    Transition,
    VanLoanNoise,
)
from torchsde_lti.nn import parametrizations

__all__ = [
    "METHODS",
    "DeployedFilter",
    "Discrete",
    "Discretization",
    "FilterResult",
    "Forecast",
    "IMMFilter",
    "KalmanFilter",
    "LTISDE",
    "SDEMatrices",
    "SmootherResult",
    "StructuredSDE",
    "Transition",
    "VanLoanNoise",
    "data",
    "discretize",
    "kalman_filter",
    "models",
    "parallel_kalman_filter",
    "parallel_rts_smoother",
    "parametrizations",
    "process_noise",
    "propagate",
    "rts_smoother",
    "stationary_covariance",
    "transition_matrix",
    "zero_order_hold",
]

__version__ = "0.1.0"
