"""Control: what the machines are told to do for the next step, and the controllers that say it.

A Control is keyed by machine name. Each machine gets joint position targets (rad) or joint velocity targets
(rad/s) per joint, track speeds (m/s) for a machine on tracks, and an emergency stop that holds the machine where it
is. Joints a Control does not name keep what they were last told. The Control carries its source and time; the
control actually applied (after clipping to the joint limits) is part of the State and is what joints.csv records.

A controller gives the Control of the next step: `controller.control(sim, t)` with t the time the step ends at.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Protocol, runtime_checkable

import numpy as np

from .errors import UserError


@dataclass
class MachineControl:
    """Commands to one machine for one step."""

    q_target: dict[str, float] = field(default_factory=dict)    # joint -> position target, rad
    qd_target: dict[str, float] = field(default_factory=dict)   # joint -> velocity target, rad/s
    track_speeds: tuple[float, float] | None = None              # left, right track surface speed, m/s
    hold: bool | None = None        # True: emergency stop (hold where it is); False: release; None: unchanged

    def to_dict(self) -> dict:
        return {"q_target": dict(self.q_target), "qd_target": dict(self.qd_target),
                "track_speeds": None if self.track_speeds is None else list(self.track_speeds), "hold": self.hold}

    @classmethod
    def from_dict(cls, data: dict) -> "MachineControl":
        speeds = data.get("track_speeds")
        return cls(dict(data.get("q_target") or {}), dict(data.get("qd_target") or {}),
                   None if speeds is None else (float(speeds[0]), float(speeds[1])), data.get("hold"))


@dataclass
class Control:
    """Commands for one step, per machine, with where they came from and the time they are for."""

    machines: dict[str, MachineControl] = field(default_factory=dict)
    t: float = math.nan
    source: str = ""

    def to_dict(self) -> dict:
        return {"t": self.t, "source": self.source, "machines": {k: v.to_dict() for k, v in self.machines.items()}}

    @classmethod
    def from_dict(cls, data: dict) -> "Control":
        return cls({k: MachineControl.from_dict(v) for k, v in (data.get("machines") or {}).items()},
                   float(data.get("t", math.nan)), str(data.get("source", "")))


def as_control(value, machine_names: list[str], t: float) -> Control:
    """A Control from what a user may pass to `sim.step`: a Control, None (keep the last commands), a
    MachineControl or a {joint: target rad} dict (the only machine), or {machine: MachineControl | dict}."""
    if isinstance(value, Control):
        if math.isnan(value.t):  # a Control made without a time is for this step
            value.t = t
        if not all(isinstance(v, MachineControl) for v in value.machines.values()):
            value.machines = {k: _machine_control(k, v) for k, v in value.machines.items()}
        return value
    if value is None:
        return Control({}, t, "hold-last")
    if isinstance(value, MachineControl):
        return Control({_only(machine_names): value}, t, "python")
    if isinstance(value, dict):
        if value and all(k in machine_names for k in value):
            return Control({k: _machine_control(k, v) for k, v in value.items()}, t, "python")
        return Control({_only(machine_names): MachineControl(q_target={k: _as_float(v) for k, v in value.items()})},
                       t, "python")
    raise TypeError(f"a control is a Control, a MachineControl, a {{joint: rad}} dict or None, got "
                    f"{type(value).__name__}")


def _machine_control(machine: str, value) -> MachineControl:
    """One machine's part of a control: a MachineControl, or a {joint: rad} dict of position targets."""
    if isinstance(value, MachineControl):
        return value
    if isinstance(value, dict):
        return MachineControl(q_target={k: _as_float(v) for k, v in value.items()})
    raise UserError(f"control of machine {machine!r}: expected a MachineControl or a {{joint: rad}} dict, got "
                    f"{type(value).__name__} {value!r:.60}")


def real_number(value) -> float | None:
    """value as a float when it is one real number (a Python or NumPy scalar, a 0-d array or tensor), else None: a
    bool, a string or an array of several values is no joint target, though float() would take some of them."""
    if type(value) is float or type(value) is int:  # (the common case, every step: no array made)
        return float(value)
    if isinstance(value, (str, bytes)):
        return None
    try:
        arr = np.asarray(value)
        if arr.ndim != 0 or arr.dtype.kind not in "iuf":  # (kind b: a bool, O: no number at all)
            return None
        return float(value)
    except (TypeError, ValueError):
        return None


def _as_float(value):
    number = real_number(value)
    return value if number is None else number  # (refused, naming its joint, where the machine applies it)


def _only(names: list[str]) -> str:
    if len(names) != 1:
        raise ValueError(f"the scene has {len(names)} machines ({names}); key the control by machine name")
    return names[0]


@runtime_checkable
class Controller(Protocol):
    """Gives the Control for the step that ends at time t."""

    def control(self, sim, t: float) -> Control: ...


class ScriptController:
    """The scene's motion scripts: each machine follows its own; a machine without one holds its initial pose."""

    source = "script"

    def __init__(self, model):
        self._machines = [(m.name, m.motion, dict(m.initial_q)) for m in model.machines]

    def control(self, sim, t: float) -> Control:
        return Control({name: MachineControl(q_target=motion.targets(t) if motion is not None else initial)
                        for name, motion, initial in self._machines}, t, self.source)


class CallableController:
    """A Python function `fn(sim, t) -> Control | {joint: rad} | None` as a controller."""

    def __init__(self, fn: Callable, source: str = "python"):
        self.fn, self.source = fn, source

    def control(self, sim, t: float) -> Control:
        ctrl = as_control(self.fn(sim, t), sim.machine_names, t)
        if not ctrl.source:
            ctrl.source = self.source
        return ctrl


def as_controller(value):
    """What run_scene takes as its controller: None (the scene's scripts), a Controller, or a function
    `fn(sim, t)` (wrapped in a CallableController). Anything else is refused before the run starts."""
    if value is None or isinstance(value, Controller):
        return value
    if callable(value):
        return CallableController(value)
    raise TypeError(f"controller: a Controller (an object with control(sim, t)) or a function fn(sim, t), got "
                    f"{type(value).__name__}")


def driver_of(controller) -> str:
    """What commands the machines, as the manifest records it: 'script' (the scene's motion scripts) or the
    controller's own name for itself (`driver`, else `source`, else its class)."""
    if controller is None or isinstance(controller, ScriptController):
        return "script"
    return (getattr(controller, "driver", None) or getattr(controller, "source", None)
            or type(controller).__name__)


class HoldController:
    """Commands nothing new: every machine keeps its last targets (its initial pose at the start)."""

    def control(self, sim, t: float) -> Control:
        return Control({}, t, "hold")
