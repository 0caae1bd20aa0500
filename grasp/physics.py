"""Physics check of a grasp: close the BarrettHand on the true object in pybullet, lift, shake.

:func:`lift_test` replays a planned :class:`grasp.autograsp.GraspResult` in rigid-body dynamics and
says whether the object stays in the hand. One trial, in its own DIRECT pybullet client
(:class:`DynamicWorld`; no module-global client):

1. **Object**: the mesh as a dynamic body. Mass and inertia at ``density`` (default
   :data:`DENSITY_KG_M3` = 500 kg/m³, solid), from the mesh when it is a closed volume, otherwise
   from its convex pieces. Collision: the convex hull when the mesh is convex, else pybullet's
   V-HACD decomposition (:func:`convex_decomposition`), cached per mesh in
   ``~/.cache/mvp-grasp/convex``. pybullet pads a hull by its 1 mm margin, so the pieces are
   shrunk by as much and the collision surface is the mesh's (a test checks it against the
   planner's contact). Without a table (the scenes float the object) a weak support, a constraint
   of at most the object's weight, keeps it from drifting while gravity is off and the hand closes;
   with ``table=True`` it stands on a table with gravity on throughout.
2. **Hand**: the URDF from :mod:`hands.barrett.urdf` (implicit cylinders, so the palm is not padded
   either), free base, carried by a fixed constraint to the world whose target is moved every step
   (``changeConstraint``, at most ``hand_force``): the hand base is driven dynamically, so contacts
   see its real velocity. The carriage only translates; the palm keeps the grasp's orientation.
   Finger–finger and finger–palm collisions are off, as in autograsp.
   It starts open, at the grasp's spread, ``pregrasp_backoff`` behind the palm pose along the
   approach axis (:func:`grasp.autograsp.pregrasp_pose`) and moves to the planned pose, or, with
   ``approach="contact"``, until it first touches the object.
3. **Close**: every finger DOF rises at ``close_speed``; J2 = DOF and J3 = DOF/3 under position
   control with torque limits. The controller (:meth:`DynamicWorld.drive_fingers`) watches each
   proximal joint's lag and velocity: stalled while its distal still moves is a proximal contact,
   so the finger breaks away (J2 keeps pressing with its torque limit, the distal target keeps
   following DOF/3 until it stalls or the DOF tops out); stalled together with the distal stops
   the finger (both joints press with their limits). Closing ends when every finger has stopped,
   plus ``close_settle``.
4. **Load**: where the object sits in the palm frame is the reference. The support goes, gravity
   comes on; settle, lift the hand by ``lift`` along world +z (cosine profile), hold, then
   ``shake_count`` shakes along seeded random directions (out and back, one cycle each), hold.

Success: the object's centre of mass never moves more than ``hold_tolerance`` (2 cm) from the
reference, in the palm frame, from gravity-on to the end. The simulation stops early once the
object is ``drop_distance`` (5 cm) away.

Numbers (:class:`LiftSettings`, in one place; the hand's facts are in ``shared/BARRETT.md``):

- Time step 1/240 s, 100 solver iterations, deterministic overlapping pairs, friction anchors (they
  stop the slow creep of a held object that pybullet shows without them). The same inputs and
  seed give bit-identical results on one machine.
- Torque limits: J3 1.0 N·m, from the BH8-series manual's "2 kg at the fingertip is about 20 N at
  5 cm = 1 N·m" (the range of its distal torque sensor); the hand motor's 0.0367 N·m continuous
  torque through the 93.75:1 distal drive and a worm of about 30 % efficiency gives the same. J2
  4/3 N·m: the same motor through 125:1 instead of 93.75:1. Spread 2.0 N·m (chosen; the
  worm-driven spread does not back-drive). Finger DOF speed 1 rad/s (the real hand closes its 140°
  in about 1 s; slower keeps the first touch from batting the object away). After a finger stops,
  its joints keep pressing with their limits (standing in for the non-back-drivable worm drives
  holding the squeeze).
- Friction: hand links get ``friction`` (default μ = 1.0, rubber, :data:`grasp.quality.MU_RUBBER`)
  and the object 1.0; pybullet multiplies the two, so a hand–object contact has exactly μ. No
  rolling or spinning friction.
- Shake: 4 cycles of 3 cm at 3 Hz, peak acceleration 2π²f²A ≈ 5.3 m/s² (about 0.5 g).
- Sim time: 0.5 s approach, up to 3.5 s closing, 3.1 s loaded (settle 0.25, lift 1.0, hold 0.25,
  shakes 1.33, hold 0.25); about 1–2 s of wall time on one core.

This module must not import torch (DESIGN.md §2).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import tempfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal, get_args

import numpy as np
import pybullet
import trimesh
from pybullet_utils import bullet_client
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError
from scipy.spatial.transform import Rotation

from grasp.autograsp import GraspResult, pregrasp_pose
from grasp.quality import MU_RUBBER
from grasp.sim import JointInfo, check_mesh, check_pose
from hands.barrett import BH8_282, FINGERS, JOINT_NAMES, BarrettParams

__all__ = [
    "APPROACHES",
    "DENSITY_KG_M3",
    "HOLD_TOLERANCE_M",
    "DynamicWorld",
    "LiftResult",
    "LiftSettings",
    "convex_decomposition",
    "lift_test",
    "mass_properties",
    "read_pieces",
]

log = logging.getLogger(__name__)

#: Density of the object (kg/m³): 500, a solid between plastic ware and wood. Objects are solid, so
#: big ones are heavy (an 18 cm ball weighs 1.5 kg); pass ``density`` for lighter ones.
DENSITY_KG_M3 = 500.0
#: The object is held if its centre of mass stays this close to where it sat in the hand.
HOLD_TOLERANCE_M = 0.02
#: V-HACD settings (pybullet's defaults, written down because they are part of the cache key).
VHACD_OPTIONS = {
    "resolution": 100_000,
    "concavity": 0.0025,
    "maxNumVerticesPerCH": 64,
    "minVolumePerCH": 0.0001,
}
_CACHE_VERSION = "1"
#: How the hand reaches the grasp pose (see :func:`lift_test`).
Approach = Literal["planned", "contact"]
APPROACHES: tuple[str, ...] = get_args(Approach)
#: Standard gravity (m/s²), along world −z.
GRAVITY = 9.81
#: pybullet pads each convex hull of a mesh shape by this collision margin (its default, measured:
#: a hull's surface lies 1 mm outside its vertices); the pieces are shrunk by as much.
MESH_MARGIN_M = 0.001


@dataclass(frozen=True)
class LiftSettings:
    """Every number of a lift test (SI units: s, m, rad, N, N·m). See the module docstring."""

    time_step: float = 1.0 / 240.0
    solver_iterations: int = 100
    # hand carriage
    hand_force: float = 1000.0  # max force of the constraint carrying the hand (N)
    pregrasp_backoff: float = 0.05  # start this far behind the grasp pose, hand open (m)
    approach_speed: float = 0.10  # m/s
    overtravel: float = 0.05  # a guarded approach goes on this far past the planned pose (m)
    # fingers
    close_speed: float = 1.0  # finger DOF speed while closing (rad/s)
    proximal_torque: float = 4.0 / 3.0  # J2 torque limit (N·m): the J3 limit × 125 / 93.75
    distal_torque: float = 1.0  # J3 torque limit (N·m): 20 N at a 5 cm fingertip lever
    spread_torque: float = 2.0  # spread torque limit (N·m)
    position_gain: float = 0.3  # pybullet POSITION_CONTROL gains
    velocity_gain: float = 1.0
    stall_lag: float = math.radians(2.0)  # a joint this far behind its target …
    stall_speed: float = 0.1  # … and slower than this (rad/s) …
    stall_steps: int = 4  # … for this many steps in a row has stalled
    close_timeout: float = 3.5  # s; the full DOF range takes 2.4 s at 1 rad/s
    close_settle: float = 0.1  # keep squeezing this long after every finger stopped (s)
    # load
    settle_time: float = 0.25  # gravity on, hand still (s)
    lift_speed: float = 0.10  # mean lift speed (m/s); smooth (cosine) profile
    hold_time: float = 0.25  # still, after the lift and after the shakes (s)
    shake_count: int = 4
    shake_amplitude: float = 0.03  # m
    shake_frequency: float = 3.0  # Hz
    # outcome
    hold_tolerance: float = HOLD_TOLERANCE_M
    drop_distance: float = 0.05  # stop simulating once the object is this far off (m)
    table_friction: float = 0.5
    support_factor: float = 1.0  # without a table, a support of this × the weight holds the object

    def __post_init__(self) -> None:
        positive = ("time_step", "hand_force", "approach_speed", "close_speed", "lift_speed")
        positive += ("proximal_torque", "distal_torque", "spread_torque", "hold_tolerance")
        bad = [name for name in positive if not getattr(self, name) > 0.0]
        if bad:
            raise ValueError(f"LiftSettings: these must be positive, got {bad}")
        if self.drop_distance < self.hold_tolerance:
            raise ValueError("LiftSettings: drop_distance must be >= hold_tolerance")
        if self.solver_iterations < 1 or self.stall_steps < 1 or self.shake_count < 0:
            raise ValueError("LiftSettings: solver_iterations, stall_steps >= 1, shake_count >= 0")

    @property
    def shake_peak_accel(self) -> float:
        """Peak acceleration of a shake (m/s²): 2π²f²A for the out-and-back cosine cycle."""
        return 2.0 * math.pi**2 * self.shake_frequency**2 * self.shake_amplitude


DEFAULT_SETTINGS = LiftSettings()


@dataclass(frozen=True)
class LiftResult:
    """Outcome of one :func:`lift_test`.

    Attributes
    ----------
    success : bool
        The object's centre of mass stayed within ``hold_tolerance`` (2 cm) of where it sat in the
        hand, in the palm frame, from gravity-on through lift and shake.
    reason : str
        What happened, in words (where it was dropped, or "held").
    displacement : float
        Distance (m) of the centre of mass from where it sat in the hand, at the end of the test
        (or when the simulation stopped because the object fell ``drop_distance`` away).
    slip : float
        Largest such distance (m) seen during the test; success means ``slip <= hold_tolerance``.
    offset : (3,) float
        The final displacement as a vector in the palm frame (m).
    rotation_deg : float
        Rotation of the object relative to the palm at the end, degrees.
    held_s : float
        Simulated time (s) from gravity-on until the object first moved more than
        ``hold_tolerance``; ``total_s`` when it was held.
    total_s : float
        Simulated duration (s) of the loaded part of the test (settle, lift, shakes, holds).
    phase : str
        Where the object left the hand ("settle", "lift", "shake"), or "held".
    finger_stops : tuple of 3 str
        How each finger's closing ended: "distal" (the distal link stalled with the proximal
        moving), "breakaway-distal" (proximal stalled, then the distal), "breakaway-limit"
        (proximal stalled, the distal reached the DOF limit), "limit" (closed on nothing),
        "timeout".
    joints_deg : (8,) float
        Joint angles (degrees, :data:`hands.barrett.JOINT_NAMES` order) at the end of closing.
    mass : float
        Object mass (kg).
    contacts : int
        Hand–object contact points at the end of closing.
    travel : float
        How far (m) the palm was moved along its approach axis from the pre-grasp pose before the
        fingers closed (``pregrasp_backoff`` for the "planned" approach).
    """

    success: bool
    reason: str
    displacement: float
    slip: float
    offset: np.ndarray
    rotation_deg: float
    held_s: float
    total_s: float
    phase: str
    finger_stops: tuple[str, ...]
    joints_deg: np.ndarray
    mass: float
    contacts: int
    travel: float

    def as_dict(self) -> dict:
        """JSON-ready dictionary (lists instead of arrays)."""
        out = asdict(self)
        out["offset"] = np.asarray(self.offset).tolist()
        out["joints_deg"] = np.asarray(self.joints_deg).tolist()
        out["finger_stops"] = list(self.finger_stops)
        return out


# -- object: mass properties and convex decomposition ----------------------------------------------
def _cache_root(cache_dir: str | Path | None) -> Path:
    if cache_dir is not None:
        return Path(cache_dir)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "mvp-grasp" / "convex"


def _mesh_key(mesh: trimesh.Trimesh) -> str:
    digest = hashlib.sha256()
    digest.update(_CACHE_VERSION.encode())
    digest.update(repr(sorted(VHACD_OPTIONS.items())).encode())
    digest.update(np.ascontiguousarray(mesh.vertices, dtype="<f8").tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype="<i8").tobytes())
    return digest.hexdigest()[:32]


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Silence C-level stdout (V-HACD prints its progress there)."""
    try:
        fd = os.dup(1)
    except OSError:  # no stdout to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as devnull:
            os.dup2(devnull.fileno(), 1)
            try:
                yield
            finally:
                os.dup2(fd, 1)
    finally:
        os.close(fd)


def _write_pieces(path: Path, pieces: Sequence[np.ndarray]) -> None:
    """Write convex pieces ((k, 3) vertex arrays) as one OBJ with an ``o`` group per hull."""
    lines, offset = [], 1
    for index, vertices in enumerate(pieces):
        hull = trimesh.convex.convex_hull(vertices)
        lines.append(f"o convex_{index}")
        lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in hull.vertices]
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in hull.faces]
        offset += len(hull.vertices)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, path)  # atomic: a concurrent reader sees the old file or the new one


def read_pieces(path: str | Path) -> list[np.ndarray]:
    """The vertex arrays ((k, 3) float each) of the ``o`` groups of an OBJ written by V-HACD."""
    pieces: list[list[list[float]]] = []
    for line in Path(path).read_text().splitlines():
        if line.startswith("o ") or (line.startswith("v ") and not pieces):
            pieces.append([])
        if line.startswith("v "):
            pieces[-1].append([float(v) for v in line.split()[1:4]])
    return [np.asarray(piece, dtype=np.float64) for piece in pieces if len(piece) >= 4]


def convex_decomposition(
    mesh: trimesh.Trimesh, *, cache_dir: str | Path | None = None
) -> tuple[Path, list[np.ndarray]]:
    """Convex pieces of ``mesh`` as an OBJ file (one ``o`` group per hull) and their vertices.

    A convex mesh is its own hull; anything else goes through pybullet's V-HACD
    (:data:`VHACD_OPTIONS`). The OBJ is cached under ``cache_dir`` (default
    ``$XDG_CACHE_HOME/mvp-grasp/convex`` or ``~/.cache/…``, falling back to the temp folder when
    that is not writable) by a hash of the vertices, faces and options, so the same mesh in the same
    pose is decomposed once.

    Returns
    -------
    (path, pieces): the OBJ path and a list of (k, 3) float vertex arrays, mesh coordinates.
    """
    check_mesh(mesh)
    root = _cache_root(cache_dir)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError:
        if cache_dir is not None:
            raise
        root = Path(tempfile.gettempdir()) / "mvp-grasp-convex"
        root.mkdir(parents=True, exist_ok=True)
    path = root / f"{_mesh_key(mesh)}.obj"
    if not path.is_file():
        if mesh.is_convex:
            _write_pieces(path, [np.asarray(mesh.vertices)])
        else:
            log.info("V-HACD decomposition of a %d-face mesh into %s", len(mesh.faces), path)
            with tempfile.TemporaryDirectory() as tmp:
                source, result = Path(tmp) / "in.obj", Path(tmp) / "out.obj"
                source.write_text(trimesh.exchange.obj.export_obj(mesh, include_normals=False))
                client = bullet_client.BulletClient(connection_mode=pybullet.DIRECT)
                try:
                    with _quiet_stdout():
                        client.vhacd(
                            str(source), str(result), str(Path(tmp) / "log.txt"), **VHACD_OPTIONS
                        )
                finally:
                    client.disconnect()
                pieces = read_pieces(result) if result.is_file() else []
            if not pieces:  # V-HACD gave nothing usable: fall back to the hull
                log.warning("V-HACD returned no pieces; using the convex hull")
                pieces = [np.asarray(mesh.vertices)]
            _write_pieces(path, pieces)
    return path, read_pieces(path)


def _shrink(vertices: np.ndarray, margin: float) -> np.ndarray:
    """Vertices (k, 3) of the convex hull of ``vertices`` with every face moved ``margin`` inward.

    A piece too thin to shrink (its centroid closer than ``margin`` to a face) is returned as is.
    """
    try:
        hull = ConvexHull(vertices)
    except QhullError:
        return vertices
    centre = vertices[hull.vertices].mean(axis=0)
    equations = hull.equations.copy()  # (f, 4): n·x + d <= 0 inside, |n| = 1
    if not np.all(equations[:, :3] @ centre + equations[:, 3] < -2.0 * margin):
        return vertices
    equations[:, 3] += margin
    try:
        return HalfspaceIntersection(equations, centre).intersections
    except QhullError:
        return vertices


def mass_properties(
    mesh: trimesh.Trimesh, pieces: Sequence[np.ndarray], density: float = DENSITY_KG_M3
) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass (kg), centre of mass (3,) and inertia tensor about it (3, 3), at ``density``.

    From the mesh when it is a closed, consistently wound volume; otherwise the sum over the convex
    ``pieces`` (overlaps counted twice, which V-HACD keeps small).
    """
    if not density > 0.0:
        raise ValueError(f"density must be positive (kg/m³), got {density}")
    parts = [mesh] if mesh.is_volume else [trimesh.convex.convex_hull(p) for p in pieces]
    props = [trimesh.triangles.mass_properties(p.triangles, density=density) for p in parts]
    masses = np.array([p.mass for p in props])
    if not masses.sum() > 0.0:
        raise ValueError("the object has no volume; cannot give it a mass")
    centres = np.array([p.center_mass for p in props])
    com = masses @ centres / masses.sum()
    inertia = np.zeros((3, 3))
    for p, m, c in zip(props, masses, centres, strict=True):
        d = c - com
        inertia += np.asarray(p.inertia) + m * (d @ d * np.eye(3) - np.outer(d, d))
    return float(masses.sum()), com, inertia


# -- the world -------------------------------------------------------------------------------------
def _to_pybullet(pose: np.ndarray) -> tuple[list[float], list[float]]:
    return pose[:3, 3].tolist(), Rotation.from_matrix(pose[:3, :3]).as_quat().tolist()


def _invert(pose: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = pose[:3, :3].T
    out[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return out


@dataclass
class _Finger:
    """Closing state of one finger (radians)."""

    prox: int  # pybullet joint indices
    dist: int
    dof: float = 0.0  # commanded DOF (motor angle in J2 units)
    mode: str = "coupled"  # coupled → breakaway → stopped; coupled → stopped; coupled → limit
    stop: str = "timeout"
    prox_count: int = 0  # consecutive stalled steps
    dist_count: int = 0

    @property
    def done(self) -> bool:
        return self.mode in ("stopped", "limit")


class DynamicWorld:
    """A pybullet world (its own DIRECT client) with a dynamic object and a free-base BarrettHand.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The object, world frame, metres; it starts where the mesh is, at rest.
    friction : float
        Lateral friction of the hand links (the object gets 1.0; pybullet multiplies them).
    density : float
        Object density (kg/m³).
    table : bool
        Put a static table top (1 m square) under the object's lowest point.
    settings : LiftSettings
    params : BarrettParams
    cache_dir : path or None
        Where the convex decomposition is cached (:func:`convex_decomposition`).

    The hand is carried by a fixed constraint to the world (:meth:`place_hand`, :meth:`move_hand`)
    and its fingers follow the Barrett closing controller (:meth:`drive_fingers`). Gravity starts
    off; :meth:`gravity` switches it. Use as a context manager (or call :meth:`close`).
    """

    def __init__(
        self,
        mesh: trimesh.Trimesh,
        *,
        friction: float = MU_RUBBER,
        density: float = DENSITY_KG_M3,
        table: bool = False,
        settings: LiftSettings = DEFAULT_SETTINGS,
        params: BarrettParams = BH8_282,
        cache_dir: str | Path | None = None,
    ) -> None:
        from hands.barrett.urdf import urdf_string

        check_mesh(mesh)
        if not (math.isfinite(friction) and friction >= 0.0):
            raise ValueError(f"friction must be a finite coefficient >= 0, got {friction}")
        self.settings = settings
        self.params = params
        obj_path, pieces = convex_decomposition(mesh, cache_dir=cache_dir)
        self.mass, com, inertia = mass_properties(mesh, pieces, density)
        principal, axes = np.linalg.eigh(inertia)
        if np.linalg.det(axes) < 0:
            axes[:, 2] *= -1.0
        # the object's body frame: centre of mass and principal axes, placed in the mesh frame
        body = np.eye(4)
        body[:3, :3], body[:3, 3] = axes, com
        to_body = _invert(body)
        self._home: tuple[list[float], list[float]] | None = None
        self._constraint: int | None = None
        self._support: int | None = None

        self.client = bullet_client.BulletClient(connection_mode=pybullet.DIRECT)
        c = self.client
        try:
            c.setPhysicsEngineParameter(
                fixedTimeStep=settings.time_step,
                numSubSteps=0,
                numSolverIterations=settings.solver_iterations,
                deterministicOverlappingPairs=1,
            )
            self.gravity(False)
            # pybullet pads every convex hull by MESH_MARGIN_M: shrink the pieces by as much so
            # that the padded shape is the true one
            body_pieces = [
                _shrink(piece, MESH_MARGIN_M) @ to_body[:3, :3].T + to_body[:3, 3]
                for piece in pieces
            ]
            with tempfile.TemporaryDirectory() as tmp:
                shape_path = Path(tmp) / "object.obj"
                _write_pieces(shape_path, body_pieces)
                shape = c.createCollisionShape(pybullet.GEOM_MESH, fileName=str(shape_path))
            position, orientation = _to_pybullet(body)
            self.object_id = c.createMultiBody(
                baseMass=self.mass,
                baseCollisionShapeIndex=shape,
                basePosition=position,
                baseOrientation=orientation,
            )
            c.changeDynamics(
                self.object_id,
                -1,
                localInertiaDiagonal=np.maximum(principal, 1e-12).tolist(),
                lateralFriction=1.0,
                frictionAnchor=1,
                spinningFriction=0.0,
                rollingFriction=0.0,
                linearDamping=0.0,
                angularDamping=0.0,
            )
            self.table_id: int | None = None
            if table:
                half = [0.5, 0.5, 0.025]
                box = c.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half)
                centre = np.asarray(mesh.bounds).mean(axis=0)
                centre[2] = float(mesh.bounds[0, 2]) - half[2]
                self.table_id = c.createMultiBody(0.0, box, basePosition=centre.tolist())
                c.changeDynamics(self.table_id, -1, lateralFriction=settings.table_friction)
            with tempfile.TemporaryDirectory() as tmp:
                urdf = Path(tmp) / "barrett.urdf"
                urdf.write_text(urdf_string(params))
                # implicit cylinders: pybullet would otherwise pad the palm's hull by its margin
                self.hand_id = c.loadURDF(
                    str(urdf),
                    useFixedBase=False,
                    flags=pybullet.URDF_USE_INERTIA_FROM_FILE | pybullet.URDF_USE_IMPLICIT_CYLINDER,
                )
            self.joints: dict[str, JointInfo] = {}
            for index in range(c.getNumJoints(self.hand_id)):
                info = c.getJointInfo(self.hand_id, index)
                record = JointInfo(
                    index, info[1].decode(), info[2], info[8], info[9], info[12].decode()
                )
                self.joints[record.name] = record
            for link in range(-1, c.getNumJoints(self.hand_id)):
                c.changeDynamics(
                    self.hand_id,
                    link,
                    lateralFriction=float(friction),
                    frictionAnchor=1,
                    spinningFriction=0.0,
                    rollingFriction=0.0,
                    jointDamping=0.0,
                    linearDamping=0.0,
                    angularDamping=0.0,
                )
            # the base of a pybullet body is its inertial frame, not the URDF palm frame
            inertial = c.getDynamicsInfo(self.hand_id, -1)
            self._palm_in_base = c.invertTransform(inertial[3], inertial[4])
        except Exception:
            c.disconnect()
            raise

    # -- lifetime --------------------------------------------------------------------------------
    def close(self) -> None:
        """Disconnect the pybullet client (idempotent)."""
        if self.client is not None:
            with contextlib.suppress(pybullet.error):
                self.client.disconnect()
            self.client = None

    def __enter__(self) -> DynamicWorld:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- state -----------------------------------------------------------------------------------
    def gravity(self, on: bool) -> None:
        """Switch gravity (−z, :data:`GRAVITY` m/s²) on or off."""
        self.client.setGravity(0.0, 0.0, -GRAVITY if on else 0.0)

    def object_in_palm(self) -> tuple[np.ndarray, np.ndarray]:
        """The object's centre of mass (3,) and body axes (3, 3) in the actual palm frame."""
        c = self.client
        base = c.getBasePositionAndOrientation(self.hand_id)
        palm = c.multiplyTransforms(*base, *self._palm_in_base)
        inverse = c.invertTransform(*palm)
        position, orientation = c.multiplyTransforms(
            *inverse, *c.getBasePositionAndOrientation(self.object_id)
        )
        rotation = np.reshape(c.getMatrixFromQuaternion(orientation), (3, 3))
        return np.asarray(position), rotation

    def joint_values_deg(self) -> np.ndarray:
        """(8,) joint angles in degrees, :data:`JOINT_NAMES` order."""
        indices = [self.joints[name].index for name in JOINT_NAMES]
        return np.degrees([s[0] for s in self.client.getJointStates(self.hand_id, indices)])

    def n_contacts(self) -> int:
        """Number of hand–object contact points."""
        return len(self.client.getContactPoints(self.hand_id, self.object_id))

    def hold_object(self, force: float | None) -> None:
        """Hold the object where it is by a constraint of at most ``force`` (N); None frees it.

        It stands in for whatever supported the floating object before the grasp: it keeps the
        object from drifting off when the palm touches it, and yields to the closing fingers.
        """
        c = self.client
        if self._support is not None:
            c.removeConstraint(self._support)
            self._support = None
        if force is None:
            return
        position, orientation = c.getBasePositionAndOrientation(self.object_id)
        self._support = self._fix_to_world(self.object_id, position, orientation)
        c.changeConstraint(self._support, maxForce=float(force))

    def _fix_to_world(self, body: int, position, orientation) -> int:
        """A fixed constraint holding ``body``'s base at a world pose (see changeConstraint)."""
        return self.client.createConstraint(
            body,
            -1,
            -1,
            -1,
            pybullet.JOINT_FIXED,
            [0.0, 0.0, 0.0],
            [0.0, 0.0, 0.0],
            position,
            childFrameOrientation=orientation,
        )

    # -- the hand --------------------------------------------------------------------------------
    def place_hand(
        self,
        palm_pose: np.ndarray,
        joints_deg: Sequence[float],
        *,
        offset: Sequence[float] = (0.0, 0.0, 0.0),
    ) -> None:
        """Put the hand at rest at ``palm_pose`` moved by ``offset`` (world, m), joints in degrees.

        ``palm_pose`` becomes the carriage's home: :meth:`move_hand` translates from it.
        """
        c = self.client
        position, orientation = _to_pybullet(check_pose(palm_pose))
        base_in_palm = c.invertTransform(*self._palm_in_base)
        self._home = c.multiplyTransforms(position, orientation, *base_in_palm)
        start = (np.asarray(self._home[0]) + np.asarray(offset, dtype=np.float64)).tolist()
        c.resetBasePositionAndOrientation(self.hand_id, start, self._home[1])
        c.resetBaseVelocity(self.hand_id, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
        for name, value in zip(JOINT_NAMES, np.radians(joints_deg), strict=True):
            c.resetJointState(self.hand_id, self.joints[name].index, float(value), 0.0)
        if self._constraint is None:
            self._constraint = self._fix_to_world(self.hand_id, start, self._home[1])
        self.move_hand(offset)

    def move_hand(self, offset: Sequence[float]) -> None:
        """Drive the hand toward its home pose translated by ``offset`` (world, m)."""
        if self._home is None:
            raise ValueError("place_hand must come before move_hand")
        target = (np.asarray(self._home[0]) + np.asarray(offset, dtype=np.float64)).tolist()
        self.client.changeConstraint(
            self._constraint,
            jointChildPivot=target,
            jointChildFrameOrientation=self._home[1],
            maxForce=self.settings.hand_force,
        )

    def hand_offset(self) -> np.ndarray:
        """(3,) where the hand actually is, as a world translation from its home pose (m)."""
        if self._home is None:
            raise ValueError("place_hand must come before hand_offset")
        position, _ = self.client.getBasePositionAndOrientation(self.hand_id)
        return np.asarray(position) - np.asarray(self._home[0])

    def hold_spread(self, spread_deg: float) -> None:
        """Position-control both spread joints at ``spread_deg`` with the spread torque limit."""
        for name in ("f1_spread", "f2_spread"):
            self._position(
                self.joints[name].index, math.radians(spread_deg), self.settings.spread_torque
            )

    def fingers(self) -> list[_Finger]:
        """Fresh closing state of the three fingers (open)."""
        return [
            _Finger(self.joints[f"{f}_prox"].index, self.joints[f"{f}_dist"].index) for f in FINGERS
        ]

    def hold_fingers_open(self, fingers: Sequence[_Finger]) -> None:
        """Position-control every finger joint at 0 (open)."""
        s = self.settings
        for finger in fingers:
            self._position(finger.prox, 0.0, s.proximal_torque)
            self._position(finger.dist, 0.0, s.distal_torque)

    def drive_fingers(self, fingers: Sequence[_Finger]) -> None:
        """One control step of every finger: Barrett coupling and breakaway.

        Coupled, the DOF rises at ``close_speed`` and J2 = DOF, J3 = DOF/3 under position control.
        The controller watches the joints: a joint more than ``stall_lag`` behind its target and
        slower than ``stall_speed`` for ``stall_steps`` steps has stalled. A stalled proximal whose
        distal still moves breaks away: J2 then presses with its torque limit and the distal
        target keeps following DOF/3. A stalled distal stops the finger: both joints press with
        their limits. A finger whose DOF reaches its maximum untouched holds there ("limit").
        """
        s, c = self.settings, self.client
        ratio = self.params.distal_ratio
        dof_max = math.radians(self.params.finger_dof_max_deg)
        j2_max = math.radians(self.params.proximal_max_deg)
        for finger in fingers:
            (q2, v2, *_), (q3, v3, *_) = c.getJointStates(self.hand_id, [finger.prox, finger.dist])
            if finger.mode in ("coupled", "breakaway"):
                if finger.mode == "coupled":
                    stalled = min(finger.dof, j2_max) - q2 > s.stall_lag and v2 < s.stall_speed
                    finger.prox_count = finger.prox_count + 1 if stalled else 0
                stalled = ratio * finger.dof - q3 > s.stall_lag and v3 < ratio * s.stall_speed
                finger.dist_count = finger.dist_count + 1 if stalled else 0
                if finger.dist_count >= s.stall_steps:
                    finger.stop = "distal" if finger.mode == "coupled" else "breakaway-distal"
                    finger.mode = "stopped"
                elif finger.mode == "coupled" and finger.prox_count >= s.stall_steps:
                    if v3 < ratio * s.stall_speed:  # the distal is blocked too
                        finger.stop, finger.mode = "distal", "stopped"
                    else:
                        finger.mode = "breakaway"
                elif finger.dof >= dof_max:
                    finger.stop = "limit" if finger.mode == "coupled" else "breakaway-limit"
                    finger.mode = "limit" if finger.mode == "coupled" else "stopped"
                else:
                    finger.dof = min(finger.dof + s.close_speed * s.time_step, dof_max)
            if finger.mode in ("coupled", "limit"):
                self._position(finger.prox, min(finger.dof, j2_max), s.proximal_torque)
            else:
                self._press(finger.prox, s.proximal_torque)
            if finger.mode == "stopped" and finger.stop != "breakaway-limit":
                self._press(finger.dist, s.distal_torque)
            else:
                self._position(finger.dist, ratio * finger.dof, s.distal_torque)

    def _position(self, joint: int, target: float, torque: float) -> None:
        self.client.setJointMotorControl2(
            self.hand_id,
            joint,
            pybullet.POSITION_CONTROL,
            targetPosition=target,
            force=torque,
            positionGain=self.settings.position_gain,
            velocityGain=self.settings.velocity_gain,
        )

    def _press(self, joint: int, torque: float) -> None:
        # a velocity motor that cannot reach its target speed applies its full torque
        self.client.setJointMotorControl2(
            self.hand_id,
            joint,
            pybullet.VELOCITY_CONTROL,
            targetVelocity=self.settings.close_speed,
            force=torque,
        )

    def step(self) -> None:
        """Advance the simulation by one ``time_step``."""
        self.client.stepSimulation()


# -- the test --------------------------------------------------------------------------------------
def _smooth(t: float) -> float:
    """Cosine ease from 0 to 1 for t in [0, 1] (zero velocity at both ends)."""
    t = min(max(t, 0.0), 1.0)
    return 0.5 - 0.5 * math.cos(math.pi * t)


def _schedule(
    lift: float, shake: bool, directions: np.ndarray, s: LiftSettings
) -> list[tuple[str, int, Callable[[float], np.ndarray]]]:
    """The loaded phases: (name, steps, hand offset (3,) from the grasp pose at time t in it)."""
    up = np.array([0.0, 0.0, 1.0])
    lift_time = lift / s.lift_speed
    phases: list[tuple[str, float, Callable[[float], np.ndarray]]] = [
        ("settle", s.settle_time, lambda t: 0.0 * up),
        ("lift", lift_time, lambda t: lift * _smooth(t / lift_time) * up),
        ("lift", s.hold_time, lambda t: lift * up),
    ]
    if shake:
        period = 1.0 / s.shake_frequency
        for d in directions:
            # out and back along d: A (1 − cos 2πft) / 2, peak acceleration 2π²f²A
            phases.append(
                (
                    "shake",
                    period,
                    lambda t, d=d: lift * up + s.shake_amplitude * _smooth(2 * t / period) * d,
                )
            )
        phases.append(("shake", s.hold_time, lambda t: lift * up))
    return [(name, round(duration / s.time_step), f) for name, duration, f in phases]


def lift_test(
    mesh: trimesh.Trimesh,
    grasp: GraspResult,
    *,
    seed: int = 0,
    lift: float = 0.10,
    shake: bool = True,
    friction: float = MU_RUBBER,
    density: float = DENSITY_KG_M3,
    table: bool = False,
    approach: Approach = "planned",
    settings: LiftSettings = DEFAULT_SETTINGS,
    params: BarrettParams = BH8_282,
    cache_dir: str | Path | None = None,
) -> LiftResult:
    """Execute ``grasp`` on ``mesh`` in pybullet dynamics, lift and shake; did the object stay?

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The true object in world coordinates (metres), the frame of ``grasp.palm_pose``.
    grasp : GraspResult
        A planned grasp (:func:`grasp.autograsp.autograsp`, :func:`grasp.planner.plan`). Its palm
        pose and spread are used; the finger joints come from the simulated closing.
    seed : int
        Seeds the shake directions. The same inputs and seed give the same result.
    lift : float
        How far the hand rises along world +z (metres, >= 0).
    shake : bool
        Shake after the lift (``settings.shake_count`` cycles along seeded directions).
    friction : float
        Hand–object Coulomb friction μ (default 1.0, rubber; BARRETT.md).
    density : float
        Object density in kg/m³ (default 500).
    table : bool
        Stand the object on a table (at its lowest point) with gravity on from the start, instead
        of floating it on a weak support until the hand has closed.
    approach : "planned" or "contact"
        From the pre-grasp pose (``settings.pregrasp_backoff`` behind the palm pose, hand open),
        "planned" moves the palm to ``grasp.palm_pose`` exactly (open loop, as for a grasp planned
        on this mesh); "contact" moves along the approach axis until the hand first touches the
        object, at most ``settings.overtravel`` past the planned pose (a guarded move, for a grasp
        planned on another mesh, e.g. a predicted shape; DESIGN.md §7's re-approach).
    settings : LiftSettings
        Time step, torque limits, speeds, shake and tolerances.
    params : BarrettParams
        Hand dimensions (the URDF is generated from them).
    cache_dir : path or None
        Cache of convex decompositions (:func:`convex_decomposition`).

    Returns
    -------
    LiftResult
        ``success``, ``displacement``, ``slip``, ``held_s`` and more. A grasp that closes on
        nothing is a failed result, not an exception.
    """
    check_mesh(mesh)
    if not isinstance(grasp, GraspResult):
        raise ValueError(f"grasp must be a GraspResult, got {type(grasp).__name__}")
    if not (math.isfinite(lift) and lift >= 0.0):
        raise ValueError(f"lift must be a finite distance >= 0 (metres), got {lift}")
    if approach not in APPROACHES:
        raise ValueError(f"approach must be one of {APPROACHES}, got {approach!r}")
    s = settings
    directions = np.random.default_rng(seed).normal(size=(s.shake_count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    palm = check_pose(grasp.palm_pose)
    spread = float(grasp.dofs_deg.spread)
    open_joints = [spread, 0.0, 0.0, spread, 0.0, 0.0, 0.0, 0.0]
    backoff = pregrasp_pose(palm, s.pregrasp_backoff)[:3, 3] - palm[:3, 3]  # (3,) world

    with DynamicWorld(
        mesh,
        friction=friction,
        density=density,
        table=table,
        settings=s,
        params=params,
        cache_dir=cache_dir,
    ) as world:
        world.gravity(table)
        if not table:
            world.hold_object(s.support_factor * world.mass * GRAVITY)
        world.place_hand(palm, open_joints, offset=backoff)
        fingers = world.fingers()
        # approach from the pre-grasp pose, hand open
        if approach == "planned":  # to the planned palm pose, smooth start and stop
            n = max(1, math.ceil(s.pregrasp_backoff / s.approach_speed / s.time_step))
            path = [backoff * (1.0 - _smooth(i / n)) for i in range(1, n + 1)]
        else:  # guarded: along the approach axis until the first touch, at constant speed
            reach = s.pregrasp_backoff + s.overtravel
            n = max(1, math.ceil(reach / s.approach_speed / s.time_step))
            path = [backoff + reach * (i / n) * palm[:3, 2] for i in range(1, n + 1)]
        for offset in path:
            world.move_hand(offset)
            world.hold_spread(spread)
            world.hold_fingers_open(fingers)
            world.step()
            if approach == "contact" and world.n_contacts():
                offset = world.hand_offset()  # stop where the hand is (it trails its target)
                world.move_hand(offset)
                break
        travel = float(np.dot(offset - backoff, palm[:3, 2]))
        # close
        steps, settle_left = 0, round(s.close_settle / s.time_step)
        while steps * s.time_step < s.close_timeout and settle_left > 0:
            world.hold_spread(spread)
            world.drive_fingers(fingers)
            world.step()
            steps += 1
            if all(f.done for f in fingers):
                settle_left -= 1
        joints_deg = world.joint_values_deg()
        contacts = world.n_contacts()
        stops = tuple(f.stop for f in fingers)
        ref_position, ref_rotation = world.object_in_palm()
        # load: gravity on, support gone
        world.hold_object(None)
        world.gravity(True)
        slip, held_s, phase, elapsed = 0.0, None, "held", 0.0
        position, rotation = ref_position, ref_rotation
        for name, n_steps, target in _schedule(lift, shake, directions, s):
            for i in range(n_steps):
                world.move_hand(target((i + 1) * s.time_step))
                world.hold_spread(spread)
                world.drive_fingers(fingers)
                world.step()
                elapsed += s.time_step
                position, rotation = world.object_in_palm()
                distance = float(np.linalg.norm(position - ref_position))
                slip = max(slip, distance)
                if held_s is None and distance > s.hold_tolerance:
                    held_s, phase = elapsed, name
                if distance > s.drop_distance:
                    break
            else:
                continue
            break

    moved = position - ref_position
    relative = ref_rotation.T @ rotation
    rotation_deg = math.degrees(Rotation.from_matrix(relative).magnitude())
    if held_s is None:
        reason = "held through the lift" + (" and the shakes" if shake else "")
    elif contacts == 0:
        reason = f"the hand closed on nothing; the object fell ({phase})"
    else:
        reason = f"the object left the hand during {phase}, {held_s:.2f} s after gravity came on"
    return LiftResult(
        success=held_s is None,
        reason=reason,
        displacement=float(np.linalg.norm(moved)),
        slip=slip,
        offset=moved,
        rotation_deg=rotation_deg,
        held_s=elapsed if held_s is None else held_s,
        total_s=elapsed,
        phase=phase,
        finger_stops=stops,
        joints_deg=joints_deg,
        mass=world.mass,
        contacts=contacts,
        travel=travel,
    )


# -- command line ----------------------------------------------------------------------------------
def _load_mesh(spec: str) -> trimesh.Trimesh:
    path = Path(spec)
    if path.is_file():
        mesh = trimesh.load(path, force="mesh")
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise ValueError(f"{path} holds no triangles")
        return mesh
    if spec.startswith(("proc/", "urdf/", "named/")):
        from completion.objects import load_object

        return load_object(spec)
    raise ValueError(f"MESH must be a mesh file or an object id (named/mug, …); got {spec!r}")


def main(argv: list[str] | None = None) -> int:
    import argparse
    import time

    from grasp.planner import plan

    parser = argparse.ArgumentParser(
        prog="python -m grasp.physics",
        description="Plan a BarrettHand grasp on a mesh, then lift-test it in pybullet dynamics.",
    )
    parser.add_argument("mesh", help="mesh file (OBJ/STL/PLY, metres) or an object id")
    parser.add_argument("--seed", type=int, default=0, help="planner and shake seed")
    parser.add_argument("--candidates", type=int, default=64, help="planner candidates")
    parser.add_argument("--top-k", type=int, default=1, help="lift-test the best K grasps")
    parser.add_argument("--lift", type=float, default=0.10, help="lift height (m)")
    parser.add_argument("--no-shake", action="store_true", help="lift only")
    parser.add_argument("--friction", type=float, default=MU_RUBBER, help="hand–object μ")
    parser.add_argument("--density", type=float, default=DENSITY_KG_M3, help="kg/m³")
    parser.add_argument("--table", action="store_true", help="object on a table")
    parser.add_argument(
        "--approach", choices=APPROACHES, default="planned", help="to the planned pose or to touch"
    )
    args = parser.parse_args(argv)
    try:
        mesh = _load_mesh(args.mesh)
        t0 = time.perf_counter()
        grasps = plan(mesh, n_candidates=args.candidates, seed=args.seed, top_k=args.top_k)
        t_plan = time.perf_counter() - t0
    except ValueError as exc:
        parser.error(str(exc))
    print(f"planned {len(grasps)} grasp(s) in {t_plan:.1f} s")
    held = 0
    for rank, grasp in enumerate(grasps):
        t0 = time.perf_counter()
        try:
            result = lift_test(
                mesh,
                grasp,
                seed=args.seed,
                lift=args.lift,
                shake=not args.no_shake,
                friction=args.friction,
                density=args.density,
                table=args.table,
                approach=args.approach,
            )
        except ValueError as exc:
            parser.error(str(exc))
        wall = time.perf_counter() - t0
        held += result.success
        print(
            f"#{rank}: planner {grasp.reason} (eps {grasp.epsilon:.3f}); "
            f"{'HELD' if result.success else 'DROPPED'}: {result.reason}; "
            f"displacement {1000 * result.displacement:.1f} mm, slip {1000 * result.slip:.1f} mm, "
            f"held {result.held_s:.2f}/{result.total_s:.2f} s, mass {result.mass:.3f} kg, "
            f"fingers {'/'.join(result.finger_stops)}, {wall:.2f} s wall"
        )
    print(f"held {held}/{len(grasps)}")
    return 0 if held else 1


if __name__ == "__main__":
    raise SystemExit(main())
