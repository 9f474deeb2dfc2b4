"""The ROS bridge of a run: one transport (rospy node or ROS-TCP-Endpoint client), the controller that turns commands
into Controls, and a ThreadedObserver that publishes the outputs, each topic at its own rate of simulated time.

The transport connects when the bridge is made (a missing master or endpoint is a one-line exit 2 before the soil is
built); the topics are registered when the run starts and the model is known. Publishing runs on the observer's
thread: per topic, only the newest sample waits there, so a slow network never slows the simulation.
"""
from __future__ import annotations

import os
import sys
import threading
from functools import partial

from ..errors import UserError
from ..observers import ThreadedObserver
from .controller import BridgeController
from .messages import MessageBuilder, deserialize
from .sampler import Sampler
from .topics import topic_table

DEFAULT_ENDPOINT = "127.0.0.1:10000"   # the ROS-TCP-Endpoint's own default port


class RosBridge(ThreadedObserver):
    rate = None   # asked after every step; the sampler says (cheaply) when a topic is due

    def __init__(self, config, *, quiet: bool = False, transport=None):
        self.config = config
        self.quiet = quiet
        self._said: set = set()
        self._said_lock = threading.Lock()
        self._sim = None
        self.controller = BridgeController(self.log, after_motion=bool(config.after_motion),
                                           command_timeout=config.command_timeout)
        if transport is None:
            transport = make_transport(config, self.log)
        self.transport = transport

    @property
    def key(self) -> str:
        return "RosBridge"

    def log(self, key, text: str) -> None:
        """Say `text` once per key (a malformed message, a lost connection): one line, never an exception."""
        # rospy calls back on one thread per publisher connection: two mistakes at once must not share a line
        with self._said_lock:
            if key in self._said:
                return
            self._said.add(key)
            line = f"ros: {text}"
            if self._sim is not None:
                self._sim._warn(line)      # printed unless --quiet, and kept in the manifest's run_warnings
            elif not self.quiet:
                print(f"warning: {line}", file=sys.stderr)

    # ------------------------------------------------------------------------------------------ observer
    def start(self, sim, run) -> None:
        self._sim = sim
        self.topics = topic_table(sim.model, self.config)
        self.controller.bind(sim.model)
        self.builder = MessageBuilder(self.transport.ros_version)
        self.sampler = Sampler(sim, self.topics)
        for topic in self.topics:
            if topic.inbound:
                self.transport.subscribe(topic.name, topic.type, partial(self._on_bytes, topic))
            else:
                self.transport.advertise(topic.name, topic.type)
        super().start(sim, run)
        if not self.quiet:
            ins = ", ".join(t.name for t in self.topics if t.inbound)
            print(f"ros: {describe(self.transport)}; commands on {ins}; {sum(not t.inbound for t in self.topics)} "
                  f"output topics (joint_states at {self._rate('joint_states')} Hz, /clock at "
                  f"{self._rate('clock')} Hz of simulated time)", file=sys.stderr)

    def _rate(self, key: str):
        return next((f"{t.rate:g}" for t in self.topics if t.key == key), "-")

    def _on_bytes(self, topic, data: bytes) -> None:
        try:
            msg = deserialize(self.builder.store, self.transport.ros_version, data, topic.type)
        except Exception as exc:  # rosbags raises several types for bytes that are not the message
            self.log((topic.name, "decode"), f"{topic.name}: not a {topic.endpoint_type} ({type(exc).__name__}: "
                                             f"{exc}); message ignored (said once)")
            return
        try:
            self.controller.handle(topic, msg)
        except Exception as exc:  # a field of an unexpected type: the user's message, not our bug
            self.log((topic.name, "field"), f"{topic.name}: {type(exc).__name__}: {exc}; message ignored (said once)")

    def snapshot(self, sim):
        return self.sampler.sample(sim)

    def merge(self, older: dict, newer: dict) -> dict:
        older.update(newer)   # latest wins per topic; a topic the newer sample does not carry still goes out
        return older

    def publish(self, snap: dict) -> None:
        for name, (topic, data) in snap.items():
            self.transport.publish(name, self.builder.serialize(self.builder.build(topic, data), topic.type))

    def close(self, sim, status, message) -> None:
        try:
            super().close(sim, status, message)
        finally:
            self.transport.close()


def describe(transport) -> str:
    if transport.protocol == "ROS1" and hasattr(transport, "rospy"):
        from .transport_ros1 import master_uri

        return f"ROS 1 node {transport.rospy.get_name()} on {master_uri()}"
    return (f"ROS-TCP-Endpoint {transport.version or '?'} at {transport.host}:{transport.port} "
            f"({transport.protocol}: {'ROS 1 serialisation' if transport.protocol == 'ROS1' else 'CDR'})")


def make_transport(config, log):
    if config.kind == "ros1":
        from .messages import typestore
        from .transport_ros1 import Ros1Transport

        if config.address:  # the scene names the master
            os.environ["ROS_MASTER_URI"] = config.address
        return Ros1Transport(typestore(1), log=log)
    from .transport_tcp import RosTcpTransport

    return RosTcpTransport(config.address or DEFAULT_ENDPOINT, log)


def run_parts(scene, *, ros1: bool = False, ros_tcp: str | None = None, pace: str | None = None,
              after_motion: bool = False, quiet: bool = False) -> tuple[object | None, list]:
    """The controller and observers `run` adds for its bridge and pace flags (flags override the scene's `bridge`,
    which is updated so the manifest records what ran). Connects now: a missing master or endpoint is exit 2."""
    from ..pacing import RealTimePacer
    from ..scene import BridgeConfig

    bridge = scene.bridge
    if ros1 or ros_tcp is not None:
        base = bridge.model_dump() if bridge is not None else {}
        if ros1:  # the scene's master URI (bridge.address, or --set bridge.address=...) stays; an endpoint's goes
            keep = base.get("address") if base.get("kind") in (None, "ros1") else None
            base.update(kind="ros1", address=keep)
        else:
            base.update(kind="ros_tcp", address=ros_tcp)
        bridge = scene.bridge = BridgeConfig.model_validate(base)
    if after_motion:
        if bridge is None:
            raise UserError("--bridge-after-motion: only with a bridge (--ros1, --ros-tcp HOST:PORT or the scene's "
                            "bridge)")
        bridge.after_motion = True
    if pace is not None and bridge is not None:
        bridge.pace = pace
    pace = pace or (bridge.pace if bridge is not None else "fast")
    observers: list = []
    controller = None
    if bridge is not None:
        from ..model import machine_entries

        if not scene.machine and not scene.machines:
            raise UserError("bridge: the scene has no machine to drive (add a machine section)")
        if bridge.kind == "ros_tcp":
            from .transport_tcp import parse_address

            parse_address(bridge.address or DEFAULT_ENDPOINT, "--ros-tcp" if ros_tcp else "bridge.address")
        node = RosBridge(bridge, quiet=quiet)   # connects: a missing master or endpoint stops here
        scripted = [key for key, _, motion in machine_entries(scene) if motion is not None]
        if scripted and not bridge.after_motion and not quiet:
            print(f"warning: {scripted[0]}.motion set aside: the ROS bridge commands the machine "
                  f"(--bridge-after-motion runs the motion first)", file=sys.stderr)
        controller = node.controller
        observers.append(node)
    if pace == "realtime":
        observers.append(RealTimePacer(quiet=quiet))
    return controller, observers
