"""torchsde_lti: exact, batched, differentiable continuous-time linear SDEs for PyTorch.

Notation (Särkkä & Solin): continuous-time F, L, Qc, B; discrete-time A, Q (= Qd), G;
observations y = H x + v, v ~ N(0, R).

The package is layered: :data:`LAYERS` names each layer with its job, in import order —
each imports only from the layers before it (enforced by tests/test_layering.py).
"""

#: The layers of the package (subpackages and top-level modules) in import order, each
#: importing only from those before it, with their jobs. Inference is kept apart from models
#: (as in dynamax): the filters are pure functions on discrete matrices, below the nn
#: modules that assemble those matrices from learned parameters and call them.
LAYERS: tuple[tuple[str, str], ...] = (
    ("core", "torch only: validation, linear-algebra kernels, exact discretisation, stationary covariance, moments"),
    ("filters", "pure Kalman filter / smoother / IMM functions on discrete matrices, NamedTuple results"),
    ("nn", "nn.Modules: the discretisation layers, parametrisations, LTISDE, KalmanFilter, IMMFilter"),
    ("models", "the motion-model library (tl.models): factories of LTISDE subclasses"),
    ("interop", "Stone Soup transition model and filterpy helper (optional peers)"),
    ("data", "simulation, the track batch type, real trajectories (tl.data.load_tracks), the Lightning DataModules"),
    ("evaluation", "research evaluation of frozen filters: metrics, calibration, baselines, selection"),
    ("pretrained", "shipped trained filters with their cards, loaded by name (tl.pretrained.load)"),
    ("training", "the Lightning module, metrics, callbacks, plots and the Hydra entry point"),
    ("train", "the `python -m torchsde_lti.train` shim"),
    ("prepare", "the `python -m torchsde_lti.prepare` entry point (out-of-core preparation, Hydra)"),
    ("runs", "a trained run rebuilt from its directory (tl.load_run), its filter over tracks from a file"),
    ("cli", "the `torchsde-lti` command: train, prepare, filter / smooth a file of tracks, evaluate, export"),
    ("__main__", "`python -m torchsde_lti`: the `torchsde-lti` command"),
)
if __doc__ is not None:  # (python -OO strips docstrings)
    __doc__ += "\n" + "\n".join(f"- :mod:`torchsde_lti.{name}` — {job}." for name, job in LAYERS) + "\n"

from torchsde_lti import data, models, pretrained  # noqa: E402 — after LAYERS, which the docstring reads
from torchsde_lti.core import (  # noqa: E402
    METHODS,
    Discrete,
    discretize,
    process_noise,
    propagate,
    stationary_covariance,
    transition_matrix,
    zero_order_hold,
)
from torchsde_lti.filters import (  # noqa: E402
    ALGORITHMS,
    FilterResult,
    IMMSmootherResult,
    IMMState,
    IMMStep,
    KalmanState,
    KalmanStep,
    SmootherResult,
    imm_smoother,
    kalman_filter,
    rts_smoother,
)
from torchsde_lti.nn import (  # noqa: E402
    LTISDE,
    DeployedFilter,
    Discretization,
    Forecast,
    Gaussian,
    IMMFilter,
    KalmanFilter,
    NonFiniteLikelihoodError,
    OnlineStep,
    PackagedProgram,
    SDEMatrices,
    StructuredSDE,
    StudentT,
    Transition,
    VanLoanNoise,
    compile_package,
    load_package,
    parametrizations,  # noqa: E402
)

__all__ = [
    "ALGORITHMS",
    "LAYERS",
    "METHODS",
    "DeployedFilter",
    "Discrete",
    "Discretization",
    "FilterResult",
    "Forecast",
    "Gaussian",
    "IMMFilter",
    "IMMSmootherResult",
    "IMMState",
    "IMMStep",
    "KalmanFilter",
    "KalmanState",
    "KalmanStep",
    "LTISDE",
    "NonFiniteLikelihoodError",
    "OnlineStep",
    "PackagedProgram",
    "Run",
    "SDEMatrices",
    "SmootherResult",
    "StructuredSDE",
    "StudentT",
    "Transition",
    "VanLoanNoise",
    "compile_package",
    "data",
    "discretize",
    "imm_smoother",
    "kalman_filter",
    "load_package",
    "load_run",
    "models",
    "parametrizations",
    "pretrained",
    "process_noise",
    "propagate",
    "rts_smoother",
    "stationary_covariance",
    "transition_matrix",
    "zero_order_hold",
]

__version__ = "0.1.0"

#: Names made on first use, with their module: ``tl.load_run`` imports Hydra, which
#: ``import torchsde_lti`` does not (the core runs with torch and numpy only).
_LAZY = {"Run": "torchsde_lti.runs", "load_run": "torchsde_lti.runs"}


def __getattr__(name: str) -> object:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'torchsde_lti' has no attribute {name!r}")
