"""``metrics.json`` and ``results.md`` of a run, for every way a run can end.

:class:`RunReport` writes them at the start (``status: "running"``: a run killed by SIGKILL
or a power cut is left saying so), and rewrites them when the run completes, is interrupted
by a signal, or fails. ``metrics.json`` is strict JSON (:func:`~torchsde_lti.training.outputs.write_json`),
schema :data:`~torchsde_lti.training.outputs.SCHEMA_VERSION`:

========================  ================================================================
key                       value
========================  ================================================================
``schema_version``        1
``status``                ``"running"`` | ``"completed"`` | ``"interrupted"`` | ``"failed"``
``model``, ``noise``      ``model.name``, ``data.noise`` (null when absent)
``run_dir``               the run's directory
``epochs``                epochs completed (held by ``last.ckpt``)
``max_epochs``            ``trainer.max_epochs``
``wall_time``             seconds of ``Trainer.fit`` in this process (null until known)
``reported``              where ``table``, ``param_errors`` and ``metrics`` come from:
                          {``checkpoint`` (path relative to ``run_dir``, null without one),
                          ``epoch``, ``description``}: the final weights = ``last.ckpt``
``metrics``               final epoch-level metrics and ``test/*`` (null for NaN / inf)
``param_errors``          relative errors against the truth ({} without one)
``skipped_steps``         optimizer steps skipped for a non-finite loss or gradient
``identifiability``       '' or why F is compared through its autocovariance
``table``                 rows {name, true, learned, rel_error} of the reported checkpoint
``best``                  {``checkpoint``, ``epoch``, ``val/nll``, ``table``, ``param_errors``}
                          of ``best.ckpt`` (lowest val/nll), or null
``data_summary``          the datamodule's ``summary`` (null when it has none)
``resumed_from``          [{``checkpoint``, ``epoch``}] for every resume of this run, oldest first
``interruption``          null, or {``signal`` ("SIGTERM" / "SIGINT"), ``phase`` ("setup",
                          "fit", "test" or "plots"), ``epochs_completed``,
                          ``resume_checkpoint`` (null when no epoch completed),
                          ``resume_command``}
``error``                 null, or ``"<ExceptionType>: <message>"`` of a failed run
========================  ================================================================
"""

from __future__ import annotations

import json
import math
import shlex
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from torchsde_lti.training.outputs import SCHEMA_VERSION, write_json, write_text

__all__ = ["RunReport", "markdown_table", "parameter_rows", "score_rows"]

#: The scores results.md shows per split, in order: metric name, column title, unit kind
#: ("nll": per observed scalar; "y": the observations' unit; "share").
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
    if not isinstance(x, (int, float)) or isinstance(x, bool) or not math.isfinite(x):
        return ""
    return format(x, spec)


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]], align: str = "") -> str:
    """A Markdown table of the columns that hold a value in some row (the first always kept).

    ``align``: one character per column, ``l`` or ``r`` (default: the first left, the rest right).
    """
    keep = [j for j in range(len(header)) if j == 0 or any(r[j] for r in rows)]
    align = align or "l" + "r" * (len(header) - 1)
    lines = [
        "| " + " | ".join(header[j] for j in keep) + " |",
        "|" + "|".join("---" if align[j] == "l" else "---:" for j in keep) + "|",
    ]
    lines += ["| " + " | ".join(r[j] for j in keep) + " |" for r in rows]
    return "\n".join(lines)


def parameter_rows(table: Sequence[dict[str, Any]]) -> str:
    """The learned values (and, where a truth is known, the true values and relative errors)."""
    rows = [
        [r["name"], _number(r.get("true")), _number(r.get("learned")), _number(100 * r["rel_error"], ".2f") + " %"
         if _number(r.get("rel_error")) else ""]
        for r in table
    ]  # fmt: skip
    return markdown_table(["parameter", "true", "learned", "rel. error"], rows)


def score_rows(metrics: dict[str, Any], unit: str) -> str:
    """Validation and test scores of ``metrics`` (``val/<name>``, ``test/<name>`` for each of
    :data:`SCORES`), with their units (``unit``: the observations'); '' when none was logged."""
    header = ["split"] + [f"{title} ({unit if kind == 'y' else kind})" for _, title, kind in SCORES]
    rows = [
        [split] + [_number(metrics.get(f"{prefix}/{name}")) for name, _, _ in SCORES]
        for split, prefix in (("validation", "val"), ("test", "test"))
    ]
    rows = [r for r in rows if any(r[1:])]
    return markdown_table(header, rows) if rows else ""


def _relative(path: str | None, root: Path) -> str | None:
    if not path:
        return None
    p = Path(path).resolve()
    try:
        return str(p.relative_to(root.resolve()))
    except ValueError:
        return str(p)


class RunReport:
    """The two report files of one run directory.

    Args:
        run_dir: the run's directory (``cfg.output_dir``).
        model, noise, max_epochs: what the run is (``model.name``, ``data.noise``,
            ``trainer.max_epochs``).
        resumed_from: ``(checkpoint path, epoch)`` when the run resumes, else None; earlier
            resumes of the same directory (from its previous ``metrics.json``) are kept.
        overrides: the command-line overrides of the run (for the resume command), if known.
    """

    def __init__(
        self,
        run_dir: Path,
        *,
        model: str | None,
        noise: Any,
        max_epochs: int | None,
        resumed_from: tuple[str, int] | None = None,
        overrides: Sequence[str] | None = None,
    ) -> None:
        self.run_dir = Path(run_dir)
        self.overrides = list(overrides) if overrides is not None else None
        previous = self._previous() if resumed_from is not None else {}
        history = list(previous.get("resumed_from") or [])
        #: epoch-level metrics the run reported before this resume (test/* excluded: it tests again)
        self.previous_metrics: dict[str, float] = {
            k: float(v)
            for k, v in (previous.get("metrics") or {}).items()
            if isinstance(v, (int, float)) and not isinstance(v, bool) and not k.startswith("test/")
        }
        if resumed_from is not None:
            history.append({"checkpoint": str(Path(resumed_from[0]).resolve()), "epoch": int(resumed_from[1])})
        self.base: dict[str, Any] = {
            "schema_version": SCHEMA_VERSION,
            "status": "running",
            "model": model,
            "noise": noise,
            "run_dir": str(self.run_dir.resolve()),
            "epochs": int(resumed_from[1]) + 1 if resumed_from is not None else 0,
            "max_epochs": max_epochs,
            "wall_time": None,
            "reported": None,
            "metrics": {},
            "param_errors": {},
            "skipped_steps": 0,
            "identifiability": "",
            "table": [],
            "best": None,
            "data_summary": None,
            "resumed_from": history,
            "interruption": None,
            "error": None,
        }

    @property
    def path(self) -> Path:
        return self.run_dir / "metrics.json"

    def _previous(self) -> dict[str, Any]:
        try:
            old = json.loads(self.path.read_text())
        except (OSError, ValueError):
            return {}
        return old if isinstance(old, dict) else {}

    def _write(self, **fields: Any) -> dict[str, Any]:
        summary = {**self.base, **fields}
        write_json(self.path, summary)
        return summary

    def running(self) -> None:
        """``status: "running"`` and a results.md that says the run has not finished."""
        self._write()
        write_text(
            self.run_dir / "results.md",
            f"# {self.base['model']}: running\n\nThis run has not finished "
            "(no final results yet). If nothing is running any more, it was killed without a chance to "
            "say so; resume it from `checkpoints/last.ckpt` if that exists (see metrics.json).\n",
        )

    def resume_command(self, checkpoint: str) -> str:
        """The command that resumes this run from ``checkpoint`` (the original overrides, if known)."""
        overrides = [o for o in (self.overrides or []) if not o.lstrip("+~").startswith("ckpt_path=")]
        args = [*overrides, f"ckpt_path={Path(checkpoint).resolve()}"]
        return " ".join([Path(sys.executable).name, "-m", "torchsde_lti.train", *map(shlex.quote, args)])

    def completed(
        self,
        *,
        title: str,
        wall_time: float,
        epochs: int,
        reported: dict[str, Any],
        metrics: dict[str, Any],
        param_errors: dict[str, float],
        skipped_steps: int,
        identifiability: str,
        table: list[dict[str, Any]],
        best: dict[str, Any] | None,
        data_summary: Any,
        data_text: str | None = None,
    ) -> dict[str, Any]:
        """Write the final report; returns the metrics.json content. ``data_text``: the data
        summary as the datamodule prints it, for results.md."""
        reported = {**reported, "checkpoint": _relative(reported.get("checkpoint"), self.run_dir)}
        if best is not None:
            best = {**best, "checkpoint": _relative(best.get("checkpoint"), self.run_dir)}
        summary = self._write(
            status="completed",
            wall_time=wall_time,
            epochs=epochs,
            reported=reported,
            metrics=metrics,
            param_errors=param_errors,
            skipped_steps=skipped_steps,
            identifiability=identifiability,
            table=table,
            best=best,
            data_summary=data_summary,
        )
        text = self._results_md(title, summary)
        if data_text:
            text += f"\n## Data\n\n```\n{data_text}\n```\n"
        write_text(self.run_dir / "results.md", text)
        return summary

    def _results_md(self, title: str, s: dict[str, Any]) -> str:
        rep = s["reported"]
        where = (
            f"`{rep['checkpoint']}` (epoch {rep['epoch']})"
            if rep.get("checkpoint")
            else "the final weights (no checkpoint written)"
        )
        text = f"# {title} ({s['wall_time']:.1f} s)\n\n"
        text += (
            f"Completed {s['epochs']} epochs. The scores and the table are those of {where}: {rep['description']}.\n"
        )
        if s["resumed_from"]:
            text += (
                f"Resumed {len(s['resumed_from'])}× (from "
                + ", ".join(f"epoch {r['epoch']}" for r in s["resumed_from"])
                + ").\n"
            )
        # real tracks are positions in metres; simulated ones are in the model's own units
        unit = "m" if isinstance(s.get("data_summary"), dict) and "load" in s["data_summary"] else "units of y"
        scores = score_rows(s["metrics"], unit)
        if scores:
            text += f"\n## Scores\n\n{scores}\n"
        if s["table"]:
            heading = "True vs learned" if any(_number(r.get("true")) for r in s["table"]) else "Learned values"
            text += f"\n## {heading}\n\n{parameter_rows(s['table'])}\n"
        best = s["best"]
        if best is not None and best.get("checkpoint"):
            val = best.get("val/nll")
            score = f", val/nll {val:.6g}" if isinstance(val, float) else ""
            if best.get("epoch") == rep.get("epoch"):
                text += (
                    f"\nThe lowest val/nll is this epoch's too: `{best['checkpoint']}` holds the same weights{score}.\n"
                )
            elif best.get("table"):
                text += f"\nLowest val/nll: `{best['checkpoint']}` (epoch {best['epoch']}{score}):\n\n{parameter_rows(best['table'])}\n"
        text += f"\nskipped optimizer steps (non-finite loss or gradient): {s['skipped_steps']}\n"
        if s["identifiability"]:
            text += f"\nNot identifiable: {s['identifiability']}\n"
        figures = [(name, caption) for name, caption in FIGURES if (self.run_dir / name).is_file()]
        if figures:
            text += (
                "\n## Figures\n\n"
                + "\n\n".join(f"{caption}:\n\n![{caption}]({name})" for name, caption in figures)
                + "\n"
            )
        return text

    def interrupted(
        self,
        signum: int,
        phase: str,
        *,
        epochs: int,
        checkpoint: str | None,
        metrics: dict[str, Any],
        data_summary: Any,
    ) -> dict[str, Any]:
        """Write the report of a run stopped by ``signum`` during ``phase``; returns metrics.json's content."""
        name = signal.Signals(signum).name
        command = self.resume_command(checkpoint) if checkpoint else None
        interruption = {
            "signal": name,
            "phase": phase,
            "epochs_completed": epochs,
            "resume_checkpoint": str(Path(checkpoint).resolve()) if checkpoint else None,
            "resume_command": command,
        }
        summary = self._write(
            status="interrupted", epochs=epochs, metrics=metrics, interruption=interruption, data_summary=data_summary
        )
        text = f"# {self.base['model']}: INTERRUPTED by {name} during {phase}\n\n"
        text += f"{epochs} of {self.base['max_epochs']} epochs completed; no final results.\n"
        if command:
            text += (
                f"\n`checkpoints/last.ckpt` holds epoch {epochs - 1}. Resume (continues in this directory, "
                f"same result as a run that never stopped):\n\n    {command}\n"
            )
        else:
            text += "\nNo epoch completed, so there is no checkpoint to resume from: run again.\n"
        write_text(self.run_dir / "results.md", text)
        return summary

    def failed(self, error: BaseException, *, epochs: int | None = None, checkpoint: str | None = None) -> None:
        """Write the report of a run that raised ``error``; ``epochs``: epochs completed, held by
        ``checkpoint`` (``last.ckpt``, from which it can be resumed), when known."""
        message = f"{type(error).__name__}: {error}"
        extra: dict[str, Any] = {} if epochs is None else {"epochs": epochs}
        self._write(status="failed", error=message, **extra)
        text = f"# {self.base['model']}: FAILED\n\n    {message}\n\nSee train.log.\n"
        if checkpoint:
            text += (
                f"\n`checkpoints/last.ckpt` holds epoch {epochs - 1 if epochs else '?'}; once the cause is "
                f"fixed, resume from it:\n\n    {self.resume_command(checkpoint)}\n"
            )
        write_text(self.run_dir / "results.md", text)
