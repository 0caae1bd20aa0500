"""What a table of the evaluation is: the jobs it needs, how it scores one, what it puts in
results.json and how it writes its part of results.md."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from grasp.evaluate.config import Job, Settings
from grasp.evaluate.records import SequenceResult


@dataclass(frozen=True)
class Sizing:
    """How a table with a size of its own is sized: the option ``--<name>`` (``help``: what it
    counts) and its size per preset (``--quick``, the default, ``--full``); 0 leaves it out.
    The command line (:mod:`grasp.evaluate.cli`) and the run's :class:`~grasp.evaluate.config.
    Settings` (``sizes``, by the table's name) take it from here."""

    help: str
    quick: int
    default: int
    full: int

    def preset(self, name: str) -> int:
        """The size of preset ``name`` ("quick", "default" or "full")."""
        return getattr(self, name)


class Table:
    """One table of the evaluation. ``name`` is its jobs' ``Job.table``; ``section`` where
    results.md places it, after a part of the main table's (:mod:`grasp.evaluate.tables.main`):
    ``"jaccard"`` (Table I and its precision), ``"grasps"`` (grasp success) or ``"objects"``
    (the grasps left out), before the timings. A table that scores its jobs like the main
    table's keeps :meth:`run`; one that does not overrides it."""

    name: str = ""
    section: str = "objects"
    #: its own size (None: sized by the main table's options)
    sizing: Sizing | None = None

    def size(self, settings: Settings) -> int:
        """How many jobs the run asks of it (its :attr:`sizing`): the run's size for its name,
        else its default."""
        return settings.size(self.name, self.sizing.default)

    def jobs(self, settings: Settings) -> list[Job]:
        return []

    def run(self, evaluator: Any, job: Job) -> SequenceResult:
        """One job: by default the main table's scoring of a generated sequence
        (:meth:`grasp.evaluate.runner.Evaluator.sequence`)."""
        return evaluator.sequence(job)

    def summarise(self, results: list[SequenceResult], settings: Settings) -> dict:
        """The results.json entries this table owns (every key, None when it has nothing)."""
        return {}

    def markdown(self, results: dict) -> list[str]:
        """Its lines of results.md (none when results.json has nothing of it)."""
        return []
