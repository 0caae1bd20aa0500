"""hands.barrett: parameters, kinematics, coupling and the generated URDF (loaded in pybullet)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pybullet
import pytest
from pybullet_utils import bullet_client

from hands.barrett import (
    BH8_282,
    JOINT_NAMES,
    LINK_NAMES,
    BarrettParams,
    HandKinematics,
    finger_joints_deg,
    joints_from_dofs,
)
from hands.barrett.urdf import SHIPPED_URDF, urdf_string, write_urdf


def test_params_are_frozen_and_follow_barrett_md_first_column():
    with pytest.raises(dataclasses.FrozenInstanceError):
        BH8_282.palm_radius = 0.05  # type: ignore[misc]
    p = BH8_282
    # hands/barrett/README.md, first column (mm and degrees)
    assert p.palm_radius == pytest.approx(0.0445)
    assert p.spread_axis_x == pytest.approx(0.025)
    assert p.base_to_proximal == pytest.approx(0.050)
    assert p.proximal_length == pytest.approx(0.070)
    assert p.distal_length == pytest.approx(0.055)
    assert p.distal_bend_deg == 40.0  # not the DH table's 42 or the URDF's 45
    assert (p.spread_max_deg, p.proximal_max_deg, p.distal_max_deg) == (180.0, 140.0, 48.0)
    assert p.distal_ratio == pytest.approx(1.0 / 3.0)


def test_params_reject_bad_values():
    with pytest.raises(ValueError, match="positive"):
        BarrettParams(proximal_length=0.0)
    with pytest.raises(ValueError, match="distal joint limit"):
        BarrettParams(finger_dof_max_deg=150.0)  # 150/3 > 48


def test_palm_frame_matches_design():
    """Palm face z = 0, fingers 1/2 spread about x = ±25 mm, finger 3's J2 at y = −50 mm."""
    kin = HandKinematics()
    poses = kin.link_poses(np.zeros(8))
    np.testing.assert_allclose(poses["f1_knuckle"][:3, 3], [0.025, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(poses["f2_knuckle"][:3, 3], [-0.025, 0.0, 0.0], atol=1e-12)
    # J2 axes: fingers 1 and 2 at +50 mm in y (opposite finger 3) at spread 0
    np.testing.assert_allclose(poses["f1_prox"][:3, 3], [0.025, 0.05, 0.0], atol=1e-12)
    np.testing.assert_allclose(poses["f2_prox"][:3, 3], [-0.025, 0.05, 0.0], atol=1e-12)
    np.testing.assert_allclose(poses["f3_prox"][:3, 3], [0.0, -0.05, 0.0], atol=1e-12)
    # the palm body lies below the face, the face is z = 0
    (palm,) = kin.primitives_of("palm")
    corners = palm.corners()
    assert corners[:, 2].max() == pytest.approx(0.0) and corners[:, 2].min() == pytest.approx(-0.08)


def test_spread_is_mirror_image_and_closing_turns_toward_plus_z():
    kin = HandKinematics()
    q = np.radians([90, 0, 0, 90, 0, 0, 0, 0])
    poses = kin.link_poses(q)
    # spread 90°: fingers 1 and 2 face each other along x
    np.testing.assert_allclose(poses["f1_prox"][:3, 3], [0.075, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(poses["f2_prox"][:3, 3], [-0.075, 0.0, 0.0], atol=1e-12)
    mirror = np.diag([-1.0, 1.0, 1.0])
    for spread in (0.0, 30.0, 125.0, 180.0):
        p = kin.link_poses(np.radians([spread, 40, 13, spread, 40, 13, 0, 0]))
        np.testing.assert_allclose(mirror @ p["f1_dist"][:3, 3], p["f2_dist"][:3, 3], atol=1e-12)
    # J2 = 90°: the proximal link points along the approach axis
    up = kin.link_poses(np.radians([0, 90, 0, 0, 90, 0, 90, 0]))
    for finger in ("f1", "f2", "f3"):
        np.testing.assert_allclose(up[f"{finger}_prox"][:3, 0], [0, 0, 1], atol=1e-12)


def test_open_fingertip_follows_link_lengths_and_distal_bend():
    """Open hand: tip of finger 3 = J2 + 70 mm out + 55 mm at the fixed 40° bend."""
    kin = HandKinematics()
    dist = kin.link_poses(np.zeros(8))["f3_dist"]
    tip = dist @ np.array([BH8_282.distal_length, 0.0, 0.0, 1.0])
    bend = np.radians(40.0)
    expected_r = 0.05 + 0.07 + 0.055 * np.cos(bend)
    np.testing.assert_allclose(tip[:3], [0.0, -expected_r, 0.055 * np.sin(bend)], atol=1e-12)


def test_coupling_and_breakaway():
    assert finger_joints_deg(90.0) == pytest.approx((90.0, 30.0))
    assert finger_joints_deg(120.0, proximal_stop_deg=50.0) == pytest.approx((50.0, 40.0))
    joints = joints_from_dofs([30.0, 60.0, 90.0, 140.0], proximal_stops_deg=(None, 20.0, None))
    np.testing.assert_allclose(joints, [30, 60, 20, 30, 20, 30, 140, 140 / 3])
    # the distal limit is never exceeded through the coupling
    assert finger_joints_deg(BH8_282.finger_dof_max_deg)[1] <= BH8_282.distal_max_deg
    with pytest.raises(ValueError, match="finger DOF"):
        finger_joints_deg(141.0)
    with pytest.raises(ValueError, match="spread"):
        joints_from_dofs([181.0, 0, 0, 0])
    with pytest.raises(ValueError, match="shape"):
        joints_from_dofs([0.0, 0.0])


def test_shipped_urdf_is_current():
    """hands/barrett/bh8_282.urdf must equal the generator's output.

    After changing BarrettParams or the kinematics on purpose, regenerate it with
    ``python -m hands.barrett.urdf --out hands/barrett/bh8_282.urdf``.
    """
    assert SHIPPED_URDF.read_text() == urdf_string(), (
        "bh8_282.urdf is stale: run python -m hands.barrett.urdf --out hands/barrett/bh8_282.urdf"
    )


@pytest.fixture(scope="module")
def loaded_hand(tmp_path_factory):
    path = write_urdf(tmp_path_factory.mktemp("urdf") / "hand.urdf")
    client = bullet_client.BulletClient(connection_mode=pybullet.DIRECT)
    hand = client.loadURDF(str(path), useFixedBase=True, flags=pybullet.URDF_USE_IMPLICIT_CYLINDER)
    yield client, hand
    client.disconnect()


def test_urdf_loads_with_joints_and_limits(loaded_hand):
    client, hand = loaded_hand
    infos = [client.getJointInfo(hand, i) for i in range(client.getNumJoints(hand))]
    revolute = {info[1].decode(): info for info in infos if info[2] == pybullet.JOINT_REVOLUTE}
    assert sorted(revolute) == sorted(JOINT_NAMES)
    fixed = [info[1].decode() for info in infos if info[2] == pybullet.JOINT_FIXED]
    assert fixed == ["f3_base"]
    links = {"palm"} | {info[12].decode() for info in infos}
    assert links == set(LINK_NAMES)
    limits = {"spread": 180.0, "prox": 140.0, "dist": 48.0}
    for name, info in revolute.items():
        assert info[8] == pytest.approx(0.0)
        assert info[9] == pytest.approx(np.radians(limits[name.split("_")[1]]))
    # collision geometry from primitives: the palm is one cylinder r = 44.5 mm, 80 mm long
    (palm,) = client.getCollisionShapeData(hand, -1)
    assert palm[2] == pybullet.GEOM_CYLINDER
    assert palm[3][:2] == pytest.approx((0.08, 0.0445))


def test_urdf_link_frames_equal_kinematics(loaded_hand):
    """pybullet's forward kinematics of the URDF = HandKinematics.link_poses, random joints."""
    client, hand = loaded_hand
    kin = HandKinematics()
    index = {client.getJointInfo(hand, i)[1].decode(): i for i in range(client.getNumJoints(hand))}
    child = {client.getJointInfo(hand, i)[12].decode(): i for i in range(client.getNumJoints(hand))}
    rng = np.random.default_rng(3)
    upper = np.radians([180, 140, 48, 180, 140, 48, 140, 48])
    for _ in range(5):
        q = rng.uniform(0.0, upper)
        for name, value in zip(JOINT_NAMES, q, strict=True):
            client.resetJointState(hand, index[name], float(value))
        expected = kin.link_poses(q)
        for link, pose in expected.items():
            if link == "palm":
                continue
            state = client.getLinkState(hand, child[link], computeForwardKinematics=True)
            rot = np.array(client.getMatrixFromQuaternion(state[5])).reshape(3, 3)
            np.testing.assert_allclose(state[4], pose[:3, 3], atol=1e-6, err_msg=link)
            np.testing.assert_allclose(rot, pose[:3, :3], atol=1e-6, err_msg=link)


def test_link_poses_rejects_wrong_shape():
    with pytest.raises(ValueError, match=r"\(8,\)"):
        HandKinematics().link_poses(np.zeros(4))
