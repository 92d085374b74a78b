r"""Scaling and doubling: the default discretisation method, one recurrence (private).

Element i (its own F, W = L Qc Lᵀ, B and dt) takes ``s_i = ⌈log₂(ν_i dt_i / θ)⌉`` halvings
(none when ``ν_i dt_i ≤ θ``; ν = max(‖F‖₁, ‖F‖∞)), sums the Taylor series of the Van Loan
integrals on the sub-step ``h_i = dt_i / 2^{s_i}`` (``M = F h``, ``𝓛(X) = F X + X Fᵀ``)::

    E_h = A_h − I = M φ₁(M),   φ₁(M) = Σ_{k<K} M^k/(k+1)!,
    Q_h = h Σ_{k<K} h^k 𝓛^k(W)/(k+1)!,   G_h = h φ₁(M) B

(Horner: plain products, so the backward is products too), then doubles ``s_i`` times::

    Q ← A Q Aᵀ + Q,   G ← A G + G,   A ← A A.

Every doubling adds PSD terms. While A is near the identity the recursion carries
``E = A − I`` (``E ← E + A E``: a slow mode is not rounded away) and switches to A once
``‖A‖_F < 1/2`` (a decayed A keeps its own relative accuracy). The doubling is masked under
torch.compile / torch.export (every element through ``max_i s_i`` doublings in torch's
``while_loop``, those that are done held); eagerly the same arithmetic runs on the elements
sorted by ``s_i``, doubling j on those with ``s_i > j`` (the read of the counts is the one read
of values; measured 1.5–1.8× faster, experiments/bench_per_element.py, bench_discretize.py).

**θ and the degree K.** ``‖𝓛‖ ≤ 2ν`` in the induced 1-norm, so the omitted terms of Q_h/h are
at most ``(2θ)^K e^{2θ}/(K+1)!`` of ‖W‖ (those of φ₁ less); K is the least degree that puts
this under the unit roundoff of the dtype, and at least 2n − 1, so that every entry of a graded
Q (an integrator chain's ``q h^{2n−1}/…``) keeps its leading term. The cost per element is
about K − 1 series steps plus ``log₂(ν dt/θ)`` doublings, of two n × n products each; halving θ
adds a doubling and removes 5, 4, 2, 2, 1 terms (float64: K = 23, 18, 14, 12, 10, 9 at θ = 1 …
1/32), so θ = 1/4 is where one more doubling stops paying for the terms it saves (float64
K = 14, float32 K = 8). The one-parameter-set specialisation (module ``series``) takes θ = 1.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from torchsde_lti.core.linalg import bl_matmul
from torchsde_lti.core.validation import SDEInputs, tracing

#: The sub-step bound ν h ≤ θ of the per-element recurrence (module docstring).
THETA = 0.25
#: The bound of the one-parameter-set series (module ``series``): its terms cost one matrix
#: product for any degree, so a larger base step saves two compositions.
THETA_SHARED = 1.0

Results = tuple[Tensor, Tensor | None, Tensor | None]
#: ``step(j, elems, shared) -> (elems, shared)``: one doubling or composition (:func:`run_steps`).
Step = Callable[[Any, list[Tensor], list[Tensor]], tuple[list[Tensor], list[Tensor]]]


@functools.cache
def series_degree(dtype: torch.dtype, n: int, theta: float = THETA) -> int:
    """K: the least degree with ``(2θ)^K e^{2θ}/(K+1)! ≤ eps/2`` of ``dtype``, at least 2n − 1."""
    eps, K = torch.finfo(dtype).eps, 1
    while (2.0 * theta) ** K * math.exp(2.0 * theta) / math.factorial(K + 1) > eps / 2.0:
        K += 1
    return max(K, 2 * n - 1)


def scale(F: Tensor) -> Tensor:
    """ν = max(‖F‖₁, ‖F‖∞) over the last two dims: (..., n, n) -> (...), without a graph."""
    with torch.no_grad():
        a = F.abs()
        return torch.maximum(a.sum(-2).amax(-1), a.sum(-1).amax(-1))


def halvings(reach: Tensor) -> Tensor:
    """s = ⌈log₂(reach / θ)⌉ ≥ 0 of reach = ν dt, int64: beyond the dtype's range that of its
    largest number (A → 0, Q → P∞ for a stable F); NaN (unchecked input) none."""
    with torch.no_grad():
        x = torch.nan_to_num(reach, nan=0.0, posinf=torch.finfo(reach.dtype).max)
        return torch.ceil(torch.log2(x.clamp_min(THETA)) - math.log2(THETA)).to(torch.int64)


def schedule(count: Tensor) -> tuple[Tensor | None, list[int] | None]:
    """(order, ends) of the step counts (N,) for :func:`run_steps`: eagerly the order that sorts
    them descending (None where every element has the same count) and, for step j, the number of elements with count > j
    (one read of values); while traced (None, None): every element masked through the most."""
    if tracing():
        return None, None
    with torch.no_grad():
        tally: list[int] = torch.bincount(count).tolist() if count.numel() else [0]
        equal = tally[-1] == count.numel()  # one count for all (a nilpotent F's 0): no order to sort into
        order = None if equal else torch.argsort(count, descending=True, stable=True)
    ends, left = [], count.numel()
    for k in tally[:-1]:
        left -= k
        ends.append(left)
    return order, ends


def run_steps(
    step: Step, count: Tensor, ends: list[int] | None, elems: list[Tensor], shared: list[Tensor]
) -> list[Tensor]:
    """``elems`` (batch-last (..., N)) after element i's ``count[i]`` steps; ``shared`` (no batch
    dim) updated at every step. Eagerly (``ends`` from :func:`schedule`, the elements sorted by
    count) step j runs on the prefix of the ``ends[j]`` elements with count > j (the others split
    off: its backward is a cat). Traced: every element through the most steps, those with
    count ≤ j held (``torch.where``), in torch's structured ``while_loop`` (differentiable under
    torch.compile; at least one iteration: an AOTInductor package gave wrong values after a loop
    of none)."""
    if ends is None:
        from torch._higher_order_ops import while_loop

        k = len(elems)

        def body(j: Tensor, *carry: Tensor) -> tuple[Tensor, ...]:
            new, sh = step(j, list(carry[:k]), list(carry[k:]))
            kept = [b.clone() if a is b else torch.where(count > j, a, b).contiguous() for a, b in zip(new, carry)]
            return (j + 1, *kept, *sh)

        start = torch.zeros((), dtype=count.dtype, device=count.device)
        most = torch.cat([count, start[None]]).max().clamp_min(1)
        out = while_loop(lambda j, *carry: j < most, body, (start, *(t.contiguous() for t in (*elems, *shared))))
        return list(out[1 : 1 + k])
    done: list[list[Tensor]] = []
    for j, end in enumerate(ends):
        if end < elems[0].shape[-1]:  # the elements with count j are done
            parts = [t.split([end, t.shape[-1] - end], -1) for t in elems]
            elems = [p[0] for p in parts]
            done.append([p[1] for p in parts])
        elems, shared = step(j, elems, shared)
    return [torch.cat([elems[i], *(d[i] for d in done[::-1])], -1) if done else elems[i] for i in range(len(elems))]


def state(E: Tensor, G: Tensor | None) -> Tensor:
    """The doubling's state ``X = [E | A | G]`` (n, 2n + p, N) of E = A − I (n, n, N) and G
    (n, p, N) or None (Q is carried apart)."""
    eye = torch.eye(E.shape[0], dtype=E.dtype, device=E.device)[..., None]
    return torch.cat([t for t in (E, E + eye, G) if t is not None], 1)


def carried(n: int, c: int, like: Tensor) -> Tensor:
    """(1, c) ones over the E and G blocks of a state ``[E | A | G]``, zeros over A: a step adds
    the E and G of the step composed (``E' = E_P + A_P E``, ``G' = G_P + A_P G``), not its A."""
    mask = torch.ones(1, c, dtype=like.dtype, device=like.device)
    mask[:, n : 2 * n] = 0.0
    return mask


def transition(X: Tensor) -> Tensor:
    """A of a state X = [E | A | G] (n, c, ...): the carried A once it has decayed
    (‖A‖_F < 1/2: it keeps its own relative accuracy), else I + E (E keeps a slow mode that the
    carried A, a product of rounded factors, loses). The products of a step use this A."""
    n = X.shape[0]
    E, A = X[:, :n], X[:, n : 2 * n]
    with torch.no_grad():
        decayed = A.square().sum((0, 1)) < 0.25
    eye = torch.eye(n, dtype=X.dtype, device=X.device).reshape(n, n, *[1] * (X.dim() - 2))
    return torch.where(decayed, A, E + eye)


def results(X: Tensor, Q: Tensor | None) -> Results:
    """(A, Q, G) of a state X = [E | A | G] (n, c, N) and Q (n, n, N) (A: :func:`transition`,
    Q made exactly symmetric)."""
    n = X.shape[0]
    G = X[:, 2 * n :] if X.shape[1] > 2 * n else None
    return transition(X), None if Q is None else 0.5 * (Q + Q.transpose(0, 1)), G


def layout(results: Results, batch: torch.Size, batch_last: bool, order: Tensor | None) -> Results:
    """Batch-last (r, c, N) results, the elements in ``order`` (None: their own) -> (*batch, r, c),
    or with ``batch_last`` contiguous (r, c, *batch)."""
    out: list[Tensor | None] = []
    inverse = None if order is None else torch.empty_like(order).scatter_(0, order, torch.arange(order.numel()))
    for t in results:
        if t is not None:
            t = t.permute(2, 0, 1)
            if inverse is not None:  # (rows of the batch-first layout: one gather)
                t = t.contiguous().index_select(0, inverse)
            t = (
                t.permute(1, 2, 0).contiguous().reshape(*t.shape[1:], *batch)
                if batch_last
                else t.reshape(*batch, *t.shape[1:])
            )
        out.append(t)
    A, Q, G = out
    assert A is not None
    return A, Q, G


def _series(F: Tensor, W: Tensor | None, B: Tensor | None, h: Tensor, K: int) -> Results:
    """(E_h, Q_h, G_h) of the module docstring by Horner on N batch-last elements: F (n, n, N),
    W (n, n, N) or None, B (n, p, N) or None, h (N,). Q_h/h as ``Z ← W + (M Z + Z Mᵀ)/(k+1)`` =
    ``T + Tᵀ`` with ``T = W/2 + M Z/(k+1)`` (exactly symmetric)."""
    M = F * h
    n = M.shape[0]
    eye = torch.eye(n, dtype=M.dtype, device=M.device)[..., None].expand_as(M)
    Y, Z = eye, W
    base = eye if W is None else torch.cat([eye, 0.5 * W], 1)
    for k in range(K - 1, 0, -1):  # [Y, T] in one product
        YT = bl_matmul(M, Y if Z is None else torch.cat([Y, Z], 1), base, 1.0 / (k + 1))
        Y = YT[:, :n]
        Z = None if Z is None else YT[:, n:] + YT[:, n:].transpose(0, 1)
    return bl_matmul(M, Y), None if Z is None else Z * h, None if B is None else bl_matmul(Y, B) * h


def per_element_doubling(x: SDEInputs, batch_last: bool = False) -> Results:
    """(A, Q, G) when every element has its own F, W, B and dt (the general algorithm): F
    (..., n, n), W (..., n, n) or None, B (..., n, p) or None, dt (...), broadcast to ``x.batch``
    -> (*batch, n, n), (*batch, n, n) or None, (*batch, n, p) or None (with ``batch_last``
    contiguous (n, n, *batch), …)."""
    assert x.dt is not None
    F, W, B = (
        None if t is None else t.expand(*x.batch, *t.shape[-2:]).reshape(-1, *t.shape[-2:]) for t in (x.F, x.W, x.B)
    )
    assert F is not None
    dt = x.dt.expand(x.batch).reshape(-1)
    s = halvings(scale(F) * dt)
    order, ends = schedule(s)
    if order is not None:  # (contiguous rows: the inputs are sorted, not the states)
        F, W, B = (None if t is None else t.index_select(0, order) for t in (F, W, B))
        dt, s = dt.index_select(0, order), s.index_select(0, order)
    F, W, B = (None if t is None else t.permute(1, 2, 0).contiguous() for t in (F, W, B))
    assert F is not None
    n = F.shape[0]
    E, Q, G = _series(F, W, B, dt * torch.exp2(-s.to(dt.dtype)), series_degree(F.dtype, n))
    X = state(E, G)
    mask = carried(n, X.shape[1], X)[..., None]

    def step(j: Any, elems: list[Tensor], shared: list[Tensor]) -> tuple[list[Tensor], list[Tensor]]:
        """A doubling: ``Q ← A Q Aᵀ + Q``, ``[E, A, G] ← [E + A E, A A, G + A G]``."""
        X, *Q = elems
        A = transition(X)
        X = torch.addcmul(bl_matmul(A, X), X, mask)
        return [X, *(bl_matmul(bl_matmul(A, q), A.transpose(0, 1), q) for q in Q)], shared

    X, *Qs = run_steps(step, s, ends, [X, *([] if Q is None else [Q])], [])
    return layout(results(X, Qs[0] if Qs else None), x.batch, batch_last, order)
