"""torchsde_lti: exact, batched, differentiable continuous-time linear SDEs for PyTorch.

Notation (Särkkä & Solin): continuous-time F, L, Qc, B; discrete-time A, Q (= Qd), G;
observations y = H x + v, v ~ N(0, R).
"""

from torchsde_lti.discretization import Discrete, discretize, propagate, transition_matrix
from torchsde_lti.stationary import stationary_covariance
from torchsde_lti.sde import LTISDE, SDEMatrices
from torchsde_lti import models, parametrizations

__all__ = [
    "LTISDE",
    "SDEMatrices",
    "models",
    "parametrizations",
    "Discrete",
    "discretize",
    "propagate",
    "stationary_covariance",
    "transition_matrix",
]

__version__ = "0.1.0"
