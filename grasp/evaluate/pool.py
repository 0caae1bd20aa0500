"""Running an evaluation's jobs: in this process, in a pool of worker processes, or on Ray
actors; each worker keeps one :class:`~grasp.evaluate.runner.Evaluator` between jobs."""

from __future__ import annotations

from grasp.evaluate.config import Job, Settings
from grasp.evaluate.runner import Evaluator
from grasp.evaluate.sequence_result import SequenceResult

_WORKER: Evaluator | None = None


def _init_worker(settings: Settings) -> None:
    global _WORKER
    import torch

    torch.set_num_threads(1)
    _WORKER = Evaluator(settings)


def _run_job(job: Job) -> SequenceResult:
    assert _WORKER is not None, "worker not initialised"
    return _WORKER.evaluate(job)


def run_jobs(settings: Settings, jobs: list[Job], *, progress: bool = True) -> list[SequenceResult]:
    """Evaluate every job, in a process pool when ``settings.workers > 1`` (on Ray actors with
    ``settings.ray``); results in job order, so the tables do not depend on how they ran."""
    from tqdm import tqdm

    bar = tqdm(total=len(jobs), desc="evaluate", unit="seq", disable=not progress)
    results: list[SequenceResult] = []
    try:
        if settings.ray:
            from completion.cluster import ray_map

            for result in ray_map(_run_job, jobs, workers=settings.workers,
                                  initializer=_init_worker, initargs=(settings,)):  # fmt: skip
                results.append(result)
                bar.update()
        elif settings.workers <= 1 or len(jobs) <= 1:
            import torch

            threads = torch.get_num_threads()
            _init_worker(settings)
            try:
                for job in jobs:
                    results.append(_run_job(job))
                    bar.update()
            finally:
                torch.set_num_threads(threads)
                if _WORKER is not None:
                    _WORKER.close()
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            # spawn: torch and pybullet do not survive fork with live threads/clients.
            with ProcessPoolExecutor(
                min(settings.workers, len(jobs)),
                mp_context=mp.get_context("spawn"),
                initializer=_init_worker,
                initargs=(settings,),
            ) as pool:
                for result in pool.map(_run_job, jobs, chunksize=1):
                    results.append(result)
                    bar.update()
    finally:
        bar.close()
    return results
