"""ROS bridge: command round-trip latency and the real-time factor with a bridge attached (needs Debian's ROS 1).

    python benchmarks/ros_latency.py [--transport ros1|ros_tcp|both] [--repeats 10] [--rtf-duration 5]
                                    [--rtf-repeats 2] [--no-latency | --no-rtf]

Latency: a roscore on a free port, `opera-taichi run scenes/zx120_dig_cycle.yaml --set motion=null --ros1` (or
`--ros-tcp` through the ROS-TCP-Endpoint's ROS 1 build from ../shared/thirdparty), and a rospy node in this process
that publishes a boom target on /zx120/boom/cmd and waits for the first /zx120/joint_states message whose boom angle
has left its rest value (> 1e-4 rad): wall time from publish() to that message's arrival, `repeats` times (the
boom goes back and forth, at rest before each). Measured at the default joint_states rate (25 Hz: up to 40 ms of
it is waiting for the next sample) and at 1 kHz (every step: the transport and one step of dead time).

Real-time factor: `scenes/zx120_excavation.yaml` (default resolution) for `rtf-duration` simulated seconds with
`--pace fast`, without a bridge and with `--ros1` (all topics published, nobody subscribed; then with a
subscriber to joint_states, wrench and terrain), from each run's manifest.json (bed settling and kernel compilation
excluded).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import xmlrpc.client
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench_args import at_least, host_line  # noqa: E402  (beside this script)
ENDPOINT = ROOT.parent / "shared" / "thirdparty" / "ros_tcp_endpoint-ros1" / "src"


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait(cond, timeout, what):
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise SystemExit(f"timed out waiting for {what}")
        time.sleep(0.05)


def master_up(uri):
    try:
        _, _, state = xmlrpc.client.ServerProxy(uri).getSystemState("/bench")
        return any(t == "/rosout_agg" for t, _ in state[0])
    except OSError:
        return False


def subscribed(uri, topic):
    _, _, state = xmlrpc.client.ServerProxy(uri).getSystemState("/bench")
    return any(t == topic for t, _ in state[1])


def start(cmd, env, log, **kw):
    return subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True, **kw)


def stop(proc, sig=signal.SIGINT):
    if proc.poll() is None:
        os.killpg(proc.pid, sig)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def latency(transport: str, rate: float, repeats: int, env: dict, tmp: Path, uri: str):
    from opera_taichi.ros.transport_ros1 import import_rospy

    rospy = import_rospy()
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64

    procs = []
    args = [sys.executable, str(ROOT / "cli.py"), "run", "scenes/zx120_dig_cycle.yaml", "--set", "motion=null",
            "--set", "sim.duration=600", "--set", f"bridge={{kind: ros1, rates: {{joint_states: {rate}}}}}",
            "--out", str(tmp / f"lat-{transport}-{rate:g}"), "--quiet"]
    if transport == "ros_tcp":
        port = free_port()
        procs.append(start(["/usr/bin/python3", "-m", "ros_tcp_endpoint.default_server_endpoint", "_tcp_ip:=127.0.0.1",
                            f"_tcp_port:={port}"], dict(env, PYTHONPATH=str(ENDPOINT)),
                           open(tmp / f"endpoint-{rate:g}.log", "w")))
        time.sleep(2.0)
        args += ["--ros-tcp", f"127.0.0.1:{port}"]
    else:
        args += ["--ros1"]
    run = start(args, env, open(tmp / f"run-{transport}-{rate:g}.log", "w"), cwd=ROOT)
    procs.append(run)
    latest = {}
    arrived = threading.Condition()

    def on_state(msg):
        with arrived:
            latest["q"] = msg.position[list(msg.name).index("boom_joint")]
            latest["t"] = time.perf_counter()
            arrived.notify_all()

    rospy.Subscriber("/zx120/joint_states", JointState, on_state, tcp_nodelay=True, queue_size=100)
    pub = rospy.Publisher("/zx120/boom/cmd", Float64, queue_size=1, tcp_nodelay=True)
    try:
        wait(lambda: "q" in latest, 120, "joint_states")
        wait(lambda: subscribed(uri, "/zx120/boom/cmd") and pub.get_num_connections() > 0, 60, "the boom subscriber")
        out = []
        targets = [-0.6, -0.8] * repeats
        for target in targets[:repeats]:
            rest = latest["q"]
            for _ in range(200):          # at rest: three samples within 1e-6 rad
                with arrived:
                    arrived.wait(1.0)
                    q1 = latest["q"]
                with arrived:
                    arrived.wait(1.0)
                    q2 = latest["q"]
                if abs(q2 - q1) < 1e-6:
                    rest = q2
                    break
            t0 = time.perf_counter()
            pub.publish(Float64(target))
            with arrived:
                arrived.wait_for(lambda: abs(latest["q"] - rest) > 1e-4, timeout=10)
                out.append(latest["t"] - t0)
            wait(lambda: abs(latest["q"] - target) < 0.01, 30, "the boom at its target")
        return out
    finally:
        for p in reversed(procs):
            stop(p)


def rtf(duration: float, args: list[str], env: dict, tmp: Path, name: str, listen=None) -> float:
    out = tmp / name
    cmd = [sys.executable, str(ROOT / "cli.py"), "run", "scenes/zx120_excavation.yaml", "--set",
           f"sim.duration={duration}", "--pace", "fast", "--out", str(out), "--quiet", *args]
    listeners = []
    proc = start(cmd, env, open(tmp / f"{name}.log", "w"), cwd=ROOT)
    if listen:
        for topic in listen:
            listeners.append(start(["rostopic", "hz", topic], env, subprocess.DEVNULL))
    proc.wait()
    for p in listeners:
        stop(p)
    return json.loads((out / "manifest.json").read_text())["real_time_factor"]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--transport", choices=("ros1", "ros_tcp", "both"), default="both")
    ap.add_argument("--repeats", type=at_least(1, int, "a whole number"), default=10)
    ap.add_argument("--rtf-duration", type=at_least(0.1), default=5.0)
    ap.add_argument("--rtf-repeats", type=at_least(1, int, "a whole number"), default=2)
    ap.add_argument("--no-rtf", action="store_true")
    ap.add_argument("--no-latency", action="store_true")
    a = ap.parse_args()
    print(host_line())
    tmp = Path(tempfile.mkdtemp(prefix="ros-bench-"))
    port = free_port()
    uri = f"http://127.0.0.1:{port}"
    os.environ.update(ROS_MASTER_URI=uri, ROS_IP="127.0.0.1", ROS_HOME=str(tmp / "ros_home"))
    env = dict(os.environ)
    core = start(["roscore", "-p", str(port)], env, open(tmp / "roscore.log", "w"))
    try:
        wait(lambda: master_up(uri), 30, "roscore")
        from opera_taichi.ros.transport_ros1 import import_rospy

        import_rospy().init_node("latency_probe", anonymous=True, disable_signals=True)
        transports = [] if a.no_latency else ["ros1", "ros_tcp"] if a.transport == "both" else [a.transport]
        for tr in transports:
            for rate in (25.0, 1000.0):
                lat = [x * 1e3 for x in latency(tr, rate, a.repeats, env, tmp, uri)]
                print(f"{tr:8s} joint_states {rate:6g} Hz: command -> motion in joint_states: median "
                      f"{statistics.median(lat):.1f} ms (min {min(lat):.1f}, max {max(lat):.1f}, n {len(lat)})",
                      flush=True)
        if not a.no_rtf:   # the three set-ups in turn, `rtf-repeats` times (a shared host's load drifts)
            found = {"no bridge": [], "--ros1": [], "--ros1 with 4 subscribers": []}
            for k in range(a.rtf_repeats):
                found["no bridge"].append(rtf(a.rtf_duration, [], env, tmp, f"rtf-none-{k}"))
                found["--ros1"].append(rtf(a.rtf_duration, ["--ros1"], env, tmp, f"rtf-ros1-{k}"))
                found["--ros1 with 4 subscribers"].append(rtf(
                    a.rtf_duration, ["--ros1"], env, tmp, f"rtf-ros1-listened-{k}",
                    listen=["/zx120/joint_states", "/zx120/bucket/wrench", "/terrain/points", "/clock"]))
            print(f"real-time factor, zx120_excavation.yaml, {a.rtf_duration:g} s simulated, --pace fast: " + "; ".join(
                f"{name} {statistics.median(v):.3f} ({', '.join(f'{x:.3f}' for x in v)})" for name, v in found.items()),
                flush=True)
    finally:
        stop(core)
    print(f"logs: {tmp}")


if __name__ == "__main__":
    main()
