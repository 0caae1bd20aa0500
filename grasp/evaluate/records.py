"""The records an evaluation passes around: one sequence's result and the time its stages took."""

from __future__ import annotations

import time
import zlib
from dataclasses import dataclass, field

from grasp.evaluate.config import Job

STAGES: tuple[str, ...] = (
    "generation",
    "inference",
    "completion_metrics",
    "grasping",
    "physics",
    "benchmark",
    "clutter",
)


@dataclass
class Timings:
    """Seconds per stage, summed over sequences: wall clock and this process's CPU time.

    The CPU time does not grow when other jobs compete for the cores, so it is the measure to
    size runs by (a run on N free cores takes about total CPU / N).
    """

    wall: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    cpu: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))

    def add(self, other: Timings) -> None:
        for stage in STAGES:
            self.wall[stage] += other.wall[stage]
            self.cpu[stage] += other.cpu[stage]


class StageClock:
    """Charges the wall and CPU time since the previous call to a stage of a :class:`Timings`."""

    def __init__(self, timings: Timings) -> None:
        self.timings = timings
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def charge(self, stage: str) -> None:
        wall, cpu = time.perf_counter(), time.process_time()
        self.timings.wall[stage] += wall - self.wall
        self.timings.cpu[stage] += cpu - self.cpu
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
    # the benchmark's object record (grasp.evaluate.benchmark.object_record) or the clutter
    # table's scene record: "rows": row -> outcome
    benchmark: dict = field(default_factory=dict)


def key_seed(*parts: object) -> int:
    """A stable 32-bit seed from a job's identity (same seed → same samples and grasps)."""
    return zlib.crc32("/".join(map(str, parts)).encode())


def markdown_timings(results: dict) -> str:
    """Per-stage seconds (wall and CPU, summed over sequences) and the run's wall times."""
    t = results["timings_s"]
    wall, cpu = t["stages_wall_summed_over_sequences"], t["stages_cpu_summed_over_sequences"]
    workers = results["config"]["workers"]
    one, many = ("Ray actor", "Ray actors") if results["config"].get("ray") else (
        "worker process", "worker processes")
    lines = [
        f"## Timings (seconds; {workers} {many if workers > 1 else one})",
        "",
        "| stage | wall, summed over sequences | CPU, summed over sequences |",
        "|---|---|---|",
        *[f"| {k} | {wall[k]:.1f} | {cpu[k]:.1f} |" for k in wall],
        f"| all stages | {sum(wall.values()):.1f} | {sum(cpu.values()):.1f} |",
        "",
        "| run | wall |",
        "|---|---|",
        *[f"| {k} | {v:.1f} |" for k, v in t["wall"].items()],
    ]
    return "\n".join(lines)
