"""The evaluated model of a module's online calls (private to nn/): its parametrisations run
once per parameter version while no gradient is recorded, and what the exact discretisation
of a step needs that does not depend on dt (:class:`TerminatingSeries`) is formed with them."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple, TypeVar

import torch
from torch import Tensor, nn

from torchsde_lti.core.linalg import nilpotency_index
from torchsde_lti.core.validation import as_float_tensor, shape_str, tracing
from torchsde_lti.filters import online
from torchsde_lti.filters.online import KalmanState

T = TypeVar("T")

_CACHE = "_online_model_cache"


def model_version(module: nn.Module) -> tuple[int, ...]:
    """(id, storage address, version counter) of every parameter and buffer of ``module`` and
    its submodules, flattened: changes with an optimiser step (in-place), ``.to()``, a
    load_state_dict or an assignment. (A plain walk over the module tree: ``named_modules``
    costs 5× more; it runs on every online call.)"""
    key: list[int] = []
    add = key.extend
    stack = [module]
    while stack:
        mod = stack.pop()
        for t in mod._parameters.values():
            if t is not None:
                add((id(t), t.data_ptr(), t._version))
        for b in mod._buffers.values():
            if b is not None:
                add((id(b), b.data_ptr(), b._version))
        stack.extend([m for m in mod._modules.values() if m is not None])
    return tuple(key)


def evaluated(module: nn.Module, build: Callable[[], T]) -> T:
    """``build()`` (the module's matrices from its parametrisations), cached on ``module``
    for its current parameter version when no gradient is recorded (a tracker's hot loop);
    evaluated afresh while recording gradients and while traced."""
    if torch.is_grad_enabled() or tracing():
        return build()
    key = model_version(module)
    hit = module.__dict__.get(_CACHE)
    if hit is not None and hit[0] == key:
        return hit[1]
    value = build()
    module.__dict__[_CACHE] = (key, value)
    return value


def online_state(state: object, dt: Tensor | float, F: Tensor) -> tuple[KalmanState, Tensor]:
    """(state, dt) of a KalmanFilter's online call as tensors of F's dtype and device, shapes
    checked: state a (mean (..., n), cov (..., n, n)) pair, n = F's; TypeError or ValueError."""
    dtype, device, n = F.dtype, F.device, F.shape[-1]
    if not isinstance(state, tuple) or len(state) != 2:
        raise TypeError(f"state must be a KalmanState (mean, cov), got {type(state).__name__}")
    mean = as_float_tensor(state[0], "state.mean", dtype, device)
    cov = as_float_tensor(state[1], "state.cov", dtype, device)
    if mean.dim() < 1 or mean.shape[-1] != n or cov.dim() < 2 or cov.shape[-2:] != (n, n):
        raise ValueError(
            f"state must be (mean (..., {n}), cov (..., {n}, {n})), got mean {shape_str(mean)}, cov {shape_str(cov)}"
        )
    return KalmanState(mean, cov), as_float_tensor(dt, "dt", dtype, device)


class TerminatingSeries(NamedTuple):
    r"""The exact discretisation over any dt of ONE parameter set whose F is nilpotent (an
    integrator chain: constant velocity, acceleration, Wiener velocity), F^k = 0.

    With ν = max(‖F‖₁, ‖F‖∞) (1 if F = 0), F̃ = F/ν, 𝓛̃(X) = F̃ X + X F̃ᵀ and x = ν dt, the
    series of expm(F s) terminate (the same closed form as core's doubling takes for a
    nilpotent F at the full step)::

        A = Σ_{i<k} x^i F̃^i / i!,   Q = Σ_{1≤i<2k} x^i 𝓛̃^{i−1}(W) / (ν i!),   G = Σ_{1≤i≤k} x^i F̃^{i−1} B / (ν i!)

    so every coefficient is a power x^i times a matrix that does not depend on dt: the
    matrices are formed once per parameter version (``coeff``) and a step costs one power and
    one product for the whole batch.

    coeff: (2k, (2n + p) n) the rows [A | Q | Gᵀ] (row-major) of each power x^i.
    exponents: (2k,) the powers i. nu: ν (0-dim). n, p: state and input dimensions (p = 0: no B).
    """

    coeff: Tensor
    exponents: Tensor
    nu: Tensor
    n: int
    p: int

    def __call__(self, dt: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """(A (..., n, n), Q (..., n, n), G (..., n, p) or None) over dt (...). Q is symmetric
        to rounding (the filters symmetrise their predicted covariances). Where an exact entry
        exceeds the float range it saturates near the largest float instead of becoming inf
        (A and G stay exact wherever they are finite).

        Layout: for at most :data:`~torchsde_lti.filters.online.SMALL_BATCH` steps (the
        online step's joint update) and while traced plain batch-first tensors; for more,
        batch-first views of batch-last storage ((2n + p), n, ...), the layout of the scalar
        updates."""
        n, rows = self.n, 2 * self.n + self.p
        x = (dt * self.nu).reshape(-1, 1)
        big = torch.finfo(x.dtype).max  # (a power beyond the float range saturates: its zero
        # coefficients, A's for i ≥ k, then give 0, not inf · 0)
        if tracing() or x.shape[0] <= online.SMALL_BATCH:
            out = (torch.pow(x, self.exponents).clamp(-big, big) @ self.coeff).view(*dt.shape, rows, n)
        else:  # the powers by products (Vandermonde rows), the result batch-last
            powers = torch.linalg.vander(x.squeeze(-1), N=self.exponents.shape[0]).clamp(-big, big)  # (N, 2k): x^i
            out = (self.coeff.mT @ powers.mT).view(rows, n, *dt.shape).movedim((0, 1), (-2, -1))
        return out[..., :n, :], out[..., n : 2 * n, :], (out[..., 2 * n :, :].mT if self.p else None)


def terminating_series(
    F: Tensor, L: Tensor, Qc: Tensor, B: Tensor | None, index: int | None = None
) -> TerminatingSeries | None:
    """:class:`TerminatingSeries` of one parameter set (F (n, n), L (n, s), Qc (s, s), B (n, p)
    or None, no batch dims) when F is nilpotent; None otherwise (a batch of parameters, or an F
    that is not nilpotent: those take core's discretisation).

    ``index``: F's nilpotency index when the model's structure fixes it (F^index = 0 whatever
    the parameter values: an integrator chain); then no value is read (no synchronisation, and
    the series may be formed inside a traced program). None: found from F's values."""
    if any(t is not None and t.dim() != 2 for t in (F, L, Qc, B)):
        return None
    k = nilpotency_index(F) if index is None else index
    if k is None:
        return None
    n, p = F.shape[-1], 0 if B is None else B.shape[-1]
    W = L @ Qc @ L.mT
    W = torch.lerp(W, W.mT, 0.5)  # exactly symmetric, as core forms it
    absF = F.abs()
    nu = torch.maximum(absF.sum(-2).amax(), absF.sum(-1).amax())
    nu = torch.where(nu > 0, nu, torch.ones_like(nu))
    Ft = F / nu
    powers = [torch.eye(n, dtype=F.dtype, device=F.device)]  # F̃^i, i < k
    for _ in range(k - 1):
        powers.append(Ft @ powers[-1])
    lyap = [W]  # 𝓛̃^j(W), j < 2k − 1 (the higher ones vanish)
    for _ in range(2 * k - 2):
        X = Ft @ lyap[-1]
        lyap.append(X + X.mT)  # exactly symmetric
    zero_n, zero_p = F.new_zeros(n, n), F.new_zeros(p, n)
    rows = []
    for i in range(2 * k):
        blocks = [
            powers[i] / math.factorial(i) if i < k else zero_n,
            lyap[i - 1] / (nu * math.factorial(i)) if i >= 1 else zero_n,
        ]
        if B is not None:
            blocks.append((powers[i - 1] @ B).mT / (nu * math.factorial(i)) if 1 <= i <= k else zero_p)
        rows.append(torch.cat(blocks).reshape(-1))
    exponents = torch.arange(2 * k, dtype=F.dtype, device=F.device)
    return TerminatingSeries(torch.stack(rows), exponents, nu, n, p)
