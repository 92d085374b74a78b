"""Every model of ``tl.models`` over steps from 1e-6 to 1e9, in float32 and float64, against
an independent 60-digit reference (mpmath's block exponential on a short sub-step, doubled in
mpmath): finite wherever the exact result fits the dtype (a ValueError naming the overflow
where it does not), normwise relative error ≤ 1e-5 in float32 and ≤ 1e-12 in float64 (A relative to
max(‖A‖, 1)), every Q symmetric PSD."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

import torchsde_lti as tl
from tests.reference import mp_doubling

F64, F32 = torch.float64, torch.float32
DTS = (1e-6, 1e-3, 0.1, 1.0, 10.0, 1e3, 1e6, 1e9)

MODELS = {
    "constant_velocity": lambda dt: tl.models.constant_velocity(dim=1, q=0.7, dtype=dt),
    "constant_acceleration": lambda dt: tl.models.constant_acceleration(dim=1, q=2.5, dtype=dt),
    "integrated_wiener_4": lambda dt: tl.models.integrated_wiener(4, q=0.3, dtype=dt),
    "singer": lambda dt: tl.models.singer(alpha=0.6, q=2.0, dtype=dt),
    "integrated_ou": lambda dt: tl.models.integrated_ou(k=1.3, q=0.6, dtype=dt),
    "ornstein_uhlenbeck": lambda dt: tl.models.ornstein_uhlenbeck(theta=1.7, q=0.9, dtype=dt),
    "matern_12": lambda dt: tl.models.matern(0.5, lengthscale=0.7, variance=2.0, dtype=dt),
    "matern_52": lambda dt: tl.models.matern(2.5, lengthscale=0.7, variance=2.0, dtype=dt),
    "mass_spring_damper": lambda dt: tl.models.mass_spring_damper(m=1.5, k=2.0, c=0.4, q=0.7, dtype=dt),
    "companion": lambda dt: tl.models.companion([2.0, 3.0, 1.5], q=0.5, dtype=dt),
    "transfer_function": lambda dt: tl.models.from_transfer_function([1.0], [1.0, 0.8, 2.0], q=0.5, dtype=dt),
    "moored": lambda dt: tl.models.moored(k=0.05, q=0.01, dim=1, dtype=dt),
    "shaped": lambda dt: tl.models.shaped(
        tl.models.constant_velocity(dim=1, q=1.0, dtype=dt), tl.models.ornstein_uhlenbeck(theta=0.5, q=1.0, dtype=dt)
    ),
    "block_diag": lambda dt: tl.models.block_diag(
        tl.models.singer(alpha=0.2, q=1.0, dtype=dt), tl.models.ornstein_uhlenbeck(theta=40.0, q=0.5, dtype=dt)
    ),
}


@functools.cache
def _reference(name: str, dtype: torch.dtype, dt: float):
    """The model's own (dtype-rounded) matrices, discretised at 60 digits."""
    sde = MODELS[name](dtype)
    m = sde.matrices()
    F = m.F.detach().double().numpy()
    W = (m.L @ m.Qc @ m.L.mT).detach().double().numpy()
    B = None if m.B is None else m.B.detach().double().numpy()
    return mp_doubling(F, W, B, float(torch.tensor(dt, dtype=dtype)))


def _rel(x: torch.Tensor, ref: np.ndarray, floor: float = 1e-300) -> float:
    """‖x − ref‖_F / max(‖ref‖_F, floor)."""
    r = torch.as_tensor(ref)
    return float((x.double() - r).norm() / r.norm().clamp_min(floor))


@pytest.mark.parametrize("dtype", [F32, F64], ids=["f32", "f64"])
@pytest.mark.parametrize("name", sorted(MODELS))
def test_every_model_over_every_step(name: str, dtype: torch.dtype) -> None:
    sde = MODELS[name](dtype)
    tol = 1e-5 if dtype == F32 else 1e-12
    big = torch.finfo(dtype).max
    refs = {dt: _reference(name, dtype, dt) for dt in DTS}
    fitting = [dt for dt in DTS if all(np.all(np.abs(r) <= big) for r in refs[dt][:2])]
    with torch.no_grad():
        for dt in sorted(set(DTS) - set(fitting)):  # the exact result exceeds the dtype: a clear error
            with pytest.raises(ValueError, match="overflows"):
                sde(torch.tensor(dt, dtype=dtype))
        steps = torch.tensor(fitting * 5, dtype=dtype)  # ≥ 32 steps: the one-parameter-set specialisation
        batched = sde(steps)
        for i, dt in enumerate(fitting):
            A_ref, Q_ref, G_ref = refs[dt]
            single = sde(steps[i])  # one element: the per-element algorithm (or the routed call)
            from_batch = type(single)(batched.A[i], batched.Q[i], None if batched.G is None else batched.G[i])
            for d in (single, from_batch):
                assert torch.isfinite(d.A).all() and torch.isfinite(d.Q).all(), (name, dt)
                # A relative to max(‖A‖, 1): a decayed A (e^{-25}) is accurate to the precision of
                # the step (relative to ‖A(0)‖ = ‖I‖), not to its own size
                assert _rel(d.A, A_ref, 1.0) <= tol, (name, dt, "A", _rel(d.A, A_ref, 1.0))
                assert _rel(d.Q, Q_ref) <= tol, (name, dt, "Q", _rel(d.Q, Q_ref))
                if G_ref is not None and np.all(np.abs(G_ref) <= big):
                    assert _rel(d.G, G_ref) <= tol, (name, dt, "G")
                eig = torch.linalg.eigvalsh(d.Q.double())
                assert bool((eig >= -1e2 * torch.finfo(dtype).eps * eig.abs().max()).all()), (name, dt, "PSD")
