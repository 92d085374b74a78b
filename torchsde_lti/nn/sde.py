r"""``LTISDE``: a continuous-time LTI SDE as an ``nn.Module`` with constrained, learnable matrices.

The SDE is ``dx = F x dt + B u dt + L dβ`` with β a Brownian motion of spectral density Qc.
Shapes (batch dimensions lead and broadcast): ``F (..., n, n)``, ``L (..., n, s)``,
``Qc (..., s, s)``, ``B (..., n, p)``.

Reading ``sde.F``, ``sde.L``, ``sde.Qc``, ``sde.B`` returns the current (constrained)
matrices; assigning ``sde.Qc = X`` stores a preimage through the parametrisation's
``right_inverse`` (:mod:`torch.nn.utils.parametrize`), in place, so an optimiser that holds
the raw parameters keeps working. Matrices named in ``learn`` are ``nn.Parameter``; the
others are buffers. Both move with ``.to()`` and are saved in ``state_dict`` (under
``parametrizations.<name>.original``; the floor of Qc, and of a positive scalar, under
``parametrizations.<name>.0._extra_state``).

Value checks (``validate_args``, per instance with a class default as in torch.distributions):
the constructor always checks its matrices; with ``validate_args`` every call also checks the
values it is given (dt finite and ≥ 0, …), once, at that call.

- Qc is always symmetric positive definite: ``C Cᵀ`` with a Cholesky factor C whose
  diagonal is ``softplus + floor`` (:class:`~torchsde_lti.nn.parametrizations.PositiveDefinite`).
- ``F_constraint="hurwitz"`` keeps F Hurwitz-stable for any raw values through
  ``F = (J − R) S`` (:class:`~torchsde_lti.nn.parametrizations.Hurwitz`, polynomial in its raw factors; covers every Hurwitz
  matrix). Any parametrisation module can be passed instead, e.g.
  ``IntegratorChain(order=2, dim=2, drag="hurwitz")`` to learn only the drag block of
  exact integrator chains.

Save and load with ``state_dict()`` / ``load_state_dict()`` (or ``copy.deepcopy``):
:mod:`torch.nn.utils.parametrize` does not support pickling whole parametrised modules.

Each read of a parametrised matrix re-evaluates its (small) parametrisation; inside one
computation use :meth:`LTISDE.matrices`, which reads all four once. The library never enters
``torch.nn.utils.parametrize.cached()``: its cache is one per process, shared by every thread,
so modules used from several threads at once would read each other's tensors.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from torchsde_lti.core.discretization import Discrete, discretize, resolve_method
from torchsde_lti.core.moments import propagate
from torchsde_lti.core.stationary import stationary_covariance
from torchsde_lti.core.validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_hurwitz,
    check_matrix,
    common_float_dtype,
    parse_learn,
    shape_str,
)
from torchsde_lti.nn._validate import ValidateArgs
from torchsde_lti.nn.layers import Transition
from torchsde_lti.nn.parametrizations import Hurwitz, IntegratorChain, Positive, PositiveDefinite, Unconstrained

__all__ = ["LTISDE", "SDEMatrices", "StructuredSDE"]

MATRIX_NAMES = ("F", "L", "Qc", "B")

Scalar = float | Tensor


class SDEMatrices(NamedTuple):
    """The continuous-time matrices of an SDE at the current parameter values.

    F: (..., n, n); L: (..., n, s); Qc: (..., s, s); B: (..., n, p) or None.
    """

    F: Tensor
    L: Tensor
    Qc: Tensor
    B: Tensor | None


class LTISDE(ValidateArgs, nn.Module):
    r"""Linear time-invariant SDE ``dx = F x dt + B u dt + L dβ``, ``E[dβ dβᵀ] = Qc dt``.

    Args:
        F: (..., n, n) drift. Must be Hurwitz when ``F_constraint="hurwitz"``.
        L: (..., n, s) noise gain.
        Qc: (..., s, s) spectral density, symmetric positive definite.
        B: optional (..., n, p) input matrix (zero-order hold over each step).
        learn: names among ``("F", "L", "Qc", "B")`` stored as ``nn.Parameter``; the rest
            are buffers.
        F_constraint: ``None`` (free F), ``"hurwitz"`` (every eigenvalue in the open left
            half-plane, see :class:`~torchsde_lti.nn.parametrizations.Hurwitz`) or a
            parametrisation module with ``forward``/``right_inverse`` (e.g.
            :class:`~torchsde_lti.nn.parametrizations.IntegratorChain`).
        method: default discretisation method, ``"doubling"`` (robust, default) or
            ``"matrix_exp"`` (torch.matrix_exp of Van Loan's block); see :attr:`method`.
        validate_args: check the values given to every call (dt finite and ≥ 0, m0, P0, u);
            None: the class default :attr:`default_validate_args` (True).

    Leading (batch) dimensions of the matrices may differ and broadcast (e.g. 16 different
    F's with one shared Qc); ``batch_shape`` is their broadcast.

    Subclasses (the motion models of :mod:`torchsde_lti.models`) derive the matrices from
    named scalar parameters instead; they override :meth:`matrices` and the properties.
    """

    #: Indices of position components in the state (for observation matrices), if known.
    position_indices: tuple[int, ...] | None = None

    if TYPE_CHECKING:  # registered tensors or parametrised attributes (read through nn.Module)
        F: Tensor
        L: Tensor
        Qc: Tensor
        B: Tensor | None

    def __init__(
        self,
        F: Tensor,
        L: Tensor,
        Qc: Tensor,
        B: Tensor | None = None,
        *,
        learn: Iterable[str] | str = ("F", "Qc"),
        F_constraint: str | nn.Module | None = None,
        method: str = "doubling",
        validate_args: bool | None = None,
    ) -> None:
        super().__init__()
        self.method = method
        self.validate_args = validate_args
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
                raise ValueError(
                    f"F_constraint must be None, 'hurwitz' or a parametrisation module, got {F_constraint!r}"
                )
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

    # ------------------------------------------------------------------ method
    _method: str = "doubling"

    @property
    def method(self) -> str:
        """Default discretisation method of :meth:`forward` and :meth:`propagate`:
        ``"doubling"`` or ``"matrix_exp"`` (assignable)."""
        return self._method

    @method.setter
    def method(self, value: str) -> None:
        self._method = resolve_method(value)

    # ------------------------------------------------------------------ matrices
    def matrices(self) -> SDEMatrices:
        """All four matrices, each parametrisation evaluated once (no process-wide cache:
        ``torch.nn.utils.parametrize.cached()`` is shared by every thread)."""
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
    def forward(self, dt: Tensor | float, method: str | None = None, *, series: bool = False) -> Discrete:
        """Exact discretisation ``Discrete(A, Q, G)`` over steps ``dt`` (see :func:`tl.discretize`):
        A, Q (and G) in ONE joint evaluation.

        Args:
            dt: (...) step lengths; broadcasts right-aligned against ``batch_shape``.
            method: ``"doubling"`` or ``"matrix_exp"``; default :attr:`method`.
            series: if True, ``dt`` is a time series (..., T) whose leading dims align with
                ``batch_shape`` (a length-1 time axis is inserted into the matrices), e.g.
                16 models with dt (16, T) give A (16, T, n, n).

        Returns:
            A (..., n, n), Q (..., n, n), G (..., n, p) or None.
        """
        m = self._aligned(series)
        return discretize(m.F, m.L, m.Qc, dt, B=m.B, method=method or self.method, validate_args=self.validate_args)

    def transition_matrix(self, dt: Tensor | float, *, series: bool = False) -> Tensor:
        """A = expm(F dt), (..., n, n), through the :class:`~torchsde_lti.Transition` layer."""
        return Transition(self.method, validate_args=self.validate_args)(self._aligned(series).F, dt)

    def stationary_covariance(self) -> Tensor:
        """P∞ (..., n, n) solving F P∞ + P∞ Fᵀ + L Qc Lᵀ = 0 (ValueError if F is not Hurwitz)."""
        m = self.matrices()
        return stationary_covariance(m.F, m.L, m.Qc, validate_args=self.validate_args)

    def structural_nilpotency(self) -> int | None:
        """F's nilpotency index k (F^k = 0) when the model's structure fixes it whatever the
        parameter values (an integrator chain), else None (the default: a free F may be
        trained away from nilpotent). A statement about the model: the discretisation finds a
        nilpotent F itself, on the device, from F's values."""
        return None

    def prior_covariance(
        self,
        mats: SDEMatrices | None = None,
        *,
        validate_args: bool | None = None,
        diffuse_variance: float | None = None,
    ) -> Tensor:
        """The covariance a filter starts from when it is given none: P∞ (..., n, n), the
        stationary covariance (the process has run for all past time).

        Subclasses override :meth:`_prior_covariance` (a shaped model: its steady-state start;
        composed models: their parts' own, ``diffuse_variance · I`` for a part without one).
        ``mats``: the matrices already evaluated by the caller (read once per call; they are
        valid by construction). ValueError when F is not Hurwitz (checked with
        ``validate_args``, default :attr:`validate_args`): a filter then starts from a diffuse
        prior.
        """
        if diffuse_variance is not None and not (math.isfinite(diffuse_variance) and diffuse_variance > 0):
            raise ValueError(f"diffuse_variance must be None or a finite positive variance, got {diffuse_variance!r}")
        m = self.matrices() if mats is None else mats
        return self._prior_covariance(m, self._validates(validate_args), diffuse_variance)

    def _prior_covariance(self, m: SDEMatrices, validate: bool, diffuse_variance: float | None) -> Tensor:
        """:meth:`prior_covariance` of the evaluated matrices ``m`` (``validate``: resolved)."""
        if validate:
            check_hurwitz(m.F, "F")
        return stationary_covariance(m.F, m.L, m.Qc, validate_args=False)

    def propagate(
        self,
        m0: Tensor,
        P0: Tensor,
        dt: Tensor | float,
        u: Tensor | None = None,
        method: str | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Moments after horizon dt: ``m = A m0 + G u`` (..., n), ``P = A P0 Aᵀ + Q`` (..., n, n)."""
        m = self.matrices()
        return propagate(
            m0, P0, m.F, m.L, m.Qc, dt, B=m.B, u=u, method=method or self.method, validate_args=self.validate_args
        )

    def _aligned(self, series: bool) -> SDEMatrices:
        m = self.matrices()
        if not series:
            return m
        return SDEMatrices(
            m.F.unsqueeze(-3), m.L.unsqueeze(-3), m.Qc.unsqueeze(-3), None if m.B is None else m.B.unsqueeze(-3)
        )

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
            method=self.method,
            validate_args=self.__dict__.get("_validate_args"),
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


def _derived_matrix(name: str) -> property:
    """Read-only property ``name`` of a :class:`StructuredSDE`: the matrix built from its
    scalar parameters; assigning raises an AttributeError that names those parameters."""

    def get(self: StructuredSDE) -> Tensor | None:
        return getattr(self.matrices(), name)

    def set_(self: StructuredSDE, value: Tensor) -> None:
        self._read_only(name)

    return property(get, set_, doc=f"{name}, derived from the model's scalar parameters (read-only).")


class StructuredSDE(LTISDE):
    """An :class:`LTISDE` whose matrices are derived from named scalar parameters.

    Subclasses call ``super().__init__(validate_args)`` and implement :meth:`_build`. Positive scalars
    are registered with :class:`~torchsde_lti.nn.parametrizations.Positive`; free ones as plain
    parameters. Constant structure matrices are non-persistent buffers (they follow
    ``.to()`` but are not in ``state_dict``).
    """

    def __init__(self, validate_args: bool | None = None) -> None:  # noqa: D107 — LTISDE.__init__ (free matrices) is bypassed on purpose
        nn.Module.__init__(self)
        self.validate_args = validate_args

    def _add_positive(self, name: str, value: Scalar, dtype: torch.dtype, device: torch.device | None) -> None:
        v = as_float_tensor(value, name, dtype, device).detach().clone()
        check_finite(v, name)
        if bool((v <= 0).any()):
            raise ValueError(f"{name} must be positive, got min {float(v.min()):.3g} (shape {shape_str(v)})")
        self.register_parameter(name, nn.Parameter(v))
        parametrize.register_parametrization(self, name, Positive(name=name).to(dtype=v.dtype, device=v.device))

    def _check_scalars(self, names: Sequence[str]) -> None:
        """ValueError naming the scalars whose batch shapes do not broadcast."""
        with torch.no_grad():
            broadcast_batch([(n, getattr(self, n).shape) for n in names])

    def _build(self) -> SDEMatrices:
        raise NotImplementedError

    def matrices(self) -> SDEMatrices:
        return self._build()

    def _read_only(self, name: str) -> None:
        params = [n.replace("parametrizations.", "").replace(".original", "") for n, _ in self.named_parameters()]
        cls = type(self).__name__.removeprefix("Parametrized")
        raise AttributeError(
            f"{name} of {cls} is derived from its parameters ({', '.join(params)}); "
            "set those, or use .to_free() for free matrices"
        )

    F = _derived_matrix("F")
    L = _derived_matrix("L")
    Qc = _derived_matrix("Qc")
    B = _derived_matrix("B")

    def _scalar_repr(self, names: Sequence[str]) -> str:
        out = []
        for n in names:
            v = getattr(self, n).detach()
            out.append(f"{n}={float(v):.4g}" if v.numel() == 1 else f"{n}: {shape_str(v)}")
        return ", ".join(out)
