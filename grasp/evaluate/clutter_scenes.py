"""The clutter table: one object among others on a table, the neighbours seen as obstacles.

Each scene (:func:`clutter_scene`) puts a held-out target (:func:`~grasp.evaluate.benchmark_scenes.
benchmark_objects`' order) on the table in a stable pose and 2–5 neighbours around it (other
test-split objects at most :data:`MAX_NEIGHBOUR_M` across, in stable poses in which they stand
still in the simulation when nudged, :func:`stands_still`), each at a gap of
2–10 cm from the target and not touching the others: gaps that matter to a BarrettHand, whose
open fingers reach 16 cm from the palm's axis. A depth camera pans 4 views around the target
as in the benchmark; every view keeps the target's mask and the pixels of the neighbours
(what a label image gives a robot).

Rows, each the top-1 grasp of the target planned with the table, executed by the lift test on
the true target with the true neighbours as dynamic bodies on the table
(:func:`grasp.physics.lift.lift_test`); success is the target held **and** no neighbour moved more
than :data:`MOVE_LIMIT_M` or tilted more than :data:`TILT_LIMIT_DEG`:

- ``true_meshes``: planned on the true target, the true neighbours as obstacles;
- ``mvp_4views_obstacles``: MVP's completion of the target's 4 views, the other pixels of those
  views as obstacles (:func:`seen_obstacles`: off the table, near the target), as the service
  does with a view's pixels outside the target's mask;
- ``mvp_4views_ignoring``: the same completion, the neighbours ignored (the planner before).
"""

from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass

import numpy as np
import trimesh

from completion import grid as G
from completion.objects import load_object
from completion.scenes import TABLE_PLANE
from grasp.evaluate.benchmark_scenes import VIEWS, benchmark_objects, grasp_kind, render_pan
from grasp.search.obstacles import Obstacles, seen_others

CLUTTER_ROWS: tuple[str, ...] = ("true_meshes", "mvp_4views_obstacles", "mvp_4views_ignoring")
#: Neighbours per scene (inclusive), and the gap (m) between each one's footprint and the
#: target's.
NEIGHBOURS = (2, 5)
GAP_M = (0.02, 0.10)
#: Neighbours wider or taller than this (m) are not drawn.
MAX_NEIGHBOUR_M = 0.15
#: A neighbour that moved more (m) or tilted more (degrees) was disturbed: the grasp failed.
MOVE_LIMIT_M = 0.02
TILT_LIMIT_DEG = 20.0
#: Points sampled on each footprint to measure gaps (seeded).
FOOTPRINT_POINTS = 400
#: A neighbour must stand still on the table: nudged along the table at this speed (m/s, in two
#: directions), it comes to rest within this distance (m) in this time (s). A capsule lying on
#: its side is "stable" but rolls on at the least touch (one rolled 18 cm beside a target the
#: hand never reached), which would count against whatever grasp is tried beside it.
NUDGE_M_S = 0.05
SETTLE_M = 0.01
SETTLE_S = 1.0


@dataclass
class ClutterScene:
    """A target among neighbours on the table, and what the camera saw."""

    target_id: str
    target: trimesh.Trimesh  # world frame, resting on z = 0
    neighbour_ids: list[str]
    neighbours: list[trimesh.Trimesh]
    gaps_m: list[float]  # each neighbour's footprint gap to the target's
    depth: np.ndarray  # (VIEWS, H, W) float32 metres, with the sensor model
    mask: np.ndarray  # (VIEWS, H, W) bool: the target's pixels
    others: np.ndarray  # (VIEWS, H, W) bool: the neighbours' pixels (what a label image tells)
    cameras: np.ndarray  # (VIEWS, 4, 4) camera→world
    intrinsics: G.Intrinsics

    #: The values of :meth:`labels`: what a robot's segmentation gives.
    TARGET, NEIGHBOUR = 1, 2

    def labels(self, view: int) -> np.ndarray:
        """View ``view``'s label image (H, W) uint8: :attr:`TARGET` the target's pixels,
        :attr:`NEIGHBOUR` the neighbours', 0 the table and the rest; send it as ``mask`` with
        ``object_label=TARGET`` and the service keeps the neighbours as obstacles."""
        return np.where(self.mask[view], self.TARGET,
                        np.where(self.others[view], self.NEIGHBOUR, 0)).astype(np.uint8)


def _resting(object_id: str, rng: np.random.Generator) -> trimesh.Trimesh:
    from completion.scenes import stable_pose

    mesh = load_object(object_id)
    pose, _ = stable_pose(mesh, object_id, rng)
    return mesh.copy().apply_transform(pose)


def _footprint(mesh: trimesh.Trimesh, seed: int) -> np.ndarray:
    """(n, 2) points of the mesh's outline seen from above: samples of its surface, xy."""
    points, _ = trimesh.sample.sample_surface(mesh, FOOTPRINT_POINTS, seed=seed)
    return np.concatenate([points, mesh.vertices])[:, :2]


def stands_still(mesh: trimesh.Trimesh) -> bool:
    """Whether ``mesh`` (world frame, resting on z = 0) on the lift test's table, nudged along
    it at :data:`NUDGE_M_S` (along x, then y), comes to rest within :data:`SETTLE_M` in
    :data:`SETTLE_S`."""
    from completion.bullet import quiet_fds
    from grasp.physics.world import DynamicWorld

    for direction in ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]):
        with quiet_fds(1), DynamicWorld(mesh, table_top=0.0) as world:
            away = np.eye(4)
            away[:3, 3] = mesh.bounds.mean(axis=0) + [0.0, 0.0, 1.0]  # the hand out of the way
            world.place_hand(away, [0.0] * 8)
            world.gravity(True)
            c, body = world.client, world.object_id
            start = np.array(c.getBasePositionAndOrientation(body)[0])
            c.resetBaseVelocity(body, linearVelocity=(NUDGE_M_S * np.array(direction)).tolist())
            for _ in range(round(SETTLE_S / world.settings.time_step)):
                world.step()
            end = np.array(c.getBasePositionAndOrientation(body)[0])
        if float(np.linalg.norm(end - start)) >= SETTLE_M:
            return False
    return True


def _gap(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    return float(cKDTree(a).query(b)[0].min())


def place_neighbours(target: trimesh.Trimesh, candidates, rng: np.random.Generator):
    """Neighbours around ``target`` (world meshes resting on z = 0), each at a footprint gap
    drawn from :data:`GAP_M` in a direction drawn at random, none closer than the smallest gap
    to another: (ids, meshes, gaps). ``candidates``: (id, mesh) pairs, tried in order."""
    count = int(rng.integers(NEIGHBOURS[0], NEIGHBOURS[1] + 1))
    centre = target.bounds.mean(axis=0)[:2]
    placed: list[tuple[str, trimesh.Trimesh, float, np.ndarray]] = []
    mine = _footprint(target, 0)
    for object_id, mesh in candidates:
        if len(placed) == count:
            break
        gap = float(rng.uniform(*GAP_M))
        mesh = mesh.copy()
        mesh.apply_translation(np.append(-mesh.bounds.mean(axis=0)[:2], 0.0))
        theirs = _footprint(mesh, 1)
        for _ in range(8):  # directions tried before the candidate is passed over
            direction = rng.normal(size=2)
            direction /= np.linalg.norm(direction)
            lo, hi = 0.0, 1.0  # the centre distance along it whose gap is the drawn one
            for _ in range(30):
                mid = 0.5 * (lo + hi)
                if _gap(mine, theirs + centre + mid * direction) < gap:
                    lo = mid
                else:
                    hi = mid
            shift = centre + hi * direction
            others = [_gap(p[3], theirs + shift) for p in placed]
            if all(g >= GAP_M[0] for g in others):
                moved = mesh.copy()
                moved.apply_translation([*shift, 0.0])
                placed.append((object_id, moved, gap, theirs + shift))
                break
    return [p[0] for p in placed], [p[1] for p in placed], [p[2] for p in placed]


def scene_objects(index: int, seed: int, pool_size: int = 200):
    """The target (the benchmark's object ``index``) and its neighbours, resting on the table:
    (target id, target, neighbour ids, neighbours, gaps), deterministic in the arguments."""
    ids = benchmark_objects(max(pool_size, index + 1), seed)
    target_id = ids[index]
    rng = np.random.default_rng([seed, zlib.crc32(b"clutter/scene"), index])
    target = _resting(target_id, rng)
    order = rng.permutation(len(ids))

    def candidates():
        for i in order:
            if ids[i] == target_id:
                continue
            mesh = _resting(ids[i], rng)
            if max(mesh.extents) <= MAX_NEIGHBOUR_M and stands_still(mesh):
                yield ids[i], mesh

    names, meshes, gaps = place_neighbours(target, candidates(), rng)
    return target_id, target, names, meshes, gaps, rng


def clutter_scene(index: int, seed: int, renderer) -> ClutterScene:
    """Scene ``index``: the objects placed and the pan rendered (target first, so its index
    image value is 0; the neighbours 1…k; the table last)."""
    target_id, target, names, meshes, gaps, rng = scene_objects(index, seed)
    lo, hi = target.bounds
    distance, elevation = rng.uniform(0.5, 0.8), np.radians(rng.uniform(45.0, 90.0))
    azimuth = rng.uniform(0, 2 * np.pi) + np.radians(30.0) * np.arange(VIEWS)
    noise = np.random.default_rng([seed, zlib.crc32(b"clutter/noise"), index])
    depths, labels, cameras = render_pan(renderer, [target, *meshes], (lo + hi) / 2, distance,
                                         elevation, azimuth, noise)
    return ClutterScene(target_id, target, names, meshes, gaps, depths, labels == 0,
                        (labels >= 1) & (labels <= len(meshes)), cameras, renderer.intrinsics)


def make_clutter_scene(index: int, seed: int = 0) -> ClutterScene:
    """The clutter table's scene ``index``, rendered: a held-out object on a table (z = 0) among
    2–5 neighbours at 2–10 cm, a depth camera's 4 views around it with their label images
    (:meth:`ClutterScene.labels`), camera poses and intrinsics. Same index and seed, same scene."""
    from completion.depth_camera import Renderer

    renderer = Renderer()
    try:
        return clutter_scene(index, seed, renderer)
    finally:
        renderer.close()


def seen_obstacles(scene: ClutterScene, views: int = VIEWS) -> Obstacles:
    """Every pixel of the first ``views`` views outside the target's mask with a depth,
    back-projected to the world and kept as the service keeps a view's other pixels
    (:func:`grasp.search.obstacles.seen_others`: off the table, near the target, not its rim)."""
    kept = []
    for t in range(views):
        outside = ~scene.mask[t]
        others = G.transform_points(G.depth_to_points(scene.depth[t], scene.intrinsics, outside),
                                    scene.cameras[t])
        target = G.transform_points(G.depth_to_points(scene.depth[t], scene.intrinsics,
                                                      scene.mask[t]), scene.cameras[t])
        kept.append(seen_others(others, target, TABLE_PLANE))
    return Obstacles.from_points(np.concatenate(kept) if kept else np.zeros((0, 3)))


def disturbed(result) -> str | None:
    """Why a lift test with neighbours failed for them (None: they stood)."""
    if result.neighbour_moved > MOVE_LIMIT_M:
        return f"a neighbour moved {100 * result.neighbour_moved:.0f} cm"
    if result.neighbour_tilt_deg > TILT_LIMIT_DEG:
        return f"a neighbour tilted {result.neighbour_tilt_deg:.0f}°"
    return None


def run_scene(scene: ClutterScene, models: dict, rows, *, candidates: int, seed: int):
    """row -> {"success", "held", "reason", "kind", "neighbour_moved_m", "neighbour_tilt_deg",
    "preshape_deg", "planned_joints_deg", "palm_pose" (world, where the fingers closed)} for one
    scene. The completion rows plan on MVP's completion in its last
    camera's frame, with the obstacles moved there; the referee runs on the true objects."""
    from grasp.evaluate.benchmark_scenes import completion_mesh
    from grasp.physics.lift import lift_test
    from grasp.planner import plan

    target_scene = _as_benchmark_scene(scene)
    out, completed = {}, None
    for row in rows:
        if row == "true_meshes":
            mesh, camera = scene.target, np.eye(4)
            obstacles = Obstacles.from_meshes(scene.neighbours)
        else:  # both MVP rows plan on the one completion
            completed = completed or completion_mesh(target_scene, "mvp", VIEWS, models)
            mesh, camera = completed
            obstacles = (seen_obstacles(scene).transformed(np.linalg.inv(camera))
                         if row == "mvp_4views_obstacles" else None)
        if mesh is None:
            out[row] = {"success": False, "held": False, "reason": "empty completion"}
            continue
        grasps = plan(mesh, n_candidates=candidates, seed=seed, top_k=1,
                      support_plane=TABLE_PLANE.transformed(camera), obstacles=obstacles)
        if not grasps or not grasps[0].success:
            why = grasps[0].reason if grasps else "no candidate"
            out[row] = {"success": False, "held": False, "reason": f"no grasp planned: {why}"}
            continue
        world = dataclasses.replace(grasps[0], palm_pose=camera @ grasps[0].palm_pose)
        result = lift_test(scene.target, world, seed=seed, support_plane=TABLE_PLANE,
                           approach="guarded", neighbours=scene.neighbours)
        knocked = disturbed(result)
        out[row] = {
            "success": bool(result.success) and knocked is None, "held": bool(result.success),
            "reason": result.reason if not result.success or knocked is None
            else f"held, but {knocked}", "kind": grasp_kind(world),
            "neighbour_moved_m": round(result.neighbour_moved, 4),
            "neighbour_tilt_deg": round(result.neighbour_tilt_deg, 2),
            "preshape_deg": world.preshape_deg,
            "planned_joints_deg": np.round(world.joints_deg, 2).tolist(),
            "palm_pose": np.round(world.end_palm_pose, 6).tolist(),  # where the fingers closed
        }
    return out


def _as_benchmark_scene(scene: ClutterScene):
    from grasp.evaluate.benchmark_scenes import Scene

    return Scene(scene.target_id, scene.target, scene.depth, scene.mask, scene.cameras,
                 scene.intrinsics)
