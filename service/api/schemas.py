"""Request and response bodies of the HTTP API (JSON; arrays as nested lists, binary as base64).

What the robot side shares with the service (a grasp, its contacts and hand, poses, the support
plane) is defined once in :mod:`grasp_client.wire` and used here as it is, so the client and this
schema cannot drift apart.

Frames (docs/design.md §3): points, poses and grids are in the camera frame of the view they
came with (OpenCV optical: x right, y down, z forward, metres); ``camera_pose`` is camera→world.
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from grasp_client.wire import Grasp, Pose, RigidPose, SupportPlane

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
# fail_fast: a list's validation stops at its first bad element, so that a million bad points
# cost one error, not a million of them (pydantic builds every error before any is capped)
Vector3 = Annotated[list[FiniteFloat], Field(min_length=3, max_length=3, fail_fast=True)]
Row4 = Annotated[list[FiniteFloat], Field(min_length=4, max_length=4)]
Matrix4 = Annotated[list[Row4], Field(min_length=4, max_length=4, description="4×4, row-major")]
SessionId = Annotated[str, Field(min_length=1, max_length=128, description="from POST /views")]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)  # no coercion: true is not 1 m


# ------------------------------------------------------------------------------- POST /views


class IntrinsicsIn(_Strict):
    """Pinhole intrinsics in pixels (pixel (u, v) has its centre at integer (u, v))."""

    fx: FiniteFloat = Field(gt=0)
    fy: FiniteFloat = Field(gt=0)
    cx: FiniteFloat
    cy: FiniteFloat


class DepthIn(_Strict):
    """A depth image: metric depth along the camera z axis, 0 (or NaN/±inf for f32_m) = no return.

    ``png16_mm``: base64 of a 16-bit single-channel PNG in millimetres (RealSense, ROS 16UC1).
    ``f32_m``: base64 of width × height little-endian float32 in metres, row-major (ROS 32FC1).
    """

    encoding: Literal["png16_mm", "f32_m"]
    width: int = Field(gt=0, le=65535)
    height: int = Field(gt=0, le=65535)
    data: str = Field(description="base64")


class GridIn(_Strict):
    """A ready voxel grid: 40³ occupancy bits packed in C order (numpy.packbits, 8000 bytes)."""

    data: str = Field(description="base64 of the 8000 packed bytes")
    grid_to_camera: Matrix4 = Field(
        description="voxel index (i, j, k) → camera-frame metres: pitch × identity (0.1 mm to "
        "10 m) plus a translation, last row [0, 0, 0, 1], the grid's centre in front of the camera"
    )


class ViewIn(_Strict):
    """One view: exactly one of ``points``, ``depth`` (with ``intrinsics``) or ``grid``."""

    session_id: SessionId | None = Field(None, description="absent: a new session is created")
    points: Annotated[list[Vector3], Field(fail_fast=True)] | None = Field(
        None, description="the object's observed points [[x, y, z], …], camera frame, metres"
    )
    depth: DepthIn | None = None
    intrinsics: IntrinsicsIn | None = Field(None, description="with depth, and only with depth")
    mask: str | None = Field(
        None,
        description="with depth only: base64 8-bit PNG of the depth image's size, 0/1 or "
        "0/255 with 0 = background, or a label image with object_label (absent: every valid "
        "pixel is the object)",
    )
    object_label: int | None = Field(
        None, ge=0, le=255, description="with a mask that is a label image: the value of the "
        "object's pixels (the others are background)"
    )
    grid: GridIn | None = None
    camera_pose: RigidPose | None = Field(
        None,
        description="camera→world, rigid (an orthonormal rotation with determinant +1, last row "
        "[0, 0, 0, 1], metres); while it stays the same from view to view, the grid "
        "is fitted to every point seen from that pose (a fixed camera watching objects move)",
    )
    support_plane: SupportPlane | None = Field(
        None,
        description="the table the object rests on, [nx, ny, nz, d] in the world frame (n·x + d "
        "= 0, n pointing up, metres; needs camera_pose). The session keeps it: the completion "
        "is cut at it (nothing below the table) and every grasp treats it as an obstacle",
    )

    obstacles: bool = Field(
        True, description="with a depth image, a mask and a camera_pose, in a session with a "
        "support plane: every pixel outside the mask with a depth, off the table and within "
        "30 cm of the object, is an obstacle every grasp keeps clear of (kept with the session, "
        "world frame); false: none from this view")
    obstacle_mask: str | None = Field(
        None, description="with depth: base64 8-bit PNG of the depth image's size whose "
        "non-zero pixels are the obstacles, instead of every pixel outside the mask")

    registered: bool | None = Field(
        None, description="with camera poses: fuse this session's posed views in the world frame, "
        "the object taken as still (true), or take the model's answer alone (false, for an "
        "object that moves); kept by the session from this view on. Absent: as the session did "
        "(a new one: the server's GRASP_REGISTERED, on by default)")

    check_frames: bool = Field(
        True, description="check camera_pose and support_plane against what this view shows "
        "(the camera above the table, the object on it and where earlier views saw it): a "
        "contradiction is a 422 naming the likely mistake; false skips it for this view")

    @model_validator(mode="after")
    def _one_input(self) -> ViewIn:
        given = [name for name in ("points", "depth", "grid") if getattr(self, name) is not None]
        if len(given) != 1:
            raise ValueError(
                "give exactly one of points, depth (with intrinsics) or grid; "
                f"got {' and '.join(given) if given else 'none'}"
            )
        if self.depth is not None and self.intrinsics is None:
            raise ValueError("depth needs intrinsics {fx, fy, cx, cy}")
        if self.depth is None and (self.intrinsics is not None or self.mask is not None
                                   or self.obstacle_mask is not None):
            raise ValueError("intrinsics, mask and obstacle_mask go with depth only")
        if self.object_label is not None and self.mask is None:
            raise ValueError("object_label goes with a mask (a label image)")
        return self


class ViewOut(BaseModel):
    session_id: str
    view_index: int = Field(description="0-based index of this view in the session")
    observed_voxels: int = Field(description="occupied voxels of this view's input grid")
    occupied_voxels: int = Field(description="voxels of the completion at the threshold")
    completion: Literal["registered", "memory"] = Field(
        "memory", description="registered: this view's completion averaged the session's posed "
        "views in the world frame; memory: the model's answer alone (no camera_pose, or the "
        "session's registered is false)")


# ------------------------------------------------------------------------------- GET /grasp


class GraspsOut(BaseModel):
    session_id: str
    views: int
    grasps: list[Grasp] = Field(description="best first; empty when no candidate held")
    reason: str | None = Field(None, description="why no grasp was found, when grasps is empty")
    camera_pose: Pose | None = Field(
        None, description="4×4 camera→world of the latest view, when it came with one"
    )
    cached: bool = Field(
        False, description="the plan of an earlier request on the same mesh with the same options"
    )
    support_plane: SupportPlane | None = Field(
        None,
        description="the support plane the grasps respect, [nx, ny, nz, d] in the latest "
        "camera frame (n·x + d = 0, n up), when one was given",
    )
    obstacle_voxels: int = Field(
        0, description="obstacle voxels (5 mm) the session keeps, which every grasp keeps clear "
        "of (POST /views' obstacles); a grasp they ruled out says so in its reason"
    )
    timing_ms: dict[str, float] = Field(
        description="load, completion, mesh, planning; waiting (for a free worker); total"
    )


#: How ``GET /sessions/{id}/observed`` writes its points: ``f32`` base64 of little-endian float32
#: rows (x, y, z), a quarter of the JSON's size and no number formatting; ``json`` lists.
ObservedFormat = Literal["f32", "json"]


class ObservedOut(BaseModel):
    session_id: str
    views: int
    format: ObservedFormat = Field(description="how points and obstacles are written")
    n_points: int = Field(description="observed voxels of the latest view")
    n_obstacles: int = Field(description="obstacle voxels the session keeps")
    points: str | list[list[float]] = Field(
        description="centres of the latest view's observed voxels, its camera frame, metres: "
        "base64 of float32 little-endian (n_points, 3) row-major (format=f32), or [x, y, z] "
        "lists (format=json)"
    )
    obstacles: str | list[list[float]] = Field(
        description="centres of the session's obstacle voxels, the same camera frame and "
        "format"
    )


# ------------------------------------------------------------------------------- sessions


class SessionOut(BaseModel):
    session_id: str
    views: int
    object_seen: bool = Field(description="whether any view showed object points")
    created: datetime
    updated: datetime
    expires: datetime = Field(description="when the session is deleted unless a view arrives")
    support_plane: SupportPlane | None = Field(
        None, description="the support plane the session keeps, [nx, ny, nz, d] in the world "
        "frame (|n| = 1), once POST /views or GET /grasp gave one"
    )
    registered: bool = Field(
        True, description="whether the session fuses its posed views (POST /views' registered)")
    completion: Literal["registered", "memory"] = Field(
        "memory", description="how the latest completion was made (POST /views' completion)")


class OccupancyOut(BaseModel):
    session_id: str
    views: int
    shape: list[int]
    encoding: Literal["packbits"] = Field(
        "packbits", description="numpy.packbits of the bool grid in C order, then base64"
    )
    data: str
    threshold: float
    occupied_voxels: int
    grid_to_camera: Pose = Field(description="4×4, latest view's camera frame")


class HealthOut(BaseModel):
    status: Literal["ok"] = "ok"
    model: str
    sessions: int


class ErrorOut(BaseModel):
    detail: str | list[dict] = Field(description="what was wrong and what was expected")
