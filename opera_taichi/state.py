"""State: everything that changes during a run, as plain data (numpy arrays and numbers).

`sim.get_state()` copies it out of the engines and `sim.set_state(state)` puts it back; a run continued from a
State goes on bit for bit as the run it was taken from (same backend and thread count). `save_checkpoint` writes
one as a single versioned .npz file.

Bullet's constraint-solver warm start is not part of the state (as MuJoCo documents for mjSTATE_WARMSTART); the
machines' joint motors do not warm-start, so a fixed-base machine resumes exactly. A machine on tracks resumes its
wheel contacts from a cold solver: the same to round-off, not to the bit.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from .control import Control


@dataclass
class MachineState:
    """One machine. Arrays over `joints` (the actuated joints, in order) unless said otherwise."""

    joints: list[str]
    q: np.ndarray              # rad
    qd: np.ndarray             # rad/s
    effort: np.ndarray         # N m, the motors' torque in the last step
    q_target: np.ndarray       # rad, position targets as applied (clipped to the joint limits)
    qd_target: np.ndarray      # rad/s, velocity targets (used where velocity_mode)
    velocity_mode: np.ndarray  # bool: the joint follows qd_target instead of q_target
    speed_cmd: np.ndarray      # rad/s, what the motors were told in the last step
    hold: bool                 # emergency stop latched
    track_speeds: np.ndarray   # (2,) m/s, left and right
    other_q: np.ndarray        # rad, the other movable joints of the rigid body (track wheels)
    other_qd: np.ndarray       # rad/s
    base_com_xyz: np.ndarray   # (3,) m, the base's centre of mass (Bullet's base frame), world
    base_com_quat: np.ndarray  # (4,) x, y, z, w
    base_com_vel: np.ndarray   # (3,) m/s
    base_com_omega: np.ndarray  # (3,) rad/s
    track_stick: np.ndarray    # (wheels, 2) m: each track contact's stick displacement (tracks.py); (0, 2) fixed
    track_contacts: np.ndarray  # (wheels, 7): the last step's normal load N, contact point, ground normal

    @property
    def q_cmd(self) -> np.ndarray:
        """Applied position target per joint (NaN where the joint is in velocity mode): joints.csv's q_cmd."""
        return np.where(self.velocity_mode, np.nan, self.q_target)

    def arrays(self) -> dict[str, np.ndarray]:
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = np.asarray(value) if f.name != "joints" else np.asarray(value, dtype=str)
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> "MachineState":
        kw = {f.name: np.array(arrays[f.name]) for f in fields(cls)}
        kw["joints"] = [str(j) for j in arrays["joints"]]
        kw["hold"] = bool(arrays["hold"])
        kw["velocity_mode"] = kw["velocity_mode"].astype(bool)
        return cls(**kw)


@dataclass
class State:
    """The whole simulation at time t, after `step` steps."""

    t: float                                   # s
    step: int                                  # rigid steps taken
    machines: dict[str, MachineState] = field(default_factory=dict)
    soil: dict[str, np.ndarray] | None = None  # the soil solver's own arrays (None: no soil, or not copied)
    tool_wrench: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))  # (n_tools, 6) soil on each tool
    # over the last step, world frame, torque about the link origin: applied to the machines in the next step
    control: Control | None = None             # the last control applied
    rng: dict | None = None                    # numpy bit generator state of sim.rng
    model: str | None = None                   # the fingerprint of the model it was taken from (None: not known)
    rigid: bytes | None = None                 # Bullet's own state of the world (contact caches; None: not copied)

    def copy(self) -> "State":
        import copy

        return copy.deepcopy(self)
