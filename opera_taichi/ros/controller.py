"""The ROS bridge as the machines' controller: commands from ROS topics become each step's Control.

Messages arrive on the network thread (`handle`), are checked, and wait in an inbox stamped with the simulated time
they arrived at; `control(sim, t)` (simulation thread) applies those whose dead time (the machine's
`command_latency`) has passed, latest wins per joint. Nothing arrived yet: the machines hold their initial pose.
A speed command (track speeds, a joint's velocity target) expires `command_timeout` simulated seconds after it
acted unless a new one came: the tracks stop, the joint's target speed becomes 0.
A message a user can get wrong (NaN, an unknown joint, arrays of the wrong length, effort mode) is logged once per
topic and kind of mistake and ignored; it never ends the run.
"""
from __future__ import annotations

import math
import threading

from ..control import Control, MachineControl, ScriptController
from .topics import Topic


class BridgeController:
    source = "ros"

    def __init__(self, log, *, after_motion: bool = False, command_timeout: float | None = 0.5):
        self._log = log                  # log(key, text): says `text` once per key
        self.after_motion = after_motion
        self.command_timeout = command_timeout
        self._speeds: dict[tuple[str, str | None], float] = {}  # (machine, joint; None: tracks) -> when it acted
        self._lock = threading.Lock()
        self._pending: list[tuple[float, str, MachineControl]] = []
        self.now = 0.0                   # simulated time the next arriving command is stamped with
        self.accepted = 0
        self._machines: dict = {}
        self._script = None
        self.motion_end = 0.0
        self._seeded = False             # the speeds the machines follow at the first step are known

    def bind(self, model) -> None:
        """Learn the machines (joints, dead time, tracks) and, with after_motion, the scripts to run first."""
        for m in model.machines:
            tracks = m.description.tracks if not m.fixed_base else None
            self._machines[m.name] = {"joints": set(m.joints), "latency": float(getattr(m, "command_latency", 0.0)),
                                      "gauge": None if not tracks else float(tracks["gauge"])}
        if self.after_motion:
            ends = [m.motion.end_time for m in model.machines if m.motion is not None]
            if ends:
                self._script = ScriptController(model)
                self.motion_end = max(ends)

    # ------------------------------------------------------------------------------------------ network thread
    def handle(self, topic: Topic, msg) -> None:
        """A decoded message on command topic `topic`: checked, then queued for its machine."""
        mc = self._decode(topic, msg)
        if mc is None:
            return
        if self._script is not None and self.now < self.motion_end and mc.hold is None:  # (a stop acts at once)
            self._log(("during-motion",), f"{topic.name}: commands are ignored until the scene's motion ends at "
                                          f"t = {self.motion_end:g} s (--bridge-after-motion)")
            return
        with self._lock:
            self._pending.append((self.now + self._machines[topic.machine]["latency"], topic.machine, mc))
            self.accepted += 1

    def _bad(self, topic: Topic, kind: str, text: str) -> None:
        self._log((topic.name, kind), f"{topic.name}: {text}; message ignored (said once for this topic and "
                                      f"mistake)")

    def _decode(self, topic: Topic, msg) -> MachineControl | None:
        kind = topic.type
        if kind == "std_msgs/msg/Float64":
            value = float(msg.data)
            if not math.isfinite(value):
                self._bad(topic, "nan", f"target {value} rad is not a finite number")
                return None
            return MachineControl(q_target={topic.item: value})
        if kind == "std_msgs/msg/Bool":
            return MachineControl(hold=bool(msg.data))
        if kind == "geometry_msgs/msg/Twist":
            v, w = float(msg.linear.x), float(msg.angular.z)
            if not (math.isfinite(v) and math.isfinite(w)):
                self._bad(topic, "nan", f"linear.x {v} / angular.z {w} is not a finite number")
                return None
            half = 0.5 * self._machines[topic.machine]["gauge"]
            left, right = v - w * half, v + w * half
            if not (math.isfinite(left) and math.isfinite(right)):
                self._bad(topic, "nan", f"linear.x {v} / angular.z {w} give track speeds beyond any number")
                return None
            return MachineControl(track_speeds=(left, right))
        if kind == "com3_msgs/msg/JointCmd":
            return self._joint_cmd(topic, msg)
        raise ValueError(f"no command decoder for {kind}")

    def _joint_cmd(self, topic: Topic, msg) -> MachineControl | None:
        names = [str(n) for n in msg.joint_name]
        known = self._machines[topic.machine]["joints"]
        unknown = [n for n in names if n not in known]
        if unknown:
            self._bad(topic, "joint", f"unknown joint {unknown[0]!r} (joints: {', '.join(sorted(known))})")
            return None
        if len(set(names)) != len(names):
            self._bad(topic, "repeat", f"joint_name repeats a joint ({names})")
            return None
        mode = int(msg.control_type)
        if mode not in (0, 1):
            self._bad(topic, "mode", f"control_type {mode} is not supported (0 position, 1 velocity; the "
                                     f"actuators follow position or speed targets, not efforts)")
            return None
        field = "position" if mode == 0 else "velocity"
        values = [float(v) for v in getattr(msg, field)]
        if len(values) != len(names):
            self._bad(topic, "length", f"control_type {mode} needs {field}[] as long as joint_name[] "
                                       f"({len(names)}), got {len(values)}")
            return None
        if not all(math.isfinite(v) for v in values):
            self._bad(topic, "nan", f"{field}[] holds a value that is not a finite number ({values})")
            return None
        pairs = dict(zip(names, values))
        return MachineControl(q_target=pairs) if mode == 0 else MachineControl(qd_target=pairs)

    # ------------------------------------------------------------------------------------------ simulation thread
    def control(self, sim, t: float) -> Control:
        self.now = sim.t
        if not self._seeded:
            self._seed_speeds(sim)
        with self._lock:
            due = [p for p in self._pending if p[0] <= t + 1e-12]
            if due:
                self._pending = [p for p in self._pending if p[0] > t + 1e-12]
        if self._script is not None and t <= self.motion_end + 1e-12:
            scripted = self._script.control(sim, t)
            for _, name, mc in due:  # (only emergency stops are queued while the motion runs)
                scripted.machines.setdefault(name, MachineControl()).hold = mc.hold
            return scripted
        merged: dict[str, MachineControl] = {}
        held = {name: m.held for name, m in sim.machines.items()} if due else {}  # (most steps bring nothing)
        for _, name, mc in due:     # in arrival order: the latest command of a joint wins
            if mc.hold is True:  # a stop ends what came before it in this step (the machine applies it first)
                merged[name] = MachineControl(hold=True)
                held[name] = True
                self._speeds = {k: v for k, v in self._speeds.items() if k[0] != name}
                continue
            if mc.hold is False:  # a release: what came under the hold was dropped below, what follows acts
                merged.setdefault(name, MachineControl()).hold = False
                held[name] = False
                continue
            if held.get(name):
                continue            # given while the machine is held: ignored
            out = merged.setdefault(name, MachineControl())
            for j, v in mc.q_target.items():
                out.qd_target.pop(j, None)
                out.q_target[j] = v
                self._speeds.pop((name, j), None)
            for j, v in mc.qd_target.items():
                out.q_target.pop(j, None)
                out.qd_target[j] = v
                self._moving((name, j), v != 0.0, t)
            if mc.track_speeds is not None:
                out.track_speeds = mc.track_speeds
                self._moving((name, None), any(v != 0.0 for v in mc.track_speeds), t)
        if self.command_timeout is not None:
            self._expire(merged, t)
        return Control(merged, t, self.source)

    def _seed_speeds(self, sim) -> None:
        """The speeds the machines already follow when this controller takes over (a run resumed from a checkpoint:
        the commands that set them are gone) expire as a command just given would."""
        self._seeded = True
        state = sim.get_state(soil=False)
        for name, ms in state.machines.items():
            if name not in self._machines or ms.hold:
                continue
            for j, moving, qd in zip(ms.joints, ms.velocity_mode, ms.qd_target):
                if moving and qd != 0.0:
                    self._speeds[(name, j)] = sim.t
            if any(v != 0.0 for v in ms.track_speeds):
                self._speeds[(name, None)] = sim.t

    def _moving(self, key: tuple, moving: bool, t: float) -> None:
        if moving:
            self._speeds[key] = t
        else:
            self._speeds.pop(key, None)  # (a command to stop has nothing to expire)

    def _expire(self, merged: dict[str, MachineControl], t: float) -> None:
        """Speed commands that acted more than command_timeout ago with none after them: stop."""
        for (name, joint), since in list(self._speeds.items()):
            if t - since <= self.command_timeout + 1e-9:
                continue
            del self._speeds[(name, joint)]
            out = merged.setdefault(name, MachineControl())
            if joint is None:
                out.track_speeds = (0.0, 0.0)
                what = "tracks/cmd_vel: the tracks stop"
            else:
                out.qd_target[joint] = 0.0
                what = f"{joint}'s velocity target: the joint stops"
            self._log(("timeout", name, joint), f"{name}: no new speed command {self.command_timeout:g} s (simulated) "
                                                f"after the last, {what} (bridge.command_timeout; said once)")
