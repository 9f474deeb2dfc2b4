"""What the ROS outputs read from the simulation, each topic at its own rate (simulated time).

`Sampler.sample(sim)` runs in the simulation's thread after a step: it copies the few numbers of the topics that are
due (a cheap comparison when none is) and returns {topic name: (Topic, data)}; building and sending the messages is
left to a publisher thread (bridge) or a bag writer.
"""
from __future__ import annotations

import math

from ..geometry import quat_to_matrix
from .topics import Topic


class Sampler:
    def __init__(self, sim, topics: list[Topic]):
        self.outputs = [t for t in topics if not t.inbound]
        several = len(sim.machines) > 1
        self._frame = {name: (lambda link, n=name: f"{n}/{link}" if several else link) for name in sim.machines}
        self._period = [1.0 / t.rate if t.rate and t.rate * sim.model.dt < 1.0 else None for t in self.outputs]
        self._next = [0.0] * len(self.outputs)
        self._next_any = 0.0
        # soil tools of each machine (binding index, link) and their hulls, for wrench and load
        self._tools: dict[str, list[tuple[int, str]]] = {}
        for i, b in enumerate(sim.model.bindings):
            if b.owner is not None:
                self._tools.setdefault(b.owner, []).append((i, b.link))
        self._planes = None
        self._density = float(sim.model.soil.bulk.density) if sim.model.soil is not None else None

    def get_state(self) -> dict:
        """When each topic is next due: a resumed run samples at the steps the run left alone would have."""
        return {"next": list(self._next)}

    def set_state(self, state: dict) -> None:
        nxt = state.get("next")
        if isinstance(nxt, list) and len(nxt) == len(self._next):
            self._next = [float(v) for v in nxt]
            self._next_any = min(self._next) if self._next else 0.0

    def due(self, t: float) -> bool:
        return t + 1e-9 >= self._next_any

    def sample(self, sim) -> dict | None:
        """{topic name: (Topic, data)} of the topics due now, or None."""
        t = sim.t
        if not self.due(t):
            return None
        out: dict = {}
        cache: dict = {}
        for k, topic in enumerate(self.outputs):
            if t + 1e-9 < self._next[k]:
                continue
            period = self._period[k]
            self._next[k] = (math.floor(t / period + 1e-6) + 1) * period if period is not None else t + 0.5 * sim.model.dt
            out[topic.name] = (topic, self._data(sim, topic, cache))
        self._next_any = min(self._next)
        return out

    # ------------------------------------------------------------------------------------------ per topic
    def _data(self, sim, topic: Topic, cache: dict) -> dict:
        t, kind = sim.t, topic.type
        if kind == "rosgraph_msgs/msg/Clock":
            return {"t": t}
        if kind == "sensor_msgs/msg/PointCloud2":
            grid = sim.model.soil.grid
            return {"t": t, "x": grid.x, "y": grid.y, "z": sim.soil.heightmap(grid.x, grid.y)}
        if kind == "tf2_msgs/msg/TFMessage":
            transforms = []
            for name in sim.machines:
                base = self._base(sim, name, cache)
                transforms.append(("world", base["frame"], base["pos"], base["quat"]))
            return {"t": t, "transforms": transforms}
        m = sim.machines[topic.machine]
        if kind == "sensor_msgs/msg/JointState":
            q, qd, effort = m.urdf_joint_states()
            return {"t": t, "names": list(m.urdf_joint_names), "q": q, "qd": qd, "effort": effort}
        if kind in ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped"):
            return self._base(sim, topic.machine, cache)
        if kind == "geometry_msgs/msg/WrenchStamped":
            index = next(i for i, link in self._tools[topic.machine] if link == topic.item)
            _, quat, _, _ = m.link_state(topic.item)
            rot = quat_to_matrix(quat)              # link -> world; the wrench is sent in the link's frame
            w = sim.tool_wrench[index]
            return {"t": t, "frame": self._frame[topic.machine](topic.item), "force": rot.T @ w[:3],
                    "torque": rot.T @ w[3:]}
        if kind == "std_msgs/msg/Float64":        # soil_mass / soil_volume: what the machine's buckets hold
            mass = self._load(sim, topic.machine, cache)
            value = mass if topic.key == "soil_mass" else mass / self._density
            return {"t": t, "value": value}
        raise ValueError(f"no sampler for {kind}")

    def _base(self, sim, name: str, cache: dict) -> dict:
        key = ("base", name)
        if key not in cache:
            m = sim.machines[name]
            pos, quat, v, w = m.link_state(m.base_link)
            rot = quat_to_matrix(quat)
            cache[key] = {"t": sim.t, "frame": self._frame[name](m.base_link), "pos": pos, "quat": quat,
                          "v_local": rot.T @ v, "w_local": rot.T @ w}
        return cache[key]

    def _load(self, sim, name: str, cache: dict) -> float:
        key = ("load", name)
        if key not in cache:
            from ..observers import hull_halfspaces, inside_tools

            if self._planes is None:
                self._planes = [hull_halfspaces(b.mesh) for b in sim.model.bindings]
            parts = sim.soil.particles()
            masks = inside_tools(sim, self._planes, parts["positions"])
            cache[key] = float(sum(parts["masses"][masks[i]].sum() for i, _ in self._tools.get(name, [])))
        return cache[key]
