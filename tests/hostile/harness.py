"""The hostile-input harness: each case is a call and the one acceptable outcome.

An outcome is either :class:`Finite` — the call returns, every floating tensor in the result
is finite, and an optional ``check`` confirms the value against one computed another way —
or :class:`Raises` — an error of the given type whose message matches a pattern naming the
argument, file or config key. Anything else (NaN, inf, another exception type, a message
that does not say what is wrong) fails the case.

Cases the package still gets wrong in code another change owns are marked
``xfail(strict=True)`` with the exact current outcome: when that change fixes them they pass,
and ``strict`` turns the XPASS into a failure that asks for the mark to be removed.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
import torch


@dataclass(frozen=True)
class Finite:
    """The call returns finite floating tensors; ``check(result)`` (if given) asserts the value."""

    check: Callable[[Any], None] | None = None


@dataclass(frozen=True)
class Raises:
    """The call raises ``error`` (or a subclass) with a message matching ``match`` (a regex,
    searched case-insensitively) and not matching ``forbid``."""

    error: type[BaseException] | tuple[type[BaseException], ...]
    match: str
    forbid: str | None = None


@dataclass(frozen=True)
class Case:
    id: str
    call: Callable[[], Any]
    expect: Finite | Raises
    xfail: str | None = None  # the exact current (wrong) outcome, for code owned by another change


def tensors(obj: Any) -> Iterator[torch.Tensor]:
    """Every tensor in a (nested) result: tensors, NamedTuples, tuples, lists, dicts, modules' parameters."""
    if isinstance(obj, torch.Tensor):
        yield obj
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from tensors(v)
    elif isinstance(obj, (tuple, list)):
        for v in obj:
            yield from tensors(v)
    elif isinstance(obj, torch.nn.Module):
        yield from obj.parameters()


def run_case(case: Case) -> None:
    expect = case.expect
    if isinstance(expect, Raises):
        with pytest.raises(expect.error) as info:
            case.call()
        message = str(info.value)
        assert re.search(expect.match, message, flags=re.IGNORECASE), f"message does not name it: {message!r}"
        if expect.forbid is not None:
            assert not re.search(expect.forbid, message, flags=re.IGNORECASE), (
                f"message says {expect.forbid!r}: {message!r}"
            )
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = case.call()
    for t in tensors(out):
        if t.is_floating_point() or t.is_complex():
            assert bool(torch.isfinite(t.detach()).all()), f"non-finite result: {t}"
    if expect.check is not None:
        expect.check(out)


def params(cases: Iterable[Case]) -> list[Any]:
    """pytest parameters of ``cases`` (ids from the cases; xfail marks where the outcome is known wrong)."""
    out, seen = [], set()
    for c in cases:
        assert c.id not in seen, f"duplicate case id {c.id}"
        seen.add(c.id)
        marks = [pytest.mark.xfail(strict=True, reason=c.xfail)] if c.xfail else []
        out.append(pytest.param(c, id=c.id, marks=marks))
    return out
