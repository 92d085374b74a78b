r"""What the doubling paths share (private).

After the sub-step series (``_doubling`` per-term Horner, ``_block`` Van Loan block), every
element i is doubled s_i times: ``Q ← A Q Aᵀ + Q``, ``G ← A G + G``, ``A ← A A``, on tensors
sorted by s_i so that step j only touches a prefix (:func:`_doubling_steps`). Also here: the
two layouts (:class:`_Layout`), the scales (:func:`_frobenius_norm`,
:func:`_operator_norm_bound`), the truncation rule (:func:`_truncation_order`), the sort and
its inverse (:class:`_Permutation`, :func:`_doubling_order`, the ``_unsort_*`` helpers).
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch
from torch import Tensor

from torchsde_lti.core.linalg import _plain_ops_required, bl_matmul
from torchsde_lti.core.validation import tracing


def _operator_norm_bound(F: Tensor) -> Tensor:
    """max(‖F‖₁, ‖F‖∞): bounds ‖F‖ and ‖𝓛‖/2 in the induced 1-norm. Shape (...)."""
    absF = F.abs()
    return torch.maximum(absF.sum(-2).amax(-1), absF.sum(-1).amax(-1))


@lru_cache(maxsize=None)
def _truncation_order(dtype: torch.dtype, bound: float) -> int:
    """Smallest m ≥ 1 with bound^m / (m+1)! < eps/8: where a Taylor series in an operator of
    norm ≤ ``bound`` can stop (its remainder below eps/8 relative to the leading term)."""
    eps = torch.finfo(dtype).eps
    m = 1
    while bound**m / math.factorial(m + 1) >= eps / 8.0:
        m += 1
    return m


def _frobenius_norm(F: Tensor) -> Tensor:
    """‖F‖_F (submultiplicative, ≥ ‖F‖₂; bounds ‖𝓛‖/2 in the Frobenius norm): the per-element
    paths' scale, one contiguous reduction per element (measured 7–16× faster than
    :func:`_operator_norm_bound` on 1e4 small matrices, ``profile_small_calls.py`` section 6).
    Where the squares overflow (entries beyond ≈ 1e19 in float32, 1e154 in float64) it is
    recomputed scaled by the largest entry. F (..., r, c) -> (...)."""
    flat = F.reshape(*F.shape[:-2], F.shape[-2] * F.shape[-1])
    norm = torch.linalg.vector_norm(flat, dim=-1)
    overflow = torch.isinf(norm)
    if tracing() or bool(overflow.any()):
        top = flat.abs().amax(-1).clamp_min(torch.finfo(F.dtype).tiny)
        norm = torch.where(overflow, top * torch.linalg.vector_norm(flat / top[..., None], dim=-1), norm)
    return norm


def _finite_or_max(x: Tensor) -> Tensor:
    """x with NaN → 0 and +inf → the largest float: ‖F‖ dt beyond the float range (finite
    F and dt) still takes the most halvings (A → 0, Q → P∞ for stable F) instead of none."""
    return torch.nan_to_num(x, nan=0.0, posinf=torch.finfo(x.dtype).max)


def _halvings_for(x: Tensor, theta: float) -> Tensor:
    """ceil(log2(x / θ)), at least 0, for x = ‖F‖ dt ≥ 0 (float; finite up to the largest float:
    the division is taken as a difference of logarithms so it cannot overflow)."""
    return torch.ceil(torch.log2(x.clamp_min(theta)) - math.log2(theta))


class _Layout:
    """Batch layout of the doubling/Horner loops: batch-last (r, c, N), whose products are
    fused multiply-adds over the contiguous batch (:func:`bl_matmul`; small n, large N), or
    batch-first (N, r, c), whose products are one ``bmm`` (measured faster for n ≥ 8 or a
    small batch). Every method is the same operation in either layout."""

    def __init__(self, batch_first: bool) -> None:
        self.batch_first = batch_first
        self.dim = 0 if batch_first else -1

    def mm(self, a: Tensor, b: Tensor, c: Tensor | None = None, alpha: float = 1.0) -> Tensor:
        """c + α a b."""
        if self.batch_first:
            if c is not None and c.dim() == 3:
                return torch.baddbmm(c, a, b, alpha=alpha)
            out = a @ b
            if c is None:
                return out if alpha == 1.0 else out * alpha
            return torch.add(c, out, alpha=alpha)
        return bl_matmul(a, b, c, alpha)

    def t(self, x: Tensor) -> Tensor:
        return x.mT if self.batch_first else x.transpose(0, 1)

    def size(self, x: Tensor) -> int:
        return x.shape[self.dim]

    def head(self, x: Tensor, c: int) -> Tensor:
        return self.part(x, 0, c)

    def part(self, x: Tensor, start: int, stop: int) -> Tensor:
        """Elements start … stop − 1 of the batch."""
        return x[start:stop] if self.batch_first else x[..., start:stop]

    def split(self, x: Tensor, c: int) -> tuple[Tensor, Tensor]:
        """(first c elements, the rest): two slicing views (cheaper than ``Tensor.split``)."""
        if self.batch_first:
            return x[:c], x[c:]
        return x[..., :c], x[..., c:]

    def cat(self, xs: list[Tensor]) -> Tensor:
        return torch.cat(xs, self.dim)

    def col(self, v: Tensor) -> Tensor:
        """A per-element scalar (N,) broadcast against matrices."""
        return v[:, None, None] if self.batch_first else v

    def eye(self, n: int, like: Tensor) -> Tensor:
        e = torch.eye(n, dtype=like.dtype, device=like.device)
        return e if self.batch_first else e[..., None]

    def expand_eye(self, eye: Tensor, count: int) -> Tensor:
        n = eye.shape[-1] if self.batch_first else eye.shape[0]
        return eye.expand(count, n, n) if self.batch_first else eye.expand(n, n, count)

    def norm_sq(self, A: Tensor) -> Tensor:
        """Squared Frobenius norm per element (≥ the squared spectral norm): (N,)."""
        return (A * A).sum((-2, -1) if self.batch_first else (0, 1))


_BATCH_LAST = _Layout(batch_first=False)


def _doubling_steps(
    X: Tensor, Q: Tensor | None, G: Tensor | None, counts: list[int], layout: _Layout = _BATCH_LAST
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Doubling on tensors sorted by number of halvings (descending).

    X: (n, n, N) holds E = A − I; Q: (n, n, N); G: (n, p, N) (batch-last; (N, n, ·) with a
    batch-first ``layout``). counts[j] is the number of
    elements with more than j halvings: step j doubles the first counts[j] of them
    (A ← A A, Q ← A Q Aᵀ + Q, G ← A G + G) and leaves the others final, so no work is
    spent on elements that are done. While A is near the identity X carries E
    (E ← 2E + E E keeps the digits of E that A = I + E would round away); once a doubling
    leaves ‖A‖_F < 1/2 (a decaying A, whose small entries E cannot resolve) it
    carries A itself. Returns A, Q, G in the same layout and (sorted) order.
    """
    lo = layout
    n = X.shape[1]
    eye = lo.eye(n, X)
    near: Tensor | None = None  # per-element 1 while X holds E, 0 once A; None: all hold E
    all_a = False  # every element holds A
    A = X + eye
    done: list[list[Tensor]] = [[], [], []]
    for j, c in enumerate(counts):
        if lo.size(A) > c:
            A, a_done = lo.split(A, c)
            done[0].append(a_done)
            X = lo.head(X, c)
            near = None if near is None else lo.head(near, c)
            if Q is not None:
                Q, q_done = lo.split(Q, c)
                done[1].append(q_done)
            if G is not None:
                G, g_done = lo.split(G, c)
                done[2].append(g_done)
        if j and not all_a:  # switch E -> A after the previous doubling where A has decayed
            with torch.no_grad():
                switch = lo.col(lo.norm_sq(A) < 0.25)  # ‖A‖_F < 1/2
                if near is not None:
                    switch = switch & (near > 0)
            if bool(switch.any()):
                sw = switch.to(X.dtype)
                X = torch.addcmul(X, sw, eye)  # = A in the switched elements
                near = 1.0 - sw if near is None else near * (1.0 - sw)
                if not bool(near.any()):
                    all_a, X, near = True, A, None
        if Q is not None:
            Q = lo.mm(lo.mm(A, Q), lo.t(A), Q)  # Q ← A Q Aᵀ + Q
        if G is not None:
            G = lo.mm(A, G, G)  # G ← A G + G
        if all_a:
            A = X = lo.mm(A, A)
        elif near is None:
            X = lo.mm(X, A, X)  # E ← E + E A = 2E + E E
            A = X + eye
        else:
            X = lo.mm(X, A, X * near)  # elements holding E: 2E + E E; holding A: A A
            A = torch.addcmul(X, near, eye)
    out: list[Tensor | None] = []
    for t, d in zip((A, Q, G), done):
        out.append(None if t is None else (lo.cat([t] + d[::-1]) if d else t))
    return out[0], out[1], out[2]  # type: ignore[return-value]


def _prefix_counts(sorted_values: Tensor, top: int) -> list[int]:
    """counts[j] = number of entries > j (j < top) of an int tensor."""
    tally = torch.bincount(sorted_values, minlength=top + 1)
    return (sorted_values.numel() - torch.cumsum(tally, 0))[:top].tolist()


class _Gather(torch.autograd.Function):
    """``x[index]`` along dim 0 for a permutation ``index`` whose inverse is ``inverse``. The
    backward is the gather ``g[inverse]`` (plain indexing would scatter-add); differentiable
    twice (the backward is this function again). Reverse mode only (see
    :func:`~torchsde_lti.core.linalg._plain_ops_required`)."""

    @staticmethod
    def forward(ctx, x: Tensor, index: Tensor, inverse: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(index, inverse)
        return x[index]

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor, None, None]:  # type: ignore[override]
        index, inverse = ctx.saved_tensors
        return _Gather.apply(g, inverse, index), None, None


#: From this many elements on, sorting and unsorting go through :class:`_Gather` (both
#: directions gathers); below it builtin indexing / ``index_copy_``, whose scatter costs less
#: than the Python autograd Function's dispatch there (``profile_small_calls.py`` section 8,
#: sort → batch-last → unsort of 4×4, fwd+bwd, 1 thread: gathers 123 vs 72 µs at 16
#: elements, 125 vs 112 at 256, 251 vs 289 at 1000, 2.06 vs 2.78 ms at 1e4).
_GATHER_MIN_BATCH = 1024


class _Permutation:
    """A sort of N elements: sorted position i holds element ``order[i]`` ((N,) int64); element
    e sits at sorted position ``inverse[e]`` (computed on first use)."""

    __slots__ = ("order", "_inverse")

    def __init__(self, order: Tensor) -> None:
        self.order = order
        self._inverse: Tensor | None = None

    @property
    def inverse(self) -> Tensor:
        if self._inverse is None:
            o = self.order
            positions = torch.arange(o.numel(), dtype=o.dtype, device=o.device)
            self._inverse = torch.empty_like(o).index_copy_(0, o, positions)
        return self._inverse

    def _gathers(self, x: Tensor) -> bool:
        return x.requires_grad and self.order.numel() >= _GATHER_MIN_BATCH and not _plain_ops_required()

    def sort(self, x: Tensor) -> Tensor:
        """Rows (dim 0) of x into sorted order."""
        return _Gather.apply(x, self.order, self.inverse) if self._gathers(x) else x[self.order]

    def unsort(self, x: Tensor) -> Tensor:
        """Rows (dim 0) of x, in sorted order, back to the elements' order. Many elements: a
        gather (measured 1–8× faster than ``index_copy_`` into a batch-first result from a
        batch-last source, n = 2 … 8, N = 1e4, ``profile_small_calls.py`` section 6)."""
        if self.order.numel() >= _GATHER_MIN_BATCH:
            return _Gather.apply(x, self.inverse, self.order) if self._gathers(x) else x[self.inverse]
        out = torch.empty(x.shape, dtype=x.dtype, device=x.device)
        return out.index_copy_(0, self.order, x)  # out[order[i]] = x[i]; its backward is a gather


def _doubling_order(halvings: Tensor | None, batch: torch.Size) -> tuple[_Permutation | None, list[int]]:
    """Sort (descending halvings) of the N = prod(batch) elements and ``counts``:
    counts[j] = number of elements with more than j halvings. (None, []) without doubling;
    no sort for a single element."""
    N = batch.numel()
    if halvings is None or not N:
        return None, []
    with torch.no_grad():
        flat = halvings.expand(batch).reshape(-1)
        steps = int(flat.max())
        if not steps:
            return None, []
        if N == 1:
            return None, [1] * steps
        return _Permutation(torch.argsort(flat, descending=True)), _prefix_counts(flat, steps)


def _unsort_batch_first(x: Tensor, perm: _Permutation | None, batch: torch.Size) -> Tensor:
    """Batch-last (r, c, N) whose column i belongs to element perm.order[i] -> (*batch, r, c)."""
    xb = x.permute(2, 0, 1)
    out = xb.contiguous() if perm is None else perm.unsort(xb)
    return out.reshape(*batch, *x.shape[:2])


def _unsort_batch_last(x: Tensor, perm: _Permutation | None, batch: torch.Size) -> Tensor:
    """Batch-last (r, c, N) whose column i belongs to element perm.order[i] -> (r, c, *batch)."""
    if perm is not None:  # out[..., order[i]] = x[..., i]; its backward is a gather
        x = torch.empty(x.shape, dtype=x.dtype, device=x.device).index_copy_(-1, perm.order, x)
    return x.reshape(*x.shape[:2], *batch)


def _unsort_from_batch_first(x: Tensor, perm: _Permutation | None, batch: torch.Size) -> Tensor:
    """Batch-first (N, r, c) whose row i belongs to element perm.order[i] -> (*batch, r, c)."""
    if perm is not None:
        x = perm.unsort(x)
    return x.reshape(*batch, *x.shape[1:])


def _unsort_from_batch_first_last(x: Tensor, perm: _Permutation | None, batch: torch.Size) -> Tensor:
    """Batch-first (N, r, c), sorted by ``perm`` -> contiguous (r, c, *batch)."""
    return _unsort_from_batch_first(x, perm, batch).movedim((-2, -1), (0, 1)).contiguous()
