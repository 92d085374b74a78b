"""The architecture, checked: the core imports and runs without the training stack, and
no module imports a private name of another subpackage."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchsde_lti"

CORE_SCRIPT = r"""
import importlib.abc, sys

class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {"lightning", "pytorch_lightning", "hydra", "omegaconf", "matplotlib"}:
            raise ImportError(f"blocked for this test: {name}")
        return None

sys.meta_path.insert(0, Block())
import torch
import torchsde_lti as tl
from torchsde_lti.data import simulate_tracks, pad_tracks, unpad_tracks
from torchsde_lti.data import load_tracks, split_objects, track_windows

torch.manual_seed(0)
F = torch.tensor([[0.0, 1.0], [-1.0, -0.3]], dtype=torch.float64)
L = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
Qc = torch.eye(1, dtype=torch.float64)
dt = torch.rand(4, 30, dtype=torch.float64)
d = tl.discretize(F, L, Qc, dt)
assert tl.Transition(method="matrix_exp")(F, dt).shape == (4, 30, 2, 2)
assert tl.VanLoanNoise()(F, L, Qc, dt).shape == (4, 30, 2, 2)
sde = tl.LTISDE(F, L, Qc, F_constraint="hurwitz")
H = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
batch = simulate_tracks(sde, H, 0.1 * torch.eye(1, dtype=torch.float64), 4, 30, seed=1)
kf = tl.KalmanFilter(sde, H, 0.1 * torch.eye(1, dtype=torch.float64))
out = kf(batch.y, batch.dt)
(-out.log_likelihood.sum()).backward()
assert sde.parametrizations.F.original.grad is not None
kf.smooth(out); kf.forecast(out, torch.tensor([1.0, 2.0], dtype=torch.float64))
tl.models.constant_velocity(dim=2)
assert not any(m.split(".")[0] in {"lightning", "hydra", "matplotlib"} for m in sys.modules)
print("core ok")
"""


def test_core_runs_without_lightning_hydra_matplotlib() -> None:
    res = subprocess.run([sys.executable, "-c", CORE_SCRIPT], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "core ok" in res.stdout


def _subpackage(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2]) if len(parts) > 2 or (PACKAGE / parts[1]).is_dir() else module


def test_no_private_names_cross_subpackages() -> None:
    """``from torchsde_lti.X.y import _name`` only inside subpackage X (own privates stay inside)."""
    offences = []
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        module = ".".join(rel.parts)
        here = _subpackage(module)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("torchsde_lti"):
                for alias in node.names:
                    if alias.name.startswith("_") and _subpackage(node.module) != here:
                        offences.append(f"{module}: from {node.module} import {alias.name}")
            elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[-1].startswith("_"):
                if node.module.startswith("torchsde_lti") and _subpackage(node.module) != here:
                    offences.append(f"{module}: from {node.module} import ...")
    assert not offences, offences


def _layer_of(path: Path) -> str:
    """The layer (a name of ``LAYERS``) of a module file of the package."""
    return path.relative_to(PACKAGE).parts[0].removesuffix(".py")


def test_layer_order_is_the_packages_and_true_in_the_code() -> None:
    """The one statement of the layer order, ``torchsde_lti.LAYERS``, covers every subpackage
    and top-level module, and every import of the package goes to an earlier layer (or stays
    inside its own); the package root only re-exports."""
    from torchsde_lti import LAYERS

    order = {name: rank for rank, (name, _) in enumerate(LAYERS)}
    assert len(order) == len(LAYERS), "a layer is named twice"
    files = [p for p in PACKAGE.rglob("*.py") if p.relative_to(PACKAGE).parts != ("__init__.py",)]
    unplaced = sorted({_layer_of(p) for p in files} - set(order))
    assert not unplaced, f"modules not placed in torchsde_lti.LAYERS: {unplaced}"
    assert set(order) <= {_layer_of(p) for p in files}, "LAYERS names a layer that does not exist"
    offences = []
    for path in files:
        here = _layer_of(path)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("torchsde_lti"):
                parts = node.module.split(".")
                targets = [parts[1]] if len(parts) > 1 else [alias.name for alias in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name.split(".")[1] for a in node.names if a.name.startswith("torchsde_lti.")]
            else:
                continue
            for target in targets:
                if target in order and order[target] > order[here]:
                    offences.append(f"{path.relative_to(PACKAGE)} ({here}) imports torchsde_lti.{target}")
    assert not offences, offences


def test_no_module_over_600_lines() -> None:
    """One job per module: none of the package's modules is over 600 lines."""
    long = {
        str(p.relative_to(PACKAGE)): n for p in PACKAGE.rglob("*.py") if (n := len(p.read_text().splitlines())) > 600
    }
    assert not long, long
