"""The ground's grip on a machine's tracks: forces on the base where its track wheels touch the ground.

Bullet's wheels carry the machine's weight (frictionless, so they only push back along the normal); this model
gives each contact the track's tangential force instead. Along the track it drives the ground under the contact at
the track's surface speed; across it resists sideways slip. Each contact holds an elastic stick displacement, as a
DEM contact spring does, so a parked or digging machine stays put instead of creeping, and its force is capped by
Coulomb on an ellipse: `friction` x N along the track, `lateral_friction` x N across it. A crawler turns by
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
        # the last step's contacts: per wheel its normal load (N), point and ground normal (world)
        self.contacts = (np.zeros(n), np.zeros((n, 3)), np.tile([0.0, 0.0, 1.0], (n, 1)))

    def forces(self, normal: np.ndarray, velocity: np.ndarray, heading: np.ndarray, up: np.ndarray,
               side: np.ndarray, track_speed: tuple[float, float], dt: float) -> np.ndarray:
        """World forces (n, 3) on the base at each wheel's contact.

        normal (n,): normal load of each wheel (0: off the ground); velocity (n, 3): the base's velocity at each
        contact point; heading (3,): the base's x axis; up (n, 3): the ground's normal at each contact; side (n,):
        0 left, 1 right; track_speed: each side's surface speed (m/s, forward positive)."""
        along = heading[None, :] - up * (up @ heading)[:, None]
        length = np.linalg.norm(along, axis=1)
        on = (normal > 0.0) & (length > 1e-6)   # (a track standing on its end has no along: no grip)
        along = along / np.where(length > 1e-6, length, 1.0)[:, None]
        across = np.cross(up, along)
        slip = np.stack([np.sum(velocity * along, axis=1) - np.asarray(track_speed, float)[side],
                         np.sum(velocity * across, axis=1)], axis=1)
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
        # a slipping contact: its spring alone carries the capped force (no damping while it slides), so the force
        # stays at Coulomb's and points against the slip
        capped = np.any(f != trial, axis=1) & on
        self.stick[capped] = -f[capped] / self.k
        return f[:, :1] * along + f[:, 1:] * across
