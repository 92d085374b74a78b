r"""``LTISDE``: a continuous-time LTI SDE as an ``nn.Module`` with constrained, learnable matrices.

The SDE is ``dx = F x dt + B u dt + L dβ`` with β a Brownian motion of spectral density Qc.
Shapes (batch dimensions lead and broadcast): ``F (..., n, n)``, ``L (..., n, s)``,
``Qc (..., s, s)``, ``B (..., n, p)``.

Reading ``sde.F``, ``sde.L``, ``sde.Qc``, ``sde.B`` returns the current (constrained)
matrices; assigning ``sde.Qc = X`` stores a preimage through the parametrisation's
``right_inverse`` (:mod:`torch.nn.utils.parametrize`), in place, so an optimiser that holds
the raw parameters keeps working. Matrices named in ``learn`` are ``nn.Parameter``; the
others are buffers. Both move with ``.to()`` and are saved in ``state_dict`` (under
``parametrizations.<name>.original``).

- Qc is always symmetric positive definite: ``C Cᵀ`` with a Cholesky factor C whose
  diagonal is ``softplus + floor`` (:class:`~torchsde_lti.parametrizations.PositiveDefinite`).
- ``F_constraint="hurwitz"`` keeps F Hurwitz-stable for any raw values through
  ``F = (J − R) P⁻¹`` (:class:`~torchsde_lti.parametrizations.Hurwitz`; covers every Hurwitz
  matrix). Any parametrisation module can be passed instead, e.g.
  ``IntegratorChain(order=2, dim=2, drag="hurwitz")`` to learn only the drag block of
  exact integrator chains.

Save and load with ``state_dict()`` / ``load_state_dict()`` (or ``copy.deepcopy``):
:mod:`torch.nn.utils.parametrize` does not support pickling whole parametrised modules.

Each read of a parametrised matrix re-evaluates its (small) parametrisation; inside one
computation use :meth:`LTISDE.matrices`, which reads all four once under
``torch.nn.utils.parametrize.cached()`` (or wrap a longer block in that context manager).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import NamedTuple

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from torchsde_lti._validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_matrix,
    common_float_dtype,
    parse_learn,
    shape_str,
)
from torchsde_lti.discretization import Discrete, discretize, propagate, transition_matrix
from torchsde_lti.parametrizations import Hurwitz, IntegratorChain, PositiveDefinite, _Parametrization
from torchsde_lti.stationary import stationary_covariance

__all__ = ["LTISDE", "SDEMatrices", "Unconstrained"]

MATRIX_NAMES = ("F", "L", "Qc", "B")


class SDEMatrices(NamedTuple):
    """The continuous-time matrices of an SDE at the current parameter values.

    F: (..., n, n); L: (..., n, s); Qc: (..., s, s); B: (..., n, p) or None.
    """

    F: Tensor
    L: Tensor
    Qc: Tensor
    B: Tensor | None


class Unconstrained(_Parametrization):
    """Identity parametrisation: ``value = raw``.

    Registered on unconstrained matrices so that ``sde.L = X`` works for Parameters and
    buffers alike (in place, casting X to the raw dtype/device, checking its shape).
    """

    def __init__(self, name: str = "value", shape_tail: tuple[int, int] | None = None) -> None:
        super().__init__()
        self.name = name
        self.shape_tail = shape_tail

    def forward(self, raw: Tensor) -> Tensor:
        return raw

    def right_inverse(self, value: object) -> Tensor:
        x = self._as_raw_tensor(value, self.name)
        if self.shape_tail is not None:
            check_matrix(x, self.name, rows=self.shape_tail[0], cols=self.shape_tail[1])
        check_finite(x, self.name)
        return x.clone()



class LTISDE(nn.Module):
    r"""Linear time-invariant SDE ``dx = F x dt + B u dt + L dβ``, ``E[dβ dβᵀ] = Qc dt``.

    Args:
        F: (..., n, n) drift. Must be Hurwitz when ``F_constraint="hurwitz"``.
        L: (..., n, s) noise gain.
        Qc: (..., s, s) spectral density, symmetric positive definite.
        B: optional (..., n, p) input matrix (zero-order hold over each step).
        learn: names among ``("F", "L", "Qc", "B")`` stored as ``nn.Parameter``; the rest
            are buffers.
        F_constraint: ``None`` (free F), ``"hurwitz"`` (every eigenvalue in the open left
            half-plane, see :class:`~torchsde_lti.parametrizations.Hurwitz`) or a
            parametrisation module with ``forward``/``right_inverse`` (e.g.
            :class:`~torchsde_lti.parametrizations.IntegratorChain`).

    Leading (batch) dimensions of the matrices may differ and broadcast (e.g. 16 different
    F's with one shared Qc); ``batch_shape`` is their broadcast.

    Subclasses (the motion models of :mod:`torchsde_lti.models`) derive the matrices from
    named scalar parameters instead; they override :meth:`matrices` and the properties.
    """

    #: Indices of position components in the state (for observation matrices), if known.
    position_indices: tuple[int, ...] | None = None

    def __init__(
        self,
        F: Tensor,
        L: Tensor,
        Qc: Tensor,
        B: Tensor | None = None,
        *,
        learn: Iterable[str] | str = ("F", "Qc"),
        F_constraint: str | nn.Module | None = None,
    ) -> None:
        super().__init__()
        names = parse_learn(learn, MATRIX_NAMES)
        if B is None and "B" in names:
            raise ValueError("learn contains 'B' but B is None")
        raw_inputs = {"F": F, "L": L, "Qc": Qc, "B": B}
        tensors = {k: v for k, v in raw_inputs.items() if isinstance(v, Tensor)}
        dtype = common_float_dtype(*tensors.values()) if tensors else torch.get_default_dtype()
        device = F.device if isinstance(F, Tensor) else None
        mats: dict[str, Tensor] = {}
        for name, value in raw_inputs.items():
            if value is not None:
                mats[name] = as_float_tensor(value, name, dtype, device).detach().clone()
        f, l_, qc = mats["F"], mats["L"], mats["Qc"]
        check_matrix(f, "F", square=True)
        n = f.shape[-1]
        check_matrix(l_, "L", rows=n)
        s = l_.shape[-1]
        check_matrix(qc, "Qc", rows=s, cols=s)
        named = [("F", f.shape[:-2]), ("L", l_.shape[:-2]), ("Qc", qc.shape[:-2])]
        if "B" in mats:
            check_matrix(mats["B"], "B", rows=n)
            named.append(("B", mats["B"].shape[:-2]))
        broadcast_batch(named)
        for name, value in mats.items():
            check_finite(value, name)

        if F_constraint is None:
            f_param: nn.Module = Unconstrained("F", (n, n))
        elif isinstance(F_constraint, str):
            if F_constraint != "hurwitz":
                raise ValueError(f"F_constraint must be None, 'hurwitz' or a parametrisation module, got {F_constraint!r}")
            f_param = Hurwitz(name="F", size=n)
        elif isinstance(F_constraint, nn.Module):
            f_param = F_constraint
            if isinstance(F_constraint, IntegratorChain):  # per-axis [x, x', ..., y, y', ...]
                self.position_indices = tuple(axis * F_constraint.order for axis in range(F_constraint.dim))
        else:
            raise ValueError(
                f"F_constraint must be None, 'hurwitz' or a parametrisation module, got {type(F_constraint).__name__}"
            )
        params: dict[str, nn.Module] = {
            "F": f_param,
            "L": Unconstrained("L", (n, s)),
            "Qc": PositiveDefinite(name="Qc", size=s),
        }
        if "B" in mats:
            params["B"] = Unconstrained("B", (n, mats["B"].shape[-1]))
        else:
            self.register_buffer("B", None)
        for name, value in mats.items():
            if name in names:
                self.register_parameter(name, nn.Parameter(value))
            else:
                self.register_buffer(name, value)
            parametrize.register_parametrization(self, name, params[name].to(dtype=value.dtype, device=value.device))

    # ------------------------------------------------------------------ matrices
    def matrices(self) -> SDEMatrices:
        """All four matrices, each parametrisation evaluated once."""
        with parametrize.cached():
            return SDEMatrices(self.F, self.L, self.Qc, self.B)

    def _shapes(self) -> SDEMatrices:
        with torch.no_grad():
            return self.matrices()

    @property
    def state_dim(self) -> int:
        """n, the state dimension."""
        return int(self._shapes().F.shape[-1])

    @property
    def noise_dim(self) -> int:
        """s, the dimension of the driving Brownian motion."""
        return int(self._shapes().L.shape[-1])

    @property
    def input_dim(self) -> int:
        """p, the input dimension (0 when B is None)."""
        B = self._shapes().B
        return 0 if B is None else int(B.shape[-1])

    @property
    def batch_shape(self) -> torch.Size:
        """Broadcast of the leading dimensions of F, L, Qc, B."""
        m = self._shapes()
        shapes = [x.shape[:-2] for x in m if x is not None]
        return torch.broadcast_shapes(*shapes)

    @property
    def dtype(self) -> torch.dtype:
        return self._shapes().F.dtype

    @property
    def device(self) -> torch.device:
        return self._shapes().F.device

    # ------------------------------------------------------------------ computations
    def forward(self, dt: Tensor | float, method: str = "doubling", *, series: bool = False) -> Discrete:
        """Exact discretisation ``Discrete(A, Q, G)`` over steps ``dt`` (see :func:`tl.discretize`).

        Args:
            dt: (...) step lengths; broadcasts right-aligned against ``batch_shape``.
            method: ``"doubling"`` or ``"van_loan"``.
            series: if True, ``dt`` is a time series (..., T) whose leading dims align with
                ``batch_shape`` (a length-1 time axis is inserted into the matrices), e.g.
                16 models with dt (16, T) give A (16, T, n, n).

        Returns:
            A (..., n, n), Q (..., n, n), G (..., n, p) or None.
        """
        m = self._aligned(series)
        return discretize(m.F, m.L, m.Qc, dt, B=m.B, method=method)

    def transition_matrix(self, dt: Tensor | float, *, series: bool = False) -> Tensor:
        """A = expm(F dt), (..., n, n)."""
        return transition_matrix(self._aligned(series).F, dt)

    def stationary_covariance(self) -> Tensor:
        """P∞ (..., n, n) solving F P∞ + P∞ Fᵀ + L Qc Lᵀ = 0 (ValueError if F is not Hurwitz)."""
        m = self.matrices()
        return stationary_covariance(m.F, m.L, m.Qc)

    def propagate(
        self,
        m0: Tensor,
        P0: Tensor,
        dt: Tensor | float,
        u: Tensor | None = None,
        method: str = "doubling",
    ) -> tuple[Tensor, Tensor]:
        """Moments after horizon dt: ``m = A m0 + G u`` (..., n), ``P = A P0 Aᵀ + Q`` (..., n, n)."""
        m = self.matrices()
        return propagate(m0, P0, m.F, m.L, m.Qc, dt, B=m.B, u=u, method=method)

    def _aligned(self, series: bool) -> SDEMatrices:
        m = self.matrices()
        if not series:
            return m
        return SDEMatrices(*(None if x is None else x.unsqueeze(-3) for x in m))

    def to_free(self, learn: Iterable[str] | str = ("F", "Qc"), F_constraint: str | nn.Module | None = None) -> LTISDE:
        """A plain :class:`LTISDE` initialised at the current matrices (detached).

        The state ordering is unchanged, so ``position_indices`` carries over (unless
        ``F_constraint`` declares its own).
        """
        m = self.matrices()
        free = LTISDE(
            m.F.detach(),
            m.L.detach(),
            m.Qc.detach(),
            None if m.B is None else m.B.detach(),
            learn=learn,
            F_constraint=F_constraint,
        )
        if free.position_indices is None and self.position_indices is not None:
            free.position_indices = tuple(self.position_indices)
        return free

    def extra_repr(self) -> str:
        m = self._shapes()
        parts = [f"F: {shape_str(m.F)}", f"L: {shape_str(m.L)}", f"Qc: {shape_str(m.Qc)}"]
        if m.B is not None:
            parts.append(f"B: {shape_str(m.B)}")
        return ", ".join(parts)
