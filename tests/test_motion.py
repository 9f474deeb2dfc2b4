"""Motion scripts: waypoints are met exactly, interpolation never overshoots, CSV logs replay as recorded."""
import math

import numpy as np
import pytest

from opera_taichi.errors import UserError
from opera_taichi.motion import joint_waypoints, read_joint_csv

JOINTS = ["swing_joint", "boom_joint", "arm_joint", "bucket_joint"]


def test_waypoints_are_met_and_missing_joints_hold():
    prof = joint_waypoints([(0.0, {"boom_joint": -0.8}), (2.0, {"boom_joint": 0.2}), (5.0, {"arm_joint": 2.0})],
                           {"swing_joint": 0.1, "boom_joint": 0.0, "arm_joint": 1.0, "bucket_joint": 0.5})
    assert prof.targets(0.0)["boom_joint"] == pytest.approx(-0.8)
    assert prof.targets(2.0)["boom_joint"] == pytest.approx(0.2)
    # boom not named at t = 5: it holds 0.2; arm holds its initial value until first named
    assert prof.targets(5.0)["boom_joint"] == pytest.approx(0.2)
    assert prof.targets(2.0)["arm_joint"] == pytest.approx(1.0)
    assert prof.targets(5.0)["arm_joint"] == pytest.approx(2.0)
    assert prof.targets(99.0)["arm_joint"] == pytest.approx(2.0)   # holds after the end
    assert prof.targets(-1.0)["boom_joint"] == pytest.approx(-0.8)  # and before the start
    assert prof.targets(3.0)["swing_joint"] == pytest.approx(0.1)


def test_interpolation_is_monotone_between_waypoints():
    """A hydraulic machine should not be asked to overshoot: PCHIP keeps each segment monotone."""
    prof = joint_waypoints([(0.0, {"arm_joint": 0.5}), (1.0, {"arm_joint": 2.5}), (2.0, {"arm_joint": 2.6}),
                            (3.0, {"arm_joint": 0.6})], {"arm_joint": 0.5})
    t = np.linspace(0.0, 3.0, 601)
    q = np.array([prof.targets(x)["arm_joint"] for x in t])
    assert q.max() <= 2.6 + 1e-12 and q.min() >= 0.5 - 1e-12
    seg1 = q[(t >= 0) & (t <= 1)]
    assert np.all(np.diff(seg1) >= -1e-12)
    seg3 = q[(t >= 2) & (t <= 3)]
    assert np.all(np.diff(seg3) <= 1e-12)
    # smooth: no jump in the commanded angle between neighbouring samples
    assert np.max(np.abs(np.diff(q))) < 0.05


def test_csv_replay_with_degree_columns(tmp_path):
    path = tmp_path / "log.csv"
    path.write_text("t,boom_joint_deg,arm_joint\n0,0,1.0\n1,90,2.0\n2,45,2.0\n")
    prof = read_joint_csv(path, JOINTS)
    assert prof.targets(1.0)["boom_joint"] == pytest.approx(math.pi / 2)
    assert prof.targets(1.5)["boom_joint"] == pytest.approx(math.radians(67.5))  # linear between samples
    assert prof.targets(0.5)["arm_joint"] == pytest.approx(1.5)
    assert set(prof.joints) == {"boom_joint", "arm_joint"}


def test_a_runs_log_in_velocity_mode_replays_its_positions(tmp_path):
    """A joint driven by speed commands (ROS, the sliders) has no position target: joints.csv leaves its .q_cmd
    empty. The replay reads only t and the .q columns, so the log is a motion file all the same."""
    path = tmp_path / "joints.csv"
    path.write_text("t,boom_joint.q,boom_joint.qd,boom_joint.q_cmd,boom_joint.qd_cmd,boom_joint.effort\n"
                    "0,0.10,0.0,,0.5,-1e5\n0.5,0.35,0.5,,0.5,-1e5\n")
    prof = read_joint_csv(path, JOINTS)
    assert prof.joints == ["boom_joint"]
    assert prof.targets(0.25)["boom_joint"] == pytest.approx(0.225)
    path.write_text("t,boom_joint.q,boom_joint.q_cmd\n0,0.10,\n0.5,,\n")
    with pytest.raises(UserError, match=r"line 3, column boom_joint.q: expected a number"):
        read_joint_csv(path, JOINTS)  # a joint's own column still has to be a number


@pytest.mark.parametrize("text, words", [
    ("time,boom_joint\n0,1\n", "no `t` column"),
    ("t,boom_joint\n0,1\n0,2\n", "strictly increasing"),
    ("t,stick_joint\n0,1\n1,2\n", "not a joint"),
    ("t,boom_joint\n0,abc\n", "expected a number"),
    ("t,boom_joint\n0,nan\n", "finite"),
    ("t,boom_joint\n", "no rows"),
    ("t,boom_joint\n0,1,2\n", "expected 2 fields"),
])
def test_bad_csv_is_one_clear_line(tmp_path, text, words):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(UserError) as err:
        read_joint_csv(path, JOINTS)
    assert words in str(err.value) and "\n" not in str(err.value) and str(path) in str(err.value)


def test_a_log_of_several_machines_replays_each_machines_own_columns(tmp_path):
    """A run's joints.csv with two machines (`<machine>.<joint>.q` ...): each machine takes its own columns."""
    path = tmp_path / "joints.csv"
    head = ["t"] + [f"{m}.{j}.{k}" for m in ("east", "west") for j in JOINTS for k in ("q", "qd", "q_cmd")]
    rows = [[t] + [(0.1 if m == "east" else -0.1) * (i + 1) * t for m in ("east", "west") for i, _ in
                   enumerate(JOINTS) for _ in range(3)] for t in (0.0, 1.0)]
    path.write_text(",".join(head) + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    east = read_joint_csv(path, JOINTS, machine="east")
    west = read_joint_csv(path, JOINTS, machine="west")
    assert set(east.joints) == set(JOINTS)
    assert east.targets(1.0)[JOINTS[0]] == pytest.approx(0.1) and west.targets(1.0)[JOINTS[0]] == pytest.approx(-0.1)
    with pytest.raises(UserError, match="a log of machine 'east', and this one is 'zx120'"):
        read_joint_csv(path, JOINTS, machine="zx120")
