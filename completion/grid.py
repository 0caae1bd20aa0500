"""Frames and the 40³ voxel grid: the one implementation used by training, evaluation and service.

Conventions (docs/design.md §3):

- Camera frame: OpenCV optical, x right, y down, z forward, metres. Depth is metric z.
- A grid is a (40, 40, 40) bool array plus a 4×4 ``grid_to_camera`` transform that maps a voxel
  index (i, j, k) (along camera x, y, z) to the metric point at that voxel's centre. The grid
  axes are parallel to the camera axes, so the transform is a uniform scale (the voxel pitch) plus
  a translation.
- Voxel (i, j, k) covers indices [i - 0.5, i + 0.5) along each axis.
- The Varley fit puts the centre of the observed points' bounding box at index (20, 20, 18) and
  makes the largest bbox extent span 32 voxels. While the camera has not moved (same pose as
  the previous view), the box is that of every point seen from that pose (:func:`fit_seen`).

Only numpy (and libigl, imported where used) lives here: torch never.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from completion.depth import DEPTH_FILTER, DepthFilter
from grasp_client.wire import SupportPlane

GRID_SIZE = 40
GRID_SHAPE = (GRID_SIZE, GRID_SIZE, GRID_SIZE)
FIT_CENTER_INDEX = np.array([20.0, 20.0, 18.0])
FIT_EXTENT_VOXELS = 32.0
#: The smallest pitch the fit will use (metres), so one point or a flat patch still gets a grid.
MIN_PITCH = 1e-3
#: A point is inside a mesh when |generalised winding number| exceeds this.
WINDING_THRESHOLD = 0.5
#: Side (m) of the world-frame voxels a session keeps the other objects in view as, obstacles to
#: the planner (:func:`voxel_keys`; ``CompletionStream.add_obstacles``, ``grasp.search.obstacles``).
OBSTACLE_PITCH_M = 0.005


def voxel_keys(points: np.ndarray, pitch: float) -> np.ndarray:
    """(n, 3) int64 indices of the axis-aligned voxels of side ``pitch`` (one corner at the
    origin) that hold ``points`` (n, 3); a voxel's centre is ``(key + 0.5) * pitch``."""
    return np.floor(np.asarray(points, dtype=np.float64).reshape(-1, 3) / pitch).astype(np.int64)


def pack_voxel_keys(keys: np.ndarray) -> np.ndarray:
    """A set of voxel keys (n, 3) as compact bytes (uint8): the occupancy of their bounding box
    as bits, deflated (zlib), after a header of the box's corner and shape (6 int32). Keys sampled
    from surfaces take well under a byte each; :func:`unpack_voxel_keys` gives them back sorted."""
    keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
    if not len(keys):
        return np.zeros(0, dtype=np.uint8)
    low = keys.min(axis=0)
    shape = keys.max(axis=0) - low + 1
    bits = np.zeros(int(np.prod(shape)), dtype=bool)
    bits[np.ravel_multi_index((keys - low).T, shape)] = True
    header = np.concatenate([low, shape]).astype("<i4").tobytes()
    return np.frombuffer(header + zlib.compress(np.packbits(bits).tobytes(), 6), dtype=np.uint8)


def unpack_voxel_keys(packed: np.ndarray) -> np.ndarray:
    """The keys (n, 3) int32 that :func:`pack_voxel_keys` packed, in lexicographic order."""
    data = np.asarray(packed, dtype=np.uint8).tobytes()
    if not data:
        return np.zeros((0, 3), dtype=np.int32)
    header = np.frombuffer(data[:24], dtype="<i4").astype(np.int64)
    low, shape = header[:3], header[3:]
    bits = np.unpackbits(np.frombuffer(zlib.decompress(data[24:]), dtype=np.uint8),
                         count=int(np.prod(shape)))
    index = np.flatnonzero(bits)
    return (np.stack(np.unravel_index(index, shape), axis=1) + low).astype(np.int32)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels; pixel (u, v) has its centre at integer (u, v)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in values) or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"intrinsics need finite fx, fy > 0 and finite cx, cy; got {values}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}×{self.height}")

    @classmethod
    def from_fov(cls, width: int, height: int, vertical_fov_deg: float) -> Intrinsics:
        """Square pixels, principal point at the image centre."""
        f = 0.5 * height / np.tan(np.radians(vertical_fov_deg) / 2.0)
        return cls(
            fx=f, fy=f, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, width=width, height=height
        )

    def as_dict(self) -> dict:
        return {
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "width": self.width,
            "height": self.height,
        }


#: Default camera: 320×240 with a RealSense-D415-like 42.5° vertical field of view.
DEFAULT_INTRINSICS = Intrinsics.from_fov(320, 240, 42.5)


def as_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    """``points`` as a finite (n, 3) float64 array; ValueError saying what was expected."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{name} must be an (n, 3) array, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{name} must be finite (no NaN or inf)")
    return pts


def _check_transform(grid_to_camera: np.ndarray) -> np.ndarray:
    t = np.asarray(grid_to_camera, dtype=np.float64)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise ValueError(f"grid_to_camera must be a finite 4×4 matrix, got shape {t.shape}")
    return t


def indices_to_points(indices: np.ndarray, grid_to_camera: np.ndarray) -> np.ndarray:
    """Voxel indices (n, 3) (int or fractional) → camera-frame points (n, 3) float, metres."""
    t = _check_transform(grid_to_camera)
    idx = np.asarray(indices, dtype=np.float64).reshape(-1, 3)
    return idx @ t[:3, :3].T + t[:3, 3]


def points_to_indices(
    points: np.ndarray, grid_to_camera: np.ndarray, *, rounded: bool = True
) -> np.ndarray:
    """Camera-frame points (n, 3) → voxel indices (n, 3): int64 when ``rounded``, else float.

    Indices may lie outside [0, 40); callers mask with :func:`in_grid`.
    """
    t = _check_transform(grid_to_camera)
    pts = as_points(points)
    idx = np.linalg.solve(t[:3, :3], (pts - t[:3, 3]).T).T
    if rounded:
        return np.floor(idx + 0.5).astype(np.int64)
    return idx


def in_grid(indices: np.ndarray) -> np.ndarray:
    """(n,) bool: which integer indices (n, 3) lie inside the 40³ grid."""
    return np.all((indices >= 0) & (indices < GRID_SIZE), axis=1)


def fit_grid(points: np.ndarray) -> np.ndarray:
    """The Varley fit: the 4×4 ``grid_to_camera`` for a view's observed object points (n, 3).

    Bounding-box centre at index (20, 20, 18); largest extent across 32 voxels (pitch no smaller
    than :data:`MIN_PITCH`). A function of the points alone.
    """
    pts = as_points(points)
    if len(pts) == 0:
        raise ValueError("fit_grid needs at least one observed point")
    return _fit_bounds(pts.min(axis=0), pts.max(axis=0))


def _fit_bounds(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    centre = (lo + hi) / 2.0
    pitch = max(float((hi - lo).max()) / FIT_EXTENT_VOXELS, MIN_PITCH)
    t = np.eye(4)
    t[:3, :3] *= pitch
    t[:3, 3] = centre - pitch * FIT_CENTER_INDEX
    return t


#: Two camera poses closer than this (metres, and radians via the rotation's entries) are "the
#: camera has not moved" for :func:`fit_seen`.
STILL_CAMERA_TOLERANCE = 1e-6


def camera_still(camera_to_world: np.ndarray | None, previous: np.ndarray | None) -> bool:
    """True when both poses are known and equal within :data:`STILL_CAMERA_TOLERANCE`."""
    if camera_to_world is None or previous is None:
        return False
    diff = np.asarray(camera_to_world, dtype=np.float64) - np.asarray(previous, dtype=np.float64)
    return bool(np.abs(diff).max() <= STILL_CAMERA_TOLERANCE)


def fit_seen(
    points: np.ndarray,
    seen: np.ndarray | None = None,
    *,
    cleaning: DepthFilter | None = DEPTH_FILTER,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The fit of a view's observed points (docs/design.md §3): the Varley fit over the bounding box
    of this view's points (the ones :meth:`completion.depth.DepthFilter.inliers` keeps: a few
    stray points do not stretch it) together with ``seen``, the (2, 3) [lo, hi] bounds of
    every point seen earlier from the same pose (None for a new pose: the plain per-view fit).
    ``cleaning=None`` frames every point.

    Returns ``(grid_to_camera, bounds)``; both None when there are no points now and none seen
    (the caller carries the previous grid). With a still camera the grid never shrinks around
    what is visible now, so an object that moves behind another stays inside it.
    """
    pts = as_points(points)
    framing = pts if cleaning is None else pts[cleaning.inliers(pts)]  # strays do not stretch it
    bounds = np.stack([framing.min(axis=0), framing.max(axis=0)]) if len(pts) else None
    if seen is not None:
        seen = np.asarray(seen, dtype=np.float64)
        if seen.shape != (2, 3) or not np.isfinite(seen).all():
            raise ValueError(f"seen bounds must be a finite (2, 3) [lo, hi], got {seen.shape}")
        if bounds is None:
            bounds = seen
        else:
            bounds = np.stack([np.minimum(seen[0], bounds[0]), np.maximum(seen[1], bounds[1])])
    if bounds is None:
        return None, None
    return _fit_bounds(bounds[0], bounds[1]), bounds


def view_grid(
    points: np.ndarray,
    camera_to_world: np.ndarray | None = None,
    previous_grid: np.ndarray | None = None,
    previous_camera: np.ndarray | None = None,
    seen: np.ndarray | None = None,
    *,
    cleaning: DepthFilter | None = DEPTH_FILTER,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The grid of a new view (docs/design.md §3), one rule for the training data and the service.

    points : (n, 3) this view's observed object points; camera_to_world : its pose, if known;
    previous_grid, previous_camera, seen : the previous view's grid, pose and the bounds this
    function returned with it; cleaning : :mod:`completion.depth`'s rule for the box (None: every
    point frames it). While the camera stands still the grid frames every point seen
    from it (:func:`fit_seen`); a view with no points (and none seen from here) keeps the previous
    grid, where it was in the world when both poses are known (:func:`carry_grid`).

    Returns ``(grid_to_camera, seen)`` to pass with the next view; the grid is None only before
    any view had points.
    """
    still = camera_still(camera_to_world, previous_camera)
    fitted, seen = fit_seen(points, seen if still else None, cleaning=cleaning)
    if fitted is not None or previous_grid is None:
        return fitted, seen
    if camera_to_world is None or previous_camera is None:
        return previous_grid, None
    return carry_grid(previous_grid, previous_camera, camera_to_world), None


def voxels_below_plane(grid_to_camera: np.ndarray, plane: SupportPlane) -> np.ndarray:
    """(40, 40, 40) bool: voxels whose centre lies strictly below ``plane`` (n·x + d < 0, n
    pointing up), the plane given in the grid's camera frame."""
    return (plane.height(voxel_centers(grid_to_camera)) < 0).reshape(GRID_SHAPE)


def voxel_centers(grid_to_camera: np.ndarray) -> np.ndarray:
    """(40³, 3) camera-frame centres of every voxel, in C order of the (i, j, k) array."""
    idx = np.stack(np.meshgrid(*(np.arange(GRID_SIZE),) * 3, indexing="ij"), axis=-1)
    return indices_to_points(idx.reshape(-1, 3), grid_to_camera)


def voxelize_points(points: np.ndarray, grid_to_camera: np.ndarray) -> np.ndarray:
    """(40, 40, 40) bool: a voxel is occupied when at least one point falls in it."""
    occ = np.zeros(GRID_SHAPE, dtype=bool)
    pts = as_points(points)
    if len(pts) == 0:
        return occ
    idx = points_to_indices(pts, grid_to_camera)
    idx = idx[in_grid(idx)]
    occ[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return occ


def voxelize_mesh(
    vertices: np.ndarray, faces: np.ndarray, grid_to_camera: np.ndarray
) -> np.ndarray:
    """Solid ground truth: (40, 40, 40) bool, a voxel occupied when its centre is inside the mesh.

    vertices : (v, 3) float, camera frame, metres
    faces : (f, 3) int

    "Inside" is the generalised winding number (libigl's fast winding number) above 0.5 in
    magnitude, which stays correct for meshes with holes or inconsistent orientation, where ray
    parity or flood fill would leak and give a hollow or empty result. Parts thinner than a voxel
    (a plate, a mug wall) contain no voxel centre; they are kept by adding the voxels that surface
    samples fall in wherever no inside voxel is adjacent, so thick parts keep their exact volume.
    """
    import igl

    v = as_points(vertices, "vertices")
    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"faces must be a non-empty (f, 3) int array, got shape {f.shape}")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError("faces index vertices that do not exist")
    t = _check_transform(grid_to_camera)
    pitch = pitch_of(t)
    # Voxels the surface passes through: the winding number is evaluated at each of their centres.
    shell = voxelize_points(sample_surface(v, f, spacing=pitch / 3.0), t)
    # Every other voxel lies in a 6-connected region that no surface crosses, so inside/outside is
    # constant over it: a vote of 16 centres decides a region; where they disagree, the samples
    # left a gap in the shell (inside met outside) and each voxel of the region is decided alone.
    labels, n_regions = ndimage.label(~shell)
    queries = [np.argwhere(shell)]
    rng = np.random.default_rng(0)
    region_samples = []
    for region, where in enumerate(ndimage.find_objects(labels), start=1):
        members = np.argwhere(labels[where] == region) + [sl.start for sl in where]
        pick = members[rng.choice(len(members), size=min(len(members), 16), replace=False)]
        region_samples.append((region, len(pick)))
        queries.append(pick)
    idx = np.concatenate(queries)
    w = np.abs(igl.fast_winding_number(v, f, indices_to_points(idx, t))) > WINDING_THRESHOLD
    n_shell = len(queries[0])
    inside = np.zeros(GRID_SHAPE, dtype=bool)
    inside[tuple(queries[0][w[:n_shell]].T)] = True
    offset = n_shell
    region_inside = np.zeros(n_regions + 1, dtype=bool)
    mixed = []
    for region, count in region_samples:
        votes = w[offset : offset + count]
        region_inside[region] = votes.mean() > 0.5
        if votes.any() and not votes.all():
            mixed.append(region)
        offset += count
    inside |= region_inside[labels]
    if mixed:  # the surface samples left a gap: inside and outside met, decide voxel by voxel
        members = np.argwhere(np.isin(labels, mixed))
        inside[tuple(members.T)] = (
            np.abs(igl.fast_winding_number(v, f, indices_to_points(members, t)))
            > WINDING_THRESHOLD
        )
    return inside | (shell & ~ndimage.binary_dilation(inside))


def sample_surface(vertices: np.ndarray, faces: np.ndarray, *, spacing: float) -> np.ndarray:
    """Deterministic area-weighted surface samples (n, 3), about one per ``spacing``² of area.

    Every vertex is included, so small faces are never missed.
    """
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[np.asarray(faces)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = float(area.sum())
    n = int(min(max(total / spacing**2, 0), 2_000_000))
    if n == 0 or total == 0:
        return v
    rng = np.random.default_rng(0)
    which = rng.choice(len(tri), size=n, p=area / total)
    r1, r2 = rng.random((2, n))
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    t = tri[which]
    pts = t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])
    return np.concatenate([v, pts])


def depth_to_points(
    depth: np.ndarray,
    intrinsics: Intrinsics,
    mask: np.ndarray | None = None,
    *,
    cleaning: DepthFilter | None = DEPTH_FILTER,
) -> np.ndarray:
    """Back-project a metric depth image (H, W) to camera-frame points (n, 3): the one path from
    a depth image to observed points (training data, evaluation, stream and service).

    Pixels with depth ≤ 0 or non-finite are treated as missing (no return), as depth cameras
    report them, and so are the flying pixels ``cleaning`` finds (:mod:`completion.depth`: a
    pixel without support from its neighbours in the mask; None back-projects every return).
    With a mask (H, W) bool/uint8, only pixels where it is non-zero are used.
    """
    d = np.asarray(depth, dtype=np.float64)
    if d.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(
            f"depth must be (height, width) = ({intrinsics.height}, {intrinsics.width}) "
            f"as the intrinsics say, got {d.shape}"
        )
    m = None
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != d.shape:
            raise ValueError(f"mask must have the depth image's shape {d.shape}, got {m.shape}")
        m = m.astype(bool)
    if cleaning is None:
        valid = np.isfinite(d) & (d > 0) & (True if m is None else m)
    else:
        valid = cleaning.supported(d, intrinsics.fx, intrinsics.fy, m)
    v, u = np.nonzero(valid)
    z = d[v, u]
    x = (u - intrinsics.cx) * z / intrinsics.fx
    y = (v - intrinsics.cy) * z / intrinsics.fy
    return np.stack([x, y, z], axis=1)


def jaccard(prediction: np.ndarray, target: np.ndarray) -> np.ndarray:
    """|A ∩ B| / |A ∪ B| of bool grids over their last three axes (leading axes broadcast);
    1 where both are empty (they agree), 0 where exactly one is."""
    a, b = np.asarray(prediction, dtype=bool), np.asarray(target, dtype=bool)
    inter = np.count_nonzero(a & b, axis=(-3, -2, -1))
    union = np.count_nonzero(a | b, axis=(-3, -2, -1))
    return np.where(union > 0, inter / np.maximum(union, 1), 1.0)


def carry_grid(
    grid_to_camera: np.ndarray, camera_to_world: np.ndarray, new_camera_to_world: np.ndarray
) -> np.ndarray:
    """The grid of a view that saw no object points: the previous view's grid, the same place in
    the world, re-expressed in the new camera frame (``grid_to_camera`` for the new view).

    grid_to_camera : (4, 4) the previous view's grid; camera_to_world, new_camera_to_world :
    (4, 4) poses of the previous and the new camera. The scenes, the stream and the service all
    carry a grid this way, so an empty view never moves the object with the camera.
    """
    old, new = _check_transform(camera_to_world), _check_transform(new_camera_to_world)
    return np.linalg.inv(new) @ old @ _check_transform(grid_to_camera)


def pitch_of(grid_to_camera: np.ndarray) -> float:
    """Voxel edge length in metres of a grid transform (cube root of its scale's determinant)."""
    t = np.asarray(grid_to_camera, dtype=np.float64)
    return float(np.cbrt(abs(np.linalg.det(t[:3, :3]))))


def transform_points(points: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """Apply a 4×4 rigid or affine transform to (n, 3) points."""
    t = np.asarray(transform, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ t[:3, :3].T + t[:3, 3]


@dataclass(frozen=True)
class VoxelGrid:
    """A (40, 40, 40) bool occupancy array plus its 4×4 ``grid_to_camera``."""

    occupancy: np.ndarray
    grid_to_camera: np.ndarray

    def __post_init__(self) -> None:
        occ = np.asarray(self.occupancy)
        if occ.shape != GRID_SHAPE:
            raise ValueError(f"occupancy must be {GRID_SHAPE}, got {occ.shape}")
        object.__setattr__(self, "occupancy", occ.astype(bool, copy=False))
        object.__setattr__(self, "grid_to_camera", _check_transform(self.grid_to_camera))

    @property
    def pitch(self) -> float:
        """Voxel edge length in metres."""
        return pitch_of(self.grid_to_camera)

    @classmethod
    def from_points(cls, points: np.ndarray, grid_to_camera: np.ndarray | None = None) -> VoxelGrid:
        """Voxelize observed points, fitting the grid to them unless a transform is given."""
        t = fit_grid(points) if grid_to_camera is None else grid_to_camera
        return cls(voxelize_points(points, t), t)

    def points(self) -> np.ndarray:
        """(n, 3) camera-frame centres of the occupied voxels."""
        return indices_to_points(np.argwhere(self.occupancy), self.grid_to_camera)

    def pack(self) -> bytes:
        """Occupancy as packed bits (C order, 8000 bytes)."""
        return np.packbits(self.occupancy.reshape(-1)).tobytes()

    @staticmethod
    def unpack(data: bytes) -> np.ndarray:
        """Inverse of :meth:`pack`: (40, 40, 40) bool."""
        n = GRID_SIZE**3
        if len(data) != n // 8:
            raise ValueError(f"packed grid must be {n // 8} bytes, got {len(data)}")
        return (
            np.unpackbits(np.frombuffer(data, dtype=np.uint8))[:n].astype(bool).reshape(GRID_SHAPE)
        )
