"""The main-job commands of docs/getting-started/main-job.md, in-process with tiny settings (the
full-size msd recovery as a ``slow`` study).

``model=cv truth=singer`` once trained all its epochs and then crashed in the plots (the learner's
4-state H applied to the 6-state truth): the run was marked FAILED with an empty table. ``model=singer
data.noise=1.0 dtype=float32 filter.method=matrix_exp`` stopped at once in core (fixed there).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from torchsde_lti.training import train

CONF = Path(__file__).resolve().parents[2] / "conf"
TINY = ["experiment=tiny", "trainer.max_epochs=1"]


def _cfg(out: Path, *overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("train", overrides=[f"output_dir={out}", *overrides])


def test_cv_learner_on_singer_truth_completes_with_its_plots(tmp_path: Path) -> None:
    metrics, _ = train(_cfg(tmp_path, "model=cv", "truth=singer", *TINY, "plots=true"))
    summary = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["status"] == summary["status"] == "completed"
    assert summary["table"] and math.isfinite(summary["metrics"]["val/nll"])


def test_float32_matrix_exp_singer_trains(tmp_path: Path) -> None:
    """main-job.md's float32 matrix_exp command: it stopped at once (the PSD check refused the Q = 0 of
    the dt = 0 padding steps, its shift underflowing in float32)."""
    overrides = ["model=singer", "data.noise=1.0", "dtype=float32", "filter.method=matrix_exp"]
    metrics, _ = train(_cfg(tmp_path, *overrides, *TINY))
    assert math.isfinite(metrics["val/nll"])


@pytest.mark.slow  # the main job at full size: ≈ 40 s on a quiet core
def test_msd_main_job_recovers_every_parameter_within_3_percent(tmp_path: Path) -> None:
    """``python -m torchsde_lti.train model=msd``: the reported weights (last.ckpt) within 3 % of the
    truth on every compared quantity (measured 2.76 %, m; the full-batch L-BFGS maximum of the same
    likelihood, ``experiment=lbfgs``, is 2.67 %: the data's own error). The best-val/nll checkpoint's
    table is not the reported one: among converged epochs its choice follows noise (3.76 %, k)."""
    metrics, _ = train(_cfg(tmp_path, "model=msd", "plots=false"))
    assert max(metrics["param_errors"].values()) < 0.03, metrics["param_errors"]
