"""``metrics.json`` and ``results.md`` of a run: one :class:`RunCard`, written at the start
(``status: "running"``: a run killed by SIGKILL or a power cut is left saying so) and again when
the run completes, is interrupted by a signal, or fails. ``metrics.json`` is strict JSON
(:func:`~torchsde_lti.training.outputs.write_json`): ``schema_version`` (:data:`SCHEMA_VERSION`)
and the card's fields.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shlex
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torchsde_lti.training.outputs import write_json, write_text

__all__ = ["SCHEMA_VERSION", "RunCard", "format_table", "markdown_table", "score_rows"]

#: Version of the layout of ``metrics.json`` (bumped when a key changes meaning or moves).
SCHEMA_VERSION = 1
#: The scores results.md shows per split: metric name, column title, unit ("y": the observations').
SCORES = (
    ("nll", "NLL", "nats per observed scalar"),
    ("rmse", "one-step RMSE", "y"),
    ("state_rmse", "state RMSE", "y"),
    ("cover2s", "2σ coverage", "share"),
)
#: The figures results.md links when the run drew them (training.plots.plot_run), with captions.
FIGURES = (
    ("map.png", "tracks on a map: reports, filtered and smoothed paths, 2σ ellipses"),
    ("track.png", "one track against time: reports, filtered and smoothed means ±2σ"),
    ("modes.png", "mode probabilities over time"),
    ("forecast.png", "forecast error against lead time"),
    ("loss.png", "loss curves"),
    ("params.png", "learned parameters per epoch"),
)


def _number(x: Any, spec: str = ".4g") -> str:
    """A table cell: '' for a missing / non-finite value."""
    ok = isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
    return format(x, spec) if ok else ""


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A Markdown table of the columns that hold a value in some row (the first, left-aligned, always)."""
    keep = [j for j in range(len(header)) if j == 0 or any(r[j] for r in rows)]
    lines = [
        "| " + " | ".join(header[j] for j in keep) + " |",
        "|" + "|".join("---:" if j else "---" for j in keep) + "|",
    ]
    return "\n".join(lines + ["| " + " | ".join(r[j] for j in keep) + " |" for r in rows])


def format_table(table: Sequence[dict[str, Any]]) -> str:
    """Markdown of :func:`~torchsde_lti.evaluation.parameter_table` rows: learned values and,
    where a truth is known, the true values and relative errors (only the columns that apply)."""
    rows = [
        [r["name"], _number(r.get("true")), _number(r.get("learned")),
         f"{100 * r['rel_error']:.2f} %" if _number(r.get("rel_error")) else ""]
        for r in table
    ]  # fmt: skip
    return markdown_table(["parameter", "true", "learned", "rel. error"], rows)


def score_rows(metrics: dict[str, Any], unit: str) -> str:
    """Validation and test scores (``val/<name>``, ``test/<name>`` of :data:`SCORES`) with their
    units (``unit``: the observations'); '' when none was logged."""
    header = ["split"] + [f"{title} ({unit if kind == 'y' else kind})" for _, title, kind in SCORES]
    rows = [
        [split] + [_number(metrics.get(f"{prefix}/{name}")) for name, _, _ in SCORES]
        for split, prefix in (("validation", "val"), ("test", "test"))
    ]
    rows = [r for r in rows if any(r[1:])]
    return markdown_table(header, rows) if rows else ""


def _checkpoint(info: dict[str, Any]) -> str:
    return (
        f"`{info['checkpoint']}` (epoch {info['epoch']})"
        if info.get("checkpoint")
        else "the final weights (no checkpoint written)"
    )


@dataclass
class RunCard:
    """What a run reports, in ``metrics.json`` and ``results.md`` (:meth:`write`).

    ``status``: "running" | "completed" | "interrupted" | "failed"; ``epochs``: epochs completed
    (held by ``last.ckpt``); ``wall_time``: seconds of ``Trainer.fit`` in this process;
    ``reported``: {``checkpoint`` (relative to ``run_dir``), ``epoch``, ``description``}, where
    ``metrics``, ``param_errors`` and ``table`` come from (``last.ckpt``, the final weights);
    ``metrics``: epoch-level metrics and ``test/*``; ``table``: rows {name, true, learned,
    rel_error}; ``best``: {``checkpoint``, ``epoch``, ``val/nll``, ``table``, ``param_errors``}
    of ``best.ckpt`` (lowest val/nll) or None; ``resumed_from``: [{``checkpoint``, ``epoch``}]
    of every resume, oldest first; ``interruption``: {``signal``, ``phase``, ``epochs_completed``,
    ``resume_checkpoint``, ``resume_command``} or None; ``error``: "<Type>: <message>" or None;
    ``overrides``: the run's command-line overrides (None outside a Hydra run).
    """

    run_dir: str
    model: str | None = None
    noise: Any = None
    max_epochs: int | None = None
    status: str = "running"
    epochs: int = 0
    wall_time: float | None = None
    reported: dict[str, Any] | None = None
    metrics: dict[str, float] = field(default_factory=dict)
    param_errors: dict[str, float] = field(default_factory=dict)
    skipped_steps: int = 0
    identifiability: str = ""
    table: list[dict[str, Any]] = field(default_factory=list)
    best: dict[str, Any] | None = None
    data_summary: Any = None
    resumed_from: list[dict[str, Any]] = field(default_factory=list)
    interruption: dict[str, Any] | None = None
    error: str | None = None
    overrides: list[str] | None = None

    def previous(self) -> dict[str, Any]:
        """The ``metrics.json`` an earlier process of this run directory wrote ({} if none)."""
        try:
            old = json.loads((Path(self.run_dir) / "metrics.json").read_text())
        except (OSError, ValueError):
            return {}
        return old if isinstance(old, dict) else {}

    def relative(self, path: str | None) -> str | None:
        """``path`` relative to the run directory (absolute where it lies elsewhere)."""
        if not path:
            return None
        p, run_dir = Path(path).resolve(), Path(self.run_dir).resolve()
        return str(p.relative_to(run_dir)) if p.is_relative_to(run_dir) else str(p)

    def resume_command(self, checkpoint: str) -> str:
        """The command that resumes this run from ``checkpoint`` (with the run's overrides, if known)."""
        overrides = [o for o in (self.overrides or []) if not o.lstrip("+~").startswith("ckpt_path=")]
        args = [*overrides, f"ckpt_path={Path(checkpoint).resolve()}"]
        return " ".join([Path(sys.executable).name, "-m", "torchsde_lti.train", *map(shlex.quote, args)])

    def write(self, data_text: str | None = None) -> None:
        """Write ``metrics.json`` and ``results.md`` (``data_text``: the data summary as printed)."""
        write_json(Path(self.run_dir) / "metrics.json", {"schema_version": SCHEMA_VERSION, **dataclasses.asdict(self)})
        write_text(Path(self.run_dir) / "results.md", self.markdown(data_text))

    def markdown(self, data_text: str | None = None) -> str:
        """``results.md``: the run's state; when completed its scores and tables, each naming its checkpoint."""
        if self.status == "running":
            return (
                f"# {self.model}: running\n\nThis run has not finished (no final results yet). If nothing is "
                "running any more, it was killed without a chance to say so; resume it from "
                "`checkpoints/last.ckpt` if that exists (see metrics.json).\n"
            )
        if self.status == "failed":
            text = f"# {self.model}: FAILED\n\n    {self.error}\n\nSee train.log.\n"
            if self.reported and self.reported.get("checkpoint"):
                text += (
                    f"\n`checkpoints/last.ckpt` holds epoch {self.epochs - 1}; once the cause is fixed, resume "
                    f"from it:\n\n    {self.resume_command(str(Path(self.run_dir) / self.reported['checkpoint']))}\n"
                )
            return text
        if self.status == "interrupted":
            stop = self.interruption or {}
            text = f"# {self.model}: INTERRUPTED by {stop.get('signal')} during {stop.get('phase')}\n\n"
            text += f"{self.epochs} of {self.max_epochs} epochs completed; no final results.\n"
            if stop.get("resume_command"):
                return text + (
                    f"\n`checkpoints/last.ckpt` holds epoch {self.epochs - 1}. Resume (continues in this directory, "
                    f"same result as a run that never stopped):\n\n    {stop['resume_command']}\n"
                )
            return text + "\nNo epoch completed, so there is no checkpoint to resume from: run again.\n"
        return self._completed(data_text)

    def _completed(self, data_text: str | None) -> str:
        rep = self.reported or {}
        truth = any(_number(r.get("true")) for r in self.table)
        text = f"# {self.model}: {'true vs learned' if truth else 'learned values'} ({self.wall_time or 0:.1f} s)\n\n"
        text += f"Completed {self.epochs} epochs. The run's answer is {_checkpoint(rep)}: {rep.get('description')}.\n"
        if self.resumed_from:
            epochs = ", ".join(f"epoch {r['epoch']}" for r in self.resumed_from)
            text += f"Resumed {len(self.resumed_from)}× (from {epochs}).\n"
        # real tracks are positions in metres; simulated ones are in the model's own units
        unit = "m" if isinstance(self.data_summary, dict) and "load" in self.data_summary else "units of y"
        if scores := score_rows(self.metrics, unit):
            text += f"\n## Scores: {_checkpoint(rep)}\n\n{scores}\n"
            if "val/cover2s" in self.metrics or "test/cover2s" in self.metrics:
                text += "\n2σ coverage: the share of reports inside the one-step predictive's 86.5 % region (0.865 when calibrated).\n"
        heading = "True vs learned" if truth else "Learned values"
        if self.table:
            text += f"\n## {heading}: {_checkpoint(rep)}, the final weights\n\n{format_table(self.table)}\n"
        best = self.best or {}
        if best.get("checkpoint"):
            val = best.get("val/nll")
            score = f", val/nll {val:.6g}" if isinstance(val, float) else ""
            if best.get("epoch") == rep.get("epoch"):
                text += (
                    f"\nThe lowest val/nll is this epoch's too: `{best['checkpoint']}` holds the same weights{score}.\n"
                )
            elif best.get("table"):
                text += (
                    f"\n## {heading}: `{best['checkpoint']}` (epoch {best['epoch']}{score}), the lowest val/nll\n\n"
                    f"For comparison, not the run's answer (the final weights above).\n\n{format_table(best['table'])}\n"
                )
        text += f"\nskipped optimizer steps (non-finite loss or gradient): {self.skipped_steps}\n"
        if self.identifiability:
            text += f"\nNot identifiable: {self.identifiability}\n"
        figures = [(name, caption) for name, caption in FIGURES if (Path(self.run_dir) / name).is_file()]
        if figures:
            text += "\n## Figures\n\n" + "\n\n".join(f"{c}:\n\n![{c}]({n})" for n, c in figures) + "\n"
        return text + (f"\n## Data\n\n```\n{data_text}\n```\n" if data_text else "")
