"""The excavator as a PyBullet articulated body (DIRECT mode) with hydraulic-like joint actuators.

Each actuated joint follows its position target through a speed command
    v_cmd = clip(gain * (q_target - q), -max_speed, max_speed)
applied as a velocity motor that can exert at most max_torque: an overloaded joint stalls or is pushed
back, it never teleports, and it never runs faster than its speed limit. Non-actuated movable joints
(OPERA's bucket_end_joint) are welded. Without a fixed base the machine stands on a ground plane on three
driven wheels per side (skid steer), which stand in for the tracks.
"""
from __future__ import annotations

import hashlib

import numpy as np
from lxml import etree

from . import paths
from ._quiet import quiet_c_output

with quiet_c_output():  # pybullet's C code prints its build time on import; keep stdout for our output
    import pybullet as pb
from .errors import UserError
from .machine_description import MOVABLE, MachineDescription, atomic_write

SOLVER_ITERATIONS = 150     # a 12 t machine with 50 kg wheels and 0.001 kg frame links needs more than 50


def _fmt(values) -> str:
    return " ".join(f"{float(v):.12g}" for v in values)


class BulletMachine:
    def __init__(self, desc: MachineDescription, *, dt: float = 1e-3, base_xyz=(0, 0, 0), base_yaw=0.0,
                 fixed_base=True, initial_q: dict[str, float] | None = None, gravity=9.81):
        self.desc = desc
        self.dt = float(dt)
        self.fixed_base = bool(fixed_base)
        self.joint_names: list[str] = list(desc.actuated_joints)
        if not self.fixed_base and not desc.tracks:
            raise UserError(f"machine {desc.name}: a free base needs a 'tracks' section in its machine config")
        initial_q = dict(initial_q or {})
        for name in initial_q:
            if name not in self.joint_names:
                raise UserError(f"initial joint angles: unknown joint {name!r} (actuated: {', '.join(self.joint_names)})")

        with quiet_c_output():
            self.client = pb.connect(pb.DIRECT)
        c = self.client
        pb.setGravity(0, 0, -gravity, physicsClientId=c)
        pb.setPhysicsEngineParameter(fixedTimeStep=self.dt, numSubSteps=0, numSolverIterations=SOLVER_ITERATIONS,
                                     solverResidualThreshold=1e-9, deterministicOverlappingPairs=1,
                                     physicsClientId=c)
        urdf = self._write_bullet_variant()
        self.body = pb.loadURDF(str(urdf), basePosition=list(base_xyz),
                                baseOrientation=pb.getQuaternionFromEuler([0, 0, base_yaw]),
                                useFixedBase=self.fixed_base,
                                flags=pb.URDF_USE_INERTIA_FROM_FILE | pb.URDF_MAINTAIN_LINK_ORDER,
                                physicsClientId=c)
        self.base_link = pb.getBodyInfo(self.body, physicsClientId=c)[0].decode()
        self.link_index = {self.base_link: -1}
        joint_index = {}
        for i in range(pb.getNumJoints(self.body, physicsClientId=c)):
            info = pb.getJointInfo(self.body, i, physicsClientId=c)
            joint_index[info[1].decode()] = i
            self.link_index[info[12].decode()] = i
            # bodies lose no energy to artificial damping: the hydraulics and the soil do the damping
            pb.changeDynamics(self.body, i, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0,
                              physicsClientId=c)
        pb.changeDynamics(self.body, -1, linearDamping=0.0, angularDamping=0.0, physicsClientId=c)
        self._indices = [joint_index[name] for name in self.joint_names]
        self._max_speed = np.array([desc.actuators[n].max_speed for n in self.joint_names])
        self._max_torque = np.array([desc.actuators[n].max_torque for n in self.joint_names])
        self._gain = np.array([desc.actuators[n].gain for n in self.joint_names])
        self._lower = np.array([desc.joint_limits[n][0] for n in self.joint_names])
        self._upper = np.array([desc.joint_limits[n][1] for n in self.joint_names])

        for name, index in zip(self.joint_names, self._indices):
            pb.resetJointState(self.body, index, float(initial_q.get(name, 0.0)), 0.0, physicsClientId=c)
        self._targets = np.array([float(initial_q.get(n, 0.0)) for n in self.joint_names])
        self._pending_wrenches: dict[int, tuple[np.ndarray, np.ndarray]] = {}

        self._wheels_left, self._wheels_right = [], []
        self._wheel_speed = (0.0, 0.0)
        if not self.fixed_base:
            self._setup_ground(joint_index)

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

    def _setup_ground(self, joint_index) -> None:
        c = self.client
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=c)
        self.ground = pb.createMultiBody(0, plane, basePosition=[0, 0, 0], physicsClientId=c)
        pb.changeDynamics(self.ground, -1, lateralFriction=1.0, physicsClientId=c)
        friction = self.desc.tracks["friction"]          # Bullet multiplies the two frictions: 1.0 * mu
        for name, index in joint_index.items():
            if not name.startswith("track_wheel_"):
                continue
            (self._wheels_left if "_left_" in name else self._wheels_right).append(index)
            pb.changeDynamics(self.body, index, lateralFriction=friction, physicsClientId=c)
        wheels = set(self._wheels_left + self._wheels_right)
        # only the wheels touch the ground: the bucket must be free to go below z = 0 into the soil
        for link in [-1, *range(pb.getNumJoints(self.body, physicsClientId=c))]:
            if link not in wheels:
                pb.setCollisionFilterPair(self.ground, self.body, -1, link, 0, physicsClientId=c)

    # ----------------------------------------------------------------------------------------- control
    def set_targets(self, q_cmd: dict[str, float]) -> None:
        """Position targets (rad), clipped to the joint limits; joints not named keep their target."""
        for name, value in q_cmd.items():
            if name not in self.joint_names:
                raise UserError(f"joint target: unknown joint {name!r} (actuated: {', '.join(self.joint_names)})")
            i = self.joint_names.index(name)
            self._targets[i] = float(np.clip(value, self._lower[i], self._upper[i]))

    def set_track_speeds(self, left: float, right: float) -> None:
        """Track surface speeds (m/s, positive drives forward)."""
        if self.fixed_base:
            raise UserError("set_track_speeds: the machine has a fixed base (set fixed_base false to drive)")
        self._wheel_speed = (float(left), float(right))

    def apply_link_wrench(self, link: str, force, torque) -> None:
        """World-frame force at the link frame origin plus world-frame torque, for the next step() only."""
        if link not in self.link_index:
            raise UserError(f"apply_link_wrench: unknown link {link!r}")
        index = self.link_index[link]
        previous = self._pending_wrenches.get(index, (np.zeros(3), np.zeros(3)))
        self._pending_wrenches[index] = (previous[0] + np.asarray(force, float),
                                         previous[1] + np.asarray(torque, float))

    def step(self) -> None:
        c = self.client
        q = np.array([s[0] for s in pb.getJointStates(self.body, self._indices, physicsClientId=c)])
        speed = np.clip(self._gain * (self._targets - q), -self._max_speed, self._max_speed)
        pb.setJointMotorControlArray(self.body, self._indices, pb.VELOCITY_CONTROL, targetVelocities=speed.tolist(),
                                     forces=self._max_torque.tolist(), physicsClientId=c)
        if not self.fixed_base:
            radius, torque = self.desc.tracks["wheel_radius"], self.desc.tracks["max_wheel_torque"]
            for wheels, surface_speed in zip((self._wheels_left, self._wheels_right), self._wheel_speed):
                pb.setJointMotorControlArray(self.body, wheels, pb.VELOCITY_CONTROL,
                                             targetVelocities=[surface_speed / radius] * len(wheels),
                                             forces=[torque] * len(wheels), physicsClientId=c)
        # Bullet clears external forces after every stepSimulation, so they are applied here, each step
        for index, (force, torque) in self._pending_wrenches.items():
            origin = self._link_state(index)[0]
            pb.applyExternalForce(self.body, index, force.tolist(), origin.tolist(), pb.WORLD_FRAME, physicsClientId=c)
            pb.applyExternalTorque(self.body, index, torque.tolist(), pb.WORLD_FRAME, physicsClientId=c)
        self._pending_wrenches.clear()
        pb.stepSimulation(physicsClientId=c)

    # ----------------------------------------------------------------------------------------- state
    def joint_states(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint positions (rad), speeds (rad/s) and motor efforts (N m), in joint_names order."""
        states = pb.getJointStates(self.body, self._indices, physicsClientId=self.client)
        return (np.array([s[0] for s in states]), np.array([s[1] for s in states]),
                np.array([s[3] for s in states]))

    def link_state(self, link: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Position and quaternion (x, y, z, w) of the URDF link frame origin in the world, the linear
        velocity of that origin and the angular velocity, world frame."""
        if link not in self.link_index:
            raise UserError(f"link_state: unknown link {link!r}")
        return self._link_state(self.link_index[link])

    def _link_state(self, index: int):
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
        com, origin, v_com, omega = (np.asarray(v, float) for v in (com, origin, v_com, omega))
        # Bullet reports the velocity of the centre of mass; move it to the link frame origin
        v_origin = v_com + np.cross(omega, origin - com)
        return origin, np.asarray(orn, float), v_origin, omega

    def tip_position(self) -> np.ndarray:
        """Cutting edge (tip link origin), world frame."""
        return self.link_state(self.desc.tip_link)[0]

    def base_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Position and quaternion (x, y, z, w) of the base link frame, world frame."""
        origin, orn, _, _ = self._link_state(-1)
        return origin, orn

    def close(self) -> None:
        if self.client is not None and pb.isConnected(self.client):
            pb.disconnect(self.client)
        self.client = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
