"""pybullet, quietly: the one place that imports it and opens its DIRECT clients.

pybullet's C code writes its build banner ("pybullet build time: …") on import and ``argv[0]=``
on every connect straight to the process's file descriptors, past Python's ``sys.stdout``: they
end up in progress bars, in piped JSON and in the service's logs. Every module here takes
``pybullet``, ``direct_client`` and the pose conversions from this module instead.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["direct_client", "pose_to_pybullet", "pybullet", "pybullet_to_pose", "quiet_fds"]


@contextlib.contextmanager
def quiet_fds(*fds: int) -> Iterator[None]:
    """Send C-level writes to the given file descriptors (default 1 and 2) to /dev/null."""
    fds = fds or (1, 2)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    saved: list[tuple[int, int]] = []
    try:
        with open(os.devnull, "wb") as null:
            for fd in fds:
                try:
                    saved.append((fd, os.dup(fd)))
                except OSError:  # nothing open there: nothing to silence
                    continue
                os.dup2(null.fileno(), fd)
            yield
    finally:
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)


with quiet_fds():
    import pybullet
    from pybullet_utils import bullet_client


def direct_client() -> bullet_client.BulletClient:
    """A new pybullet DIRECT client (its own physics server), opened without printing."""
    with quiet_fds(1):
        return bullet_client.BulletClient(connection_mode=pybullet.DIRECT)


def pose_to_pybullet(pose: np.ndarray) -> tuple[list[float], list[float]]:
    """4×4 pose -> (position, quaternion x, y, z, w) as pybullet takes them."""
    pose = np.asarray(pose, dtype=np.float64)
    return pose[:3, 3].tolist(), Rotation.from_matrix(pose[:3, :3]).as_quat().tolist()


def pybullet_to_pose(position, quaternion) -> np.ndarray:
    """Inverse of :func:`pose_to_pybullet`."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    pose[:3, 3] = position
    return pose
