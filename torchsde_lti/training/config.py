"""The run config's schema and checks, before any work: each error names the key.

:class:`RunSchema` (Hydra's ConfigStore ``train_schema``, first in ``conf/train.yaml``'s
defaults) types the top-level keys Hydra can check strictly: ``seed=1.5`` or
``num_threads=two`` fail when the config is composed, naming the key. OmegaConf converts
more loosely than a run needs elsewhere (``3`` to ``true``, ``123`` to ``"123"``), so ``test``,
``plots``, ``ckpt_path`` and ``dtype`` stay untyped there and :func:`check_config` checks them
with the ranges Hydra does not (``trainer.max_epochs=-1`` trains forever; ``lr: 0`` trains
nothing; a negative thread count fails inside torch). Values the built objects check themselves
(``data.noise``, ``module.k_step``, a model's ``q``...) fail when built, with the config node
named by :func:`instantiate_node`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any, Optional

from hydra.core.config_store import ConfigStore
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from lightning.fabric.utilities.exceptions import MisconfigurationException
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

__all__ = ["RunSchema", "check_config", "instantiate_node"]

_MAX_SEED = 2**32 - 1  # numpy's and Lightning's seed range


@dataclass
class RunSchema:
    """The top-level keys of ``conf/train.yaml`` (see there); the groups are checked by the
    objects built from them (:func:`instantiate_node`)."""

    seed: int = 0
    num_threads: Optional[int] = 1  # noqa: UP045 - OmegaConf reads typing.Optional, not `int | None`
    init_jitter: float = 0.0
    restart: int = 0
    dtype: Any = "float64"
    ckpt_path: Any = None
    test: Any = True
    plots: Any = True
    output_dir: str = MISSING
    model: Any = MISSING
    truth: Any = None
    data: Any = MISSING
    filter: Any = MISSING
    trainer: Any = MISSING
    logger: Any = None
    callbacks: Any = None
    module: Any = MISSING


ConfigStore.instance().store(name="train_schema", node=RunSchema)


def _value(cfg: DictConfig, key: str) -> Any:
    """The resolved value at a dotted key (None when absent); a broken interpolation names the key."""
    try:
        return OmegaConf.select(cfg, key, default=None, throw_on_missing=True)
    except OmegaConfBaseException as err:
        raise ValueError(f"config key {key}: {err}") from None


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _integer(cfg: DictConfig, key: str, low: int, *, optional: bool = True, note: str = "") -> None:
    x = _value(cfg, key)
    if not (x is None and optional) and (not _is_int(x) or x < low):
        raise ValueError(f"{key} must be an integer >= {low}{note}, got {x!r}")


def _positive(cfg: DictConfig, key: str, *, allow_zero: bool = False) -> None:
    x = _value(cfg, key)
    number = isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
    if x is not None and not (number and (x >= 0 if allow_zero else x > 0)):
        raise ValueError(f"{key} must be a finite number {'>= 0' if allow_zero else '> 0'}, got {x!r}")


def _check_filter_model(cfg: DictConfig) -> None:
    """An IMM filter learns a bank of modes (a model group with ``mode_names``); a Kalman filter one model."""
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

    Checked: the required nodes; the filter and model paired; ``dtype``; ``seed`` in
    [0, 2³² − 1]; ``num_threads`` (null, 0 = torch's default, or >= 1); ``init_jitter`` and
    ``restart`` >= 0; ``test`` / ``plots`` booleans; ``ckpt_path`` a string;
    ``trainer.max_epochs`` >= 1 (``-1``, Lightning's "train forever", is refused; null only
    with a positive ``trainer.max_steps``), ``trainer.max_steps`` (-1 or >= 1),
    ``trainer.min_epochs`` <= max_epochs, ``trainer.gradient_clip_val`` >= 0;
    ``data.batch_size`` (null or >= 1); ``module.optimizer.lr`` > 0, its ``weight_decay`` /
    ``momentum`` >= 0 and ``eps`` > 0; ``module.scheduler.T_max`` >= 1 (where the scheduler
    has one) and ``eta_min`` >= 0.
    """
    for key in ("model", "data", "trainer", "filter", "module"):
        if cfg.get(key) is None:
            raise ValueError(f"config is missing the '{key}' node")
    _check_filter_model(cfg)
    if (dtype := _value(cfg, "dtype")) not in ("float32", "float64"):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    _integer(cfg, "seed", 0, optional=False)
    if _value(cfg, "seed") > _MAX_SEED:
        raise ValueError(f"seed must be an integer in [0, {_MAX_SEED}], got {_value(cfg, 'seed')!r}")
    _integer(cfg, "num_threads", 0, note=" (0 or null: torch's default)")
    _positive(cfg, "init_jitter", allow_zero=True)
    _integer(cfg, "restart", 0)
    for key in ("test", "plots"):
        if not isinstance(x := _value(cfg, key), bool) and x is not None:
            raise ValueError(f"{key} must be true or false, got {x!r}")
    if (ckpt := _value(cfg, "ckpt_path")) is not None and (not isinstance(ckpt, str) or not ckpt):
        raise ValueError(f"ckpt_path must be null or the path of a checkpoint file, got {ckpt!r}")

    max_epochs, max_steps = _value(cfg, "trainer.max_epochs"), _value(cfg, "trainer.max_steps")
    if max_steps is not None and max_steps != -1:
        _integer(cfg, "trainer.max_steps", 1, note=" (or -1: no step limit)")
    if max_epochs is not None or not (_is_int(max_steps) and max_steps >= 1):
        forever = " (-1 means 'train forever' in Lightning; give a number of epochs)" if max_epochs == -1 else ""
        null = " (null only with trainer.max_steps >= 1)" if max_epochs is None else ""
        _integer(cfg, "trainer.max_epochs", 1, optional=False, note=forever + null)
    _integer(cfg, "trainer.min_epochs", 0)
    min_epochs = _value(cfg, "trainer.min_epochs")
    if _is_int(min_epochs) and _is_int(max_epochs) and min_epochs > max_epochs:
        raise ValueError(f"trainer.min_epochs ({min_epochs}) must be <= trainer.max_epochs ({max_epochs})")
    _positive(cfg, "trainer.gradient_clip_val", allow_zero=True)
    _integer(cfg, "data.batch_size", 1, note=" (or null: a whole split per batch)")

    _positive(cfg, "module.optimizer.lr")
    for key in ("weight_decay", "momentum"):
        _positive(cfg, f"module.optimizer.{key}", allow_zero=True)
    _positive(cfg, "module.optimizer.eps")
    scheduler = _value(cfg, "module.scheduler")
    if scheduler is not None and "T_max" in scheduler:  # (null: trainer.max_epochs=null, which it follows)
        follows = " (it follows trainer.max_epochs: with trainer.max_epochs=null give module.scheduler.T_max)"
        _integer(cfg, "module.scheduler.T_max", 1, optional=False, note=follows)
    _positive(cfg, "module.scheduler.eta_min", allow_zero=True)


def instantiate_node(cfg: DictConfig, key: str, **kwargs: Any) -> Any:
    """``hydra.utils.instantiate`` of the node at the dotted ``key`` of ``cfg``; a ValueError /
    TypeError (or Lightning's MisconfigurationException) raised by the target comes out as a
    ValueError / TypeError that names the config node and the target, instead of Hydra's
    InstantiationException."""
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
