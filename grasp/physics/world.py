"""The pybullet world of a lift test: a dynamic object and a free-base BarrettHand whose fingers
follow the Barrett closing controller (breakaway included)."""

from __future__ import annotations

import contextlib
import math
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from completion.bullet import direct_client, pose_to_pybullet, pybullet
from grasp.hand.collision import check_mesh, check_pose
from grasp.hand.quality import MU_RUBBER
from grasp.physics.body import convex_decomposition, mass_properties, shrink, write_pieces
from grasp.physics.fingers import FingerController
from grasp.physics.hand import JointInfo, load_hand
from grasp.physics.settings import (
    DEFAULT_SETTINGS,
    DENSITY_KG_M3,
    GRAVITY,
    MESH_MARGIN_M,
    LiftSettings,
)
from hands.barrett import BH8_282, FINGERS, JOINT_NAMES, BarrettParams


def _invert(pose: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = pose[:3, :3].T
    out[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return out


#: The object's, the neighbours' and the hand links' contact and damping settings beyond their
#: friction: anchored friction, no spinning or rolling friction, no damping.
_UNDAMPED = {"frictionAnchor": 1, "spinningFriction": 0.0, "rollingFriction": 0.0,
             "linearDamping": 0.0, "angularDamping": 0.0}


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
    table_top : float or None
        Put a static table (1 m square) whose top is the plane z = ``table_top``, centred under
        the object; None: no table.
    neighbours : sequence of trimesh.Trimesh
        Other objects on the table (world frame, at rest), dynamic bodies of the same density.
    settings : LiftSettings
    params : BarrettParams
    cache_dir : path or None
        Where the convex decomposition is cached (:func:`convex_decomposition`).

    The hand is carried by a fixed constraint to the world (:meth:`place_hand`, :meth:`move_hand`)
    and its fingers follow the Barrett closing controller (``controller``,
    :class:`grasp.physics.fingers.FingerController`). Gravity starts
    off; :meth:`gravity` switches it. Use as a context manager (or call :meth:`close`).
    """

    def __init__(
        self,
        mesh: trimesh.Trimesh,
        *,
        friction: float = MU_RUBBER,
        density: float = DENSITY_KG_M3,
        table_top: float | None = None,
        neighbours: Sequence[trimesh.Trimesh] = (),
        settings: LiftSettings = DEFAULT_SETTINGS,
        params: BarrettParams = BH8_282,
        cache_dir: str | Path | None = None,
    ) -> None:
        check_mesh(mesh)
        if not (math.isfinite(friction) and friction >= 0.0):
            raise ValueError(f"friction must be a finite coefficient >= 0, got {friction}")
        self.settings = settings
        self.params = params
        self._home: tuple[list[float], list[float]] | None = None
        self._constraint: int | None = None
        self._support: int | None = None

        self.client = direct_client()
        c = self.client
        try:
            c.setPhysicsEngineParameter(
                fixedTimeStep=settings.time_step,
                numSubSteps=0,
                numSolverIterations=settings.solver_iterations,
                deterministicOverlappingPairs=1,
            )
            self.gravity(False)
            self.object_id, self.mass = self._add_body(mesh, density, cache_dir)
            # other objects on the table, dynamic as the object (same density)
            self.neighbour_ids = [self._add_body(check_mesh(m), density, cache_dir)[0]
                                  for m in neighbours]
            self.table_id = None if table_top is None else self._add_table(mesh, table_top)
            self.hand_id, self.joints = self._load_hand(params, friction)
            # the base of a pybullet body is its inertial frame, not the URDF palm frame
            inertial = c.getDynamicsInfo(self.hand_id, -1)
            self._palm_in_base = c.invertTransform(inertial[3], inertial[4])
            self.controller = FingerController(c, self.hand_id, self.joints, settings, params)
        except Exception:
            c.disconnect()
            raise

    def _add_table(self, mesh: trimesh.Trimesh, table_top: float) -> int:
        """A static 1 m square table whose top is the plane z = ``table_top``, centred under
        ``mesh``; its body id."""
        c, half = self.client, [0.5, 0.5, 0.025]
        box = c.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half)
        centre = np.asarray(mesh.bounds).mean(axis=0)
        centre[2] = float(table_top) - half[2]
        table = c.createMultiBody(0.0, box, basePosition=centre.tolist())
        c.changeDynamics(table, -1, lateralFriction=self.settings.table_friction)
        return table

    def _load_hand(self, params: BarrettParams,
                   friction: float) -> tuple[int, dict[str, JointInfo]]:
        """The hand (:func:`grasp.physics.hand.load_hand`, free base), every link with
        ``friction`` and no damping; its body id and its joints by name."""
        c = self.client
        hand, joints = load_hand(c, params, fixed_base=False)
        for link in range(-1, c.getNumJoints(hand)):
            c.changeDynamics(hand, link, lateralFriction=float(friction), jointDamping=0.0,
                             **_UNDAMPED)
        return hand, joints

    def _add_body(self, mesh: trimesh.Trimesh, density: float,
                  cache_dir: str | Path | None) -> tuple[int, float]:
        """A dynamic body of ``mesh`` (its convex decomposition) where the mesh is, at rest; its
        id and mass."""
        _, pieces = convex_decomposition(mesh, cache_dir=cache_dir)
        mass, com, inertia = mass_properties(mesh, pieces, density)
        principal, axes = np.linalg.eigh(inertia)
        if np.linalg.det(axes) < 0:
            axes[:, 2] *= -1.0
        # the body frame: centre of mass and principal axes, placed in the mesh frame
        body = np.eye(4)
        body[:3, :3], body[:3, 3] = axes, com
        to_body = _invert(body)
        c = self.client
        # pybullet pads every convex hull by MESH_MARGIN_M: shrink the pieces by as much so
        # that the padded shape is the true one
        body_pieces = [
            shrink(piece, MESH_MARGIN_M) @ to_body[:3, :3].T + to_body[:3, 3] for piece in pieces
        ]
        with tempfile.TemporaryDirectory() as tmp:
            shape_path = Path(tmp) / "object.obj"
            write_pieces(shape_path, body_pieces)
            shape = c.createCollisionShape(pybullet.GEOM_MESH, fileName=str(shape_path))
        position, orientation = pose_to_pybullet(body)
        body_id = c.createMultiBody(
            baseMass=mass,
            baseCollisionShapeIndex=shape,
            basePosition=position,
            baseOrientation=orientation,
        )
        c.changeDynamics(
            body_id,
            -1,
            localInertiaDiagonal=np.maximum(principal, 1e-12).tolist(),
            lateralFriction=1.0,
            **_UNDAMPED,
        )
        return body_id, mass

    def neighbour_poses(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each neighbour's centre of mass (3,) and body axes (3, 3), world frame."""
        out = []
        for body in self.neighbour_ids:
            position, orientation = self.client.getBasePositionAndOrientation(body)
            rotation = np.array(self.client.getMatrixFromQuaternion(orientation)).reshape(3, 3)
            out.append((np.array(position), rotation))
        return out

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

    def finger_dofs_deg(self) -> np.ndarray:
        """(3,) each finger's DOF (degrees) as its motor encoder reads it: J2, or J3 / ratio once
        J3 ran ahead (after a breakaway)."""
        states = self.client.getJointStates(
            self.hand_id, [self.joints[f"{f}_{j}"].index for f in FINGERS for j in ("prox", "dist")]
        )
        angles = np.reshape([s[0] for s in states], (len(FINGERS), 2))
        return np.degrees(np.maximum(angles[:, 0], angles[:, 1] / self.params.distal_ratio))

    def n_contacts(self) -> int:
        """Number of hand–object contact points."""
        return len(self.client.getContactPoints(self.hand_id, self.object_id))

    def touches(self) -> bool:
        """Whether the hand touches the object, the table or a neighbour (what a wrist
        force-torque sensor feels during a guarded move)."""
        if self.n_contacts():
            return True
        others = [b for b in (self.table_id, *self.neighbour_ids) if b is not None]
        return any(self.client.getContactPoints(self.hand_id, b) for b in others)

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
        position, orientation = pose_to_pybullet(check_pose(palm_pose))
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

    def step(self) -> None:
        """Advance the simulation by one ``time_step``."""
        self.client.stepSimulation()
