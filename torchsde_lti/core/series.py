r"""The terminating series of a nilpotent F: the exact discretisation as a polynomial in dt.

When F^m = 0 (an integrator chain: constant velocity, constant acceleration, Wiener velocity)
the series of expm(F s) terminate. With ν = max(‖F‖₁, ‖F‖∞) (1 for F = 0), F̃ = F/ν,
𝓛̃(X) = F̃ X + X F̃ᵀ, x = ν dt and r_k = x^k / k!::

    A = Σ_{k<m} r_k F̃^k,   Q = dt Σ_{k<2m−1} r_k 𝓛̃^k(W) / (k+1),   G = dt Σ_{k<m} r_k F̃^k B / (k+1)

(exact: every omitted term is zero). The matrices F̃^k, 𝓛̃^k(W), F̃^k B do not depend on dt:
:func:`terminating_series` forms them once, and a batch of steps costs the rows r_k and one
product per result (:class:`TerminatingSeries`). With ``gradient_terms`` the series keeps the
terms whose value is zero but whose derivative with respect to F is not (2m, 3m − 1 and 2m
terms), their coefficients clamped to the float range so that an overflowing coefficient of a
zero term gives 0, not inf · 0.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

__all__ = ["TerminatingSeries", "terminating_series"]


def series_matrices(F: Tensor, X: Tensor, count: int, lyapunov: bool = False) -> Tensor:
    """F^k X, or with ``lyapunov`` 𝓛^k(X) (𝓛(X) = F X + X Fᵀ, exactly symmetric), for
    k < count: (count, n, c)."""
    terms = [X]
    for _ in range(1, count):
        FX = F @ terms[-1]
        terms.append(FX + FX.mT if lyapunov else FX)
    return torch.stack(terms)


class TerminatingSeries(NamedTuple):
    """The dt-independent matrices of a nilpotent F's exact discretisation (module docstring).

    terms: for A, Q and G (None where absent) the pair (term 0 (entries,), terms 1 … K−1
    (K − 1, entries)), flattened: A's F̃^k row-major (n² entries), Q's the upper triangle of
    𝓛̃^k(W)/(k+1) (n(n+1)/2), G's F̃^k B/(k+1) (n p). exact: how many terms of each are not
    zero in value (the rest carry a derivative only). scale: (K − 1,) ν / k for k = 1 … K − 1
    (K the most terms), so that r_k = Π_{j≤k} (dt ν / j) = x^k / k!. mirror: (n²,) the
    upper-triangle entry of each (i, j) (Q exactly symmetric). n, p: state and input dimensions.
    """

    terms: tuple[tuple[Tensor, Tensor] | None, ...]
    exact: tuple[int, int, int]
    scale: Tensor
    mirror: Tensor
    n: int
    p: int

    def __call__(self, dt: Tensor, batch_last: bool = False) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """(A, Q, G) over steps dt (...): A (..., n, n), Q (..., n, n) exactly symmetric or
        None, G (..., n, p) or None; with ``batch_last`` contiguous (n, n, ...), (n, n, ...),
        (n, p, ...). Differentiable with respect to dt and to the parameters the terms came
        from. One product per result (term 0, r_0 = 1, its bias)."""
        batch, N = dt.shape, dt.numel()
        h = dt.reshape(N, 1)
        r = torch.cumprod(h * self.scale, -1)  # (N, K − 1): r_k = x^k / k!, k ≥ 1
        out: list[Tensor | None] = []
        for i, (pair, cols) in enumerate(zip(self.terms, (self.n, self.n, self.p))):
            if pair is None:
                out.append(None)
                continue
            bias, rest = pair
            coeff, exact = (r if rest.shape[0] == r.shape[1] else r[:, : rest.shape[0]]), self.exact[i] - 1
            if coeff.shape[1] > exact:  # terms that are zero in value: no inf · 0
                big = torch.finfo(dt.dtype).max
                coeff = torch.cat([coeff[:, :exact], coeff[:, exact:].clamp(-big, big)], -1)
            if batch_last:
                res = torch.addmm(bias[:, None], rest.mT, coeff.mT)  # (entries, N)
                res = res if i == 0 else res * h.reshape(1, N)
                res = res.index_select(0, self.mirror) if i == 1 else res
                out.append(res.reshape(self.n, cols, *batch))
            else:
                res = torch.addmm(bias, coeff, rest)  # (N, entries)
                res = res if i == 0 else res * h
                res = res.index_select(1, self.mirror) if i == 1 else res
                out.append(res.reshape(*batch, self.n, cols))
        assert out[0] is not None
        return out[0], out[1], out[2]


def terminating_series(
    F: Tensor, W: Tensor | None, B: Tensor | None, index: int, gradient_terms: bool = False
) -> TerminatingSeries:
    """:class:`TerminatingSeries` of ONE parameter set: F (n, n) with F^index = 0, W = L Qc Lᵀ
    (n, n) symmetric or None, B (n, p) or None. ``gradient_terms``: also the terms whose value is
    zero but whose derivative with respect to F is not (for a gradient with respect to F)."""
    n, p = F.shape[-1], 0 if B is None else B.shape[-1]
    with torch.no_grad():  # (a scale: any positive ν gives the same exact series)
        absF = F.abs()
        nu = torch.maximum(absF.sum(-2).amax(-1), absF.sum(-1).amax(-1))
        nu = torch.where(nu > 0, nu, torch.ones_like(nu))
    exact = (index, 2 * index - 1, index)
    count = (2 * index, 3 * index - 1, 2 * index) if gradient_terms else exact
    Ft = F / nu
    k1 = torch.arange(1, max(count) + 1, dtype=F.dtype, device=F.device)[:, None, None]
    A_terms = series_matrices(Ft, torch.eye(n, dtype=F.dtype, device=F.device), count[0]).reshape(count[0], n * n)
    Q_terms = G_terms = None
    upper = [(i, j) for i in range(n) for j in range(i, n)]
    if W is not None:
        rows, cols = (torch.tensor(c, dtype=torch.int64, device=F.device) for c in zip(*upper))
        Q_terms = (series_matrices(Ft, W, count[1], lyapunov=True) / k1[: count[1]])[:, rows, cols]
    if B is not None:
        G_terms = (series_matrices(Ft, B, count[2]) / k1[: count[2]]).reshape(count[2], n * p)
    where = {ij: e for e, ij in enumerate(upper)}
    mirror = torch.tensor([where[min(i, j), max(i, j)] for i in range(n) for j in range(n)], device=F.device)
    scale = nu / k1[: max(count) - 1].reshape(-1)
    terms = tuple(None if t is None else (t[0], t[1:]) for t in (A_terms, Q_terms, G_terms))
    return TerminatingSeries(terms, exact, scale, mirror, n, p)
