"""Forward and inverse kinematics of a machine description, in the frame of its root link (base_link).

Generic over the URDF: the chain, axes and lengths come from the file, nothing ZX120-specific. Joints not
named in a configuration dict are at 0 (OPERA's dummy bucket_end_joint, for example).
"""
from __future__ import annotations

import math

import numpy as np
import yourdfpy
from scipy.optimize import least_squares

from .machine_description import MOVABLE, MachineDescription

POSITION_TOLERANCE = 1e-3             # m: solve_tip accepts a solution this close...
ANGLE_TOLERANCE = math.radians(0.5)   # ...with the bucket angle this close
ANGLE_WEIGHT = 1.0                    # m per rad: how the bucket angle error counts against position error


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix about a unit axis (Rodrigues)."""
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    t = 1.0 - c
    return np.array([[t * x * x + c, t * x * y - s * z, t * x * z + s * y],
                     [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
                     [t * x * z - s * y, t * y * z + s * x, t * z * z + c]])


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


class Kinematics:
    def __init__(self, desc: MachineDescription):
        robot = yourdfpy.URDF.load(str(desc.bullet_urdf_path), build_scene_graph=False, load_meshes=False).robot
        for joint in robot.joints:
            joint.origin = np.eye(4) if joint.origin is None else joint.origin
        for link in robot.links:
            if link.inertial is not None and link.inertial.origin is None:
                link.inertial.origin = np.eye(4)
        self.desc = desc
        self._joints = {joint.name: joint for joint in robot.joints}
        self._parent_joint = {joint.child: joint for joint in robot.joints}
        self._inertials = {link.name: link.inertial for link in robot.links}
        self.base_link = next(link.name for link in robot.links if link.name not in self._parent_joint)
        self._chains: dict[str, list] = {}
        tip_chain = self._chain(desc.tip_link)
        # the joints that move the tip, in chain order (swing, boom, arm, bucket)
        self.tip_joints = [j.name for j in tip_chain if j.name in desc.actuated_joints]
        if not self.tip_joints:
            raise ValueError(f"no actuated joint moves tip link {desc.tip_link!r}")
        self._pin_joint = self._joints[self.tip_joints[-1]]     # its child frame origin is the bucket pin
        self._swing_joint = next((self._joints[name] for name in self.tip_joints
                                  if abs(self._joints[name].axis[2]) > 0.9), None)

    # ----------------------------------------------------------------------------------------- forward
    def _chain(self, link: str) -> list:
        if link not in self._chains:
            if link != self.base_link and link not in self._parent_joint:
                raise ValueError(f"unknown link {link!r}")
            chain, name = [], link
            while name in self._parent_joint:
                joint = self._parent_joint[name]
                chain.append(joint)
                name = joint.parent
            self._chains[link] = chain[::-1]
        return self._chains[link]

    def _check(self, q: dict[str, float]) -> None:
        for name in q:
            if name not in self._joints or self._joints[name].type not in MOVABLE:
                raise ValueError(f"unknown movable joint {name!r}")

    def _joint_transform(self, joint, value: float) -> np.ndarray:
        transform = joint.origin.copy()
        if joint.type in ("revolute", "continuous") and value != 0.0:
            transform[:3, :3] = transform[:3, :3] @ _rotation(joint.axis, value)
        elif joint.type == "prismatic" and value != 0.0:
            transform[:3, 3] += transform[:3, :3] @ (joint.axis * value)
        return transform

    def link_pose(self, q: dict[str, float], link: str) -> np.ndarray:
        """4x4 pose of `link`'s frame in the base_link frame."""
        self._check(q)
        pose = np.eye(4)
        for joint in self._chain(link):
            pose = pose @ self._joint_transform(joint, float(q.get(joint.name, 0.0)))
        return pose

    def tip_position(self, q: dict[str, float]) -> np.ndarray:
        """Cutting edge (tip_link origin) in the base_link frame."""
        return self.link_pose(q, self.desc.tip_link)[:3, 3].copy()

    def _forward_direction(self, q) -> np.ndarray:
        """Horizontal unit vector the upper structure faces (x of the swing joint's child link)."""
        if self._swing_joint is None:
            return np.array([1.0, 0.0, 0.0])
        x_axis = self.link_pose(q, self._swing_joint.child)[:3, 0]
        return np.array([x_axis[0], x_axis[1], 0.0]) / max(math.hypot(x_axis[0], x_axis[1]), 1e-12)

    def bucket_angle(self, q: dict[str, float]) -> float:
        """Angle of the bucket pin -> cutting edge vector below the horizontal, in the arm's vertical plane
        (rad), in (-pi/2, 3pi/2]: 0 edge level ahead of the pin, pi/2 edge straight below it, > pi/2 edge
        pointing back toward the machine, > pi curled up; negative: edge raised ahead (dumping)."""
        pin_pose = self.link_pose(q, self._pin_joint.child)
        edge = self.tip_position(q) - pin_pose[:3, 3]
        forward = self._forward_direction(q)
        normal = pin_pose[:3, :3] @ self._pin_joint.axis       # the bucket joint axis, normal to the arm plane
        horizontal = np.cross(normal, [0.0, 0.0, 1.0])
        norm = np.linalg.norm(horizontal)
        horizontal = forward if norm < 1e-9 else horizontal / norm
        if horizontal @ forward < 0:                           # a URDF may write the axis as -y
            horizontal = -horizontal
        angle = math.atan2(-edge[2], edge @ horizontal)
        return angle + 2 * math.pi if angle <= -math.pi / 2 else angle

    # ----------------------------------------------------------------------------------------- gravity
    def static_joint_torques(self, q: dict[str, float], gravity: float = 9.81) -> dict[str, float]:
        """Torque (N m; N for prismatic) each actuated joint must apply along its axis to hold `q` still
        against gravity (-z of the base frame), from the link masses and centres of mass."""
        self._check(q)
        g = np.array([0.0, 0.0, -gravity])
        coms = {}
        for link, inertial in self._inertials.items():
            if inertial is not None and inertial.mass:
                coms[link] = (inertial.mass, (self.link_pose(q, link) @ inertial.origin)[:3, 3])
        torques = {}
        for name in self.desc.actuated_joints:
            joint = self._joints[name]
            frame = self.link_pose(q, joint.child)
            axis, pivot = frame[:3, :3] @ joint.axis, frame[:3, 3]
            load = 0.0
            for link, (mass, com) in coms.items():
                if any(j.name == name for j in self._chain(link)):
                    force = mass * g
                    load += (force @ axis) if joint.type == "prismatic" else np.cross(com - pivot, force) @ axis
            torques[name] = -float(load)
        return torques

    # ----------------------------------------------------------------------------------------- inverse
    def solve_tip(self, xyz, bucket_angle: float, q_guess: dict | None = None) -> dict[str, float]:
        """Joint angles that put the cutting edge at `xyz` (base frame) with the given bucket angle,
        within joint limits. Raises ValueError("... unreachable ...") if no solution comes within 1 mm and
        0.5 deg. Numerical (bounded least squares) from several starts: q_guess, an analytic swing with
        mid-range joints, then spread starts."""
        target = np.asarray(xyz, float).reshape(3)
        names = self.tip_joints
        lower = np.array([self.desc.joint_limits[n][0] for n in names])
        upper = np.array([self.desc.joint_limits[n][1] for n in names])
        guess = dict(q_guess or {})
        self._check(guess)

        def config(x) -> dict[str, float]:
            return {**guess, **{n: float(v) for n, v in zip(names, x)}}

        def residual(x) -> np.ndarray:
            q = config(x)
            angle_error = _wrap(self.bucket_angle(q) - bucket_angle)
            return np.append(self.tip_position(q) - target, ANGLE_WEIGHT * angle_error)

        best = None
        for x0 in self._starts(names, lower, upper, guess, target):
            result = least_squares(residual, x0, bounds=(lower, upper), method="trf",
                                   xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=300)
            position_error = float(np.linalg.norm(result.fun[:3]))
            angle_error = abs(float(result.fun[3])) / ANGLE_WEIGHT
            if best is None or position_error + angle_error < best[0]:
                best = (position_error + angle_error, position_error, angle_error)
            if position_error <= POSITION_TOLERANCE and angle_error <= ANGLE_TOLERANCE:
                solution = config(result.x)
                for n in names:
                    if self._joints[n].type == "continuous":
                        solution[n] = _wrap(solution[n])
                return solution
        raise ValueError(f"tip target {np.round(target, 4).tolist()} m with bucket angle "
                         f"{math.degrees(bucket_angle):.1f} deg is unreachable within the joint limits "
                         f"(closest: {best[1] * 1e3:.0f} mm, {math.degrees(best[2]):.1f} deg off)")

    def _starts(self, names, lower, upper, guess, target):
        finite_lo = np.where(np.isfinite(lower), lower, -math.pi)
        finite_hi = np.where(np.isfinite(upper), upper, math.pi)
        middle = (finite_lo + finite_hi) / 2
        if guess:
            yield np.clip([guess.get(n, m) for n, m in zip(names, middle)], lower, upper)
        seed = middle.copy()
        if self._swing_joint is not None:
            i = names.index(self._swing_joint.name)
            seed[i] = self._swing_towards(target, config={**guess, **dict(zip(names, middle)),
                                                          self._swing_joint.name: 0.0})
            seed = np.clip(seed, lower, upper)
        yield seed
        rng = np.random.default_rng(0)
        for _ in range(6):
            spread = rng.uniform(finite_lo, finite_hi)
            if self._swing_joint is not None:
                spread[i] = seed[i]
            yield np.clip(spread, lower, upper)

    def _swing_towards(self, target, config) -> float:
        """Swing angle that turns the arm's vertical plane through the target, allowing for the
        sideways offset of the boom foot from the swing axis."""
        swing = self._swing_joint
        axis_point = self.link_pose(config, swing.parent) @ np.append(swing.origin[:3, 3], 1.0)
        body = self.link_pose(config, swing.child)
        tip_in_body = body[:3, :3].T @ (self.tip_position(config) - body[:3, 3])
        lateral = tip_in_body[1]
        relative = target - axis_point[:3]
        reach = math.sqrt(max(relative[0] ** 2 + relative[1] ** 2 - lateral ** 2, 1e-12))
        body_yaw_at_zero = math.atan2(body[1, 0], body[0, 0])
        direction = 1.0 if swing.axis[2] > 0 else -1.0
        return direction * _wrap(math.atan2(relative[1], relative[0]) - math.atan2(lateral, reach) - body_yaw_at_zero)
