"""The ROS bridge without a ROS graph: the topic table, the messages (CDR checked against a second, independent CDR
implementation: mcap-ros2-support's; ROS 1 md5 sums against genpy's), com3_msgs/JointCmd against OPERA's .msg, and
the controller's handling of commands (latest wins, dead time, malformed messages logged once and ignored)."""
import hashlib
import json
import math
import re
import struct
import subprocess
from pathlib import Path

import numpy as np

import pytest

import opera_taichi as ot
from conftest import ON_CI, SHARED
from opera_taichi.cli import main
from opera_taichi.errors import UserError
from opera_taichi.model import build_model
from opera_taichi.ros.controller import BridgeController
from opera_taichi.ros.messages import JOINT_CMD_MSG, MessageBuilder, msgdef, typestore
from opera_taichi.ros.sampler import Sampler
from opera_taichi.ros.topics import topic_table
from opera_taichi.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
DIG_CYCLE = ROOT / "scenes" / "zx120_dig_cycle.yaml"
EXCAVATION = ROOT / "scenes" / "zx120_excavation.yaml"
COM3_MSG = SHARED / "thirdparty" / "com3_msgs" / "msg" / "JointCmd.msg"


def _table(scene=EXCAVATION, sets=()):
    scene = load_scene(scene, list(sets))
    return topic_table(build_model(scene), scene.bridge)


def test_topic_table_has_operas_names_types_and_rates():
    topics = {t.name: t for t in _table()}
    for joint in ("swing", "boom", "arm", "bucket"):
        assert topics[f"/zx120/{joint}/cmd"].type == "std_msgs/msg/Float64"
        assert topics[f"/zx120/{joint}/cmd"].item == f"{joint}_joint" and topics[f"/zx120/{joint}/cmd"].inbound
    assert topics["/zx120/front_cmd"].type == "com3_msgs/msg/JointCmd"
    assert topics["/zx120/emg_stop"].type == "std_msgs/msg/Bool"
    assert "/zx120/tracks/cmd_vel" not in topics          # a fixed base has no tracks to drive
    expected = {"/zx120/joint_states": ("sensor_msgs/msg/JointState", 25), "/zx120/odom": ("nav_msgs/msg/Odometry", 25),
                "/zx120/base_link/pose": ("geometry_msgs/msg/PoseStamped", 25),
                "/zx120/bucket/wrench": ("geometry_msgs/msg/WrenchStamped", 25),
                "/zx120/soil_volume": ("std_msgs/msg/Float64", 5), "/zx120/soil_mass": ("std_msgs/msg/Float64", 5),
                "/tf": ("tf2_msgs/msg/TFMessage", 25), "/clock": ("rosgraph_msgs/msg/Clock", 100),
                "/terrain/points": ("sensor_msgs/msg/PointCloud2", 1)}
    for name, (typ, rate) in expected.items():
        assert (topics[name].type, topics[name].rate) == (typ, rate)
    # on tracks the base takes cmd_vel; without soil there is no wrench, load or terrain
    free = {t.name for t in _table(DIG_CYCLE, ["machine.fixed_base=false"])}
    assert "/zx120/tracks/cmd_vel" in free and "/zx120/bucket/wrench" not in free and "/terrain/points" not in free


def test_topics_and_rates_are_configurable_and_checked():
    topics = {t.key: t for t in _table(sets=["bridge={kind: ros1, namespace: ex1, rates: {joint_states: 50, "
                                             "terrain: 0.5}, topics: {boom/cmd: /opera/boom_target, "
                                             "joint_states: js}}"])}
    assert topics["boom/cmd"].name == "/opera/boom_target"
    assert topics["joint_states"].name == "/ex1/js" and topics["joint_states"].rate == 50
    assert topics["terrain"].rate == 0.5 and topics["odom"].name == "/ex1/odom"
    with pytest.raises(UserError, match=r"bridge.rates.joint_state: no such topic.*did you mean 'joint_states'"):
        _table(sets=["bridge={kind: ros1, rates: {joint_state: 50}}"])
    with pytest.raises(UserError, match="bridge.rates.boom/cmd: a command topic has no rate"):
        _table(sets=["bridge={kind: ros1, rates: {boom/cmd: 50}}"])
    with pytest.raises(UserError, match="two topics are named /zx120/odom"):
        _table(sets=["bridge={kind: ros1, topics: {joint_states: odom}}"])


def test_validate_and_run_report_bridge_mistakes_in_one_line(capsys):
    assert main(["validate", str(EXCAVATION), "--set", "bridge={kind: ros1, topics: {bom/cmd: x}}"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bridge.topics.bom/cmd" in err and "boom/cmd" in err
    assert main(["validate", str(EXCAVATION), "--set", "bridge={kind: ros2}"]) == 2
    assert "bridge.kind" in capsys.readouterr().err
    assert main(["run", str(DIG_CYCLE), "--ros-tcp", "localhost"]) == 2
    assert "--ros-tcp: expected HOST:PORT" in capsys.readouterr().err
    assert main(["run", str(DIG_CYCLE), "--bridge-after-motion"]) == 2
    assert "--bridge-after-motion: only with a bridge" in capsys.readouterr().err
    # what `run` refuses before it connects, `validate` refuses too
    bad_port = ["--set", "bridge={kind: ros_tcp, address: '127.0.0.1:99999'}"]
    assert main(["validate", str(DIG_CYCLE), *bad_port]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bridge.address: expected HOST:PORT" in err, err


def test_ros_tcp_without_an_endpoint_is_a_one_line_error(tmp_path, capsys):
    import socket

    with socket.socket() as s:   # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = main(["run", str(DIG_CYCLE), "--ros-tcp", f"127.0.0.1:{port}", "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("error: --ros-tcp: cannot connect to a ROS-TCP-Endpoint")
    assert not (tmp_path / "r").exists()     # refused before a run folder was made


def test_a_peer_that_sends_no_frames_is_refused_before_anything_is_allocated(tmp_path, capsys):
    """Bytes from something that is no ROS-TCP-Endpoint: the lengths they spell are refused (no 4 GiB buffer)."""
    import socket
    import threading

    from opera_taichi.ros.transport_tcp import MAX_PAYLOAD, frame, read_frame

    for sent, words in [(b"\xff" * 64, "a destination of 4294967295 bytes"),
                        (frame("/zx120/boom/cmd", b"x")[:-5] + struct.pack("<I", MAX_PAYLOAD + 1),
                         f"a message of {MAX_PAYLOAD + 1} bytes to '/zx120/boom/cmd'"),
                        (struct.pack("<I", 2) + b"\xc3\x28", "not UTF-8"),
                        (frame("__handshake", b"{}"), None)]:
        a, b = socket.socketpair()
        with a, b:
            b.sendall(sent)
            if words is None:
                assert read_frame(a) == ("__handshake", b"{}")
                continue
            with pytest.raises(ConnectionError, match=re.escape(words)):
                read_frame(a)
    with socket.socket() as server:   # the same at a run's first connection: one line, exit 2
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]

        def junk():
            conn, _ = server.accept()
            with conn:
                conn.sendall(b"\xff" * 64)
                try:
                    conn.recv(1)   # until the run hangs up
                except OSError:
                    pass

        peer = threading.Thread(target=junk, daemon=True)
        peer.start()
        code = main(["run", str(DIG_CYCLE), "--ros-tcp", f"127.0.0.1:{port}", "--out", str(tmp_path / "r")])
        peer.join(10)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("error: --ros-tcp: ") and "did not greet" in err[-1], err


def test_a_handshake_that_is_no_endpoints_greeting_is_refused_in_one_line():
    from opera_taichi.ros.transport_tcp import _greeting

    assert _greeting(b'{"version": "v0.7.0", "metadata": "{\\"protocol\\": \\"ROS2\\"}"}\x00') == ("v0.7.0", "ROS2")
    assert _greeting(b'{"version": "v0.7.0"}') == ("v0.7.0", "ROS1")   # the ROS 1 endpoint sends no metadata
    for payload, words in [(b"[1]", "no JSON object"), (b'{"metadata": {"protocol": "ROS2"}}', "metadata is no"),
                           (b'{"metadata": "[2]"}', "unknown protocol"), (b"\xff", "decode")]:
        with pytest.raises(ValueError, match=words):
            _greeting(payload)


def _endpoint(server, protocol="ROS1"):
    """Accept one client and greet it as a ROS-TCP-Endpoint; returns the connection."""
    from opera_taichi.ros.transport_tcp import frame

    conn, _ = server.accept()
    conn.sendall(frame("__handshake", json.dumps({"version": "v0.7.0",
                                                  "metadata": json.dumps({"protocol": protocol})}).encode()))
    return conn


def test_ros_tcp_input_survives_messages_it_cannot_read_and_stays_closed_once_closed():
    """An endpoint's __error whose JSON is no object, then a command: the command arrives (the reader thread went on)
    and the odd message is logged once. Then the endpoint drops the connection and the run closes the transport
    while it waits to reconnect: it does not connect again."""
    import socket
    import threading

    from opera_taichi.ros.transport_tcp import RosTcpTransport, frame

    said, lost, got = [], threading.Event(), []
    arrived = threading.Event()

    def log(key, text):
        said.append(text)
        if key == ("tcp", "lost"):
            lost.set()

    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        accepted = []
        greeter = threading.Thread(target=lambda: accepted.append(_endpoint(server)), daemon=True)
        greeter.start()
        transport = RosTcpTransport(f"127.0.0.1:{server.getsockname()[1]}", log)
        greeter.join(10)
        conn = accepted[0]
        transport.subscribe("/zx120/boom/cmd", "com3_msgs/msg/JointCmd",
                            lambda payload: (got.append(payload), arrived.set()))
        conn.sendall(frame("__error", b"[1]") + frame("__warn", b'{"text": 5}') + frame("/zx120/boom/cmd", b"abc"))
        assert arrived.wait(10) and got == [b"abc"]
        assert said == ["ros-tcp endpoint error: [1]", "ros-tcp endpoint warn: 5"]
        conn.shutdown(socket.SHUT_RDWR)
        conn.close()
        assert lost.wait(10)
        transport.close()
        assert not transport._reader.is_alive() and transport.sock is None
        server.setblocking(False)
        with pytest.raises(BlockingIOError):   # no connection came after the close
            server.accept()


def test_joint_cmd_is_operas_message():
    """Our com3_msgs/JointCmd has the fields of OPERA's .msg and its ROS 1 md5 sum (ROS's rule: the md5 of the
    definition without comments; the text is plain builtin types, so that is the field lines)."""
    if not COM3_MSG.is_file():
        if ON_CI:
            pytest.fail(f"{COM3_MSG} is missing on CI")
        pytest.skip(f"{COM3_MSG} not found (../shared/thirdparty)")
    lines = [re.sub(r"\s+", " ", line.split("#")[0]).strip() for line in COM3_MSG.read_text().splitlines()]
    fields = [line for line in lines if line]
    assert fields == JOINT_CMD_MSG.strip().splitlines()
    _, md5 = msgdef(typestore(1), "com3_msgs/msg/JointCmd", 1)
    assert md5 == hashlib.md5("\n".join(fields).encode()).hexdigest()


PUBLISHED = ["sensor_msgs/msg/JointState", "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
             "geometry_msgs/msg/WrenchStamped", "std_msgs/msg/Float64", "tf2_msgs/msg/TFMessage",
             "rosgraph_msgs/msg/Clock", "sensor_msgs/msg/PointCloud2"]
COMMANDS = ["std_msgs/msg/Float64", "std_msgs/msg/Bool", "geometry_msgs/msg/Twist", "com3_msgs/msg/JointCmd"]


def test_ros1_md5_sums_match_genpy():
    """The md5 sums the ROS 1 transports and .bag files announce are those of Debian's generated message classes
    (a mismatch and rospy refuses the connection)."""
    python = Path("/usr/bin/python3")
    probe = "import json, importlib\nout = {}\nfor t in %r:\n    pkg, _, name = t.split('/')\n" \
            "    try:\n        out[t] = getattr(importlib.import_module(pkg + '.msg'), name)._md5sum\n" \
            "    except ImportError:\n        pass\nprint(json.dumps(out))" % (PUBLISHED + COMMANDS)
    found = {}
    if python.is_file():
        done = subprocess.run([str(python), "-c", probe], capture_output=True, text=True, timeout=60)
        found = json.loads(done.stdout or "{}")
    wanted = set(PUBLISHED + COMMANDS) - {"com3_msgs/msg/JointCmd"}   # no Debian package for com3_msgs
    if not wanted <= set(found):
        if ON_CI:
            pytest.fail(f"ROS 1 message packages missing on CI: {sorted(wanted - set(found))}")
        pytest.skip("Debian's ROS 1 message packages are not installed")
    for t in wanted:
        assert msgdef(typestore(1), t, 1)[1] == found[t], t


@pytest.fixture(scope="module")
def coarse_sim():
    sim = ot.Simulation.from_scene(EXCAVATION, {"soil.overrides.radius": 0.16, "motion": None})
    for _ in range(20):
        sim.step({"boom_joint": -0.5})
    yield sim
    sim.close()


@pytest.mark.parametrize("ros_version", [1, 2])
def test_every_published_type_round_trips_and_cdr_matches_an_independent_encoder(coarse_sim, ros_version):
    """Each output message of a coarse excavation, serialised, reads back to the same values; in CDR it is byte for
    byte what mcap-ros2-support's encoder (another implementation, driven by the ros2msg schema text that run.mcap
    carries) makes of the decoded message."""
    from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

    topics = topic_table(coarse_sim.model)
    snap = Sampler(coarse_sim, topics).sample(coarse_sim)
    assert {t.type for t, _ in snap.values()} == set(PUBLISHED)
    builder = MessageBuilder(ros_version)
    store = builder.store
    for name, (topic, data) in snap.items():
        msg = builder.build(topic, data)
        raw = builder.serialize(msg, topic.type)
        back = store.deserialize_ros1(raw, topic.type) if ros_version == 1 else store.deserialize_cdr(raw, topic.type)
        again = store.serialize_ros1(back, topic.type) if ros_version == 1 else store.serialize_cdr(back, topic.type)
        assert bytes(again) == raw, name
        if ros_version == 2:
            text, _ = msgdef(store, topic.type, 2)
            decoded = generate_dynamic(topic.type, text)[topic.type](raw)
            assert serialize_dynamic(topic.type, text)[topic.type](decoded) == raw, name
    js = snap["/zx120/joint_states"][1]
    msg = builder.build(snap["/zx120/joint_states"][0], js)
    # every movable joint of the URDF, actuated first: robot_state_publisher needs bucket_end_joint to place
    # bucket_end_link; the welded dummy rests at 0
    assert list(msg.name) == [*coarse_sim.machine.joint_names, "bucket_end_joint"]
    assert len(msg.position) == len(msg.velocity) == len(msg.effort) == len(msg.name)
    np.testing.assert_array_equal(msg.position[:4], coarse_sim.machine.joint_states()[0])
    np.testing.assert_array_equal(msg.velocity[:4], coarse_sim.machine.joint_states()[1])
    assert msg.position[4] == 0.0 and msg.velocity[4] == 0.0
    cloud = builder.build(*snap["/terrain/points"])
    grid = coarse_sim.model.soil.grid
    pts = np.frombuffer(cloud.data.tobytes(), "<f4").reshape(cloud.height, cloud.width, 3)
    assert (cloud.height, cloud.width) == (len(grid.y), len(grid.x))
    np.testing.assert_allclose(pts[3, 5], [grid.x[5], grid.y[3], coarse_sim.soil.heightmap(grid.x, grid.y)[5, 3]],
                               rtol=1e-6, atol=1e-6)
    wrench = builder.build(*snap["/zx120/bucket/wrench"])
    assert wrench.header.frame_id == "bucket_link"
    world = coarse_sim.tool_wrench[0, :3]
    assert math.isclose(np.linalg.norm([wrench.wrench.force.x, wrench.wrench.force.y, wrench.wrench.force.z]),
                        np.linalg.norm(world), rel_tol=1e-9, abs_tol=1e-9)   # rotated into the link frame


# ---------------------------------------------------------------------------------------------- controller
class _Log:
    def __init__(self):
        self.lines, self._keys = [], set()

    def __call__(self, key, text):
        if key not in self._keys:
            self._keys.add(key)
            self.lines.append(text)


@pytest.fixture
def machine_sim():
    s = ot.Simulation.from_scene(DIG_CYCLE, {"motion": None, "machine.command_latency": 0.2})
    yield s
    s.close()


def _msg(typename, **fields):
    T = typestore(2).types
    if typename == "com3_msgs/msg/JointCmd":
        fields.setdefault("effort", np.zeros(0))
        for k in ("position", "velocity", "effort"):
            fields.setdefault(k, np.zeros(0))
            fields[k] = np.asarray(fields[k], np.float64)
    return T[typename](**fields)


def _topics(sim):
    return {t.key: t for t in topic_table(sim.model) if t.inbound}


def test_malformed_commands_are_logged_once_and_ignored(machine_sim):
    log = _Log()
    ctl = BridgeController(log)
    ctl.bind(machine_sim.model)
    topics = _topics(machine_sim)
    bad = [(topics["boom/cmd"], _msg("std_msgs/msg/Float64", data=math.nan)),
           (topics["front_cmd"], _msg("com3_msgs/msg/JointCmd", joint_name=["stick_joint"], control_type=0,
                                      position=[0.1])),
           (topics["front_cmd"], _msg("com3_msgs/msg/JointCmd", joint_name=["boom_joint", "arm_joint"], control_type=0,
                                      position=[0.1])),
           (topics["front_cmd"], _msg("com3_msgs/msg/JointCmd", joint_name=["boom_joint"], control_type=2,
                                      effort=[10.0])),
           (topics["front_cmd"], _msg("com3_msgs/msg/JointCmd", joint_name=["arm_joint"], control_type=1,
                                      velocity=[math.inf]))]
    for topic, msg in bad + bad:           # each mistake twice
        ctl.handle(topic, msg)
    assert len(log.lines) == len(bad)       # once each
    assert "/zx120/boom/cmd: target nan rad is not a finite number" in log.lines[0]
    assert "unknown joint 'stick_joint'" in log.lines[1]
    assert "needs position[] as long as joint_name[] (2), got 1" in log.lines[2]
    assert "control_type 2 is not supported" in log.lines[3]
    assert ctl.accepted == 0
    assert ctl.control(machine_sim, 0.001).machines == {}   # nothing reached the machine


def test_commands_wait_out_the_dead_time_and_the_latest_wins(machine_sim):
    """machine.command_latency = 0.2 s: a command arriving at t acts from t + 0.2 s; of two for one joint in the same
    step the later wins, and a velocity command replaces a position command of the same joint."""
    ctl = BridgeController(_Log())
    ctl.bind(machine_sim.model)
    topics = _topics(machine_sim)
    boom = machine_sim.machine.joint_names.index("boom_joint")
    q0 = machine_sim.machine.joint_states()[0][boom]
    ctl.control(machine_sim, machine_sim.t + 0.001)
    ctl.handle(topics["boom/cmd"], _msg("std_msgs/msg/Float64", data=-0.3))
    ctl.handle(topics["boom/cmd"], _msg("std_msgs/msg/Float64", data=-0.5))
    ctl.handle(topics["front_cmd"], _msg("com3_msgs/msg/JointCmd", joint_name=["arm_joint"], control_type=0,
                                         position=[1.0]))
    ctl.handle(topics["front_cmd"], _msg("com3_msgs/msg/JointCmd", joint_name=["arm_joint"], control_type=1,
                                         velocity=[0.2]))
    applied_at = None
    while machine_sim.t < 0.5:
        c = ctl.control(machine_sim, machine_sim.t_next)
        if c.machines and applied_at is None:
            applied_at = c.t
            mc = c.machines["zx120"]
            assert mc.q_target == {"boom_joint": -0.5} and mc.qd_target == {"arm_joint": 0.2}
        machine_sim.step(c)
        if applied_at is None:
            assert abs(machine_sim.machine.joint_states()[0][boom] - q0) < 1e-6   # held until then
    assert applied_at == pytest.approx(0.2 + 0.001, abs=1.5e-3)
    assert machine_sim.machine.joint_states()[0][boom] > q0 + 0.05


def test_cmd_vel_drives_the_tracks_of_a_free_base():
    """On tracks (fixed_base: false) Twist linear.x / angular.z become left / right track speeds (skid steer over
    the gauge), and the machine drives forward."""
    sim = ot.Simulation.from_scene(DIG_CYCLE, {"motion": None, "machine.fixed_base": False})
    try:
        ctl = BridgeController(_Log())
        ctl.bind(sim.model)
        topic = _topics(sim)["tracks/cmd_vel"]
        T = typestore(2).types
        V = T["geometry_msgs/msg/Vector3"]
        gauge = sim.model.machines[0].description.tracks["gauge"]
        ctl.handle(topic, T["geometry_msgs/msg/Twist"](linear=V(x=0.5, y=0, z=0), angular=V(x=0, y=0, z=0.2)))
        c = ctl.control(sim, sim.t_next)
        assert c.machines["zx120"].track_speeds == pytest.approx((0.5 - 0.1 * gauge, 0.5 + 0.1 * gauge))
        x0 = sim.machine.base_pose()[0][0]
        while sim.t < 2.0:  # a teleop's stream at 10 Hz (each command lasts bridge.command_timeout, 0.5 s)
            if sim.step_count % 50 == 0:
                ctl.handle(topic, T["geometry_msgs/msg/Twist"](linear=V(x=0.5, y=0, z=0), angular=V(x=0, y=0, z=0)))
            sim.step(ctl.control(sim, sim.t_next))
        assert sim.machine.base_pose()[0][0] > x0 + 0.6
    finally:
        sim.close()


def _tracked_machine_and_bridge():
    """The dig-cycle machine on its tracks, no motion, and a bridge controller bound to it (speeds expire in 0.5 s)."""
    sim = ot.Simulation.from_scene(DIG_CYCLE, {"motion": None, "machine.fixed_base": False})
    log = _Log()
    ctl = BridgeController(log, command_timeout=0.5)
    ctl.bind(sim.model)
    return sim, log, ctl, _topics(sim)


def test_speed_commands_expire_so_a_dead_controller_does_not_leave_the_machine_driving():
    """A cmd_vel and a joint velocity target each sent once: they act for bridge.command_timeout (0.5 s of simulated
    time), then the tracks stop and the joint's target speed becomes 0 (said once each); the machine comes to rest
    and stays there, also after an emergency stop is released. A position target does not expire."""
    sim, log, ctl, topics = _tracked_machine_and_bridge()
    T = typestore(2).types
    V = T["geometry_msgs/msg/Vector3"]
    try:
        arm = sim.machine.joint_names.index("arm_joint")
        ctl.handle(topics["tracks/cmd_vel"], T["geometry_msgs/msg/Twist"](linear=V(x=0.5, y=0, z=0),
                                                                            angular=V(x=0, y=0, z=0)))
        ctl.handle(topics["front_cmd"], _msg("com3_msgs/msg/JointCmd", joint_name=["arm_joint"], control_type=1,
                                             velocity=[0.2]))
        ctl.handle(topics["boom/cmd"], _msg("std_msgs/msg/Float64", data=-0.3))
        expired_at, x, q_arm = None, [], []
        while sim.t < 2.5:
            c = ctl.control(sim, sim.t_next)
            mc = c.machines.get("zx120")
            if mc is not None and mc.track_speeds == (0.0, 0.0):
                assert expired_at is None and mc.qd_target == {"arm_joint": 0.0}  # both at once, once
                expired_at = c.t
            if sim.t == pytest.approx(1.5):
                ctl.handle(topics["emg_stop"], _msg("std_msgs/msg/Bool", data=True))
            if sim.t == pytest.approx(1.7):
                ctl.handle(topics["emg_stop"], _msg("std_msgs/msg/Bool", data=False))
            sim.step(c)
            x.append(sim.machine.base_pose()[0][0])
            q_arm.append(sim.machine.joint_states()[0][arm])
        assert expired_at == pytest.approx(0.5 + 0.002, abs=2.5e-3)
        x, q_arm = np.array(x), np.array(q_arm)
        t = np.arange(1, len(x) + 1) * sim.model.dt
        assert x[t <= 0.5][-1] - x[0] > 0.1 and q_arm[t <= 0.5][-1] - q_arm[0] > 0.05  # they moved ...
        rest = t >= 1.2
        assert np.ptp(x[rest]) < 0.01 and np.ptp(q_arm[rest]) < 0.005               # ... then stood still
        assert sum("no new speed command" in line for line in log.lines) == 2
        assert any("tracks/cmd_vel: the tracks stop" in line for line in log.lines)
        assert any("arm_joint's velocity target: the joint stops" in line for line in log.lines)
        boom = sim.machine.joint_names.index("boom_joint")
        assert sim.machine.joint_states()[0][boom] == pytest.approx(-0.3, abs=0.02)    # the position target held
    finally:
        sim.close()


def test_a_released_emergency_stop_resumes_no_drive_given_before_it():
    """A cmd_vel, then the emergency stop 0.25 s later and its release 1 s after that: the machine stops under the
    hold and stays still after the release (the speed it had been given is gone, and expired under the hold),
    until a new cmd_vel drives it again."""
    sim = ot.Simulation.from_scene(DIG_CYCLE, {"motion": None, "machine.fixed_base": False})
    try:
        ctl = BridgeController(_Log(), command_timeout=0.5)
        ctl.bind(sim.model)
        topics = _topics(sim)
        T = typestore(2).types
        V = T["geometry_msgs/msg/Vector3"]
        drive = T["geometry_msgs/msg/Twist"](linear=V(x=0.5, y=0, z=0), angular=V(x=0, y=0, z=0))
        events = {0.0: ("tracks/cmd_vel", drive), 0.25: ("emg_stop", _msg("std_msgs/msg/Bool", data=True)),
                  1.25: ("emg_stop", _msg("std_msgs/msg/Bool", data=False)), 2.5: ("tracks/cmd_vel", drive)}
        x = {}
        while sim.t < 3.0:
            for at, (key, msg) in events.items():
                if abs(sim.t - at) < 0.5 * sim.model.dt:
                    ctl.handle(topics[key], msg)
            sim.step(ctl.control(sim, sim.t_next))
            x[round(sim.t, 3)] = sim.machine.base_pose()[0][0]
        assert x[0.25] - x[0.002] > 0.02                  # it drove ...
        assert abs(x[2.5] - x[1.0]) < 0.005               # ... stood under the hold and after its release ...
        assert x[3.0] - x[2.5] > 0.05                     # ... and a new command drives it again
    finally:
        sim.close()


def test_mistakes_arriving_on_several_threads_at_once_are_said_once_each_on_its_own_line(capsys):
    """rospy delivers each publisher's messages on its own thread: the same mistake from several publishers at the
    same moment is still one line, and different mistakes at the same moment never share a line."""
    import threading

    from opera_taichi.ros.bridge import RosBridge
    from opera_taichi.scene import BridgeConfig

    bridge = RosBridge(BridgeConfig(kind="ros1"), transport=object())
    go = threading.Barrier(8)

    def hammer(k):
        go.wait()
        for i in range(300):
            bridge.log(("/zx120/front_cmd", "joint"), "/zx120/front_cmd: unknown joint 'stick_joint'")
            bridge.log((k, i), f"mistake {k}-{i}")

    threads = [threading.Thread(target=hammer, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    lines = capsys.readouterr().err.splitlines()
    assert sum("unknown joint 'stick_joint'" in line for line in lines) == 1
    assert len(lines) == 1 + 8 * 300 and all(line.count("warning: ros:") == 1 for line in lines)


def test_command_latency_comes_from_machine_yaml_or_the_scene(tmp_path):
    import shutil

    machine = tmp_path / "zx120"
    shutil.copytree(ROOT / "machines" / "zx120", machine)
    cfg = machine / "machine.yaml"
    cfg.write_text(cfg.read_text().replace("command_latency: 0.0", "command_latency: 0.15"))
    assert build_model(load_scene(DIG_CYCLE)).machines[0].command_latency == 0.0
    assert build_model(load_scene(DIG_CYCLE, [f"machine.config={cfg}"])).machines[0].command_latency == 0.15
    assert build_model(load_scene(DIG_CYCLE, [f"machine.config={cfg}", "machine.command_latency=0.3"])
                       ).machines[0].command_latency == 0.3
    cfg.write_text(cfg.read_text().replace("command_latency: 0.15", "command_latency: -1"))
    with pytest.raises(UserError, match="command_latency must be a number of seconds >= 0 and <= 10, got -1"):
        build_model(load_scene(DIG_CYCLE, [f"machine.config={cfg}"]))


def test_the_ros1_master_watch_says_a_gone_master_once_and_a_master_that_forgot_the_node(monkeypatch):
    """One slow probe is not a dead master; two misses in a row are, said once; a master back that still knows the
    node is said as such, and one that does not (a restarted roscore) is said as a master to restart the run for."""
    import threading

    from opera_taichi.ros import transport_ros1

    monkeypatch.setattr(transport_ros1, "MASTER_CHECK_S", 0.001)
    # per probe: 1 the master knows the node, -1 it answers but does not, None no answer
    script = [1, None, 1, None, None, None, 1, None, None, -1, -1, 1]
    done = threading.Event()

    class Probe:
        def lookupNode(self, caller, node):
            assert node == "/opera_taichi_1234"
            if not script:
                done.set()
                raise OSError("end of script")
            code = script.pop(0)
            if code is None:
                raise TimeoutError("timed out")
            return [code, "", "http://node:1"]

    said = []
    watch = transport_ros1.MasterWatch("http://127.0.0.1:1", "/opera_taichi_1234",
                                       lambda key, text: said.append((key, text)), probe=Probe())
    try:
        assert done.wait(30)
    finally:
        watch.close()
    texts = [t for _, t in said]
    assert len({k for k, _ in said}) == len(said)        # each its own key: the bridge says each once
    assert [("stopped" in t, "answers again" in t, "does not know this node" in t) for t in texts][:5] == [
        (True, False, False), (False, True, False), (True, False, False), (False, False, True), (False, True, False)]


def test_the_bridge_after_a_resume_a_stop_in_the_same_step_and_an_overflowing_twist():
    """(1) a cmd_vel of huge finite numbers whose track speeds overflow: logged and ignored, not the run's end;
    (2) a controller that takes over a machine already moving (a resumed run: the commands are gone) lets those
    speeds expire as its own; (3) a target and a release of the stop arriving in the same step: the target, given
    under the hold, does not act; (4) with --bridge-after-motion, a stop acts during the scene's motion."""
    sim, log, ctl, topics = _tracked_machine_and_bridge()
    T = typestore(2).types
    V = T["geometry_msgs/msg/Vector3"]
    try:
        ctl.handle(topics["tracks/cmd_vel"], T["geometry_msgs/msg/Twist"](linear=V(x=1e308, y=0, z=0),
                                                                            angular=V(x=0, y=0, z=1e308)))
        assert ctl.accepted == 0 and "give track speeds beyond any number" in log.lines[-1]
        # a machine left moving by commands this controller never saw
        arm = sim.machine.joint_names.index("arm_joint")
        sim.step(ot.MachineControl(qd_target={"arm_joint": 0.2}, track_speeds=(0.4, 0.4)))
        fresh = BridgeController(_Log(), command_timeout=0.5)
        fresh.bind(sim.model)
        while sim.t < 1.5:
            sim.step(fresh.control(sim, sim.t_next))
        q1, x1 = sim.machine.joint_states()[0][arm], sim.machine.base_pose()[0][0]
        while sim.t < 2.0:
            sim.step(fresh.control(sim, sim.t_next))
        assert abs(sim.machine.joint_states()[0][arm] - q1) < 0.005 and abs(sim.machine.base_pose()[0][0] - x1) < 0.01
        # under the hold: a boom target, then the release, both due in the same step
        boom = sim.machine.joint_names.index("boom_joint")
        fresh.handle(topics["emg_stop"], _msg("std_msgs/msg/Bool", data=True))
        for _ in range(10):
            sim.step(fresh.control(sim, sim.t_next))
        held = sim.machine.joint_states()[0][boom]
        fresh.handle(topics["boom/cmd"], _msg("std_msgs/msg/Float64", data=held + 0.3))
        fresh.handle(topics["emg_stop"], _msg("std_msgs/msg/Bool", data=False))
        for _ in range(250):
            sim.step(fresh.control(sim, sim.t_next))
        assert sim.machine.joint_states()[0][boom] == pytest.approx(held, abs=0.01)
        # a release sent again (the machine no longer held) with a command in the same step: the command acts
        fresh.handle(topics["boom/cmd"], _msg("std_msgs/msg/Float64", data=held + 0.3))
        fresh.handle(topics["emg_stop"], _msg("std_msgs/msg/Bool", data=False))
        for _ in range(250):
            sim.step(fresh.control(sim, sim.t_next))
        assert sim.machine.joint_states()[0][boom] > held + 0.1
    finally:
        sim.close()
    scripted = ot.Simulation.from_scene(DIG_CYCLE)
    try:
        ctl = BridgeController(_Log(), after_motion=True)
        ctl.bind(scripted.model)
        ctl.handle(_topics(scripted)["emg_stop"], _msg("std_msgs/msg/Bool", data=True))
        for _ in range(500):
            scripted.step(ctl.control(scripted, scripted.t_next))
        q_held = scripted.machine.joint_states()[0].copy()
        for _ in range(500):   # the script goes on moving its targets; the held machine does not follow
            scripted.step(ctl.control(scripted, scripted.t_next))
        assert scripted.machine.held and np.max(np.abs(scripted.machine.joint_states()[0] - q_held)) < 0.005
    finally:
        scripted.close()
