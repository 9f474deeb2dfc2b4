"""The ground's grip on a machine's tracks: forces on the base where its track wheels touch the ground.

Bullet's wheels carry the machine's weight (frictionless, so they only push back along the normal); this model
gives each contact the track's tangential force instead. Along the track it drives the ground under the contact at
the track's surface speed; across it resists sideways slip. Each contact holds an elastic stick displacement, as a
DEM contact spring does, so a parked or digging machine stays put instead of creeping, and its force is capped by
Coulomb on an ellipse: tractive_friction x N along the track, lateral_friction x N across it. A crawler turns by
slipping its tracks sideways, which needs lateral resistance below the tractive grip (Wong, Theory of Ground
Vehicles: about 0.5-0.7 across and 0.8 along on firm soil). Each side's total drive force is capped by its motors
(n wheels x max_wheel_torque / wheel_radius).
"""
from __future__ import annotations

import math

import numpy as np

STICK_SLIP = 0.01       # m of elastic stick displacement at which a contact carrying its share of the weight slips


class TrackGround:
    def __init__(self, tracks: dict, machine_mass: float, gravity: float):
        self.mu_t = float(tracks["friction"])
        self.mu_l = float(tracks["lateral_friction"])
        n = 2 * len(tracks["x"])
        share = machine_mass / n
        self.k = self.mu_t * share * gravity / STICK_SLIP          # N/m per contact
        self.c = 2.0 * math.sqrt(self.k * share)                   # critically damped on its share of the mass
        self.drive_limit = len(tracks["x"]) * tracks["max_wheel_torque"] / tracks["wheel_radius"]   # N per side
        self.stick = np.zeros((n, 2))                              # per wheel: (along, across) displacement, m

    def forces(self, normal: np.ndarray, velocity: np.ndarray, heading: np.ndarray, up: np.ndarray,
               side: np.ndarray, track_speed: tuple[float, float], dt: float) -> np.ndarray:
        """World forces (n, 3) on the base at each wheel's contact.

        normal (n,): normal load of each wheel (0: off the ground); velocity (n, 3): the base's velocity at each
        contact point; heading, up (3,): the base's x axis and the ground normal; side (n,): 0 left, 1 right;
        track_speed: each side's surface speed (m/s, forward positive)."""
        along = heading - up * float(heading @ up)
        along /= np.linalg.norm(along)
        across = np.cross(up, along)
        slip = np.stack([velocity @ along - np.asarray(track_speed, float)[side], velocity @ across], axis=1)
        on = normal > 0.0
        self.stick[~on] = 0.0
        self.stick[on] += slip[on] * dt
        trial = -(self.k * self.stick + self.c * slip)
        limit = np.stack([self.mu_t * normal, self.mu_l * normal], axis=1)
        excess = np.sqrt(np.sum(np.divide(trial, limit, out=np.zeros_like(trial), where=limit > 0) ** 2, axis=1))
        f = trial * np.where(excess > 1.0, 1.0 / np.maximum(excess, 1e-300), 1.0)[:, None]
        for s in (0, 1):  # the motors' limit on each side's total drive force (along the track only)
            mine = side == s
            total = abs(float(np.sum(f[mine, 0])))
            if total > self.drive_limit:
                f[mine, 0] *= self.drive_limit / total
        f[~on] = 0.0
        # a slipping contact keeps the stick displacement its capped force stands for
        capped = np.any(f != trial, axis=1) & on
        self.stick[capped] = -(f[capped] + self.c * slip[capped]) / self.k
        return f[:, :1] * along + f[:, 1:] * across
