"""Independent high-precision references for the discretisation tests (mpmath, scipy).

Nothing here calls torchsde_lti: every value is computed another way.
"""

from __future__ import annotations

import math

import mpmath
import numpy as np
import scipy.linalg
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
    Q = quad_vec(lambda s: scipy.linalg.expm(F * s) @ W @ scipy.linalg.expm(F * s).T, 0.0, dt, epsabs=0, epsrel=1e-13)[0]
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


def numpy_filter_with_feedthrough(y, A, Q, H, R, m0, P0, c=None, Du=None):
    """Plain covariance-form Kalman filter for one track with a feedthrough term.

    x_k = A_k x_{k-1} + c_k + q_k,  y_k = H x_k + Du_k + r_k;  y (T, m) with NaN = missing
    component; A, Q (T, n, n); H (m, n); R (m, m); c (T, n) = G_k u_k; Du (T, m) = D u_k.
    Returns dict of arrays: mean, cov, pred_mean, pred_cov (T, ...), ll (T,).
    """
    import scipy.stats

    T = y.shape[0]
    m, P = np.array(m0, dtype=float), np.array(P0, dtype=float)
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
            K = P @ Ho.T @ np.linalg.inv(S)
            m = m + K @ v
            IKH = np.eye(len(m)) - K @ Ho
            P = IKH @ P @ IKH.T + K @ Ro @ K.T
            ll = float(scipy.stats.multivariate_normal(mean=np.zeros(int(o.sum())), cov=S).logpdf(v))
        out["mean"].append(m.copy())
        out["cov"].append(P.copy())
        out["ll"].append(ll)
    return {k: np.array(v) for k, v in out.items()}


def expm_zoh_steps(F, L, Qc, B, dt):
    """Per-step (A, Q, G) over a 1-D array dt by scipy block exponentials (float64, moderate dt)."""
    n = F.shape[0]
    W = L @ Qc @ L.T
    As, Qs, Gs = [], [], []
    for h in np.ravel(dt):
        E = scipy.linalg.expm(np.block([[F, W], [np.zeros((n, n)), -F.T]]) * h)
        A = E[:n, :n]
        Qd = E[:n, n:] @ A.T
        As.append(A)
        Qs.append(0.5 * (Qd + Qd.T))
        if B is not None:
            p = B.shape[1]
            Z = scipy.linalg.expm(np.block([[F, B], [np.zeros((p, n)), np.zeros((p, p))]]) * h)
            Gs.append(Z[:n, n:])
    return np.array(As), np.array(Qs), (np.array(Gs) if B is not None else None)
