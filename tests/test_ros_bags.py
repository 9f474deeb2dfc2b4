"""`output.bag: mcap | ros1`: a coarse excavation (scripted, no bridge) writes run.mcap / run.bag, read back with
rosbags (and run.mcap also with mcap-ros2-support's reader, another implementation): every topic is there, at its
rate of simulated time, and the joint states are those of joints.csv."""
import csv
import math
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

import opera_taichi as ot
from opera_taichi.ros.topics import DEFAULT_RATES

ROOT = Path(__file__).resolve().parent.parent
DURATION = 1.5
# (periods of whole rigid steps, 2 ms in the scene: a sample is taken at the first step at or after it is due)
RATES = {"/clock": 100, "/zx120/joint_states": 25, "/zx120/odom": 25, "/zx120/base_link/pose": 25,
         "/zx120/bucket/wrench": 50, "/tf": 25, "/zx120/soil_mass": 5, "/zx120/soil_volume": 5, "/terrain/points": 2}
TYPES = {"/clock": "rosgraph_msgs/msg/Clock", "/zx120/joint_states": "sensor_msgs/msg/JointState",
         "/zx120/odom": "nav_msgs/msg/Odometry", "/zx120/base_link/pose": "geometry_msgs/msg/PoseStamped",
         "/zx120/bucket/wrench": "geometry_msgs/msg/WrenchStamped", "/tf": "tf2_msgs/msg/TFMessage",
         "/zx120/soil_mass": "std_msgs/msg/Float64", "/zx120/soil_volume": "std_msgs/msg/Float64",
         "/terrain/points": "sensor_msgs/msg/PointCloud2"}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One coarse run per bag kind, shared by the tests below."""
    tmp = tmp_path_factory.mktemp("bags")
    return {kind: _run(tmp, kind) for kind in ("mcap", "ros1")}


def _run(tmp_path, kind):
    scene = ot.load_scene(ROOT / "scenes" / "zx120_excavation.yaml",
                          ["soil.overrides.radius=0.16", f"sim.duration={DURATION}", f"output.bag={kind}",
                           "output.plots=false",
                           # a bag takes the bridge's rates when the scene has one (the bridge itself is not started)
                           "bridge={kind: ros1, rates: {bucket/wrench: 50, terrain: 2}}"])
    out = tmp_path / kind
    ot.run_scene(scene, out_dir=out, quiet=True)
    return out


def _read(path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    stamps, msgs, types = defaultdict(list), defaultdict(list), {}
    store = get_typestore(Stores.ROS2_HUMBLE if path.suffix == ".mcap" else Stores.ROS1_NOETIC)
    with AnyReader([path], default_typestore=store) as reader:
        for con, ts, raw in reader.messages():
            types[con.topic] = con.msgtype
            stamps[con.topic].append(ts * 1e-9)
            msgs[con.topic].append(reader.deserialize(raw, con.msgtype))
    return stamps, msgs, types


@pytest.mark.parametrize("kind", ["mcap", "ros1"])
def test_bag_holds_every_topic_at_its_rate(runs, kind):
    out = runs[kind]
    path = out / ("run.mcap" if kind == "mcap" else "run.bag")
    stamps, msgs, types = _read(path)
    assert types == TYPES
    for topic, rate in RATES.items():
        times = np.array(stamps[topic])
        assert len(times) == math.floor(DURATION * rate + 1e-9) + 1, topic       # t = 0 included
        np.testing.assert_allclose(np.diff(times), 1.0 / rate, atol=1e-6, err_msg=topic)
    assert DEFAULT_RATES["joint_states"] == 25 and DEFAULT_RATES["clock"] == 100
    # the joint states are the run's own: joints.csv at 100 Hz holds the same samples
    with open(out / "joints.csv") as fh:
        rows = {round(float(r["t"]), 6): r for r in csv.DictReader(fh)}
    for t, js in zip(stamps["/zx120/joint_states"], msgs["/zx120/joint_states"]):
        assert js.header.stamp.sec + js.header.stamp.nanosec * 1e-9 == pytest.approx(t, abs=1e-9)
        row = rows[round(t, 6)]
        for name, q in zip(js.name, js.position):   # joints.csv has the actuated joints; the welded one rests at 0
            assert q == pytest.approx(float(row[f"{name}.q"]) if f"{name}.q" in row else 0.0, abs=1e-8)
    # what the bucket holds: soil_volume is soil_mass at the bulk density
    mass = [m.data for m in msgs["/zx120/soil_mass"]]
    volume = [m.data for m in msgs["/zx120/soil_volume"]]
    np.testing.assert_allclose(np.array(mass) / 1474.0, volume, rtol=1e-12)
    cloud = msgs["/terrain/points"][-1]
    assert cloud.width * cloud.height * cloud.point_step == len(cloud.data) and cloud.is_dense
    if kind == "ros1":
        assert all(m.header.seq == i for i, m in enumerate(msgs["/zx120/joint_states"]))


def test_mcap_reads_with_mcap_ros2_support(runs):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = runs["mcap"]
    counts = defaultdict(int)
    with open(out / "run.mcap", "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            counts[channel.topic] += 1
            assert schema.name == TYPES[channel.topic]
            if channel.topic == "/zx120/joint_states":
                assert list(decoded.name) == ["swing_joint", "boom_joint", "arm_joint", "bucket_joint",
                                              "bucket_end_joint"]
                assert len(decoded.position) == len(decoded.velocity) == len(decoded.effort) == 5
    assert dict(counts) == {t: math.floor(DURATION * r + 1e-9) + 1 for t, r in RATES.items()}


@pytest.mark.parametrize("kind", ["mcap", "ros1"])
def test_compare_reads_a_runs_own_bag_as_its_joint_log(runs, kind, tmp_path):
    """The run against its own bag: the same joint profile (25 Hz, linearly interpolated to 100: within 1 mrad), no
    lag."""
    from opera_taichi.studies.compare import compare

    out = runs[kind]
    res = compare(out, joints=out / ("run.mcap" if kind == "mcap" else "run.bag"), out=tmp_path / "cmp")
    assert set(res["joints"]) == {"swing_joint", "boom_joint", "arm_joint", "bucket_joint"}
    assert res["joints_rmse_rad"] < 1e-3 and res["joints_lag_s"] == 0.0


def _ros1_messages(paths):
    from rosbags.rosbag1 import Reader

    out = []
    for path in paths:
        with Reader(path) as reader:
            out += [(con.topic, ts, bytes(raw)) for con, ts, raw in reader.messages()]
    return out


def test_a_killed_and_resumed_run_has_every_ros1_message_once(tmp_path):
    """SIGKILL after the first checkpoint, a part of a killed resume left behind (rosbags refuses to overwrite a
    file), then a resume to the end: the run.bag part finished at the checkpoint and the parts after it hold the
    messages of the run left alone, header seq included, each once. (The machine alone: no soil, fast.)"""
    import json
    import os
    import subprocess
    import sys

    from conftest import kill_after_first_checkpoint
    from opera_taichi.ros.bag import bag_parts

    scene = ROOT / "scenes" / "zx120_dig_cycle.yaml"
    args = [sys.executable, str(ROOT / "cli.py"), "run", str(scene), "--quiet", "--set", "sim.duration=6",
            "--set", "output.bag=ros1", "--set", "output.plots=false"]
    alone, killed = tmp_path / "alone", tmp_path / "killed"
    assert subprocess.run([*args, "--out", str(alone)], cwd=ROOT).returncode == 0
    proc = subprocess.Popen([*args, "--checkpoint-every", "0.5", "--out", str(killed)], cwd=ROOT)
    kill_after_first_checkpoint(proc, killed)
    assert json.loads((killed / "manifest.json").read_text())["status"] == "running"
    latest = sorted((killed / "checkpoints").glob("step-*.ckpt.npz"))[-1]
    step = int(latest.name.split("-")[1].split(".")[0])
    (killed / f"run-from-step-{step + 1:09d}.bag").write_bytes(b"#ROSBAG V2.0\n")  # a killed resume's part
    resumed = subprocess.run([sys.executable, str(ROOT / "cli.py"), "run", "--resume", str(killed), "--quiet"],
                             cwd=ROOT, capture_output=True, text=True, env=dict(os.environ))
    assert resumed.returncode == 0, resumed.stderr
    parts = bag_parts(killed, ".bag")
    assert parts[0].name == "run.bag" and len(parts) >= 2
    expected = _ros1_messages([alone / "run.bag"])
    assert len(expected) > 1000
    assert _ros1_messages(parts) == expected
