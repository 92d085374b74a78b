"""The run config's schema and checks, before any work: each error names the key.

:class:`RunSchema` (Hydra's ConfigStore ``train_schema``, first in ``conf/train.yaml``'s
defaults) types the top-level keys: ``seed=1.5`` or ``num_threads=two`` fail when the config is
composed (OmegaConf's ``ValidationError``, a ValueError naming the key). OmegaConf converts more
loosely than a run needs (``3`` to ``true``, ``123`` to ``"123"``), so ``test``, ``plots``,
``ckpt_path`` and ``dtype`` stay untyped there. :func:`check_config` adds the ranges types cannot
say (``trainer.max_epochs=-1`` trains forever, ``lr: 0`` trains nothing); values the built
objects check themselves (``data.noise``, ``module.k_step``, a model's ``q``) fail when built,
with the config node named by :func:`instantiate_node`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Optional

from hydra.core.config_store import ConfigStore
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from lightning.fabric.utilities.exceptions import MisconfigurationException
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

__all__ = ["RunSchema", "check_config", "instantiate_node"]


@dataclass
class RunSchema:
    """The top-level keys of ``conf/train.yaml`` (see there)."""

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


def _int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


#: (key, test, what it must be): checked where the key is set and not null.
RANGES: tuple[tuple[str, Callable[[Any], bool], str], ...] = (
    ("dtype", lambda x: x in ("float32", "float64"), "'float32' or 'float64'"),
    ("seed", lambda x: _int(x) and 0 <= x <= 2**32 - 1, "an integer in [0, 4294967295]"),
    ("num_threads", lambda x: _int(x) and x >= 0, "an integer >= 0 (0 or null: torch's default)"),
    ("init_jitter", lambda x: _number(x) and x >= 0, "a finite number >= 0"),
    ("restart", lambda x: _int(x) and x >= 0, "an integer >= 0"),
    ("test", lambda x: isinstance(x, bool), "true or false"),
    ("plots", lambda x: isinstance(x, bool), "true or false"),
    ("ckpt_path", lambda x: isinstance(x, str) and x != "", "null or the path of a checkpoint file"),
    ("trainer.max_steps", lambda x: _int(x) and (x == -1 or x >= 1), "an integer >= 1 (or -1: no step limit)"),
    ("trainer.min_epochs", lambda x: _int(x) and x >= 0, "an integer >= 0"),
    ("trainer.gradient_clip_val", lambda x: _number(x) and x >= 0, "a finite number >= 0"),
    ("data.batch_size", lambda x: _int(x) and x >= 1, "an integer >= 1 (or null: a whole split per batch)"),
    ("module.optimizer.lr", lambda x: _number(x) and x > 0, "a finite number > 0"),
    ("module.optimizer.weight_decay", lambda x: _number(x) and x >= 0, "a finite number >= 0"),
    ("module.optimizer.momentum", lambda x: _number(x) and x >= 0, "a finite number >= 0"),
    ("module.optimizer.eps", lambda x: _number(x) and x > 0, "a finite number > 0"),
    ("module.scheduler.eta_min", lambda x: _number(x) and x >= 0, "a finite number >= 0"),
)


def _value(cfg: DictConfig, key: str) -> Any:
    """The resolved value at a dotted key (None when absent); a broken interpolation names the key."""
    try:
        return OmegaConf.select(cfg, key, default=None, throw_on_missing=True)
    except OmegaConfBaseException as err:
        raise ValueError(f"config key {key}: {err}") from None


def _check_filter_model(cfg: DictConfig) -> None:
    """An IMM filter learns a bank of modes (a model group with ``mode_names``); a Kalman filter one model."""
    target, model = str(_value(cfg, "filter._target_") or ""), _value(cfg, "model.name")
    bank = _value(cfg, "model.mode_names") is not None
    if target.endswith("IMMFilter") and not bank:
        raise ValueError(
            f"filter=imm needs a bank of modes: model=imm or model=imm3 (with truth=null and real data, as "
            f"experiment=ais_imm and experiment=ais_moving set), got model={model}"
        )
    if target.endswith(".KalmanFilter") and bank:
        raise ValueError(f"model={model} is a bank of modes for filter=imm (experiment=ais_imm), not for filter=kalman")


def check_config(cfg: DictConfig) -> None:
    """Raise ValueError naming the key for a config that cannot make a sensible run: a missing
    node, a filter and model that do not pair, a value outside :data:`RANGES`,
    ``trainer.max_epochs`` < 1 (Lightning's -1, "train forever", included; null only with
    ``trainer.max_steps`` >= 1) or below ``trainer.min_epochs``, ``module.scheduler.T_max`` < 1."""
    for key in ("model", "data", "trainer", "filter", "module"):
        if cfg.get(key) is None:
            raise ValueError(f"config is missing the '{key}' node")
    _check_filter_model(cfg)
    for key, ok, what in RANGES:
        if (x := _value(cfg, key)) is not None and not ok(x):
            raise ValueError(f"{key} must be {what}, got {x!r}")
    if _value(cfg, "dtype") is None:
        raise ValueError("dtype must be 'float32' or 'float64', got None")
    max_epochs, max_steps = _value(cfg, "trainer.max_epochs"), _value(cfg, "trainer.max_steps")
    if not (_int(max_epochs) and max_epochs >= 1) and not (max_epochs is None and _int(max_steps) and max_steps >= 1):
        forever = " (-1 means 'train forever' in Lightning; give a number of epochs)" if max_epochs == -1 else ""
        null = " (null only with trainer.max_steps >= 1)" if max_epochs is None else ""
        raise ValueError(f"trainer.max_epochs must be an integer >= 1{forever}{null}, got {max_epochs!r}")
    if (min_epochs := _value(cfg, "trainer.min_epochs")) is not None and _int(max_epochs) and min_epochs > max_epochs:
        raise ValueError(f"trainer.min_epochs ({min_epochs}) must be <= trainer.max_epochs ({max_epochs})")
    scheduler = _value(cfg, "module.scheduler")
    if scheduler is not None and "T_max" in scheduler and not (_int(t_max := scheduler.T_max) and t_max >= 1):
        raise ValueError(
            f"module.scheduler.T_max must be an integer >= 1 (it follows trainer.max_epochs: with "
            f"trainer.max_epochs=null give module.scheduler.T_max), got {t_max!r}"
        )


def instantiate_node(cfg: DictConfig, key: str, **kwargs: Any) -> Any:
    """``hydra.utils.instantiate`` of the node at the dotted ``key``; a ValueError / TypeError (or
    Lightning's MisconfigurationException) of the target comes out as a ValueError / TypeError
    naming the config node and the target, instead of Hydra's InstantiationException."""
    try:
        return instantiate(OmegaConf.select(cfg, key), **kwargs)
    except InstantiationException as err:
        cause, text = err.__cause__, str(err)
        found, target = re.search(r"full_key: (\S+)", text), re.search(r"target '([^']+)'", text)
        where = f"config {found.group(1) if found else key}{f' (calling {target.group(1)})' if target else ''}"
        if isinstance(cause, TypeError):
            raise TypeError(f"{where}: {cause}") from cause
        if isinstance(cause, (ValueError, MisconfigurationException)):
            raise ValueError(f"{where}: {cause}") from cause
        raise
