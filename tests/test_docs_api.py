"""The API pages' docstrings as mkdocstrings renders them (docs/scripts/griffe_docstrings.py, the
griffe extension mkdocs.yml loads): no raw reST role, no private base class on a public class,
and the members a private base gives its public class kept."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

griffe = pytest.importorskip("griffe")

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def package():  # noqa: ANN201 - a griffe Module
    extensions = griffe.load_extensions(f"{ROOT / 'docs/scripts/griffe_docstrings.py'}:PublicDocstrings")
    return griffe.load("torchsde_lti", search_paths=[str(ROOT)], extensions=extensions, resolve_aliases=False)


def _objects(obj):  # noqa: ANN001, ANN202
    for member in obj.members.values():
        if member.is_alias:
            continue
        yield member
        if member.is_module or member.is_class:
            yield from _objects(member)


def test_no_docstring_keeps_a_rest_role(package) -> None:  # noqa: ANN001
    raw = [
        o.path
        for o in _objects(package)
        if o.docstring and re.search(r":(class|func|meth|mod|data|attr|math):`", o.docstring.value)
    ]
    assert not raw, raw[:10]
    assert re.search(r":class:`", (ROOT / "torchsde_lti/nn/kalman.py").read_text())  # the sources keep theirs


def test_public_classes_show_no_private_base_and_keep_inherited_members(package) -> None:  # noqa: ANN001
    kalman = package["nn.kalman.KalmanFilter"]
    assert [str(b) for b in kalman.bases] == ["nn.Module"]
    assert {"step", "predict", "initial_state"} <= set(kalman.all_members)
    for cls in (o for o in _objects(package) if o.is_class and not any(p.startswith("_") for p in o.path.split("."))):
        private = [
            str(b)
            for b in cls.bases
            if any(
                p.startswith("_") and not p.startswith("__") for p in str(getattr(b, "canonical_path", b)).split(".")
            )
        ]
        assert not private, (cls.path, private)
