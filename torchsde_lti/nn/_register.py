"""Registering a module's tensors as trained parameters or as buffers (private to nn/)."""

from __future__ import annotations

from torch import Tensor, nn


def register_tensor(module: nn.Module, name: str, value: Tensor, learnable: bool) -> None:
    """``value`` as ``nn.Parameter`` ``name`` when ``learnable`` (trained), else as a buffer;
    both follow ``.to()`` and are saved in ``state_dict``."""
    if learnable:
        module.register_parameter(name, nn.Parameter(value))
    else:
        module.register_buffer(name, value)
