"""The functional core (torch only): validation, linear-algebra kernels, exact
discretisation, stationary covariance and moment propagation."""

from torchsde_lti.core.discretization import (
    METHODS,
    Discrete,
    SharedSeries,
    discretization_series,
    discretize,
    discretize_series,
    process_noise,
    transition_matrix,
    zero_order_hold,
)
from torchsde_lti.core.moments import predict_moments, propagate
from torchsde_lti.core.series import transition_apply
from torchsde_lti.core.stationary import stationary_covariance

__all__ = [
    "METHODS",
    "Discrete",
    "SharedSeries",
    "discretization_series",
    "discretize",
    "discretize_series",
    "predict_moments",
    "process_noise",
    "propagate",
    "stationary_covariance",
    "transition_apply",
    "transition_matrix",
    "zero_order_hold",
]
