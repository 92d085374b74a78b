"""What the model families share: keyword options, scalar dtype/device rules, block helpers."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn
from typing_extensions import TypedDict

from torchsde_lti.core.validation import common_float_dtype

__all__ = ["ModelOptions", "Scalar", "block_diag_matrix", "check_int", "eye_blocks", "scalar_dtype_device"]

Scalar = float | Tensor


class ModelOptions(TypedDict, total=False):
    """Keyword options of every model factory.

    dtype, device: of the parameters (default: those of the tensors given, else torch's
    default dtype and the CPU); validate_args: value checks of every call (default: the
    class default, see :class:`~torchsde_lti.LTISDE`).
    """

    dtype: torch.dtype | None
    device: torch.device | str | None
    validate_args: bool | None


def check_int(value: object, name: str, minimum: int) -> int:
    """``value`` if it is an int ≥ ``minimum`` (not a bool); ValueError naming it otherwise."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return value


def scalar_dtype_device(values: Sequence[object], options: ModelOptions) -> tuple[torch.dtype, torch.device | None]:
    """dtype and device of a model's parameters: the options' when given, else those of the
    tensors among ``values`` (promoted), else torch's default dtype and no device. TypeError
    naming an option that is not one of :class:`ModelOptions`'."""
    unknown = sorted(set(options) - set(ModelOptions.__annotations__))
    if unknown:
        raise TypeError(
            f"unknown model options {unknown}: a model factory takes {sorted(ModelOptions.__annotations__)}"
        )
    tensors = [v for v in values if isinstance(v, Tensor)]
    dtype = options.get("dtype") or common_float_dtype(*tensors)
    device = options.get("device")
    if device is not None:
        return dtype, torch.device(device)
    return dtype, tensors[0].device if tensors else None


def block_diag_matrix(blocks: Sequence[Tensor]) -> Tensor:
    """Batched block-diagonal matrix of (..., r_i, c_i) blocks (batch dims broadcast)."""
    batch = torch.broadcast_shapes(*(b.shape[:-2] for b in blocks))
    total_c = sum(b.shape[-1] for b in blocks)
    rows = []
    offset = 0
    for b in blocks:
        c = b.shape[-1]
        b = b.expand(*batch, *b.shape[-2:])
        rows.append(nn.functional.pad(b, (offset, total_c - offset - c)))
        offset += c
    return torch.cat(rows, dim=-2)


def eye_blocks(like: Tensor, dim: int, scale: Tensor) -> Tensor:
    """``scale[..., None, None] · I_dim`` (..., dim, dim) in the dtype/device of ``like``."""
    eye = torch.eye(dim, dtype=like.dtype, device=like.device)
    return scale[..., None, None] * eye
