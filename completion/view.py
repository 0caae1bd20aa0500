"""One view as :meth:`completion.stream.CompletionStream.add_view` takes it: a typed value whose
rules are checked once, where the view enters.

A Python caller builds it with :meth:`View.of` (a depth image with its intrinsics and mask, a
camera-frame point cloud, or a ready grid; every rule below checked, ValueError saying what was
expected); the service's intake builds it from arrays it has already checked at the HTTP door
(:mod:`service.intake.inputs`, as its subclass ``DecodedView``). The stream only asserts.

Rules of a view: exactly one of depth (with intrinsics), points or grid; points finite (n, 3)
metres in the camera frame; ``camera_to_world`` a finite 4×4 camera→world pose; a
``support_plane`` (world frame) only with a camera pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from completion import grid as G
from grasp_client.wire import SupportPlane

#: Why a view without a camera pose is refused where a support plane is (the view's or the
#: stream's): the plane is in the world frame, the grid in the camera's.
PLANE_NEEDS_POSE = f"{SupportPlane.NEEDS_POSES}: every view of a stream with one needs its pose"


@dataclass(frozen=True)
class View:
    """The object's points (n, 3) float64 in the camera frame, or a ready ``grid``; its camera
    pose (4, 4) float64 camera→world, when given; the support plane it brings (world frame)."""

    points: np.ndarray | None = None
    grid: G.VoxelGrid | None = None
    camera_to_world: np.ndarray | None = None
    support_plane: SupportPlane | None = None

    def __post_init__(self) -> None:
        assert (self.points is None) != (self.grid is None), "a view is points or a grid"
        assert self.support_plane is None or self.camera_to_world is not None

    @classmethod
    def of(
        cls,
        *,
        depth: np.ndarray | None = None,
        intrinsics: G.Intrinsics | None = None,
        mask: np.ndarray | None = None,
        points: np.ndarray | None = None,
        grid: G.VoxelGrid | None = None,
        camera_to_world: np.ndarray | None = None,
        support_plane: SupportPlane | None = None,
    ) -> View:
        """A checked view from exactly one of ``depth`` (+ ``intrinsics``, ``mask``: back-projected
        by :func:`completion.grid.depth_to_points`, as the training data), ``points`` or
        ``grid``; ValueError naming what was expected."""
        if sum(x is not None for x in (depth, points, grid)) != 1:
            raise ValueError("give exactly one of depth (with intrinsics), points or grid")
        if depth is not None:
            if intrinsics is None:
                raise ValueError("a depth image needs its intrinsics")
            points = G.depth_to_points(depth, intrinsics, mask)
        if points is not None:
            points = G.as_points(points)
        if camera_to_world is not None:
            camera_to_world = np.asarray(camera_to_world, dtype=np.float64)
            if camera_to_world.shape != (4, 4) or not np.isfinite(camera_to_world).all():
                raise ValueError("camera_to_world must be a finite 4×4 matrix")
        elif support_plane is not None:
            raise ValueError(PLANE_NEEDS_POSE)
        return cls(points, grid, camera_to_world, support_plane)
