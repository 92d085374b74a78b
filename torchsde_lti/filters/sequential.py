r"""The sequential Kalman filter (Joseph form, whitened scalar updates), O(T) depth.

On the per-step discrete model (see :mod:`torchsde_lti.filters` for the conventions)::

    x_k = A_k x_{k-1} + G_k u_k + q_k,    q_k ~ N(0, Q_k),     x_{-1} ~ N(m0, P0)
    y_k = H_k x_k + r_k,                  r_k ~ N(0, R_k),     k = 0 … T-1

Each step's noise is whitened with the Cholesky factor of the (masked) R_k (input
preparation, :mod:`~torchsde_lti.filters.inputs`), so R' = I, and the m scalar observations
are processed one after the other (Bierman's sequential processing: equal to the joint
update). Each scalar update uses the Joseph form ``P⁺ = (I − k hᵀ) P (I − k hᵀ)ᵀ + k kᵀ``;
P is symmetrised once per step. No matrix is inverted; there is no Cholesky in the loop.
The loop runs on the batch-last layout of :mod:`~torchsde_lti.filters.layout`; one step is
:func:`_joseph_step`, which the online step (:func:`~torchsde_lti.filters.kalman_step`) calls too.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from torchsde_lti.filters.inputs import PreparedInputs, assemble_result, complete_from_filtered, observed_count
from torchsde_lti.filters.layout import mv, tr
from torchsde_lti.filters.noise import GAUSSIAN, NoiseModel, StudentTNoise
from torchsde_lti.filters.results import FilterResult

__all__ = ["sequential_filter", "structured_filtered"]


def sequential_filter(prep: PreparedInputs, structured: bool = False, noise: NoiseModel = GAUSSIAN) -> FilterResult:
    r"""The sequential loop on prepared inputs: step k predicts ``m⁻ = A_k m + G_k u_k``,
    ``P⁻ = A_k P A_kᵀ + Q_k``, then updates with the observed components of y_k (whitened
    scalar updates in Joseph form); the log-likelihood core is ``−½ Σ_j (log s_j + e_j² / s_j)``
    over the scalar innovations e_j and their variances s_j.

    ``structured``: run the loop as torch's structured scan (``torch._higher_order_ops.scan``)
    through its own ``torch.compile``: one step's graph is compiled (once), the T steps are not
    unrolled; inside a caller's ``torch.compile`` trace the loop is a graph break (inductor
    cannot yet lower the scan inside a larger graph). The loop then yields the filtered moments
    alone, the rest is formed batched over the steps
    (:func:`~torchsde_lti.filters.inputs.complete_from_filtered`).

    ``noise``: the observation-noise model (:mod:`~torchsde_lti.filters.noise`): after each
    step's update its ``update`` rescales the filtered covariance (a Student-t's scale; the
    Gaussian's is the identity), and its ``log_likelihood_core`` gives the step's core.
    """
    if structured:
        return complete_from_filtered(prep, *structured_filtered(prep, noise), noise)
    mean, P = _initial_state(prep)
    P = noise.full_batch(P, mean)
    h_rows = prep.Hw.flatten(0, 1).unbind(0)  # T·m rows, each (n, *b)
    y_vals = prep.yw.flatten(0, 1).unbind(0)  # T·m values, each (*b)
    m = prep.yw.shape[1]
    # (unbind, not indexing, inside the loop: the backward of T separate index operations
    # would materialise T full-size zero gradients; unbind's backward is one stack)
    A, Q = prep.A.unbind(0), prep.Q.unbind(0)
    c = None if prep.c is None else prep.c.unbind(0)
    d = observed_count(prep)  # (T, *b)
    steps = []
    for k in range(prep.T):
        ck = None if c is None else c[k]
        rows = slice(k * m, (k + 1) * m)
        pm_k, pc_k, mean, P, e_k, s_k = _joseph_step(A[k], Q[k], mean, P, ck, h_rows[rows], y_vals[rows], None, None)
        P = noise.update(P, e_k, s_k, d[k])  # (the Gaussian's: P itself)
        steps.append((pm_k, pc_k, mean, P, e_k, s_k))
    pm, pc, fm, fc = (torch.stack([step[i] for step in steps]) for i in range(4))  # type: ignore[misc]
    e = torch.stack([torch.stack(step[4]) for step in steps])  # (T, m, *b)
    s = torch.stack([torch.stack(step[5]) for step in steps])
    core = noise.log_likelihood_core(torch.log(s).sum(1), (e * e / s).sum(1), d)
    return assemble_result(prep, (fm, fc), (pm, pc), core)


def _initial_state(prep: PreparedInputs) -> tuple[Tensor, Tensor]:
    """The prior (m0 (n, *b), P0 (n, n, *b)) broadcast to the batch every step's mean and
    covariance take, so that the T steps stack."""
    cov_batch = torch.broadcast_shapes(prep.P0.shape[2:], prep.A.shape[3:], prep.Q.shape[3:], prep.Hw.shape[3:])
    mean_batch = torch.broadcast_shapes(cov_batch, prep.m0.shape[1:], prep.yw.shape[2:])
    if prep.c is not None:
        mean_batch = torch.broadcast_shapes(mean_batch, prep.c.shape[2:])
    n = prep.m0.shape[0]
    return prep.m0.expand(n, *mean_batch), prep.P0.expand(n, n, *cov_batch)


def _joseph_step(
    Ak: Tensor,
    Qk: Tensor,
    mean: Tensor,
    P: Tensor,
    ck: Tensor | None,
    h_rows: Sequence[Tensor],
    y_vals: Sequence[Tensor],
    pc_out: Tensor | None = None,
    fc_out: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, list[Tensor], list[Tensor]]:
    """One step of the loop, batch-last: predict with (A_k (n, n, *b), Q_k, c_k (n, *b)), then
    one whitened scalar Joseph update per observed row h_j (n, *b) with value y_j (*b).

    Returns (predicted mean, predicted cov, filtered mean, filtered cov, innovations e_j,
    innovation variances s_j). ``pc_out`` / ``fc_out``: optional buffers the two covariances are
    copied into (no autograd there)."""
    mean = mv(Ak, mean)
    if ck is not None:
        mean = mean + ck
    P = _sym(_mm_t(_mm(Ak, P), Ak) + Qk, pc_out)
    pmean, pcov = mean, P
    es: list[Tensor] = []
    ss: list[Tensor] = []
    for h, yj in zip(h_rows, y_vals):
        ph = mv(P, h)
        s = torch.linalg.vecdot(h, ph, dim=0) + 1.0
        gain = ph / s
        e = yj - torch.linalg.vecdot(h, mean, dim=0)
        mean = torch.addcmul(mean, gain, e)
        MP = torch.addcmul(P, gain.unsqueeze(1), ph.unsqueeze(0), value=-1.0)  # (I − k hᵀ) P
        w = mv(MP, h)  # (I − k hᵀ) P h
        P = torch.addcmul(MP, (gain - w).unsqueeze(1), gain.unsqueeze(0))  # … (I − h kᵀ) + k kᵀ
        es.append(e)
        ss.append(s)
    return pmean, pcov, mean, _sym(P, fc_out), es, ss


def _mm(a: Tensor, b: Tensor) -> Tensor:
    """``a b`` of a (r, k, *b), b (k, s, *b) -> (r, s, *b): one broadcast dot product over k."""
    return torch.linalg.vecdot(a.unsqueeze(2), b.unsqueeze(0), dim=1)


def _mm_t(a: Tensor, b: Tensor) -> Tensor:
    """``a bᵀ`` of a (r, k, *b), b (s, k, *b) -> (r, s, *b): one broadcast dot product over k."""
    return torch.linalg.vecdot(a.unsqueeze(1), b.unsqueeze(0), dim=2)


def _sym(P: Tensor, out: Tensor | None) -> Tensor:
    """``(P + Pᵀ) / 2`` of P (k, k, *b), copied into ``out`` when given."""
    P = 0.5 * (P + tr(P))
    return P if out is None else out.copy_(P)


def structured_filtered(prep: PreparedInputs, noise: NoiseModel = GAUSSIAN) -> tuple[Tensor, Tensor]:
    """The filtered means (T, n, *b) and covariances (T, n, n, *b) of the loop run as torch's
    structured scan (:func:`sequential_filter` with ``structured``): one step's graph, no
    unrolling, no Python per step; the loop carries and returns the filtered moments alone
    (each output of a step costs a compiled program buffers every iteration). A Student-t
    ``noise`` scans its ν and each step's observed count along."""
    mean, P = _initial_state(prep)
    P = noise.full_batch(P, mean)
    T = prep.T
    c = prep.c if prep.c is not None else torch.zeros_like(mean).unsqueeze(0)
    loop = _scan_loop if torch.compiler.is_exporting() else _run_compiled_loop
    args = (prep.A, prep.Q, prep.Hw, prep.yw, c.expand(T, *c.shape[1:]), _row_major(mean), _row_major(P))
    fm, fc = loop(*args, *noise.scanned(observed_count(prep)))
    return fm, fc


def _row_major(x: Tensor) -> Tensor:
    """A copy with row-major strides for every dim (size-1 dims included): the scan operator
    needs its initial carry laid out exactly as the step body returns it."""
    return torch.empty(x.shape, dtype=x.dtype, device=x.device).copy_(x)


def _scan_body(
    carry: tuple[Tensor, Tensor], step: tuple[Tensor, ...]
) -> tuple[tuple[Tensor, Tensor], tuple[Tensor, Tensor]]:
    """:func:`_joseph_step` as the body of ``torch._higher_order_ops.scan``: carry (mean, P),
    step slices (A_k, Q_k, H'_k (m, n, *), y'_k (m, *), c_k (n, *)[, (d_k, ν) (2, *) of a
    Student-t noise]); outputs the filtered (mean, P)."""
    mean, P = carry
    Ak, Qk, hk, yk, ck = step[:5]
    _, _, mean, P, e, s = _joseph_step(Ak, Qk, mean, P, ck, hk.unbind(0), yk.unbind(0))
    if len(step) > 5:
        P = StudentTNoise(step[5][1]).update(P, e, s, step[5][0])
    # outputs must not alias the carry (a requirement of the scan operator)
    return (mean, P), (mean.clone(), P.clone())


def _scan_loop(
    A: Tensor, Q: Tensor, H: Tensor, y: Tensor, c: Tensor, mean: Tensor, P: Tensor, *t_noise: Tensor
) -> tuple[Tensor, ...]:
    """The sequential loop over the leading T axis of A, Q (T, n, n, *), H' (T, m, n, *),
    y' (T, m, *), c (T, n, *) (and a Student-t noise's (d_k, ν) (T, 2, *)): the filtered means
    (T, n, *) and covariances (T, n, n, *)."""
    from torch._higher_order_ops import scan

    _, outs = scan(_scan_body, (mean, P), (A, Q, H, y, c, *t_noise))
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
