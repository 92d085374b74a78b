"""Griffe extension for the API pages (mkdocs.yml: mkdocstrings ``extensions``), applied at render time.

The package's docstrings are written for Sphinx as much as for mkdocstrings: they cross-refer
with reST roles (``:class:`~torchsde_lti.KalmanFilter```, ``:func:``, ``:meth:``, ``:mod:``,
``:data:``, ``:attr:``, ``:math:``), which Markdown shows raw. This extension rewrites them in
every loaded docstring, leaving the sources alone:

- ``:class:`~a.b.C``` -> `` `C` `` (the ``~`` form shows the last name), ``:class:`a.b.C``` ->
  `` `a.b.C` ``; ``:func:`` and ``:meth:`` add ``()``; ``:math:`x``` -> ``$x$`` (arithmatex);
- a class whose base is private (``KalmanOnline`` of ``nn._kalman_online``,
  ``ValidateArgs`` of ``nn._validate``) shows that base's public bases instead, and keeps the
  public members it inherits from it (as inherited members: the pages' ``inherited_members``
  option still picks which are shown).
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(class|func|meth|mod|data|attr|obj|exc|math):`([^`]+)`")


def _role(match: re.Match[str]) -> str:
    kind, target = match.group(1), match.group(2)
    if kind == "math":
        return f"${target}$"
    title = re.sub(r"^(.*?)\s*<(.+)>$", r"\1", target)  # "title <target>"
    if title.startswith("~"):
        title = title[1:].rsplit(".", 1)[-1]
    if kind in ("func", "meth") and not title.endswith(")"):
        title += "()"
    return f"`{title}`"


def plain_roles(text: str) -> str:
    """``text`` with every reST role of :data:`ROLE` turned into Markdown."""
    return ROLE.sub(_role, text)


def _private(path: str) -> bool:
    return any(part.startswith("_") and not part.startswith("__") for part in path.split("."))


class PublicDocstrings(griffe.Extension):
    """Plain Markdown for reST roles; no private base class on a public class."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = plain_roles(obj.docstring.value)

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        for cls in _classes(pkg):
            self._hide_private_bases(cls)

    def _hide_private_bases(self, cls: griffe.Class) -> None:
        if _private(cls.path):
            return
        bases: list[Any] = []
        todo = list(cls.bases)
        while todo:  # a private base's own bases are looked at in its place (they may be private too)
            base = todo.pop(0)
            path = base.canonical_path if isinstance(base, griffe.Expr) else str(base)
            if not _private(path):
                if all(str(b) != str(base) for b in bases):
                    bases.append(base)
                continue
            try:
                target = cls.modules_collection[path]
            except KeyError:
                continue  # an unresolvable private base: dropped
            for name, member in target.all_members.items():
                if not name.startswith("_") and name not in cls.members:
                    cls.set_member(name, griffe.Alias(name, member, parent=cls, inherited=True))
            todo = [*getattr(target, "bases", []), *todo]
        cls.bases = bases


def _classes(obj: griffe.Object) -> list[griffe.Class]:
    found = []
    for member in obj.members.values():
        if member.is_alias:
            continue
        if member.is_class:
            found.append(member)
        if member.is_module or member.is_class:
            found += _classes(member)
    return found
