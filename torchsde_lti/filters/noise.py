r"""Observation-noise models of the filters: Gaussian, or Student-t with ν degrees of freedom.

A noise model is data the filters' loops read after each step's (Gaussian) update; the loops
stay one. It says two things:

- the step's log-likelihood core, from the whitened innovation's log-determinant
  ``log |S|`` (S the innovation covariance of the whitened model), its squared Mahalanobis
  length ``Δ² = eᵀ S⁻¹ e`` and the number d of observed components (the loops' scalar updates
  give ``log |S| = Σ_j log s_j`` and ``Δ² = Σ_j e_j² / s_j``; the callers add the constants
  ``−½ d log 2π − log |L_R|`` common to both);
- the rescaling of the filtered covariance after the update (none for a Gaussian).

:class:`GaussianNoise` is the Kalman filter. :class:`StudentTNoise` is the Student-t filter of
Roth, Özkan & Gustafsson (2013, "A Student's t filter for heavy tailed process and
measurement noise", ICASSP): the state, the process noise and the measurement noise are
jointly Student-t with ν degrees of freedom, Q, R and every covariance of the filter are the
t's *scale matrices* (the covariance is ``ν / (ν − 2)`` times the scale), and

- the prediction is the Kalman prediction of the scale matrix: ``P⁻ = A P Aᵀ + Q``;
- the one-step predictive is exactly ``St(y; H m⁻, S = H P⁻ Hᵀ + R, ν)`` over the d observed
  components, with log density ``log Γ((ν+d)/2) − log Γ(ν/2) − (d/2) log(νπ) − ½ log |S|
  − ((ν+d)/2) log(1 + Δ²/ν)``;
- the posterior is ``St(m⁺, (ν + Δ²)/(ν + d) · P⁺, ν + d)`` with (m⁺, P⁺) the Kalman update
  (so the mean update is the Kalman one: linear in y; the scale grows with the surprise Δ²);
- its ν + d degrees of freedom are brought back to ν by matching the covariance:
  ``scale × (ν + d)(ν − 2) / ((ν + d − 2) ν)``, so in all the filtered scale is
  ``f P⁺`` with ``f = (1 + Δ²/ν)(1 − d / (ν + d − 2))`` (ν > 2).

As ν → ∞, f → 1 and the density → the Gaussian's, the gap shrinking like Δ⁴/ν: on residuals
of Δ² ~ 100, ν = 1e8 is the Kalman filter to ~4e-4 and ν = 1e12 to ~4e-8 (tests). A
fully missing step (d = 0) has f = 1 and contributes 0. The IMM mixes t-distributed modes
matched in their covariances. With one shared ν the factor ``ν / (ν − 2)`` of every mode's
scale cancels and the spread of the mode means enters a scale matrix with the weight
``(ν − 2) / ν`` (:meth:`StudentTNoise.spread`). With a ν per mode (``per_mode``: dof (..., M))
the modes' scales P_i are covariances ``r_i P_i`` (``r_i = ν_i / (ν_i − 2)``,
:meth:`StudentTNoise.covariance_factor`), mixed as Gaussians, and mixed into mode j they are
its scale again, ``Σ_i w_ij (r_i P_i + d_ij d_ijᵀ) / r_j``; the combined output of such an IMM
is the mixture's covariance (no single ν).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple, TypeVar

import torch
from torch import Tensor

from torchsde_lti.core.validation import shape_str

T = TypeVar("T")
_LOG_2PI = math.log(2.0 * math.pi)

__all__ = ["GAUSSIAN", "GaussianNoise", "NoiseModel", "StudentTNoise", "log_gamma_ratio", "weighted_outer"]

#: Below this x, ``log_gamma_ratio`` takes torch's lgamma; above, Stirling's series (whose 7
#: terms are below 1e-15 there).
_STIRLING_FROM = 8.0
#: Stirling's series of ``lgamma(z) − ((z − ½) log z − z + ½ log 2π)``: the coefficients of
#: z^-1, z^-3, …, z^-13 (B_2k / (2k (2k − 1))).
_STIRLING = (1 / 12, -1 / 360, 1 / 1260, -1 / 1680, 1 / 1188, -691 / 360360, 1 / 156)


def _stirling_tail(z: Tensor) -> Tensor:
    """``lgamma(z) − ((z − ½) log z − z + ½ log 2π)`` by Stirling's series (z ≥ 8)."""
    w = 1.0 / (z * z)
    acc = torch.full_like(z, _STIRLING[-1])
    for c in reversed(_STIRLING[:-1]):
        acc = acc * w + c
    return acc / z


def log_gamma_ratio(x: Tensor, a: Tensor) -> Tensor:
    r"""``log Γ(x + a) − log Γ(x) − a log x`` for x ≥ 1, a ≥ 0, elementwise, accurate for any x.

    The difference of two lgamma values of size ~x log x loses all precision for large x
    (lgamma(5e7) ≈ 8e8: float32 rounds it to ±32); here, for x ≥ 8, Stirling's series gives
    ``(x + a − ½) log1p(a/x) − a + ζ(x + a) − ζ(x)`` (ζ the series' tail), which → 0 as x → ∞.
    Differentiable in x and a (both branches are finite everywhere).
    """
    big = x >= _STIRLING_FROM
    xs = torch.where(big, x, torch.full_like(x, _STIRLING_FROM))
    stirling = (xs + a - 0.5) * torch.log1p(a / xs) - a + _stirling_tail(xs + a) - _stirling_tail(xs)
    xd = torch.where(big, torch.ones_like(x), x)
    direct = torch.lgamma(xd + a) - torch.lgamma(xd) - a * torch.log(xd)
    return torch.where(big, stirling, direct)


def weighted_outer(d: Tensor, spread: Tensor | None, event: int) -> Tensor:
    """``w d dᵀ`` of deviations d (..., n): the outer products (..., n, n) weighted by ``spread`` w,
    (b) over the batch before d's last ``event − 1`` dims (None: 1; :meth:`StudentTNoise.spread`)."""
    outer = d.unsqueeze(-1) * d.unsqueeze(-2)
    return outer if spread is None else outer * spread.reshape(*spread.shape, *[1] * event)


class GaussianNoise(NamedTuple):
    """Gaussian observation (and process) noise: the Kalman filter (no fields)."""

    def log_likelihood_core(self, log_det: Tensor, maha: Tensor, d: Tensor) -> Tensor:
        """``−½ (log |S| + Δ²)`` (log N without ``−½ d log 2π``); every argument (*b)."""
        return -0.5 * (log_det + maha)

    def scale(self, maha: Tensor, d: Tensor) -> Tensor | None:
        """The posterior scale factor: None (the Kalman update's covariance stands)."""
        return None

    def update(self, P: Tensor, e: Sequence[Tensor], s: Sequence[Tensor], d: Tensor) -> Tensor:
        """The filtered covariance P (n, n, *b) unchanged."""
        return P

    def step_update(self, P: Tensor, e: Tensor, s: Tensor, obs: Tensor) -> tuple[Tensor, Tensor]:
        """The online step's (P, ``Σ_j (log s_j + e_j² / s_j + log 2π [j observed])``): P (n, n, *b)
        unchanged; e, s (m, *b) the whitened innovations and their variances, obs (m, *b) bool."""
        return P, torch.add(torch.addcdiv(torch.log(s), e * e, s), obs.to(s.dtype), alpha=_LOG_2PI).sum(0)

    def spread(self) -> Tensor | None:
        """The weight of the spread of mode means in a mixed covariance: None (1)."""
        return None

    def covariance_factor(self) -> Tensor | None:
        """The modes' covariance per unit scale matrix: None (1, the covariances mix as they are)."""
        return None

    def with_axis(self) -> GaussianNoise:
        """The noise of an IMM's results with one more axis (T or K) before the modes: itself."""
        return self

    def full_batch(self, P: Tensor, mean: Tensor) -> Tensor:
        """The loop's initial covariance P (n, n, *b): P itself (its batch is the model's)."""
        return P

    def scanned(self, d: Tensor) -> tuple[Tensor, ...]:
        """What the structured loop scans along besides the model: nothing."""
        return ()

    def over_modes(self) -> GaussianNoise:
        """The noise of each mode of an IMM (the modes a batch dimension): itself."""
        return self

    def update_bound(self, update: T) -> T | None:
        """``update`` (the modules' (H, observed, P) of the updates): a Kalman update's filtered
        variance of an observed component is below R, which the modules check."""
        return update

    def check(
        self, batch: Sequence[int], algorithm: str, validate_args: bool = True, modes: int | None = None
    ) -> GaussianNoise:
        """Itself (every batch, algorithm and number of modes)."""
        return self


class StudentTNoise(NamedTuple):
    """Student-t noise with ``dof`` ν > 2 degrees of freedom: the filter of Roth et al. (2013)
    (module docstring). dof: () or a batch shape that broadcasts to the filter's batch; with
    ``per_mode`` (an IMM only), (..., M): each mode's ν on the last axis, the rest broadcasting
    to the filter's batch."""

    dof: Tensor
    per_mode: bool = False

    def log_likelihood_core(self, log_det: Tensor, maha: Tensor, d: Tensor) -> Tensor:
        """``log St(e; 0, S, ν) + (d/2) log 2π``: ``log Γ((ν+d)/2) − log Γ(ν/2) − (d/2) log(ν/2)
        − ½ log |S| − ((ν+d)/2) log1p(Δ²/ν)``; every argument (*b), d the observed count."""
        nu = self.dof
        return log_gamma_ratio(0.5 * nu, 0.5 * d) - 0.5 * log_det - 0.5 * (nu + d) * torch.log1p(maha / nu)

    def scale(self, maha: Tensor, d: Tensor) -> Tensor:
        """The posterior scale factor ``f = (1 + Δ²/ν)(1 − d / (ν + d − 2))`` (*b)."""
        nu = self.dof
        return (1.0 + maha / nu) * (1.0 - d / (nu + d - 2.0))

    def update(self, P: Tensor, e: Sequence[Tensor], s: Sequence[Tensor], d: Tensor) -> Tensor:
        """``f P`` of the Kalman-updated scale P (n, n, *b), from the step's whitened scalar
        innovations e_j and their variances s_j (*b each) and the observed count d (*b)."""
        maha = sum(ej * ej / sj for ej, sj in zip(e, s))
        assert isinstance(maha, Tensor)
        return P * self.scale(maha, d)

    def step_update(self, P: Tensor, e: Tensor, s: Tensor, obs: Tensor) -> tuple[Tensor, Tensor]:
        """The online step's (``f P``, ``−2 log St + log|S_R|`` terms): as :meth:`GaussianNoise.step_update`,
        −2 × :meth:`log_likelihood_core` + d log 2π (the caller subtracts the whitening's log-determinant)."""
        d = obs.to(s.dtype).sum(0)
        maha = (e * e / s).sum(0)
        core = self.log_likelihood_core(torch.log(s).sum(0), maha, d)
        return P * self.scale(maha, d), -2.0 * core + _LOG_2PI * d

    def spread(self) -> Tensor | None:
        """``(ν − 2) / ν``: the weight of the spread of mode means in a mixed scale matrix (the
        mixture matched in its covariance); None (1) with ``per_mode``: the modes mix as
        covariances (:meth:`covariance_factor`)."""
        return None if self.per_mode else (self.dof - 2.0) / self.dof

    def covariance_factor(self) -> Tensor | None:
        """``ν_i / (ν_i − 2)`` (..., M): each mode's covariance per unit scale, with ``per_mode``;
        None with one ν (the common factor cancels in the mixing: :meth:`spread`)."""
        return self.dof / (self.dof - 2.0) if self.per_mode else None

    def with_axis(self) -> StudentTNoise:
        """The noise of an IMM's results with one more axis (T or K) before the modes: ν (...)
        as (..., 1), or, ``per_mode``, (..., M) as (..., 1, M)."""
        return StudentTNoise(self.dof.unsqueeze(-2), True) if self.per_mode else StudentTNoise(self.dof.unsqueeze(-1))

    def full_batch(self, P: Tensor, mean: Tensor) -> Tensor:
        """The loop's initial scale P (n, n, *b) expanded to the batch of the mean (n, *b'):
        the rescaling depends on each series' innovations, so every step's P has that batch."""
        return P.expand(*P.shape[:2], *mean.shape[1:])

    def scanned(self, d: Tensor) -> tuple[Tensor, ...]:
        """The observed counts d (T, *b) and ν stacked, (T, 2, *b'), for the structured loop."""
        return (torch.stack(torch.broadcast_tensors(d, self.dof), 1),)

    def over_modes(self) -> StudentTNoise:
        """The noise of each mode of an IMM (the modes a batch dimension after the batch): ν
        (...) as (..., 1), shared by the modes; ``per_mode``, ν (..., M) itself, its last axis
        the modes'."""
        if self.per_mode:
            return StudentTNoise(self.dof)
        return StudentTNoise(self.dof.unsqueeze(-1)) if self.dof.dim() else self

    def update_bound(self, update: T) -> T | None:
        """None: the filtered scale ``f P⁺`` has no bound by R (f grows with Δ²)."""
        return None

    def check(
        self, batch: Sequence[int], algorithm: str, validate_args: bool = True, modes: int | None = None
    ) -> StudentTNoise:
        """Itself, after checking that ν's shape broadcasts to the filter's ``batch`` without
        growing it (``per_mode``: its last axis of size ``modes``, the IMM's M, and a single
        filter, ``modes`` None, refuses it), that ``algorithm`` has the t update and
        (``validate_args``) that ν is finite and > 2; ValueError naming them otherwise."""
        if algorithm == "scan":
            raise ValueError(
                "noise=StudentTNoise has no associative scan (its scale recursion is not linear): use "
                "algorithm='sequential' (the default) or 'square_root'"
            )
        shape = tuple(self.dof.shape)
        if self.per_mode:
            if modes is None or not shape or shape[-1] != modes:
                raise ValueError(
                    f"noise.dof of shape {shape_str(self.dof)} is per mode: it needs an IMM's modes on its last "
                    f"axis (M={modes}; a single filter takes one ν)"
                )
            shape = shape[:-1]
        if len(shape) > len(batch) or any(s not in (1, b) for s, b in zip(shape[::-1], tuple(batch)[::-1])):
            raise ValueError(
                f"noise.dof of shape {shape_str(self.dof)} must broadcast to the filter's batch {tuple(batch)}"
            )
        if validate_args and not bool(torch.all(torch.isfinite(self.dof) & (self.dof > 2.0))):
            raise ValueError(f"noise.dof must be finite and > 2 (the t's covariance exists), got {self.dof.tolist()}")
        return self


#: A noise model of the filters.
NoiseModel = GaussianNoise | StudentTNoise
#: The Gaussian noise model (the filters' default).
GAUSSIAN = GaussianNoise()
