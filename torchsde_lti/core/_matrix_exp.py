r"""The ``"matrix_exp"`` method: :func:`torch.matrix_exp` of block matrices (private).

A = expm(F dt); with B ``expm([[F, B], [0, 0]] dt) = [[A, G], [0, I]]``; with noise (Van Loan)
``expm([[F, W, B], [0, −Fᵀ, 0], [0, 0, 0]] dt) = [[A, X, G], [0, A⁻ᵀ, 0], [0, 0, I]]``,
``Q = X Aᵀ``. The ``−Fᵀ`` block makes Q a cancellation whose error grows like
``‖e^{F dt}‖ ‖e^{−F dt}‖``, and torch.matrix_exp's norm-based Taylor degree can drop the
small entries of a graded Q (an integrator chain's at small dt).
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
    F, W, B, dt, batch = x.F, x.W, x.B, x.dt, x.batch
    assert dt is not None
    n = F.shape[-1]
    p = 0 if B is None else B.shape[-1]
    dt_mat = dt[..., None, None]
    if W is None and B is None:
        return torch.matrix_exp((F * dt_mat).expand(*batch, n, n)), None, None
    Fd = F * dt_mat
    top = [Fd.expand(*batch, n, n)]
    if W is not None:
        top.append((W * dt_mat).expand(*batch, n, n))
    if B is not None:
        top.append((B * dt_mat).expand(*batch, n, p))
    rows = [torch.cat(top, -1)] if len(top) > 1 else top
    if W is not None:  # [0, −Fᵀ dt, 0]
        zero = Fd.new_zeros(())
        blocks = [zero.expand(*batch, n, n), -rows[0][..., :n].mT]
        rows.append(torch.cat(blocks + ([zero.expand(*batch, n, p)] if B is not None else []), -1))
    if B is not None:  # [0, 0, 0]
        rows.append(Fd.new_zeros(()).expand(*batch, p, rows[0].shape[-1]))
    E = torch.matrix_exp(torch.cat(rows, -2))
    A = E[..., :n, :n]
    Q = None if W is None else E[..., :n, n : 2 * n] @ A.mT
    G = None if B is None else E[..., :n, n + (0 if W is None else n) :]
    return A, None if Q is None else sym(Q), G
