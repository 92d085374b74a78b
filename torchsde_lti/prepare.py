"""``python -m torchsde_lti.prepare source=... out=...``: out-of-core preparation (Hydra; conf/prepare.yaml).

The work is :func:`torchsde_lti.data.prepare_dataset`; this entry point only reads the config.
"""

from __future__ import annotations

import logging
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from torchsde_lti.training.train import config_path

__all__ = ["main", "prepare"]

log = logging.getLogger("torchsde_lti.prepare")


def prepare(cfg: DictConfig) -> object:
    """Prepare per ``cfg`` (conf/prepare.yaml); returns the :class:`~torchsde_lti.data.prepare.PreparedSummary`."""
    from torchsde_lti.data.prepare import prepare_dataset

    options: dict[str, Any] = {str(k): v for k, v in OmegaConf.to_container(cfg, resolve=True).items()}  # type: ignore[union-attr]
    options.pop("hydra", None)
    source, out = options.pop("source"), options.pop("out")
    summary = prepare_dataset(source, out, **options)
    log.info("%s", summary)
    return summary


@hydra.main(version_base="1.3", config_path=config_path(), config_name="prepare")
def main(cfg: DictConfig) -> None:
    """Hydra entry point."""
    print(prepare(cfg))


if __name__ == "__main__":
    main()
