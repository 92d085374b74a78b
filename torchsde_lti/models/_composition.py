r"""Composition of models: shaping filters (coloured noise), independent models side by side, and
the observation of positions."""

from __future__ import annotations

from typing import cast

import torch
from torch import Tensor, nn

from torchsde_lti.core.stationary import stationary_covariance
from torchsde_lti.core.validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_hurwitz,
    check_matrix,
    shape_str,
)
from torchsde_lti.models._common import block_diag_matrix
from torchsde_lti.nn.sde import LTISDE, SDEMatrices, StructuredSDE

__all__ = ["block_diag", "position_observation", "shaped"]


class ShapedSDE(StructuredSDE):
    """A system driven by coloured noise (see :func:`shaped`)."""

    system: LTISDE
    shaping: LTISDE
    shaping_output: Tensor

    def __init__(
        self, system: LTISDE, shaping: LTISDE, C: Tensor | None = None, *, validate_args: bool | None = None
    ) -> None:
        super().__init__(validate_args)
        for name, value in (("system", system), ("shaping", shaping)):
            if not isinstance(value, LTISDE):
                raise TypeError(f"{name} must be an LTISDE, got {type(value).__name__}")
        feedthrough = getattr(shaping, "D", None)
        if isinstance(feedthrough, Tensor) and bool((feedthrough != 0).any()):
            raise ValueError(
                f"the shaping filter must be strictly proper (D = 0): its D (shape {shape_str(feedthrough)}) "
                "would pass white noise straight into the system"
            )
        broadcast_batch([("system", system.batch_shape), ("shaping", shaping.batch_shape)])
        self.system = system
        self.shaping = shaping
        n_s, s, n_f = system.state_dim, system.noise_dim, shaping.state_dim
        dtype, device = system.dtype, system.device
        self._c_from_shaping = C is None and isinstance(getattr(shaping, "C", None), Tensor)
        if C is None:
            C = getattr(shaping, "C", None)
            if C is None:
                if n_f != s:
                    raise ValueError(
                        f"C is needed: the shaping filter has {n_f} states but the system's noise has "
                        f"{s} components (L_s shape (…, {n_s}, {s})); give C of shape ({s}, {n_f})"
                    )
                C = torch.eye(s, dtype=dtype, device=device)
            else:
                C = C.detach().clone()
        C = as_float_tensor(C, "C", dtype, device).detach().clone()
        check_matrix(C, "C", rows=s, cols=n_f)
        check_finite(C, "C")
        self.register_buffer("shaping_output", C, persistent=False)
        self.system_dim = n_s
        if system.position_indices is not None:
            self.position_indices = tuple(system.position_indices)

    def _build(self) -> SDEMatrices:
        ms, mf = self.system.matrices(), self.shaping.matrices()
        n_s, n_f = ms.F.shape[-1], mf.F.shape[-1]
        C_f = cast(Tensor, self.shaping.C) if self._c_from_shaping else self.shaping_output  # a learned C too
        coupling = ms.L @ C_f  # L_s C_f (..., n_s, n_f)
        batch = torch.broadcast_shapes(ms.F.shape[:-2], coupling.shape[:-2], mf.F.shape[:-2])
        top = torch.cat([ms.F.expand(*batch, n_s, n_s), coupling.expand(*batch, n_s, n_f)], dim=-1)
        bottom = nn.functional.pad(mf.F.expand(*batch, n_f, n_f), (n_s, 0))
        F = torch.cat([top, bottom], dim=-2)
        L = nn.functional.pad(mf.L, (0, 0, n_s, 0))  # [0; L_f]
        if ms.B is None and mf.B is None:
            B = None
        else:
            B = block_diag_matrix([m.B if m.B is not None else m.F.new_zeros(*m.F.shape[:-1], 0) for m in (ms, mf)])
        return SDEMatrices(F, L, mf.Qc, B)

    def _prior_covariance(self, m: SDEMatrices, validate: bool, diffuse_variance: float | None) -> Tensor:
        r"""Seed 003's steady-state start ``P0 = [[0, 0], [0, P∞_f]]`` (..., n, n).

        ``P∞_f`` solves ``F_f P + P F_fᵀ + L_f Qc_f L_fᵀ = 0`` at the current parameters
        (read from the augmented matrices, so a filter evaluates each parametrisation once).
        ValueError when F_f is not Hurwitz (checked with ``validate``).
        """
        n_s = self.system_dim
        F_f = m.F[..., n_s:, n_s:]
        if validate:
            check_hurwitz(F_f, "F of the shaping filter")
        P_f = stationary_covariance(F_f, m.L[..., n_s:, :], m.Qc, validate_args=False)
        return nn.functional.pad(P_f, (n_s, 0, n_s, 0))

    def extra_repr(self) -> str:
        return f"system_dim={self.system_dim}, shaping_dim={int(self.shaping_output.shape[-1])}"


def shaped(system: LTISDE, shaping: LTISDE, C: Tensor | None = None, *, validate_args: bool | None = None) -> ShapedSDE:
    r"""A system driven by coloured noise: the system plus a shaping filter driven by white noise.

    The system ``dx_s = F_s x_s dt + B_s u dt + L_s ν dt`` has its white noise ν replaced by
    the output ``ν = C_f x_f`` of the shaping filter ``dx_f = F_f x_f dt + B_f u_f dt + L_f dβ``
    (spectral density Qc_f). The augmented state ``[x_s, x_f]`` (n_s + n_f) has

        F = [[F_s, L_s C_f], [0, F_f]],   L = [[0], [L_f]],   Qc = Qc_f,
        B = diag(B_s, B_f)   (deterministic inputs of either part; None when neither has one).

    The system's own Qc is not used (its noise *is* the shaping filter's output). The parts
    stay submodules (``model.system``, ``model.shaping``), learned jointly; a C taken
    from the shaping model (its ``C`` property) is re-read at every evaluation.

    ``model.prior_covariance()`` is the steady-state start: every
    covariance entry that involves a system state is 0, the shaping-filter block is the
    shaping filter's own P∞ (white noise applied for all past time); with it the
    shaping-filter block stays at P∞ for all t. ``KalmanFilter`` starts from it by default.

    C (s, n_f) defaults to the shaping filter's ``C`` (companion, mass–spring–damper,
    transfer-function models) or the identity when dimensions match.

    Example (first-order system with a Gauss–Markov input, ``ẋ = −a x + f``,
    ``ḟ = −b f + w``): ``shaped(ornstein_uhlenbeck(a, 1.0), ornstein_uhlenbeck(b, q))``.

    Args:
        system: the driven system (its own Qc is not used).
        shaping: the shaping filter whose output drives the system.
        C: optional (s, n_f) output of the shaping filter (default: its ``C``, or the identity).
        validate_args: value checks of every call (default: the class default).

    Returns:
        ShapedSDE: state ``[x_s, x_f]`` (n_s + n_f); learns the parts' parameters.
    """
    return ShapedSDE(system, shaping, C, validate_args=validate_args)


class BlockDiagSDE(StructuredSDE):
    """Independent SDEs side by side (see :func:`block_diag`)."""

    parts: nn.ModuleList

    def __init__(self, *sdes: LTISDE, validate_args: bool | None = None) -> None:
        super().__init__(validate_args)
        if len(sdes) == 0:
            raise ValueError("sdes must contain at least one LTISDE, got none")
        for i, s in enumerate(sdes):
            if not isinstance(s, LTISDE):
                raise ValueError(f"sdes[{i}] must be an LTISDE, got {type(s).__name__}")
        broadcast_batch([(f"sdes[{i}]", s.batch_shape) for i, s in enumerate(sdes)])
        self.parts = nn.ModuleList(sdes)
        with torch.no_grad():  # which parts start from a prior of their own (F Hurwitz, or their own rule)
            self._own_prior = tuple(_has_prior(s) for s in sdes)
        dims = [s.state_dim for s in sdes]
        self._block_sizes = tuple(zip(dims, (s.noise_dim for s in sdes)))  # (n_i, s_i): the parts' blocks
        if all(s.position_indices is not None for s in sdes):
            idx: list[int] = []
            offset = 0
            for s, n in zip(sdes, dims):
                idx.extend(offset + i for i in s.position_indices)  # type: ignore[union-attr]
                offset += n
            self.position_indices = tuple(idx)

    def _build(self) -> SDEMatrices:
        mats = [s.matrices() for s in self._parts()]
        F = block_diag_matrix([m.F for m in mats])
        L = block_diag_matrix([m.L for m in mats])
        Qc = block_diag_matrix([m.Qc for m in mats])
        if all(m.B is None for m in mats):
            B = None
        else:
            B = block_diag_matrix([m.B if m.B is not None else m.F.new_zeros(*m.F.shape[:-1], 0) for m in mats])
        return SDEMatrices(F, L, Qc, B)

    def _parts(self) -> list[LTISDE]:
        return [p for p in self.parts if isinstance(p, LTISDE)]  # every part (checked at construction)

    def _prior_covariance(self, m: SDEMatrices, validate: bool, diffuse_variance: float | None) -> Tensor:
        """The parts' own priors, block diagonally (..., n, n): each part's ``prior_covariance``
        of its diagonal blocks of ``m`` (a shaped part: its steady-state start),
        ``diffuse_variance · I`` for a part without one (F not Hurwitz when the model was built;
        ValueError when ``diffuse_variance`` is None)."""
        blocks = []
        parts = self._parts()
        a = b = 0  # offsets of the part's state and noise blocks
        for i, (part, own, (n, s)) in enumerate(zip(parts, self._own_prior, self._block_sizes)):
            if own:
                block = SDEMatrices(
                    m.F[..., a : a + n, a : a + n],
                    m.L[..., a : a + n, b : b + s],
                    m.Qc[..., b : b + s, b : b + s],
                    None,
                )
                blocks.append(part.prior_covariance(block, validate_args=validate))
            elif diffuse_variance is None:
                raise ValueError(
                    f"parts[{i}] ({type(part).__name__}) has no prior covariance of its own (F not Hurwitz)"
                )
            else:
                blocks.append(diffuse_variance * torch.eye(n, dtype=m.F.dtype, device=m.F.device))
            a, b = a + n, b + s
        return block_diag_matrix(blocks)

    def extra_repr(self) -> str:
        return f"{len(self.parts)} parts"


def _has_prior(sde: LTISDE) -> bool:
    """Whether ``sde.prior_covariance()`` gives a prior (its F Hurwitz, or its own rule)."""
    try:
        sde.prior_covariance(validate_args=True)
    except ValueError:
        return False
    return True


def block_diag(*sdes: LTISDE, validate_args: bool | None = None) -> BlockDiagSDE:
    r"""Compose independent SDEs: ``F = diag(F_1, F_2, …)`` and likewise L, Qc, B.

    ``B`` is block diagonal over the parts that have an input (parts without one get a
    zero-width block); it is None when no part has an input. The parts stay submodules
    (``model.parts[i].q``), so their parameters are learned jointly.

    Args:
        *sdes: the independent parts (LTISDEs).
        validate_args: value checks of every call (default: the class default).

    Returns:
        BlockDiagSDE: F, L, Qc (and B) block diagonal; the parts stay submodules (``model.parts``).
    """
    return BlockDiagSDE(*sdes, validate_args=validate_args)


def position_observation(model: LTISDE) -> Tensor:
    """H (k, n) with a one at each position component: ``y = H x`` observes positions.

    Uses ``model.position_indices`` (set by every model of this module and by
    :func:`block_diag` of such models); dtype/device follow the model.

    Args:
        model: an LTISDE with ``position_indices`` (every model of ``tl.models``).

    Returns:
        Tensor: H (k, n), one row per position component.
    """
    idx = getattr(model, "position_indices", None)
    if idx is None:
        raise ValueError(f"model ({type(model).__name__}) does not declare position_indices; build H by hand")
    with torch.no_grad():
        F = model.matrices().F
    n = F.shape[-1]
    H = F.new_zeros(len(idx), n)
    for row, col in enumerate(idx):
        H[row, col] = 1.0
    return H
