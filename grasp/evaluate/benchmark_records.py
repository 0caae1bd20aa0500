"""The benchmark's results.json records read back as types: one :class:`ObjectRecord` per object
(``grasp_benchmark_objects``), a :class:`RowOutcome` per row of it, a :class:`RowSummary` per row
of ``grasp_benchmark``. :mod:`grasp.evaluate.benchmark_scenes` writes them as JSON; the tables'
markdown reads them here, by attribute, not by string keys."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from grasp_client.wire import Verification


@dataclass(frozen=True)
class RowOutcome:
    """One row's top grasp on one object, executed by the lift test (the referee)."""

    held: bool
    reason: str
    kind: str | None = None
    planned_joints_deg: list[float] | None = None
    executed_joints_deg: list[float] | None = None
    hold_probability: float | None = None
    verification: Verification | None = None  # the verified rows: the top grasp's trials
    tried: int | None = None  # the verified rows: grasps lift-tested before the answer

    @classmethod
    def from_json(cls, o: Mapping[str, Any]) -> RowOutcome:
        v = o.get("verification")
        return cls(bool(o["held"]), str(o["reason"]), o.get("kind"),
                   o.get("planned_joints_deg"), o.get("executed_joints_deg"),
                   o.get("hold_probability"), None if v is None else Verification.from_json(v),
                   o.get("tried"))

    @property
    def joint_gap_deg(self) -> float | None:
        """The mean |planned − executed| finger joint (degrees); None when not executed."""
        if self.planned_joints_deg is None or self.executed_joints_deg is None:
            return None
        return float(np.mean(np.abs(np.subtract(self.planned_joints_deg,
                                                self.executed_joints_deg))))


@dataclass(frozen=True)
class ObjectRecord:
    """One benchmark object: its id, size (m), mass (kg) and its rows' outcomes."""

    id: str
    size_m: list[float]
    mass_kg: float
    rows: dict[str, RowOutcome] = field(default_factory=dict)

    @classmethod
    def from_json(cls, r: Mapping[str, Any]) -> ObjectRecord:
        return cls(str(r["id"]), list(r["size_m"]), float(r["mass_kg"]),
                   {row: RowOutcome.from_json(o) for row, o in r["rows"].items()})


@dataclass(frozen=True)
class RowSummary:
    """One row over the benchmark: held of tested, Wilson's 95 % interval, failures by kind."""

    held: int
    tested: int
    ci95: tuple[float, float]
    reasons: dict[str, int]

    @classmethod
    def from_json(cls, cell: Mapping[str, Any]) -> RowSummary:
        return cls(int(cell["held"]), int(cell["tested"]), tuple(cell["ci95"]),
                   dict(cell["reasons"]))

    @property
    def rate(self) -> float | None:
        return self.held / self.tested if self.tested else None
