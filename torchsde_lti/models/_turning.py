r"""Turning targets: the (known or learned) turn-rate model, state ``[x, vx, y, vy]``."""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize
from typing_extensions import Unpack

from torchsde_lti.core.validation import as_float_tensor, check_finite
from torchsde_lti.models._common import ModelOptions, Scalar, eye_blocks, scalar_dtype_device
from torchsde_lti.nn.parametrizations import Unconstrained, integrator_chain
from torchsde_lti.nn.sde import SDEMatrices, StructuredSDE

__all__ = ["turn_rate"]


class TurnRate(StructuredSDE):
    """Planar motion turning at a constant rate ω (see :func:`turn_rate`)."""

    omega: Tensor
    q: Tensor
    _chain: Tensor
    _rotation: Tensor
    _top: Tensor

    def __init__(self, omega: Scalar, q: Scalar, **options: Unpack[ModelOptions]) -> None:
        super().__init__(options.get("validate_args"))
        dtype, device = scalar_dtype_device([omega, q], options)
        w = as_float_tensor(omega, "omega", dtype, device).detach().clone()
        check_finite(w, "omega")
        self.omega = nn.Parameter(w)  # signed, free: left turns > 0, right turns < 0
        parametrize.register_parametrization(  # model.omega = 0.1 works
            self, "omega", Unconstrained(name="omega").to(dtype=w.dtype, device=w.device)
        )
        self._add_positive("q", q, dtype, device)
        self._check_scalars(("omega", "q"))
        chain, top = integrator_chain(2, 2, dtype, device)  # [x, vx, y, vy]: dx = vx dt, dy = vy dt
        rotation = torch.zeros(4, 4, dtype=dtype, device=device)
        rotation[3, 1], rotation[1, 3] = 1.0, -1.0  # dvx = -ω vy dt, dvy = ω vx dt
        self.register_buffer("_chain", chain, persistent=False)
        self.register_buffer("_rotation", rotation, persistent=False)
        self.register_buffer("_top", top, persistent=False)  # L: the noise drives the velocities
        self.dim = 2
        self.position_indices = (0, 2)

    def _build(self) -> SDEMatrices:
        omega, q = self.omega, self.q
        batch = torch.broadcast_shapes(omega.shape, q.shape)
        F = self._chain + omega.expand(batch)[..., None, None] * self._rotation
        L = self._top.expand(*batch, *self._top.shape)
        return SDEMatrices(F, L, eye_blocks(F, 2, q.expand(batch)), None)

    def extra_repr(self) -> str:
        return self._scalar_repr(["omega", "q"])


def turn_rate(omega: Scalar = 0.0, q: Scalar = 1.0, **options: Unpack[ModelOptions]) -> TurnRate:
    r"""Planar motion turning at a constant rate ω, state ``[x, vx, y, vy]`` (the coordinated turn).

    ``dx = vx dt``, ``dy = vy dt``, ``dvx = −ω vy dt + dβ_x``, ``dvy = ω vx dt + dβ_y``,
    ``E[dβ dβᵀ] = q I₂ dt``: the velocity rotates at ω rad/s (ω > 0 turns left,
    counter-clockwise in east/north; ω < 0 right) and is perturbed by white acceleration::

        F = [[0, 1, 0,  0],
             [0, 0, 0, −ω],
             [0, 0, 0,  1],
             [0, ω, 0,  0]],   L = [[0, 0], [1, 0], [0, 0], [0, 1]],   Qc = q I₂.

    Exact discretisation (``s = sin ωΔ``, ``c = cos ωΔ``): the transition is Stone Soup's
    ``KnownTurnRate``, ``A = [[1, s/ω, 0, −(1−c)/ω], [0, c, 0, −s], [0, (1−c)/ω, 1, s/ω],
    [0, s, 0, c]]``, and the process noise is the exact integral
    ``Q = q ∫₀^Δ e^{Fτ} L Lᵀ e^{Fτ}ᵀ dτ``, with ``Q_xx = Q_yy = 2q(Δ − s/ω)/ω²``,
    ``Q_{x,vx} = Q_{y,vy} = q(1 − c)/ω²``, ``Q_{x,vy} = −Q_{vx,y} = q(Δ − s/ω)/ω``,
    ``Q_{vx,vx} = Q_{vy,vy} = qΔ``, 0 elsewhere (Stone Soup's ``KnownTurnRate`` uses the
    constant-velocity Q and so lacks the cross terms ``Q_{x,vy}``, ``Q_{vx,y}``). Both come from
    the library's discretisation of F, L, Qc (no closed form with a 1/ω is evaluated), so ω → 0
    is continuous: at ω = 0 this is :func:`constant_velocity` in 2-D.

    ω is a free (signed) parameter, learned with q; several turn rates in one module are a
    batch (``omega`` of shape (3,)), or modes of an IMM bank (left / straight / right).

    Args:
        omega: turn rate ω (rad/s), any finite sign; a float or a tensor whose shape is the
            parameter batch (...).
        q: spectral density of the white acceleration (m²/s³), positive.
        **options: ``dtype``, ``device`` (of the parameters) and ``validate_args`` (see
            :class:`~torchsde_lti.LTISDE`).

    Returns:
        TurnRate: F (4, 4), L (4, 2), Qc (2, 2), state ``[x, vx, y, vy]``; learns omega and q.

    Raises:
        ValueError: for a non-finite omega, a q that is not positive, or batch shapes that do not
            broadcast.
    """
    return TurnRate(omega, q, **options)
