"""Turn a ``POST /views`` body into the arrays ``CompletionStream.add_view`` takes.

Everything a client can get wrong is checked here and raised as :class:`InputError`, which the
app answers with 422 and a message that says what was expected. Nothing here touches a session,
so a rejected view changes nothing.
"""

from __future__ import annotations

import base64
import binascii
import io
import re
from dataclasses import dataclass

import numpy as np

from completion.grid import (
    GRID_SIZE,
    OBSTACLE_PITCH_M,
    Intrinsics,
    VoxelGrid,
    depth_to_points,
    indices_to_points,
)
from completion.view import View

# MAX_COORDINATE_M: the largest |coordinate| (metres) accepted in points, depth and transforms:
# far beyond any depth camera, small enough that fitting a grid cannot overflow
from grasp_client.wire import MAX_COORDINATE_M, SupportPlane, object_pixels, transform
from service.api.schemas import DepthIn, GridIn, ViewIn

#: Voxel pitch (metres) a client-made grid may have: 0.1 mm to 10 m.
MIN_PITCH_M, MAX_PITCH_M = 1e-4, 10.0
#: Fields of view (degrees) a depth camera has: focal lengths that give one outside are not in
#: pixels (or belong to another image size).
MIN_FOV_DEG, MAX_FOV_DEG = 20.0, 150.0
#: A depth image whose median over the object is nearer (metres) is refused.
MIN_DEPTH_MEDIAN_M = 0.05
#: fx / fy of a depth camera lies within this factor of 1 (square pixels).
MAX_ASPECT = 1.25
#: A depth camera's principal point lies within this share of the image's size from its centre.
MAX_OFF_CENTRE = 0.25


class InputError(ValueError):
    """Bad client input; ``loc`` names the field as FastAPI does, e.g. ("body", "depth", "data")."""

    def __init__(self, loc: tuple[str | int, ...], message: str) -> None:
        super().__init__(message)
        self.loc = loc
        self.message = message


@dataclass(frozen=True)
class DecodedView(View):
    """A view decoded and checked at the door: the :class:`completion.view.View` the stream takes
    (the object's points, a depth image back-projected here, or a ready grid; its pose and
    plane), plus what only the service uses."""

    background: np.ndarray | None = None  # (m, 3) some of a masked depth image's other pixels
    # (k, 3) camera frame: the pixels that may be obstacles (outside the mask, or the
    # obstacle_mask's), one about every OBSTACLE_PITCH_M at their depth; None: none sent
    others: np.ndarray | None = None
    check_frames: bool = True  # service.intake.frames checks this view (the body's check_frames)
    registered: bool | None = None  # the session fuses posed views from now on (None: as it did)


@dataclass(frozen=True)
class DecodeLimits:
    """What a view may hold (the service's settings build it: ``GRASP_MAX_IMAGE_PIXELS``,
    ``GRASP_MAX_POINTS``, ``GRASP_MAX_DEPTH_MEDIAN_M``, ``GRASP_MAX_POINT_DISTANCE_M``)."""

    max_image_pixels: int
    max_points: int
    max_depth_median_m: float
    max_point_distance_m: float


def decode_view(view: ViewIn, limits: DecodeLimits) -> DecodedView:
    """Decode and check one view; raises :class:`InputError`.

    A depth image is back-projected with :func:`completion.grid.depth_to_points`, exactly as
    ``CompletionStream.add_view(depth=...)`` and the training data do, so that the points can be
    checked like client-sent ones. What a robot integration gets wrong is caught here: a label
    image as the mask, millimetres as metres (a depth median beyond ``limits.max_depth_median_m``,
    the object's points beyond ``limits.max_point_distance_m``), intrinsics that are not in pixels
    or not of this image.
    """
    pose = view.camera_pose  # checked rigid by its type (grasp_client.wire.rigid_pose)
    max_points, max_point_distance_m = limits.max_points, limits.max_point_distance_m
    if view.support_plane is not None and pose is None:
        raise InputError(("body", "support_plane"),
                         f"{SupportPlane.NEEDS_POSES} (this view has no camera_pose)")
    posed = {"camera_to_world": None if pose is None else np.asarray(pose, dtype=np.float64),
             "support_plane": view.support_plane,
             "check_frames": view.check_frames, "registered": view.registered}
    if view.points is not None:
        if not view.points:
            raise InputError(("body", "points"), "points is empty: send the object's observed "
                             "points (at least one), or skip a view in which it is hidden")
        if len(view.points) > max_points:
            raise InputError(
                ("body", "points"), f"at most {max_points} points per view, got {len(view.points)}"
            )
        points = _checked_points(np.asarray(view.points, dtype=np.float64).reshape(-1, 3))
        _plausible_distance(points, max_point_distance_m, ("body", "points"), POINTS_HINT)
        return DecodedView(points=points, **posed)
    if view.grid is not None:
        return DecodedView(grid=_grid(view.grid), **posed)
    assert view.depth is not None and view.intrinsics is not None  # ViewIn's own check
    depth = _depth(view.depth, limits.max_image_pixels)  # (H, W) uint16 mm or float32 m, as sent
    _plausible_intrinsics(view.intrinsics, depth.shape)
    mask = None if view.mask is None else _mask(view.mask, depth.shape, view.object_label)
    outside = None  # the pixels that may be obstacles
    if view.obstacles and view.obstacle_mask is not None:
        outside = _mask(view.obstacle_mask, depth.shape, None, ("body", "obstacle_mask"))
    elif view.obstacles and mask is not None:
        outside = ~mask
    step = thinning_step(depth, mask, max_points)
    if step > 1:  # every step-th pixel along both axes: the same camera at a lower resolution
        depth = depth[::step, ::step].copy()  # copies, so that the full images are freed now
        mask = None if mask is None else mask[::step, ::step].copy()
        outside = None if outside is None else outside[::step, ::step].copy()
    _some_depth(depth, mask, view.depth.encoding)  # on the thinned image: no full-size copies
    intrinsics = scaled(view.intrinsics, step, depth.shape)
    metres = depth.astype(np.float64)
    if depth.dtype == np.uint16:
        metres /= 1000.0
    _plausible_depth(metres, mask, limits.max_depth_median_m, view.depth.encoding)
    with np.errstate(over="ignore", invalid="ignore"):
        points = depth_to_points(metres, intrinsics, mask)
        background = None if mask is None else _background(metres, intrinsics, mask)
        others = None if outside is None else _others(metres, intrinsics, outside)
    points = _checked_points(points, from_depth=True)
    _plausible_distance(points, max_point_distance_m, ("body", "depth", "data"), MILLIMETRES_HINT)
    return DecodedView(points=points, background=background, others=others, **posed)


#: At most this many of the background's points are kept to check the support plane against.
BACKGROUND_POINTS = 4096


def _background(metres: np.ndarray, intrinsics: Intrinsics, mask: np.ndarray) -> np.ndarray:
    """Up to :data:`BACKGROUND_POINTS` back-projected pixels outside ``mask`` with valid depth
    (the table, where the camera sees it), every s-th pixel along both axes."""
    outside = ~mask & np.isfinite(metres) & (metres > 0)
    count = int(outside.sum())
    if count < 50:  # too little to tell the table by (service.intake.frames); nothing allocated
        return None
    step = max(1, int(np.ceil(np.sqrt(count / BACKGROUND_POINTS))))
    return _every(step, metres, intrinsics, outside, cleaning=None)[:BACKGROUND_POINTS]


def _others(metres: np.ndarray, intrinsics: Intrinsics, outside: np.ndarray) -> np.ndarray:
    """The pixels of ``outside`` with a depth, back-projected (cleaned of flying pixels as the
    object's are) one about every :data:`completion.grid.OBSTACLE_PITCH_M` at their median
    depth: as dense as the obstacle voxels they fill, and no denser."""
    valid = outside & np.isfinite(metres) & (metres > 0)
    if not valid.any():
        return np.zeros((0, 3))
    spacing = float(np.median(metres[valid])) / intrinsics.fx  # metres between two pixels
    return _every(max(1, int(OBSTACLE_PITCH_M / spacing)), metres, intrinsics, valid)


def _every(step: int, metres: np.ndarray, intrinsics: Intrinsics, pixels: np.ndarray,
           **cleaning) -> np.ndarray:
    """``pixels`` of every ``step``-th row and column back-projected as the same camera at that
    lower resolution sees them (:func:`scaled`; ``cleaning``: :func:`depth_to_points`'s)."""
    thinned = metres[::step, ::step]  # a view: nothing copied
    points = depth_to_points(thinned, scaled(intrinsics, step, thinned.shape),
                             pixels[::step, ::step], **cleaning)
    return points[np.isfinite(points).all(axis=1)]


def scaled(intrinsics, step: int, shape: tuple[int, int]) -> Intrinsics:
    """The intrinsics (pixels: fx, fy, cx, cy) of an image thinned to every ``step``-th pixel
    along both axes, of ``shape`` (H, W) once thinned: the same camera at a lower resolution."""
    return Intrinsics(intrinsics.fx / step, intrinsics.fy / step, intrinsics.cx / step,
                      intrinsics.cy / step, width=shape[1], height=shape[0])


MILLIMETRES_HINT = "it looks like millimetres: send png16_mm (uint16 millimetres) or divide by 1000"
POINTS_HINT = "they look like millimetres: send metres (divide by 1000)"


def _some_depth(depth: np.ndarray, mask: np.ndarray | None, encoding: str) -> None:
    """A depth image with at least one return, and one inside a non-empty mask (a mask with no
    pixel, the object hidden, is a view like any other)."""
    valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():
        hint = ("metres cast to uint16 are all 0 or 1: send png16_mm in millimetres, or f32_m"
                if encoding == "png16_mm" else "every pixel is 0, NaN or ±inf")
        raise InputError(("body", "depth", "data"),
                         f"the depth image has no valid pixel (no return anywhere): {hint}")
    if encoding == "png16_mm" and depth[valid].max() < 1000 * MIN_DEPTH_MEDIAN_M:
        raise InputError(("body", "depth", "data"),
                         f"the depth image's returns are all below {1000 * MIN_DEPTH_MEDIAN_M:g} "
                         f"mm (at most {int(depth[valid].max())}): metres cast to uint16 leave 0 "
                         "or 1 mm; send millimetres (or f32_m in metres)")
    if mask is not None and mask.any() and not valid[mask].any():
        raise InputError(("body", "mask"),
                         f"none of the mask's {int(mask.sum())} object pixels has a depth return "
                         f"(the depth image has {int(valid.sum())}): is the mask of this depth "
                         "image, aligned with it?")


def _plausible_depth(metres: np.ndarray, mask, limit: float, encoding: str) -> None:
    """The depth's median over the object (valid pixels, inside the mask) within ``limit``."""
    valid = np.isfinite(metres) & (metres > 0)
    if mask is not None:
        valid &= mask
    if not valid.any():
        return
    median = float(np.median(metres[valid]))
    if median < MIN_DEPTH_MEDIAN_M:
        hint = ("metres cast to uint16 leave 0 or 1 mm: send millimetres" if encoding == "png16_mm"
                else "check the depth scale")
        raise InputError(("body", "depth", "data"),
                         f"the depth's median over the object is {1000 * median:g} mm, nearer than "
                         f"a depth camera sees ({1000 * MIN_DEPTH_MEDIAN_M:g} mm): {hint}")
    if median > limit:
        hint = MILLIMETRES_HINT if encoding == "f32_m" else "check the depth scale"
        raise InputError(("body", "depth", "data"),
                         f"the depth's median over the object is {median:g} m, farther than a "
                         f"depth camera sees (GRASP_MAX_DEPTH_MEDIAN_M = {limit:g} m): {hint}")


def _plausible_distance(points: np.ndarray, limit: float, loc: tuple[str, ...], hint: str) -> None:
    """The object's points (their median distance from the camera) within ``limit``."""
    if not len(points):
        return
    median = float(np.median(np.linalg.norm(points, axis=1)))
    if median > limit:
        raise InputError(loc, f"the object's points lie {median:g} m from the camera (median), "
                         f"farther than a depth camera sees (GRASP_MAX_POINT_DISTANCE_M = "
                         f"{limit:g} m): {hint}")


def _plausible_intrinsics(k, shape: tuple[int, int]) -> None:
    """The principal point inside the image; focal lengths in pixels that give this image a
    field of view a depth camera has (:data:`MIN_FOV_DEG` … :data:`MAX_FOV_DEG`); square pixels
    (:data:`MAX_ASPECT`) and the principal point near the centre (:data:`MAX_OFF_CENTRE`): K's
    numbers in another order fail these."""
    h, w = shape
    loc = ("body", "intrinsics")

    def off_centre(cx: float, cy: float) -> float:  # as a share of the image's size
        return max(abs(cx - (w - 1) / 2) / w, abs(cy - (h - 1) / 2) / h)

    swapped = off_centre(k.cy, k.cx) < 0.02  # exchanged, they would sit at the centre
    where = f"the principal point (cx, cy) = ({k.cx:g}, {k.cy:g})"
    if not (0 <= k.cx <= w - 1 and 0 <= k.cy <= h - 1):
        raise InputError(loc, f"{where} lies outside the {w}×{h} depth image (cx in 0…{w - 1}, "
                         f"cy in 0…{h - 1})" + ("; are cx and cy swapped?" if swapped else ""))
    if off_centre(k.cx, k.cy) > 0.1 and swapped:
        raise InputError(loc, f"{where} lies far from the centre of the {w}×{h} depth image, "
                         f"where ({k.cy:g}, {k.cx:g}) would sit: cx and cy look swapped (cx "
                         f"runs along the width), or the depth image is transposed (K fits a "
                         f"{h}×{w} image)")
    for name, f, size, side in (("fx", k.fx, w, "wide"), ("fy", k.fy, h, "high")):
        fov = float(np.degrees(2.0 * np.arctan(size / (2.0 * f))))
        if not MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
            raise InputError(loc, f"{name} = {f:g} gives the {size}-pixel-{side} image a field of "
                             f"view of {fov:.1f}°, where a depth camera's is {MIN_FOV_DEG:g}–"
                             f"{MAX_FOV_DEG:g}°: focal lengths are in pixels (about "
                             f"{size / (2 * np.tan(np.radians(30))):.0f} for a 60° view of "
                             f"this image)")
    ratio = k.fx / k.fy
    if not 1 / MAX_ASPECT <= ratio <= MAX_ASPECT:
        factor = max(ratio, 1 / ratio)
        raise InputError(loc, f"fx = {k.fx:g} and fy = {k.fy:g} differ by a factor {factor:.2f}: "
                         f"a depth camera's pixels are square (fx ≈ fy, within ×{MAX_ASPECT:g}); "
                         "is K in the order fx, fy, cx, cy? (ROS's CameraInfo.k is row-major: "
                         "fx = k[0], cx = k[2], fy = k[4], cy = k[5])")
    if off_centre(k.cx, k.cy) > MAX_OFF_CENTRE:
        raise InputError(loc, f"{where} lies {100 * off_centre(k.cx, k.cy):.0f} % of the image "
                         f"from the centre of the {w}×{h} depth image, where a depth camera's "
                         f"lies within {100 * MAX_OFF_CENTRE:.0f} %: is K in the order fx, fy, cx, "
                         "cy, and of this image?")


def thinning_step(depth: np.ndarray, mask: np.ndarray | None, max_points: int) -> int:
    """The smallest pixel step s ≥ 1 such that every s-th pixel along both axes gives at most
    ``max_points`` object points (valid depth, inside the mask): how a depth image with more
    points than a view may hold is thinned (GRASP_MAX_POINTS), before any point is made."""
    valid = depth > 0 if depth.dtype == np.uint16 else np.isfinite(depth) & (depth > 0)
    if mask is not None:
        valid &= mask
    count = int(np.count_nonzero(valid))
    if count <= max_points:
        return 1
    step = max(2, int(np.ceil(np.sqrt(count / max_points))))
    while np.count_nonzero(valid[::step, ::step]) > max_points:
        step += 1
    return step


def _base64(text: str, loc: tuple[str, ...]) -> bytes:
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise InputError(loc, f"{'.'.join(loc[1:])} must be standard base64 ({exc})") from exc


def _checked_points(pts: np.ndarray, *, from_depth: bool = False) -> np.ndarray:
    loc = ("body", "intrinsics") if from_depth else ("body", "points")
    far = np.flatnonzero(~(np.abs(pts).max(axis=1, initial=0.0) <= MAX_COORDINATE_M))
    if len(far) and from_depth:
        raise InputError(
            loc,
            f"the depth image back-projects to points beyond ±{MAX_COORDINATE_M:g} m "
            f"(e.g. {pts[far[0]].tolist()}): fx, fy, cx, cy must be in pixels",
        )
    if len(far):
        raise InputError(
            loc,
            f"point coordinates must lie within ±{MAX_COORDINATE_M:g} m; "
            f"point {far[0]} is {pts[far[0]].tolist()}",
        )
    behind = np.flatnonzero(pts[:, 2] <= 0)
    if len(behind):
        raise InputError(
            loc,
            "points must lie in front of the camera (z > 0 m, camera frame); "
            f"point {behind[0]} has z = {pts[behind[0], 2]:g}",
        )
    return pts


def _image_size_ok(width: int, height: int, max_pixels: int, loc: tuple[str, ...]) -> None:
    if width * height > max_pixels:
        raise InputError(
            loc,
            f"image is {width}×{height} = {width * height} pixels; "
            f"the limit is {max_pixels} pixels",
        )


def _png(raw: bytes, loc: tuple[str, ...], modes: tuple[str, ...], expected: str):
    """A decoded PNG as an array; checks the format and mode before decoding the pixels."""
    from PIL import Image

    try:
        image = Image.open(io.BytesIO(raw), formats=["PNG"])
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        reason = re.sub(r"<[^<>]* at 0x[0-9a-fA-F]+>", "the data", str(exc))  # no object reprs
        raise InputError(loc, f"{'.'.join(loc[1:])} is not a PNG image ({reason})") from exc
    if image.mode not in modes:
        raise InputError(loc, f"{'.'.join(loc[1:])} must be {expected}, got PNG mode {image.mode}")
    return image


def _pixels(image, loc: tuple[str, ...]) -> np.ndarray:
    """The pixels as an array; the image is closed (its buffer freed) either way."""
    from PIL import Image

    try:
        return np.array(image)
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        raise InputError(loc, f"{'.'.join(loc[1:])} could not be decoded ({exc})") from exc
    finally:
        image.close()


def _depth(depth: DepthIn, max_pixels: int) -> np.ndarray:
    """The depth image as sent: (H, W) uint16 millimetres (png16_mm) or float32 metres (f32_m)."""
    loc = ("body", "depth", "data")
    w, h = depth.width, depth.height
    _image_size_ok(w, h, max_pixels, ("body", "depth"))
    raw = _base64(depth.data, loc)
    if depth.encoding == "f32_m":
        if len(raw) != 4 * w * h:
            raise InputError(
                loc,
                f"f32_m depth of {w}×{h} needs width × height × 4 = {4 * w * h} bytes, "
                f"got {len(raw)}",
            )
        values = np.frombuffer(raw, dtype="<f4").reshape(h, w).astype(np.float32)
        finite = values[np.isfinite(values)]
        if finite.size and finite.min() < 0:
            raise InputError(
                loc,
                "depth must be ≥ 0 m (0, NaN or ±inf mark pixels without a return); "
                f"found {finite.min():g}",
            )
        if finite.size and finite.max() > MAX_COORDINATE_M:
            raise InputError(
                loc, f"depth must be at most {MAX_COORDINATE_M:g} m; found {finite.max():g}"
            )
        return values
    image = _png(raw, loc, ("I;16", "I;16B", "I;16L", "I"), "a 16-bit single-channel PNG (mm)")
    if image.size != (w, h):
        raise InputError(
            loc, f"depth PNG is {image.size[0]}×{image.size[1]} but width × height say {w}×{h}"
        )
    millimetres = _pixels(image, loc)
    if millimetres.min(initial=0) < 0 or millimetres.max(initial=0) > 65535:
        raise InputError(loc, "depth PNG values must be 0…65535 mm")
    return millimetres.astype(np.uint16, copy=False)


def _mask(text: str, shape: tuple[int, int], label: int | None = None,
          loc: tuple = ("body", "mask")) -> np.ndarray:
    """The object's pixels: a 0/1 or 0/255 mask, or the pixels equal to ``label`` in a label
    image; anything else is refused with the values it holds. (An obstacle mask: ``loc``
    names it, and its non-zero pixels are the obstacles.)"""
    image = _png(_base64(text, loc), loc, ("L", "1", "P"), "an 8-bit single-channel PNG")
    h, w = shape
    if image.size != (w, h):
        raise InputError(
            loc, f"{loc[-1]} is {image.size[0]}×{image.size[1]} but the depth image is {w}×{h}"
        )
    if loc[-1] == "obstacle_mask":
        return _pixels(image, loc) != 0
    try:
        return object_pixels(_pixels(image, loc), label, kind="an 8-bit PNG")
    except ValueError as exc:
        raise InputError(loc, str(exc)) from None


def _grid(grid: GridIn) -> VoxelGrid:
    raw = _base64(grid.data, ("body", "grid", "data"))
    n = GRID_SIZE**3 // 8
    if len(raw) != n:
        raise InputError(
            ("body", "grid", "data"),
            f"grid.data must hold {n} bytes (40³ bits packed with numpy.packbits), got {len(raw)}",
        )
    loc = ("body", "grid", "grid_to_camera")
    try:
        t = transform(grid.grid_to_camera, "grid_to_camera")
    except ValueError as exc:
        raise InputError(loc, str(exc)) from None
    pitch = float(t[0, 0])
    scale = t[:3, :3]
    if not MIN_PITCH_M <= pitch <= MAX_PITCH_M or not np.allclose(
        scale, pitch * np.eye(3), rtol=0.0, atol=1e-6 * pitch
    ):
        raise InputError(
            loc,
            "grid_to_camera must be pitch × identity plus a translation (grid axes along the "
            f"camera axes, docs/design.md §3) with a pitch of {MIN_PITCH_M:g}…{MAX_PITCH_M:g} m; "
            f"got the 3×3 part {np.round(scale, 9).tolist()}",
        )
    centre = indices_to_points(np.full((1, 3), (GRID_SIZE - 1) / 2.0), t)[0]
    if not centre[2] > 0.0:
        raise InputError(
            loc,
            "the grid lies behind the camera: grid_to_camera must put the grid's centre in "
            f"front of it (camera z > 0), got z = {centre[2]:.3g} m",
        )
    return VoxelGrid(VoxelGrid.unpack(raw), t)
