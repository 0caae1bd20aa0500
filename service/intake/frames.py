"""Frames checked against what the camera saw: a wrong pose or plane is a 422, not a grasp.

A camera pose and a support plane are numbers the robot's code computes; a wrong convention
(millimetres, world→camera, OpenGL's camera frame, the plane in the camera frame, its normal or
its offset's sign flipped) still gives rigid poses and valid planes, and once accepted it becomes
a confident grasp in the wrong place. What the views show can refute them:

- the camera's distance from the world's origin (:attr:`FrameChecks.max_camera_distance_m`);
- with a support plane (given with the view, or kept by the session): the camera above the table,
  the object's points on its upper side, and the table itself where the depth image shows it
  (the pixels outside the mask: some of them lie on the plane), or else the object's lowest point
  near it (:attr:`FrameChecks.max_plane_gap_m`);
- from the second posed view on: the object where the previous view saw it, in the world, once
  the camera has moved (:attr:`FrameChecks.max_object_jump_m`); a refusal there says that this
  view or an earlier one is wrong, since an earlier view was accepted on less evidence.

Each refusal is an :class:`~service.intake.inputs.InputError` (422) naming the field and the mistake
that would explain it: the checks are run again with each likely mistake undone, and the first
that makes the view consistent is named. ``GRASP_CHECK_FRAMES=false`` (the service) or
``"check_frames": false`` (one view) turns them off for a caller who knows better.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from completion.grid import transform_points
from grasp_client.wire import SupportPlane
from service.intake.inputs import DecodedView, InputError

#: OpenGL's camera frame (x right, y up, z backward) against OpenCV's (x right, y down, z forward).
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
#: A camera that moved less than this (metres) between views has not moved.
STILL_M = 0.02
#: The table counts as seen where at least this share of the background's points lie on the plane
#: (within the tolerance) ...
TABLE_SHARE = 0.10
#: ... and at least this many times the share a plane cutting across the background at random
#: would hold (the tolerance's slab against the background's spread of heights), or half of it.
TABLE_CONCENTRATION = 3.0
FRAMES = ("OpenCV optical: x right, y down, z forward; camera_pose is camera→world in metres; "
          "support_plane is [nx, ny, nz, d] in the world frame, n pointing up")


@dataclass(frozen=True)
class FrameChecks:
    """The tolerances (metres) of the frame checks; the service's settings build it
    (``GRASP_MAX_CAMERA_DISTANCE_M``, ``GRASP_PLANE_TOLERANCE_M``, ``GRASP_MAX_PLANE_GAP_M``,
    ``GRASP_MAX_OBJECT_JUMP_M``: :meth:`service.settings.Settings.frame_checks`)."""

    max_camera_distance_m: float
    plane_tolerance_m: float
    max_plane_gap_m: float
    max_object_jump_m: float


@dataclass(frozen=True)
class Previous:
    """What the session saw before this view: its camera pose and the object's world points."""

    camera_to_world: np.ndarray
    points_world: np.ndarray  # (n, 3)


def check_view(view: DecodedView, plane: SupportPlane | None, previous: Previous | None,
               limits: FrameChecks) -> None:
    """Refuse ``view`` (:class:`InputError`) when its camera pose or the support plane
    (``plane``: the view's or the session's, world frame) contradict what its
    depth or points show, or what ``previous`` showed."""
    pose = view.camera_to_world
    if pose is None or view.points is None or not len(view.points):
        return
    _check_distance(pose, previous, limits)
    problem = _problem(view.points, view.background, pose, plane, previous, limits)
    if problem is None:
        return
    loc, said = problem
    fix = _likely_mistake(view.points, view.background, pose, plane, previous, limits)
    if fix is None:
        raise InputError(loc, f"{said} ({FRAMES})")
    field, advice = fix  # the field to correct is the mistake's, whichever check noticed it
    raise InputError(("body", field), f"{said}; {advice}")


def check_plane(plane: SupportPlane, points: np.ndarray, camera_to_world: np.ndarray,
                limits: FrameChecks) -> None:
    """Refuse (:class:`InputError` on the query's ``support_plane``) a plane given apart from a
    view (``GET /grasp``, the inspector's scene) that contradicts what the session's latest view
    saw (``points``, its camera frame; ``camera_to_world``, its pose): the plane checks of
    :func:`check_view`, with no depth image to show the table."""
    problem = _problem(points, None, camera_to_world, plane, None, limits)
    if problem is None:
        return
    said = problem[1].replace("camera_pose and support_plane put", "support_plane puts")
    fix = _likely_mistake(points, None, camera_to_world, plane, None, limits, poses=False)
    raise InputError(("query", "support_plane"), f"{said} ({FRAMES})" if fix is None
                     else f"{said}; {fix[1]}")


def _check_distance(pose: np.ndarray, previous: Previous | None, limits: FrameChecks) -> None:
    far = float(np.linalg.norm(pose[:3, 3]))
    if far > limits.max_camera_distance_m:
        said = (f"camera_pose puts the camera {far:g} m from the world's origin (at most "
                f"GRASP_MAX_CAMERA_DISTANCE_M = {limits.max_camera_distance_m:g} m)")
        if far / 1000.0 <= limits.max_camera_distance_m:
            said += ": its translation looks like millimetres; poses are in metres"
        raise InputError(("body", "camera_pose"), said)
    if previous is not None:
        moved = float(np.linalg.norm(pose[:3, 3] - previous.camera_to_world[:3, 3]))
        if moved > limits.max_camera_distance_m:
            raise InputError(("body", "camera_pose"),
                             f"the camera moved {moved:g} m since the previous view (at most "
                             f"{limits.max_camera_distance_m:g} m): is this view's pose in "
                             "another unit or frame than the earlier ones'?")


def _problem(points, background, pose, plane, previous, limits) -> tuple[tuple, str] | None:
    """What is inconsistent, as (field, what), or None."""
    world = transform_points(points, pose)
    if plane is not None:
        camera = float(plane.height(pose[:3, 3]))
        if camera < -limits.plane_tolerance_m:
            return (("body", "camera_pose"),
                    f"camera_pose and support_plane put the camera {-camera:.3g} m below the "
                    "table")
        low = float(np.percentile(plane.height(world), 2))
        if low < -limits.plane_tolerance_m:
            return (("body", "support_plane"),
                    f"the object's points lie down to {-low:.3g} m below the support plane")
        table = _table_seen(background, pose, plane, limits)
        if table is False and low > limits.plane_tolerance_m or \
                table is None and low > limits.max_plane_gap_m:
            seen = " and none of the table the depth image shows lies on it" if table is False \
                else ""
            return (("body", "support_plane"),
                    f"the object's lowest point lies {low:.3g} m above the support plane{seen}")
    if previous is not None and len(previous.points_world):
        moved = float(np.linalg.norm(pose[:3, 3] - previous.camera_to_world[:3, 3]))
        turned = float(np.abs(pose[:3, :3] - previous.camera_to_world[:3, :3]).max())
        jump = float(np.linalg.norm(np.median(world, axis=0)
                                    - np.median(previous.points_world, axis=0)))
        if (moved > STILL_M or turned > 0.05) and jump > limits.max_object_jump_m:
            return (("body", "camera_pose"),
                    f"with this camera_pose the object lies {jump:.3g} m from where the "
                    "session's previous view saw it (this view's pose, or an earlier one, is "
                    "wrong: the views disagree)")
    return None


def _table_seen(background, pose, plane, limits) -> bool | None:
    """Whether some of the depth image's background lies on the plane (None: too little
    background to tell)."""
    if background is None or len(background) < 50:
        return None
    heights = plane.height(transform_points(background, pose))
    share = float(np.mean(np.abs(heights) <= limits.plane_tolerance_m))
    lo, hi = np.percentile(heights, [5, 95])
    chance = min(1.0, 2.0 * limits.plane_tolerance_m / max(float(hi - lo), 1e-9))
    # a background that is all table (a spread within the tolerance) is the table
    return share >= TABLE_SHARE and share >= min(TABLE_CONCENTRATION * chance, 0.5)


def _likely_mistake(points, background, pose, plane, previous, limits,
                    poses: bool = True) -> tuple[str, str] | None:
    """The first common mistake whose undoing makes the view consistent: the field it is in, and
    advice (``poses=False``: the plane's mistakes alone)."""
    alternatives: list[tuple[str, str, Callable[[], tuple]]] = [] if not poses else [
        ("camera_pose", "camera_pose looks like world→camera: send camera→world (its inverse)",
         lambda: (np.linalg.inv(pose), plane)),
        ("camera_pose", "camera_pose looks like an OpenGL camera (y up, z backward): the camera "
         "frame is OpenCV's (x right, y down, z forward); multiply it by diag(1, -1, -1, 1) on "
         "the right", lambda: (pose @ OPENGL_TO_OPENCV, plane)),
    ]
    if plane is not None:
        alternatives += [
            ("support_plane", "support_plane's normal points down: n points up, from the table "
             "toward the object (send -n, -d)",
             lambda: (pose, SupportPlane(-plane.normal, -plane.offset))),
            ("support_plane", "support_plane's d has the wrong sign: n·x + d = 0 for points x on "
             "the table", lambda: (pose, SupportPlane(plane.normal, -plane.offset))),
            ("support_plane", "support_plane looks like it is in the camera frame: send it in the "
             "world frame", lambda: (pose, plane.transformed(np.linalg.inv(pose)))),
        ]
    for field, advice, undo in alternatives:
        other_pose, other_plane = undo()
        if _problem(points, background, other_pose, other_plane, previous, limits) is None:
            return field, advice
    return None

