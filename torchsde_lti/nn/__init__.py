"""Modules: the parameter-free discretisation layers, parametrisations, the LTISDE (and the
StructuredSDE base of the motion models), the KalmanFilter and IMMFilter modules and their
observation-noise options (Gaussian, StudentT)."""

from torchsde_lti.nn._online import model_version
from torchsde_lti.nn._validate import NonFiniteLikelihoodError
from torchsde_lti.nn.deploy import DeployedFilter, OnlineStep, PackagedProgram, compile_package, load_package
from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import FilterMode, Forecast, KalmanFilter
from torchsde_lti.nn.layers import Discretization, Transition, VanLoanNoise
from torchsde_lti.nn.noise import Gaussian, StudentT
from torchsde_lti.nn.sde import LTISDE, SDEMatrices, StructuredSDE

__all__ = [
    "DeployedFilter",
    "Discretization",
    "FilterMode",
    "Forecast",
    "Gaussian",
    "IMMFilter",
    "KalmanFilter",
    "LTISDE",
    "NonFiniteLikelihoodError",
    "OnlineStep",
    "PackagedProgram",
    "SDEMatrices",
    "StructuredSDE",
    "StudentT",
    "Transition",
    "VanLoanNoise",
    "compile_package",
    "load_package",
    "model_version",
]
