"""The sequential loop as torch's structured scan (what torch.compile and torch.export run):
the filtered moments from the compiled loop, the rest batched after it, equal to the eager
loop with inputs, missing components, a covariance batch shared by the tracks and T = 1."""

from __future__ import annotations

import pytest
import torch

from torchsde_lti.filters.inputs import FilterInputs
from torchsde_lti.filters.kalman import run_filter

F64 = torch.float64


def _problem(T: int, seed: int) -> FilterInputs:
    g = torch.Generator().manual_seed(seed)
    n, m, p, B = 3, 2, 1, 5
    A = torch.eye(n, dtype=F64) + 0.1 * torch.randn(n, n, generator=g, dtype=F64)  # one A for every track and step
    X = torch.randn(n, n, generator=g, dtype=F64)
    Q = 0.1 * X @ X.mT + 0.01 * torch.eye(n, dtype=F64)
    H = torch.randn(m, n, generator=g, dtype=F64)
    R = torch.tensor([[0.4, 0.1], [0.1, 0.3]], dtype=F64)
    y = torch.randn(B, T, m, generator=g, dtype=F64)
    mask = torch.rand(B, T, m, generator=g) > 0.2  # missing components
    G = torch.randn(n, p, generator=g, dtype=F64)
    u = torch.randn(B, T, p, generator=g, dtype=F64)
    return FilterInputs(y, A, Q, H, R, torch.zeros(n, dtype=F64), torch.eye(n, dtype=F64), G, u, mask, None)


@pytest.mark.slow  # compiles one step of the loop: ≈ 10–20 s
@pytest.mark.parametrize("T", [1, 9])
def test_structured_loop_equals_eager_loop(T):
    args = _problem(T, seed=T)
    with torch.no_grad():
        ref = run_filter(args, "sequential")
        out = run_filter(args, "sequential", compiled_loop=True)
    for name in ("log_likelihood", "step_log_likelihood", "mean", "cov", "pred_mean", "pred_cov", "innovation"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=0, atol=1e-10, msg=name)
