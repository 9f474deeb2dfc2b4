"""Motion scripts: where the machine's joints should be at time t (the Control of each step).

Three kinds, all ending as a smooth joint-space profile:
- joint waypoints (times and targets, PCHIP-interpolated so there is no overshoot between waypoints),
- a CSV replay of a recorded joint-angle log (linear between samples, as a real log is dense),
- a cutting-edge path in the machine frame, sampled along straight Cartesian segments and solved by IK.
"""
from __future__ import annotations

import math
from bisect import bisect_right
from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator

from .errors import UserError

# Cartesian paths are solved by IK at this rate, then interpolated in joint space.
TIP_PATH_SAMPLE_HZ = 10.0


class JointProfile:
    """Per-joint time profile; holds the first value before the start and the last after the end."""

    def __init__(self, times: dict[str, np.ndarray], values: dict[str, np.ndarray], *, linear: bool = False):
        # per joint: breakpoints and the cubic's coefficients on each interval (highest power first); a linear
        # profile has zero cubic and quadratic terms. Evaluated in plain Python (Horner): a controller asks once per
        # rigid step, where SciPy's call overhead cost more than the rest of the step's Python
        self._curves = {}
        for joint, t in times.items():
            t = np.asarray(t, dtype=np.float64)
            v = np.asarray(values[joint], dtype=np.float64)
            if len(t) == 1:
                coeffs = np.zeros((0, 4))
            elif linear:
                slope = np.diff(v) / np.diff(t)
                coeffs = np.stack([np.zeros_like(slope), np.zeros_like(slope), slope, v[:-1]], axis=1)
            else:
                coeffs = PchipInterpolator(t, v, extrapolate=False).c.T
            self._curves[joint] = (t.tolist(), float(v[0]), float(v[-1]), coeffs.tolist())
        self.end_time = max((float(t[-1]) for t in times.values()), default=0.0)

    @property
    def joints(self) -> list[str]:
        return list(self._curves)

    def extremes(self) -> dict[str, tuple[float, float]]:
        """Each joint's lowest and highest target: at a breakpoint (the monotone cubics and the lines between
        breakpoints do not overshoot them)."""
        out = {}
        for joint, (times, first, last, coeffs) in self._curves.items():
            values = [first, last] + [c[3] for c in coeffs]
            out[joint] = (min(values), max(values))
        return out

    def targets(self, t: float) -> dict[str, float]:
        out = {}
        for joint, (times, first, last, coeffs) in self._curves.items():
            if t <= times[0]:
                out[joint] = first
            elif t >= times[-1]:
                out[joint] = last
            else:
                i = bisect_right(times, t) - 1
                a, b, c, d = coeffs[i]
                x = t - times[i]
                out[joint] = ((a * x + b) * x + c) * x + d
        return out


def joint_waypoints(waypoints: list[tuple[float, dict[str, float]]], initial_q: dict[str, float]) -> JointProfile:
    """Waypoints [(t, {joint: rad})]; a joint missing from a waypoint holds its previous value
    (its initial value before it is first named)."""
    current = dict(initial_q)
    times: dict[str, list[float]] = {}
    values: dict[str, list[float]] = {}
    for t, q in waypoints:
        current.update(q)
        for joint, value in current.items():
            times.setdefault(joint, []).append(float(t))
            values.setdefault(joint, []).append(float(value))
    return JointProfile({j: np.asarray(v) for j, v in times.items()},
                        {j: np.asarray(v) for j, v in values.items()})


def read_joint_csv(path: Path, joints: list[str], time_offset: float = 0.0, machine: str = "") -> JointProfile:
    """A recorded profile: column `t` (s) and per joint `<joint>` (rad) or `<joint>_deg` columns; in a log of several
    machines (a run's joints.csv: `<machine>.<joint>`), the columns of `machine`."""
    from .scene import CsvProblem, read_motion_csv

    try:
        times, angles = read_motion_csv(Path(path))
    except CsvProblem as exc:
        raise UserError(f"{path}: {exc}") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read the motion CSV ({exc.strerror})") from None
    mine = f"{machine}."
    if machine and any(j.startswith(mine) for j in angles):
        angles = {j[len(mine):]: v for j, v in angles.items() if j.startswith(mine)}
    for joint in angles:
        if joint not in joints:
            other = f"; a log of machine {joint.split('.')[0]!r}, and this one is {machine!r}" \
                if "." in joint and machine else ""
            raise UserError(f"{path}: column {joint!r} is not a joint of this machine "
                            f"(joints: {', '.join(joints)}){other}")
    if not angles:
        raise UserError(f"{path}: no joint columns (expected some of {', '.join(joints)})")
    t = np.asarray(times, float) + time_offset
    return JointProfile({j: t for j in angles}, {j: np.asarray(v, float) for j, v in angles.items()}, linear=True)


def bucket_tip_path(waypoints: list[tuple[float, np.ndarray, float]], kinematics, initial_q: dict[str, float],
                    joints: list[str]) -> JointProfile:
    """Cutting-edge waypoints [(t, xyz in the machine frame, bucket angle below horizontal)].

    Segments are straight lines in Cartesian space (linear in xyz and bucket angle), sampled at
    TIP_PATH_SAMPLE_HZ and solved by IK seeded from the previous sample, so the edge follows the line
    (a drag stays level) rather than an arc in joint space.
    """
    q_prev = dict(initial_q)
    # Check every waypoint first, so an unreachable one is named even if an earlier segment fails.
    for i, (t, xyz, angle) in enumerate(waypoints):
        try:
            q_prev = kinematics.solve_tip(np.asarray(xyz, float), float(angle), q_guess=q_prev)
        except ValueError as exc:
            raise UserError(f"motion.waypoints.{i}: cutting edge at {list(map(float, xyz))} with bucket angle "
                            f"{math.degrees(angle):.1f} deg is unreachable for this machine ({exc})") from None
    samples_t, samples_q = [], []
    q_prev = dict(initial_q)
    for i, (t, xyz, angle) in enumerate(waypoints):
        if i == 0:
            seg = [(t, np.asarray(xyz, float), angle)]
        else:
            t0, xyz0, a0 = waypoints[i - 1]
            n = max(1, int(math.ceil((t - t0) * TIP_PATH_SAMPLE_HZ)))
            seg = [(t0 + (t - t0) * k / n,
                    np.asarray(xyz0, float) + (np.asarray(xyz, float) - np.asarray(xyz0, float)) * k / n,
                    a0 + (angle - a0) * k / n) for k in range(1, n + 1)]
        for ts, p, a in seg:
            try:
                q_prev = kinematics.solve_tip(p, float(a), q_guess=q_prev)
            except ValueError as exc:
                raise UserError(f"motion.waypoints: the straight path from waypoint {i - 1} to {i} leaves the "
                                f"reachable space near {np.round(p, 3).tolist()} ({exc})") from None
            samples_t.append(ts)
            samples_q.append(dict(q_prev))
    times = np.asarray(samples_t)
    names = [j for j in joints if j in samples_q[0]]
    values = {j: np.unwrap(np.asarray([q[j] for q in samples_q])) for j in names}
    if len(times) == 1:
        return JointProfile({j: times for j in names}, values)
    return JointProfile({j: times for j in names}, values, linear=False)
