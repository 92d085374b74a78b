"""Parameter recovery (torchsde_lti.evaluation.recovery) and the masked Gaussian NLL: parameter errors, identifiability.

References: scipy's multivariate normal, hand values, and a similarity-transformed twin model
(same likelihood, different F) for the identifiable autocovariance metric.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchsde_lti as tl
from torchsde_lti import models
from torchsde_lti.evaluation import (
    masked_gaussian_nll,
    observed_autocovariance,
    parameter_errors,
    raw_f_identifiable,
)


def test_masked_gaussian_nll_matches_scipy_marginal() -> None:
    stats = pytest.importorskip("scipy.stats")
    g = torch.Generator().manual_seed(0)
    M = torch.randn(3, 3, generator=g, dtype=torch.float64)
    S = M @ M.T + 0.5 * torch.eye(3, dtype=torch.float64)
    r = torch.randn(3, generator=g, dtype=torch.float64)
    obs = torch.tensor([True, False, True])
    got = masked_gaussian_nll(r.clone().index_fill_(0, torch.tensor([1]), math.nan), S, obs)
    idx = [0, 2]
    ref = -stats.multivariate_normal(mean=[0, 0], cov=S[idx][:, idx].numpy()).logpdf(r[idx].numpy())
    assert abs(float(got) - ref) < 1e-10
    assert float(masked_gaussian_nll(r, S, torch.zeros(3, dtype=torch.bool))) == 0.0


def test_parameter_errors_against_hand_values() -> None:
    truth = models.singer(alpha=0.5, q=2.0, dim=2)
    learned = models.singer(alpha=0.55, q=1.0, dim=2)
    e = parameter_errors(learned, truth, R=torch.eye(2) * 1.2, R_true=torch.eye(2), dts=(1.0,))
    assert e["alpha"] == pytest.approx(0.1, rel=1e-6) and e["q"] == pytest.approx(0.5, rel=1e-6)
    assert e["R"] == pytest.approx(0.2, rel=1e-6)
    assert e["expmF"] > 0
    same = parameter_errors(truth, truth)
    assert same["expmF"] == 0.0 and same["alpha"] == 0.0


def test_autocovariance_is_basis_free_and_raw_f_is_not() -> None:
    """A similarity transform of a free F (with H T⁻¹, T L) changes F but not H e^{Fτ} P∞ Hᵀ."""
    import torchsde_lti as tl

    F = torch.tensor([[0.0, 1.0], [-2.0, -0.6]], dtype=torch.float64)
    L = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    Qc = torch.tensor([[0.7]], dtype=torch.float64)
    H = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    T = torch.tensor([[1.0, 0.0], [0.8, 1.5]], dtype=torch.float64)  # H T⁻¹ = H: same observation
    Ti = torch.linalg.inv(T)
    truth = tl.LTISDE(F, L, Qc, F_constraint="hurwitz")
    twin = tl.LTISDE(T @ F @ Ti, T @ L, Qc, F_constraint="hurwitz")
    assert not raw_f_identifiable(twin, H) and raw_f_identifiable(twin, torch.eye(2, dtype=torch.float64))
    e = parameter_errors(twin, truth, H=H, compare=("F", "Qc"))
    assert set(e) == {"autocov"} and e["autocov"] < 1e-12
    raw = parameter_errors(twin, truth, compare=("F", "Qc"))  # without H: entrywise (and large)
    assert raw["expmF"] > 0.3
    # against a hand value: scalar OU dx = -a x dt + dβ (q): C(τ) = q/(2a) e^{-aτ}
    ou = tl.LTISDE(
        -torch.ones(1, 1, dtype=torch.float64),
        torch.ones(1, 1, dtype=torch.float64),
        2 * torch.ones(1, 1, dtype=torch.float64),
    )
    C = observed_autocovariance(ou, torch.ones(1, 1, dtype=torch.float64), [0.0, 1.0])
    torch.testing.assert_close(C.flatten(), torch.tensor([1.0, math.exp(-1.0)], dtype=torch.float64))


def test_qc_is_not_compared_where_the_data_cannot_identify_it() -> None:
    """A free F seen through a one-row H: the model T F T⁻¹, T Qc Tᵀ gives the same
    observations as the truth, so its raw Qc (220 % away) is not reported with compare=("Qc",)
    (the docstring: Qc only if identifiable); the observed autocovariance agrees."""
    d = torch.float64
    F = torch.tensor([[-1.0, 1.0], [0.0, -2.0]], dtype=d)
    T = torch.tensor([[2.0, 0.3], [0.0, 1.0]], dtype=d)
    eye = torch.eye(2, dtype=d)
    truth = tl.LTISDE(F, eye, eye, learn=("F", "Qc"))
    learned = tl.LTISDE(T @ F @ torch.linalg.inv(T), eye, T @ T.mT, learn=("F", "Qc"))
    H_true = torch.tensor([[1.0, 0.0]], dtype=d)
    H = H_true @ torch.linalg.inv(T)
    assert parameter_errors(learned, truth, H=H, H_true=H_true, compare=("Qc",)) == {}
    assert parameter_errors(learned, truth, H=H, H_true=H_true)["autocov"] < 1e-12
