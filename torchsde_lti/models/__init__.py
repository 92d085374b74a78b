r"""Motion-model library: each factory returns an :class:`~torchsde_lti.LTISDE` with exact (F, L, Qc[, B]).

One public name per model, the factory (``tl.models.singer(...)``); the classes behind them
are :class:`~torchsde_lti.StructuredSDE` subclasses whose matrices are functions of a few
named scalars (``q``, ``alpha``, ``k``, ``theta``, ``lengthscale``, ``variance``, ``m``,
``c`` …) that are learnable ``nn.Parameter``\ s, positive by construction
(:class:`~torchsde_lti.nn.parametrizations.Positive`, ``softplus + floor``), except the signed
turn rate ``omega`` of :func:`turn_rate` (a plain parameter). Read and set them
by name: ``model.q`` is the current positive value, ``model.q = 2.0`` stores it (in place);
the raw tensor is ``model.parametrizations.q.original``. Scalars may carry a batch shape
(``q`` of shape (16,) gives 16 models in one module, matrices (16, n, n)); Python floats
become tensors of ``dtype`` (default: torch's default dtype).

Every factory takes the keyword options ``dtype``, ``device`` and ``validate_args`` (see
:class:`~torchsde_lti.LTISDE`). ``model.F`` etc. are read-only (they are derived); use
:meth:`~torchsde_lti.LTISDE.to_free` to continue from a model with free matrices. A filter
started without a P0 uses ``model.prior_covariance()``: the stationary covariance for a
Hurwitz F, the steady-state start for :func:`shaped` models.

Multi-axis models use per-axis state ordering ``[x, vx, y, vy]`` (``[x, vx, ax, y, vy, ay]``),
one independent Brownian motion per axis (``Qc = q I_dim``), and ``position_indices`` lists the
position components (:func:`position_observation` builds the matching H).

Families: integrator chains and drag models (:func:`integrated_wiener`,
:func:`constant_velocity`, :func:`constant_acceleration`, :func:`singer`,
:func:`integrated_ou`, :func:`ornstein_uhlenbeck`, :func:`moored`); turning targets
(:func:`turn_rate`: the velocity rotating at a learned, signed rate ω); Gaussian processes
(:func:`matern`); ODE systems (:func:`mass_spring_damper`, :func:`companion`,
:func:`from_transfer_function`); composition (:func:`shaped`, :func:`block_diag`,
:func:`position_observation`).
"""

from torchsde_lti.models._composition import block_diag, position_observation, shaped
from torchsde_lti.models._gaussian_process import matern
from torchsde_lti.models._kinematics import (
    constant_acceleration,
    constant_velocity,
    integrated_ou,
    integrated_wiener,
    moored,
    ornstein_uhlenbeck,
    singer,
)
from torchsde_lti.models._ode import companion, from_transfer_function, mass_spring_damper
from torchsde_lti.models._turning import turn_rate

__all__ = [
    "block_diag",
    "companion",
    "constant_acceleration",
    "constant_velocity",
    "from_transfer_function",
    "integrated_ou",
    "integrated_wiener",
    "mass_spring_damper",
    "matern",
    "moored",
    "ornstein_uhlenbeck",
    "position_observation",
    "shaped",
    "singer",
    "turn_rate",
]
