"""Worlds holding one object mesh and one BarrettHand.

Two views of the same world, built from the same :class:`hands.barrett.HandKinematics`:

- :class:`GraspWorld`: a pybullet world that owns its client (DIRECT, one per object). The object
  is a static concave triangle mesh, the hand is loaded from its generated URDF and placed
  kinematically (base pose and joint states reset, no dynamics). Used for pictures, for physics
  built on top of it, and to cross-check the collision model.
- :class:`CollisionScene`: the fcl mirror that autograsp queries thousands of times per grasp. fcl
  answers "does this link overlap the mesh?" in ~10 µs with an early exit (OBBRSS tree over the
  triangles), where pybullet's ``getClosestPoints`` enumerates every overlapping triangle (~1.5 ms
  for a link pressed on a 20k-face sphere) and has no boolean query. A convex polytope around the
  object (a k-DOP: 106 support planes, an fcl ``Convex``; GJK distance ~20 µs) bounds the
  distance to the object from below, which lets autograsp take long safe steps through free
  space. (fcl's exact mesh distance would also do, but costs ~1 ms near a large surface.)
  With a :class:`SupportPlane` the table is an obstacle too: an fcl ``Halfspace`` (exact against
  boxes and cylinders, ~1 µs a query) in the same collision checks; contacts with it stop the
  hand but are not object contacts.

Both treat the object as a triangle soup, like GraspIt! and pybullet's concave meshes: a link that
is entirely inside a closed mesh without crossing its surface is not "in collision". Autograsp's
steps are small enough that a link cannot jump inside.

pybullet tuples become named records (:class:`JointInfo`, :class:`ClosestPoint`), and
:meth:`GraspWorld.saved` restores the world between trials.
"""

from __future__ import annotations

import contextlib
import copy
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import fcl
import numpy as np
import trimesh
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

from completion.bullet import direct_client, pose_to_pybullet, pybullet, pybullet_to_pose
from grasp.table import SupportPlane
from hands.barrett import BH8_282, JOINT_NAMES, LINK_NAMES, BarrettParams, HandKinematics
from hands.barrett.kinematics import Primitive

#: Two surfaces closer than this are in contact (GraspIt!: 0.2 mm).
CONTACT_DISTANCE_M = 2e-4
#: A contact patch (one link, like normals) keeps at most this many corner points.
MAX_CONTACTS_PER_PATCH = 4
#: Contact normals within this angle belong to one patch.
_PATCH_COS = float(np.cos(np.radians(10.0)))
#: A patch smaller than this across counts as a point contact (or a line if only narrower).
_POINT_PATCH_M = 0.010
#: Subtracted from GJK distances to the bounding polytope so that they stay lower bounds.
_GJK_SLACK_M = 2e-4
#: Directions (besides ±x, ±y, ±z) of the k-DOP that bounds the object for free-space steps.
_BOUND_DIRECTIONS = 100


# -- records ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Contact:
    """One hand–object contact, world frame, metres.

    ``normal`` is a unit vector pointing from the hand into the object: the direction of the
    normal force the link can exert.
    """

    link: str
    point: np.ndarray  # (3,)
    normal: np.ndarray  # (3,)


class JointInfo(NamedTuple):
    """The fields of ``getJointInfo`` that matter here (angles in radians)."""

    index: int
    name: str
    kind: int  # pybullet.JOINT_REVOLUTE or pybullet.JOINT_FIXED
    lower: float
    upper: float
    child_link: str


class ClosestPoint(NamedTuple):
    """One pair of closest points between a hand link and the object (world frame, metres)."""

    link: str
    point_on_hand: np.ndarray  # (3,)
    point_on_object: np.ndarray  # (3,)
    normal_on_object: np.ndarray  # (3,) from the object toward the hand
    distance: float  # negative when penetrating


def check_pose(pose: np.ndarray, name: str = "palm_pose") -> np.ndarray:
    """Return ``pose`` as a (4, 4) float array, or raise ValueError if it is not a rigid motion."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"{name} must be a finite (4, 4) array, got shape {pose.shape}")
    rot = pose[:3, :3]
    if (
        not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9)
        or not np.allclose(rot.T @ rot, np.eye(3), atol=1e-6)
        or np.linalg.det(rot) < 0
    ):
        raise ValueError(f"{name} must be a rigid transform (rotation + translation)")
    return pose


def check_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Raise ValueError unless ``mesh`` is a non-empty triangle mesh with finite vertices."""
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0 or not np.all(np.isfinite(mesh.vertices)):
        raise ValueError("the mesh must have at least one face and finite vertices")
    return mesh


def object_frame(mesh: trimesh.Trimesh) -> tuple[np.ndarray, float]:
    """Reference point and size for wrench torques: (centre (3,), max radius).

    The centre is the centre of mass for a watertight mesh, the surface centroid otherwise; the
    radius is the largest centre-to-vertex distance (hands/barrett/README.md, quality measures).
    """
    center = mesh.center_mass if mesh.is_volume else mesh.centroid
    center = np.asarray(center, dtype=np.float64)
    radius = float(np.max(np.linalg.norm(mesh.vertices - center, axis=1)))
    return center, max(radius, 1e-9)


def _fcl_geometry(prim: Primitive, inflate: float = 0.0):
    if prim.kind == "box":
        sx, sy, sz = (s + 2.0 * inflate for s in prim.size)
        return fcl.Box(sx, sy, sz)
    radius, length = prim.size
    return fcl.Cylinder(radius + inflate, length + 2.0 * inflate)


class _LinkShapes:
    """The fcl objects of one link: exact (for stepping) and inflated (to gather contacts)."""

    def __init__(self, prims: Sequence[Primitive], inflate: float) -> None:
        self.local = [prim.pose for prim in prims]
        self.exact = [fcl.CollisionObject(_fcl_geometry(prim)) for prim in prims]
        self.inflated = [fcl.CollisionObject(_fcl_geometry(prim, inflate)) for prim in prims]
        # (n, 8, 3) bounding-box corners in the link frame, to bound how fast the link moves
        self.corners = np.concatenate([prim.corners() for prim in prims])


class CollisionScene:
    """fcl collision model of one object mesh and the BarrettHand's primitives.

    Build one per mesh and reuse it for every grasp on that mesh (building the OBBRSS tree costs
    ~0.1 s for 20k faces; a query costs ~10 µs).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The object, world frame, metres. Any triangle soup (need not be watertight).
    params : BarrettParams
        Hand dimensions.
    contact_distance : float
        Surfaces closer than this (metres) are reported as contacts.
    support_plane : SupportPlane or None
        The table under the object: the hand collides with the half-space below it too
        (:meth:`with_support_plane` adds one to a built scene).
    """

    def __init__(
        self,
        mesh: trimesh.Trimesh,
        *,
        params: BarrettParams = BH8_282,
        contact_distance: float = CONTACT_DISTANCE_M,
        support_plane: SupportPlane | None = None,
    ) -> None:
        self.mesh = check_mesh(mesh)
        if not contact_distance > 0.0:
            raise ValueError(f"contact_distance must be positive, got {contact_distance}")
        self.kinematics = HandKinematics(params)
        self.contact_distance = contact_distance
        vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        faces = np.ascontiguousarray(mesh.faces, dtype=np.int32)
        bvh = fcl.BVHModel()
        bvh.beginModel(len(vertices), len(faces))
        bvh.addSubModel(vertices, faces)
        bvh.endModel()
        self._object = fcl.CollisionObject(bvh, fcl.Transform())
        self._hull = self._bounding_polytope(mesh)
        self.center, self.max_radius = object_frame(mesh)
        self.links = {
            link: _LinkShapes(self.kinematics.primitives_of(link), contact_distance)
            for link in LINK_NAMES
        }
        self._bool_request = fcl.CollisionRequest()
        self._contact_request = fcl.CollisionRequest(num_max_contacts=256, enable_contact=True)
        self._distance_request = fcl.DistanceRequest()
        self._set_table(support_plane)

    def _set_table(self, plane: SupportPlane | None) -> None:
        if plane is not None and not isinstance(plane, SupportPlane):
            raise ValueError(f"support_plane must be a SupportPlane or None, got {type(plane)}")
        self.support_plane = plane
        self._table = None
        if plane is not None:  # fcl's Halfspace(n, d) is {x : n·x <= d}
            shape = fcl.Halfspace(plane.normal, -plane.offset)
            self._table = fcl.CollisionObject(shape, fcl.Transform())

    def with_support_plane(self, plane: SupportPlane | None) -> CollisionScene:
        """This scene with ``plane`` as the table (None: without one), sharing the object's
        collision model (no rebuild)."""
        if plane is self.support_plane:
            return self
        out = copy.copy(self)
        out._set_table(plane)
        return out

    @staticmethod
    def _bounding_polytope(mesh: trimesh.Trimesh):
        """fcl ``Convex`` of a k-DOP around the mesh (None for a flat or degenerate mesh)."""
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        directions = np.vstack([np.eye(3), -np.eye(3), fibonacci_directions(_BOUND_DIRECTIONS)])
        support = (vertices @ directions.T).max(axis=0) + 1e-6  # strictly outside the mesh
        try:
            corners = HalfspaceIntersection(
                np.hstack([directions, -support[:, None]]), vertices.mean(axis=0)
            ).intersections
            faces = ConvexHull(corners).simplices
        except (QhullError, ValueError):  # flat mesh: no interior point, no free-space bound
            return None
        flat = np.hstack([np.full((len(faces), 1), 3), faces]).ravel()
        return fcl.CollisionObject(fcl.Convex(corners, len(faces), flat), fcl.Transform())

    # -- queries ---------------------------------------------------------------------------------
    def link_collides(self, link: str, link_to_world: np.ndarray) -> bool:
        """Whether ``link`` at pose ``link_to_world`` (4, 4) overlaps the object's surface or
        reaches below the table."""
        shapes = self.links[link]
        table = self._table
        for local, obj in zip(shapes.local, shapes.exact, strict=True):
            pose = link_to_world @ local
            obj.setTransform(fcl.Transform(pose[:3, :3], pose[:3, 3]))
            if fcl.collide(obj, self._object, self._bool_request, fcl.CollisionResult()):
                return True
            if table is not None and fcl.collide(
                obj, table, self._bool_request, fcl.CollisionResult()
            ):
                return True
        return False

    def colliding_links(self, link_poses: Mapping[str, np.ndarray]) -> list[str]:
        """Names of the links (keys of ``link_poses``, link→world (4, 4)) overlapping the object
        or the table."""
        return [link for link, pose in link_poses.items() if self.link_collides(link, pose)]

    def table_distance(self, link: str, link_to_world: np.ndarray) -> float:
        """Lower bound on the height (m) of ``link`` above the table (inf without one): its
        primitives' bounding-box corners."""
        if self.support_plane is None:
            return np.inf
        corners = self.links[link].corners
        world = corners @ link_to_world[:3, :3].T + link_to_world[:3, 3]
        return max(float(self.support_plane.height(world).min()), 0.0)

    def hull_distance(self, link: str, link_to_world: np.ndarray) -> float:
        """Lower bound on the distance (m) from ``link`` to the object and the table; 0 if
        unknown or touching.

        It is the exact distance to a convex polytope that contains the object (and a lower
        bound on the height above the table).
        """
        if self._hull is None:
            return 0.0
        shapes = self.links[link]
        best = self.table_distance(link, link_to_world)
        if best <= 0.0:
            return 0.0
        for local, obj in zip(shapes.local, shapes.exact, strict=True):
            pose = link_to_world @ local
            obj.setTransform(fcl.Transform(pose[:3, :3], pose[:3, 3]))
            dist = fcl.distance(obj, self._hull, self._distance_request, fcl.DistanceResult())
            best = min(best, dist - _GJK_SLACK_M)  # GJK on cylinders is ~µm approximate
            if best <= 0.0:
                return 0.0
        return float(best)

    def hand_link_poses(self, palm_pose: np.ndarray, joints_rad: Sequence[float]):
        """Every link→world (4, 4) pose for a palm pose and 8 joint angles (radians)."""
        return {
            link: palm_pose @ pose for link, pose in self.kinematics.link_poses(joints_rad).items()
        }

    def hand_collides(self, palm_pose: np.ndarray, joints_rad: Sequence[float]) -> bool:
        """Whether any link of the hand overlaps the object (or the table)."""
        poses = self.hand_link_poses(check_pose(palm_pose), joints_rad)
        return any(self.link_collides(link, pose) for link, pose in poses.items())

    def contacts(
        self, link_poses: Mapping[str, np.ndarray], *, max_per_patch: int = MAX_CONTACTS_PER_PATCH
    ) -> list[Contact]:
        """Contacts between the given links (link→world (4, 4)) and the object (never the
        table: it stops the hand but takes no part in the grasp's quality).

        A link is in contact where it comes within ``contact_distance`` of the surface (its
        primitives are inflated by that much). fcl reports one contact per touching triangle;
        per link they are grouped into patches of like normals (within 10°), and each patch is
        reduced to a point, a line (2 points) or the corners of its outline (at most
        ``max_per_patch``), with the patch's mean normal. For a fixed force direction a contact's
        wrenches are linear in its position, so the corners span the wrench hull of the patch.
        """
        out: list[Contact] = []
        for link, link_pose in link_poses.items():
            shapes = self.links[link]
            points, normals = [], []
            for local, obj in zip(shapes.local, shapes.inflated, strict=True):
                pose = link_pose @ local
                obj.setTransform(fcl.Transform(pose[:3, :3], pose[:3, 3]))
                result = fcl.CollisionResult()
                if not fcl.collide(obj, self._object, self._contact_request, result):
                    continue
                pos = np.array([c.pos for c in result.contacts], dtype=np.float64)  # (m, 3)
                nrm = np.array([c.normal for c in result.contacts], dtype=np.float64)
                length = np.linalg.norm(nrm, axis=1)
                pos, nrm = pos[length > 0.0], nrm[length > 0.0] / length[length > 0.0, None]
                # fcl's sign convention depends on the pair; the force points from the
                # primitive's inside toward the contact
                outward = np.einsum("ij,ij->i", nrm, pos - pose[:3, 3]) < 0.0
                nrm[outward] *= -1.0
                points.extend(pos)
                normals.extend(nrm)
            if points:
                for point, normal in _patches(np.array(points), np.array(normals), max_per_patch):
                    out.append(Contact(link, point, normal))
        return out


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (golden-angle spiral)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _patches(points: np.ndarray, normals: np.ndarray, k: int) -> list[tuple[np.ndarray, ...]]:
    """Reduce (n, 3) contact points and unit normals to patch corners with mean normals."""
    out = []
    remaining = np.arange(len(points))
    while remaining.size:
        alike = normals[remaining] @ normals[remaining[0]] > _PATCH_COS
        members, remaining = remaining[alike], remaining[~alike]
        normal = normals[members].mean(axis=0)
        normal /= np.linalg.norm(normal)
        out.extend((point, normal) for point in _outline(points[members], k))
    return out


def _outline(points: np.ndarray, k: int) -> list[np.ndarray]:
    """Representative points of one contact patch of (n, 3) ``points``.

    A patch whose extent is under ``_POINT_PATCH_M`` becomes one point (its mean), a patch
    narrower than that a line (its two ends along the long axis), anything wider the corners of
    its outline (at most ``k``, farthest-point subset). The 0.2 mm contact band turns a touching
    sphere or cylinder into a patch a few millimetres wide; this undoes that.
    """
    if len(points) == 1 or np.ptp(points, axis=0).max() < _POINT_PATCH_M / 2:
        return [points.mean(axis=0)]
    centred = points - points.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    along = centred @ axes[:2].T  # (n, 2) coordinates along the patch's principal axes
    extent = np.ptp(along, axis=0)
    if extent[0] < _POINT_PATCH_M:
        return [points.mean(axis=0)]
    if extent[1] < _POINT_PATCH_M:
        return [points[int(np.argmin(along[:, 0]))], points[int(np.argmax(along[:, 0]))]]
    corners = ConvexHull(along, qhull_options="QJ").vertices
    pts = along[corners]
    # farthest-point sampling from the corner farthest from the centroid (rigid-motion invariant)
    chosen = [int(np.argmax(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    while len(chosen) < min(k, len(pts)):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[nxt], axis=1))
    return [points[corners[i]] for i in chosen]


# -- pybullet world ----------------------------------------------------------------------------
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
        from hands.barrett.urdf import urdf_string

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
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / "barrett.urdf"
                path.write_text(urdf_string(params))
                self.hand_id = self.client.loadURDF(
                    str(path),
                    useFixedBase=True,
                    flags=pybullet.URDF_USE_INERTIA_FROM_FILE | pybullet.URDF_USE_IMPLICIT_CYLINDER,
                )
        except Exception:
            self.client.disconnect()
            raise
        self.joints: dict[str, JointInfo] = {}
        self.link_index: dict[str, int] = {"palm": -1}
        for index in range(self.client.getNumJoints(self.hand_id)):
            info = self.client.getJointInfo(self.hand_id, index)
            record = JointInfo(
                index, info[1].decode(), info[2], info[8], info[9], info[12].decode()
            )
            self.joints[record.name] = record
            self.link_index[record.child_link] = index
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
