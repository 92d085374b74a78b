r"""The ``"matrix_exp"`` method: :func:`torch.matrix_exp` of block matrices (private).

A = expm(F dt); with B ``expm([[F, B], [0, 0]] dt) = [[A, G], [0, I]]``; with noise (Van Loan)
``expm([[F, W, B], [0, −Fᵀ, 0], [0, 0, 0]] dt) = [[A, X, G], [0, A⁻ᵀ, 0], [0, 0, I]]``,
``Q = X Aᵀ``. The ``−Fᵀ`` block makes Q a cancellation whose error grows like
``‖e^{F dt}‖ ‖e^{−F dt}‖``; :func:`accurate` is the a-priori bound under which the default
method routes a call here.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsde_lti.core.thresholds import ROUTE_BOUNDS
from torchsde_lti.core.validation import SDEInputs, cholesky_succeeds

__all__ = ["accurate", "matrix_exp"]


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
        zeros = Fd.new_zeros(()).expand(*batch, n, n)
        rows.append(torch.cat([zeros, -rows[0][..., :n].mT] + ([zeros[..., :p]] if B is not None else []), -1))
    if B is not None:  # [0, 0, 0]
        rows.append(Fd.new_zeros(()).expand(*batch, p, rows[0].shape[-1]))
    E = torch.matrix_exp(torch.cat(rows, -2))
    A = E[..., :n, :n]
    Q = None if W is None else E[..., :n, n : 2 * n] @ A.mT
    G = None if B is None else E[..., :n, n + (0 if W is None else n) :]
    return A, None if Q is None else torch.lerp(Q, Q.mT, 0.5), G


def accurate(x: SDEInputs) -> bool:
    """Whether :func:`matrix_exp` is accurate for every element, by an a-priori bound (one
    synchronisation) with :data:`ROUTE_BOUNDS` (θ_F, θ_C, δ; float32 / float64 only):

    - ‖F‖_F dt ≤ θ_F: the cancellation in ``Q = X Aᵀ`` costs at most ``e^{2θ_F}`` over rounding;
    - ‖C‖_F dt ≤ θ_C, ‖C‖_F² = 2‖F‖_F² + ‖W‖_F² + ‖B‖_F²: at most a couple of squarings;
    - λ_min(W) ≥ δ ‖W‖_F: Q = W dt (1 + O(θ_F)) is well conditioned, so a normwise-accurate Q is
      accurate in every direction (a rank-deficient W gives a graded Q: stays with doubling).
    """
    F, W, B, dt, batch = x.F, x.W, x.B, x.dt, x.batch
    bounds = ROUTE_BOUNDS.get(F.dtype)
    if bounds is None or dt is None or batch.numel() == 0:
        return False
    theta_f, theta_c, delta = bounds
    if x.host is not None:
        return _accurate_values(x.host, F, W, B, dt, bounds)
    with torch.no_grad():
        f_sq = F.square().sum((-2, -1))
        c_sq = 2.0 * f_sq
        checks = [(f_sq.sqrt() * dt).amax() <= theta_f]
        for t in (W, B):
            if t is not None:
                c_sq = c_sq + t.square().sum((-2, -1))
        checks.append((c_sq.sqrt() * dt).amax() <= theta_c)
        if W is not None:
            shift = delta * W.square().sum((-2, -1)).sqrt()
            n = W.shape[-1]
            shifted = W - shift[..., None, None] * torch.eye(n, dtype=W.dtype, device=W.device)
            checks.append((torch.linalg.cholesky_ex(shifted).info == 0).all())
        return bool(torch.stack(checks).all())


def _accurate_values(
    host: dict[str, list[float]],
    F: Tensor,
    W: Tensor | None,
    B: Tensor | None,
    dt: Tensor,
    bounds: tuple[float, float, float],
) -> bool:
    """:func:`accurate` on Python floats (:attr:`SDEInputs.host`). Norms pair with their own
    element's dt where the batch shapes agree, else the largest norm with the largest step."""
    theta_f, theta_c, delta = bounds
    steps = host["dt"]
    worst = {}  # per argument: the largest ‖·‖_F² dt² over the elements, or its bound
    for name, t in (("F", F), ("W", W), ("B", B)):
        if t is None:
            continue
        size, v = t.shape[-2] * t.shape[-1], host[name]
        sq = [sum(x * x for x in v[i : i + size]) for i in range(0, len(v), size)]
        if t.shape[:-2] == dt.shape:
            worst[name] = max(q * h * h for q, h in zip(sq, steps))
        else:
            worst[name] = max(sq) * max(steps) * max(steps)
    if worst["F"] > theta_f**2 or 2.0 * worst["F"] + worst.get("W", 0.0) + worst.get("B", 0.0) > theta_c**2:
        return False
    if W is None:
        return True
    n, v = W.shape[-1], host["W"]
    matrices = (v[i : i + n * n] for i in range(0, len(v), n * n))
    return all(cholesky_succeeds(m, n, -delta * sum(x * x for x in m) ** 0.5) for m in matrices)
