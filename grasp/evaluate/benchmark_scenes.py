"""The grasp-success benchmark: objects resting on a table, grasped from what the views show.

Each object (held-out: the named pybullet_data objects, one in ten, and test-split objects) rests
on a table (the world plane z = 0) in one of its stable poses (:func:`completion.scenes.
stable_pose`). A depth camera 0.45–0.8 m away, at 45–90° of elevation, takes 4 views spread
around the object, :data:`AZIMUTH_STEP_DEG` of azimuth apart (a robot moving its camera around
what it will grasp: views 0, 3, 6 and 9 of a training pan); every view goes through the sensor
model and, as the service receives it with its camera pose, into a
:class:`completion.stream.CompletionStream` with the table as its support plane (the completion
is cut at it). Rows, each the top-1 grasp planned with the table as an obstacle and executed by
the lift test on the *true* object standing on the table (guarded approach, close, lift 10 cm,
shake; :func:`grasp.physics.lift.lift_test`):

- ``true_mesh``: planned on the true mesh itself (what a perfect completion would get);
- ``mvp_1view`` / ``mvp_4views``: MVP's completion of the first view / of the 4 views, the camera
  poses used as the service uses them (the posed model, :data:`completion.config.POSED_MODEL`,
  and the registered evidence);
- ``mvp_4views_memory``: MVP's completion of the 4 views, the poses not used (``registered=false``:
  its memory alone, what a session without camera poses gets);
- ``single_view_1view``: Single-View's completion of the first view;
- ``registered_fusion_4views``: the 4 views' observed points merged with the known camera poses,
  voxelized in the last view's grid (no learning).

results.json's ``grasp_benchmark[row] = {"held", "tested", "ci95": [lo, hi], "reasons"}``: held out
of tested with the Wilson score interval, and how often each failure reason occurred; and
``grasp_benchmark_objects``, one record per object (:func:`object_record`): its id, size and mass,
and per row whether it held, why, the grasp's kind, the planned and the executed finger joints.
The planner plans the execution (guarded, :func:`grasp.physics.lift.lift_test`), so on the true mesh
the two agree but for the dynamics; where they differ by much, the plan was not what happened.
"""

from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass

import numpy as np
import trimesh

from completion import grid as G
from completion.objects import load_object, object_ids
from completion.scenes import TABLE_PLANE

#: The source of a row that streams MVP without using the camera poses (``registered=false``).
MEMORY = "mvp_memory"
BENCHMARK_ROWS: tuple[str, ...] = (
    "true_mesh",
    "mvp_1view",
    "mvp_4views",
    "mvp_4views_memory",
    "single_view_1view",
    "registered_fusion_4views",
    "true_mesh_verified",
    "mvp_1view_verified",
    "mvp_4views_verified",
)
#: row -> (what completes the views: a model name, "fusion" or None for the truth, views used)
ROW_SOURCES = {
    "true_mesh": (None, 0),
    "mvp_1view": ("mvp", 1),
    "mvp_4views": ("mvp", 4),
    "mvp_4views_memory": (MEMORY, 4),
    "single_view_1view": ("single_view", 1),
    "registered_fusion_4views": ("fusion", 4),
    "true_mesh_verified": (None, 0),
    "mvp_1view_verified": ("mvp", 1),
    "mvp_4views_verified": ("mvp", 4),
}
#: The rows whose grasps are tried in physics on the mesh they were planned on before the top
#: one is chosen (``plan(..., verify=N)``, :mod:`grasp.physics.verify`).
VERIFIED_ROWS = tuple(row for row in BENCHMARK_ROWS if row.endswith("_verified"))
VIEWS = 4
#: Azimuth between the benchmark's views (the training pans turn 30° a view; 4 views 90° apart
#: see the object from every side, as a robot circling it would).
AZIMUTH_STEP_DEG = 90.0


def benchmark_objects(count: int, seed: int) -> list[str]:
    """``count`` distinct held-out objects: every tenth a named pybullet_data object (while they
    last), the rest the test split's objects in an order drawn from ``seed``."""
    named = object_ids("test", sources=("named",))
    pool = object_ids("test")
    order = np.random.default_rng([seed, zlib.crc32(b"benchmark")]).permutation(len(pool))
    others = iter(pool[i] for i in order)
    return [named[k // 10] if k % 10 == 0 and k // 10 < len(named) else next(others)
            for k in range(count)]


@dataclass
class Scene:
    """One benchmark object on its table and what the camera saw of it."""

    object_id: str
    mesh: trimesh.Trimesh  # the true object, world frame, resting on z = 0
    depth: np.ndarray  # (VIEWS, H, W) float32 metres, with the sensor model
    mask: np.ndarray  # (VIEWS, H, W) bool, the object's pixels (the table excluded)
    cameras: np.ndarray  # (VIEWS, 4, 4) camera→world
    intrinsics: G.Intrinsics


def resting_object(object_id: str, index: int, seed: int):
    """The benchmark's object ``index`` resting on the table z = 0 (a stable pose drawn from the
    seed), and the generator the rest of its scene draws from."""
    from completion.scenes import stable_pose

    rng = np.random.default_rng([seed, zlib.crc32(b"benchmark/scene"), index])
    mesh = load_object(object_id)
    pose, _ = stable_pose(mesh, object_id, rng)
    return mesh.copy().apply_transform(pose), rng


def make_scene(object_id: str, index: int, seed: int, renderer) -> Scene:
    """Place ``object_id`` on the table and render the pan; deterministic in its arguments."""
    world, rng = resting_object(object_id, index, seed)
    lo, hi = world.bounds
    distance, elevation = rng.uniform(0.45, 0.8), np.radians(rng.uniform(45.0, 90.0))
    azimuth = rng.uniform(0, 2 * np.pi) + np.radians(AZIMUTH_STEP_DEG) * np.arange(VIEWS)
    noise = np.random.default_rng([seed, zlib.crc32(b"benchmark/noise"), index])
    depths, labels, cameras = render_pan(renderer, [world], (lo + hi) / 2, distance, elevation,
                                         azimuth, noise)
    return Scene(object_id, world, depths, labels == 0, cameras, renderer.intrinsics)


def render_pan(renderer, meshes, aim, distance: float, elevation: float, azimuth, noise):
    """``meshes`` on the table seen from cameras ``distance`` from ``aim`` at ``elevation``
    (radians), one per ``azimuth``: (views, H, W) depths through the sensor model (``noise``
    its generator), index images (mesh i is i, the table ``len(meshes)``, nothing −1) and
    camera→world poses."""
    from completion.depth_camera import SensorModel, look_at
    from completion.scenes import table_mesh

    renderer.clear()
    for mesh in (*meshes, table_mesh()):
        renderer.add_mesh(mesh)
    sensor = SensorModel()
    depths, labels, cameras = [], [], []
    for a in azimuth:
        eye = aim + distance * np.array([np.cos(a) * np.cos(elevation),
                                         np.sin(a) * np.cos(elevation), np.sin(elevation)])
        camera = look_at(eye, aim)
        depth, index_image = renderer.render(camera)
        depths.append(sensor.apply(depth, noise))
        labels.append(index_image)
        cameras.append(camera)
    renderer.clear()
    return np.stack(depths), np.stack(labels), np.stack(cameras)


def completion_mesh(scene: Scene, source: str, views: int, models: dict):
    """The mesh a row plans on (camera frame of its last view) and that camera's pose; the mesh
    is None when the completion is empty. ``models``: name -> :class:`~grasp.evaluate.rows.
    ModelRow` (MVP's grid, cut at the table, is the fusion's too); MVP streams as the service
    does, with the posed model where ``models`` has it, unless ``source`` is :data:`MEMORY`."""
    from completion.config import POSED_MODEL
    from completion.mesh import EmptyMeshError, grid_to_mesh
    from completion.stream import CompletionStream
    from grasp.evaluate.rows import fuse

    row = models["mvp" if source in ("fusion", MEMORY) else source]
    posed = models.get(POSED_MODEL) if source == "mvp" else None
    stream = CompletionStream(row.model, threshold=None if source == "fusion" else row.decision,
                              registered=source != MEMORY,
                              posed_model=None if posed is None else posed.model)
    seen = []
    for t in range(views):
        stream.add_view(depth=scene.depth[t], intrinsics=scene.intrinsics, mask=scene.mask[t],
                        camera_to_world=scene.cameras[t], support_plane=TABLE_PLANE)
        if source == "fusion":  # its own points; the other rows need only the stream's grid
            points = G.depth_to_points(scene.depth[t], scene.intrinsics, scene.mask[t])
            seen.append(G.transform_points(points, scene.cameras[t]))
    camera = scene.cameras[views - 1]
    if not stream.seen:
        return None, camera
    c = stream.completion()  # cut at the table
    probabilities, threshold = c.probabilities, c.threshold
    if source == "fusion":  # every point seen so far, in the last view's grid, cut the same way
        occupied = fuse(seen, c.grid_to_camera, camera)
        occupied &= ~G.voxels_below_plane(c.grid_to_camera, TABLE_PLANE.transformed(camera))
        probabilities, threshold = occupied.astype(np.float32), 0.5
    try:
        return grid_to_mesh(probabilities, c.grid_to_camera, threshold=threshold), camera
    except EmptyMeshError:
        return None, camera


def grasp_kind(grasp, up: np.ndarray = TABLE_PLANE.normal) -> str:
    """"table pinch" (:mod:`grasp.hand.pinch`), or "power" (the palm touches) or "fingertip", "from
    above" (within 45° of straight down) or "from the side"."""
    from grasp.hand.pinch import TABLE_PINCH
    from grasp.ranking.rank import palm_touches

    if grasp.kind == TABLE_PINCH:
        return TABLE_PINCH
    above = float(-np.asarray(grasp.palm_pose)[:3, 2] @ up) >= np.cos(np.radians(45.0))
    return (f"{'power' if palm_touches(grasp) else 'fingertip'}, "
            f"{'from above' if above else 'from the side'}")


def run_object(scene: Scene, models: dict, rows, *, candidates: int, seed: int,
               verify: int = 4) -> dict[str, dict]:
    """row -> {"held", "reason", "kind", "planned_joints_deg", "executed_joints_deg",
    "hold_probability", "palm_pose"} for one object (the palm pose in the world frame; a table
    pinch adds "end_palm_pose", where closing ended); the
    verified rows add "verification" (what the top grasp's trials on the planned mesh saw) and
    "verified" (tried: how many grasps were lift-tested before the answer).

    The planner sees only the row's mesh (a completion, in its camera frame, for the completion
    rows: never the true object or its mass); the referee, :func:`grasp.physics.lift.lift_test` on
    the true object, runs after it with its own seed."""
    from grasp.physics.lift import lift_test
    from grasp.planner import plan

    out = {}
    for row in rows:
        source, views = ROW_SOURCES[row]
        if source is None:
            mesh, camera = scene.mesh, np.eye(4)
        else:
            mesh, camera = completion_mesh(scene, source, views, models)
        if mesh is None:
            out[row] = {"held": False, "reason": "empty completion"}
            continue
        tries, timings = (verify if row in VERIFIED_ROWS else 0), {}
        grasps = plan(mesh, n_candidates=candidates, seed=seed, top_k=1,
                      support_plane=TABLE_PLANE.transformed(camera), verify=tries, timings=timings)
        if not grasps or not grasps[0].success:
            why = grasps[0].reason if grasps else "no candidate"
            out[row] = {"held": False, "reason": f"no grasp planned: {why}"}
            continue
        world = dataclasses.replace(grasps[0], palm_pose=camera @ grasps[0].palm_pose)
        result = lift_test(scene.mesh, world, seed=seed, support_plane=TABLE_PLANE,
                           approach="guarded")
        p = world.hold_probability
        out[row] = {
            "held": bool(result.success), "reason": result.reason, "kind": grasp_kind(world),
            "planned_joints_deg": np.round(world.joints_deg, 2).tolist(),
            "executed_joints_deg": np.round(result.joints_deg, 2).tolist(),
            "hold_probability": None if np.isnan(p) else round(float(p), 4),
            "palm_pose": np.round(world.palm_pose, 6).tolist(),
        }
        if world.wrist_rise is not None:  # a table pinch: where its palm rose to while closing
            out[row]["end_palm_pose"] = np.round(world.end_palm_pose, 6).tolist()
        if tries:
            out[row] |= {"verification": dataclasses.asdict(world.verification),
                         "tried": timings["verified"]}
    return out


def object_record(object_id: str, mesh: trimesh.Trimesh, rows: dict[str, dict]) -> dict:
    """results.json's ``grasp_benchmark_objects`` entry: the object, its size (m, the extents
    of its box on the table), its mass (kg, at the lift test's density) and its rows."""
    from grasp.ranking.lift_model import estimated_mass

    return {"id": object_id, "size_m": np.round(mesh.extents, 4).tolist(),
            "mass_kg": round(estimated_mass(mesh), 4), "rows": rows}


def wilson(held: int, tested: int, z: float = 1.96) -> list[float]:
    """The Wilson score interval of a success rate (95 % for z = 1.96); [0, 1] for no trials."""
    if tested == 0:
        return [0.0, 1.0]
    p = held / tested
    centre = (p + z * z / (2 * tested)) / (1 + z * z / tested)
    half = z * np.sqrt(p * (1 - p) / tested + z * z / (4 * tested**2)) / (1 + z * z / tested)
    return [round(float(max(0.0, centre - half)), 4), round(float(min(1.0, centre + half)), 4)]


def summarise(records: list[dict[str, dict]], rows) -> dict:
    """results.json's ``grasp_benchmark`` from one record per object."""
    out = {}
    for row in rows:
        outcomes = [r[row] for r in records if row in r]
        held = sum(o["held"] for o in outcomes)
        reasons: dict[str, int] = {}
        for o in outcomes:
            if not o["held"]:
                key = _reason_kind(o["reason"])
                reasons[key] = reasons.get(key, 0) + 1
        out[row] = {"held": held, "tested": len(outcomes), "ci95": wilson(held, len(outcomes)),
                    "reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1]))}
    return out


def _reason_kind(reason: str) -> str:
    """A reason without its numbers and details, so that alike failures count together."""
    if reason.startswith("the object left the hand"):
        return reason.split(",")[0]
    if reason.startswith("no grasp planned"):
        return reason.split(" (")[0].split(";")[0]
    return reason
