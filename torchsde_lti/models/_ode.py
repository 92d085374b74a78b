r"""ODE systems as SDEs: mass–spring–damper, companion form of an order-n ODE, transfer functions.

Each has an output equation ``y = C x + D u`` (``model.C``, ``model.D``: pass them as the
filter's H and D) and a force input B.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn
from typing_extensions import Unpack

from torchsde_lti.core.validation import as_float_tensor, broadcast_batch, check_finite, shape_str
from torchsde_lti.models._common import ModelOptions, Scalar, scalar_dtype_device
from torchsde_lti.nn.parametrizations import integrator_chain
from torchsde_lti.nn.sde import SDEMatrices, StructuredSDE

__all__ = ["companion", "from_transfer_function", "mass_spring_damper"]


class OutputEquation:
    """Models with an output equation ``y = C x + D u``: ``C`` is the registered buffer
    ``output_matrix`` (1, n) (pass it as the filter's H), ``D`` the (1, p) zero feedthrough
    unless a subclass says otherwise (pass it as the filter's D)."""

    output_matrix: Tensor

    @property
    def C(self) -> Tensor:
        return self.output_matrix

    @property
    def D(self) -> Tensor:
        return self.output_matrix.new_zeros(1, 1)


class MassSpringDamper(OutputEquation, StructuredSDE):
    """Mass–spring–damper with force input (see :func:`mass_spring_damper`)."""

    m: Tensor
    k: Tensor
    c: Tensor
    q: Tensor

    def __init__(self, m: Scalar, k: Scalar, c: Scalar, q: Scalar = 1.0, **options: Unpack[ModelOptions]) -> None:
        super().__init__(options.get("validate_args"))
        dt_, dev = scalar_dtype_device([m, k, c, q], options)
        for name, value in (("m", m), ("k", k), ("c", c), ("q", q)):
            self._add_positive(name, value, dt_, dev)
        self._check_scalars(("m", "k", "c", "q"))
        self.register_buffer("output_matrix", torch.tensor([[1.0, 0.0]], dtype=dt_, device=dev), persistent=False)
        self.position_indices = (0,)

    def _build(self) -> SDEMatrices:
        m, k, c, q = self.m, self.k, self.c, self.q
        batch = torch.broadcast_shapes(m.shape, k.shape, c.shape, q.shape)
        zero = m.new_zeros(batch)
        one = zero + 1.0
        F = torch.stack(
            (torch.stack((zero, one), -1), torch.stack(((-k / m).expand(batch), (-c / m).expand(batch)), -1)), -2
        )
        Bm = torch.stack((zero, (1.0 / m).expand(batch)), -1)[..., None]
        return SDEMatrices(F, Bm, q.expand(batch)[..., None, None], Bm)

    def extra_repr(self) -> str:
        return self._scalar_repr(["m", "k", "c", "q"])


def mass_spring_damper(
    m: Scalar, k: Scalar, c: Scalar, q: Scalar = 1.0, **options: Unpack[ModelOptions]
) -> MassSpringDamper:
    r"""Mass–spring–damper ``m p'' = u − c p' − k p + w``, state ``[p, p']``.

    u is a known force input (through B), w a random force of spectral density q.

    ``F = [[0, 1], [−k/m, −c/m]]``, ``B = L = [0, 1/m]ᵀ``, ``Qc = q`` (spectral density of
    the random force), output ``C = [[1, 0]]`` (``output_matrix``).

    Args:
        m: mass, positive.
        k: spring constant, positive.
        c: damping coefficient, positive.
        q: spectral density of the random force, positive.
        **options: ``dtype``, ``device`` (of the parameters) and ``validate_args`` (see
            :class:`~torchsde_lti.LTISDE`).

    Returns:
        MassSpringDamper: F (2, 2), B and L (2, 1), output ``C`` (1, 2); learns m, k, c and q.
    """
    return MassSpringDamper(m, k, c, q, **options)


class Companion(OutputEquation, StructuredSDE):
    """Order-n ODE in companion form (see :func:`companion`)."""

    a: Tensor
    q: Tensor
    _chain: Tensor
    _e_n: Tensor

    def __init__(self, a: Sequence[float] | Tensor, q: Scalar = 1.0, **options: Unpack[ModelOptions]) -> None:
        super().__init__(options.get("validate_args"))
        dt_, dev = scalar_dtype_device([a, q], options)
        coeffs = as_float_tensor(a, "a", dt_, dev).detach().clone()
        if coeffs.dim() < 1 or coeffs.shape[-1] < 2:
            raise ValueError(
                f"a must hold coefficients a_0..a_n with n >= 1, shape (..., n+1); got shape {shape_str(coeffs)}"
            )
        check_finite(coeffs, "a")
        if bool((coeffs[..., -1] == 0).any()):
            raise ValueError(f"a: the leading coefficient a_n must be non-zero (shape {shape_str(coeffs)})")
        self.a = nn.Parameter(coeffs)
        self._add_positive("q", q, dt_, dev)
        broadcast_batch([("a", coeffs.shape[:-1]), ("q", self.q.shape)])
        n = coeffs.shape[-1] - 1
        self.order = n
        chain, e_n = integrator_chain(n, 1, dt_, dev)  # one axis: [y, y', …], e_n (n, 1)
        self.register_buffer("_chain", chain, persistent=False)
        self.register_buffer("_e_n", e_n[:, 0], persistent=False)
        out = torch.zeros(1, n, dtype=dt_, device=dev)
        out[0, 0] = 1.0
        self.register_buffer("output_matrix", out, persistent=False)
        self.position_indices = (0,)

    def _build(self) -> SDEMatrices:
        a, q = self.a, self.q
        lead = a[..., -1:]
        last = -a[..., :-1] / lead  # (..., n)
        F = self._chain + self._e_n[:, None] * last[..., None, :]
        batch = torch.broadcast_shapes(F.shape[:-2], q.shape)
        F = F.expand(*batch, *F.shape[-2:])
        Bm = (self._e_n / lead)[..., None].expand(*batch, self.order, 1)
        return SDEMatrices(F, Bm, q.expand(batch)[..., None, None], Bm)

    def extra_repr(self) -> str:
        return f"order={self.order}, a: {shape_str(self.a)}, " + self._scalar_repr(["q"])


def companion(a: Sequence[float] | Tensor, q: Scalar = 1.0, **options: Unpack[ModelOptions]) -> Companion:
    r"""Order-n ODE ``a_n y⁽ⁿ⁾ + … + a_1 y' + a_0 y = u + w`` in companion form.

    From the coefficients ``a = [a_0, …, a_n]``, state ``[y, y', …, y⁽ⁿ⁻¹⁾]``.

    F has ones on the superdiagonal and last row ``−a_0/a_n … −a_{n−1}/a_n``;
    ``B = L = [0, …, 0, 1/a_n]ᵀ``; ``Qc = q`` (spectral density of w); output
    ``C = [[1, 0, …, 0]]``. The coefficients ``a`` (..., n+1) are free (unconstrained)
    parameters — an ODE may be unstable or undamped — and a_n must stay non-zero; ``q`` is
    positive.

    Args:
        a: (..., n+1) coefficients ``[a_0, …, a_n]`` (free parameters; a_n non-zero).
        q: spectral density of w, positive.
        **options: ``dtype``, ``device`` (of the parameters) and ``validate_args`` (see
            :class:`~torchsde_lti.LTISDE`).

    Returns:
        Companion: F (..., n, n), B and L (..., n, 1), output ``C`` (1, n); learns a and q.
    """
    return Companion(a, q, **options)


class TransferFunction(Companion):
    r"""A proper transfer function ``G(s) = num(s) / den(s)`` in controllable canonical form.

    With ``den(s) = a_n sⁿ + … + a_0`` and ``num(s) = b_n sⁿ + … + b_0`` (``b_n = 0`` unless
    deg num = deg den), write ``num = d · den + r`` with ``d = b_n / a_n`` and deg r < n.
    The state ``x = [z, z', …, z⁽ⁿ⁻¹⁾]`` of ``den(d/dt) z = u + w`` (the :func:`companion`
    matrices: F with ones on the superdiagonal and last row ``−a_0/a_n … −a_{n−1}/a_n``,
    ``B = L = e_n / a_n``, ``Qc = q``) gives ``y = num(d/dt) z = C x + D u`` with

        C = [r_0, r_1, …, r_{n−1}]  (1, n),      D = [[d]]  (1, 1).

    State ordering: ascending derivatives. scipy's ``tf2ss`` uses the reversed order and a
    monic denominator: its state is ``a_n J x`` with J the exchange matrix (ones on the
    anti-diagonal), so ``A_scipy = J F J``, ``B_scipy = a_n J B`` (= e_1),
    ``C_scipy = C J / a_n``, ``D_scipy = D``; transfer function and responses are identical.

    The denominator coefficients ``a`` are free parameters (as in :func:`companion`);
    the numerator is a constant buffer ``numerator`` (..., n+1) in ascending powers; C and
    D are recomputed from the current ``a``.
    """

    def __init__(
        self,
        num: Sequence[float] | Tensor,
        den: Sequence[float] | Tensor,
        q: Scalar = 1.0,
        **options: Unpack[ModelOptions],
    ) -> None:
        dt_, dev = scalar_dtype_device([num, den, q], options)
        b = as_float_tensor(num, "num", dt_, dev).detach().clone()
        a = as_float_tensor(den, "den", dt_, dev).detach().clone()
        if b.dim() < 1 or a.dim() < 1:
            raise ValueError(
                f"num and den must hold polynomial coefficients (..., k), highest power first; got shapes "
                f"num {shape_str(b)}, den {shape_str(a)}"
            )
        check_finite(b, "num")
        check_finite(a, "den")
        a = _strip_leading_zeros(a)
        b = _strip_leading_zeros(b)
        if a.shape[-1] < 2:
            raise ValueError(
                f"den must have degree >= 1 (a transfer function with a state), got den of shape {shape_str(a)} "
                "after removing leading zeros"
            )
        if b.shape[-1] > a.shape[-1]:
            raise ValueError(
                f"improper transfer function: deg num = {b.shape[-1] - 1} > deg den = {a.shape[-1] - 1} "
                f"(num shape {shape_str(b)}, den shape {shape_str(a)}); a state-space model y = C x + D u needs "
                "deg num <= deg den"
            )
        n1 = a.shape[-1]
        b = nn.functional.pad(b, (n1 - b.shape[-1], 0))  # same length as den
        super().__init__(torch.flip(a, (-1,)), q, dtype=dt_, device=dev, validate_args=options.get("validate_args"))
        broadcast_batch([("num", b.shape[:-1]), ("den", a.shape[:-1])])
        self.register_buffer("numerator", torch.flip(b, (-1,)), persistent=False)  # ascending b_0..b_n
        self.position_indices = None  # the output is C x + D u, not a state component: use model.C as H

    numerator: Tensor

    def _output(self) -> tuple[Tensor, Tensor]:
        a, b = self.a, self.numerator
        d = b[..., -1:] / a[..., -1:]  # (..., 1)
        r = b[..., :-1] - d * a[..., :-1]  # (..., n) remainder of num − d·den (ascending)
        return r[..., None, :], d[..., None]

    @property
    def C(self) -> Tensor:
        """Output matrix ``[r_0 … r_{n−1}]`` (..., 1, n): pass it as the filter's H."""
        return self._output()[0]

    @property
    def D(self) -> Tensor:
        """Feedthrough ``[[b_n / a_n]]`` (..., 1, 1): pass it as the filter's D."""
        return self._output()[1]

    def extra_repr(self) -> str:
        return f"order={self.order}, num: {shape_str(self.numerator)}, a: {shape_str(self.a)}, " + self._scalar_repr(
            ["q"]
        )


def _strip_leading_zeros(coeffs: Tensor) -> Tensor:
    """Drop leading (highest-power) coefficients that are zero across the whole batch."""
    while coeffs.shape[-1] > 1 and bool((coeffs[..., 0] == 0).all()):
        coeffs = coeffs[..., 1:]
    return coeffs


def from_transfer_function(
    num: Sequence[float] | Tensor, den: Sequence[float] | Tensor, q: Scalar = 1.0, **options: Unpack[ModelOptions]
) -> TransferFunction:
    r"""State-space model of ``G(s) = num(s) / den(s)`` (coefficients highest power first, as in scipy).

    Controllable canonical (companion) form, state ``[z, z', …]``: ``ẋ = F x + B u + L w``,
    ``y = C x + D u`` with ``model.C`` (1, n) and ``model.D`` (1, 1); white noise w of
    spectral density q enters where u does (``L = B``). D ≠ 0 exactly when
    deg num = deg den; ValueError for an improper G (deg num > deg den).

    Example: ``from_transfer_function([1.0], [1.0, 3.0, 2.0])`` is ``1 / (s² + 3s + 2)``.

    Args:
        num: numerator coefficients, highest power first (deg num <= deg den).
        den: denominator coefficients, highest power first (learned, free).
        q: spectral density of the noise entering with u, positive.
        **options: ``dtype``, ``device`` (of the parameters) and ``validate_args`` (see
            :class:`~torchsde_lti.LTISDE`).

    Returns:
        TransferFunction: F (n, n), B = L (n, 1), ``C`` (1, n), ``D`` (1, 1) with n = deg den.
    """
    return TransferFunction(num, den, q, **options)
