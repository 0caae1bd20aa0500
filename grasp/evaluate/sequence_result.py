"""The records an evaluation passes around: one sequence's result and the time its stages took."""

from __future__ import annotations

import time
import zlib
from dataclasses import dataclass, field

from grasp.evaluate.config import Job

#: The stages of the main table's scoring (a table with work of its own declares its stages:
#: :attr:`grasp.evaluate.tables.base.Table.stages`).
STAGES: tuple[str, ...] = ("generation", "inference", "completion_metrics", "grasping", "physics")


@dataclass
class Timings:
    """Seconds per stage, summed over sequences: wall clock and this process's CPU time.

    The CPU time does not grow when other jobs compete for the cores, so it is the measure to
    size runs by (a run on N free cores takes about total CPU / N).
    """

    wall: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    cpu: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))

    def add(self, other: Timings) -> None:
        for mine, theirs in ((self.wall, other.wall), (self.cpu, other.cpu)):
            for stage, seconds in theirs.items():
                mine[stage] = mine.get(stage, 0.0) + seconds


class StageClock:
    """Charges the wall and CPU time since the previous call to a stage of a :class:`Timings`."""

    def __init__(self, timings: Timings) -> None:
        self.timings = timings
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def charge(self, stage: str) -> None:
        wall, cpu = time.perf_counter(), time.process_time()
        self.timings.wall[stage] = self.timings.wall.get(stage, 0.0) + wall - self.wall
        self.timings.cpu[stage] = self.timings.cpu.get(stage, 0.0) + cpu - self.cpu
        self.wall, self.cpu = wall, cpu


@dataclass
class SequenceResult:
    job: Job
    object_ids: list[str]
    # row -> metric -> per-view list (jaccard, fscore_1, fscore_2; below_plane where the scene
    # has a support plane: the share of the predicted voxels whose centre lies below it)
    per_view: dict[str, dict[str, list[float]]]
    # row -> JointError.as_dict() (only for grasped jobs)
    grasps: dict[str, dict] = field(default_factory=dict)
    timings: Timings = field(default_factory=Timings)
    example: dict | None = None  # final-view grids for the figures
    # row (and TRUE_MESH) -> lift test summary (only for physics jobs)
    physics: dict[str, dict] = field(default_factory=dict)
    # fscore_1 / fscore_2 -> per-view F-score of the 40³ target itself (a perfect completion);
    # below_plane -> the target's share below the support plane (scenes with one)
    ceiling: dict[str, list[float]] = field(default_factory=dict)
    elevation_deg: list[float] = field(default_factory=list)  # the camera's, per view
    # a table's own record of the job, as its module declares it (the benchmark's object
    # record, the clutter table's scene record: "rows": row -> outcome)
    record: dict = field(default_factory=dict)


def key_seed(*parts: object) -> int:
    """A stable 32-bit seed from a job's identity (same seed → same samples and grasps)."""
    return zlib.crc32("/".join(map(str, parts)).encode())
