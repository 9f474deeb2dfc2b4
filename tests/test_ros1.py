"""The ZX120 driven from a real ROS 1 graph: Debian's roscore on a free port, `opera-taichi run ... --ros1` and
`--ros-tcp` (through Unity's real ROS-TCP-Endpoint, ROS 1 build, from ../shared/thirdparty) as processes, commands
sent with `rostopic pub` and the state read with `rostopic echo`, both Debian's tools.

What it proves: a ROS 1 user's own tools move the boom to a target no sooner than its speed limit allows, /clock
follows simulated time, emg_stop holds the machine, OPERA's com3_msgs/JointCmd works by joint name, malformed
messages are logged once and never end the run, and SIGINT closes the run folder. Skips without ROS 1 unless CI.
"""
import json
import math
import signal
import subprocess

import pytest

from ros_tools import (ENDPOINT_ROS1, SYSTEM_PYTHON, RosCore, TopicEcho, generate_com3_msgs, joint_rows,
                       require_ros1, rostopic_pub, start_run, stop, wait_for)

BOOM_Q0 = math.radians(-46)        # scenes/zx120_dig_cycle.yaml's initial boom angle
BOOM_MAX_SPEED = 0.70              # machines/zx120/machine.yaml
MACHINE_ONLY = ["scenes/zx120_dig_cycle.yaml", "--set", "motion=null", "--set", "sim.duration=300"]


@pytest.fixture(scope="module")
def ros(tmp_path_factory):
    require_ros1()
    tmp = tmp_path_factory.mktemp("ros1")
    core = RosCore(tmp)
    gen = generate_com3_msgs(tmp / "gen")
    env = dict(core.env, PYTHONPATH=str(gen))     # rostopic (system python) finds com3_msgs there
    yield core, env, tmp
    core.close()


def _boom(echo):
    return joint_rows(echo, "boom_joint")


def _ticks(echo):
    return [int(r["field.clock"]) * 1e-9 for r in echo.snapshot()]


def _wait_subscribed(core, topic, timeout=60):
    wait_for(lambda: topic in core.subscribers(), timeout, f"a subscriber on {topic}")


def _reach(echo, target, timeout=60):
    """Wait until the boom is within 0.02 rad of target; returns (stamp it left its previous rest, stamp it
    arrived)."""
    rows = wait_for(lambda: (r := _boom(echo)) and abs(r[-1][1] - target) < 0.02 and r, timeout,
                    f"the boom at {target} rad")
    arrived = next(t for t, q in rows if abs(q - target) < 0.02 and t >= _left(rows, target))
    return _left(rows, target), arrived


def _left(rows, target):
    """Stamp of the last sample at rest before the final approach to target (the command's arrival is after it)."""
    start = 0
    for i in range(1, len(rows)):
        if abs(rows[i][1] - rows[i - 1][1]) < 1e-5 and abs(rows[i][1] - target) >= 0.02:
            start = i
    return rows[start][0]


def _close_run(proc, out, err_path):
    assert stop(proc, signal.SIGINT, timeout=60) == 130
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "interrupted"
    assert (out / "joints.csv").stat().st_size > 0
    return err_path.read_text()


def test_ros1_rostopic_drives_the_boom_clock_follows_and_emg_stop_holds(ros):
    core, env, tmp = ros
    proc, out, err = start_run(MACHINE_ONLY + ["--ros1"], env, tmp, "ros1_boom")
    states = TopicEcho("/zx120/joint_states", env)
    clock = TopicEcho("/clock", env)
    try:
        # the machine holds its initial pose until the first command
        wait_for(lambda: (r := _boom(states)) and r[-1][0] - r[0][0] > 0.5, 90, "0.5 s of joint_states")
        assert all(abs(q - BOOM_Q0) < 1e-3 for _, q in _boom(states))
        _wait_subscribed(core, "/zx120/boom/cmd")
        rostopic_pub("/zx120/boom/cmd", "std_msgs/Float64", "data: -0.5", env)
        left, arrived = _reach(states, -0.5)
        assert arrived - left >= (abs(-0.5 - BOOM_Q0) - 0.02) / BOOM_MAX_SPEED   # no faster than its speed limit

        # /clock publishes simulated time: increasing in 100 Hz steps, and on past the boom's arrival
        ticks = wait_for(lambda: (c := _ticks(clock)) and c[-1] >= arrived and c, 30, "/clock past the arrival")
        assert len(ticks) > 50 and all(b > a for a, b in zip(ticks, ticks[1:]))
        assert min(b - a for a, b in zip(ticks, ticks[1:])) == pytest.approx(0.01, abs=1e-6)

        # emg_stop holds: a new target is ignored while it is on, reached once it is released
        rostopic_pub("/zx120/emg_stop", "std_msgs/Bool", "data: true", env)
        rostopic_pub("/zx120/boom/cmd", "std_msgs/Float64", "data: -0.9", env)
        t_held, q_held = _boom(states)[-1]
        wait_for(lambda: _boom(states)[-1][0] > t_held + 1.0, 30, "1 s of simulated time under emg_stop")
        assert all(abs(q - q_held) < 1e-3 for t, q in _boom(states) if t >= t_held)
        rostopic_pub("/zx120/emg_stop", "std_msgs/Bool", "data: false", env)
        rostopic_pub("/zx120/boom/cmd", "std_msgs/Float64", "data: -0.9", env)
        _reach(states, -0.9)
    finally:
        states.close()
        clock.close()
        text = _close_run(proc, out, err)
    assert "ROS 1 node /opera_taichi" in text


def test_ros1_joint_cmd_by_name_and_malformed_messages_logged_once(ros):
    core, env, tmp = ros
    proc, out, err = start_run(MACHINE_ONLY + ["--ros1"], env, tmp, "ros1_malformed")
    states = TopicEcho("/zx120/joint_states", env)
    try:
        wait_for(lambda: _boom(states), 90, "joint_states")
        _wait_subscribed(core, "/zx120/front_cmd")
        _wait_subscribed(core, "/zx120/bucket/cmd")
        bad = [("/zx120/front_cmd", "com3_msgs/JointCmd", "{joint_name: [stick_joint], control_type: 0, position: [1]}"),
               ("/zx120/front_cmd", "com3_msgs/JointCmd", "{joint_name: [stick_joint], control_type: 0, position: [1]}"),
               ("/zx120/front_cmd", "com3_msgs/JointCmd",
                "{joint_name: [boom_joint, arm_joint], control_type: 0, position: [0.1]}"),
               ("/zx120/bucket/cmd", "std_msgs/Float64", "data: .nan")]
        pubs = [subprocess.Popen(["rostopic", "pub", "-1", *b], env=env, stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL) for b in bad]
        for p in pubs:
            assert p.wait(60) == 0
        wait_for(lambda: err.read_text().count("message ignored") >= 3, 30, "the three mistakes logged")
        # the run goes on and takes a good command by joint name
        rostopic_pub("/zx120/front_cmd", "com3_msgs/JointCmd",
                     "{joint_name: [arm_joint, boom_joint], control_type: 0, position: [1.5, -0.6]}", env)
        wait_for(lambda: (a := joint_rows(states, "arm_joint")) and abs(a[-1][1] - 1.5) < 0.02, 60, "arm at 1.5")
        assert abs(_boom(states)[-1][1] + 0.6) < 0.02
        assert proc.poll() is None
    finally:
        states.close()
        text = _close_run(proc, out, err)
    lines = [line for line in text.splitlines() if "message ignored" in line]
    assert len(lines) == 3, text
    assert sum("unknown joint 'stick_joint'" in line for line in lines) == 1
    assert sum("needs position[] as long as joint_name[] (2), got 1" in line for line in lines) == 1
    assert sum("/zx120/bucket/cmd: target nan rad" in line for line in lines) == 1
    manifest = json.loads((out / "manifest.json").read_text())
    assert sum("message ignored" in w for w in manifest["run_warnings"]) == 3


@pytest.fixture
def endpoint(ros):
    """Unity's ROS-TCP-Endpoint (ROS 1 build) run from ../shared/thirdparty as its README says, with com3_msgs on its
    path (an OPERA user builds com3_ros in their workspace)."""
    core, env, tmp = ros
    if not ENDPOINT_ROS1.is_dir():
        pytest.fail(f"{ENDPOINT_ROS1} is missing (../shared/thirdparty)")
    from ros_tools import free_port

    port = free_port()
    log = open(tmp / f"endpoint-{port}.log", "w")
    proc = subprocess.Popen([SYSTEM_PYTHON, "-m", "ros_tcp_endpoint.default_server_endpoint", "_tcp_ip:=127.0.0.1",
                             f"_tcp_port:={port}"], env=dict(env, PYTHONPATH=f"{ENDPOINT_ROS1}:{env['PYTHONPATH']}"),
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)

    def listening():
        import socket

        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return True
        except OSError:
            assert proc.poll() is None, (tmp / f"endpoint-{port}.log").read_text()
            return False

    # the probe connection is one the endpoint serves and drops; the run's own connection comes after it
    wait_for(listening, 60, "the ROS-TCP-Endpoint listening")
    yield port
    stop(proc, signal.SIGINT)
    log.close()


def test_ros_tcp_through_the_real_ros1_endpoint(ros, endpoint):
    core, env, tmp = ros
    proc, out, err = start_run(MACHINE_ONLY + ["--ros-tcp", f"127.0.0.1:{endpoint}"], env, tmp, "ros_tcp_ros1")
    states = TopicEcho("/zx120/joint_states", env)
    clock = TopicEcho("/clock", env)
    try:
        wait_for(lambda: (r := _boom(states)) and r[-1][0] - r[0][0] > 0.5, 90, "0.5 s of joint_states")
        assert all(abs(q - BOOM_Q0) < 1e-3 for _, q in _boom(states))
        _wait_subscribed(core, "/zx120/boom/cmd")
        rostopic_pub("/zx120/boom/cmd", "std_msgs/Float64", "data: -0.5", env)
        left, arrived = _reach(states, -0.5)
        assert arrived - left >= (abs(-0.5 - BOOM_Q0) - 0.02) / BOOM_MAX_SPEED
        ticks = wait_for(lambda: (c := _ticks(clock)) and c[-1] >= arrived and c, 30, "/clock past the arrival")
        assert len(ticks) > 50 and all(b > a for a, b in zip(ticks, ticks[1:]))
        # com3_msgs/JointCmd through the endpoint (it deserialises it with the genpy class)
        _wait_subscribed(core, "/zx120/front_cmd")
        arm0 = joint_rows(states, "arm_joint")[-1][1]
        rostopic_pub("/zx120/front_cmd", "com3_msgs/JointCmd",
                     "{joint_name: [arm_joint], control_type: 1, velocity: [-0.3]}", env)
        wait_for(lambda: joint_rows(states, "arm_joint")[-1][1] < arm0 - 0.05, 60, "the arm opening")
        # one speed command lasts bridge.command_timeout (0.5 s of simulated time): then the arm stops
        t_open = next(t for t, q in joint_rows(states, "arm_joint") if q < arm0 - 0.05)
        wait_for(lambda: _boom(states)[-1][0] > t_open + 2.0, 60, "2 s after the arm opened")
        stopped = [q for t, q in joint_rows(states, "arm_joint") if t >= t_open + 1.0]
        assert max(stopped) - min(stopped) < 1e-3 and arm0 - stopped[-1] < 0.3  # 2 s at 0.3 rad/s would be 0.6
        # emg_stop through the endpoint holds it: a speed command under it is ignored
        rostopic_pub("/zx120/emg_stop", "std_msgs/Bool", "data: true", env)
        t_held = _boom(states)[-1][0]
        arm_held = joint_rows(states, "arm_joint")[-1][1]
        rostopic_pub("/zx120/front_cmd", "com3_msgs/JointCmd",
                     "{joint_name: [arm_joint], control_type: 1, velocity: [-0.3]}", env)
        wait_for(lambda: _boom(states)[-1][0] > t_held + 1.0, 30, "1 s under emg_stop")
        assert all(abs(q - arm_held) < 1e-3 for t, q in joint_rows(states, "arm_joint") if t >= t_held)
    finally:
        states.close()
        clock.close()
        text = _close_run(proc, out, err)
    assert "ROS-TCP-Endpoint v0.7.0 at 127.0.0.1" in text and "ROS1: ROS 1 serialisation" in text
    assert "arm_joint's velocity target: the joint stops (bridge.command_timeout" in text


def test_joint_cmd_md5_matches_genpys_class(ros):
    """The com3_msgs/JointCmd we announce is the class genpy generates from OPERA's .msg (same md5 sum), so rospy
    and the endpoint accept it."""
    from opera_taichi.ros.messages import msgdef, typestore

    core, env, tmp = ros
    done = subprocess.run([SYSTEM_PYTHON, "-c", "from com3_msgs.msg import JointCmd; print(JointCmd._md5sum)"],
                          env=env, capture_output=True, text=True, timeout=60, check=True)
    assert done.stdout.strip() == msgdef(typestore(1), "com3_msgs/msg/JointCmd", 1)[1]


def test_ros1_a_master_that_dies_is_said(ros, tmp_path):
    """roscore ends under a running node: the run says so once (stderr and the manifest's run_warnings) and goes on."""
    _, env0, tmp = ros
    core = RosCore(tmp_path)
    env = dict(env0, ROS_MASTER_URI=core.uri)
    proc, out, err = start_run(MACHINE_ONLY + ["--ros1"], env, tmp_path, "ros1_master_dies")
    try:
        wait_for(lambda: "/zx120/joint_states" in core.publishers(), 90, "the run's joint_states registered")
        core.close()
        wait_for(lambda: "stopped answering" in err.read_text(), 30, "the run saying the master is gone")
        assert proc.poll() is None
    finally:
        text = _close_run(proc, out, err)
    assert sum("stopped answering" in line for line in text.splitlines()) == 1
    warnings = json.loads((out / "manifest.json").read_text())["run_warnings"]
    assert any(f"ROS master at {core.uri} stopped answering" in w for w in warnings)
