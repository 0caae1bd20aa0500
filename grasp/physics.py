"""Physics check of a grasp: close the BarrettHand on the true object in pybullet, lift, shake.

:func:`lift_test` replays a planned :class:`grasp.autograsp.GraspResult` in rigid-body dynamics and
says whether the object stays in the hand. One trial, in its own DIRECT pybullet client:

1. **Object**: the mesh as a dynamic body. Mass and inertia at ``density`` (default
   :data:`DENSITY_KG_M3` = 500 kg/m³, a solid between hollow plastic and wood), from the mesh when
   it is a closed volume, otherwise from its convex pieces. Collision: the convex hull when the mesh
   is convex, else pybullet's V-HACD decomposition (:func:`convex_decomposition`), cached per mesh.
   Optionally a table under it (``table=True``; the scenes here float the object, so off by
   default).
2. **Hand**: the URDF from :mod:`hands.barrett.urdf`, free base, carried by a fixed constraint to
   the world whose target pose is moved every step (``changeConstraint``, max force
   ``hand_force``), so contacts see the hand's real velocity. Placed open, at the grasp's spread,
   ``pregrasp_backoff`` behind the grasp pose along its approach axis, then moved to the grasp pose.
3. **Close**: every finger DOF rises at ``close_speed`` with J2 = DOF and J3 = DOF/3 (position
   control, torque limited). A controller watches each proximal joint: when it lags its target
   while barely moving (stalled on the object) the finger breaks away, its proximal joint now
   presses with its torque limit and the distal target keeps following DOF/3; a stalled distal
   stops the finger (then both joints press with their limits). Gravity is off while the hand
   approaches and closes (the object floats where the planner saw it) unless there is a table.
4. **Load**: gravity on, settle, lift the hand by ``lift`` along world +z (smooth profile), hold,
   then ``shake_count`` shakes along seeded random directions (out and back, one cycle each), hold.

Success: the object's centre of mass never moves more than ``hold_tolerance`` (2 cm) from where it
sat in the hand at the end of closing, measured in the palm frame, from gravity-on to the end.

Numbers (:class:`LiftSettings`, one place; the hand's facts are in ``shared/BARRETT.md``):

- Time step 1/240 s, 100 solver iterations, deterministic overlapping pairs: the same inputs and
  seed give bit-identical results on one machine.
- Torque limits: J3 0.75 N·m (15 N at the 5 cm fingertip lever, the BH8-28x active fingertip
  force; Barrett's distal torque sensor spans ±1 N·m for "2 kg at the fingertip"); J2 1.0 N·m
  (the same motor through 125:1 instead of 93.75:1, i.e. 4/3 of J3); spread 2.0 N·m (chosen; the
  worm-driven spread does not back-drive). Finger DOF speed 1 rad/s (the real hand closes its
  140° in about 1 s; slower keeps the first touch from batting the floating object away).
- Friction: hand links get ``friction`` (default μ = 1.0, rubber, :data:`grasp.quality.MU_RUBBER`)
  and the object 1.0; pybullet multiplies the two, so a hand–object contact has exactly μ.
- Shake: 4 cycles of 3 cm at 3 Hz, peak acceleration 2π²f²A ≈ 5.3 m/s² (about 0.5 g).

This module must not import torch (DESIGN.md §2).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

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
    "DENSITY_KG_M3",
    "HOLD_TOLERANCE_M",
    "LiftResult",
    "LiftSettings",
    "convex_decomposition",
    "lift_test",
    "mass_properties",
]

log = logging.getLogger(__name__)

#: Density of the object (kg/m³): 500, between hollow plastic ware and solid wood.
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
    # fingers
    close_speed: float = 1.0  # finger DOF speed while closing (rad/s)
    proximal_torque: float = 1.0  # J2 torque limit (N·m)
    distal_torque: float = 0.75  # J3 torque limit (N·m)
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

    def __post_init__(self) -> None:
        positive = ("time_step", "hand_force", "approach_speed", "close_speed", "lift_speed")
        positive += ("proximal_torque", "distal_torque", "spread_torque", "hold_tolerance")
        bad = [name for name in positive if not getattr(self, name) > 0.0]
        if bad:
            raise ValueError(f"LiftSettings: these must be positive, got {bad}")
        if self.drop_distance < self.hold_tolerance:
            raise ValueError("LiftSettings: drop_distance must be >= hold_tolerance")

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


def _from_pybullet(position, quaternion) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    pose[:3, 3] = position
    return pose


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
    mode: str = "coupled"  # coupled → breakaway → stopped, or limit
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
        The object, world frame, metres; it starts where the mesh is.
    friction : float
        Lateral friction of the hand links (the object gets 1.0; pybullet multiplies them).
    density : float
        Object density (kg/m³).
    table : bool
        Put a static table top under the object's lowest point.
    settings : LiftSettings
    params : BarrettParams
    cache_dir : path or None
        Where the convex decomposition is cached (:func:`convex_decomposition`).

    Use as a context manager (or call :meth:`close`) to disconnect the client.
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
        # body frame: centre of mass, principal axes; the mesh sits in it at body_to_mesh
        self._body_in_mesh = np.eye(4)
        self._body_in_mesh[:3, :3], self._body_in_mesh[:3, 3] = axes, com

        self.client = bullet_client.BulletClient(connection_mode=pybullet.DIRECT)
        try:
            c = self.client
            c.setPhysicsEngineParameter(
                fixedTimeStep=settings.time_step,
                numSubSteps=0,
                numSolverIterations=settings.solver_iterations,
                deterministicOverlappingPairs=1,
            )
            c.setGravity(0.0, 0.0, 0.0)
            # pybullet pads every convex hull by its margin (MESH_MARGIN_M): shrink the pieces by
            # as much so that the padded shape is the true one, and put them in the body frame
            to_body = _invert(self._body_in_mesh)
            body_pieces = [
                _shrink(piece, MESH_MARGIN_M) @ to_body[:3, :3].T + to_body[:3, 3]
                for piece in pieces
            ]
            with tempfile.TemporaryDirectory() as tmp:
                shape_path = Path(tmp) / "object.obj"
                _write_pieces(shape_path, body_pieces)
                shape = c.createCollisionShape(pybullet.GEOM_MESH, fileName=str(shape_path))
            position, orientation = _to_pybullet(self._body_in_mesh)
            self.object_id = c.createMultiBody(
                baseMass=self.mass,
                baseCollisionShapeIndex=shape,
                basePosition=position,
                baseOrientation=orientation,
            )
            c.changeDynamics(
                self.object_id,
                -1,
                localInertiaDiagonal=np.maximum(principal, 1e-9).tolist(),
                lateralFriction=1.0,
                spinningFriction=0.0,
                rollingFriction=0.0,
                linearDamping=0.0,
                angularDamping=0.0,
            )
            self.table_id = None
            if table:
                top = float(mesh.bounds[0, 2])
                half = [0.5, 0.5, 0.025]
                box = c.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half)
                centre = [*np.asarray(mesh.bounds).mean(axis=0)[:2].tolist(), top - half[2]]
                self.table_id = c.createMultiBody(0.0, box, basePosition=centre)
                c.changeDynamics(self.table_id, -1, lateralFriction=settings.table_friction)
            with tempfile.TemporaryDirectory() as tmp:
                urdf = Path(tmp) / "barrett.urdf"
                urdf.write_text(urdf_string(params))
                self.hand_id = c.loadURDF(
                    str(urdf),
                    useFixedBase=False,
                    flags=pybullet.URDF_USE_INERTIA_FROM_FILE | pybullet.URDF_USE_IMPLICIT_CYLINDER,
                )
        except Exception:
            self.client.disconnect()
            raise
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
                spinningFriction=0.0,
                rollingFriction=0.0,
                jointDamping=0.0,
                linearDamping=0.0,
                angularDamping=0.0,
            )
        local = c.getDynamicsInfo(self.hand_id, -1)
        self._palm_to_base = _from_pybullet(local[3], local[4])
        self._constraint: int | None = None

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
    def object_pose(self) -> np.ndarray:
        """(4, 4) object body frame (centre of mass, principal axes) → world."""
        return _from_pybullet(*self.client.getBasePositionAndOrientation(self.object_id))

    def palm_pose(self) -> np.ndarray:
        """(4, 4) actual palm → world."""
        base = _from_pybullet(*self.client.getBasePositionAndOrientation(self.hand_id))
        return base @ _invert(self._palm_to_base)

    def joint_values_deg(self) -> np.ndarray:
        """(8,) joint angles in degrees, :data:`JOINT_NAMES` order."""
        indices = [self.joints[name].index for name in JOINT_NAMES]
        return np.degrees([s[0] for s in self.client.getJointStates(self.hand_id, indices)])

    def n_contacts(self) -> int:
        """Number of hand–object contact points."""
        return len(self.client.getContactPoints(self.hand_id, self.object_id))

    # -- the hand --------------------------------------------------------------------------------
    def place_hand(self, palm_pose: np.ndarray, joints_deg: Sequence[float]) -> None:
        """Put the hand at rest at ``palm_pose`` with the given joints, and hold it there."""
        base = check_pose(palm_pose) @ self._palm_to_base
        position, orientation = _to_pybullet(base)
        c = self.client
        c.resetBasePositionAndOrientation(self.hand_id, position, orientation)
        c.resetBaseVelocity(self.hand_id, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
        for name, value in zip(JOINT_NAMES, np.radians(joints_deg), strict=True):
            c.resetJointState(self.hand_id, self.joints[name].index, float(value), 0.0)
        if self._constraint is None:
            self._constraint = c.createConstraint(
                self.hand_id,
                -1,
                -1,
                -1,
                pybullet.JOINT_FIXED,
                [0.0, 0.0, 0.0],
                [0.0, 0.0, 0.0],
                position,
                childFrameOrientation=orientation,
            )
        self.move_hand(palm_pose)

    def move_hand(self, palm_pose: np.ndarray) -> None:
        """Set the target palm pose of the constraint that carries the hand."""
        position, orientation = _to_pybullet(palm_pose @ self._palm_to_base)
        self.client.changeConstraint(
            self._constraint,
            jointChildPivot=position,
            jointChildFrameOrientation=orientation,
            maxForce=self.settings.hand_force,
        )

    def hold_spread(self, spread_deg: float) -> None:
        """Position-control both spread joints at ``spread_deg`` with the spread torque limit."""
        for name in ("f1_spread", "f2_spread"):
            self.client.setJointMotorControl2(
                self.hand_id,
                self.joints[name].index,
                pybullet.POSITION_CONTROL,
                targetPosition=math.radians(spread_deg),
                force=self.settings.spread_torque,
                positionGain=self.settings.position_gain,
                velocityGain=self.settings.velocity_gain,
            )

    def fingers(self) -> list[_Finger]:
        """Fresh closing state for the three fingers (open)."""
        return [
            _Finger(self.joints[f"{f}_prox"].index, self.joints[f"{f}_dist"].index) for f in FINGERS
        ]

    def drive_fingers(self, fingers: Sequence[_Finger]) -> None:
        """One control step of the Barrett coupling and breakaway (see the module docstring)."""
        s, c = self.settings, self.client
        ratio = self.params.distal_ratio
        dof_max = math.radians(self.params.finger_dof_max_deg)
        j2_max = math.radians(self.params.proximal_max_deg)
        for finger in fingers:
            (q2, v2, *_), (q3, v3, *_) = c.getJointStates(self.hand_id, [finger.prox, finger.dist])
            if finger.mode in ("coupled", "breakaway"):
                # watch the joints: lagging and not moving means stalled on the object
                if finger.mode == "coupled":
                    stalled = min(finger.dof, j2_max) - q2 > s.stall_lag and v2 < s.stall_speed
                    finger.prox_count = finger.prox_count + 1 if stalled else 0
                stalled = ratio * finger.dof - q3 > s.stall_lag and v3 < s.stall_speed * ratio
                finger.dist_count = finger.dist_count + 1 if stalled else 0
                if finger.dist_count >= s.stall_steps:
                    finger.stop = "distal" if finger.mode == "coupled" else "breakaway-distal"
                    finger.mode = "stopped"
                elif finger.mode == "coupled" and finger.prox_count >= s.stall_steps:
                    finger.mode = "breakaway"
                elif finger.dof >= dof_max:
                    finger.stop = "limit" if finger.mode == "coupled" else "breakaway-limit"
                    finger.mode = "limit" if finger.mode == "coupled" else "stopped"
                else:
                    finger.dof = min(finger.dof + s.close_speed * s.time_step, dof_max)
            # proximal: follow the DOF while coupled, else press with its torque limit
            if finger.mode in ("coupled", "limit"):
                self._position(finger.prox, min(finger.dof, j2_max), s.proximal_torque)
            else:
                self._press(finger.prox, s.proximal_torque)
            # distal: follow DOF/3 until it stalls, then press
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
        self.client.stepSimulation()


# -- the test --------------------------------------------------------------------------------------
def _smooth(t: float) -> float:
    """Cosine ease from 0 to 1 over t in [0, 1] (zero velocity at both ends)."""
    t = min(max(t, 0.0), 1.0)
    return 0.5 - 0.5 * math.cos(math.pi * t)


def _shift(pose: np.ndarray, offset: np.ndarray) -> np.ndarray:
    out = pose.copy()
    out[:3, 3] += offset
    return out


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
    settings: LiftSettings = DEFAULT_SETTINGS,
    params: BarrettParams = BH8_282,
    cache_dir: str | Path | None = None,
) -> LiftResult:
    """Execute ``grasp`` on ``mesh`` in pybullet dynamics, lift and shake; did the object stay?

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The true object in world coordinates (metres), the same frame as ``grasp.palm_pose``.
    grasp : GraspResult
        A planned grasp (from :func:`grasp.autograsp.autograsp` or :func:`grasp.planner.plan`);
        its palm pose and spread are used, the finger joints come from the simulated closing.
    seed : int
        Seeds the shake directions. The same inputs and seed give the same result.
    lift : float
        How far the hand rises along world +z (metres, >= 0).
    shake : bool
        Shake after the lift (``settings.shake_count`` cycles along seeded directions).
    friction : float
        Hand–object Coulomb friction μ (default 1.0, rubber).
    density : float
        Object density in kg/m³ (default 500).
    table : bool
        Put the object on a table (its lowest point); gravity is then on from the start.
    settings : LiftSettings
        Time step, torque limits, speeds, shake and tolerances.
    params : BarrettParams
        Hand dimensions (the URDF is generated from them).
    cache_dir : path or None
        Cache of convex decompositions (:func:`convex_decomposition`).

    Returns
    -------
    LiftResult
        ``success``, ``displacement``, ``slip``, ``held_s`` and more; a grasp that closes on
        nothing is a failed result, not an exception.
    """
    check_mesh(mesh)
    if not isinstance(grasp, GraspResult):
        raise ValueError(f"grasp must be a GraspResult, got {type(grasp).__name__}")
    if not (math.isfinite(lift) and lift >= 0.0):
        raise ValueError(f"lift must be a finite distance >= 0 (metres), got {lift}")
    s = settings
    dt = s.time_step
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(s.shake_count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)

    palm = check_pose(grasp.palm_pose)
    spread = float(grasp.dofs_deg.spread)
    start = pregrasp_pose(palm, s.pregrasp_backoff)
    open_joints = [spread, 0.0, 0.0, spread, 0.0, 0.0, 0.0, 0.0]

    with DynamicWorld(
        mesh,
        friction=friction,
        density=density,
        table=table,
        settings=s,
        params=params,
        cache_dir=cache_dir,
    ) as world:
        if table:
            world.client.setGravity(0.0, 0.0, -9.81)
        world.place_hand(start, open_joints)
        fingers = world.fingers()

        def control() -> None:
            world.hold_spread(spread)
            world.drive_fingers(fingers)
            world.step()

        # approach: fingers held open
        n = max(1, math.ceil(s.pregrasp_backoff / s.approach_speed / dt))
        for i in range(1, n + 1):
            world.move_hand(pregrasp_pose(palm, s.pregrasp_backoff * (1.0 - i / n)))
            world.hold_spread(spread)
            for finger in fingers:
                world._position(finger.prox, 0.0, s.proximal_torque)
                world._position(finger.dist, 0.0, s.distal_torque)
            world.step()
        # close
        steps, settle_left = 0, round(s.close_settle / dt)
        while steps * dt < s.close_timeout and settle_left > 0:
            control()
            steps += 1
            if all(f.done for f in fingers):
                settle_left -= 1
        joints_deg = world.joint_values_deg()
        contacts = world.n_contacts()
        stops = tuple(f.stop for f in fingers)

        # reference: where the object sits in the hand
        def in_palm() -> np.ndarray:
            return _invert(world.palm_pose()) @ world.object_pose()

        reference = in_palm()
        world.client.setGravity(0.0, 0.0, -9.81)
        lifted = _shift(palm, np.array([0.0, 0.0, lift]))
        schedule = [("settle", s.settle_time, lambda t: palm)]
        lift_time = lift / s.lift_speed
        if lift > 0.0:
            schedule.append(
                ("lift", lift_time, lambda t: _shift(palm, [0, 0, lift * _smooth(t / lift_time)]))
            )
        schedule.append(("hold", s.hold_time, lambda t: lifted))
        if shake:
            period = 1.0 / s.shake_frequency
            for d in directions:
                schedule.append(
                    (
                        "shake",
                        period,
                        lambda t, d=d: _shift(
                            lifted, d * s.shake_amplitude * _smooth(2 * t / period)
                        ),
                    )
                )
            schedule.append(("shake", s.hold_time, lambda t: lifted))

        slip, held_s, phase, elapsed = 0.0, None, "held", 0.0
        current = reference
        for name, duration, target in schedule:
            for i in range(round(duration / dt)):
                world.move_hand(target((i + 1) * dt))
                control()
                elapsed += dt
                current = in_palm()
                distance = float(np.linalg.norm(current[:3, 3] - reference[:3, 3]))
                slip = max(slip, distance)
                if held_s is None and distance > s.hold_tolerance:
                    held_s, phase = elapsed, "lift" if name == "hold" else name
                if distance > s.drop_distance:
                    break
            else:
                continue
            break

    offset = reference[:3, :3].T @ (current[:3, 3] - reference[:3, 3])
    relative = reference[:3, :3].T @ current[:3, :3]
    rotation = math.degrees(Rotation.from_matrix(relative).magnitude())
    success = held_s is None
    if success:
        reason = "held through lift" + (" and shake" if shake else "")
    elif contacts == 0:
        reason = f"the hand closed on nothing; the object fell ({phase})"
    else:
        reason = f"the object left the hand during {phase} after {held_s:.2f} s"
    return LiftResult(
        success=success,
        reason=reason,
        displacement=float(np.linalg.norm(offset)),
        slip=slip,
        offset=offset,
        rotation_deg=rotation,
        held_s=elapsed if held_s is None else held_s,
        total_s=elapsed,
        phase=phase,
        finger_stops=stops,
        joints_deg=joints_deg,
        mass=world.mass,
        contacts=contacts,
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
        result = lift_test(
            mesh,
            grasp,
            seed=args.seed,
            lift=args.lift,
            shake=not args.no_shake,
            friction=args.friction,
            density=args.density,
            table=args.table,
        )
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
