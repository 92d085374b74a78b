"""The arguments of the IMM filter (:func:`~torchsde_lti.filters.imm.imm_filter`), checked:
shapes always (the mode axis M after the time axis T, batches broadcasting), values on request."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsde_lti.core.validation import (
    broadcast_batch,
    check_finite,
    check_matrix,
    check_no_inf,
    check_symmetric_psd,
    checks_values,
    shape_str,
)
from torchsde_lti.filters.inputs import as_float_tensors, check_mask

__all__ = ["check_imm_inputs"]


def check_imm_inputs(
    y: Tensor,
    A: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    Pi: Tensor,
    m0: Tensor,
    P0: Tensor,
    mode_prob0: Tensor,
    mask: Tensor | None,
    validate_args: bool = True,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor | None]:
    """The arguments of :func:`~torchsde_lti.filters.imm.imm_filter` as float tensors of one dtype
    and device, their shapes checked (and, ``validate_args``, their values: y without Inf;
    finite A, H, Pi, m0, mode_prob0; symmetric PSD Q, R, P0; stochastic Pi and mode_prob0);
    ValueError naming the argument otherwise. Returns (y, A, Q, H, R, Pi, m0, P0, mode_prob0, mask)."""
    t = as_float_tensors(y=y, A=A, Q=Q, H=H, R=R, Pi=Pi, m0=m0, P0=P0, mode_prob0=mode_prob0)
    checked = [t[k] for k in ("y", "A", "Q", "H", "R", "Pi", "m0", "P0", "mode_prob0")]
    assert all(x is not None for x in checked)
    y, A, Q, H, R, Pi, m0, P0, mode_prob0 = checked  # type: ignore[assignment]
    dtype, device = y.dtype, y.device
    if y.dim() < 2 or y.shape[-2] < 1 or y.shape[-1] < 1:
        raise ValueError(f"y must have shape (..., T, m) with T, m >= 1, got shape {shape_str(y)}")
    T, m = y.shape[-2], y.shape[-1]
    if mode_prob0.dim() < 1:
        raise ValueError(f"mode_prob0 must have shape (..., M), got shape {shape_str(mode_prob0)}")
    M = mode_prob0.shape[-1]
    check_matrix(A, "A", square=True)
    n = A.shape[-1]
    for name, x, r, c in (("A", A, n, n), ("Q", Q, n, n), ("H", H, m, n), ("R", R, m, m), ("P0", P0, n, n)):
        check_matrix(x, name, rows=r, cols=c)
        if x.dim() >= 3 and x.shape[-3] not in (1, M):
            raise ValueError(
                f"{name} must have its mode axis (dim -3) of size 1 or M={M} "
                f"(mode_prob0 {shape_str(mode_prob0)}), got shape {shape_str(x)}"
            )
    for name, x in (("A", A), ("Q", Q), ("H", H), ("R", R)):
        if x.dim() >= 4 and x.shape[-4] not in (1, T):
            raise ValueError(
                f"{name} must have its time axis (dim -4) of size 1 or T={T} "
                f"(y {shape_str(y)}), got shape {shape_str(x)}"
            )
    if Pi.dim() < 2 or Pi.shape[-2:] != (M, M):
        raise ValueError(
            f"Pi must have shape (..., T, {M}, {M}) to match mode_prob0 {shape_str(mode_prob0)}, "
            f"got shape {shape_str(Pi)}"
        )
    if Pi.dim() >= 3 and Pi.shape[-3] not in (1, T):
        raise ValueError(f"Pi must have its time axis (dim -3) of size 1 or T={T}, got shape {shape_str(Pi)}")
    if m0.dim() < 1 or m0.shape[-1] != n or (m0.dim() >= 2 and m0.shape[-2] not in (1, M)):
        raise ValueError(f"m0 must have shape (..., {M}, {n}) or (..., 1, {n}) or ({n},), got shape {shape_str(m0)}")
    mask = check_mask(mask, T, m, device, y.dim())
    named = [("y", y.shape[:-2]), ("Pi", Pi.shape[:-3]), ("m0", m0.shape[:-2]), ("P0", P0.shape[:-3])]
    named += [(k, x.shape[:-4]) for k, x in (("A", A), ("Q", Q), ("H", H), ("R", R))]
    named += [("mode_prob0", mode_prob0.shape[:-1]), *([] if mask is None else [("mask", mask.shape[:-2])])]
    broadcast_batch(named)
    if checks_values(validate_args):
        check_no_inf(y, "y")
        for name, x in (("A", A), ("H", H), ("Pi", Pi), ("m0", m0), ("mode_prob0", mode_prob0)):
            check_finite(x, name)
        for name, x in (("Q", Q), ("R", R), ("P0", P0)):
            check_symmetric_psd(x, name)
        if bool((Pi < 0).any()) or bool(((Pi.sum(-1) - 1).abs() > 1e3 * torch.finfo(dtype).eps * M).any()):
            raise ValueError(f"Pi must be row-stochastic (entries >= 0, rows summing to 1), shape {shape_str(Pi)}")
        if bool((mode_prob0 < 0).any()) or bool(
            ((mode_prob0.sum(-1) - 1).abs() > 1e3 * torch.finfo(dtype).eps * M).any()
        ):
            raise ValueError(
                f"mode_prob0 must be a probability vector over the last axis, shape {shape_str(mode_prob0)}"
            )
    return y, A, Q, H, R, Pi, m0, P0, mode_prob0, mask
