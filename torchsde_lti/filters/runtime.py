"""What a traced filter is built for: torch's compilers (Inductor, AOTInductor), which fuse
small matrix products written as elementwise ops, or a program that runs as it is, op by op
(``ExportedProgram.module()``), where batched BLAS / LAPACK calls are fewer."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from torchsde_lti.core.validation import tracing

__all__ = ["compiler_tracing", "traced_for_eager_runtime"]

#: Whether a trace in progress is for a program that runs op by op (set by
#: :func:`traced_for_eager_runtime`; a plain flag, which torch.compile reads without a graph break).
_EAGER_RUNTIME = [False]


@contextmanager
def traced_for_eager_runtime(on: bool = True) -> Iterator[None]:
    """Trace (torch.export) a program that runs as it is, op by op (``ExportedProgram.module()``),
    not through Inductor: small products stay batched BLAS / LAPACK calls (read by
    :func:`compiler_tracing`). The sequence filters run the same algorithm either way."""
    before = _EAGER_RUNTIME[0]
    _EAGER_RUNTIME[0] = on
    try:
        yield
    finally:
        _EAGER_RUNTIME[0] = before


def compiler_tracing() -> bool:
    """Whether torch.compile or torch.export traces the call for torch's compilers (Inductor,
    AOTInductor), which fuse small products written as elementwise ops:
    tracing, and not inside :func:`traced_for_eager_runtime`."""
    return tracing() and not _EAGER_RUNTIME[0]
