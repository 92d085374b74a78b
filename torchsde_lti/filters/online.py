r"""Online Kalman filtering: one report per track at a time, each track with its own step.

A live tracker holds a :class:`KalmanState` (mean (..., n), cov (..., n, n), one entry per
live track) and, when reports arrive, calls :func:`kalman_step` with every track's own
discrete model (A, Q) over its own gap. The step is the SAME predict/update as the
sequence filter's loop (the loop's step in :mod:`~torchsde_lti.filters.sequential`: predict
``m⁻ = A m + c``, ``P⁻ = A P Aᵀ + Q``, then whitened scalar Joseph updates with the observed
components of y), so running :func:`kalman_step` over a series reproduces
:func:`~torchsde_lti.kalman_filter` to rounding. Missing reports (NaN in y, or mask False)
are pure predictions and contribute 0 to the log-likelihood.

:func:`~torchsde_lti.filters.imm_online.imm_step` is the same for the interacting multiple
model filter, with the mode probabilities in the state.

Tracks join and leave by indexing or concatenating the state (every field has the batch
leading)::

    state = state.select(keep)                      # drop tracks (bool mask or indices)
    state = KalmanState.cat([state, new_tracks])   # add tracks

:class:`KalmanStep` carries what gating and data association need: the innovation
``e = y − H m⁻``, its covariance ``S = H P⁻ Hᵀ + R`` and the step log-likelihood
``log N(e; 0, S)`` over the observed components.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsde_lti.core.linalg import cholesky, fused_matmul, matvec, solve_lower, solve_upper_t, sym, to_batch_last
from torchsde_lti.core.validation import broadcast_shapes, tracing
from torchsde_lti.filters.inputs import (
    LOG_2PI,
    mask_observation_model,
    whiten,
)
from torchsde_lti.filters.results import serializable
from torchsde_lti.filters.runtime import compiler_tracing
from torchsde_lti.filters.sequential import _joseph_step

__all__ = ["KalmanState", "KalmanStep", "kalman_predict", "kalman_step"]


@serializable
class KalmanState(NamedTuple):
    """The filter's belief about live tracks, batch leading.

    mean: (..., n) state means. cov: (..., n, n) state covariances.
    """

    mean: Tensor
    cov: Tensor

    def select(self, idx: Tensor | slice | int | Sequence[int]) -> KalmanState:
        """The tracks ``idx`` of the (first) batch dimension: a bool mask, indices or a slice."""
        return type(self)(*(t[idx] for t in self))

    @classmethod
    def cat(cls, states: Sequence[KalmanState]) -> KalmanState:
        """The tracks of several states (each with one batch dimension) in one state."""
        return cls(*(torch.cat(fields) for fields in zip(*states)))


@serializable
class KalmanStep(NamedTuple):
    """What one update saw, per track.

    pred_mean: (..., n) m⁻. pred_cov: (..., n, n) P⁻.
    innovation: (..., m) ``y − H m⁻`` (0 in unobserved components).
    innovation_cov: (..., m, m) ``S = H P⁻ Hᵀ + R`` (all components; gate with
        ``eᵀ S⁻¹ e`` on the observed ones).
    log_likelihood: (...) ``log N(y^obs; H^obs m⁻, S^obs)`` (0 for a fully missing report).
    observed: (..., m) bool, the components that entered the update.
    """

    pred_mean: Tensor
    pred_cov: Tensor
    innovation: Tensor
    innovation_cov: Tensor
    log_likelihood: Tensor
    observed: Tensor


#: Batches of at most this many tracks take the joint update with small matrix products
#: (fewest ops: what one live track costs); larger batches the sequence loop's scalar
#: updates on the batch-last layout (elementwise over the tracks, no tiny batched GEMMs).
#: Traced programs (export, compile) always take the joint update.
SMALL_BATCH = 128


#: Eager CPU steps whose (n, n) covariances of all tracks take more than CHUNKED_STEP_MIN_BYTES
#: run the scalar updates chunk by chunk along the leading batch dimension, a chunk
#: STEP_CHUNK_BYTES of covariances: the temporaries stay in the caches and in memory the
#: allocator reuses (a fresh large allocation costs a page fault every 4 KiB).
CHUNKED_STEP_MIN_BYTES = 1 << 22
STEP_CHUNK_BYTES = 1 << 20


#: Traced joint updates with n and m up to this form their matrix products as broadcast sums
#: (:func:`~torchsde_lti.core.linalg.fused_matmul`), which a compiler (AOTInductor,
#: torch.compile) fuses into its kernels instead of calling a GEMM per product; an exported
#: program run eagerly materialises the k-fold product, hence the bound. Larger: bmm.
FUSED_MAX_INNER = 4


def kalman_predict(state: KalmanState, A: Tensor, Q: Tensor, c: Tensor | None = None) -> KalmanState:
    """Prediction only: ``m⁻ = A m + c``, ``P⁻ = A P Aᵀ + Q``.

    Args:
        state: mean (..., n), cov (..., n, n).
        A: (..., n, n) transitions. Q: (..., n, n) process noise. c: optional (..., n) input term G u.

    Returns:
        :class:`KalmanState` of the predictions (batch dims broadcast).
    """
    pm = (A @ state.mean.unsqueeze(-1)).squeeze(-1)
    if c is not None:
        pm = pm + c
    pc = sym(A @ state.cov @ A.mT + Q)
    batch = broadcast_shapes(pm.shape[:-1], pc.shape[:-2])
    n = pm.shape[-1]
    return KalmanState(pm.expand(*batch, n), pc.expand(*batch, n, n))


def _batch_last(
    state: KalmanState, A: Tensor, Q: Tensor, c: Tensor | None, cb: torch.Size, mb: torch.Size
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]:
    """A, Q, P (n, n, *cb), mean and c (n, *mb): the sequence loop's batch-last layout."""
    n = A.shape[-1]
    Ab = to_batch_last(A.expand(*cb, n, n), 2)
    Qb = to_batch_last(Q.expand(*cb, n, n), 2)
    Pb = to_batch_last(state.cov.expand(*cb, n, n), 2)
    mean_b = to_batch_last(state.mean.expand(*mb, n), 1)
    cbl = None if c is None else to_batch_last(c.expand(*mb, n), 1)
    return Ab, Qb, Pb, mean_b, cbl


#: Reports with at most this many values are checked for NaN as Python floats.
_FEW_VALUES = 64


def _online_observed(y: Tensor, mask: Tensor | None) -> tuple[Tensor | None, Tensor]:
    """(obs, y0) of one report: obs (..., m) bool (None: all observed, known without a
    device sync only on the CPU), y0 = y with missing entries 0. Traced and off the CPU the
    masked path always runs (no data-dependent branch, no host sync; the same values)."""
    obs: Tensor | None = None
    if tracing() or not y.is_cpu:
        obs = ~torch.isnan(y)
    elif y.numel() <= _FEW_VALUES:  # a few reports: read on the host (one call, no reduction)
        values: list[Any] = y.tolist() if y.dim() else [y.item()]
        for _ in range(y.dim() - 1):  # nested lists, flattened
            values = [v for row in values for v in row]
        if any(v != v for v in values):
            obs = ~torch.isnan(y)
    else:
        nan = torch.isnan(y)
        if bool(nan.any()):
            obs = ~nan
    if mask is not None:
        obs = mask if obs is None else (obs & mask)
    y0 = y if obs is None else torch.where(obs, y, torch.zeros((), dtype=y.dtype, device=y.device))
    return obs, y0


def kalman_step(
    state: KalmanState,
    y: Tensor,
    A: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    c: Tensor | None = None,
    mask: Tensor | None = None,
) -> tuple[KalmanState, KalmanStep]:
    r"""One predict + update of every track (the sequence filter's step).

    Arguments are taken as checked (the modules check them once at their boundary). Float32
    steps compute in float64 and round their results once (:func:`_widens`). Up to
    :data:`SMALL_BATCH` tracks (and always when traced) the update is the joint Joseph update
    ``K = P⁻Hᵀ S⁻¹`` (one Cholesky factor of S), ``P = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ``;
    larger batches run the sequence loop's whitened scalar Joseph updates, eagerly on the CPU
    in chunks of tracks along the leading batch dimension beyond
    :data:`CHUNKED_STEP_MIN_BYTES` of covariances. All equal the sequence filter to rounding.

    Args:
        state: mean (..., n), cov (..., n, n) before the step.
        y: (..., m) reports; NaN = missing component.
        A: (..., n, n) transitions over each track's gap. Q: (..., n, n) process noise.
        H: (..., m, n) observation matrix. R: (..., m, m) noise covariance (symmetric PD).
        c: optional (..., n) input term ``G u`` of the prediction (the feedthrough ``D u``,
            if any, is subtracted from y by the caller).
        mask: optional bool (...) (whole report) or (..., m); False = not observed.

    Returns:
        (:class:`KalmanState` after the update, :class:`KalmanStep`); batch dims broadcast.
    """
    if _widens(state.cov):
        w = _widened((state, y, A, Q, H, R, c))
        return _narrowed(kalman_step(w[0], w[1], w[2], w[3], w[4], w[5], w[6], mask))
    if mask is not None and mask.dim() < y.dim():
        mask = mask.unsqueeze(-1)
    obs, y0 = _online_observed(y, mask)
    mb = broadcast_shapes(
        state.mean.shape[:-1], state.cov.shape[:-2], A.shape[:-2], Q.shape[:-2], H.shape[:-2], R.shape[:-2],
        y0.shape[:-1], *(() if c is None else (c.shape[:-1],)), *(() if obs is None else (obs.shape[:-1],)),
    )  # fmt: skip
    if tracing() or mb.numel() <= SMALL_BATCH:
        return _joint_step(state, y0, obs, A, Q, H, R, c, mb)
    rows = _rows_per_chunk(mb, A.shape[-1] ** 2 * A.element_size(), y0)
    if rows >= mb[0]:
        return _scalar_step(state, y0, obs, A, Q, H, R, c, mb)
    args = [(state.mean, 1), (state.cov, 2), (y0, 1), (obs, 1), (A, 2), (Q, 2), (H, 2), (R, 2), (c, 1)]

    def chunk(mean: Tensor, cov: Tensor, *rest: Tensor | None) -> tuple[KalmanState, KalmanStep]:
        yk, ok, Ak, Qk, Hk, Rk, ck, size = rest
        assert yk is not None and Ak is not None and Qk is not None and Hk is not None and Rk is not None
        return _scalar_step(KalmanState(mean, cov), yk, ok, Ak, Qk, Hk, Rk, ck, size)  # type: ignore[arg-type]

    new, out = _by_chunks(chunk, args, mb, rows)
    return new, out  # type: ignore[return-value]


def _widens(cov: Tensor) -> bool:
    """Whether an online step of float32 covariances ``cov`` runs in float64: a float32 update
    whose prior dwarfs R (a long gap, a precise sensor) cancels to a covariance that is not PSD
    (a Singer track with R = 1e-4: eigenvalues −100× the largest, NaN log-likelihoods), which
    float64 arithmetic and one rounding of the results avoid. Not on devices without float64."""
    return cov.dtype == torch.float32 and cov.device.type != "mps"


def _widened(args: tuple[Any, ...]) -> tuple[Any, ...]:
    """``args`` (tensors, NamedTuples of tensors, None) with float32 tensors in float64."""

    def wide(x: Any) -> Any:
        if isinstance(x, Tensor):
            return x.double() if x.dtype == torch.float32 else x
        if isinstance(x, tuple):
            return type(x)(*(wide(v) for v in x)) if hasattr(x, "_fields") else tuple(wide(v) for v in x)
        return x

    return tuple(wide(a) for a in args)


def _narrowed(out: Any) -> Any:
    """A step's results (NamedTuples of tensors) with float64 tensors rounded to float32."""
    return tuple(
        type(t)(*(v.float() if isinstance(v, Tensor) and v.dtype == torch.float64 else v for v in t)) for t in out
    )


def _rows_per_chunk(mb: torch.Size, bytes_per_track: int, like: Tensor) -> int:
    """Rows of the leading batch dimension per chunk of an online step over the batch ``mb``
    whose tracks hold ``bytes_per_track`` of covariances: all of them (one pass) while traced,
    off the CPU or up to :data:`CHUNKED_STEP_MIN_BYTES` in all, else :data:`STEP_CHUNK_BYTES`
    of covariances a chunk."""
    if not mb:
        return 1
    per_row = math.prod(mb[1:]) * bytes_per_track
    if tracing() or like.device.type != "cpu" or mb[0] * per_row <= CHUNKED_STEP_MIN_BYTES:
        return mb[0]
    return max(1, STEP_CHUNK_BYTES // per_row)


def _by_chunks(
    step: Callable[..., tuple[NamedTuple, ...]], args: Sequence[tuple[Tensor | None, int]], mb: torch.Size, rows: int
) -> tuple[NamedTuple, ...]:
    """``step`` over consecutive chunks of ``rows`` rows of the leading batch dimension, its
    results (NamedTuples of tensors with the batch leading) joined: ``args`` are
    (tensor or None, event ndim) pairs broadcast against ``mb``, passed to ``step`` chunk by
    chunk, followed by the chunk's batch shape."""
    parts = []
    for i in range(0, mb[0], rows):
        cut = slice(i, min(i + rows, mb[0]))
        size = torch.Size([cut.stop - cut.start, *mb[1:]])
        parts.append(step(*(_leading_rows(x, e, mb, cut) for x, e in args), size))
    return tuple(type(group[0])(*map(_joined_tracks, zip(*group))) for group in zip(*parts))


def _leading_rows(x: Tensor | None, event_ndim: int, mb: torch.Size, rows: slice) -> Tensor | None:
    """The rows ``rows`` of the leading batch dimension of ``x`` (..., *event) broadcast
    against ``mb``; x as it is where it broadcasts along that dimension (shared, or size 1)."""
    if x is None or x.dim() - event_ndim < len(mb) or x.shape[0] == 1:
        return x
    return x[rows]


def _joined_tracks(parts: Sequence[Tensor]) -> Tensor:
    """Chunks of tracks joined along the leading dimension, in the chunks' memory layout
    where they share one dense layout (the scalar updates' batch-last storage: the next step
    then reads it without a copy), else batch-first."""
    if len(parts) == 1:
        return parts[0]
    strides = parts[0].stride()
    order = sorted(range(len(strides)), key=lambda d: -strides[d])  # outermost first
    if all(p.permute(order).is_contiguous() for p in parts):
        joined = torch.cat([p.permute(order) for p in parts], order.index(0))
        return joined.permute([order.index(d) for d in range(len(order))])
    return torch.cat(list(parts))


def _joint_step(
    state: KalmanState,
    y0: Tensor,
    obs: Tensor | None,
    A: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    c: Tensor | None,
    mb: torch.Size,
) -> tuple[KalmanState, KalmanStep]:
    """:func:`kalman_step` with the joint update: batch flattened to one dimension b, batched
    matrix products (bmm, baddbmm: the fewest ops for a few tracks).

    With ``M = I − K H`` the Joseph form is taken as
    ``P = M P⁻ Mᵀ + K R Kᵀ = M P⁻ − (M P⁻ Hᵀ − K R) Kᵀ`` (three products after ``M P⁻``).
    Unobserved components get a zero row of H P⁻, zero innovation and a decoupled unit
    variance in S, so K has zero columns there and H, R enter the Joseph form unmasked."""
    n, m = A.shape[-1], y0.shape[-1]
    b = math.prod(mb)  # symbolic-safe (Size.numel() specialises a traced batch)
    traced = tracing()
    flat_batch = not traced and len(mb) == 1  # (b, *event) is already each output's shape

    def flat(x: Tensor, *event: int) -> Tensor:
        if x.dim() == len(event):  # shared by every track: a stride-0 view
            return x.expand(b, *event)
        if flat_batch and x.shape[0] == b:  # already (b, *event)
            return x
        return x.expand(*mb, *event).reshape(b, *event)

    compiled = compiler_tracing()  # (not a program run op by op: traced_for_eager_runtime)
    fused = compiled and max(n, m) <= FUSED_MAX_INNER  # products a compiler fuses with the elementwise ops
    mm: Callable[[Tensor, Tensor], Tensor] = fused_matmul if fused else torch.bmm
    addmm: Callable[..., Tensor] = _fused_addmm if fused else torch.baddbmm  # else: the fewest eager calls

    A3, Q3, H3, R3 = flat(A, n, n), flat(Q, n, n), flat(H, m, n), flat(R, m, m)
    Ht = H3.mT
    mean = flat(state.mean, n).unsqueeze(-1)
    pm = mm(A3, mean) if c is None else addmm(flat(c, n).unsqueeze(-1), A3, mean)  # (b, n, 1)
    pc = _sym(addmm(Q3, mm(A3, flat(state.cov, n, n)), A3.mT, beta=0.5, alpha=0.5))
    HP = mm(H3, pc)  # (b, m, n)
    S_all = _sym(addmm(R3, HP, Ht, beta=0.5, alpha=0.5))  # every component (the output)
    e = addmm(flat(y0, m).unsqueeze(-1), H3, pm, alpha=-1.0)  # (b, m, 1)
    if obs is None:
        S = S_all
        observed = torch.ones((*mb, m), dtype=torch.bool, device=y0.device)
    else:
        observed = obs.expand(*mb, m)
        o = flat(observed, m).to(y0.dtype).unsqueeze(-1)  # (b, m, 1)
        S = S_all * (o * o.mT) + torch.diag_embed(1.0 - o.squeeze(-1))
        HP = HP * o
        e = e * o
    if compiled:
        # unrolled over m (elementwise ops an AOTInductor program fuses; its calls of the
        # LAPACK kernels cost tens to hundreds of µs each through the fallback path)
        L = cholesky(S)
        W = solve_lower(L, torch.cat([HP, e], -1))  # L⁻¹ [H P⁻, e]
        Kt = solve_upper_t(L, W[..., :n])  # Kᵀ = S⁻¹ H P⁻ (b, m, n)
        K = Kt.mT
    else:
        L = torch.linalg.cholesky_ex(S)[0]
        W = torch.linalg.solve_triangular(L, torch.cat([HP, e], -1), upper=False)
        K = torch.linalg.solve_triangular(L, W[..., :n].mT, upper=False, left=False)  # K L = (L⁻¹ H P⁻)ᵀ
        Kt = K.mT
    z = W.select(-1, n)  # (b, m) the whitened innovation
    filt_mean = addmm(pm, K, e)
    MP = addmm(pc, K, HP, alpha=-1.0)  # M P⁻ = (I − K H) P⁻
    T = addmm(mm(MP, Ht), K, R3, alpha=-1.0)  # M P⁻ Hᵀ − K R  (b, n, m)
    P = _sym(addmm(MP, T, Kt, beta=0.5, alpha=-0.5))  # M P⁻ Mᵀ + K R Kᵀ
    # −log N(e; 0, S) per observed component: log L_jj + z_j²/2 + log(2π)/2 (an unobserved
    # component has L_jj = 1, z_j = 0: it adds log(2π)/2, taken off with n_obs)
    nll = torch.addcmul(torch.log(torch.diagonal(L, 0, -2, -1)), z, z, value=0.5).sum(-1)
    if obs is None:
        ll = torch.rsub(nll, -0.5 * LOG_2PI * m)
    else:
        ll = torch.add(nll, o.sum((-2, -1)), alpha=0.5 * LOG_2PI).neg_()
    if flat_batch:  # (b, n, 1) -> (b, n); matrices as they are
        return KalmanState(filt_mean.view(b, n), P), KalmanStep(pm.view(b, n), pc, e.view(b, m), S_all, ll, observed)
    vector, matrix = (*mb, n), (*mb, n, n)
    return KalmanState(filt_mean.reshape(vector), P.reshape(matrix)), KalmanStep(
        pm.reshape(vector), pc.reshape(matrix), e.reshape((*mb, m)), S_all.reshape((*mb, m, m)), ll.reshape(mb),
        observed,
    )  # fmt: skip


def _fused_addmm(c: Tensor, a: Tensor, x: Tensor, *, beta: float = 1.0, alpha: float = 1.0) -> Tensor:
    """``beta c + alpha a x`` (the signature of ``torch.baddbmm``) with
    :func:`~torchsde_lti.core.linalg.fused_matmul` for ``a x``: a (b, r, k), x (b, k, s), c (b, r, s)."""
    return c * beta + fused_matmul(a, x) * alpha


def _sym(half: Tensor) -> Tensor:
    """``X + Xᵀ`` of ``X = P / 2`` (the caller's product scaled by 1/2 with its α and β):
    ``(P + Pᵀ) / 2``, exactly symmetric, in two torch calls."""
    return half + half.mT


def _scalar_step(
    state: KalmanState,
    y0: Tensor,
    obs: Tensor | None,
    A: Tensor,
    Q: Tensor,
    H: Tensor,
    R: Tensor,
    c: Tensor | None,
    mb: torch.Size,
) -> tuple[KalmanState, KalmanStep]:
    """:func:`kalman_step` with the sequence loop's whitened scalar Joseph updates (batch-last)."""
    n, m = A.shape[-1], y0.shape[-1]
    if obs is None and H.dim() == 2 and R.dim() == 2 and len(mb) == 1:
        # one (H, R) for every track, all observed: whiten with one LAPACK factor and one
        # triangular solve of all reports at once, straight into the batch-last layout
        LR = torch.linalg.cholesky(R)
        Hw = torch.linalg.solve_triangular(LR, H, upper=False)
        yw_bl = torch.linalg.solve_triangular(LR, y0.expand(*mb, m).mT, upper=False)  # (m, B)
        log_det = torch.log(torch.diagonal(LR)).sum()
    else:
        Hw, yw, log_det = whiten(*mask_observation_model(H, R, obs), y0)
        yw_bl = to_batch_last(yw.expand(*mb, m), 1)
    cb = broadcast_shapes(state.cov.shape[:-2], A.shape[:-2], Q.shape[:-2], Hw.shape[:-2])
    cb = torch.Size([1] * (len(mb) - len(cb)) + list(cb))  # (as many dims as mb: batch-last, they align)
    # batch-last layout (event dims first, batch contiguous), as in the sequence loop
    Ab, Qb, Pb, mean_b, cbl = _batch_last(state, A, Q, c, cb, mb)
    h_rows = to_batch_last(Hw.expand(*cb, m, n), 2).unbind(0)
    y_vals = yw_bl.unbind(0)
    pm, pc, mean, P, es, ss = _joseph_step(Ab, Qb, mean_b, Pb, cbl, h_rows, y_vals, None, None)
    core = torch.zeros((), dtype=y0.dtype, device=y0.device)
    for e, s in zip(es, ss):
        core = core - 0.5 * (torch.log(s) + e * e / s)
    nd = len(mb)
    perm1 = [*range(1, 1 + nd), 0]
    perm2 = [*range(2, 2 + len(cb)), 0, 1]
    pred_mean, filt_mean = pm.permute(perm1), mean.permute(perm1)
    pred_cov, filt_cov = pc.permute(perm2).expand(*mb, n, n), P.permute(perm2).expand(*mb, n, n)
    if H.dim() == 2 and len(cb) == 1:
        # one H for every track: single matrix products on the batch-last (n, B), (n·n, B)
        innovation = y0 - (H @ pm).mT
        HH = (H[:, None, :, None] * H[None, :, None, :]).reshape(m * m, n * n)
        innovation_cov = sym((HH @ pc.reshape(n * n, -1)).reshape(m, m, -1).permute(2, 0, 1) + R)
    else:
        innovation = y0 - matvec(H, pred_mean)
        innovation_cov = sym(H @ pred_cov @ H.mT + R)
    if obs is None:
        n_obs = torch.full((), float(m), dtype=y0.dtype, device=y0.device)
        observed = torch.ones((*mb, m), dtype=torch.bool, device=y0.device)
    else:
        observed = obs.expand(*mb, m)
        innovation = innovation * observed
        n_obs = observed.to(y0.dtype).sum(-1)
    ll = core - 0.5 * n_obs * LOG_2PI - log_det  # e_j, s_j: (*batch), batch-last = batch-first
    return KalmanState(filt_mean, filt_cov), KalmanStep(
        pred_mean,
        pred_cov.expand(*mb, n, n),
        innovation.expand(*mb, m),
        innovation_cov.expand(*mb, m, m),
        ll.expand(mb),
        observed,
    )
