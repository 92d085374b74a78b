"""Lightning glue: train a Kalman filter's learned motion model by maximum likelihood.

Loss (per batch) = -Σ_tracks log p(y_1:T) / #(observed scalars in y), from the filter's
prediction-error decomposition, optionally plus ``k_step_weight`` × the k-step-ahead predictive
NLL per observed scalar (summed over the horizons of a list ``k_step``): a KalmanFilter pushes
each filtered (m_t, P_t) k steps through the exact discrete model (A, Q, G u of each step) and
scores y_{t+k}; an IMMFilter scores y_{t+k} under its forecast MIXTURE over the lead
τ = t_{t+k} − t_t (:mod:`torchsde_lti.evaluation.batch_scores`). Batches are :class:`~torchsde_lti.data.TrackBatch`.

Logged, each over a whole epoch (every batch, every process): ``train/nll``, ``{val,test}/nll``
(Σ NLL / Σ observed scalars), ``{val,test}/rmse`` (one-step prediction error of y,
√(Σ squared errors / Σ observed scalars)), ``{val,test}/state_rmse`` (filtered mean vs true
state, when batches carry ``x``), ``{val,test}/cover2s`` (the share of reports after each
window's first whose observed coordinates lie in the one-step predictive's 86.5 % region:
:func:`~torchsde_lti.evaluation.hpd_inside`, d² = νᵀS⁻¹ν <= 4 for m = 2), with a truth
``val/param_error`` (the largest of :func:`~torchsde_lti.evaluation.filter_errors`) and
``val/param_error/<name>``, and ``param/<name>`` (every learned value,
:func:`~torchsde_lti.evaluation.flat_values`) after each training epoch. A non-finite loss or
gradient skips the step (warned, counted in ``skipped_steps`` / ``train/skipped_steps``);
gradient-norm clipping is the Trainer's (``trainer.gradient_clip_val``).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from lightning.pytorch import LightningModule
from torch import Tensor

from torchsde_lti.data.tracks import TrackBatch
from torchsde_lti.evaluation import (
    batch_predictive,
    coverage_counts,
    filter_errors,
    filter_values,
    flat_values,
    imm_k_step_nll,  # also torchsde_lti.training.module.imm_k_step_nll, for old imports
    kalman_k_step_nll,
    predictive_dof,
)
from torchsde_lti.nn import NonFiniteLikelihoodError
from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import KalmanFilter
from torchsde_lti.nn.noise import StudentT
from torchsde_lti.nn.parametrizations import reset_default_floors

__all__ = ["KalmanFilterModule"]


class KalmanFilterModule(LightningModule):
    """LightningModule around a ``tl.KalmanFilter`` or ``tl.IMMFilter`` whose motion models are learned.

    Args:
        kf: the filter (its models' learned parameters, R, an IMM's switching rates, ...):
            anything with ``kf(y, dt, u=...)``, ``H`` and ``modes()`` (:class:`~torchsde_lti.nn.FilterMode`).
        optimizer, scheduler: ``functools.partial`` of a torch optimizer and (optional) of an LR
            scheduler stepped per epoch (Hydra ``_partial_: true``).
        truth: optional {"sde": true LTISDE, "R": true R, "H"} for parameter errors.
        k_step, k_step_weight: horizon(s) in reports of the optional k-step-ahead predictive loss
            (an int, 0 = off, or a list whose NLLs are added) and its weight.
        dtype: "float64" or "float32": parameters and batches, and the default floors of the
            filter's positive parametrisations (this dtype's eps:
            :func:`~torchsde_lti.nn.parametrizations.reset_default_floors`).
        param_names: the scalars to track (default: the model's own).
        compare: which of "F", "Qc", "R" are compared with the truth (``learn`` says what is trained).
        skip_nonfinite: a NaN/Inf loss or gradient drops that step's gradients before the
            Trainer clips them (Adam leaves parameters and moments as they are, L-BFGS stops its
            iteration), warns, and counts it in ``skipped_steps`` (saved in checkpoints).
    """

    def __init__(
        self,
        kf: KalmanFilter | IMMFilter,
        optimizer: Callable[..., torch.optim.Optimizer] | None = None,
        scheduler: Callable[..., Any] | None = None,
        truth: Mapping[str, Any] | None = None,
        k_step: int | Sequence[int] = 0,
        k_step_weight: float = 0.0,
        dtype: str = "float64",
        param_names: Sequence[str] | None = None,
        compare: Sequence[str] = ("F", "Qc", "R"),
        skip_nonfinite: bool = True,
    ) -> None:
        super().__init__()
        if dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
        ks = [int(k) for k in k_step] if isinstance(k_step, Sequence) else [int(k_step)]
        if not ks or any(k < 0 for k in ks) or not k_step_weight >= 0:
            raise ValueError(
                f"k_step must be >= 0 (an int, or a non-empty list of ints) and k_step_weight >= 0, "
                f"got {k_step}, {k_step_weight}"
            )
        if max(ks) > 0 and k_step_weight > 0 and not isinstance(kf, (KalmanFilter, IMMFilter)):
            raise ValueError(
                f"the k-step loss (k_step={k_step}, k_step_weight={k_step_weight}) needs a KalmanFilter "
                f"or an IMMFilter, got {type(kf).__name__}; set k_step=0"
            )
        if max(ks) > 0 and k_step_weight > 0 and isinstance(getattr(kf, "noise", None), StudentT):
            raise ValueError(
                f"the k-step loss (k_step={k_step}, k_step_weight={k_step_weight}) is a Gaussian density and the "
                "filter's observation noise is a Student t: set module.k_step_weight=0"
            )
        k_step = ks if isinstance(k_step, Sequence) else ks[0]
        # plain containers only, so checkpoints load with torch.load(weights_only=True)
        compare = [str(x) for x in compare]
        param_names = [str(x) for x in param_names] if param_names is not None else None
        self.save_hyperparameters(ignore=["kf", "optimizer", "scheduler", "truth"])
        self.float_dtype = getattr(torch, dtype)
        self.kf = kf.to(self.float_dtype)
        reset_default_floors(self.kf, self.float_dtype)
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler
        # a plain dict, so the true model is neither trained nor saved in checkpoints
        self._truth = dict(truth) if truth is not None else None
        self.k_steps = [k for k in ks if k > 0]
        self.k_step, self.k_step_weight = max(ks), float(k_step_weight)
        self.param_names = list(param_names) if param_names is not None else None
        self.compare = tuple(compare)
        self.skip_nonfinite = bool(skip_nonfinite)
        self.skipped_steps = 0
        self._finite_loss = True  # of the last training step (a closure call), read before the optimizer step
        self._sums: dict[str, dict[str, Tensor]] = {}  # stage -> score -> (numerator, denominator) of one epoch
        self.trained_at: int | None = None  # the optimizer step after this process's last training batch
        self.validated_at: int | None = None  # ... and at the end of its last validation (not a sanity check)

    def unpack(self, batch: TrackBatch) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None, Tensor | None]:
        """(y, dt, mask, u, x) of a :class:`~torchsde_lti.data.TrackBatch`, floats in the module's dtype."""
        if not isinstance(batch, TrackBatch):
            raise TypeError(f"batches must be torchsde_lti.data.TrackBatch, got {type(batch).__name__}")
        u, x = (None if t is None else t.to(self.float_dtype) for t in (batch.u, batch.x))
        return batch.y.to(self.float_dtype), batch.dt.to(self.float_dtype), batch.mask, u, x

    def forward(self, y: Tensor, dt: Tensor, u: Tensor | None = None) -> Any:
        """Run the filter: y (B, T, m), dt (B, T), u (B, T, p) -> the filter's output."""
        return self.kf(y, dt, u=u)

    def k_step_nll(
        self,
        out: Any,
        y: Tensor,
        observed: Tensor,
        k: int | None = None,
        dt: Tensor | None = None,
        u: Tensor | None = None,
    ) -> Tensor:
        """Σ of the k-step-ahead predictive NLL of y_{t+k} given the filtered state at t:
        :func:`~torchsde_lti.evaluation.kalman_k_step_nll` (with the inputs ``u``) or, for an
        IMMFilter, :func:`~torchsde_lti.evaluation.imm_k_step_nll` (needs ``dt``). ``k``
        defaults to ``self.k_step``. Returns a scalar.
        """
        k = self.k_step if k is None else int(k)
        if not isinstance(self.kf, IMMFilter):
            return kalman_k_step_nll(self.kf, out, y, observed, k, u)
        if dt is None:
            raise ValueError("the k-step loss of an IMMFilter needs dt (the leads t_{t+k} - t_t)")
        return imm_k_step_nll(self.kf, out, y, dt, observed, k)

    def _step(self, batch: Any) -> tuple[Tensor, Tensor, Any, dict[str, Any]]:
        y, dt, mask, u, x = self.unpack(batch)
        observed = ~torch.isnan(y) if mask is None else ~torch.isnan(y) & mask.unsqueeze(-1)
        if mask is not None:  # padding: no observation, no motion
            y = torch.where(mask.unsqueeze(-1), y, torch.full_like(y, math.nan))
            dt = torch.where(mask, dt, torch.zeros_like(dt))
        out = self.kf(y, dt, u=u)
        count = observed.sum().clamp_min(1).to(y.dtype)
        nll = -out.log_likelihood.sum() / count
        loss = nll
        if self.k_steps and self.k_step_weight > 0:
            kst = sum(self.k_step_nll(out, y, observed, k, dt, u) for k in self.k_steps)
            loss = loss + self.k_step_weight * kst / count
        return loss, nll, out, {"y": y, "x": x, "observed": observed, "mask": mask, "count": count, "u": u}

    def training_step(self, batch: Any, batch_idx: int) -> Tensor:
        try:
            loss, nll, _, info = self._step(batch)
        except NonFiniteLikelihoodError:
            if not self.skip_nonfinite:
                raise
            # a NaN loss on the parameters' graph: the gradient guard skips, counts and warns
            # (and L-BFGS, seeing no gradient, ends its iteration)
            params = [p for p in self.parameters() if p.requires_grad]
            self._finite_loss = False
            return sum((p.sum() * 0.0 for p in params), torch.zeros((), dtype=self.float_dtype)) + math.nan
        self._finite_loss = bool(torch.isfinite(loss.detach()))
        # weighted by observed scalars: the epoch's value is the NLL per observed scalar of all its batches
        count = int(info["count"])
        self.log("train/nll", nll, on_step=False, on_epoch=True, prog_bar=True, batch_size=count, sync_dist=True)
        if self.k_steps and self.k_step_weight > 0:
            self.log("train/loss", loss, on_step=False, on_epoch=True, batch_size=count, sync_dist=True)
        return loss

    def _eval_step(self, batch: Any, stage: str) -> Tensor:
        loss, nll, out, info = self._step(batch)
        y, observed, x, mask = info["y"], info["observed"], info["x"], info["mask"]
        self.log(
            f"{stage}/nll", nll, on_epoch=True, prog_bar=stage == "val", batch_size=int(info["count"]), sync_dist=True
        )
        with torch.no_grad():
            w, mu, S = batch_predictive(self.kf, out, info["u"])
            err = torch.where(observed, (w.unsqueeze(-1) * mu).sum(-2) - y, torch.zeros_like(y))
            sums = {
                "rmse": ((err**2).sum(), observed.sum()),
                "cover2s": coverage_counts(y, w, mu, S, observed, self._dof()),
            }
            if x is not None and x.shape[-1] == out.mean.shape[-1]:  # the truth's state (same kind of model)
                valid = torch.ones_like(x[..., 0], dtype=torch.bool) if mask is None else mask
                sums["state_rmse"] = ((((out.mean - x) ** 2).sum(-1) * valid).sum(), valid.sum() * x.shape[-1])
        epoch = self._sums.setdefault(stage, {})
        for name, (num, den) in sums.items():
            pair = torch.stack([num.to(torch.float64), den.to(torch.float64)])
            epoch[name] = pair if name not in epoch else epoch[name] + pair
        return loss

    def _log_scores(self, stage: str) -> None:
        """``{stage}/rmse``, ``state_rmse`` and ``cover2s`` of the whole epoch (all batches, all processes)."""
        sums = self._sums.pop(stage, {})
        if not sums:
            return
        total = self.trainer.strategy.reduce(torch.stack(list(sums.values())), reduce_op="sum")
        for name, (num, den) in zip(sums, total):
            value = num / den.clamp_min(1)
            self.log(f"{stage}/{name}", value if name == "cover2s" else value.sqrt(), sync_dist=False)

    def on_validation_epoch_start(self) -> None:
        self._sums.pop("val", None)

    def on_test_epoch_start(self) -> None:
        self._sums.pop("test", None)

    def on_test_epoch_end(self) -> None:
        self._log_scores("test")

    def validation_step(self, batch: Any, batch_idx: int) -> Tensor:
        return self._eval_step(batch, "val")

    def test_step(self, batch: Any, batch_idx: int) -> Tensor:
        return self._eval_step(batch, "test")

    def parameter_errors(self) -> dict[str, float]:
        """:func:`~torchsde_lti.evaluation.filter_errors` of the filter against the truth ({} without one)."""
        return filter_errors(self.kf, self._truth, self.param_names, self.compare)

    def on_train_batch_end(self, *args: Any) -> None:
        self.trained_at = int(self.global_step)

    def on_validation_epoch_end(self) -> None:
        self._log_scores("val")
        if not self.trainer.sanity_checking:
            self.validated_at = int(self.global_step)
        errors = self.parameter_errors()
        for name, value in errors.items():
            self.log(f"val/param_error/{name}", value, sync_dist=False)
        if errors:
            self.log("val/param_error", max(errors.values()), prog_bar=True, sync_dist=False)

    @property
    def validation_stale(self) -> bool:
        """Whether this process trained after its last validation (``check_val_every_n_epoch > 1``,
        ``max_steps`` mid-epoch): the logged validation scores are older weights'."""
        return self.trained_at is not None and self.trained_at != self.validated_at

    def on_before_optimizer_step(self, optimizer: Any) -> None:
        """After the backward of every closure call, before the Trainer clips the gradients: skip
        a step whose loss or gradient is non-finite (grads -> None, counted, warned)."""
        params = [p for p in self.parameters() if p.grad is not None]
        finite = self._finite_loss and all(bool(torch.isfinite(p.grad).all()) for p in params if p.grad is not None)
        if finite or not self.skip_nonfinite:
            return
        for p in params:
            p.grad = None
        self.skipped_steps += 1
        warnings.warn(
            f"non-finite loss or gradient at epoch {self.current_epoch}, step {self.global_step}: "
            f"step skipped ({self.skipped_steps} so far)",
            RuntimeWarning,
            stacklevel=2,
        )

    def on_train_epoch_end(self) -> None:
        self.log("train/skipped_steps", float(self.skipped_steps), sync_dist=False)
        values = flat_values(filter_values(self.kf, self.param_names))
        self.log_dict({f"param/{k}": v for k, v in values.items()}, sync_dist=False)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["skipped_steps"] = int(self.skipped_steps)

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        self.skipped_steps = int(checkpoint.get("skipped_steps", 0))

    def _dof(self) -> Tensor | None:
        """ν of the filter's Student-t predictive (``noise=tl.StudentT``); None for a Gaussian."""
        return predictive_dof(self.kf) if isinstance(self.kf, (KalmanFilter, IMMFilter)) else None

    def configure_optimizers(self) -> Any:
        if self.optimizer_factory is None:
            raise ValueError("KalmanFilterModule needs an optimizer (a partial, e.g. Hydra `_partial_: true`)")
        opt = self.optimizer_factory(params=self.parameters())
        if self.scheduler_factory is None:
            return opt
        sched = self.scheduler_factory(optimizer=opt)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}
