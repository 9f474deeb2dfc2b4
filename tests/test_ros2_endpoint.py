"""`--ros-tcp` against a ROS 2 endpoint: a stand-in for ROS-TCP-Endpoint's ROS 2 build (no ROS 2 runtime is
packaged for this machine), written from its code (tests/ros_tools.py), serves `opera-taichi run` as a process.

What it proves: the client registers OPERA's topics with the ROS 2 message names, its command JSON survives the ROS 2
endpoint cutting its last byte, every published message is CDR byte-identical to rosbags' serialiser and to
mcap-ros2-support's independent encoder, and a boom command in CDR moves the boom to its target (round trip)."""
import json
import signal

from ros_tools import StandInRos2Endpoint, start_run, stop, wait_for

from opera_taichi.ros.messages import msgdef, typestore

EXPECTED_NAMES = {
    "/zx120/joint_states": "sensor_msgs/JointState", "/zx120/odom": "nav_msgs/Odometry",
    "/zx120/base_link/pose": "geometry_msgs/PoseStamped", "/zx120/bucket/wrench": "geometry_msgs/WrenchStamped",
    "/zx120/soil_volume": "std_msgs/Float64", "/zx120/soil_mass": "std_msgs/Float64", "/tf": "tf2_msgs/TFMessage",
    "/clock": "rosgraph_msgs/Clock", "/terrain/points": "sensor_msgs/PointCloud2"}
EXPECTED_COMMANDS = {"/zx120/boom/cmd": "std_msgs/Float64", "/zx120/front_cmd": "com3_msgs/JointCmd",
                     "/zx120/emg_stop": "std_msgs/Bool"}


def test_ros2_endpoint_round_trip_and_cdr_on_the_wire(tmp_path):
    from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

    store = typestore(2)
    endpoint = StandInRos2Endpoint()
    args = ["scenes/zx120_excavation.yaml", "--set", "soil.overrides.radius=0.16", "--set", "motion=null",
            "--set", "sim.duration=3600", "--pace", "fast", "--ros-tcp", f"127.0.0.1:{endpoint.port}"]
    # (an hour of simulated time: at fast pace the run must outlast the exchange on any host; it is stopped below)
    proc, out, err = start_run(args, None, tmp_path, "ros2")
    try:
        wait_for(lambda: all(endpoint.messages(t) for t in EXPECTED_NAMES) or proc.poll() is not None, 120,
                 "a message on every output topic")
        assert proc.poll() is None, err.read_text()
        assert {t: endpoint.published[t] for t in EXPECTED_NAMES} == EXPECTED_NAMES
        assert {t: endpoint.subscribed[t] for t in EXPECTED_COMMANDS} == EXPECTED_COMMANDS
        assert endpoint.errors == []
        for topic, name in EXPECTED_NAMES.items():
            typename = name.replace("/", "/msg/")
            text, _ = msgdef(store, typename, 2)
            encode = serialize_dynamic(typename, text)[typename]
            decode = generate_dynamic(typename, text)[typename]
            raw = endpoint.messages(topic)[-1]
            assert raw[:4] == b"\x00\x01\x00\x00"              # CDR little endian, as rclpy serialises
            assert bytes(store.serialize_cdr(store.deserialize_cdr(raw, typename), typename)) == raw, topic
            assert encode(decode(raw)) == raw, topic

        def boom():
            msg = store.deserialize_cdr(endpoint.messages("/zx120/joint_states")[-1], "sensor_msgs/msg/JointState")
            return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, float(msg.position[list(msg.name).index(
                "boom_joint")])

        t0, q0 = boom()
        Float64 = store.types["std_msgs/msg/Float64"]
        endpoint.send("/zx120/boom/cmd", bytes(store.serialize_cdr(Float64(data=-0.5), "std_msgs/msg/Float64")))
        wait_for(lambda: abs(boom()[1] + 0.5) < 0.02, 120, "the boom at -0.5 rad")
        t1, _ = boom()
        assert t1 - t0 >= (abs(q0 + 0.5) - 0.02) / 0.70        # no faster than the boom's speed limit
        clock = [store.deserialize_cdr(r, "rosgraph_msgs/msg/Clock").clock for r in endpoint.messages("/clock")]
        ticks = [c.sec + c.nanosec * 1e-9 for c in clock]
        assert ticks == sorted(ticks) and ticks[-1] > t1 - 0.5
        # a malformed command (wrong array length) is logged once and ignored; the run goes on
        JointCmd = store.types["com3_msgs/msg/JointCmd"]
        import numpy as np

        bad = JointCmd(joint_name=["boom_joint", "arm_joint"], control_type=0, position=np.array([0.1]),
                       velocity=np.zeros(0), effort=np.zeros(0))
        for _ in range(2):
            endpoint.send("/zx120/front_cmd", bytes(store.serialize_cdr(bad, "com3_msgs/msg/JointCmd")))
        endpoint.send("/zx120/boom/cmd", bytes(store.serialize_cdr(Float64(data=-0.7), "std_msgs/msg/Float64")))
        wait_for(lambda: abs(boom()[1] + 0.7) < 0.02, 120, "the boom at -0.7 rad")
        # the endpoint restarts: the client connects again, registers its topics again and goes on
        endpoint.drop()
        wait_for(lambda: endpoint.connections == 2 and EXPECTED_COMMANDS.keys() <= endpoint.subscribed.keys(), 60,
                 "the client back with its subscriptions")
        endpoint.send("/zx120/boom/cmd", bytes(store.serialize_cdr(Float64(data=-0.9), "std_msgs/msg/Float64")))
        wait_for(lambda: abs(boom()[1] + 0.9) < 0.02, 120, "the boom at -0.9 rad (raised) after the reconnection")
    finally:
        code = stop(proc, signal.SIGTERM, timeout=60)
        endpoint.close()
    text = err.read_text()
    assert code == 143, text
    assert text.count("needs position[] as long as joint_name[] (2), got 1") == 1
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "interrupted"
    assert any("reconnected" in w for w in manifest["run_warnings"])  # the loss and the reconnection, both kept
    assert "ROS-TCP-Endpoint v0.7.0" in text and "ROS2: CDR" in text
    assert text.count("lost the endpoint") == 1 and "reconnected" in text
