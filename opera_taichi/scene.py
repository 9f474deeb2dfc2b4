"""Scene files: the YAML schema, safe loading, `--set` overrides and one-line errors.

Every default and allowed range lives in the models below (field defaults and descriptions);
docs/scene_reference.md is generated from them: `python -m opera_taichi.scene > docs/scene_reference.md`.
"""
from __future__ import annotations

import contextlib
import csv
import inspect
import json
import math
import re
from datetime import datetime
from pathlib import Path, PurePath
from typing import Annotated, Any, Literal, Optional, Union, get_args, get_origin

import yaml
from pydantic import (BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, ValidationInfo,
                      model_validator)
from pydantic_core import PydanticCustomError

from .errors import UserError, did_you_mean
from .paths import machines_dir

MAX_SCENE_BYTES = 5 * 1024 * 1024
MAX_CSV_BYTES = 50 * 1024 * 1024
# A real scene has a few hundred values; anything far beyond is an alias bomb or not a scene
# (long joint profiles belong in a motion CSV). Counted while composing, so a refused file costs < ~1 s.
MAX_YAML_VALUES = 20_000
MAX_YAML_DEPTH = 50
MAX_COMMAND_LATENCY = 10.0  # s: a machine's response delay, far beyond a real one; machine.yaml has the same bound
SOIL_PRESETS = ("sand", "dirt", "gravel", "kanto_loam", "glass_beads")


# ----------------------------------------------------------------------------- value rules
def _show(value: Any, limit: int = 60) -> str:
    """A value as a user would recognise it from YAML, kept short."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif value is None:
        text = "null"
    elif isinstance(value, float):
        text = "nan" if math.isnan(value) else ("inf" if value == math.inf else
                                                 "-inf" if value == -math.inf else repr(value))
    elif isinstance(value, str):
        text = repr(value)
    elif isinstance(value, (list, tuple, dict)):
        text = json.dumps(value, default=str, allow_nan=True).replace("NaN", "nan").replace(
            "Infinity", "inf")
    else:
        text = str(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _fail(expected: str | None = None, value: Any = ..., *, message: str | None = None,
          key: str | None = None, hint: str = "") -> PydanticCustomError:
    """An error the loader turns into `<file>: <path>[.key]: expected <expected>, got <value><hint>`."""
    ctx: dict[str, Any] = {"expected": expected or "", "message": message or "", "key": key or "",
                           "hint": hint, "got": "" if value is ... else _show(value)}
    return PydanticCustomError("scene_value", "{expected}{message}", ctx)


def _fmt(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


class _NumberRule:
    """A real number (not a bool, not a string), finite, within bounds; `doc` is shown in the reference."""

    def __init__(self, unit: str = "", *, gt=None, ge=None, le=None, integer: bool = False):
        self.unit, self.gt, self.ge, self.le, self.integer = unit, gt, ge, le, integer
        bounds = [f"> {_fmt(gt)}" if gt is not None else "", f">= {_fmt(ge)}" if ge is not None else "",
                  f"<= {_fmt(le)}" if le is not None else ""]
        self.bounds = " and ".join(b for b in bounds if b)
        kind = "integer" if integer else "number"
        self.doc = kind + (f", {unit}" if unit else "") + (f", {self.bounds}" if self.bounds else "")

    def expected(self, finite: bool = False) -> str:
        kind = "an integer" if self.integer else ("a finite number" if finite else "a number")
        unit = f" in {self.unit}" if self.unit else ""
        return kind + unit + (f" {self.bounds}" if self.bounds else "")

    def __call__(self, value):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (
                self.integer and not isinstance(value, int)):
            raise _fail(self.expected(), value)
        if not self.integer:
            try:
                value = float(value)
            except OverflowError:
                raise _fail(self.expected(finite=True), value) from None
            if not math.isfinite(value):
                raise _fail(self.expected(finite=True), value)
        if (self.gt is not None and not value > self.gt) or (self.ge is not None and not value >= self.ge) \
                or (self.le is not None and not value <= self.le):
            raise _fail(self.expected(), value)
        return value


def _num(unit: str = "", **bounds):
    return Annotated[float, BeforeValidator(_NumberRule(unit, **bounds))]


class _ChoiceRule:
    def __init__(self, choices: tuple[str, ...], not_yet: tuple[str, ...] = ()):
        self.choices, self.not_yet = choices, not_yet
        self.doc = " \\| ".join(choices)

    def __call__(self, value):
        if isinstance(value, str) and value in self.choices:
            return value
        hint = (f" ({value} is not available yet)" if value in self.not_yet
                else did_you_mean(value, self.choices))
        raise _fail("one of " + ", ".join(self.choices), value, hint=hint)


def _choice(*choices: str, not_yet: tuple[str, ...] = ()):
    return Annotated[str, BeforeValidator(_ChoiceRule(choices, not_yet))]


class _NameRule:
    def __init__(self, pattern: str, words: str):
        self.pattern, self.words, self.doc = re.compile(pattern), words, f"name ({words})"

    def __call__(self, value):
        if not isinstance(value, str) or not self.pattern.fullmatch(value):
            raise _fail(f"a name of {self.words}", value)
        return value


class _VectorRule:
    """A list of exactly 3 entries; each entry is then checked by its own rule (so errors name the index)."""

    def __init__(self, what: str, doc: str):
        self.what, self.doc = what, doc

    def __call__(self, value):
        if not isinstance(value, (list, tuple)) or len(value) != 3:
            raise _fail(f"a list of 3 numbers {self.what}", value)
        return tuple(value)


def _vec3(unit: str, what: str = "[x, y, z]", **bounds):
    item = _num(unit, **bounds)
    rule = _VectorRule(f"{what} in {unit}" + (f" (each {item.__metadata__[0].func.bounds})"
                                                if bounds else ""), f"{what}, {unit}")
    return Annotated[tuple[item, item, item], BeforeValidator(rule)]


def _strict_bool(value):
    if not isinstance(value, bool):
        raise _fail("true or false", value)
    return value


_strict_bool.doc = "true \\| false"


def _bool_or_auto(value):
    if isinstance(value, bool) or value == "auto":
        return value
    raise _fail("true, false or auto", value)


_bool_or_auto.doc = "true \\| false \\| auto"


def _bool_or_null(value):
    if value is None or isinstance(value, bool):
        return value
    raise _fail("true, false or null", value)


_bool_or_null.doc = "true \\| false \\| null"


def _scene_dir(info: ValidationInfo) -> Path:
    base = (info.context or {}).get("base_dir")
    return Path(base) if base else Path.cwd()


class _FileRule:
    """A path to an existing file; relative paths are relative to the scene file's directory."""

    doc = "file path"

    def __call__(self, value, info: ValidationInfo) -> Path:
        if isinstance(value, Path):
            value = str(value)
        if not isinstance(value, str) or not value.strip():
            raise _fail("a file path", value)
        path = Path(value).expanduser()
        if not path.is_absolute():
            path = _scene_dir(info) / path
        if path.is_dir():
            raise _fail("a file, not a directory", value)
        if not path.is_file():
            raise _fail("an existing file (relative to the scene file)", value, hint=f" (no file at {path})")
        return path.resolve()


def _dir_string(value):
    if isinstance(value, Path):
        return value
    if not isinstance(value, str) or not value.strip():
        raise _fail("a folder path", value)
    return Path(value)


_dir_string.doc = "folder path"


def _builtin_machines() -> list[str]:
    root = machines_dir()
    return sorted(p.name for p in root.iterdir() if p.is_dir() and p.name[0] not in "._") \
        if root.is_dir() else []


def _looks_like_path(value: str) -> bool:
    return "/" in value or "\\" in value or "." in value


class _UrdfRule:
    doc = "built-in machine name or .urdf path"

    def __call__(self, value, info: ValidationInfo) -> Path:
        if isinstance(value, str) and value and not _looks_like_path(value):
            builtin = _builtin_machines()
            if value not in builtin:
                raise _fail(f"a built-in machine ({', '.join(builtin) or 'none installed'}) or a path to a "
                            ".urdf file", value, hint=did_you_mean(value, builtin))
            urdf = machines_dir() / value / f"{value}.urdf"
            if not urdf.is_file():
                raise _fail(message=f"built-in machine {value!r} has no URDF (no file at {urdf})")
            return urdf
        return _FileRule()(value, info)


class _MachineConfigRule:
    doc = "built-in machine name or machine.yaml path"

    def __call__(self, value, info: ValidationInfo) -> Path:
        if isinstance(value, str) and value and not _looks_like_path(value):
            path = machines_dir() / value / "machine.yaml"
            if not path.is_file():
                builtin = _builtin_machines()
                raise _fail(f"a built-in machine ({', '.join(builtin) or 'none installed'}) or a path to a "
                            "machine.yaml", value, hint=did_you_mean(value, builtin))
            return path
        return _FileRule()(value, info)


def _none_to(empty):
    return BeforeValidator(lambda v: type(empty)() if v is None else v)


Seconds = _num("s")
NonNegSeconds = _num("s", ge=0)
Radians = _num("rad")
Degrees = _num("deg")
Rate = _num("Hz", gt=0)
Vec3M = _vec3("m")
Bool = Annotated[bool, BeforeValidator(_strict_bool)]
ExistingFile = Annotated[Path, BeforeValidator(_FileRule())]
JointAngles = Annotated[dict[str, Radians], _none_to({})]
JointAnglesDeg = Annotated[dict[str, Degrees], _none_to({})]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _exactly_one(model: BaseModel, first: str, second: str, *, required: bool = True):
    given = [k for k in (first, second) if getattr(model, k) is not None]
    if len(given) == 2:
        raise _fail(message=f"give {first} or {second}, not both", key=second)
    if required and not given:
        raise _fail(message=f"missing: give {first} or {second}", key=first)


def _radians_from_deg(model: BaseModel, rad_key: str, deg_key: str):
    """Fold a `<key>_deg` field into its radian twin so the resolved scene holds radians only."""
    deg = getattr(model, deg_key)
    if deg is None:
        return
    if rad_key in model.model_fields_set:
        raise _fail(message=f"give {rad_key} (rad) or {deg_key}, not both", key=deg_key)
    if isinstance(deg, dict):
        setattr(model, rad_key, {k: math.radians(v) for k, v in deg.items()})
    elif isinstance(deg, tuple):
        setattr(model, rad_key, tuple(math.radians(v) for v in deg))
    else:
        setattr(model, rad_key, math.radians(deg))
    setattr(model, deg_key, None)


def _strictly_increasing(waypoints: list, prefix: str = "waypoints"):
    for i in range(1, len(waypoints)):
        if not waypoints[i].t > waypoints[i - 1].t:
            raise _fail(f"a time > {_fmt(waypoints[i - 1].t)} s (waypoint times must strictly increase)",
                        waypoints[i].t, key=f"{prefix}.{i}.t")


# ----------------------------------------------------------------------------- the schema
class SimConfig(_Model):
    """Time stepping and backend."""

    duration: _num("s", gt=0, le=3600) = Field(20.0, description="Simulated time to run, in whole steps of dt (a "
                                                                "remainder takes one more step).")
    dt: _num("s", ge=1e-5, le=0.01) = Field(0.001, description="Rigid-body (PyBullet) step.")
    soil_dt: Optional[_num("s", gt=0)] = Field(
        None, description="Soil substep; null = from the soil's stability limit. Must be <= dt; a value "
                          "above the soil's stability limit is rejected when the soil is built.")
    arch: _choice("cpu", "cuda", "auto") = Field("cpu", description="Taichi backend; `--arch` overrides it.")
    spin_wait: Annotated[Union[bool, Literal["auto"]], BeforeValidator(_bool_or_auto)] = Field(
        "auto", description="On the CPU, keep the other cores running while the soil steps (a lowest-priority helper "
                            "process per other core spins; docs/performance.md): faster where an idle core halts "
                            "at once, as on the 2-vCPU cloud VM measured (1-16% by grain size), at the cost of "
                            "those cores' idle time. `auto`: on where the CPUs' idle driver halts at once (Linux's `haltpoll` with "
                            "`guest_halt_poll_ns` 0), off elsewhere. Same results.")
    seed: Annotated[int, BeforeValidator(_NumberRule(ge=0, le=2**32 - 1, integer=True))] = Field(
        0, description="Random seed (bed packing); same seed, backend and thread count give the same run.")

    @model_validator(mode="after")
    def _substep_fits(self):
        if self.soil_dt is not None and self.soil_dt > self.dt:
            raise _fail(f"a number in s <= sim.dt ({_fmt(self.dt)}) or null", self.soil_dt, key="soil_dt")
        return self


class Box(_Model):
    """An axis-aligned box in the world frame (x forward, y left, z up; ground at z = 0)."""

    min: Vec3M = Field(description="Lower corner [x, y, z].")
    max: Vec3M = Field(description="Upper corner; greater than `min` on every axis.")

    @model_validator(mode="after")
    def _ordered(self):
        for axis, lo, hi in zip("xyz", self.min, self.max):
            if not lo < hi:
                raise _fail(f"max > min on every axis ({axis}: min is {_fmt(lo)})", list(self.max), key="max")
        return self

    def contains(self, other: "Box") -> bool:
        return all(a <= b for a, b in zip(self.min, other.min)) and \
            all(a >= b for a, b in zip(self.max, other.max))


def _default_bed() -> list[Box]:
    return [Box(min=(3.0, -1.5, -1.0), max=(9.0, 1.5, 0.0))]


class TerrainConfig(_Model):
    """A bed from real terrain: the soil fills each bed's footprint from the scanned surface down to `depth` below
    its lowest point (a box pit whose fill is trimmed to the surface instead of level), poured, settled and cached
    like any bed."""

    file: ExistingFile = Field(description="Scan (LAS/LAZ, PLY, XYZ/CSV, GeoTIFF or NPZ heightmap), relative to the "
                                           "scene file; it must cover every bed's footprint.")
    xyz: Vec3M = Field((0.0, 0.0, 0.0), description="Scan frame -> world: translation [x, y, z], applied after the "
                                                    "rotation.")
    yaw: Radians = Field(0.0, description="Scan frame -> world: rotation about z.")
    yaw_deg: Optional[Degrees] = Field(None, exclude=True, description="Same, in degrees.")
    roll: Radians = Field(0.0, description="Rotation about x (before pitch and yaw).")
    roll_deg: Optional[Degrees] = Field(None, exclude=True, description="Same, in degrees.")
    pitch: Radians = Field(0.0, description="Rotation about y.")
    pitch_deg: Optional[Degrees] = Field(None, exclude=True, description="Same, in degrees.")
    depth: _num("m", gt=0) = Field(1.0, description="Depth of the soil below the lowest scanned point of a bed's "
                                                    "footprint (the bed's floor; replaces its min z).")

    @model_validator(mode="after")
    def _to_radians(self):
        for name in ("yaw", "roll", "pitch"):
            _radians_from_deg(self, name, name + "_deg")
        return self


class SoilConfig(_Model):
    """The soil: a bed of pits cut into the ground and filled with particles."""

    model: _choice("dem", not_yet=("mpm",)) = Field("dem", description="Soil solver (only `dem` for now).")
    preset: _choice(*SOIL_PRESETS) = Field("dirt", description="Bulk parameter preset (their values: the README's "
                                           "Scenes section, opera_taichi/soil.py).")
    overrides: Annotated[dict[str, _num()], _none_to({})] = Field(
        default_factory=dict, description="Bulk parameters replacing the preset's (density, friction_angle, "
        "friction_angle_deg, cohesion, youngs_modulus, restitution, radius, rolling_resistance, "
        "tool_friction_angle, tool_friction_angle_deg, polydispersity, adhesion (soil-tool, Pa); SI units); names are "
        "checked by the soil module.")
    domain: Box = Field(default_factory=lambda: Box(min=(-2.0, -6.0, -3.0), max=(12.0, 6.0, 8.0)),
                        description="Region where particles live; a particle leaving it is removed and "
                                    "counted as out-of-domain mass.")
    bed: Annotated[list[Box], Field(min_length=1)] = Field(
        default_factory=_default_bed, description="Pit boxes cut into the ground and filled with soil; each "
        "inside the domain with max z <= 0 (0 = flush with the ground).")
    settle_time: _num("s", ge=0) = Field(1.0, description="Time the bed settles under gravity before the run.")
    max_speed: _num("m/s", gt=0) = Field(30.0, description="Divergence guard: a faster particle stops the run "
                                                           "(exit 3).")
    heightmap_cell: _num("m", gt=0) = Field(0.05, description="Cell size of the terrain heightmaps, adjusted on "
                                            "each axis to the nearest that divides the domain into whole cells "
                                            "(the files' x and y give the cells' centres).")
    terrain: Optional[TerrainConfig] = Field(
        None, description="Fill the beds up to a scanned surface instead of level with their top (see TerrainConfig).")
    preset_file: Optional[ExistingFile] = Field(
        None, description="Soil preset file (YAML of bulk parameters, the keys of `overrides`, e.g. written by "
        "`opera-taichi calibrate`), relative to the scene file: its values replace the preset's and `overrides` "
        "replace its; its own `preset` key, when given, names the preset it builds on.")
    sleep: Bool = Field(False, description="Let particles at rest away from every tool sleep (not integrated; woken "
                                           "by a tool within a grain's reach or a moving neighbour; while a tool "
                                           "moves slowly, nothing sleeps near it and a sleeper the soil it shoves "
                                           "closes in on wakes too): the cost of a step follows the soil that "
                                           "moves. The settled bed starts asleep; in a big bed the soil far from "
                                           "every tool and from anything moving is also left out of the neighbour "
                                           "rebuilds (frozen) until something nears it. Mass and contact history "
                                           "stay exact; the soil's path is another, as a chaotic dig's with another "
                                           "seed.")
    bed_shift: Vec3M = Field((0.0, 0.0, 0.0), description="Moves every settled bed particle by [dx, dy, dz] at "
                             "t = 0, leaving the pits empty: [dx, 0, H] stands a settled block of height H on the "
                             "ground, released at once (column collapse, heaps, free-standing cuts).")
    clear_above: Optional[_num("m", gt=0)] = Field(
        None, description="Spoil-clearing plane: during the run a particle whose centre rises above this height "
        "is removed and booked as out-of-domain mass (soil-bin tests of the cutting force without the spoil's "
        "surcharge); null = only the domain top.")

    @model_validator(mode="after")
    def _bed_fits(self):
        if self.preset_file is not None:
            from .soil import read_preset_file

            try:
                base, _ = read_preset_file(self.preset_file)
            except UserError as exc:
                raise _fail(message=str(exc), key="preset_file") from None
            if base is not None and "preset" in self.model_fields_set and base != self.preset:
                raise _fail(message=f"{self.preset_file.name} builds on preset {base!r}, the scene names "
                                    f"{self.preset!r}; remove one", key="preset")
        if self.clear_above is not None and self.clear_above > self.domain.max[2]:
            raise _fail(f"a height <= the domain top {_fmt(self.domain.max[2])} m", self.clear_above,
                        key="clear_above")
        for i, box in enumerate(self.bed):
            if box.max[2] > 0:
                raise _fail("a pit top z <= 0 (0 = flush with the ground)", list(box.max), key=f"bed.{i}.max")
            if not self.domain.contains(box):
                raise _fail(f"a box inside soil.domain ({list(self.domain.min)} .. {list(self.domain.max)})",
                            {"min": list(box.min), "max": list(box.max)}, key=f"bed.{i}")
        return self


class BasePose(_Model):
    """Where the machine's base_link stands."""

    xyz: Vec3M = Field((0.0, 0.0, 0.0), description="Position [x, y, z] of base_link.")
    yaw: Radians = Field(0.0, description="Heading about z.")
    yaw_deg: Optional[Degrees] = Field(None, exclude=True, description="Heading in degrees, instead of yaw.")

    @model_validator(mode="after")
    def _to_radians(self):
        _radians_from_deg(self, "yaw", "yaw_deg")
        return self


class ActuatorLimits(_Model):
    """Per-joint actuator settings; null keeps the machine config's value."""

    max_speed: Optional[_num("rad/s", gt=0)] = Field(None, description="Joint speed limit.")
    max_torque: Optional[_num("N m", gt=0)] = Field(None, description="Joint torque limit.")
    gain: Optional[_num("1/s", gt=0)] = Field(None, description="Position-loop gain: commanded speed = gain "
                                                                "x position error, capped at max_speed.")


class MachineConfig(_Model):
    """The articulated machine (PyBullet)."""

    urdf: Annotated[Path, BeforeValidator(_UrdfRule())] = Field(
        "zx120", validate_default=True, description="Built-in machine name (a folder of machines/) or a path "
        "to a URDF, relative to the scene file.")
    config: Optional[Annotated[Path, BeforeValidator(_MachineConfigRule())]] = Field(
        None, description="machine.yaml path or built-in machine name; null = machine.yaml beside the URDF "
                          "when there is one.")
    base_pose: BasePose = Field(default_factory=BasePose, description="Pose of base_link in the world.")
    fixed_base: Bool = Field(True, description="Weld base_link to the world (no tracks on the ground).")
    initial_joints: JointAngles = Field(default_factory=dict, description="Joint name -> initial angle; a joint "
                                        "not given starts at 0, or at its limit nearest to 0.")
    initial_joints_deg: Optional[JointAnglesDeg] = Field(
        None, exclude=True, description="Joint name -> initial angle in degrees (may be combined with "
                                        "initial_joints for other joints).")
    actuators: Annotated[dict[str, ActuatorLimits], _none_to({})] = Field(
        default_factory=dict, description="Joint name -> actuator settings overriding the machine config.")
    command_latency: Optional[_num("s", ge=0, le=MAX_COMMAND_LATENCY)] = Field(
        None, description="Dead time between a command from a ROS bridge and the machine acting on it (the real "
                          "machine's response delay); null = the machine config's `command_latency` (0 if none).")
    soil_wedge: Annotated[Optional[bool], BeforeValidator(_bool_or_null)] = Field(
        None, description="Cut with the soil wedge at the machine's cutting edges (the machine config's "
                          "`cutting_edges`): where the edge meets the soil it pushes back with the earthmoving "
                          "equation's equilibrium at any grain size, where the grains alone push back with a layer "
                          "of coarse grains under the edge (the main job's drag at 12 cm grains: 0.99 x its 5 cm "
                          "drag with the wedge, 1.74 x with the grains alone; docs/dig_path.md). null: where fewer "
                          "than 4 grain diameters span the edge's width (the ZX120: grain radius over 8.75 cm), "
                          "since from there down the grains alone drag within the seeds' spread of the wedge and run "
                          "faster; true: at any grain size (an error where the machine config gives no edges); "
                          "false: the soil pushes back grain by grain. The manifest's soil.wedges names the tools "
                          "that cut with it.")

    @model_validator(mode="after")
    def _resolve(self):
        if self.initial_joints_deg:
            both = sorted(set(self.initial_joints) & set(self.initial_joints_deg))
            if both:
                raise _fail(message=f"joint {both[0]!r} is given in both initial_joints and "
                                    "initial_joints_deg", key=f"initial_joints_deg.{both[0]}")
            self.initial_joints = {**self.initial_joints,
                                   **{k: math.radians(v) for k, v in self.initial_joints_deg.items()}}
        self.initial_joints_deg = None
        if self.config is None and (Path(self.urdf).parent / "machine.yaml").is_file():
            self.config = Path(self.urdf).parent / "machine.yaml"
        return self


class CuttingEdgeConfig(_Model):
    """A tool's cutting edge in the tool's frame: the soil it cuts pushes back as one wedge (AGX's aggregate)."""

    centre: Vec3M = Field(description="Middle of the edge.")
    face_normal: _vec3("tool frame") = Field(description="Normal of the face that pushes the soil, pointing into it "
                                                         "(any length).")
    face_up: _vec3("tool frame") = Field(description="Direction up the face, away from the edge (any length).")
    width: _num("m", gt=0) = Field(description="Length of the edge (within the tool's own extent).")
    opening: Bool = Field(False, description="The face is an opening, not a plate (a bucket's mouth, from its cutting "
                                             "edge to its top edge): the wedge is the soil the edge meets, which "
                                             "rises with it until it clears the edge, and the soil over the edge "
                                             "passes into the bucket; false: the whole wedge slides up the face as "
                                             "up a blade.")

    @model_validator(mode="after")
    def _check(self):
        directions = {}
        for key in ("face_normal", "face_up"):
            v = [float(c) for c in getattr(self, key)]
            big = max(abs(c) for c in v)
            if big == 0.0:
                raise _fail("a direction (not all zero)", v, key=key)
            v = [c / big for c in v]  # (scaled first: any length, 1e-12 or 1e300)
            length = math.sqrt(sum(c * c for c in v))
            directions[key] = [c / length for c in v]
        (ax, ay, az), (bx, by, bz) = directions["face_normal"], directions["face_up"]
        if math.hypot(ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx) < 1e-6:
            raise _fail("a direction across face_normal (up the face, away from the edge)", [float(c) for c in self.face_up],
                        key="face_up")
        return self


class ToolConfig(_Model):
    """A standalone rigid tool moved along a straight line at constant velocity (kinematic)."""

    name: Annotated[str, BeforeValidator(_NameRule(r"[A-Za-z0-9_]+", "letters, digits and _"))] = Field(
        description="Unique tool name (used in tool_wrench.csv).")
    box: Optional[_vec3("m", "[sx, sy, sz]", gt=0)] = Field(None, description="Box size; give box or mesh.")
    mesh: Optional[ExistingFile] = Field(None, description="Mesh file (any format trimesh reads), relative to "
                                                           "the scene file; give box or mesh.")
    start: Vec3M = Field(description="Position of the tool origin at t = start_time.")
    rpy: _vec3("rad", "[roll, pitch, yaw]") = Field((0.0, 0.0, 0.0), description="Orientation (fixed axes).")
    rpy_deg: Optional[_vec3("deg", "[roll, pitch, yaw]")] = Field(None, exclude=True,
                                                                  description="Orientation in degrees.")
    velocity: _vec3("m/s", "[vx, vy, vz]") = Field((0.0, 0.0, 0.0), description="Constant velocity.")
    start_time: NonNegSeconds = Field(0.0, description="Before it the tool waits at `start`.")
    stop_time: Optional[NonNegSeconds] = Field(None, description="After it the tool stops; null = never.")
    cutting_edge: Optional[CuttingEdgeConfig] = Field(
        None, description="The tool's cutting edge (DEM soil): the soil it cuts pushes back as the earthmoving "
                          "equation's wedge instead of grain by grain; null = grain by grain.")

    @model_validator(mode="after")
    def _check(self):
        _exactly_one(self, "box", "mesh")
        _radians_from_deg(self, "rpy", "rpy_deg")
        if self.stop_time is not None and not self.stop_time > self.start_time:
            raise _fail(f"a time > start_time ({_fmt(self.start_time)} s) or null", self.stop_time,
                        key="stop_time")
        return self


class JointWaypoint(_Model):
    """Joint targets reached at time t (interpolated between waypoints without overshoot)."""

    t: NonNegSeconds = Field(description="Time.")
    q: Optional[JointAngles] = Field(None, description="Joint name -> target angle; joints not given hold "
                                                       "their previous value.")
    q_deg: Optional[JointAnglesDeg] = Field(None, exclude=True, description="Same, in degrees (give q or "
                                                                            "q_deg).")

    @model_validator(mode="after")
    def _to_radians(self):
        _exactly_one(self, "q", "q_deg")
        _radians_from_deg(self, "q", "q_deg")
        return self


class JointWaypoints(_Model):
    """Motion as joint-space waypoints."""

    type: Literal["joint_waypoints"] = Field(description="Selects this kind of motion.")
    waypoints: Annotated[list[JointWaypoint], Field(min_length=1)] = Field(
        description="At least one; strictly increasing t.")

    @model_validator(mode="after")
    def _ordered(self):
        _strictly_increasing(self.waypoints)
        return self


class CsvProblem(Exception):
    """A bad cell or header in a motion CSV (the loader names the file and the scene key)."""


def read_motion_csv(path: Path) -> tuple[list[float], dict[str, list[float]]]:
    """Reads a joint profile: header `t` plus `<joint>` (rad) or `<joint>_deg` columns, or a run's own joints.csv
    (its `<joint>.q` columns).

    Returns (times as written, joint -> angles in rad). Raises CsvProblem with a one-line reason.
    Joint names are checked later, against the machine.
    """
    if path.stat().st_size > MAX_CSV_BYTES:
        raise CsvProblem(f"larger than the {MAX_CSV_BYTES // 2**20} MB limit for a motion CSV")
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise CsvProblem(f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start})") from None
    reader = csv.reader(text.splitlines())
    try:
        rows = [row for row in reader if row and any(c.strip() for c in row)]
    except csv.Error as exc:  # e.g. a cell beyond the csv module's field size limit (128 KiB)
        raise CsvProblem(f"line {reader.line_num}: not readable as CSV ({exc})") from None
    if not rows:
        raise CsvProblem("empty; expected a header `t,<joint>,...` and at least one row")
    header = [c.strip() for c in rows[0]]
    if "t" not in header:
        raise CsvProblem(f"header has no `t` column, got {_show(header)}")
    repeated = next((name for name in header if header.count(name) > 1), None)
    if repeated is not None:  # which of two `t` (or two joint) columns is meant cannot be told
        raise CsvProblem(f"header: column {repeated!r} appears more than once")
    joints: dict[str, tuple[int, float]] = {}
    # a run's own joints.csv: `<joint>.q` are the positions; its other `<joint>.*` columns are not angles
    recorded = any(name.endswith(".q") for name in header)
    for col, name in enumerate(header):
        if name == "t" or (recorded and "." in name and not name.endswith(".q")):
            continue
        if recorded and name.endswith(".q"):
            name = name[:-2]
        joint, scale = (name[:-4], math.pi / 180) if name.endswith("_deg") else (name, 1.0)
        if not joint or joint in joints or header.count(name) > 1:
            raise CsvProblem(f"header: column {name!r} is empty or repeats a joint")
        joints[joint] = (col, scale)
    if len(rows) < 2:
        raise CsvProblem("has a header but no rows")
    t_col = header.index("t")
    used = {col for col, _ in joints.values()}
    times: list[float] = []
    angles: dict[str, list[float]] = {j: [] for j in joints}
    for line, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise CsvProblem(f"line {line}: expected {len(header)} fields, got {len(row)}")
        # only t and the joints' columns are read: a run's other columns may be empty (its .q_cmd in velocity mode)
        values = {}
        for col in [t_col, *sorted(used)]:
            try:
                values[col] = float(row[col])
            except ValueError:
                raise CsvProblem(f"line {line}, column {header[col]}: expected a number, got {row[col].strip()!r}") \
                    from None
            if not math.isfinite(values[col]):
                raise CsvProblem(f"line {line}, column {header[col]}: expected a finite number, got {values[col]}")
        if times and not values[t_col] > times[-1]:
            raise CsvProblem(f"line {line}, column t: expected t > {_fmt(times[-1])} (strictly increasing), "
                             f"got {_fmt(values[t_col])}")
        times.append(values[t_col])
        for joint, (col, scale) in joints.items():
            angles[joint].append(values[col] * scale)
    return times, angles


class CsvMotion(_Model):
    """Motion replayed from a CSV of joint angles (linear interpolation between rows)."""

    type: Literal["csv"] = Field(description="Selects this kind of motion.")
    file: ExistingFile = Field(description="CSV relative to the scene file: header `t` plus `<joint>` (rad) or "
                                           "`<joint>_deg` columns (or a run's own joints.csv: its `<joint>.q` columns); t "
                                           "strictly increasing.")
    # bounded: far beyond any run's 3600 s, yet small enough that t + time_offset keeps the rows' times apart
    time_offset: _num("s", ge=-1e6, le=1e6) = Field(0.0, description="Row time t plays at simulated time "
                                                                      "t + time_offset.")

    @model_validator(mode="after")
    def _readable(self):
        try:
            read_motion_csv(self.file)
        except CsvProblem as exc:
            raise _fail(message=f"{self.file.name}: {exc}", key="file") from None
        return self


class TipWaypoint(_Model):
    """A bucket cutting-edge target at time t, in the machine (base_link) frame."""

    t: NonNegSeconds = Field(description="Time.")
    xyz: Vec3M = Field(description="Cutting-edge position in the base_link frame.")
    bucket_angle: Optional[Radians] = Field(
        None, description="Angle of the bucket pin -> cutting edge line below the horizontal (0 = edge level "
                          "ahead of the pin, pi/2 = straight below it); null = the previous waypoint's (the "
                          "first waypoint needs one).")
    bucket_angle_deg: Optional[Degrees] = Field(None, exclude=True, description="Same, in degrees.")

    @model_validator(mode="after")
    def _to_radians(self):
        _radians_from_deg(self, "bucket_angle", "bucket_angle_deg")
        return self


class BucketTipPath(_Model):
    """Motion as a path of the bucket cutting edge (solved to joints by inverse kinematics)."""

    type: Literal["bucket_tip_path"] = Field(description="Selects this kind of motion.")
    waypoints: Annotated[list[TipWaypoint], Field(min_length=1)] = Field(
        description="At least one; strictly increasing t.")

    @model_validator(mode="after")
    def _ordered(self):
        _strictly_increasing(self.waypoints)
        if self.waypoints[0].bucket_angle is None:
            raise _fail(message="missing: the first waypoint needs bucket_angle or bucket_angle_deg",
                        key="waypoints.0.bucket_angle")
        for prev, wp in zip(self.waypoints, self.waypoints[1:]):
            if wp.bucket_angle is None:
                wp.bucket_angle = prev.bucket_angle
        return self


Motion = Annotated[Union[JointWaypoints, CsvMotion, BucketTipPath], Field(discriminator="type")]


class MachineEntry(MachineConfig):
    """One machine of several (`machines:`): a machine section with its own name and motion."""

    name: Optional[Annotated[str, BeforeValidator(_NameRule(r"[A-Za-z][A-Za-z0-9_]{0,39}",
                                                            "a letter, then letters, digits or _ (at most 40)"))]] \
        = Field(None, description="Unique machine name (ROS namespace, joints.csv prefix); null = the URDF's robot "
                                  "name.")
    motion: Optional[Motion] = Field(None, description="This machine's motion, chosen by `type`; null = hold still.")


class OutputConfig(_Model):
    """What the run folder gets."""

    dir: Optional[Annotated[Path, BeforeValidator(_dir_string)]] = Field(
        None, description="Run folder, relative to the current directory; null = "
                          "runs/<name>-<YYYYmmdd-HHMMSS>. `--out` overrides it.")
    joints_rate: Rate = Field(100.0, description="joints.csv sample rate; at most 1/sim.dt.")
    wrench_rate: Rate = Field(100.0, description="tool_wrench.csv sample rate; at most 1/sim.dt.")
    mass_rate: Rate = Field(10.0, description="soil_mass.csv sample rate; at most 1/sim.dt.")
    particles_final: Bool = Field(False, description="Write particles_final.npz.")
    plots: Bool = Field(True, description="Write PNG plots.")
    replay: Bool = Field(False, description="Write replay.bin (frames for `opera-taichi view RUN_DIR`: the 3-D "
                                            "replay, --html, --mp4); `run --replay` sets it.")
    replay_rate: Rate = Field(10.0, description="replay.bin frame rate, Hz of simulated time; at most 1/sim.dt.")
    bag: Optional[_choice("mcap", "ros1")] = Field(
        None, description="Also write the run's ROS topics (the bridge's topics and rates): `mcap` = run.mcap (ROS 2 "
                          "schemas, CDR; ros2 bag, Foxglove, rosbags), `ros1` = run.bag (ROS 1); null = none. With "
                          "--checkpoint-every the bag is finished at each checkpoint and goes on in "
                          "run-from-step-<n> parts (README: The run folder).")


_ROS_NAME = r"[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*"


class BridgeConfig(_Model):
    """A ROS bridge: commands from ROS topics in, the machines' state out (README: Connect your ROS stack)."""

    kind: _choice("ros1", "ros_tcp") = Field(description="`ros1`: a rospy node on the master of ROS_MASTER_URI; "
                                                         "`ros_tcp`: a client of Unity's ROS-TCP-Endpoint (ROS 1 or 2). "
                                                         "`run --ros1` / `--ros-tcp HOST:PORT` override it (and "
                                                         "`--pace`, `--bridge-after-motion` the keys below).")
    address: Optional[Annotated[str, BeforeValidator(_NameRule(r"[^\s]{1,200}", "no spaces"))]] = Field(
        None, description="ros_tcp: the endpoint's HOST:PORT (null = 127.0.0.1:10000); ros1: the master URI "
                          "(null = ROS_MASTER_URI).")
    namespace: Optional[Annotated[str, BeforeValidator(_NameRule(_ROS_NAME, "letters, digits, _ and / (ROS)"))]] \
        = Field(None, description="Topic namespace of the machine; null = the machine's name (zx120).")
    rates: Annotated[dict[str, Rate], _none_to({})] = Field(
        default_factory=dict, description="Output topic key (joint_states, odom, base_link/pose, bucket/wrench, "
                                          "soil_mass, soil_volume, tf, clock, terrain) -> rate in Hz of simulated time.")
    topics: Annotated[dict[str, str], _none_to({})] = Field(
        default_factory=dict, description="Topic key (its default name relative to the namespace, e.g. boom/cmd, "
                                          "joint_states; or tf, clock, terrain) -> name; relative names are in the "
                                          "namespace.")
    pace: _choice("realtime", "fast") = Field(
        "realtime", description="`realtime`: simulated time kept to the wall clock; `fast`: as fast as it goes "
                                "(/clock published for use_sim_time stacks).")
    after_motion: Bool = Field(False, description="Run the scene's motion first, then take commands from ROS "
                                                  "(otherwise the motion is set aside).")
    command_timeout: Optional[_num("s", gt=0, le=60)] = Field(
        0.5, description="A speed command (tracks/cmd_vel, a JointCmd velocity target) lasts this long in simulated "
                         "time: with no new one by then the tracks stop and the joint's target speed becomes 0, so a "
                         "controller that dies does not leave the machine driving (ros_control's cmd_vel_timeout); "
                         "position targets do not expire; null = never.")


class Scene(_Model):
    """A whole scene file."""

    name: Optional[Annotated[str, BeforeValidator(_NameRule(r"[A-Za-z0-9_.-]{1,80}",
                                                            "letters, digits, _ . - (at most 80)"))]] = Field(
        None, description="Scene name (run folder prefix); null = the scene file's stem.")
    sim: Annotated[SimConfig, _none_to({})] = Field(default_factory=SimConfig, description="Time stepping.")
    soil: Optional[SoilConfig] = Field(None, description="Soil; null = no soil.")
    machine: Optional[MachineConfig] = Field(None, description="Machine; null = no machine.")
    machines: Annotated[list[MachineEntry], _none_to([])] = Field(
        default_factory=list, description="Several machines in one world (instead of `machine` + `motion`), each "
                                          "with its name and motion; they touch each other and the same soil.")
    tools: Annotated[list[ToolConfig], _none_to([])] = Field(default_factory=list,
                                                            description="Standalone rigid tools.")
    motion: Optional[Motion] = Field(None, description="Machine motion, chosen by `type`; null = hold still.")
    bridge: Optional[BridgeConfig] = Field(None, description="ROS bridge (commands in, state out); null = none.")
    output: Annotated[OutputConfig, _none_to({})] = Field(default_factory=OutputConfig,
                                                         description="Run folder contents.")
    source: Optional[Path] = Field(None, exclude=True, description="The scene file (set by load_scene).")

    @model_validator(mode="after")
    def _whole_scene(self, info: ValidationInfo):
        if self.name is None:
            source = (info.context or {}).get("source") or self.source
            self.name = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(source).stem)[:80] if source else "scene"
        seen: dict[str, int] = {}
        for i, tool in enumerate(self.tools):
            if tool.name in seen:
                raise _fail(f"a unique tool name (tools.{seen[tool.name]} is already {tool.name!r})", tool.name,
                            key=f"tools.{i}.name")
            seen[tool.name] = i
        if self.machine is not None and self.machines:
            raise _fail(message="give either machine (one) or machines (a list), not both", key="machines")
        if self.motion is not None and self.machine is None:
            raise _fail(message="a motion needs a machine: add a machine section (or remove motion; with "
                                "machines, each has its own motion)", key="motion")
        for key in ("joints_rate", "wrench_rate", "mass_rate", "replay_rate"):
            if getattr(self.output, key) > 1.0 / self.sim.dt * (1 + 1e-9):
                raise _fail(f"a rate in Hz > 0 and <= 1/sim.dt ({_fmt(1.0 / self.sim.dt)})",
                            getattr(self.output, key), key=f"output.{key}")
        return self


# ----------------------------------------------------------------------------- schema walking
def _strip(annotation):
    """Drops Annotated[...] and Optional[...] wrappers."""
    while True:
        if get_origin(annotation) is Annotated:
            annotation = get_args(annotation)[0]
            continue
        if get_origin(annotation) is Union:
            members = [a for a in get_args(annotation) if a is not type(None)]
            if len(members) == 1:
                annotation = members[0]
                continue
        return annotation


def _is_model(annotation) -> bool:
    return inspect.isclass(annotation) and issubclass(annotation, BaseModel)


def _union_members(annotation) -> dict[str, type[BaseModel]]:
    """Tag -> model for a union discriminated by `type` (motion); {} otherwise."""
    core = _strip(annotation)
    if get_origin(core) is not Union:
        return {}
    return {get_args(m.model_fields["type"].annotation)[0]: m for m in get_args(core) if _is_model(m)}


def _user_keys(model: type[BaseModel]) -> list[str]:
    return [k for k in model.model_fields if k != "source"]


def _child(annotation, item):
    """The annotation one step down (a model field, a dict value, a list entry), or None."""
    core = _strip(annotation)
    if _is_model(core):
        field = core.model_fields.get(item) if isinstance(item, str) else None
        return field.annotation if field is not None else None
    origin = get_origin(core)
    if origin is dict:
        return get_args(core)[1]
    if origin is list:
        return get_args(core)[0]
    if origin is tuple and isinstance(item, int) and item < len(get_args(core)):
        return get_args(core)[item]
    return None


def _is_mapping(annotation) -> bool:
    core = _strip(annotation)
    return _is_model(core) or get_origin(core) is dict or bool(_union_members(annotation))


def _walk_loc(loc) -> tuple[list[str], Any]:
    """Pydantic's error location -> the user's dotted key parts and the annotation there."""
    parts, annotation = [], Scene
    for item in loc:
        members = _union_members(annotation)
        if members and item in members:  # pydantic inserts the union tag; the user never wrote it
            annotation = members[item]
            continue
        if item == "[key]":
            continue
        parts.append(str(item))
        annotation = _child(annotation, item)
    return parts, annotation


def _allowed_keys(annotation, data=None) -> list[str] | None:
    """Keys a mapping may have there; None = any key (a dict such as joint name -> angle)."""
    members = _union_members(annotation)
    if members:
        chosen = members.get(data.get("type")) if isinstance(data, dict) and isinstance(
            data.get("type"), str) else None
        if chosen is not None:
            return _user_keys(chosen)
        return sorted({k for m in members.values() for k in _user_keys(m)})
    core = _strip(annotation)
    return _user_keys(core) if _is_model(core) else None


def _member_for(annotation, data, key):
    """The union member to walk into for --set: the one named by data's `type`, else any with `key`."""
    members = _union_members(annotation)
    if isinstance(data, dict) and data.get("type") in members:
        return members[data["type"]]
    return next((m for m in members.values() if key in m.model_fields), annotation)


# ----------------------------------------------------------------------------- errors
_PLAIN = {
    "string_type": "a string", "bool_type": "true or false", "int_type": "an integer",
    "float_type": "a number", "list_type": "a list", "tuple_type": "a list", "dict_type": "a mapping",
    "invalid_key": "a string key", "path_type": "a path",
}


def _message_for(error: dict) -> tuple[list[str], str]:
    parts, annotation = _walk_loc(error["loc"])
    kind, ctx, value = error["type"], error.get("ctx") or {}, error.get("input")
    if kind == "scene_value":
        if ctx.get("key"):
            parts += ctx["key"].split(".")
        if ctx.get("message"):
            return parts, ctx["message"]
        return parts, f"expected {ctx['expected']}, got {ctx['got']}{ctx['hint']}"
    if kind == "missing":
        parent = _strip(_walk_loc(error["loc"][:-1])[1])
        field = parent.model_fields.get(parts[-1]) if _is_model(parent) and parts else None
        rule = next((m.func for m in getattr(field, "metadata", ()) if isinstance(getattr(m, "func", None), _ChoiceRule)),
                    None)
        what = f" ({' | '.join(rule.choices)})" if rule is not None else ""
        if parts == ["bridge", "kind"]:  # (a bridge key set alone, e.g. --set bridge.command_timeout=1)
            what += "; or run with --ros1 or --ros-tcp HOST:PORT"
        return parts, f"required key is missing{what}"
    if kind == "extra_forbidden":
        parent_parts, parent = _walk_loc(error["loc"][:-1])
        allowed = _allowed_keys(parent) or []
        hint = did_you_mean(parts[-1], allowed)
        return parts, f"unknown key{hint}; allowed: {', '.join(allowed)}"
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        allowed = _allowed_keys(annotation)
        what = f"a mapping with keys {', '.join(allowed)}" if allowed else "a mapping"
        return parts, f"expected {what}, got {_show(value)}"
    if kind in ("union_tag_invalid", "union_tag_not_found"):
        tags = ", ".join(_union_members(annotation))
        if kind == "union_tag_not_found":
            return parts + ["type"], f"required key is missing (one of {tags})"
        tag = ctx.get("tag")
        hint = did_you_mean(tag, _union_members(annotation))
        return parts + ["type"], f"expected one of {tags}, got {_show(tag)}{hint}"
    if kind in ("too_short", "too_long"):
        bound = ctx.get("min_length") if kind == "too_short" else ctx.get("max_length")
        more = "at least" if kind == "too_short" else "at most"
        return parts, f"expected {more} {bound} entr{'y' if bound == 1 else 'ies'}, got {_show(value)}"
    if kind == "literal_error":
        return parts, f"expected {ctx.get('expected')}, got {_show(value)}"
    if kind in _PLAIN:
        return parts, f"expected {_PLAIN[kind]}, got {_show(value)}"
    return parts, f"{error['msg']}, got {_show(value)}"


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _from_set(parts: list[str], overridden: list[str]) -> str:
    dotted = ".".join(parts)
    return " (from --set)" if any(dotted == o or dotted.startswith(o + ".") or o.startswith(dotted + ".")
                                  for o in overridden) else ""


def _validation_error(label: str, exc: ValidationError, overridden: list[str]) -> UserError:
    parts, text = _message_for(exc.errors(include_url=False)[0])
    where = ".".join(parts) or "(top level)"
    return UserError(_one_line(f"{label}: {where}{_from_set(parts, overridden)}: {text}"))


# ----------------------------------------------------------------------------- YAML reading
class _YamlProblem(Exception):
    def __init__(self, parts: list[str], text: str):
        super().__init__(text)
        self.parts, self.text = parts, text


class _SceneLoader(yaml.SafeLoader):
    """PyYAML's safe loader that stops composing past MAX_YAML_VALUES nodes or MAX_YAML_DEPTH levels;
    the composed graph is then checked for alias expansion and duplicate keys before objects are built."""

    def __init__(self, stream):
        super().__init__(stream)
        self._nodes = self._depth = 0

    def compose_node(self, parent, index):
        self._nodes += 1
        if self._nodes > MAX_YAML_VALUES:
            raise _YamlProblem([], f"more than {MAX_YAML_VALUES} values; not a scene file")
        if self._depth >= MAX_YAML_DEPTH:
            line = self.peek_event().start_mark.line + 1
            raise _YamlProblem([], f"nested more than {MAX_YAML_DEPTH} levels deep (line {line})")
        self._depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


# PyYAML follows YAML 1.1, where an unquoted `1e-4` is a string, `on`/`yes`/`no` are booleans, `010` is octal (8)
# and `1:30` is base 60 (90), `2024-05-01` a date and `=` a "value". Scenes read booleans, integers and floats as YAML
# 1.2's core schema does (what the docs promise: true | false), with no timestamps or values, so those forms are
# strings that the schema then takes (a name) or refuses.
_YAML12_SCALARS = (  # (tag, pattern, first characters); int before float: the float pattern matches `10` too
    ("tag:yaml.org,2002:bool", r"true|True|TRUE|false|False|FALSE", "tTfF"),
    ("tag:yaml.org,2002:int", r"[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+", "-+0123456789"),
    ("tag:yaml.org,2002:float", r"[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)"
                                r"|\.(?:nan|NaN|NAN)", "-+.0123456789"),
)
_SceneLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers
            if tag not in {t for t, _, _ in _YAML12_SCALARS} | {"tag:yaml.org,2002:timestamp", "tag:yaml.org,2002:value"}]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
for _tag, _pattern, _first in _YAML12_SCALARS:
    _SceneLoader.add_implicit_resolver(_tag, re.compile(f"^(?:{_pattern})$"), list(_first))


def _construct_int(loader, node) -> int:
    """YAML 1.2 integers: decimal (`010` is ten, not octal eight), 0o octal, 0x hex."""
    text = loader.construct_scalar(node)
    if text[:2] in ("0o", "0x"):
        return int(text[2:], 8 if text[1] == "o" else 16)
    return int(text, 10)


_SceneLoader.add_constructor("tag:yaml.org,2002:int", _construct_int)


def _check_nodes(root: yaml.Node) -> None:
    """Counts values as if every alias were expanded, and finds duplicate keys, without building objects."""
    sizes: dict[int, int] = {}
    active: set[int] = set()

    def visit(node: yaml.Node, parts: list[str], depth: int) -> int:
        ident = id(node)
        if ident in sizes:
            return sizes[ident]
        if ident in active:
            raise _YamlProblem(parts, "a YAML alias refers to its own anchor (a recursive structure)")
        if depth > MAX_YAML_DEPTH:
            raise _YamlProblem(parts, f"nested more than {MAX_YAML_DEPTH} levels deep (through aliases)")
        active.add(ident)
        size = 1
        if isinstance(node, yaml.MappingNode):
            seen: dict[str, int] = {}
            for key_node, value_node in node.value:
                key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
                if key is not None and key_node.tag != "tag:yaml.org,2002:merge":
                    if key in seen:
                        raise _YamlProblem(parts + [key], f"duplicate key (lines {seen[key]} and "
                                                          f"{key_node.start_mark.line + 1})")
                    seen[key] = key_node.start_mark.line + 1
                size += visit(key_node, parts, depth + 1)
                size += visit(value_node, parts + ([key] if key is not None else []), depth + 1)
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                size += visit(item, parts + [str(i)], depth + 1)
        active.discard(ident)
        sizes[ident] = size
        if size > MAX_YAML_VALUES:  # the composer capped plain nodes, so aliases did this
            raise _YamlProblem([], f"YAML aliases expand to more than {MAX_YAML_VALUES} values (an alias "
                                   "bomb?); write the values out")
        return size

    visit(root, [], 0)


def _fresh_copy(value):
    """Unshares containers that YAML aliases made the same object, so --set changes one place only."""
    if isinstance(value, dict):
        return {k: _fresh_copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_fresh_copy(v) for v in value]
    return value


def _parse_yaml(text: str, label: str):
    """Parses one YAML document safely. Raises UserError naming `label` and the line."""
    loader = _SceneLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_nodes(node)
        return _fresh_copy(loader.construct_document(node))
    except _YamlProblem as exc:
        where = f"{'.'.join(exc.parts)}: " if exc.parts else ""
        raise UserError(_one_line(f"{label}: {where}{exc.text}")) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        what = "unsupported YAML" if isinstance(exc, yaml.constructor.ConstructorError) else "YAML syntax error"
        raise UserError(_one_line(f"{label}: {what}{at}: {exc.problem or exc.context}")) from None
    except yaml.YAMLError as exc:
        raise UserError(_one_line(f"{label}: YAML error: {exc}")) from None
    except RecursionError:
        raise UserError(f"{label}: YAML nested too deeply") from None
    except (ValueError, OverflowError) as exc:  # e.g. an integer with more than 4300 digits
        raise UserError(_one_line(f"{label}: cannot read a value ({exc})")) from None
    finally:
        loader.dispose()


def _read_scene_text(path: Path, label: str) -> str:
    if not path.exists():
        raise UserError(f"{label}: file not found")
    if path.is_dir():
        raise UserError(f"{label}: is a directory, expected a scene YAML file")
    if not path.is_file():
        raise UserError(f"{label}: not a regular file, expected a scene YAML file")
    size = path.stat().st_size
    if size > MAX_SCENE_BYTES:
        raise UserError(f"{label}: file is {size / 2**20:.1f} MB, larger than the "
                        f"{MAX_SCENE_BYTES // 2**20} MB limit for a scene file")
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_SCENE_BYTES + 1)
    except OSError as exc:
        raise UserError(_one_line(f"{label}: cannot read ({exc.strerror})")) from None
    if len(data) > MAX_SCENE_BYTES:
        raise UserError(f"{label}: larger than the {MAX_SCENE_BYTES // 2**20} MB limit for a scene file")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise UserError(f"{label}: not UTF-8 text (byte 0x{data[exc.start]:02x} at offset {exc.start})") from None


# ----------------------------------------------------------------------------- --set overrides
def _plain(value):
    """A Python API override as the data YAML would give: numpy scalars and arrays as numbers and lists, paths as
    strings (a float('nan') stays a float, so it is refused as the number it is)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, PurePath):
        return str(value)
    if type(value).__module__ == "numpy" and hasattr(value, "tolist"):
        return _plain(value.tolist())
    return value


def _apply_override(data: dict, text: str, label: str, value: Any = ...) -> str:
    """Applies one `key.path=value` (or `key.path=` with the value already read, from the Python API); returns the
    dotted key."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise UserError(_one_line(f"{label}: --set {text}: expected key.path=value"))
    parts = key.split(".")
    if any(not p for p in parts):
        raise UserError(_one_line(f"{label}: --set {key}: empty key component"))
    value = _fresh_copy(_parse_yaml(raw, f"{label}: --set {key}") if value is ... else _plain(value))
    node, annotation = data, Scene
    for i, part in enumerate(parts):
        here = ".".join(parts[:i + 1])
        last = i == len(parts) - 1
        if isinstance(node, list):
            if not part.isdigit():
                raise UserError(_one_line(f"{label}: --set {here}: {'.'.join(parts[:i])} is a list; expected "
                                          f"an index 0..{len(node) - 1}, got {part!r}"))
            index = int(part)
            if index >= len(node):
                raise UserError(_one_line(f"{label}: --set {here}: index out of range; "
                                          f"{'.'.join(parts[:i])} has {len(node)} entries"))
            child = _child(annotation, index)
            if last:
                node[index] = value
                break
            nxt = node[index]
        elif isinstance(node, dict):
            allowed = _allowed_keys(annotation, node)
            if allowed is not None and part not in allowed:
                raise UserError(_one_line(f"{label}: --set {here}: unknown key{did_you_mean(part, allowed)}; "
                                          f"allowed: {', '.join(allowed)}"))
            child = _child(_member_for(annotation, node, part), part)
            if last:
                node[part] = value
                break
            nxt = node.get(part)
            if nxt is None:
                nxt = _default_as_data(_member_for(annotation, node, part), part)
                if nxt is None and not _is_mapping(child):
                    raise UserError(_one_line(f"{label}: --set {key}: {here} is not a mapping or list, so it "
                                              f"has no entry {parts[i + 1]!r}"))
                nxt = node[part] = {} if nxt is None else nxt
        else:
            raise UserError(_one_line(f"{label}: --set {here}: {'.'.join(parts[:i])} is {_show(node)}, "
                                      "not a mapping or list"))
        node, annotation = nxt, child
    return key


def _is_all_defaults(value) -> bool:
    """True for a model equal to the one built from an empty mapping."""
    if not isinstance(value, BaseModel):
        return False
    try:
        return type(value)() == value
    except ValidationError:
        return False


def _default_as_data(annotation, key: str):
    """A field's default written out as YAML-like data (so --set can index the default bed), or None."""
    core = _strip(annotation)
    field = core.model_fields.get(key) if _is_model(core) else None
    if field is None or field.is_required():
        return None
    value = field.get_default(call_default_factory=True, validated_data={})
    if value is None or isinstance(value, (str, int, float, Path)) or _is_all_defaults(value):
        return None  # an empty mapping means the same and keeps `_deg` twins free to be set
    dumped = json.loads(json.dumps(value, default=lambda v: v.model_dump(mode="json")))
    return dumped if isinstance(dumped, (dict, list)) else None


# ----------------------------------------------------------------------------- public API
def load_scene(path: str | Path, overrides: list[str] | tuple[str, ...] | dict = ()) -> Scene:
    """Reads a scene YAML safely, applies `--set key.path=value` overrides (or a mapping {key.path: value}, as
    Simulation.from_scene takes), validates, resolves paths.

    Every problem a user can cause raises errors.UserError with one line naming the file and the key.
    """
    # a mapping's values are used as given (not written out and read back: a Path or a numpy number is no JSON, and
    # JSON's NaN would read back as a string)
    items = [(f"{k}=", v) for k, v in overrides.items()] if isinstance(overrides, dict) else \
        [(text, ...) for text in overrides]
    label = str(path)
    path = Path(path)
    text = _read_scene_text(path, label)
    data = _parse_yaml(text, label)
    if data is None:
        raise UserError(f"{label}: empty file, expected a mapping of scene keys ({', '.join(_user_keys(Scene))})")
    if not isinstance(data, dict):
        raise UserError(_one_line(f"{label}: expected a mapping of scene keys ({', '.join(_user_keys(Scene))}), "
                                  f"got {_show(data)}"))
    overridden = [_apply_override(data, text, label, value) for text, value in items]
    if "source" in data:
        raise UserError(f"{label}: source: unknown key; allowed: {', '.join(_user_keys(Scene))}")
    source = path.resolve()
    try:
        scene = Scene.model_validate(data, context={"base_dir": source.parent, "source": source})
    except ValidationError as exc:
        raise _validation_error(label, exc, overridden) from None
    scene.source = source
    return scene


def scene_to_dict(scene: Scene) -> dict:
    """The resolved scene (radians, absolute paths, defaults filled) as JSON-safe data for manifest.json."""
    return scene.model_dump(mode="json")


def resolve_out_dir(scene: Scene, out: str | Path | None = None, now: datetime | None = None) -> Path:
    """The run folder: `--out`, else output.dir, else runs/<name>-<YYYYmmdd-HHMMSS> (current directory)."""
    if out is not None:
        return Path(out)
    if scene.output.dir is not None:
        return Path(scene.output.dir)
    stamp = (now or datetime.now()).strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{scene.name}-{stamp}"


# ----------------------------------------------------------------------------- reference doc
def _rule_doc(metadata) -> str | None:
    for item in metadata:
        func = getattr(item, "func", None)
        if hasattr(func, "doc"):
            return func.doc
    return None


def _type_doc(annotation, models: list) -> str:
    optional = get_origin(annotation) is Union and type(None) in get_args(annotation)
    core = annotation
    while get_origin(core) is Union and type(None) in get_args(core):
        core = next(a for a in get_args(core) if a is not type(None))
    text = None
    if get_origin(core) is Annotated:
        text = _rule_doc(core.__metadata__)
        if text is None:
            core_inner = get_args(core)[0]
            if _union_members(core):
                members = _union_members(core)
                models.extend(members.values())
                text = "mapping chosen by `type`: " + ", ".join(f"`{t}`" for t in members)
            else:
                text = _type_doc(core_inner, models)
    elif _is_model(core):
        models.append(core)
        text = f"mapping ({core.__name__})"
    elif get_origin(core) is list:
        text = f"list of {_type_doc(get_args(core)[0], models)}"
    elif get_origin(core) is dict:
        text = f"mapping: name -> {_type_doc(get_args(core)[1], models)}"
    elif get_origin(core) is Literal:
        text = " \\| ".join(f"`{a}`" for a in get_args(core))
    else:
        text = getattr(core, "__name__", str(core))
    return text + (" or null" if optional else "")


def _default_doc(field) -> str:
    if field.is_required():
        return "required"
    value = field.get_default(call_default_factory=True)
    if isinstance(value, BaseModel):
        if _is_all_defaults(value):
            return "(its table's defaults)"
        value = value.model_dump(mode="json")
    if isinstance(value, list) and value and isinstance(value[0], BaseModel):
        value = [v.model_dump(mode="json") for v in value]
    if isinstance(value, tuple):
        value = list(value)
    if value is None:
        return "`null`"
    return "`" + json.dumps(value, default=str).replace('"', "") + "`"


_REFERENCE_INTRO = """# Scene file reference

Generated from `opera_taichi/scene.py` by `python -m opera_taichi.scene > docs/scene_reference.md`;
a test fails when this page is out of date.

- SI units and radians; a key ending `_deg` takes degrees instead and is stored in radians
  (give one of the pair, not both).
- Numbers must be finite numbers: not strings, not booleans, not `.nan`/`.inf`. Unknown keys are errors.
- Relative paths of input files (`machine.urdf`, `machine.config`, `tools[].mesh`, `motion.file`)
  are relative to the scene file's directory; `output.dir` and `--out` are relative to the current directory.
- `--set key.path=value` overrides any key before validation: the value is read as YAML
  (`--set sim.duration=5`, `--set soil.bed.0.max.2=-0.5`, `--set machine.base_pose.xyz=[1,0,0]`);
  integer components index lists; a missing mapping on the path is created when the schema allows it.
- Refused files: larger than 5 MB, not UTF-8, duplicate keys, more than 20000 values (aliases
  counted as expanded), nesting deeper than 50 levels.
- Every error is one line, `<file>: <key>: <what is allowed>, got <value>`, exit status 2.
"""


def scene_reference_markdown() -> str:
    """The scene reference page, built from the models' fields, defaults and descriptions."""
    sections: dict[type[BaseModel], list[str]] = {Scene: []}  # model -> where it is used, in order found
    rows: dict[type[BaseModel], list[str]] = {}
    queue = [Scene]
    while queue:
        model = queue.pop(0)
        rows[model] = []
        for key, field in model.model_fields.items():
            if key == "source":
                continue
            found: list[type[BaseModel]] = []
            annotation = Annotated[(field.annotation, *field.metadata)] if field.metadata else field.annotation
            rows[model].append(f"| `{key}` | {_type_doc(annotation, found)} | {_default_doc(field)} | "
                               f"{field.description or ''} |")
            container = get_origin(_strip(field.annotation))
            suffix = "[]" if container is list else ".<name>" if container is dict else ""
            for where in sections[model] or [""]:
                for sub in found:
                    at = f"{where}.{key}{suffix}".lstrip(".")
                    if "type" in sub.model_fields and model is Scene:
                        at += f" (type: {get_args(sub.model_fields['type'].annotation)[0]})"
                    elif "type" in model.model_fields:  # inside a motion kind: drop the "(type: ...)"
                        at = at.replace(where, where.split(" ")[0], 1)
                    if sub not in sections:
                        sections[sub] = []
                        queue.append(sub)
                    if at not in sections[sub]:
                        sections[sub].append(at)
    lines = [_REFERENCE_INTRO]
    for model, places in sections.items():
        title = ", ".join(f"`{p}`" for p in places) or "top level"
        lines += [f"## {title} ({model.__name__})", "", (model.__doc__ or "").strip(), "",
                  "| key | type | default | description |", "|---|---|---|---|", *rows[model], ""]
    return "\n".join(lines)


@contextlib.contextmanager
def naming_the_scene(path):
    """A scene key found wrong after loading (building the model, the machine, the soil) is reported with the
    scene file, as load_scene reports its own errors."""
    try:
        yield
    except UserError as exc:
        section = str(exc).split(":", 1)[0].split(".", 1)[0]
        if section in Scene.model_fields:
            raise UserError(f"{path}: {exc}") from None
        raise


if __name__ == "__main__":
    print(scene_reference_markdown(), end="")
