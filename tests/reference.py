"""Independent high-precision references for the discretisation tests (mpmath, scipy).

Nothing here calls torchsde_lti: every value is computed another way.
"""

from __future__ import annotations

import math

import mpmath
import numpy as np
import scipy.linalg
import scipy.stats
import torch
from scipy.integrate import quad_vec


def mp_matrix(x: np.ndarray) -> mpmath.matrix:
    return mpmath.matrix([[mpmath.mpf(float(v)) for v in row] for row in np.atleast_2d(x)])


def to_numpy(m: mpmath.matrix) -> np.ndarray:
    return np.array([[float(m[i, j]) for j in range(m.cols)] for i in range(m.rows)])


def mp_discretize(F: np.ndarray, W: np.ndarray, dt: float, dps: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """(A, Q) by quadrature of Q = ∫_0^dt e^{Fs} W e^{Fs}ᵀ ds in mpmath at ``dps`` digits.

    The integrand is smooth; the interval is split at multiples of the fastest time scale so
    tanh-sinh quadrature resolves stiff decays. A = mpmath.expm(F dt).
    """
    n = F.shape[0]
    with mpmath.workdps(dps):
        Fm, Wm = mp_matrix(F), mp_matrix(W)
        dtm = mpmath.mpf(float(dt))
        A = mpmath.expm(Fm * dtm)
        rate = max(float(np.abs(np.linalg.eigvals(F)).max()), 1e-12)
        cuts = [mpmath.mpf(0)]
        for c in (0.1, 1.0, 5.0, 20.0, 80.0):
            point = c / rate
            if point < float(dt):
                cuts.append(mpmath.mpf(point))
        cuts.append(dtm)
        cache: dict = {}

        def integrand(s, i, j):
            key = s
            if key not in cache:
                E = mpmath.expm(Fm * s)
                cache[key] = E * Wm * E.T
            return cache[key][i, j]

        Q = mpmath.matrix(n, n)
        for i in range(n):
            for j in range(i, n):
                Q[i, j] = mpmath.quad(lambda s: integrand(s, i, j), cuts)
                Q[j, i] = Q[i, j]
        return to_numpy(A), to_numpy(Q)


def quad_discretize(F: np.ndarray, W: np.ndarray, B: np.ndarray | None, dt: float):
    """(A, Q, G) in float64: scipy.linalg.expm for A and G, adaptive quadrature for Q."""
    A = scipy.linalg.expm(F * dt)
    Q = quad_vec(lambda s: scipy.linalg.expm(F * s) @ W @ scipy.linalg.expm(F * s).T, 0.0, dt, epsabs=0, epsrel=1e-13)[
        0
    ]
    G = None
    if B is not None:
        n, p = B.shape
        block = np.zeros((n + p, n + p))
        block[:n, :n] = F
        block[:n, n:] = B
        G = scipy.linalg.expm(block * dt)[:n, n:]
    return A, Q, G


def integrator_chain_Q(order: int, q: float, dt: float) -> np.ndarray:
    """Closed form Q of an integrator chain of ``order`` states with white noise q on the last.

    Q_ij = q dt^{2N-1-i-j} / ((N-1-i)! (N-1-j)! (2N-1-i-j)), N = order, i, j = 0..N-1.
    """
    N = order
    Q = np.zeros((N, N))
    for i in range(N):
        for j in range(N):
            p = 2 * N - 1 - i - j
            Q[i, j] = q * dt**p / (math.factorial(N - 1 - i) * math.factorial(N - 1 - j) * p)
    return Q


def rel_err(x: np.ndarray, ref: np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(x, dtype=np.float64) - ref) / max(np.linalg.norm(ref), 1e-300))


def scipy_discretize(F: np.ndarray, L: np.ndarray, Qc: np.ndarray, dt, B: np.ndarray | None = None):
    """(A, Q, G) by scipy.linalg.expm of the Van Loan / ZOH blocks in float64 (moderate dt).

    dt: a scalar or an array of any shape; A, Q (*dt.shape, n, n), G (*dt.shape, n, p) or None.
    """
    n = F.shape[0]
    W = L @ Qc @ L.T
    out_A, out_Q, out_G = [], [], []
    for h in np.ravel(dt):
        E = scipy.linalg.expm(np.block([[F, W], [np.zeros((n, n)), -F.T]]) * h)
        A = E[:n, :n]
        Q = E[:n, n:] @ A.T
        out_A.append(A)
        out_Q.append(0.5 * (Q + Q.T))
        if B is not None:
            p = B.shape[1]
            Z = scipy.linalg.expm(np.block([[F, B], [np.zeros((p, n)), np.zeros((p, p))]]) * h)
            out_G.append(Z[:n, n:])
    shape = np.shape(dt)
    A = np.array(out_A).reshape(shape + (n, n))
    Q = np.array(out_Q).reshape(shape + (n, n))
    G = np.array(out_G).reshape(shape + (n, B.shape[1])) if B is not None else None
    return A, Q, G


# ----------------------------------------------------------------------------------------
# numpy reference filter / smoother and test problems (independent of torchsde_lti)
# ----------------------------------------------------------------------------------------


def numpy_kalman_filter(y, A, Q, H, R, m0, P0, c=None, Du=None):
    """One track. y (T, m) with NaN = missing; A, Q (T, n, n); H (m, n); R (m, m); c (T, n)
    control term; Du (T, m) feedthrough (y_k = H x_k + D u_k + r_k)."""
    T = y.shape[0]
    m, P = m0.copy(), P0.copy()
    out = {k: [] for k in ("mean", "cov", "pred_mean", "pred_cov", "ll")}
    for k in range(T):
        m = A[k] @ m + (c[k] if c is not None else 0.0)
        P = A[k] @ P @ A[k].T + Q[k]
        out["pred_mean"].append(m.copy())
        out["pred_cov"].append(P.copy())
        o = ~np.isnan(y[k])
        ll = 0.0
        if o.any():
            Ho, Ro = H[o], R[np.ix_(o, o)]
            S = Ho @ P @ Ho.T + Ro
            v = y[k][o] - Ho @ m - (Du[k][o] if Du is not None else 0.0)
            K = np.linalg.solve(S, Ho @ P).T
            m = m + K @ v
            P = P - K @ S @ K.T
            ll = scipy.stats.multivariate_normal(mean=np.zeros(o.sum()), cov=S).logpdf(v)
        out["mean"].append(m.copy())
        out["cov"].append(P.copy())
        out["ll"].append(ll)
    return {k: np.array(v) for k, v in out.items()}


def numpy_rts(mean, cov, pred_mean, pred_cov, A):
    T = mean.shape[0]
    ms, Ps = mean.copy(), cov.copy()
    for k in range(T - 2, -1, -1):
        Ek = np.linalg.solve(pred_cov[k + 1], A[k + 1] @ cov[k]).T
        ms[k] = mean[k] + Ek @ (ms[k + 1] - pred_mean[k + 1])
        Ps[k] = cov[k] + Ek @ (Ps[k + 1] - pred_cov[k + 1]) @ Ek.T
    return ms, Ps


def cv_matrices(dt: np.ndarray, q: float = 1.0, axes: int = 2):
    """Closed-form constant-velocity (A, Q, G) per step, state [x, vx, y, vy]."""
    T = dt.shape[-1]
    A = np.zeros(dt.shape + (2 * axes, 2 * axes))
    Q = np.zeros_like(A)
    G = np.zeros(dt.shape + (2 * axes, axes))
    for a in range(axes):
        i = 2 * a
        A[..., i, i] = A[..., i + 1, i + 1] = 1.0
        A[..., i, i + 1] = dt
        Q[..., i, i] = q * dt**3 / 3
        Q[..., i, i + 1] = Q[..., i + 1, i] = q * dt**2 / 2
        Q[..., i + 1, i + 1] = q * dt
        G[..., i, a] = dt**2 / 2
        G[..., i + 1, a] = dt
    assert A.shape[-3] == T
    return A, Q, G


def random_problem(rng, batch=(3,), T=12, n=4, m=2, p=2, missing=True):
    """Random time-varying A, PSD Q, H, R; NaN-missing steps and partial observations."""
    A = np.eye(n) + 0.3 * rng.standard_normal(batch + (T, n, n))
    Wq = rng.standard_normal(batch + (T, n, n))
    Q = 0.1 * Wq @ np.swapaxes(Wq, -1, -2)
    H = rng.standard_normal((m, n))
    Wr = rng.standard_normal((m, m))
    R = Wr @ Wr.T + 0.5 * np.eye(m)
    m0 = rng.standard_normal(batch + (n,))
    W0 = rng.standard_normal(batch + (n, n))
    P0 = W0 @ np.swapaxes(W0, -1, -2) + np.eye(n)
    G = rng.standard_normal(batch + (T, n, p))
    u = rng.standard_normal(batch + (T, p))
    y = rng.standard_normal(batch + (T, m))
    if missing:
        flat = y.reshape(-1, T, m)
        flat[0, 2 % T, :] = np.nan  # fully missing step
        flat[0, 5 % T, 1] = np.nan  # partial observation
        flat[-1, 0, 0] = np.nan
        flat[-1, 7 % T, :] = np.nan
    return dict(y=y, A=A, Q=Q, H=H, R=R, m0=m0, P0=P0, G=G, u=u)


def to_torch(d, dtype=torch.float64):
    return {k: torch.as_tensor(v, dtype=dtype) for k, v in d.items()}


def reference_batch(d):
    """Run the numpy reference over the flattened batch; returns dict of stacked arrays."""
    batch = d["y"].shape[:-2]
    outs = []
    for idx in np.ndindex(*batch):
        c = d["G"][idx] @ d["u"][idx][..., None]
        outs.append(
            numpy_kalman_filter(
                d["y"][idx], d["A"][idx], d["Q"][idx], d["H"], d["R"], d["m0"][idx], d["P0"][idx], c[..., 0]
            )
        )
    return {k: np.stack([o[k] for o in outs]).reshape(batch + outs[0][k].shape) for k in outs[0]}


def mp_doubling(F: np.ndarray, W: np.ndarray, B: np.ndarray | None, dt: float, dps: int = 60):
    """(A, Q, G) at ``dps`` digits for ANY step (including dt ≫ 1/‖F‖): mpmath's expm of the
    Van Loan and ZOH blocks on a sub-step h = dt / 2^s with ‖F‖_F h ≤ 1/4 (no cancellation at
    that step), then s doublings Q ← A Q Aᵀ + Q, G ← A G + G, A ← A A in mpmath (2^s ulps of
    60 digits are far below float64's). Returns float64 arrays (inf where the value overflows)."""
    n = F.shape[0]
    with mpmath.workdps(dps):
        Fm, Wm = mp_matrix(F), mp_matrix(W)
        norm = mpmath.sqrt(sum(mpmath.mpf(float(v)) ** 2 for v in np.ravel(F)))
        dtm = mpmath.mpf(float(dt))
        s = 0 if norm * dtm <= mpmath.mpf(0.25) else int(mpmath.ceil(mpmath.log(norm * dtm / mpmath.mpf(0.25), 2)))
        h = dtm / mpmath.mpf(2) ** s
        Z = mpmath.zeros(n, n)
        E = mpmath.expm(
            mpmath.matrix(
                [[Fm[i, j] if j < n else Wm[i, j - n] for j in range(2 * n)] for i in range(n)]
                + [[Z[i, j] if j < n else -Fm[j - n, i] for j in range(2 * n)] for i in range(n)]
            )
            * h
        )
        A = E[:n, :n]
        Q = E[:n, n:] * A.T
        G = None
        if B is not None:
            p = B.shape[1]
            Bm = mp_matrix(B)
            blk = mpmath.zeros(n + p, n + p)
            for i in range(n):
                for j in range(n):
                    blk[i, j] = Fm[i, j]
                for j in range(p):
                    blk[i, n + j] = Bm[i, j]
            G = mpmath.expm(blk * h)[:n, n:]
        for _ in range(s):
            Q = A * Q * A.T + Q
            if G is not None:
                G = A * G + G
            A = A * A
        Q = (Q + Q.T) / 2

        def f64(m: mpmath.matrix) -> np.ndarray:
            big = mpmath.mpf(np.finfo(np.float64).max)
            return np.array(
                [
                    [
                        float(m[i, j]) if abs(m[i, j]) <= big else math.copysign(math.inf, float(mpmath.sign(m[i, j])))
                        for j in range(m.cols)
                    ]
                    for i in range(m.rows)
                ]
            )

        return f64(A), f64(Q), None if G is None else f64(G)
