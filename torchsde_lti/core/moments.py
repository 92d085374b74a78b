r"""Moment propagation of an LTI SDE over a horizon: the mean ODE and the Lyapunov ODE.

``m(t) = A m0 + G u`` and ``P(t) = A P0 Aᵀ + Q`` with (A, Q, G) the exact discretisation
over t; they solve ``dm/dt = F m + B u`` and ``dP/dt = F P + P Fᵀ + L Qc Lᵀ``.
:func:`predict_moments` is the one implementation of that push used by :func:`propagate`,
the filters' forecasts and the training metrics.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsde_lti.core.discretization import discretize
from torchsde_lti.core.linalg import matvec, sym
from torchsde_lti.core.validation import (
    as_float_tensor,
    broadcast_batch,
    check_finite,
    check_matrix,
    check_symmetric_psd,
    check_vector,
    checks_values,
    shape_str,
)

__all__ = ["predict_moments", "propagate"]


def predict_moments(
    m: Tensor, P: Tensor, A: Tensor, Q: Tensor, G: Tensor | None = None, u: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """``(A m + G u, A P Aᵀ + Q)`` (symmetrised), all batch dims broadcast.

    Args:
        m: (..., n); P: (..., n, n); A, Q: (..., n, n); G: optional (..., n, p); u: (..., p).

    Returns:
        mean (..., n), covariance (..., n, n).
    """
    mean = matvec(A, m)
    if G is not None and u is not None:
        mean = mean + matvec(G, u)
    return mean, sym(A @ P @ A.mT + Q)


def propagate(
    m0: Tensor,
    P0: Tensor,
    F: Tensor,
    L: Tensor,
    Qc: Tensor,
    dt: Tensor | float,
    B: Tensor | None = None,
    u: Tensor | None = None,
    method: str = "doubling",
    *,
    validate_args: bool = True,
) -> tuple[Tensor, Tensor]:
    """Moments after a horizon dt: ``m = A m0 + G u``, ``P = A P0 Aᵀ + Q``.

    They solve dm/dt = F m + B u and the Lyapunov ODE dP/dt = F P + P Fᵀ + L Qc Lᵀ.

    Args:
        m0: (..., n) mean at the start. P0: (..., n, n) covariance at the start.
        F, L, Qc, dt, B, method, validate_args: as in :func:`~torchsde_lti.discretize`
            (``validate_args`` also checks m0, P0 and u).
        u: (..., p) input held constant over the horizon; requires B.

    Returns:
        m (..., n), P (..., n, n) symmetric, both over the broadcast batch of every argument.
    """
    if u is not None and B is None:
        raise ValueError(f"u was given (shape {shape_str(torch.as_tensor(u))}) but the SDE has no input matrix B")
    d = discretize(F, L, Qc, dt, B=B, method=method, validate_args=validate_args)
    n = d.A.shape[-1]
    m0 = as_float_tensor(m0, "m0", d.A.dtype, d.A.device)
    P0 = as_float_tensor(P0, "P0", d.A.dtype, d.A.device)
    check_vector(m0, "m0", n)
    check_matrix(P0, "P0", rows=n, cols=n)
    if checks_values(validate_args):
        check_finite(m0, "m0")
        check_symmetric_psd(P0, "P0")
    if u is not None:
        assert d.G is not None
        u = as_float_tensor(u, "u", d.A.dtype, d.A.device)
        check_vector(u, "u", d.G.shape[-1])
        if checks_values(validate_args):
            check_finite(u, "u")
    named = [("discretisation (F, L, Qc, B, dt)", d.A.shape[:-2]), ("m0", m0.shape[:-1]), ("P0", P0.shape[:-2])]
    batch = broadcast_batch(named + ([] if u is None else [("u", u.shape[:-1])]))
    m, P = predict_moments(m0, P0, d.A, d.Q, d.G, u)
    return m.expand(*batch, n), P.expand(*batch, n, n)  # (both with the whole batch)
