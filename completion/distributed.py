"""Training on several processes: ``torchrun --nproc-per-node N -m completion.train …``.

torchrun sets ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK`` and the rendezvous address; :func:`setup`
reads them and joins the process group (gloo on the CPU, nccl on CUDA). Without torchrun
everything here is a no-op for one process, so ``python -m completion.train`` is unchanged.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist


@dataclass(frozen=True)
class World:
    """This process's place among the training processes."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def distributed(self) -> bool:
        return self.size > 1

    @property
    def main(self) -> bool:
        """Rank 0: the one that generates data, validates, prints and writes checkpoints."""
        return self.rank == 0

    def barrier(self) -> None:
        if self.distributed:
            dist.barrier()

    def gather(self, value: Any) -> list[Any]:
        """``value`` of every rank, in rank order (pickled)."""
        if not self.distributed:
            return [value]
        out: list[Any] = [None] * self.size
        dist.all_gather_object(out, value)
        return out

    def all_true(self, flag: bool) -> bool:
        """True when ``flag`` is true on every rank (so that all ranks take the same branch)."""
        if not self.distributed:
            return flag
        t = torch.tensor([int(flag)], dtype=torch.int32, device=_collective_device())
        dist.all_reduce(t, op=dist.ReduceOp.MIN)
        return bool(t.item())

    def close(self, *, wait: bool = True) -> None:
        """Leave the process group; with ``wait`` (a normal finish) all ranks leave together,
        since a rank that tears gloo down while another still talks to it can abort at exit
        ("terminate called without an active exception"). A failing rank must not wait: the
        others may be inside a collective it will never join."""
        if self.distributed and dist.is_initialized():
            if wait:
                dist.barrier()
            dist.destroy_process_group()


def _collective_device() -> torch.device:
    if dist.get_backend() == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


def setup(requested: str = "auto") -> tuple[World, torch.device]:
    """Join the process group torchrun describes (none when not under torchrun) and pick this
    rank's device: ``auto`` is the rank's GPU (``LOCAL_RANK``) when there is one, else the CPU."""
    if requested == "auto":
        requested = "cuda" if torch.cuda.is_available() else "cpu"
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        return World(), torch.device(requested)
    world = World(int(os.environ["RANK"]), size, int(os.environ.get("LOCAL_RANK", "0")))
    device = torch.device(requested)
    if device.type == "cuda":
        device = torch.device("cuda", world.local_rank)
        torch.cuda.set_device(device)
    dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return world, device
