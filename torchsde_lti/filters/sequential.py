r"""The sequential Kalman filter (Joseph form, whitened scalar updates), O(T) depth.

On the per-step discrete model (see :mod:`torchsde_lti.filters` for the conventions)::

    x_k = A_k x_{k-1} + G_k u_k + q_k,    q_k ~ N(0, Q_k),     x_{-1} ~ N(m0, P0)
    y_k = H_k x_k + r_k,                  r_k ~ N(0, R_k),     k = 0 … T-1

Each step's noise is whitened with the Cholesky factor of the (masked) R_k (input
preparation, :mod:`~torchsde_lti.filters.inputs`), so R' = I, and the m scalar observations
are processed one after the other (Bierman's sequential processing: equal to the joint
update). Each scalar update uses the Joseph form ``P⁺ = (I − k hᵀ) P (I − k hᵀ)ᵀ + k kᵀ``;
P is symmetrised once per step. No matrix is inverted; there is no Cholesky in the loop.

The covariance recursion depends on (A, Q, H, R, mask, P0) only, never on y, so it runs at
the batch shape of those: with a shared dt grid and no missing data it runs once for all
tracks. Inside the loop tensors are laid out batch-last, ``(n, n, *batch)``, so elementwise
work runs over the contiguous batch (:mod:`torchsde_lti.core.linalg`); the returned tensors
are (possibly non-contiguous) views in the documented batch-first shapes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from torchsde_lti.core.linalg import bl_matmul, bl_matvec, bl_sym_into, from_batch_last, to_batch_last
from torchsde_lti.filters.inputs import PreparedInputs, assemble_result, complete_from_filtered
from torchsde_lti.filters.results import FilterResult

__all__ = ["CHUNKED_MIN_BYTES", "CHUNK_BYTES", "sequential_filter", "structured_filtered"]

#: Eager CPU filters at one intra-op thread whose per-track covariances (tracks · n² entries)
#: take CHUNKED_MIN_BYTES or more run the loop chunk by chunk of tracks along the leading
#: batch dimension, a chunk CHUNK_BYTES of covariances: each step's batch-last temporaries then
#: stay in the caches, which a loop over all tracks at once streams through memory every
#: operation (``python experiments/filter_chunks.py``).
CHUNKED_MIN_BYTES = 1 << 23
CHUNK_BYTES = 1 << 20

#: Event dimensions of the fields of :class:`~torchsde_lti.filters.inputs.PreparedInputs`
#: (the dimensions after the batch).
_EVENT_DIMS = {
    "A": 3, "Q": 3, "Hw": 3, "yw": 2, "c": 2, "m0": 1, "P0": 2, "H": 3, "R": 3, "y0": 2, "obs": 2, "log_det_chol_R": 1,
}  # fmt: skip


def sequential_filter(prep: PreparedInputs, structured: bool = False) -> FilterResult:
    r"""The sequential loop on prepared inputs (what :func:`~torchsde_lti.filters.kalman_filter`
    runs by default): step k predicts ``m⁻ = A_k m + G_k u_k``, ``P⁻ = A_k P A_kᵀ + Q_k``, then
    updates with the observed components of y_k (whitened scalar updates in Joseph form).

    ``structured``: run the loop as torch's structured scan (``torch._higher_order_ops.scan``)
    through its own ``torch.compile``: one step's graph is compiled (once), the T steps are not
    unrolled; inside a caller's ``torch.compile`` trace the loop is a graph break (inductor
    cannot yet lower the scan inside a larger graph). What ``torch.compile(kf)`` uses. The
    loop then yields the filtered moments alone, the rest is formed batched over the steps
    (:func:`~torchsde_lti.filters.inputs.complete_from_filtered`).
    """
    if structured:
        return complete_from_filtered(prep, *structured_filtered(prep))
    rows = _chunk_rows(prep)
    pm_bl, pc_bl, fm_bl, fc_bl, e_t, s_t = _loop(prep) if rows is None else _chunked_loop(prep, rows)
    m_dim, nd = prep.yw.shape[-1], len(prep.mean_batch)
    # Innovations and their covariances, batched over all steps in the same layout.
    H_bl = to_batch_last(prep.H, 2, time=True)  # (T or 1, m, n, *)
    R_bl = to_batch_last(prep.R, 2, time=True)
    y0_bl = to_batch_last(prep.y0, 1, time=True)
    n = pm_bl.shape[1]
    if H_bl.shape[0] == 1 and all(d == 1 for d in H_bl.shape[3:]):
        # One H for every step and track: contract with a single matrix product (BLAS) on
        # the flattened (T, n·n, batch) covariances.
        Hm = H_bl.reshape(H_bl.shape[1:3])  # (m, n)
        bshape = pc_bl.shape[3:]
        mshape = pm_bl.shape[2:]  # explicit sizes below: -1 is ambiguous for an empty batch
        innov = y0_bl - (Hm @ pm_bl.reshape(prep.T, n, math.prod(mshape))).reshape(prep.T, m_dim, *mshape)
        HH = (Hm[:, None, :, None] * Hm[None, :, None, :]).reshape(m_dim * m_dim, n * n)  # (m², n²)
        S = (HH @ pc_bl.reshape(prep.T, n * n, math.prod(bshape))).reshape(prep.T, m_dim, m_dim, *bshape) + R_bl
    else:
        # (accumulated over the contracted index: no (T, m, n, n, *batch) intermediate)
        innov = y0_bl
        HP = None
        for j in range(n):
            innov = innov - H_bl[:, :, j] * pm_bl[:, j : j + 1]
            term = H_bl[:, :, j : j + 1] * pc_bl[:, j : j + 1]  # (T, m, n, *)
            HP = term if HP is None else HP + term
        assert HP is not None
        S = R_bl
        for j in range(n):
            S = S + HP[:, :, j : j + 1] * H_bl[:, :, j].unsqueeze(1)  # (T, m, m, *)
    S = 0.5 * (S + S.transpose(1, 2))
    mean_t = from_batch_last(fm_bl, 1, nd)
    cov_t = from_batch_last(fc_bl, 2, nd)
    pmean_t = from_batch_last(pm_bl, 1, nd)
    pcov_t = from_batch_last(pc_bl, 2, nd)
    terms = torch.log(s_t) + e_t * e_t / s_t
    core = -0.5 * terms.reshape(prep.T, m_dim, *terms.shape[1:]).sum(1)  # (T, *mb)
    core = core.permute(*range(1, core.dim()), 0)  # (*mb, T)
    innovation = from_batch_last(innov, 1, nd)
    innovation_cov = from_batch_last(S, 2, nd)
    return assemble_result(prep, (mean_t, cov_t), (pmean_t, pcov_t), core, (innovation, innovation_cov))


def _chunk_rows(prep: PreparedInputs) -> int | None:
    """Rows of the leading batch dimension per chunk of an eager CPU loop at one intra-op
    thread (the caller's ``torch.set_num_threads``) whose
    per-track covariances take at least :data:`CHUNKED_MIN_BYTES` (a chunk about
    :data:`CHUNK_BYTES` of them); None where the loop runs on all tracks at once (traced, off
    the CPU, more threads, a covariance batch that is not the tracks' leading dimension, or a
    small one)."""
    mb, A = prep.mean_batch, prep.A
    if not mb or A.device.type != "cpu" or torch.compiler.is_compiling() or torch.compiler.is_exporting():
        return None
    if torch.get_num_threads() > 1:  # (chunks take many small ops: each a parallel region at 2+ threads)
        return None
    cb = torch.broadcast_shapes(A.shape[:-3], prep.P0.shape[:-2])
    if len(cb) != len(mb) or cb[0] != mb[0] or mb[0] < 2:
        return None
    n = A.shape[-1]
    row_bytes = math.prod(cb[1:]) * n * n * A.element_size()
    if mb[0] * row_bytes < CHUNKED_MIN_BYTES:
        return None
    rows = max(1, CHUNK_BYTES // max(row_bytes, 1))
    return rows if rows < mb[0] else None


def _loop(prep: PreparedInputs) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The loop of :func:`sequential_filter`, batch-last: predicted means (T, n, *mb) and
    covariances (T, n, n, *cb), filtered ones (same shapes), innovations of the whitened
    scalar updates (T m, *mb) and their variances (T m, *cb)."""
    m_dim = prep.yw.shape[-1]
    # Batch-last layout: per-step tensors (n, n, *batch) keep the batch as the contiguous
    # inner dimension, so every elementwise op and the broadcast-and-sum products below run
    # at full vector speed (batched 4×4 `bmm`/transposes are several times slower).
    # A_k, Q_k are moved to this layout one step at a time (a small, cache-friendly copy).
    # (unbind, not indexing, inside the loop: the backward of T separate index operations
    # would materialise T full-size zero gradients; unbind's backward is one stack.)
    A_bf, Q_bf = prep.A, prep.Q  # (*cb, T, n, n)
    nb = A_bf.dim() - 3
    to_bl = list(range(nb, nb + 2)) + list(range(nb))
    H_s = _observation_rows(prep)  # (T or 1, m, n, *cb)
    h_single = H_s.shape[0] == 1
    yw_bl = to_batch_last(prep.yw, 1, time=True)  # (T, m, *mb)

    mean = to_batch_last(prep.m0, 1)  # (n, *mb)
    P = to_batch_last(prep.P0, 2)  # (n, n, *cb)
    means, covs, pmeans, pcovs, es, ss = [], [], [], [], [], []
    # Without autograd the covariances are written straight into (T, n, n, *cb) outputs
    # (no stack of T tensors at the end); with autograd they are stacked.
    buffers = not torch.is_grad_enabled() or not any(
        t.requires_grad for t in (prep.A, prep.Q, prep.Hw, prep.P0) if isinstance(t, Tensor)
    )
    n_state = P.shape[0]
    pc_buf = P.new_empty((prep.T, n_state, n_state, *P.shape[2:])) if buffers else None
    fc_buf = P.new_empty((prep.T, n_state, n_state, *P.shape[2:])) if buffers else None
    A_steps, Q_steps = A_bf.unbind(-3), Q_bf.unbind(-3)
    h_rows = H_s.flatten(0, 1).unbind(0)  # (T or 1)·m rows, each (n, *)
    y_rows = yw_bl.flatten(0, 1).unbind(0)  # T·m entries, each (*mb)
    c_steps = to_batch_last(prep.c, 1, time=True).unbind(0) if prep.c is not None else None
    c_single = c_steps is not None and len(c_steps) == 1
    for k in range(prep.T):
        Ak = A_steps[k].permute(to_bl)
        Qk = Q_steps[k].permute(to_bl)
        if Ak.stride(-1) != 1 or Ak.dim() == 2:
            Ak, Qk = Ak.contiguous(), Qk.contiguous()
        ck = None if c_steps is None else c_steps[0 if c_single else k]
        hk0 = 0 if h_single else k * m_dim
        pm, pc, mean, P, e_k, s_k = _joseph_step(
            Ak,
            Qk,
            mean,
            P,
            ck,
            h_rows[hk0 : hk0 + m_dim],
            y_rows[k * m_dim : (k + 1) * m_dim],
            None if pc_buf is None else pc_buf[k],
            None if fc_buf is None else fc_buf[k],
        )
        pmeans.append(pm)
        pcovs.append(pc)
        es.extend(e_k)
        ss.extend(s_k)
        means.append(mean)
        covs.append(P)
    pm_bl = torch.stack(pmeans)  # (T, n, *mb)
    pc_bl = torch.stack(pcovs) if pc_buf is None else pc_buf  # (T, n, n, *cb)
    fm_bl = torch.stack(means)
    fc_bl = torch.stack(covs) if fc_buf is None else fc_buf
    e_t = torch.stack(torch.broadcast_tensors(*es))  # (T m, *mb)
    s_t = torch.stack(ss)  # (T m, *cb)
    return pm_bl, pc_bl, fm_bl, fc_bl, e_t, s_t


def _chunked_loop(prep: PreparedInputs, rows: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`_loop` on consecutive chunks of ``rows`` rows of the leading batch dimension (each
    an independent filter of its tracks), its outputs joined along that dimension."""
    nd, total = len(prep.mean_batch), prep.mean_batch[0]
    sizes = [min(rows, total - start) for start in range(0, total, rows)]
    # (one split a field: its backward is one concatenation, where a slice a chunk would
    # materialise a full-size zero gradient per chunk)
    pieces = {
        name: x.split(sizes) if isinstance(x, Tensor) and x.dim() - _EVENT_DIMS[name] == nd and x.shape[0] > 1 else None
        for name, x in prep._asdict().items()
        if name in _EVENT_DIMS
    }
    parts = []
    for i, size in enumerate(sizes):
        fields = {name: split[i] for name, split in pieces.items() if split is not None}
        part = prep._replace(**fields, mean_batch=torch.Size([size, *prep.mean_batch[1:]]))
        parts.append(_loop(part))
    # the batch position of each output: (T, n, *mb), (T, n, n, *cb), …, (T m, *mb), (T m, *cb)
    return tuple(torch.cat(group, dim) for group, dim in zip(zip(*parts), (2, 3, 2, 3, 1, 1)))  # type: ignore[return-value]


def _observation_rows(prep: PreparedInputs) -> Tensor:
    """The whitened H' batch-last, (T or 1, m, n, *cb), materialised over the covariance batch
    cb: products with a stride-0 (broadcast) inner dimension take a slow path, same-shape ones
    do not."""
    H_s = to_batch_last(prep.Hw, 2, time=True)  # (T or 1, m, n, *cb or broadcastable)
    cb = prep.A.shape[: prep.A.dim() - 3]
    return H_s.expand(*H_s.shape[:3], *torch.broadcast_shapes(H_s.shape[3:], cb)).contiguous()


def structured_filtered(prep: PreparedInputs) -> tuple[Tensor, Tensor]:
    """The filtered means (..., T, n) and covariances (..., T, n, n) of the loop run as torch's
    structured scan (:func:`sequential_filter` with ``structured``): one step's graph, no
    unrolling, no Python per step; the loop carries and returns the filtered moments alone
    (each output of a step costs a compiled program buffers every iteration). Batch-last
    layout as in the eager loop."""
    H_s = _observation_rows(prep)
    mean = to_batch_last(prep.m0, 1)  # (n, *mb)
    T = prep.T
    c_all = to_batch_last(prep.c, 1, time=True) if prep.c is not None else torch.zeros_like(mean).unsqueeze(0)
    loop = _scan_loop if torch.compiler.is_exporting() else _run_compiled_loop
    fm_bl, fc_bl = loop(
        to_batch_last(prep.A, 2, time=True),
        to_batch_last(prep.Q, 2, time=True),
        H_s.expand(T, *H_s.shape[1:]),
        to_batch_last(prep.yw, 1, time=True),
        c_all.expand(T, *c_all.shape[1:]),
        _row_major(mean),
        _row_major(to_batch_last(prep.P0, 2)),
    )
    nd = len(prep.mean_batch)
    return from_batch_last(fm_bl, 1, nd), from_batch_last(fc_bl, 2, nd)


def _joseph_step(
    Ak: Tensor,
    Qk: Tensor,
    mean: Tensor,
    P: Tensor,
    ck: Tensor | None,
    h_rows: Sequence[Tensor],
    y_vals: Sequence[Tensor],
    pc_out: Tensor | None,
    fc_out: Tensor | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, list[Tensor], list[Tensor]]:
    """One step of the loop, batch-last: predict with (A_k, Q_k, c_k), then one whitened
    scalar Joseph update per observed row h_j (n, *) with value y_j.

    Returns (predicted mean, predicted cov, filtered mean, filtered cov, innovations e_j,
    innovation variances s_j). ``pc_out`` / ``fc_out``: optional buffers the covariances are
    written into (no autograd there)."""
    mean = bl_matvec(Ak, mean)
    if ck is not None:
        mean = mean + ck
    P = bl_sym_into(bl_matmul(bl_matmul(Ak, P), Ak.transpose(0, 1)) + Qk, pc_out)
    pmean, pcov = mean, P
    es: list[Tensor] = []
    ss: list[Tensor] = []
    for h, yj in zip(h_rows, y_vals):
        ph = bl_matvec(P, h)
        s = torch.linalg.vecdot(h, ph, dim=0) + 1.0
        gain = ph / s
        e = yj - torch.linalg.vecdot(h, mean, dim=0)
        mean = torch.addcmul(mean, gain, e)
        MP = torch.addcmul(P, gain.unsqueeze(1), ph.unsqueeze(0), value=-1.0)  # (I − k hᵀ) P
        w = bl_matvec(MP, h)  # (I − k hᵀ) P h
        P = torch.addcmul(MP, (gain - w).unsqueeze(1), gain.unsqueeze(0))  # … (I − h kᵀ) + k kᵀ
        es.append(e)
        ss.append(s)
    P = bl_sym_into(P, fc_out)
    return pmean, pcov, mean, P, es, ss


def _row_major(x: Tensor) -> Tensor:
    """A copy with row-major strides for every dim (size-1 dims included): the scan operator
    needs its initial carry laid out exactly as the step body returns it."""
    return torch.empty(x.shape, dtype=x.dtype, device=x.device).copy_(x)


def _scan_body(
    carry: tuple[Tensor, Tensor], step: tuple[Tensor, Tensor, Tensor, Tensor, Tensor]
) -> tuple[tuple[Tensor, Tensor], tuple[Tensor, Tensor]]:
    """:func:`_joseph_step` as the body of ``torch._higher_order_ops.scan``: carry (mean, P),
    step slices (A_k, Q_k, H'_k (m, n, *), y'_k (m, *), c_k (n, *)); outputs the filtered
    (mean, P)."""
    mean, P = carry
    Ak, Qk, hk, yk, ck = step
    _, _, mean, P, _, _ = _joseph_step(Ak, Qk, mean, P, ck, hk.unbind(0), yk.unbind(0), None, None)
    # outputs must not alias the carry (a requirement of the scan operator)
    return (mean, P), (mean.clone(), P.clone())


def _scan_loop(A: Tensor, Q: Tensor, H: Tensor, y: Tensor, c: Tensor, mean: Tensor, P: Tensor) -> tuple[Tensor, ...]:
    """The sequential loop over the leading T axis of A, Q (T, n, n, *), H' (T, m, n, *),
    y' (T, m, *), c (T, n, *): the filtered means (T, n, *) and covariances (T, n, n, *)."""
    from torch._higher_order_ops import scan

    _, outs = scan(_scan_body, (mean, P), (A, Q, H, y, c))
    return tuple(outs)


_COMPILED_LOOP: Callable[..., tuple[Tensor, ...]] | None = None


@torch.compiler.disable
def _run_compiled_loop(*args: Tensor) -> tuple[Tensor, ...]:
    """:func:`_compiled_loop` called from eager code (a graph break inside a caller's trace)."""
    return _compiled_loop()(*args)


def _compiled_loop() -> Callable[..., tuple[Tensor, ...]]:
    """:func:`_scan_loop` through ``torch.compile`` (built once): torch's structured scan
    compiles ONE step's graph however long T is, and runs the loop without Python per step."""
    global _COMPILED_LOOP
    if _COMPILED_LOOP is None:
        _COMPILED_LOOP = torch.compile(_scan_loop, fullgraph=True)
    return _COMPILED_LOOP
