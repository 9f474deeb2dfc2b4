"""Forward and inverse kinematics of the ZX120, for our URDF and for OPERA's."""
import math
from pathlib import Path

import numpy as np
import pytest

from opera_taichi.kinematics import Kinematics
from opera_taichi.machine_description import load_machine

from conftest import ON_CI, SHARED

OPERA_URDF = SHARED / "opera" / "zx120_description" / "urdf" / "zx120.urdf"
MACHINES = ["zx120", pytest.param(OPERA_URDF, marks=pytest.mark.skipif(
    not OPERA_URDF.is_file() and not ON_CI, reason="OPERA's zx120_description is not in ../shared (OPERA_TAICHI_SHARED)"))]
PHYSX_POSE = {"boom_joint": math.radians(-46), "arm_joint": math.radians(114), "bucket_joint": math.radians(46)}
ARM_JOINTS = ["boom_joint", "arm_joint", "bucket_joint"]


@pytest.fixture(scope="module", params=MACHINES, ids=["ours", "opera"])
def kin(request):
    return Kinematics(load_machine(request.param))


def test_tip_at_reference_poses(kin):
    # reference/zx120.yaml workspace_derived_v2: all zero, and OPERA PhysX's initial targets
    assert kin.tip_position({}) == pytest.approx([8.489, -0.164, 1.424], abs=0.01)
    assert kin.tip_position(PHYSX_POSE) == pytest.approx([3.779, -0.164, 1.274], abs=0.01)
    assert kin.link_pose({}, "bucket_end_link")[:3, 3] == pytest.approx(kin.tip_position({}))


def test_swing_turns_the_arm_to_the_left(kin):
    tip = kin.tip_position({**PHYSX_POSE, "swing_joint": math.pi / 2})
    assert tip[1] == pytest.approx(3.779, abs=0.01)        # the reach, now along +y
    assert abs(tip[0]) < 0.2                               # only the boom foot's 0.164 m side offset
    assert tip[2] == pytest.approx(1.274, abs=0.01)


def test_bucket_angle_follows_the_joint_sum_in_the_arm_plane(kin):
    # boom, arm and bucket all turn about parallel horizontal axes, so the pin -> edge direction below
    # the horizontal is their sum, whatever the swing
    assert kin.bucket_angle({}) == pytest.approx(0.0, abs=1e-9)
    for swing in (0.0, 1.0, -2.5):
        assert kin.bucket_angle({**PHYSX_POSE, "swing_joint": swing}) == pytest.approx(math.radians(114))
    curled = {"boom_joint": -0.5, "arm_joint": 1.5, "bucket_joint": 2.4}
    assert kin.bucket_angle(curled) == pytest.approx(3.4)             # past pi: curled up, no wrap
    dumped = {"boom_joint": -1.0, "arm_joint": 0.6, "bucket_joint": -0.5}
    assert kin.bucket_angle(dumped) == pytest.approx(-0.9)            # edge raised ahead of the pin


def test_inverse_kinematics_round_trip(kin):
    limits = kin.desc.joint_limits
    rng = np.random.default_rng(7)
    for _ in range(25):
        q = {"swing_joint": rng.uniform(-math.pi, math.pi), **{n: rng.uniform(*limits[n]) for n in ARM_JOINTS}}
        target, angle = kin.tip_position(q), kin.bucket_angle(q)
        solution = kin.solve_tip(target, angle)
        assert np.linalg.norm(kin.tip_position(solution) - target) < 1e-3
        assert abs(kin.bucket_angle(solution) - angle) < math.radians(0.5)
        for name in ARM_JOINTS:
            assert limits[name][0] - 1e-9 <= solution[name] <= limits[name][1] + 1e-9


def test_inverse_kinematics_uses_the_guess_and_refuses_the_unreachable(kin):
    q = {**PHYSX_POSE, "swing_joint": 0.4}
    solution = kin.solve_tip(kin.tip_position(q), kin.bucket_angle(q), q_guess=q)
    assert [solution[n] for n in q] == pytest.approx([q[n] for n in q], abs=1e-5)
    with pytest.raises(ValueError, match="unreachable"):
        kin.solve_tip([12.0, 0.0, 0.0], math.pi / 2)                 # beyond boom + arm + bucket (8.35 m)
    with pytest.raises(ValueError, match="unreachable"):
        # boom pin -> bucket pin would be 7.34 m, more than boom + arm (7.12 m)
        kin.solve_tip([7.2, -0.164, 1.2], math.radians(100))


def test_holding_torques_are_the_gradient_of_potential_energy(kin):
    # independent check of static_joint_torques: the torque that holds a pose is dV/dq, with V the
    # gravitational potential energy of the link masses
    import yourdfpy
    robot = yourdfpy.URDF.load(str(kin.desc.bullet_urdf_path), build_scene_graph=False, load_meshes=False).robot

    def potential(q):
        energy = 0.0
        for link in robot.links:
            if link.inertial is not None and link.inertial.mass:
                com = kin.link_pose(q, link.name) @ link.inertial.origin[:, 3]
                energy += link.inertial.mass * 9.81 * com[2]
        return energy

    q = {"swing_joint": 0.7, "boom_joint": -0.6, "arm_joint": 1.2, "bucket_joint": 0.9}
    torques = kin.static_joint_torques(q)
    for name in kin.desc.actuated_joints:
        h = 1e-6
        gradient = (potential({**q, name: q[name] + h}) - potential({**q, name: q[name] - h})) / (2 * h)
        assert torques[name] == pytest.approx(gradient, rel=1e-5, abs=1e-3)
    assert torques["boom_joint"] < -3e4      # the boom must push up (negative = raise) to hold the front
    assert torques["swing_joint"] == pytest.approx(0.0, abs=1e-6)   # gravity does not turn a level swing
