"""What a table of the evaluation is: its command-line options, the jobs it needs, how it scores
one and what it keeps of it, what it puts in results.json and results.md, and its figures."""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass
from pathlib import Path
from typing import Any

from grasp.evaluate.aggregate import sequence_records
from grasp.evaluate.config import Job, Settings
from grasp.evaluate.sequence_result import SequenceResult


def per_preset(default: int, quick: int, full: int) -> str:
    """How ``--help`` states an option's value per preset (the main table's and the tables')."""
    return f"default {default}, {quick} with --quick, {full} with --full"


@dataclass(frozen=True)
class Option:
    """An integer option of a table, ``--<name>`` (underscores written as dashes): what it sets
    (``help``), its value per preset (``--quick``, the default, ``--full``; the default in all
    three when ``quick`` and ``full`` are None), the least value it takes, the value of the
    option given alone (``bare``; None: it needs a value), the option whose value it takes when
    that one is given and it is not (``follows``), and whether ``--no-<name>`` sets it to 0.
    The command line (:mod:`grasp.evaluate.cli`) adds it, applies ``bare`` and ``follows``, and
    fills the run's :class:`~grasp.evaluate.config.Settings` (``options``, by name); :meth:`of`
    reads it back (settings built in code name each value they want)."""

    name: str
    help: str
    _: KW_ONLY
    default: int
    quick: int | None = None
    full: int | None = None
    least: int = 0
    bare: int | None = None
    follows: str | None = None
    negatable: bool = False

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    def preset(self, name: str) -> int:
        """Its value in preset ``name`` ("quick", "default" or "full")."""
        value = getattr(self, name)
        return self.default if value is None else value

    def of(self, settings: Settings) -> int:
        """Its value in a run: what the settings give it, else its default."""
        return dict(settings.options).get(self.name, self.default)

    def help_text(self) -> str:
        """``help`` and where its value comes from, read from the fields (so it cannot drift)."""
        if self.quick is None and self.full is None:
            where = f"default {self.default}"
        else:
            where = per_preset(*(self.preset(p) for p in ("default", "quick", "full")))
        if self.least == 0:
            where = "0 = none; " + where
        if self.bare is not None:
            where += f"; {self.flag} alone: {self.bare}"
        if self.follows is not None:
            where += f"; with --{self.follows.replace('_', '-')} N and no {self.flag}: N"
        return f"{self.help} ({where})"


class Table:
    """One table of the evaluation. ``name`` is its jobs' ``Job.table``; ``section`` where
    results.md places it, after a part of the main table's (:mod:`grasp.evaluate.tables.main`):
    ``"jaccard"`` (Table I and its precision), ``"grasps"`` (grasp success) or ``"objects"``
    (the grasps left out), before the timings. A table that scores its jobs like the main
    table's keeps :meth:`run`, :meth:`records` and :attr:`stages`; one that does not overrides
    them (its own per-job record in :attr:`SequenceResult.record`, its timed stages)."""

    name: str = ""
    section: str = "objects"
    #: its own command-line options (none: sized by the main table's, :mod:`grasp.evaluate.cli`)
    options: tuple[Option, ...] = ()
    #: the stages its :meth:`run` charges beyond the main table's (sequence_result.STAGES), in order
    stages: tuple[str, ...] = ()

    def jobs(self, settings: Settings) -> list[Job]:
        return []

    def run(self, evaluator: Any, job: Job) -> SequenceResult:
        """One job: by default the main table's scoring of a generated sequence
        (:meth:`grasp.evaluate.runner.Evaluator.sequence`)."""
        return evaluator.sequence(job)

    def summarise(self, results: list[SequenceResult], settings: Settings) -> dict:
        """The results.json entries this table owns (every key, None when it has nothing)."""
        return {}

    def records(self, result: SequenceResult, settings: Settings) -> list[dict]:
        """results.json's ``per_object`` records of one of its jobs: by default one per row, as
        the main table's (:func:`grasp.evaluate.aggregate.sequence_records`)."""
        return sequence_records(result, settings)

    def markdown(self, results: dict) -> list[str]:
        """Its lines of results.md (none when results.json has nothing of it)."""
        return []

    def figures(self, raw: list[SequenceResult], out: Path, plt: Any, *, seed: int) -> list[Path]:
        """The figures of its own it writes in ``out`` (``plt``: matplotlib.pyplot), if any."""
        return []


def rows_record(result: SequenceResult) -> list[dict]:
    """The one ``per_object`` record of a job whose :attr:`SequenceResult.record` holds each
    row's outcome under ``"rows"`` (the benchmark's object, the clutter table's scene); the
    outcomes sit under the key ``"benchmark"`` for both, as results.json has always had them."""
    r = result
    return [{"table": r.job.table, "index": r.job.index, "object_ids": r.object_ids,
             "benchmark": r.record["rows"]}]
