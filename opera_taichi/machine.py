"""The excavator as a PyBullet articulated body in a RigidWorld, with hydraulic-like joint actuators.

Each actuated joint follows its position target through a speed command
    v_cmd = clip(gain * (q_target - q), -max_speed, max_speed)
(or, in velocity mode, v_cmd = clip(qd_target, -max_speed, max_speed))
applied as a velocity motor that can exert at most max_torque: an overloaded joint stalls or is pushed
back and never teleports. Under its own drive a joint never runs faster than its speed limit; a load beyond its
torque limit backdrives it as fast as the load and the inertia make it (a relief valve giving way: 150 kN on the
ZX120's bucket drives the boom down at several times its 0.7 rad/s). Non-actuated movable joints
(OPERA's bucket_end_joint) are welded. Without a fixed base the machine stands on a ground plane on three
frictionless wheels per side, and the ground grips its tracks where they touch (tracks.py; skid steer).
"""
from __future__ import annotations

import hashlib
import math

import numpy as np
from lxml import etree

from . import paths
from ._quiet import quiet_c_output

with quiet_c_output():  # pybullet's C code prints its build time on import; keep stdout for our output
    import pybullet as pb
from .control import real_number
from .errors import UserError
from .geometry import quat_to_matrix
from .machine_description import MOVABLE, MachineDescription, atomic_write
from .tracks import TrackGround



def _fmt(values) -> str:
    return " ".join(f"{float(v):.12g}" for v in values)


class BulletMachine:
    def __init__(self, desc: MachineDescription, *, dt: float = 1e-3, base_xyz=(0, 0, 0), base_yaw=0.0,
                 fixed_base=True, initial_q: dict[str, float] | None = None, gravity=9.81, world=None,
                 name: str | None = None, warn=None):
        from .rigid import RigidWorld

        self.desc = desc
        self.name = name or desc.name
        self.fixed_base = bool(fixed_base)
        self.joint_names: list[str] = list(desc.actuated_joints)
        if not self.fixed_base and not desc.tracks:
            raise UserError(f"machine {desc.name}: a free base needs a 'tracks' section in its machine config")
        initial_q = dict(initial_q or {})
        for name_ in initial_q:
            if name_ not in self.joint_names:
                raise UserError(f"initial joint angles: unknown joint {name_!r} "
                                f"(actuated: {', '.join(self.joint_names)})")
        self._own_world = world is None
        self.world = RigidWorld(dt=dt, gravity=gravity) if world is None else world
        self.dt = self.world.dt
        self._warn = warn
        c = self.client = self.world.client
        urdf = self._write_bullet_variant()
        self.body = pb.loadURDF(str(urdf), basePosition=list(base_xyz),
                                baseOrientation=pb.getQuaternionFromEuler([0, 0, base_yaw]),
                                useFixedBase=self.fixed_base,
                                flags=pb.URDF_USE_INERTIA_FROM_FILE | pb.URDF_MAINTAIN_LINK_ORDER,
                                physicsClientId=c)
        self.base_link = pb.getBodyInfo(self.body, physicsClientId=c)[0].decode()
        self.link_index = {self.base_link: -1}
        joint_index = {}
        self._other_indices = []      # movable joints that are not actuated (track wheels): state, not commands
        for i in range(pb.getNumJoints(self.body, physicsClientId=c)):
            info = pb.getJointInfo(self.body, i, physicsClientId=c)
            joint_index[info[1].decode()] = i
            self.link_index[info[12].decode()] = i
            if info[2] != pb.JOINT_FIXED and info[1].decode() not in self.joint_names:
                self._other_indices.append(i)
            # bodies lose no energy to artificial damping: the hydraulics and the soil do the damping
            pb.changeDynamics(self.body, i, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0,
                              physicsClientId=c)
        pb.changeDynamics(self.body, -1, linearDamping=0.0, angularDamping=0.0, physicsClientId=c)
        self._indices = [joint_index[name_] for name_ in self.joint_names]
        self._max_speed = np.array([desc.actuators[n].max_speed for n in self.joint_names])
        self._max_torque = np.array([desc.actuators[n].max_torque for n in self.joint_names])
        self._gain = np.array([desc.actuators[n].gain for n in self.joint_names])
        self._lower = np.array([desc.joint_limits[n][0] for n in self.joint_names])
        self._upper = np.array([desc.joint_limits[n][1] for n in self.joint_names])
        self._column = {n: i for i, n in enumerate(self.joint_names)}
        # every movable joint of the URDF, actuated first: robot_state_publisher places a link only when joint_states
        # names its joint (OPERA's bucket_end_joint, welded here); the added track wheels are not the URDF's
        self.urdf_joint_names = self.joint_names + [n for n in desc.movable_joints if n not in self._column]
        self._urdf_other_indices = [joint_index[n] for n in self.urdf_joint_names[len(self.joint_names):]]

        for name_, index in zip(self.joint_names, self._indices):
            pb.resetJointState(self.body, index, float(initial_q.get(name_, 0.0)), 0.0, physicsClientId=c)
        n = len(self.joint_names)
        self._targets = np.array([float(initial_q.get(j, 0.0)) for j in self.joint_names])
        self._qd_targets = np.zeros(n)
        self._velocity_mode = np.zeros(n, bool)
        self._hold = False
        self._speed_cmd = np.zeros(n)        # the motors' speed commands of the last step, rad/s
        self._clip_warned: set[str] = set()
        self._track_clip_warned = False   # a track speed beyond tracks.max_speed is said once
        self._pending_wrenches: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._link_cache: dict[int, tuple] = {}  # link states of the current pose (emptied when the world moves)

        self._wheels_left, self._wheels_right = [], []
        self._wheel_speed = (0.0, 0.0)
        self._ground = None
        if not self.fixed_base:
            for name_, index in joint_index.items():
                if name_.startswith("track_wheel_"):
                    (self._wheels_left if "_left_" in name_ else self._wheels_right).append(index)
                    # the wheels only carry the weight; the tracks' grip is TrackGround's
                    pb.changeDynamics(self.body, index, lateralFriction=0.0, physicsClientId=c)
            self._wheels = self._wheels_left + self._wheels_right
            self._wheel_side = np.array([0] * len(self._wheels_left) + [1] * len(self._wheels_right))
            mass = sum(pb.getDynamicsInfo(self.body, i, physicsClientId=c)[0]
                       for i in range(-1, pb.getNumJoints(self.body, physicsClientId=c)))
            self._ground = TrackGround(desc.tracks, mass, gravity)
        self._contacts = None   # the track contacts a state brought (set_state), for the step after it
        self.world.attach(self)
        self._read_joints()

    # ----------------------------------------------------------------------------------------- model
    def _write_bullet_variant(self):
        """The description's URDF with non-actuated movable joints welded and, for a free base, the
        track wheels added; cached by content."""
        tree = etree.parse(str(self.desc.bullet_urdf_path))
        robot = tree.getroot()
        for joint in robot.findall("joint"):
            if joint.get("type") in MOVABLE and joint.get("name") not in self.joint_names:
                joint.set("type", "fixed")
        if not self.fixed_base:
            root = [link.get("name") for link in robot.findall("link")
                    if link.get("name") not in {j.find("child").get("link") for j in robot.findall("joint")}][0]
            for element in self._wheel_elements(root):
                robot.append(element)
        text = etree.tostring(robot, xml_declaration=True, encoding="utf-8", pretty_print=True).decode()
        target = paths.cache_dir() / "urdf" / f"bullet-{hashlib.sha256(text.encode()).hexdigest()[:16]}.urdf"
        if not target.is_file():
            atomic_write(target, text)
        return target

    def _wheel_elements(self, root: str):
        tracks = self.desc.tracks
        radius, mass, width = tracks["wheel_radius"], tracks["wheel_mass"], 0.5
        axial = 0.5 * mass * radius ** 2
        radial = mass * (3 * radius ** 2 + width ** 2) / 12
        elements = []
        for side, y in (("left", tracks["gauge"] / 2), ("right", -tracks["gauge"] / 2)):
            for k, x in enumerate(tracks["x"]):
                name = f"track_wheel_{side}_{k}"
                # cylinder axis along y (rpy roll 90 deg); positive spin about +y rolls the machine forward
                elements.append(etree.fromstring(
                    f'<link name="{name}"><inertial><origin xyz="0 0 0"/><mass value="{mass}"/>'
                    f'<inertia ixx="{radial}" ixy="0" ixz="0" iyy="{axial}" iyz="0" izz="{radial}"/></inertial>'
                    f'<collision><origin xyz="0 0 0" rpy="1.5707963267949 0 0"/>'
                    f'<geometry><cylinder radius="{radius}" length="{width}"/></geometry></collision></link>'))
                elements.append(etree.fromstring(
                    f'<joint name="{name}_joint" type="continuous"><parent link="{root}"/><child link="{name}"/>'
                    f'<origin xyz="{_fmt((x, y, radius))}" rpy="0 0 0"/><axis xyz="0 1 0"/>'
                    f'<limit effort="{tracks["max_wheel_torque"]}" velocity="100"/></joint>'))
        return elements

    # ----------------------------------------------------------------------------------------- control
    def set_targets(self, q_cmd: dict[str, float]) -> None:
        """Position targets (rad), clipped to the joint limits; joints not named keep their command."""
        self.command(q_target=q_cmd)

    @property
    def held(self) -> bool:
        """Whether the emergency stop is latched."""
        return self._hold

    def command(self, q_target=None, qd_target=None, track_speeds=None, hold=None) -> None:
        """Apply one step's commands: position targets (rad, clipped to the joint limits, a warning once per joint
        when clipped), velocity targets (rad/s, capped by the actuators), track speeds (m/s) and the emergency stop
        (hold: True latches the current pose as the target of every joint and stops the tracks until released with
        False; a release resumes no speed given before the hold). A target that is no finite number is refused before
        anything is applied (it would turn the machine's state into NaN)."""
        for kind, unit, values in (("target", "rad", q_target), ("speed target", "rad/s", qd_target)):
            if values is not None and not hasattr(values, "items"):
                raise UserError(f"joint {kind}s: a {{joint name: {unit}}} dict, got {type(values).__name__} "
                                f"{values!r}")
            for name, value in (values or {}).items():
                self._joint(name)
                if not _finite(value):
                    raise UserError(f"joint {kind}: {name} = {value!r} ({type(value).__name__}) is not a finite "
                                    f"number ({unit})")
        if track_speeds is not None and (isinstance(track_speeds, (str, bytes)) or not hasattr(track_speeds, "__len__")
                                         or len(track_speeds) != 2 or not all(_finite(v) for v in track_speeds)):
            raise UserError(f"track speeds: (left, right) in m/s, two finite numbers, got {track_speeds!r}")
        if hold is not None and not isinstance(hold, (bool, np.bool_)):
            raise UserError(f"hold: True (emergency stop), False (release) or None (unchanged), got {hold!r}")
        if hold is not None and bool(hold) != self._hold:
            self._hold = bool(hold)
            if self._hold:
                self._targets = self._q.copy()
                self._velocity_mode[:] = False
                self._wheel_speed = (0.0, 0.0)
        for name, value in (q_target or {}).items():
            i = self._joint(name)
            if self._hold:
                continue
            value = float(value)
            clipped = min(max(value, self._lower[i]), self._upper[i])
            if clipped != value and name not in self._clip_warned and math.isfinite(value):
                self._clip_warned.add(name)
                self._say(f"machine {self.name}: {name} target {value:.6g} rad is beyond the joint's limits "
                          f"[{self._lower[i]:.4f}, {self._upper[i]:.4f}] rad; clipped (said once per joint)")
            self._targets[i] = clipped
            self._velocity_mode[i] = False
        for name, value in (qd_target or {}).items():
            i = self._joint(name)
            if self._hold:
                continue
            self._qd_targets[i] = float(value)
            self._velocity_mode[i] = True
        if track_speeds is not None and not self._hold:
            self.set_track_speeds(*track_speeds)

    def _joint(self, name: str) -> int:
        i = self._column.get(name)
        if i is None:
            raise UserError(f"joint target: unknown joint {name!r} (actuated: {', '.join(self.joint_names)})")
        return i

    def _say(self, text: str) -> None:
        if self._warn is not None:
            self._warn(text)

    def set_track_speeds(self, left: float, right: float) -> None:
        """Track surface speeds (m/s, positive drives forward). Each side is capped at the machine's travel speed
        (machine.yaml tracks.max_speed), as a travel motor's flow caps it: a faster command is clipped, not refused
        (said once), so a turn asked beyond the cap turns tighter than asked."""
        if self.fixed_base:
            raise UserError("set_track_speeds: the machine has a fixed base (set fixed_base false to drive)")
        cap = self.desc.tracks.get("max_speed")
        speeds = (float(left), float(right))
        if cap is not None:
            capped = tuple(min(max(v, -cap), cap) for v in speeds)
            if capped != speeds and not self._track_clip_warned and all(math.isfinite(v) for v in speeds):
                self._track_clip_warned = True
                self._say(f"machine {self.name}: track speeds ({speeds[0]:g}, {speeds[1]:g}) m/s beyond its travel "
                          f"speed {cap:g} m/s (tracks.max_speed); capped (said once)")
            speeds = capped
        self._wheel_speed = speeds

    def apply_link_wrench(self, link: str, force, torque) -> None:
        """World-frame force at the link frame origin plus world-frame torque, for the next step() only."""
        if link not in self.link_index:
            raise UserError(f"apply_link_wrench: unknown link {link!r}")
        index = self.link_index[link]
        previous = self._pending_wrenches.get(index, (np.zeros(3), np.zeros(3)))
        self._pending_wrenches[index] = (previous[0] + np.asarray(force, float),
                                         previous[1] + np.asarray(torque, float))

    def pre_step(self) -> None:
        """Set the motors and external forces for the world's next step."""
        c = self.client
        q = self._q
        speed = np.where(self._velocity_mode, self._qd_targets, self._gain * (self._targets - q))
        # a velocity command never drives a joint through its limit
        speed = np.where(self._velocity_mode & (((q >= self._upper) & (speed > 0)) | ((q <= self._lower) & (speed < 0))),
                         0.0, speed)
        speed = np.clip(speed, -self._max_speed, self._max_speed)
        self._speed_cmd = speed
        pb.setJointMotorControlArray(self.body, self._indices, pb.VELOCITY_CONTROL, targetVelocities=speed.tolist(),
                                     forces=self._max_torque.tolist(), physicsClientId=c)
        if not self.fixed_base:
            self._apply_track_forces()
        # Bullet clears external forces after every stepSimulation, so they are applied here, each step
        for index, (force, torque) in self._pending_wrenches.items():
            origin = self._link_state(index)[0]
            pb.applyExternalForce(self.body, index, force.tolist(), origin.tolist(), pb.WORLD_FRAME, physicsClientId=c)
            pb.applyExternalTorque(self.body, index, torque.tolist(), pb.WORLD_FRAME, physicsClientId=c)
        self._pending_wrenches.clear()

    def _apply_track_forces(self) -> None:
        """The ground's grip on the tracks (TrackGround) at each wheel's contact, from the loads of the last step."""
        c = self.client
        pb.setJointMotorControlArray(self.body, self._wheels, pb.VELOCITY_CONTROL, forces=[0.0] * len(self._wheels),
                                     physicsClientId=c)   # free wheels: the tracks' drive is in the forces below
        n = len(self._wheels)
        normal, point, up = np.zeros(n), np.zeros((n, 3)), np.tile([0.0, 0.0, 1.0], (n, 1))
        ground = self.world.ground
        for k, w in enumerate(self._wheels):
            for cp in pb.getContactPoints(bodyA=self.body, bodyB=ground, linkIndexA=w, physicsClientId=c):
                if cp[9] > 0.0:
                    normal[k] += cp[9]
                    point[k] += cp[9] * np.asarray(cp[6])
                    up[k] = cp[7]   # the ground's normal (body B), towards the wheel
        point[normal > 0] /= normal[normal > 0, None]
        if self._contacts is not None:  # the first step after set_state: Bullet has no contacts yet, the state has
            if not normal.any():
                normal, point, up = self._contacts
            self._contacts = None
        if not normal.any():
            self._ground.stick[:] = 0.0
            return
        self._ground.contacts = (normal.copy(), point.copy(), up.copy())
        com, _ = pb.getBasePositionAndOrientation(self.body, physicsClientId=c)
        vel, omega = (np.asarray(v) for v in pb.getBaseVelocity(self.body, physicsClientId=c))
        velocity = vel + np.cross(omega, point - np.asarray(com))
        heading = quat_to_matrix(self.base_pose()[1])[:, 0]
        speeds = (0.0, 0.0) if self._hold else self._wheel_speed
        forces = self._ground.forces(normal, velocity, heading, up, self._wheel_side, speeds, self.dt)
        for k in np.flatnonzero(normal > 0):
            pb.applyExternalForce(self.body, -1, forces[k].tolist(), point[k].tolist(), pb.WORLD_FRAME,
                                  physicsClientId=c)

    def post_step(self) -> None:
        self._link_cache.clear()
        self._read_joints()

    def step(self) -> None:
        """Step this machine's world (every machine in it)."""
        self.world.step()

    def _read_joints(self) -> None:
        self._link_cache.clear()
        states = pb.getJointStates(self.body, self._indices, physicsClientId=self.client)
        self._q = np.array([s[0] for s in states])
        self._qd = np.array([s[1] for s in states])
        self._effort = np.array([s[3] for s in states])

    # ----------------------------------------------------------------------------------------- state
    def joint_states(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint positions (rad), speeds (rad/s) and motor efforts (N m) after the last step, in joint_names
        order."""
        return self._q.copy(), self._qd.copy(), self._effort.copy()

    def urdf_joint_states(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """joint_states() followed by the URDF's other movable joints as PyBullet has them (a welded one rests at
        0), in urdf_joint_names order: what a ROS joint_states message carries."""
        q, qd, effort = self.joint_states()
        if not self._urdf_other_indices:
            return q, qd, effort
        rest = pb.getJointStates(self.body, self._urdf_other_indices, physicsClientId=self.client)
        return (np.concatenate([q, [s[0] for s in rest]]), np.concatenate([qd, [s[1] for s in rest]]),
                np.concatenate([effort, [s[3] for s in rest]]))

    @property
    def max_speed(self) -> np.ndarray:
        """Actuator speed limit per joint, rad/s (joint_names order)."""
        return self._max_speed.copy()

    @property
    def max_torque(self) -> np.ndarray:
        """Actuator torque limit per joint, N m."""
        return self._max_torque.copy()

    @property
    def joint_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper joint limits, rad."""
        return self._lower.copy(), self._upper.copy()

    @property
    def applied_targets(self) -> np.ndarray:
        """Position target of each joint as applied (rad, clipped; NaN where the joint is in velocity mode)."""
        return np.where(self._velocity_mode, np.nan, self._targets)

    @property
    def applied_speed_commands(self) -> np.ndarray:
        """Speed the motors were last told (rad/s), in joint_names order."""
        return self._speed_cmd.copy()

    def get_state(self):
        """Everything this machine needs to go on exactly: joints, base, actuator internals (State data)."""
        from .state import MachineState

        c = self.client
        other = pb.getJointStates(self.body, self._other_indices, physicsClientId=c) if self._other_indices else []
        pos, orn = pb.getBasePositionAndOrientation(self.body, physicsClientId=c)
        vel, omega = pb.getBaseVelocity(self.body, physicsClientId=c)
        return MachineState(
            joints=list(self.joint_names), q=self._q.copy(), qd=self._qd.copy(), effort=self._effort.copy(),
            q_target=self._targets.copy(), qd_target=self._qd_targets.copy(),
            velocity_mode=self._velocity_mode.copy(), speed_cmd=self._speed_cmd.copy(), hold=self._hold,
            track_speeds=np.array(self._wheel_speed, float),
            other_q=np.array([s[0] for s in other]), other_qd=np.array([s[1] for s in other]),
            base_com_xyz=np.array(pos), base_com_quat=np.array(orn), base_com_vel=np.array(vel),
            base_com_omega=np.array(omega),
            track_stick=np.zeros((0, 2)) if self._ground is None else self._ground.stick.copy(),
            track_contacts=np.zeros((0, 7)) if self._ground is None else np.column_stack(self._ground.contacts))

    def in_world(self, s) -> bool:
        """Whether Bullet holds this machine as the state s has it (joints and base): false for a state edited after
        it was taken, which a restored world would otherwise overrule."""
        c = self.client
        states = pb.getJointStates(self.body, list(self._indices) + list(self._other_indices), physicsClientId=c)
        pos, orn = pb.getBasePositionAndOrientation(self.body, physicsClientId=c)
        return (np.array_equal([j[0] for j in states], np.concatenate([s.q, s.other_q]))
                and np.array_equal([j[1] for j in states], np.concatenate([s.qd, s.other_qd]))
                and np.array_equal(pos, s.base_com_xyz) and np.array_equal(orn, s.base_com_quat))

    def set_state(self, s) -> None:
        if list(s.joints) != self.joint_names:
            raise ValueError(f"machine {self.name}: the state's joints {list(s.joints)} are not this machine's "
                             f"{self.joint_names}")
        c = self.client
        pb.resetBasePositionAndOrientation(self.body, s.base_com_xyz.tolist(), s.base_com_quat.tolist(),
                                           physicsClientId=c)
        pb.resetBaseVelocity(self.body, s.base_com_vel.tolist(), s.base_com_omega.tolist(), physicsClientId=c)
        for index, q, qd in zip(self._indices, s.q, s.qd):
            pb.resetJointState(self.body, index, float(q), float(qd), physicsClientId=c)
        for index, q, qd in zip(self._other_indices, s.other_q, s.other_qd):
            pb.resetJointState(self.body, index, float(q), float(qd), physicsClientId=c)
        self._q, self._qd, self._effort = s.q.copy(), s.qd.copy(), s.effort.copy()
        self._targets, self._qd_targets = s.q_target.copy(), s.qd_target.copy()
        self._velocity_mode, self._speed_cmd = s.velocity_mode.astype(bool).copy(), s.speed_cmd.copy()
        self._hold = bool(s.hold)
        self._link_cache.clear()
        self._wheel_speed = (float(s.track_speeds[0]), float(s.track_speeds[1]))
        if self._ground is not None:
            self._ground.stick[:] = s.track_stick
            self._contacts = (s.track_contacts[:, 0].copy(), s.track_contacts[:, 1:4].copy(),
                              s.track_contacts[:, 4:7].copy())
            self._ground.contacts = self._contacts
        self._pending_wrenches.clear()

    def link_state(self, link: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Position and quaternion (x, y, z, w) of the URDF link frame origin in the world, the linear
        velocity of that origin and the angular velocity, world frame."""
        if link not in self.link_index:
            raise UserError(f"link_state: unknown link {link!r}")
        return self._link_state(self.link_index[link])

    def _link_state(self, index: int):
        cached = self._link_cache.get(index)
        if cached is None:
            cached = self._link_cache[index] = self._query_link_state(index)
        return tuple(a.copy() for a in cached)

    def _query_link_state(self, index: int):
        c = self.client
        if index == -1:
            com, com_orn = pb.getBasePositionAndOrientation(self.body, physicsClientId=c)
            v_com, omega = pb.getBaseVelocity(self.body, physicsClientId=c)
            local_pos, local_orn = pb.getDynamicsInfo(self.body, -1, physicsClientId=c)[3:5]
            inv_pos, inv_orn = pb.invertTransform(local_pos, local_orn)
            origin, orn = pb.multiplyTransforms(com, com_orn, inv_pos, inv_orn)
        else:
            state = pb.getLinkState(self.body, index, computeLinkVelocity=1, computeForwardKinematics=1,
                                    physicsClientId=c)
            com, origin, orn, v_com, omega = state[0], state[4], state[5], state[6], state[7]
        # Bullet reports the velocity of the centre of mass; move it to the link frame origin (omega x r written
        # out: np.cross costs more than the rest of this call)
        (wx, wy, wz), (rx, ry, rz) = omega, (origin[0] - com[0], origin[1] - com[1], origin[2] - com[2])
        v_origin = np.array((v_com[0] + (wy * rz - wz * ry), v_com[1] + (wz * rx - wx * rz),
                             v_com[2] + (wx * ry - wy * rx)))
        return np.asarray(origin, float), np.asarray(orn, float), v_origin, np.asarray(omega, float)

    def tip_position(self) -> np.ndarray:
        """Cutting edge (tip link origin), world frame."""
        return self.link_state(self.desc.tip_link)[0]

    def base_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Position and quaternion (x, y, z, w) of the base link frame, world frame."""
        origin, orn, _, _ = self._link_state(-1)
        return origin, orn

    def close(self) -> None:
        if self._own_world:
            self.world.close()
        self.client = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _finite(value) -> bool:
    """One finite real number (control.real_number: not a bool, a string or an array of several)."""
    number = real_number(value)
    return number is not None and math.isfinite(number)
