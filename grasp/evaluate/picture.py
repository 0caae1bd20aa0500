"""The pybullet world of one object mesh and one BarrettHand.

:class:`GraspWorld` owns its pybullet client (DIRECT, one per object). The object is a static
concave triangle mesh, the hand is loaded from its generated URDF and placed kinematically (base
pose and joint states reset, no dynamics). The hand is loaded as the lift test loads it
(:func:`grasp.physics.hand.load_hand`). Used for pictures (:mod:`grasp.evaluate.render`) and to
cross-check the fcl collision scene the planner uses (:mod:`grasp.hand.collision`, built from the
same :class:`hands.barrett.HandKinematics`). pybullet tuples become named records
(:class:`grasp.physics.hand.JointInfo`, :class:`ClosestPoint`), and :meth:`GraspWorld.saved`
restores the world between trials.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from typing import NamedTuple

import numpy as np
import trimesh

from completion.bullet import direct_client, pose_to_pybullet, pybullet, pybullet_to_pose
from grasp.hand.collision import CONTACT_DISTANCE_M, CollisionScene, check_mesh, check_pose
from grasp.physics.hand import load_hand
from hands.barrett import BH8_282, JOINT_NAMES, BarrettParams


class ClosestPoint(NamedTuple):
    """One pair of closest points between a hand link and the object (world frame, metres)."""

    link: str
    point_on_hand: np.ndarray  # (3,)
    point_on_object: np.ndarray  # (3,)
    normal_on_object: np.ndarray  # (3,) from the object toward the hand
    distance: float  # negative when penetrating


class GraspWorld:
    """A pybullet world (its own DIRECT client) with one static object and one BarrettHand.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The object, world frame, metres. Loaded as a static concave triangle mesh
        (``GEOM_MESH`` with ``GEOM_FORCE_CONCAVE_TRIMESH``, mass 0).
    params : BarrettParams
        Hand dimensions; the URDF is generated from them.
    object_rgba : (4,) float
        Colour of the object in pictures.

    Use as a context manager (or call :meth:`close`) to disconnect the client.
    """

    def __init__(
        self,
        mesh: trimesh.Trimesh,
        *,
        params: BarrettParams = BH8_282,
        object_rgba: Sequence[float] = (0.85, 0.55, 0.3, 1.0),
    ) -> None:
        self.mesh = check_mesh(mesh)
        self.params = params
        self.client = direct_client()
        self._scene: CollisionScene | None = None
        try:
            vertices = np.asarray(mesh.vertices, dtype=np.float64).tolist()
            indices = np.asarray(mesh.faces, dtype=np.int32).ravel().tolist()
            collision = self.client.createCollisionShape(
                pybullet.GEOM_MESH,
                vertices=vertices,
                indices=indices,
                flags=pybullet.GEOM_FORCE_CONCAVE_TRIMESH,
            )
            visual = self.client.createVisualShape(
                pybullet.GEOM_MESH,
                vertices=vertices,
                indices=indices,
                normals=np.asarray(mesh.vertex_normals).tolist(),
                rgbaColor=list(object_rgba),
            )
            self.object_id = self.client.createMultiBody(
                baseMass=0.0, baseCollisionShapeIndex=collision, baseVisualShapeIndex=visual
            )
            self.hand_id, self.joints = load_hand(self.client, params, fixed_base=True)
        except Exception:
            self.client.disconnect()
            raise
        self.link_index: dict[str, int] = {"palm": -1}
        for record in self.joints.values():
            self.link_index[record.child_link] = record.index
        self.link_name = {index: name for name, index in self.link_index.items()}
        # pybullet pads concave meshes with a 1 mm margin; kinematic queries want true distances
        self.client.changeDynamics(self.object_id, -1, collisionMargin=0.0)
        for index in self.link_name:
            self.client.changeDynamics(self.hand_id, index, collisionMargin=0.0)
        # the base of a pybullet body is its inertial frame, not the URDF link frame
        local = self.client.getDynamicsInfo(self.hand_id, -1)
        self._palm_to_base = pybullet_to_pose(local[3], local[4])
        self.set_hand(np.eye(4), np.zeros(8))

    # -- lifetime --------------------------------------------------------------------------------
    def close(self) -> None:
        """Disconnect the pybullet client (idempotent)."""
        if self.client is not None:
            with contextlib.suppress(pybullet.error):
                self.client.disconnect()
            self.client = None

    def __enter__(self) -> GraspWorld:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def scene(self) -> CollisionScene:
        """The fcl :class:`CollisionScene` of the same mesh and hand (built on first use)."""
        if self._scene is None:
            self._scene = CollisionScene(self.mesh, params=self.params)
        return self._scene

    # -- the hand --------------------------------------------------------------------------------
    def set_hand(self, palm_pose: np.ndarray, joints_deg: Sequence[float]) -> None:
        """Place the hand kinematically: palm→world (4, 4) and 8 joint angles in degrees."""
        palm_pose = check_pose(palm_pose)
        q = np.asarray(joints_deg, dtype=np.float64)
        if q.shape != (8,):
            raise ValueError(f"joints_deg must have shape (8,), got {q.shape}")
        position, orientation = pose_to_pybullet(palm_pose @ self._palm_to_base)
        self.client.resetBasePositionAndOrientation(self.hand_id, position, orientation)
        for name, value in zip(JOINT_NAMES, np.radians(q), strict=True):
            self.client.resetJointState(self.hand_id, self.joints[name].index, float(value))

    def joint_values_deg(self) -> np.ndarray:
        """(8,) current joint angles in degrees, :data:`JOINT_NAMES` order."""
        states = self.client.getJointStates(
            self.hand_id, [self.joints[name].index for name in JOINT_NAMES]
        )
        return np.degrees([state[0] for state in states])

    def link_poses(self) -> dict[str, np.ndarray]:
        """Every hand link's URDF frame as link→world (4, 4)."""
        position, orientation = self.client.getBasePositionAndOrientation(self.hand_id)
        base = pybullet_to_pose(position, orientation)
        poses = {"palm": base @ np.linalg.inv(self._palm_to_base)}
        for name, index in self.link_index.items():
            if index < 0:
                continue
            state = self.client.getLinkState(self.hand_id, index, computeForwardKinematics=True)
            poses[name] = pybullet_to_pose(state[4], state[5])
        return poses

    def closest_points(self, max_distance: float = CONTACT_DISTANCE_M) -> list[ClosestPoint]:
        """Closest-point pairs between hand links and the object within ``max_distance`` (m)."""
        records = self.client.getClosestPoints(self.hand_id, self.object_id, max_distance)
        return [
            ClosestPoint(
                self.link_name[rec[3]],
                np.asarray(rec[5]),
                np.asarray(rec[6]),
                np.asarray(rec[7]),
                float(rec[8]),
            )
            for rec in records
        ]

    @contextlib.contextmanager
    def saved(self) -> Iterator[GraspWorld]:
        """Context manager: whatever happens inside, the world's state is restored on exit."""
        state = self.client.saveState()
        try:
            yield self
        finally:
            self.client.restoreState(stateId=state)
            self.client.removeState(state)

