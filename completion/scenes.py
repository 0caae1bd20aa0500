"""The paper's five experimental conditions as simulated 12-view sequences (docs/design.md §4).

``make_sequence(condition, split, index, seed)`` is deterministic in its arguments: it draws
the objects, their poses and the camera path from one generator seeded by
(seed, condition, split, index), renders each view, fits that view's grid to the observed points
(:func:`completion.grid.view_grid`: to this view's points, or, while the camera has not moved, to
every point seen from it) and voxelizes the observed points (input) and the complete objects
(target, solid) in it.

- camera_pan: one object at the origin in a random orientation; the camera circles it at a random
  radius (0.45–0.75 m) and elevation (15–60°), 30° of azimuth per view.
- two_object_pan: two objects side by side, scaled down if needed so that both fit in a 0.3 m
  cube (0.027 m³); same pan; the target holds both.
- object_hiding: camera_pan, then a 1-voxel-thick curtain at grid index i = p_t sweeps along the
  grid's x axis (p_t = round(t·40/11), t = 0…11); input voxels with i ≤ p_t are removed. The
  first view is complete (p_0 = 0 only covers the empty border column), the last one empty. The
  grid is fitted to the uncovered observation: the curtain is a synthetic occluder in voxel
  space, as in the paper.
- object_reveal: the reverse sweep (p_t = round((11 − t)·40/11)): hidden at first, then revealed.
- slide_behind: a fixed camera looks at a stationary object; a second, smaller object (0.5–0.9 of
  its diagonal), 2–10 cm further back (bounding spheres apart), starts beside it and slides
  behind it, arriving at view 3–6 (random) and staying there, partly or fully hidden for the rest
  of the sequence (the paper: "partially or fully occluded for several views"). The camera
  stands still, so every view's grid frames all the points seen so far and the hidden object
  stays in grid and target.
- tabletop (the product's own condition, not the paper's): one object resting on a table (the
  plane z = 0 of the world, ``meta["support_plane"]`` = n·x + d = 0 as [nx, ny, nz, d]) in one
  of its stable poses (:func:`stable_pose`), the camera 0.4–1.0 m from it at 20–90° of elevation
  (overhead included) and one of three motions (``meta["camera_motion"]``): ``still``, ``pan``
  (30° of azimuth a view, as camera_pan) or ``arc`` (a wrist camera closing in: 40–90° of azimuth
  over the sequence, the elevation moving by up to 20°, the distance shrinking by up to 30 %).
  The table is rendered (it occludes, and the sensor's edges form against it) but the mask
  excludes it, as a segmentation would: the input is the object's points, the target the object
  alone. The sensor model (:class:`completion.depth_camera.SensorModel`) is on by default.
"""

from __future__ import annotations

import functools
import warnings
import zlib
from dataclasses import dataclass, field

import numpy as np
import trimesh

from completion import grid
from completion.depth import DEPTH_FILTER, DepthFilter
from completion.depth_camera import Renderer, SensorModel, look_at
from completion.objects import SPLITS, load_object, object_ids
from grasp_client.wire import SupportPlane

CONDITIONS: tuple[str, ...] = (
    "camera_pan",
    "two_object_pan",
    "object_hiding",
    "object_reveal",
    "slide_behind",
    "tabletop",
)
#: The paper's five conditions (Tables I–III keep its protocol).
PAPER_CONDITIONS: tuple[str, ...] = CONDITIONS[:5]
#: Conditions with a single object (the ones the grasp joint error applies to).
SINGLE_OBJECT_CONDITIONS: tuple[str, ...] = (
    "camera_pan",
    "object_hiding",
    "object_reveal",
    "tabletop",
)
#: Conditions whose sensor model is on unless a caller says otherwise.
NOISY_BY_DEFAULT: tuple[str, ...] = ("tabletop",)
CAMERA_MOTIONS: tuple[str, ...] = ("still", "pan", "arc")
#: The table of the tabletop condition: its top is the world plane z = 0.
TABLE_PLANE = SupportPlane([0.0, 0.0, 1.0], 0.0)
TABLE_SIZE_M = (1.2, 1.2, 0.03)
DEFAULT_SENSOR = SensorModel()
VIEWS = 12
PAIR_CUBE_M = 0.3


@dataclass
class Sequence:
    """One simulated sequence; arrays are per view (L = number of views)."""

    inputs: np.ndarray  # (L, 40, 40, 40) bool, observed voxels
    targets: np.ndarray  # (L, 40, 40, 40) bool, complete object(s), solid
    grid_to_camera: np.ndarray  # (L, 4, 4) float64
    camera_to_world: np.ndarray  # (L, 4, 4) float64
    meta: dict = field(default_factory=dict)
    depth: np.ndarray | None = None  # (L, H, W) float32 metres, 0 = no return
    mask: np.ndarray | None = None  # (L, H, W) int16 object index, −1 = background

    def __len__(self) -> int:
        return len(self.inputs)


def _rng(condition: str, split: str, index: int, seed: int, *stream: int) -> np.random.Generator:
    """The sequence's generator; ``stream`` (e.g. 1 for the sensor) names an independent one."""
    key = zlib.crc32(f"{condition}/{split}".encode())
    return np.random.default_rng([seed, key, index, *stream])


def _load_or_redraw(
    object_id: str, ids: list[str], rng: np.random.Generator, *, tries: int = 20
) -> tuple[trimesh.Trimesh, str]:
    """Load ``object_id``; if its mesh is unusable, warn naming it and draw another from ``ids``
    with the sequence's generator (deterministic; sequences of good objects are unchanged)."""
    for _ in range(tries):
        try:
            return load_object(object_id), object_id
        except ValueError as exc:
            warnings.warn(f"skipping object {object_id}: {exc}", stacklevel=3)
            object_id = str(ids[int(rng.integers(len(ids)))])
    raise ValueError(f"no loadable object after {tries} draws from a pool of {len(ids)}")


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return trimesh.transformations.quaternion_matrix(q)


def _placed(mesh: trimesh.Trimesh, pose: np.ndarray) -> trimesh.Trimesh:
    out = mesh.copy()
    out.apply_transform(pose)
    return out


def _pan_cameras(rng: np.random.Generator, centre: np.ndarray, views: int) -> list[np.ndarray]:
    radius = rng.uniform(0.45, 0.75)
    elevation = np.radians(rng.uniform(15, 60))
    azimuth0 = rng.uniform(0, 2 * np.pi)
    poses = []
    for t in range(views):
        az = azimuth0 + t * np.radians(30.0)
        eye = centre + radius * np.array(
            [np.cos(az) * np.cos(elevation), np.sin(az) * np.cos(elevation), np.sin(elevation)]
        )
        poses.append(look_at(eye, centre))
    return poses


def _pair(rng: np.random.Generator, a: trimesh.Trimesh, b: trimesh.Trimesh):
    """Two objects side by side, both inside a 0.3 m cube centred at the origin.

    Returns the (possibly scaled-down) meshes, their rigid poses and the scale applied to both.
    """
    ra, rb = _random_rotation(rng), _random_rotation(rng)
    a_w, b_w = _placed(a, ra), _placed(b, rb)
    angle = rng.uniform(0, 2 * np.pi)
    u = np.array([np.cos(angle), np.sin(angle), 0.0])
    # Push b along u until the two bounding boxes no longer overlap along u, plus a small gap.
    ext_a = np.abs(a_w.vertices @ u).max()
    ext_b = np.abs(b_w.vertices @ u).max()
    gap = rng.uniform(0.0, 0.02)
    pa, pb = ra.copy(), rb.copy()
    pb[:3, 3] = u * (ext_a + ext_b + gap)
    both = np.concatenate([a_w.vertices, b_w.vertices + pb[:3, 3]])
    lo, hi = both.min(0), both.max(0)
    scale = min(1.0, PAIR_CUBE_M / float((hi - lo).max()))
    shift = -(lo + hi) / 2
    poses = []
    for p in (pa, pb):
        q = p.copy()
        q[:3, 3] = (p[:3, 3] + shift) * scale
        poses.append(q)
    return [a.copy().apply_scale(scale), b.copy().apply_scale(scale)], poses, scale


def _slide(rng: np.random.Generator, a: trimesh.Trimesh, b: trimesh.Trimesh, views: int):
    """The (possibly shrunk) sliding mesh b, the camera pose, per-view poses of a and b, and
    the scale applied to b."""
    ra, rb = _random_rotation(rng), _random_rotation(rng)
    size_a = float(np.linalg.norm(a.extents))
    size_b = float(np.linalg.norm(b.extents))
    shrink = min(1.0, size_a * rng.uniform(0.5, 0.9) / size_b)
    b = b.copy().apply_scale(shrink)
    radius_a, radius_b = size_a / 2, size_b * shrink / 2
    azimuth = rng.uniform(0, 2 * np.pi)
    elevation = np.radians(rng.uniform(5, 20))
    dist = rng.uniform(0.5, 0.7)
    eye = dist * np.array(
        [
            np.cos(azimuth) * np.cos(elevation),
            np.sin(azimuth) * np.cos(elevation),
            np.sin(elevation),
        ]
    )
    camera = look_at(eye, np.zeros(3))
    forward = -eye / dist  # along the viewing ray through the front object's centre
    side = camera[:3, 0]  # the image's x axis
    depth_gap = radius_a + radius_b + rng.uniform(0.02, 0.10)
    span = (radius_a + radius_b) * rng.uniform(1.3, 1.8)
    start = rng.choice([-1.0, 1.0]) * span
    offset = rng.uniform(-0.1, 0.1) * radius_a
    arrive = int(rng.integers(3, 7))  # the view from which it stays behind the front object
    poses = []
    for x in start * np.clip(1.0 - np.arange(views) / arrive, 0.0, None):
        pb = rb.copy()
        pb[:3, 3] = forward * depth_gap + side * (x + offset)
        poses.append([ra, pb])
    return b, camera, poses, shrink


@functools.lru_cache(maxsize=256)
def _stable_poses(object_id: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    mesh = load_object(object_id).apply_scale(scale)
    poses, probs = trimesh.poses.compute_stable_poses(mesh)
    if len(poses) == 0:  # a degenerate hull: rest on its lowest face as loaded
        return np.eye(4)[None], np.ones(1)
    return np.asarray(poses), np.asarray(probs) / np.sum(probs)


def stable_pose(
    mesh: trimesh.Trimesh, object_id: str, rng: np.random.Generator, scale: float = 1.0
) -> tuple[np.ndarray, float]:
    """A resting pose of ``mesh`` on the plane z = 0 and its probability: one of
    ``trimesh.poses.compute_stable_poses`` drawn by probability, turned by a random yaw about
    the table's normal and centred on the world's z axis, its lowest point on the plane."""
    poses, probs = _stable_poses(object_id, scale)
    k = int(rng.choice(len(poses), p=probs))
    yaw = trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi), [0, 0, 1])
    pose = yaw @ poses[k]
    v = grid.transform_points(mesh.vertices, pose)
    lo, hi = v.min(0), v.max(0)
    pose[:3, 3] -= [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]
    return pose, float(probs[k])


def table_mesh() -> trimesh.Trimesh:
    """The tabletop condition's table: a slab whose top face is the plane z = 0."""
    return trimesh.creation.box(TABLE_SIZE_M).apply_translation([0, 0, -TABLE_SIZE_M[2] / 2])


def _tabletop_cameras(
    rng: np.random.Generator, centre: np.ndarray, views: int
) -> tuple[list[np.ndarray], str]:
    """Camera poses of one tabletop sequence and the name of its motion."""
    motion = CAMERA_MOTIONS[int(rng.integers(len(CAMERA_MOTIONS)))]
    dist = rng.uniform(0.4, 1.0)
    elevation = rng.uniform(20.0, 90.0)
    azimuth0 = rng.uniform(0, 360.0)
    t = np.arange(views)
    if motion == "still":
        az, el, d = np.full(views, azimuth0), np.full(views, elevation), np.full(views, dist)
    elif motion == "pan":
        az, el, d = azimuth0 + 30.0 * t, np.full(views, elevation), np.full(views, dist)
    else:  # a wrist camera's short arc, closing in
        frac = t / (views - 1)
        az = azimuth0 + rng.choice([-1.0, 1.0]) * rng.uniform(40.0, 90.0) * frac
        el = np.clip(elevation + rng.uniform(-20.0, 20.0) * frac, 20.0, 90.0)
        d = np.maximum(dist * (1 - rng.uniform(0.0, 0.3) * frac), 0.4)
    target = centre + rng.uniform(-0.01, 0.01, size=3)
    cameras = []
    for a, e, r in zip(np.radians(az), np.radians(el), d, strict=True):
        eye = target + r * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
        cameras.append(look_at(eye, target))
    return cameras, motion


def curtain_position(t: int, views: int, *, reveal: bool) -> int:
    """Grid index of the curtain at view t; voxels with i ≤ position are covered."""
    step = t if not reveal else views - 1 - t
    return int(round(step * grid.GRID_SIZE / (views - 1)))


def make_sequence(
    condition: str,
    split: str,
    index: int,
    seed: int = 0,
    *,
    views: int = VIEWS,
    pool: list[str] | None = None,
    noise: bool | None = None,
    sensor: SensorModel = DEFAULT_SENSOR,
    keep_depth: bool = False,
    renderer: Renderer | None = None,
    cleaning: DepthFilter | None = DEPTH_FILTER,
) -> Sequence:
    """Render and voxelize one sequence of ``condition``; deterministic in its arguments.

    pool : object ids to draw from (default: every procedural and random_urdf object of
        ``split``). ``renderer`` may be passed to reuse one pybullet client across calls.
    noise : pass the depth through ``sensor`` (None: the condition's default, on for
        :data:`NOISY_BY_DEFAULT`). The sensor draws from its own generator, so a sequence with
        noise shows the same scene as the one without.
    cleaning : how a depth image becomes points and a grid (:mod:`completion.depth`, the
        service's and the training data's; None: every return, the plain box).
    """
    if condition not in CONDITIONS:
        raise ValueError(f"condition must be one of {CONDITIONS}, got {condition!r}")
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if views < 2:
        raise ValueError(f"a sequence needs at least 2 views, got {views}")
    rng = _rng(condition, split, index, seed)
    ids = pool if pool is not None else object_ids(split)
    if not ids:
        raise ValueError("the object pool is empty")
    n_objects = 2 if condition in ("two_object_pan", "slide_behind") else 1
    chosen = [str(ids[i]) for i in rng.choice(len(ids), size=n_objects, replace=len(ids) < 2)]
    meshes = []
    for k, object_id in enumerate(chosen):
        mesh, chosen[k] = _load_or_redraw(object_id, ids, rng)
        meshes.append(mesh)

    scales = [1.0] * n_objects  # what each loaded mesh was scaled by before it was posed
    scenery: list[trimesh.Trimesh] = []  # rendered, never in the input or the target
    extra: dict = {}
    if condition == "tabletop":
        pose, probability = stable_pose(meshes[0], chosen[0], rng)
        object_poses = [[pose]] * views
        centre = grid.transform_points(meshes[0].vertices, pose)
        cameras, motion = _tabletop_cameras(rng, (centre.min(0) + centre.max(0)) / 2, views)
        scenery = [table_mesh()]
        extra = {"support_plane": TABLE_PLANE.as_array().tolist(), "camera_motion": motion,
                 "stable_pose_probability": probability}
    elif condition == "two_object_pan":
        meshes, poses, scale = _pair(rng, *meshes)
        scales = [scale, scale]
        object_poses = [poses] * views
        cameras = _pan_cameras(rng, np.zeros(3), views)
    elif condition == "slide_behind":
        sliding, camera, object_poses, scales[1] = _slide(rng, *meshes, views)
        meshes = [meshes[0], sliding]
        cameras = [camera] * views
    else:
        object_poses = [[_random_rotation(rng)]] * views
        cameras = _pan_cameras(rng, np.zeros(3), views)

    own = renderer is None
    r = Renderer() if own else renderer
    try:
        r.clear()
        for mesh in [*meshes, *scenery]:
            r.add_mesh(mesh)
        if noise is None:
            noise = condition in NOISY_BY_DEFAULT
        noise_rng = _rng(condition, split, index, seed, 1) if noise else None
        seq = _observe(r, condition, meshes, object_poses, cameras,
                       sensor if noise else None, noise_rng, keep_depth, cleaning)
    finally:
        if own:
            r.close()
        else:
            r.clear()
    seq.meta.update(
        condition=condition,
        split=split,
        index=index,
        seed=seed,
        views=views,
        object_ids=chosen,
        intrinsics=r.intrinsics.as_dict(),
        object_to_world=[[p.tolist() for p in ps] for ps in object_poses],
        object_scale=[float(x) for x in scales],
        noise=bool(noise),
        elevation_deg=[round(float(np.degrees(np.arcsin(np.clip(-c[2, 2], -1, 1)))), 3)
                       for c in cameras],
        **extra,
    )
    return seq


def _observe(
    r: Renderer,
    condition: str,
    meshes: list[trimesh.Trimesh],
    object_poses: list[list[np.ndarray]],
    cameras: list[np.ndarray],
    sensor: SensorModel | None,
    noise_rng: np.random.Generator | None,
    keep_depth: bool,
    cleaning: DepthFilter | None,
) -> Sequence:
    views = len(cameras)
    inputs = np.zeros((views, *grid.GRID_SHAPE), dtype=bool)
    targets = np.zeros_like(inputs)
    transforms = np.zeros((views, 4, 4))
    depths, masks, visible, curtains = [], [], [], []
    previous = previous_camera = seen = None
    for t, (camera, poses) in enumerate(zip(cameras, object_poses, strict=True)):
        for i, pose in enumerate(poses):
            r.set_pose(i, pose)
        depth, mask = r.render(camera)
        mask[mask >= len(meshes)] = -1  # scenery (the table): seen, never segmented
        if sensor is not None:
            depth = sensor.apply(depth, noise_rng)
        points = grid.depth_to_points(depth, r.intrinsics, mask >= 0, cleaning=cleaning)
        labels = mask[(mask >= 0) & (depth > 0)]
        visible.append([int((labels == i).sum()) for i in range(len(meshes))])
        previous, seen = grid.view_grid(points, camera, previous, previous_camera, seen,
                                        cleaning=cleaning)
        if previous is None:  # nothing seen yet: frame the objects where they are
            previous = grid.fit_grid(_camera_vertices(meshes, poses, camera))
        previous_camera = camera
        transforms[t] = previous
        occ = grid.voxelize_points(points, previous)
        if condition in ("object_hiding", "object_reveal"):
            c = curtain_position(t, views, reveal=condition == "object_reveal")
            occ[: c + 1] = False
            curtains.append(c)
        inputs[t] = occ
        for mesh, pose in zip(meshes, poses, strict=True):
            v = grid.transform_points(mesh.vertices, np.linalg.inv(camera) @ pose)
            targets[t] |= grid.voxelize_mesh(v, mesh.faces, previous)
        if keep_depth:
            depths.append(depth)
            masks.append(mask)
    meta = {"visible_points": visible}
    if curtains:
        meta["curtain"] = curtains
    return Sequence(
        inputs=inputs,
        targets=targets,
        grid_to_camera=transforms,
        camera_to_world=np.stack(cameras),
        meta=meta,
        depth=np.stack(depths) if keep_depth else None,
        mask=np.stack(masks) if keep_depth else None,
    )


def object_meshes_in_camera(seq: Sequence, view: int) -> list:
    """The true object meshes posed in view ``view``'s camera frame, each scaled as the scene
    scaled it (two-object pan fits a pair into a 0.3 m cube, slide behind shrinks the sliding
    object; ``meta["object_scale"]``, 1 where absent)."""
    to_camera = np.linalg.inv(seq.camera_to_world[view])
    ids = seq.meta["object_ids"]
    scales = seq.meta.get("object_scale", [1.0] * len(ids))
    meshes = []
    for object_id, pose, scale in zip(ids, seq.meta["object_to_world"][view], scales, strict=True):
        mesh = load_object(object_id)
        mesh.apply_scale(scale)
        mesh.apply_transform(to_camera @ np.asarray(pose))
        meshes.append(mesh)
    return meshes


def _camera_vertices(meshes, poses, camera) -> np.ndarray:
    inv = np.linalg.inv(camera)
    return np.concatenate(
        [grid.transform_points(m.vertices, inv @ p) for m, p in zip(meshes, poses, strict=True)]
    )
