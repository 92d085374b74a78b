"""Deployment entry points of a trained :class:`~torchsde_lti.KalmanFilter`: modules with
plain tensor inputs and outputs whose ``forward`` is what a service calls, ready for
``torch.export`` (with dynamic shapes) and AOTInductor packaging.

- :class:`DeployedFilter`: the sequence filter, ``(y, dt) -> (log_likelihood, mean)``;
- :class:`OnlineStep`: one online step of live tracks (:meth:`~torchsde_lti.KalmanFilter.step`);
- :func:`compile_package` builds an exported program into an AOTInductor package (runtime
  constant folding on, the program's input signature recorded); :func:`load_package` loads
  one as a :class:`PackagedProgram`, a callable with its calling convention read once and its
  inputs checked against the recorded signature.
"""

from __future__ import annotations

import json
import os
import warnings
from typing import Any

import sympy
import torch
from torch import Tensor, nn
from torch.export import ExportedProgram
from torch.utils import _pytree as pytree

from torchsde_lti.core.validation import shape_str
from torchsde_lti.filters.online import KalmanState
from torchsde_lti.nn._kalman_online import OnlineModel
from torchsde_lti.nn.imm import IMMFilter
from torchsde_lti.nn.kalman import KalmanFilter

__all__ = ["DeployedFilter", "OnlineStep", "PackagedProgram", "compile_package", "load_package"]


def _no_runtime(runtime: str | None, module: str) -> None:
    """Warn that ``runtime=`` is accepted for compatibility only: it changes nothing."""
    if runtime is not None:
        warnings.warn(
            f"{module}(runtime={runtime!r}): runtime has no effect and is deprecated; the filters have "
            "one path, eager or traced, so one program serves torch.export and AOTInductor alike",
            DeprecationWarning,
            stacklevel=3,
        )


class DeployedFilter(nn.Module):
    """The entry point to ship a trained :class:`KalmanFilter` or :class:`IMMFilter` with
    ``torch.export`` (or ``torch.jit``-free serving): plain tensor outputs instead of a
    :class:`FilterResult` / :class:`IMMResult`.

    ``forward(y, dt, u=None)``: y (..., T, m) with NaN = missing, dt (..., T), optional inputs
    u (..., T, p) of a Kalman filter's model with B or D (as in :meth:`KalmanFilter.forward`;
    without them the inputs count as 0; an IMM takes none) -> ``(log_likelihood (...), mean
    (..., T, n))``, the filter's log-likelihood and filtered (for an IMM: combined) means.

    The exported program runs as it is (``ExportedProgram.module()``) or packaged by
    :func:`compile_package`: it is the same program. ``runtime``: deprecated, no effect (a
    :class:`DeprecationWarning` when given).
    """

    def __init__(self, kf: KalmanFilter | IMMFilter, runtime: str | None = None) -> None:
        super().__init__()
        if not isinstance(kf, (KalmanFilter, IMMFilter)):
            raise TypeError(f"kf must be a KalmanFilter or an IMMFilter, got {type(kf).__name__}")
        _no_runtime(runtime, "DeployedFilter")
        self.kf = kf

    def forward(self, y: Tensor, dt: Tensor, u: Tensor | None = None) -> tuple[Tensor, Tensor]:
        out = self.kf(y, dt, u)  # (an IMMFilter refuses a u)
        return out.log_likelihood, out.mean


class OnlineStep(nn.Module):
    """:meth:`KalmanFilter.step` as a module's ``forward``, to export and package (torch.export,
    AOTInductor) for a live tracker: plain tensors in and out.

    ``forward(mean, cov, y, dt, u=None)``: mean (B, n), cov (B, n, n), y (B, m) (NaN = missing),
    dt (B,), optional inputs u (B, p) held over the step (as in :meth:`KalmanFilter.step`)
    -> ``(mean, cov, innovation (B, m), innovation_cov (B, m, m), log_likelihood (B,))``.
    The step is :meth:`KalmanFilter.step` with the snapshot as its ``model``; an exported
    program skips the value checks (check reports where they enter the tracker).

    The step is a snapshot of the filter when it is built: the model's matrices (the SDE's, H,
    R, D and the dt-independent part of its discretisation) are evaluated
    then, without gradients, and held as buffers, so an exported program runs the step alone
    and not the parametrisations. Build it after training (again after any change of ``kf``;
    ``load_state_dict`` on the step re-evaluates it). ``runtime``: deprecated, no effect.
    """

    def __init__(self, kf: KalmanFilter, runtime: str | None = None) -> None:
        super().__init__()
        if not isinstance(kf, KalmanFilter):
            raise TypeError(f"kf must be a KalmanFilter, got {type(kf).__name__}")
        _no_runtime(runtime, "OnlineStep")
        self.kf = kf
        self._snapshot()
        self.register_load_state_dict_post_hook(lambda module, _incompatible: module._snapshot())

    def _snapshot(self) -> None:
        """Evaluate ``kf``'s online model now and hold its tensors as (non-persistent) buffers."""
        with torch.no_grad():
            leaves, self._model_spec = pytree.tree_flatten(self.kf.online_model())
        self._model_slots = [i for i, leaf in enumerate(leaves) if isinstance(leaf, Tensor)]
        for i in self._model_slots:
            self.register_buffer(f"_model_{i}", leaves[i].detach().clone(), persistent=False)
            leaves[i] = None
        self._model_leaves = leaves  # the non-tensor leaves (flags, sizes); None in a tensor's slot

    def _model(self) -> OnlineModel:
        """The snapshot of ``kf.online_model()`` (its tensors the buffers)."""
        leaves = list(self._model_leaves)
        for i in self._model_slots:
            leaves[i] = getattr(self, f"_model_{i}")
        return pytree.tree_unflatten(leaves, self._model_spec)

    def forward(self, mean: Tensor, cov: Tensor, y: Tensor, dt: Tensor, u: Tensor | None = None) -> tuple[Tensor, ...]:
        state, out = self.kf.step(KalmanState(mean, cov), y, dt, u, model=self._model())
        return state.mean, state.cov, out.innovation, out.innovation_cov, out.log_likelihood


#: AOTInductor options of :func:`compile_package`: fold the subgraphs that depend on the
#: program's parameters and buffers alone once, when the package is loaded and run first
#: (and again after ``load_constants``), not on every call. (Inductor's folder leaves out any
#: chain that starts from a factory call such as ``torch.eye``; :class:`OnlineStep` holds its
#: model evaluated and needs none of it.)
PACKAGE_CONFIGS: dict[str, Any] = {"aot_inductor.use_runtime_constant_folding": True}

#: The package metadata key under which :func:`compile_package` records the program's tensor
#: inputs: a JSON list of [name, dtype, number of dims, device type, sizes, ranges]; sizes has an
#: int for a fixed size, a dynamic dim's symbol ("s0") or None (an expression of symbols); ranges
#: maps each symbol to [lowest, highest or None].
_INPUTS_KEY = "torchsde_lti.inputs"


def _dim_record(d: int | torch.SymInt) -> int | str | None:
    """A fixed size as it is, a dynamic dim as its symbol's name, an expression of symbols as None."""
    if isinstance(d, int):
        return d
    expr = d.node.expr
    return str(expr) if getattr(expr, "is_Symbol", False) else None


def _ranges(program: ExportedProgram) -> dict[str, list[int | None]]:
    """symbol -> [lowest, highest or None] of the program's dynamic dims (None: unbounded, as
    a ``Dim`` without ``max=`` or a size the trace creates, such as a scan's)."""
    return {str(sym): [_bound(vr.lower) or 0, _bound(vr.upper)] for sym, vr in program.range_constraints.items()}


def _bound(value: object) -> int | None:
    """A range bound as an int, None for an unbounded one: torch marks those with its own
    infinity (``int_oo``), which says it is finite and has no int value, or sympy's ``oo``."""
    return int(value) if isinstance(value, (int, sympy.Integer)) else None


def compile_package(
    program: ExportedProgram, path: str | os.PathLike[str], inductor_configs: dict[str, Any] | None = None
) -> str:
    """Build ``program`` (from ``torch.export.export`` of :class:`OnlineStep`,
    :class:`DeployedFilter` or any module) into an AOTInductor package at ``path`` with
    :data:`PACKAGE_CONFIGS` (updated by ``inductor_configs``) and its input signature in the
    package's metadata (read by :class:`PackagedProgram`); returns the package's path. Needs a
    C++ compiler; the package then runs with torch alone (:func:`load_package`)."""
    if not isinstance(program, ExportedProgram):
        raise TypeError(f"program must be a torch.export.ExportedProgram, got {type(program).__name__}")
    user_inputs = set(program.graph_signature.user_inputs)
    ranges = _ranges(program)
    signature = [
        [
            node.name, str(val.dtype).removeprefix("torch."), val.dim(), val.device.type,
            [_dim_record(d) for d in val.shape], ranges,
        ]
        for node in program.graph.nodes
        if node.op == "placeholder" and node.name in user_inputs and isinstance(val := node.meta.get("val"), Tensor)
    ]  # fmt: skip
    configs = {**PACKAGE_CONFIGS, **(inductor_configs or {})}
    configs["aot_inductor.metadata"] = {**configs.get("aot_inductor.metadata", {}), _INPUTS_KEY: json.dumps(signature)}
    return torch._inductor.aoti_compile_and_package(program, package_path=os.fspath(path), inductor_configs=configs)


class PackagedProgram:
    """A loaded AOTInductor package, called like the module it was exported from.

    Its input and output structure is read once when it is loaded (``torch._inductor``'s
    loader object parses it again on every call, which costs a small call more than the
    compiled program itself); positional tensor arguments go to the compiled program
    (made contiguous where they are not: it reads an expanded or transposed view as if it were
    contiguous), checked first against the input signature :func:`compile_package` recorded:
    dtype, number of dims, on the CPU or not, every fixed size, and each dynamic size within its
    range and equal in every input that shares it (the compiled program itself reads a wrong
    one's memory as if it were right). ``loader`` is torch's ``AOTIModelPackageLoader``
    (``load_constants`` to swap weights).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        if not os.path.isfile(path):
            raise ValueError(f"path must name an AOTInductor package file, got {os.fspath(path)!r} (no such file)")
        self._compiled = torch._inductor.aoti_load_package(os.fspath(path))
        self.loader = self._compiled.loader
        in_spec, out_spec = (pytree.treespec_loads(s) for s in self.loader.get_call_spec())
        self._n_inputs = in_spec.num_leaves
        self._out_spec = out_spec
        self._flat_tuple_out = out_spec == pytree.tree_structure((0,) * out_spec.num_leaves)
        recorded = self.loader.get_metadata().get(_INPUTS_KEY)
        rows = None if recorded is None else json.loads(recorded)
        # (packages of an earlier release recorded no sizes: dtype, dims and device only)
        self._inputs = None if rows is None else [(r[0], getattr(torch, r[1]), r[2], r[3]) for r in rows]
        self._sizes: list[list[int | str | None]] | None = None
        self._ranges: dict[str, list[int | None]] = {}
        if rows and all(len(r) >= 6 for r in rows):
            self._sizes = [r[4] for r in rows]
            self._ranges = rows[0][5]
        # what each call compares (dtype, number of dims, on the CPU or not): one list equality
        self._expected = None
        if self._inputs is not None:
            self._expected = [(d, k, dev == "cpu") for _, d, k, dev in self._inputs]
        # the dims each call reads: (input, dim) of every fixed size, and of every dynamic one
        self._fixed = [] if self._sizes is None else [
            (i, j, v) for i, sizes in enumerate(self._sizes) for j, v in enumerate(sizes) if isinstance(v, int)
        ]  # fmt: skip
        self._dynamic = [] if self._sizes is None else [
            (i, j, v) for i, sizes in enumerate(self._sizes) for j, v in enumerate(sizes) if isinstance(v, str)
        ]  # fmt: skip

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if kwargs or not all(isinstance(a, Tensor) for a in args):
            return self._compiled(*args, **kwargs)  # torch's own flattening of any structure
        if self._expected is not None:
            if [(a.dtype, a.ndim, a.is_cpu) for a in args] != self._expected:
                self._raise_mismatch(args)
            self._check_sizes(args)
        elif len(args) != self._n_inputs:
            return self._compiled(*args)
        out = self.loader.boxed_run([a if a.is_contiguous() else a.contiguous() for a in args])
        return tuple(out) if self._flat_tuple_out else pytree.tree_unflatten(out, self._out_spec)

    def _check_sizes(self, args: tuple[Tensor, ...]) -> None:
        """ValueError naming the input whose fixed size differs, or whose dynamic size is out of
        its range or differs from another input's size of the same dim."""
        assert self._inputs is not None
        for i, j, v in self._fixed:
            if args[i].shape[j] != v:
                raise ValueError(
                    f"{self._inputs[i][0]} must have size {v} in dim {j} (the program's fixed size), "
                    f"got {shape_str(args[i])}"
                )
        seen: dict[str, tuple[int, int]] = {}
        for i, j, sym in self._dynamic:
            size = args[i].shape[j]
            if sym in seen:
                k, d = seen[sym]
                if args[k].shape[d] != size:
                    raise ValueError(
                        f"{self._inputs[i][0]} {shape_str(args[i])} and {self._inputs[k][0]} {shape_str(args[k])} "
                        f"must agree in the program's dynamic dim {sym} (dim {j} and dim {d})"
                    )
                continue
            seen[sym] = (i, j)
            lowest, highest = self._ranges.get(sym, (0, None))
            if size < (lowest or 0) or (highest is not None and size > highest):
                raise ValueError(
                    f"{self._inputs[i][0]} has size {size} in dim {j}, outside the program's range "
                    f"[{lowest}, {'∞' if highest is None else highest}] for it ({shape_str(args[i])})"
                )

    def _raise_mismatch(self, args: tuple[Tensor, ...]) -> None:
        """ValueError naming the first argument whose dtype, number of dims or device (CPU or not) differs
        from the recorded signature (or a wrong number of arguments)."""
        assert self._inputs is not None
        if len(args) != len(self._inputs):
            names = ", ".join(name for name, *_ in self._inputs)
            raise ValueError(f"the package takes {len(self._inputs)} tensors ({names}), got {len(args)}")
        for a, (name, dtype, dim, device) in zip(args, self._inputs):
            if a.dtype != dtype or a.dim() != dim or a.is_cpu != (device == "cpu"):
                raise ValueError(
                    f"{name} must be a {dim}-dim {dtype} tensor on {device}, got {shape_str(a)} {a.dtype} on {a.device.type}"
                )


def load_package(path: str | os.PathLike[str]) -> PackagedProgram:
    """The package at ``path`` (from :func:`compile_package` or
    ``torch._inductor.aoti_compile_and_package``) as a :class:`PackagedProgram`."""
    return PackagedProgram(path)
