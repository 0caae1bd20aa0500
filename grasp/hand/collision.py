"""The fcl collision scene autograsp queries: one object mesh, one BarrettHand, maybe a table.

:class:`CollisionScene` answers "does this link overlap the mesh?" in ~10 µs with an early exit
(python-fcl, an OBBRSS tree over the triangles), where pybullet's ``getClosestPoints``
enumerates every overlapping triangle (~1.5 ms for a link pressed on a 20k-face sphere) and has
no boolean query. A convex polytope around the object (a k-DOP: 106 support planes, an fcl
``Convex``; GJK distance ~20 µs) bounds the distance to the object from below, which lets
autograsp take long safe steps through free space. (fcl's exact mesh distance would also do, but
costs ~1 ms near a large surface.) With a :class:`SupportPlane` the table is an obstacle too: an
fcl ``Halfspace`` (exact against boxes and cylinders, ~1 µs a query) in the same collision
checks; contacts with it stop the hand but are not object contacts.

The object is a triangle soup, as in GraspIt! and pybullet's concave meshes: a link entirely
inside a closed mesh without crossing its surface is not "in collision"; autograsp's steps are
small enough that a link cannot jump inside. This is the planner's hot path and imports no
pybullet: the pybullet world of the same object and hand (pictures, physics, a cross-check) is
:mod:`grasp.evaluate.picture`.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import fcl
import numpy as np
import trimesh
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

from grasp_client.wire import SupportPlane
from hands.barrett import BH8_282, LINK_NAMES, BarrettParams, HandKinematics
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
