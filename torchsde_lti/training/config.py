"""Checks of a composed run config, before any work: each error names the key.

:func:`check_config` catches the values that would otherwise run silently wrong or fail
late (``trainer.max_epochs=-1`` trains forever; ``lr: 0`` trains nothing; a float seed
is truncated; a negative thread count fails inside torch). Values the built objects check
themselves (``data.noise``, ``module.k_step``, a model's ``q``...) fail when built, with the
config node named by :func:`instantiate_node`.
"""

from __future__ import annotations

import math
import re
from typing import Any

from hydra.errors import InstantiationException
from hydra.utils import instantiate
from lightning.fabric.utilities.exceptions import MisconfigurationException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

__all__ = ["check_config", "instantiate_node"]

_REQUIRED = ("model", "data", "trainer", "filter", "module")
_MAX_SEED = 2**32 - 1  # numpy's and Lightning's seed range


def _value(cfg: DictConfig, key: str) -> Any:
    """The resolved value at a dotted key (None when absent); a broken interpolation names the key."""
    try:
        return OmegaConf.select(cfg, key, default=None, throw_on_missing=True)
    except OmegaConfBaseException as err:
        raise ValueError(f"config key {key}: {err}") from None


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _integer(cfg: DictConfig, key: str, low: int, *, optional: bool = True, note: str = "") -> None:
    x = _value(cfg, key)
    if x is None and optional:
        return
    if not _is_int(x) or x < low:
        raise ValueError(f"{key} must be an integer >= {low}{note}, got {x!r}")


def _positive(cfg: DictConfig, key: str, *, allow_zero: bool = False) -> None:
    x = _value(cfg, key)
    if x is None:
        return
    ok = _is_number(x) and math.isfinite(x) and (x >= 0 if allow_zero else x > 0)
    if not ok:
        raise ValueError(f"{key} must be a finite number {'>= 0' if allow_zero else '> 0'}, got {x!r}")


def _boolean(cfg: DictConfig, key: str) -> None:
    x = _value(cfg, key)
    if x is not None and not isinstance(x, bool):
        raise ValueError(f"{key} must be true or false, got {x!r}")


def _check_filter_model(cfg: DictConfig) -> None:
    """An IMM filter learns a bank of modes (a model group with ``mode_names``, e.g. model=imm);
    a Kalman filter one model."""
    target = str(OmegaConf.select(cfg, "filter._target_", default="") or "")
    model = OmegaConf.select(cfg, "model.name", default=None)
    bank = OmegaConf.select(cfg, "model.mode_names", default=None) is not None
    if target.endswith("IMMFilter") and not bank:
        raise ValueError(
            f"filter=imm needs a bank of modes: model=imm or model=imm3 (with truth=null and real data, as "
            f"experiment=ais_imm and experiment=ais_moving set), got model={model}"
        )
    if target.endswith(".KalmanFilter") and bank:
        raise ValueError(f"model={model} is a bank of modes for filter=imm (experiment=ais_imm), not for filter=kalman")


def check_config(cfg: DictConfig) -> None:
    """Raise ValueError naming the key for a config that cannot make a sensible run.

    Checked: the required nodes; the filter and model paired (filter=imm with a bank of modes); ``dtype``; ``seed`` (an integer in [0, 2³² − 1]);
    ``num_threads`` (null, 0 = torch's default, or >= 1); ``init_jitter`` >= 0;
    ``restart`` >= 0; ``test`` / ``plots`` booleans; ``ckpt_path`` a string;
    ``trainer.max_epochs`` >= 1 (``-1``, Lightning's "train forever", is refused; null only
    with a positive ``trainer.max_steps``), ``trainer.max_steps`` (-1 or >= 1),
    ``trainer.min_epochs`` <= max_epochs; ``data.batch_size`` (null or >= 1);
    ``module.optimizer.lr`` > 0 and its ``weight_decay`` / ``momentum`` >= 0, ``eps`` > 0;
    ``module.scheduler.T_max`` >= 1 (where the scheduler has one; null is refused) and ``eta_min`` >= 0; ``module.grad_clip_norm`` >= 0.
    """
    for key in _REQUIRED:
        if cfg.get(key) is None:
            raise ValueError(f"config is missing the '{key}' node")
    _check_filter_model(cfg)
    dtype = _value(cfg, "dtype")
    if dtype not in ("float32", "float64"):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    seed = _value(cfg, "seed")
    if not _is_int(seed) or not 0 <= seed <= _MAX_SEED:
        raise ValueError(f"seed must be an integer in [0, {_MAX_SEED}], got {seed!r}")
    _integer(cfg, "num_threads", 0, note=" (0 or null: torch's default)")
    _positive(cfg, "init_jitter", allow_zero=True)
    _integer(cfg, "restart", 0)
    _boolean(cfg, "test")
    _boolean(cfg, "plots")
    ckpt = _value(cfg, "ckpt_path")
    if ckpt is not None and (not isinstance(ckpt, str) or not ckpt):
        raise ValueError(f"ckpt_path must be null or the path of a checkpoint file, got {ckpt!r}")

    max_epochs, max_steps = _value(cfg, "trainer.max_epochs"), _value(cfg, "trainer.max_steps")
    if max_steps is not None and max_steps != -1:
        _integer(cfg, "trainer.max_steps", 1, note=" (or -1: no step limit)")
    if max_epochs is None:
        if not (_is_int(max_steps) and max_steps >= 1):
            raise ValueError(
                "trainer.max_epochs must be an integer >= 1 (null only with trainer.max_steps >= 1), got None"
            )
    elif not _is_int(max_epochs) or max_epochs < 1:
        forever = " (-1 means 'train forever' in Lightning; give a number of epochs)" if max_epochs == -1 else ""
        raise ValueError(f"trainer.max_epochs must be an integer >= 1{forever}, got {max_epochs!r}")
    _integer(cfg, "trainer.min_epochs", 0)
    min_epochs = _value(cfg, "trainer.min_epochs")
    if _is_int(min_epochs) and _is_int(max_epochs) and min_epochs > max_epochs:
        raise ValueError(f"trainer.min_epochs ({min_epochs}) must be <= trainer.max_epochs ({max_epochs})")

    batch_size = _value(cfg, "data.batch_size")
    if batch_size is not None and (not _is_int(batch_size) or batch_size < 1):
        raise ValueError(
            f"data.batch_size must be null (a whole split per batch) or an integer >= 1, got {batch_size!r}"
        )

    if _value(cfg, "module.optimizer") is not None:
        lr = _value(cfg, "module.optimizer.lr")
        if lr is not None and not (_is_number(lr) and math.isfinite(lr) and lr > 0):
            raise ValueError(f"module.optimizer.lr must be a finite number > 0, got {lr!r}")
        for key in ("weight_decay", "momentum"):
            _positive(cfg, f"module.optimizer.{key}", allow_zero=True)
        _positive(cfg, "module.optimizer.eps")
    scheduler = _value(cfg, "module.scheduler")
    if scheduler is not None:
        if "T_max" in scheduler:  # (null: trainer.max_epochs=null, which it follows by default)
            follows = " (it follows trainer.max_epochs: with trainer.max_epochs=null give module.scheduler.T_max)"
            _integer(cfg, "module.scheduler.T_max", 1, optional=False, note=follows)
        _positive(cfg, "module.scheduler.eta_min", allow_zero=True)
    _positive(cfg, "module.grad_clip_norm", allow_zero=True)


def instantiate_node(cfg: DictConfig, key: str, **kwargs: Any) -> Any:
    """``hydra.utils.instantiate`` of the node at the dotted ``key`` of ``cfg``; a ValueError / TypeError (or Lightning's
    MisconfigurationException) raised by the target comes out as a ValueError / TypeError that
    names the config node and the target, instead of Hydra's InstantiationException."""
    try:
        return instantiate(OmegaConf.select(cfg, key), **kwargs)
    except InstantiationException as err:
        cause = err.__cause__
        found = re.search(r"full_key: (\S+)", str(err))
        where = found.group(1) if found else key
        target = re.search(r"target '([^']+)'", str(err))
        called = f" (calling {target.group(1)})" if target else ""
        if isinstance(cause, TypeError):
            raise TypeError(f"config {where}{called}: {cause}") from cause
        if isinstance(cause, (ValueError, MisconfigurationException)):
            raise ValueError(f"config {where}{called}: {cause}") from cause
        raise
