"""grasp.evaluate.picture and grasp.hand.collision: the pybullet GraspWorld and its fcl mirror
CollisionScene agree with each other."""

from __future__ import annotations

import numpy as np
import pybullet
import pytest
import trimesh
from grasp_scenes import box, mug
from scipy.spatial.transform import Rotation

from grasp.evaluate.picture import GraspWorld
from grasp.hand.collision import CollisionScene, check_mesh, check_pose
from hands.barrett import JOINT_NAMES, HandKinematics


def random_pose(rng: np.random.Generator, scale: float = 0.1) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    pose[:3, 3] = rng.uniform(-scale, scale, 3)
    return pose


def random_joints_deg(rng: np.random.Generator) -> np.ndarray:
    spread = rng.uniform(0, 180)
    f = rng.uniform(0, 140, 3)
    return np.array([spread, f[0], f[0] / 3, spread, f[1], f[1] / 3, f[2], f[2] / 3])


@pytest.fixture(scope="module")
def mug_world():
    with GraspWorld(mug()) as world:
        yield world


def test_object_is_static_concave_mesh(mug_world):
    client = mug_world.client
    assert client.getDynamicsInfo(mug_world.object_id, -1)[0] == 0.0  # mass 0: static
    (shape,) = client.getCollisionShapeData(mug_world.object_id, -1)
    assert shape[2] == pybullet.GEOM_MESH
    # a ball inside the cup touches nothing; a convex hull of the mug would swallow it
    ball = client.createMultiBody(
        baseMass=0.0,
        baseCollisionShapeIndex=client.createCollisionShape(pybullet.GEOM_SPHERE, radius=0.02),
        basePosition=[0.0, 0.0, 0.06],
    )
    try:
        assert client.getClosestPoints(ball, mug_world.object_id, 0.0) == ()
        assert client.getClosestPoints(ball, mug_world.object_id, 0.02)  # the wall is near
    finally:
        client.removeBody(ball)


def test_worlds_own_their_clients():
    a = GraspWorld(box((0.05, 0.05, 0.05), (0, 0, 0.1)))
    b = GraspWorld(box((0.05, 0.05, 0.05), (0, 0, 0.1)))
    assert a.client._client != b.client._client
    a.set_hand(np.eye(4), [10, 20, 5, 10, 0, 0, 0, 0])
    np.testing.assert_allclose(b.joint_values_deg(), np.zeros(8), atol=1e-12)
    a.close()
    a.close()  # idempotent
    b.set_hand(np.eye(4), np.zeros(8))  # b still works
    assert b.closest_points(1.0)
    b.close()


def test_set_hand_places_links_like_the_kinematics(mug_world):
    rng = np.random.default_rng(0)
    kin = HandKinematics()
    for _ in range(3):
        palm, joints = random_pose(rng), random_joints_deg(rng)
        mug_world.set_hand(palm, joints)
        np.testing.assert_allclose(mug_world.joint_values_deg(), joints, atol=1e-9)
        got = mug_world.link_poses()
        for link, pose in kin.link_poses(np.radians(joints)).items():
            np.testing.assert_allclose(got[link], palm @ pose, atol=1e-6, err_msg=link)


def test_saved_restores_the_world_even_after_an_error(mug_world):
    palm = np.eye(4)
    palm[2, 3] = -0.2
    joints = [30, 40, 13, 30, 50, 16, 60, 20]
    mug_world.set_hand(palm, joints)
    before = mug_world.link_poses()
    with pytest.raises(RuntimeError), mug_world.saved():
        mug_world.set_hand(np.eye(4), np.zeros(8))
        raise RuntimeError("trial failed")
    np.testing.assert_allclose(mug_world.joint_values_deg(), joints, atol=1e-9)
    for link, pose in mug_world.link_poses().items():
        np.testing.assert_allclose(pose, before[link], atol=1e-9)


def test_closest_points_are_named_records(mug_world):
    palm = np.eye(4)
    palm[2, 3] = -0.005  # palm face 5 mm under the mug's bottom
    mug_world.set_hand(palm, np.zeros(8))
    points = mug_world.closest_points(0.01)
    assert points and {p.link for p in points} <= set(mug_world.link_index)
    palm_points = [p for p in points if p.link == "palm"]
    assert min(p.distance for p in palm_points) == pytest.approx(0.005, abs=1e-6)
    np.testing.assert_allclose(palm_points[0].normal_on_object, [0, 0, -1], atol=1e-6)


def test_fcl_scene_agrees_with_pybullet(mug_world):
    """Random hand placements around the mug: fcl's overlap test matches pybullet's distances."""
    scene = mug_world.scene
    rng = np.random.default_rng(1)
    checked = {True: 0, False: 0}
    for _ in range(60):
        palm = random_pose(rng, 0.12)
        joints = random_joints_deg(rng)
        mug_world.set_hand(palm, joints)
        fcl_links = scene.hand_link_poses(palm, np.radians(joints))
        for link, index in mug_world.link_index.items():
            records = mug_world.client.getClosestPoints(
                mug_world.hand_id, mug_world.object_id, 0.05, linkIndexA=index
            )
            distance = min((r[8] for r in records), default=np.inf)
            collides = scene.link_collides(link, fcl_links[link])
            if distance < -1e-3:
                assert collides, (link, distance)
                checked[True] += 1
            elif distance > 1e-3:
                assert not collides, (link, distance)
                checked[False] += 1
                # the bounding polytope's distance never exceeds the true distance
                assert scene.hull_distance(link, fcl_links[link]) <= distance + 1e-6
    assert checked[True] > 10 and checked[False] > 100


def test_contacts_of_a_box_resting_on_the_palm():
    """A 40 mm cube on the palm face: one patch, 4 corners on the face, normal along +z."""
    scene = CollisionScene(box((0.04, 0.04, 0.04), (0.0, 0.0, 0.02 + 5e-5)))
    poses = scene.hand_link_poses(np.eye(4), np.zeros(8))
    contacts = scene.contacts(poses)
    assert {c.link for c in contacts} == {"palm"}
    assert len(contacts) == 4
    points = np.array([c.point for c in contacts])
    np.testing.assert_allclose(points[:, 2], 0.0, atol=3e-4)
    np.testing.assert_allclose(np.abs(points[:, :2]), 0.02, atol=1e-3)  # the cube's corners
    for c in contacts:
        np.testing.assert_allclose(c.normal, [0, 0, 1], atol=1e-6)
    # lifted by 1 mm (more than the 0.2 mm contact distance): no contact
    far = CollisionScene(box((0.04, 0.04, 0.04), (0.0, 0.0, 0.021)))
    assert far.contacts(far.hand_link_poses(np.eye(4), np.zeros(8))) == []


def test_input_checks():
    with pytest.raises(ValueError, match="rigid"):
        check_pose(np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        check_pose(np.eye(3))
    with pytest.raises(ValueError, match="at least one face"):
        check_mesh(trimesh.Trimesh())
    with pytest.raises(ValueError, match="trimesh"):
        check_mesh("mesh.obj")  # type: ignore[arg-type]
    with GraspWorld(box((0.05, 0.05, 0.05), (0, 0, 0.1))) as world:
        with pytest.raises(ValueError, match=r"\(8,\)"):
            world.set_hand(np.eye(4), np.zeros(7))
    assert len(JOINT_NAMES) == 8
