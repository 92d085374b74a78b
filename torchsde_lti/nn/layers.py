r"""The design card's layers: parameter-free ``nn.Module`` wrappers of the exact discretisation.

They take the continuous-time matrices as INPUTS, so they can follow any network that
outputs F, L, Qc (and B) — per track, per time step, per model of a bank — and they
broadcast, run in float32 and float64 on any device, and are differentiable in every
input, dt included::

    A = tl.Transition()(F, dt)                  # F (..., n, n), dt (...) -> (..., n, n)
    A, G = tl.Transition()(F, dt, B=B)          # + G (..., n, p), the zero-order hold
    Q = tl.VanLoanNoise()(F, L, Qc, dt)         # (..., n, n) symmetric PSD
    d = tl.Discretization()(F, L, Qc, dt, B)    # A, Q, G in one joint evaluation

``method="matrix_exp"`` evaluates :func:`torch.matrix_exp` (A = expm(F dt), G from the ZOH
block, Q from Van Loan's block exponential); ``method="doubling"`` (default) the scaling-and-
doubling series, accurate and PSD for stiff F and large dt. See
:mod:`torchsde_lti.core.discretization`. ``validate_args`` (per layer, default True) checks
the values of every call (finite, dt ≥ 0, Qc symmetric PSD); shapes are always checked.
"""

from __future__ import annotations

from torch import Tensor, nn

from torchsde_lti.core.discretization import (
    Discrete,
    discretize,
    process_noise,
    resolve_method,
    transition_matrix,
    zero_order_hold,
)
from torchsde_lti.nn._validate import ValidateArgs

__all__ = ["Discretization", "Transition", "VanLoanNoise"]


class _MethodLayer(ValidateArgs, nn.Module):
    def __init__(self, method: str = "doubling", *, validate_args: bool | None = None) -> None:
        super().__init__()
        self.method = method
        self.validate_args = validate_args

    @property
    def method(self) -> str:
        """Discretisation method, ``"doubling"`` or ``"matrix_exp"``."""
        return self._method

    @method.setter
    def method(self, value: str) -> None:
        self._method = resolve_method(value)

    def extra_repr(self) -> str:
        return f"method={self.method!r}"


class Transition(_MethodLayer):
    r"""``A = expm(F dt)`` and, with B, the zero-order-hold ``G = ∫_0^dt expm(F s) ds B``.

    Args:
        method: ``"doubling"`` (default) or ``"matrix_exp"``.
        validate_args: value checks of every call (None: the class default, True).

    ``forward(F, dt, B=None)``: F (..., n, n), dt (...), B (..., n, p) -> A (..., n, n), or
    the pair (A, G (..., n, p)) when B is given; batch dims broadcast.
    """

    def forward(self, F: Tensor, dt: Tensor | float, B: Tensor | None = None) -> Tensor | tuple[Tensor, Tensor]:
        if B is None:
            return transition_matrix(F, dt, method=self.method, validate_args=self.validate_args)
        return zero_order_hold(F, B, dt, method=self.method, validate_args=self.validate_args)


class VanLoanNoise(_MethodLayer):
    r"""``Q = ∫_0^dt expm(F s) L Qc Lᵀ expm(F s)ᵀ ds``, the exact discrete process noise.

    Args:
        method: ``"doubling"`` (default) or ``"matrix_exp"`` (Van Loan's block exponential).

    ``forward(F, L, Qc, dt)``: F (..., n, n), L (..., n, s), Qc (..., s, s) symmetric PSD,
    dt (...) -> Q (..., n, n) symmetric PSD; batch dims broadcast.
    """

    def forward(self, F: Tensor, L: Tensor, Qc: Tensor, dt: Tensor | float) -> Tensor:
        return process_noise(F, L, Qc, dt, method=self.method, validate_args=self.validate_args)


class Discretization(_MethodLayer):
    r"""``Discrete(A, Q, G)`` in one joint evaluation (what :class:`Transition` and
    :class:`VanLoanNoise` give separately, without repeating the shared work).

    ``forward(F, L, Qc, dt, B=None)``: shapes as in :func:`~torchsde_lti.discretize`.
    """

    def forward(self, F: Tensor, L: Tensor, Qc: Tensor, dt: Tensor | float, B: Tensor | None = None) -> Discrete:
        return discretize(F, L, Qc, dt, B=B, method=self.method, validate_args=self.validate_args)
