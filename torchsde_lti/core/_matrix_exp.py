r"""The ``"matrix_exp"`` discretisation method: :func:`torch.matrix_exp` of block matrices (private).

- transition only: ``A = expm(F dt)``;
- with B (zero-order hold): ``expm([[F, B], [0, 0]] dt) = [[A, G], [0, I]]``;
- with noise (Van Loan 1978): ``expm([[F, W, B], [0, −Fᵀ, 0], [0, 0, 0]] dt)`` has blocks
  ``[[A, X, G], [0, A⁻ᵀ, 0], [0, 0, I]]`` and ``Q = X Aᵀ`` (W = L Qc Lᵀ).

Exact in exact arithmetic and the fastest path for benign inputs. In floating point the
``−Fᵀ`` block holds ``e^{|λ| dt}`` for stable F and Q is recovered by cancellation, so it
loses accuracy (asymmetric or indefinite Q, overflow) for stiff F or large dt; the doubling
method is the robust default.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsde_lti.core.linalg import sym
from torchsde_lti.core.validation import SDEInputs

__all__ = ["matrix_exp"]


def matrix_exp(x: SDEInputs) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """(A, Q, G) of shapes (*batch, n, n), (*batch, n, n) or None, (*batch, n, p) or None.

    F: (..., n, n); W = L Qc Lᵀ: (..., n, n) or None; B: (..., n, p) or None; dt: (...),
    all broadcast to ``batch`` (the fields of ``x``). One :func:`torch.matrix_exp` of the
    smallest block that holds what is asked for: (n, n) for A alone, (n+p) with B, (2n+p) with W.
    """
    F, W, B, dt, batch = x
    n = F.shape[-1]
    p = 0 if B is None else B.shape[-1]
    dt_mat = dt[..., None, None]
    if W is None and B is None:
        return torch.matrix_exp((F * dt_mat).expand(*batch, n, n)), None, None
    w = 0 if W is None else n
    size = n + w + p
    block = F.new_zeros(*batch, size, size)
    block[..., :n, :n] = F * dt_mat
    if W is not None:
        block[..., :n, n : 2 * n] = W * dt_mat
        block[..., n : 2 * n, n : 2 * n] = -F.mT * dt_mat
    if B is not None:
        block[..., :n, n + w :] = B * dt_mat
    E = torch.matrix_exp(block)
    A = E[..., :n, :n]
    Q = None if W is None else sym(E[..., :n, n : 2 * n] @ A.mT)
    G = None if B is None else E[..., :n, n + w :]
    return A, Q, G
