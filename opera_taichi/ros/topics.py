"""The topic table: OPERA's topics for each machine (namespace = machine name), their ROS types and rates.

Keys are the default names relative to the machine's namespace (`boom/cmd`, `joint_states`, `bucket/wrench`), or
`tf`, `clock` and `terrain` for the three topics the whole simulation publishes once. The scene's `bridge.topics`
renames any of them (a name without a leading `/` is relative to the namespace) and `bridge.rates` sets the rate of
any output; both are checked here so `validate` catches a misspelt key.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

from ..errors import UserError

# Output rates, Hz of simulated time (OPERA's simulators publish joint_states at 25 Hz; /clock at 100 Hz is what a
# use_sim_time stack needs to run timers smoothly; the terrain cloud is large and changes slowly).
DEFAULT_RATES = {"joint_states": 25.0, "odom": 25.0, "base_link/pose": 25.0, "wrench": 25.0, "soil_mass": 5.0,
                 "soil_volume": 5.0, "tf": 25.0, "clock": 100.0, "terrain": 1.0}
GLOBAL_NAMES = {"tf": "/tf", "clock": "/clock", "terrain": "/terrain/points"}
_NAME = re.compile(r"/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*")


@dataclass(frozen=True)
class Topic:
    key: str              # the scene's key for it (default relative name, or tf / clock / terrain)
    name: str             # resolved absolute name
    type: str             # rosbags type name, e.g. sensor_msgs/msg/JointState (the same for ROS 1 and ROS 2)
    inbound: bool         # a command the simulation subscribes to
    machine: str | None   # owning machine, None for the global topics
    rate: float | None    # Hz of simulated time (outputs)
    item: str | None = None   # the joint of a per-joint command, the soil link of a wrench

    @property
    def endpoint_type(self) -> str:
        """The type as ROS 1 tools and the ROS-TCP-Endpoint name it: sensor_msgs/JointState."""
        return self.type.replace("/msg/", "/")


def short(name: str, suffix: str) -> str:
    """boom_joint -> boom, bucket_link -> bucket."""
    return name[: -len(suffix)] if name.endswith(suffix) and len(name) > len(suffix) else name


def _resolve(name: str, namespace: str) -> str:
    return name if name.startswith("/") else f"/{namespace}/{name}"


def topic_table(model, bridge=None) -> list[Topic]:
    """Every topic of the run: per machine its commands and outputs, then tf, clock and terrain (with soil).

    `bridge` is the scene's BridgeConfig (or None for the defaults: a bag of a run without a bridge)."""
    renames = dict(getattr(bridge, "topics", None) or {})
    rates = dict(getattr(bridge, "rates", None) or {})
    namespace_given = getattr(bridge, "namespace", None)
    if namespace_given is not None and len(model.machines) > 1:
        raise UserError("bridge.namespace: the scene has several machines; each uses its own name as namespace "
                        "(remove bridge.namespace)")
    rows: list[tuple[str, str, str, bool, str | None, str | None, str | None]] = []  # key, default, type, in, ...
    for m in model.machines:
        desc = m.description
        ns = namespace_given or m.name
        for j in m.joints:
            rows.append((f"{short(j, '_joint')}/cmd", ns, "std_msgs/msg/Float64", True, m.name, j, None))
        rows.append(("front_cmd", ns, "com3_msgs/msg/JointCmd", True, m.name, None, None))
        if not m.fixed_base and desc.tracks:
            rows.append(("tracks/cmd_vel", ns, "geometry_msgs/msg/Twist", True, m.name, None, None))
        rows.append(("emg_stop", ns, "std_msgs/msg/Bool", True, m.name, None, None))
        rows.append(("joint_states", ns, "sensor_msgs/msg/JointState", False, m.name, None, "joint_states"))
        rows.append(("odom", ns, "nav_msgs/msg/Odometry", False, m.name, None, "odom"))
        rows.append(("base_link/pose", ns, "geometry_msgs/msg/PoseStamped", False, m.name, None, "base_link/pose"))
        if model.soil is not None:
            for link in desc.soil_links:
                rows.append((f"{short(link, '_link')}/wrench", ns, "geometry_msgs/msg/WrenchStamped", False, m.name,
                             link, "wrench"))
            rows.append(("soil_volume", ns, "std_msgs/msg/Float64", False, m.name, None, "soil_volume"))
            rows.append(("soil_mass", ns, "std_msgs/msg/Float64", False, m.name, None, "soil_mass"))
    if model.machines:
        rows.append(("tf", "", "tf2_msgs/msg/TFMessage", False, None, None, "tf"))
    rows.append(("clock", "", "rosgraph_msgs/msg/Clock", False, None, None, "clock"))
    if model.soil is not None:
        rows.append(("terrain", "", "sensor_msgs/msg/PointCloud2", False, None, None, "terrain"))

    keys = sorted({r[0] for r in rows})
    for what, given in (("topics", renames), ("rates", rates)):
        for key in given:
            if key not in keys:
                from difflib import get_close_matches

                close = get_close_matches(str(key), keys, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise UserError(f"bridge.{what}.{key}: no such topic in this scene{hint}; keys: {', '.join(keys)}")
    inbound_keys = {r[0] for r in rows if r[3]}
    for key in rates:
        if key in inbound_keys:
            raise UserError(f"bridge.rates.{key}: a command topic has no rate (it is applied when it arrives)")
    for key, name in renames.items():
        if not isinstance(name, str) or not _NAME.fullmatch(name):
            raise UserError(f"bridge.topics.{key}: expected a ROS topic name (letters, digits, _ and /), got {name!r}")

    topics: list[Topic] = []
    for key, ns, typ, inbound, machine, item, rate_key in rows:
        name = renames.get(key, GLOBAL_NAMES.get(key, key))
        name = _resolve(name, ns) if ns else (name if name.startswith("/") else f"/{name}")
        rate = None
        if not inbound:
            rate = float(rates.get(key, DEFAULT_RATES[rate_key]))
        topics.append(Topic(key, name, typ, inbound, machine, rate, item))
    names = [t.name for t in topics]
    for t in topics:
        if names.count(t.name) > 1:
            raise UserError(f"bridge.topics: two topics are named {t.name} (rename one of them)")
    return topics
