"""Load a machine: its URDF (ours or OPERA's, unchanged) plus machine.yaml (actuators, masses, tracks).

The result names what the rest of the simulator needs and points at a cleaned copy of the URDF that
PyBullet can load as is: absolute mesh paths (package:// and relative URIs resolved, COLLADA converted to
OBJ), real masses in place of placeholders, unit joint axes, actuator limits in <limit>.
"""
from __future__ import annotations

import hashlib
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
import yourdfpy
from lxml import etree

from . import paths
from .errors import UserError, did_you_mean

DEFAULT_GAIN = 5.0          # 1/s, position-error-to-speed gain when a machine config gives none
PLACEHOLDER_MASS = 1.0      # kg: a link with geometry lighter than this is a stand-in, not a machine part
MOVABLE = ("revolute", "continuous", "prismatic")
PYBULLET_MESH_SUFFIXES = (".obj", ".stl")
CONFIG_KEYS = ("name", "urdf", "actuated_joints", "tip_link", "soil_links", "joints", "masses", "tracks",
               "struck_volume", "command_latency", "cutting_edges")
ACTUATOR_KEYS = ("max_speed", "max_torque", "gain")
TRACK_KEYS = ("wheel_radius", "wheel_mass", "x", "gauge", "friction", "max_wheel_torque")
# optional: lateral_friction (below); max_speed, the travel speed (m/s) the tracks' motors reach, null = not capped
TRACK_OPTIONAL_KEYS = ("lateral_friction", "max_speed")
# optional: the ground's resistance to sideways slip of a track (opera_taichi/tracks.py); below the tractive friction,
# or the machine cannot turn on the spot
LATERAL_FRICTION_SHARE = 0.6   # default lateral_friction / friction


@dataclass
class Actuator:
    max_speed: float     # rad/s (m/s for prismatic)
    max_torque: float    # N m (N for prismatic)
    gain: float          # 1/s: speed command per unit position error


@dataclass
class MachineDescription:
    name: str
    urdf_path: Path                  # the URDF the user named
    bullet_urdf_path: Path           # cleaned copy in paths.cache_dir() for PyBullet and kinematics
    actuated_joints: list[str]
    actuators: dict[str, Actuator]
    joint_limits: dict[str, tuple[float, float]]   # (lower, upper) rad; continuous -> (-inf, inf)
    tip_link: str
    soil_links: list[str]
    collision_meshes: dict[str, trimesh.Trimesh]    # per soil link, in the link frame
    tracks: dict | None
    warnings: list[str] = field(default_factory=list)
    struck_volume: dict[str, float] = field(default_factory=dict)   # m3 per soil link (a bucket's rated capacity)
    command_latency: float = 0.0    # s, dead time before the machine acts on a command from a ROS bridge
    movable_joints: list[str] = field(default_factory=list)   # every revolute/continuous/prismatic joint, URDF order
    # per soil link, its cutting edge (scene.CuttingEdgeConfig, link frame): the soil wedge of AGX's shovels
    cutting_edges: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------------------- entry point
def load_machine(urdf: str | Path, config: str | Path | None = None,
                 actuator_overrides: dict[str, dict] | None = None) -> MachineDescription:
    """Load a machine from a built-in name ("zx120"), a URDF path, or a machine.yaml path (which names
    its URDF). `config` is a machine.yaml path or built-in name; None looks beside the URDF, then for a
    built-in machine of the same robot name, then falls back to the URDF's own limits (with a warning).
    `actuator_overrides` = {joint: {max_speed/max_torque/gain: value}} replaces single values."""
    warnings: list[str] = []
    urdf_path, robot, config_path, cfg, where, actuators = _read_actuators(urdf, config, actuator_overrides,
                                                                           warnings)
    links = {link.name: link for link in robot.links}
    joints = {joint.name: joint for joint in robot.joints}
    children = _children(robot)
    root = _root_link(robot, urdf_path)
    tip_link, soil_links = _tip_and_soil_links(cfg, where, links, children, root, warnings,
                                               from_config=bool(config_path))
    _check_tip_is_moved(tip_link, "tip_link" in cfg, where, joints, list(actuators), urdf_path)
    tracks = _tracks(cfg, where)
    if tracks is not None and tracks["lateral_friction"] >= tracks["friction"]:
        warnings.append(f"{where}: tracks.lateral_friction {tracks['lateral_friction']:g} >= tracks.friction "
                        f"{tracks['friction']:g}: a machine on these tracks can hardly turn on the spot (the ground's "
                        f"grip across a track is usually 0.6-0.8 of its grip along it)")
    if tracks is not None and tracks["max_speed"] is None:
        warnings.append(f"{where}: no tracks.max_speed (the machine's travel speed, m/s): track speeds are not capped")
    masses = _masses(cfg, where, links)

    meshes = _MeshCache(urdf_path)
    for link in robot.links:
        for element in [*link.visuals, *link.collisions]:
            meshes.resolve_element(element, link.name)
            if isinstance(element, yourdfpy.Visual) and element.material is not None:
                element.material.texture = None      # PyBullet does not need (or find) textures
    for joint in robot.joints:
        _normalise_axis(joint, urdf_path)
        if joint.name in actuators:
            _write_actuator_limit(joint, actuators[joint.name])

    _fix_masses(robot, masses, meshes, urdf_path, config_path, warnings)
    _warn_misaligned_soil_geometry(links, soil_links, urdf_path, warnings)
    for link in robot.links:
        if link.inertial is None:
            # what PyBullet assumes anyway for a link without <inertial>, written out to silence its warning
            link.inertial = yourdfpy.Inertial(origin=np.eye(4), mass=1.0, inertia=np.eye(3))

    collision_meshes = {name: meshes.link_mesh(links[name], collision=True) for name in soil_links}
    bullet_path = _write_cached_urdf(robot)
    limits = {name: _limits(joint) for name, joint in joints.items() if joint.type in MOVABLE}
    return MachineDescription(
        name=str(cfg.get("name") or robot.name), urdf_path=urdf_path, bullet_urdf_path=bullet_path,
        actuated_joints=list(actuators), actuators=actuators, joint_limits=limits, tip_link=tip_link,
        soil_links=soil_links, collision_meshes=collision_meshes, tracks=tracks, warnings=warnings,
        struck_volume=_struck_volume(cfg, where, soil_links),
        cutting_edges=_cutting_edges(cfg, where, soil_links),
        command_latency=_latency(cfg.get("command_latency", 0.0), f"{where}: command_latency"),
        movable_joints=_movable(joints))


@dataclass
class JointSpec:
    """A movable joint as a check of a recorded angle needs it."""
    type: str                  # revolute, continuous, prismatic
    lower: float               # rad (m); -inf for a continuous joint
    upper: float               # rad (m); inf for a continuous joint
    max_speed: float | None    # rad/s (m/s): the actuator's limit; None for a joint that is not actuated

    @property
    def turns(self) -> bool:
        """Can turn past a full turn (a swing): continuous, or limits wider than one turn; its angle, unwrapped, has
        no bound to check."""
        return self.type != "prismatic" and not self.upper - self.lower <= 2 * math.pi + 1e-9


def joint_specs(urdf: str | Path, config: str | Path | None = None,
                actuator_overrides: dict[str, dict] | None = None) -> dict[str, JointSpec]:
    """{joint: JointSpec} of the machine's movable joints, read as load_machine reads them (same files, same
    errors), without its meshes or the cleaned URDF: cheap enough for a study that only reads a run's angles."""
    _, robot, _, _, _, actuators = _read_actuators(urdf, config, actuator_overrides, [])
    return {joint.name: JointSpec(joint.type, *_limits(joint),
                                  actuators[joint.name].max_speed if joint.name in actuators else None)
            for joint in robot.joints if joint.type in MOVABLE}


def description_source(machine: dict) -> tuple[str | Path, str | Path | None, dict[str, dict]]:
    """(urdf, config, actuator_overrides) for load_machine or joint_specs, of a scene's machine entry as plain data
    (MachineConfig.model_dump(), or a run manifest's resolved scene). An entry without a URDF (a hand-made manifest)
    means the scene's default machine; an actuator setting left null keeps the machine config's."""
    from .scene import MachineConfig

    urdf = machine.get("urdf") or MachineConfig.model_fields["urdf"].default
    overrides = {joint: {k: v for k, v in settings.items() if v is not None}
                 for joint, settings in (machine.get("actuators") or {}).items()}
    return urdf, machine.get("config"), overrides


def _read_actuators(urdf, config, actuator_overrides, warnings: list[str]):
    """(urdf_path, robot, config_path, cfg, where, actuators): the URDF and machine.yaml resolved and read, and the
    actuated joints' limits with the overrides applied (what load_machine and joint_specs both start from)."""
    urdf_path, config = _resolve_urdf(urdf, config)
    robot = _parse_urdf(urdf_path)
    config_path = _resolve_config(config, urdf_path, robot.name, warnings)
    cfg = _read_config(config_path) if config_path else {}
    where = str(config_path) if config_path else "machine config"
    links = {link.name: link for link in robot.links}
    joints = {joint.name: joint for joint in robot.joints}
    actuated = _actuated_joints(cfg, where, joints, _children(robot), links, urdf_path)
    actuators = _actuators(cfg, where, actuated, joints, urdf_path, warnings)
    _apply_overrides(actuators, actuator_overrides)
    return urdf_path, robot, config_path, cfg, where, actuators


def _latency(value, where: str) -> float:
    """Seconds, 0 to the bound a scene's machine.command_latency has."""
    from .scene import MAX_COMMAND_LATENCY

    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0 \
            or value > MAX_COMMAND_LATENCY:
        raise UserError(f"{where} must be a number of seconds >= 0 and <= {MAX_COMMAND_LATENCY:g}, got {value!r}")
    return float(value)


def _struck_volume(cfg, where, soil_links) -> dict[str, float]:
    value = cfg.get("struck_volume") or {}
    if not isinstance(value, dict):
        raise UserError(f"{where}: struck_volume must map soil links to volumes in m3")
    out = {}
    for link, vol in value.items():
        if link not in soil_links:
            raise UserError(f"{where}: struck_volume: {link!r} is not a soil link (soil_links: {', '.join(soil_links)})")
        out[link] = _positive(vol, f"{where}: struck_volume.{link}")
    return out


def _cutting_edges(cfg, where, soil_links) -> dict:
    """cutting_edges: {soil link: {centre, face_normal, face_up, width}} in the link's frame, checked as a scene's
    tools[].cutting_edge is (the soil checks that each edge lies on its link's mesh)."""
    import pydantic

    from .scene import CuttingEdgeConfig

    value = cfg.get("cutting_edges") or {}
    if not isinstance(value, dict):
        raise UserError(f"{where}: cutting_edges must map soil links to {{centre, face_normal, face_up, width}}")
    out = {}
    for link, edge in value.items():
        if link not in soil_links:
            raise UserError(f"{where}: cutting_edges: {link!r} is not a soil link (soil_links: {', '.join(soil_links)})")
        try:
            out[link] = CuttingEdgeConfig.model_validate(edge)
        except pydantic.ValidationError as exc:
            err = exc.errors()[0]
            ctx = err.get("ctx") or {}
            key = ".".join(str(k) for k in (*err.get("loc", ()), ctx.get("key")) if k)
            text = ctx.get("message") or (f"expected {ctx['expected']}, got {ctx.get('got', '')}"
                                          if ctx.get("expected") else err.get("msg"))
            raise UserError(f"{where}: cutting_edges.{link}{'.' + key if key else ''}: {text}") from None
    return out


# ----------------------------------------------------------------------------------------- files
def _builtin_machines() -> list[str]:
    root = paths.machines_dir()
    return sorted(p.name for p in root.iterdir() if (p / f"{p.name}.urdf").is_file()) if root.is_dir() else []


def _looks_like_name(value) -> bool:
    return isinstance(value, str) and re.fullmatch(r"[A-Za-z0-9_\-]+", value) is not None


def _resolve_urdf(urdf, config):
    if _looks_like_name(urdf) and not Path(urdf).is_file():
        candidate = paths.machines_dir() / urdf / f"{urdf}.urdf"
        if not candidate.is_file():
            raise UserError(f"machine {urdf!r}: no such URDF file or built-in machine "
                            f"(built-in: {', '.join(_builtin_machines()) or 'none'})")
        return candidate, config
    path = Path(urdf).expanduser()
    if path.suffix.lower() in (".yaml", ".yml"):
        # a machine.yaml names its URDF; it is then also the config
        cfg = _read_config(path)
        if "urdf" not in cfg:
            raise UserError(f"{path}: key 'urdf' missing (the machine's URDF file, relative to this file)")
        return _resolve_urdf_path(path.parent / str(cfg["urdf"]), f"{path}: urdf"), config or path
    return _resolve_urdf_path(path, "URDF"), config


def _resolve_urdf_path(path: Path, what: str) -> Path:
    if not path.is_file():
        raise UserError(f"{what}: file {path} does not exist")
    return path.resolve()


def _parse_urdf(path: Path) -> yourdfpy.Robot:
    try:
        root = etree.parse(str(path), etree.XMLParser(remove_blank_text=True)).getroot()
    except etree.XMLSyntaxError as exc:
        raise UserError(f"{path}: not valid XML ({' '.join(str(exc).split())})") from None
    if root.tag != "robot":
        raise UserError(f"{path}: root element is <{root.tag}>, a URDF needs <robot>")
    try:
        model = yourdfpy.URDF.load(str(path), build_scene_graph=False, build_collision_scene_graph=False,
                                   load_meshes=False, load_collision_meshes=False)
    except Exception as exc:  # yourdfpy raises KeyError/ValueError/AttributeError on bad elements
        raise UserError(f"{path}: bad URDF element ({type(exc).__name__}: {' '.join(str(exc).split())})") from None
    robot = model.robot
    names = {link.name for link in robot.links}
    for joint in robot.joints:
        if joint.type not in (*MOVABLE, "fixed", "floating", "planar"):
            raise UserError(f"{path}: joint {joint.name!r} has type {joint.type!r} "
                            "(allowed: revolute, continuous, prismatic, fixed)")
        for role, link in (("parent", joint.parent), ("child", joint.child)):
            if link not in names:
                raise UserError(f"{path}: joint {joint.name!r} names {role} link {link!r}, which is not defined")
        limit = joint.limit
        if joint.type in ("revolute", "prismatic") and limit is not None and None not in (limit.lower, limit.upper) \
                and not (math.isfinite(limit.lower) and math.isfinite(limit.upper) and limit.lower <= limit.upper):
            raise UserError(f"{path}: joint {joint.name!r} <limit> lower={limit.lower:g} upper={limit.upper:g}: "
                            "expected finite numbers with lower <= upper")
    for link in robot.links:
        for element in [*link.visuals, *link.collisions]:
            _check_geometry(element.geometry, link.name, path)
    return robot


def _check_geometry(geometry, link: str, path: Path) -> None:
    """Box, cylinder and sphere sizes: the right count of finite positive numbers (yourdfpy reads any count, and
    trimesh then fails on them, or builds an empty shape from zeros)."""
    if geometry is None:
        return
    shapes = (("box", "size", 3), ("cylinder", "radius", 1), ("cylinder", "length", 1), ("sphere", "radius", 1))
    for shape, attribute, count in shapes:
        element = getattr(geometry, shape)
        if element is None:
            continue
        values = np.atleast_1d(np.asarray(getattr(element, attribute), float))
        if len(values) != count or not np.all(np.isfinite(values)) or not np.all(values > 0):
            what = f"{count} finite positive numbers" if count > 1 else "a finite positive number"
            shown = " ".join(f"{v:g}" for v in values)
            raise UserError(f"{path}: link {link!r} <{shape} {attribute}=\"{shown}\">: expected {what}")


def _resolve_config(config, urdf_path: Path, robot_name: str, warnings: list[str]) -> Path | None:
    if config is not None:
        if _looks_like_name(config) and not Path(config).is_file():
            candidate = paths.machines_dir() / config / "machine.yaml"
            if not candidate.is_file():
                raise UserError(f"machine config {config!r}: no such file or built-in machine "
                                f"(built-in: {', '.join(_builtin_machines()) or 'none'})")
            return candidate
        path = Path(config).expanduser()
        if not path.is_file():
            raise UserError(f"machine config: file {path} does not exist")
        return path.resolve()
    beside = urdf_path.parent / "machine.yaml"
    if beside.is_file():
        return beside
    builtin = paths.machines_dir() / robot_name / "machine.yaml"
    if builtin.is_file():
        warnings.append(f"no machine.yaml beside {urdf_path}; using built-in machine {robot_name!r} "
                        f"({builtin}) because the robot is named {robot_name!r}")
        return builtin
    warnings.append(f"no machine config for {urdf_path}: actuators from the URDF <limit> velocity/effort, "
                    f"gain {DEFAULT_GAIN} 1/s; masses as in the URDF")
    return None


def _read_config(path: Path) -> dict:
    # the scene's reader: one line for a non-UTF-8 byte or a duplicate key, and YAML 1.2 numbers (1e-3 is a number)
    from .scene import _parse_yaml, _read_scene_text

    cfg = _parse_yaml(_read_scene_text(Path(path), str(path)), str(path))
    if cfg is None:
        return {}
    if not isinstance(cfg, dict):
        raise UserError(f"{path}: expected a mapping of keys ({', '.join(CONFIG_KEYS)})")
    unknown = [key for key in cfg if key not in CONFIG_KEYS]
    if unknown:
        raise UserError(f"{path}: unknown key {unknown[0]!r} (allowed: {', '.join(CONFIG_KEYS)})")
    return cfg


# ----------------------------------------------------------------------------------------- structure
def _children(robot) -> dict[str, list]:
    children: dict[str, list] = {link.name: [] for link in robot.links}
    for joint in robot.joints:
        children[joint.parent].append(joint)
    return children


def _root_link(robot, path: Path) -> str:
    roots = [link.name for link in robot.links if link.name not in {j.child for j in robot.joints}]
    if len(roots) != 1:
        raise UserError(f"{path}: expected one root link, found {len(roots)} ({', '.join(roots) or 'a loop'})")
    return roots[0]


def _subtree_has_collision(link_name, children, links) -> bool:
    if links[link_name].collisions:
        return True
    return any(_subtree_has_collision(j.child, children, links) for j in children[link_name])


def _actuated_joints(cfg, where, joints, children, links, urdf_path) -> list[str]:
    if "actuated_joints" in cfg:
        names = cfg["actuated_joints"]
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
            raise UserError(f"{where}: actuated_joints must be a non-empty list of joint names")
        for name in names:
            if name not in joints:
                raise UserError(f"{where}: actuated_joints names joint {name!r}, which {urdf_path.name} "
                                f"does not have (movable joints: {', '.join(_movable(joints))})")
            if joints[name].type not in MOVABLE:
                raise UserError(f"{where}: actuated joint {name!r} is {joints[name].type} in {urdf_path.name} "
                                "(allowed: revolute, continuous, prismatic)")
        return list(names)
    # dummy joints (OPERA's bucket_end_joint) carry no collision geometry below them
    return [name for name, joint in joints.items()
            if joint.type in MOVABLE and _subtree_has_collision(joint.child, children, links)]


def _movable(joints) -> list[str]:
    return [name for name, joint in joints.items() if joint.type in MOVABLE]


def _positive(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise UserError(f"{where} must be a positive number, got {value!r}")
    return float(value)


def _actuators(cfg, where, actuated, joints, urdf_path, warnings) -> dict[str, Actuator]:
    section = cfg.get("joints") or {}
    if not isinstance(section, dict):
        raise UserError(f"{where}: joints must be a mapping joint -> {{max_speed, max_torque, gain}}")
    for name in section:
        if name not in joints:
            raise UserError(f"{where}: joints.{name}: {urdf_path.name} has no joint {name!r} "
                            f"(movable joints: {', '.join(_movable(joints))})")
        if name not in actuated:
            raise UserError(f"{where}: joints.{name}: not in actuated_joints ({', '.join(actuated)})")
    actuators = {}
    from_urdf = []
    for name in actuated:
        entry = section.get(name)
        if entry is None:
            limit = joints[name].limit
            speed, effort = (limit.velocity, limit.effort) if limit is not None else (None, None)
            label = f"{urdf_path}: joint {name!r} <limit>"
            actuators[name] = Actuator(_positive(speed, f"{label} velocity"), _positive(effort, f"{label} effort"),
                                       DEFAULT_GAIN)
            from_urdf.append(name)
            continue
        if not isinstance(entry, dict):
            raise UserError(f"{where}: joints.{name} must be a mapping with {', '.join(ACTUATOR_KEYS)}")
        unknown = [key for key in entry if key not in ACTUATOR_KEYS]
        if unknown:
            raise UserError(f"{where}: joints.{name}.{unknown[0]}: unknown key (allowed: {', '.join(ACTUATOR_KEYS)})")
        values = {}
        for key in ACTUATOR_KEYS:
            if key not in entry:
                raise UserError(f"{where}: joints.{name}.{key} missing (a positive number)")
            values[key] = _positive(entry[key], f"{where}: joints.{name}.{key}")
        actuators[name] = Actuator(**values)
    if from_urdf and "joints" in cfg:
        warnings.append(f"{where}: no joints entry for {', '.join(from_urdf)}; using the URDF limits "
                        f"and gain {DEFAULT_GAIN} 1/s")
    return actuators


def _apply_overrides(actuators: dict[str, Actuator], overrides) -> None:
    for name, values in (overrides or {}).items():
        if name not in actuators:
            raise UserError(f"actuators.{name}: not an actuated joint{did_you_mean(name, actuators)} (actuated: "
                            f"{', '.join(actuators)})")
        if not isinstance(values, dict):
            raise UserError(f"actuators.{name}: expected a mapping of {', '.join(ACTUATOR_KEYS)}")
        for key, value in values.items():
            if key not in ACTUATOR_KEYS:
                raise UserError(f"actuators.{name}.{key}: unknown key (allowed: {', '.join(ACTUATOR_KEYS)})")
            setattr(actuators[name], key, _positive(value, f"actuators.{name}.{key}"))


def _tip_and_soil_links(cfg, where, links, children, root, warnings, from_config):
    def check(name, key):
        if not isinstance(name, str) or name not in links:
            raise UserError(f"{where}: {key} {name!r} is not a link of the URDF (links: {', '.join(links)})")
        return name

    # default tip: the end of the longest chain from the root; default soil link: the last link with
    # collision geometry on that chain
    chain = _longest_chain(root, children)
    tip = check(cfg["tip_link"], "tip_link") if "tip_link" in cfg else chain[-1]
    if "soil_links" in cfg:
        soil = cfg["soil_links"]
        if not isinstance(soil, list):
            raise UserError(f"{where}: soil_links must be a list of link names")
        soil = [check(name, "soil_links entry") for name in soil]
    else:
        with_geometry = [name for name in chain if links[name].collisions]
        soil = with_geometry[-1:]
    for name in soil:
        if not links[name].collisions:
            raise UserError(f"{where}: soil link {name!r} has no <collision> geometry for the soil to touch")
    if from_config and ("tip_link" not in cfg or "soil_links" not in cfg):
        warnings.append(f"{where}: tip_link/soil_links not given; using tip_link={tip}, soil_links={soil}")
    elif not from_config:
        warnings.append(f"defaults: tip_link={tip}, soil_links={soil}")
    return tip, soil


def _check_tip_is_moved(tip, from_config, where, joints, actuated, urdf_path) -> None:
    """The tip must hang below an actuated joint: the kinematics (a bucket-tip path, the summary's tip) follow the
    joints that move it."""
    parent = {joint.child: joint for joint in joints.values()}
    name = tip
    while name in parent:
        if parent[name].name in actuated:
            return
        name = parent[name].parent
    moved_by = f"(actuated joints: {', '.join(actuated) or 'none'})"
    if from_config:
        raise UserError(f"{where}: tip_link {tip!r}: no actuated joint moves this link {moved_by}")
    raise UserError(f"{urdf_path}: no actuated joint moves link {tip!r}, the end of its longest chain and so the "
                    f"default tip {moved_by}; name the tip in a machine.yaml's tip_link")


def _longest_chain(root, children) -> list[str]:
    best = [root]
    for joint in children[root]:
        chain = [root, *_longest_chain(joint.child, children)]
        if len(chain) > len(best):
            best = chain
    return best


def _tracks(cfg, where) -> dict | None:
    tracks = cfg.get("tracks")
    if tracks is None:
        return None
    if not isinstance(tracks, dict):
        raise UserError(f"{where}: tracks must be a mapping with {', '.join(TRACK_KEYS)}")
    unknown = [key for key in tracks if key not in TRACK_KEYS + TRACK_OPTIONAL_KEYS]
    if unknown:
        raise UserError(f"{where}: tracks.{unknown[0]}: unknown key (allowed: {', '.join(TRACK_KEYS)}, "
                        f"{', '.join(TRACK_OPTIONAL_KEYS)})")
    out = {}
    for key in TRACK_KEYS:
        if key not in tracks:
            raise UserError(f"{where}: tracks.{key} missing")
        if key == "x":
            xs = tracks["x"]
            if not isinstance(xs, list) or not xs or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                              and math.isfinite(v) for v in xs):
                raise UserError(f"{where}: tracks.x must be a list of finite wheel positions along the base x axis "
                                f"(m), got {xs!r}")
            out["x"] = [float(v) for v in xs]
        else:
            out[key] = _positive(tracks[key], f"{where}: tracks.{key}")
    out["lateral_friction"] = _positive(tracks["lateral_friction"], f"{where}: tracks.lateral_friction") \
        if "lateral_friction" in tracks else LATERAL_FRICTION_SHARE * out["friction"]
    out["max_speed"] = _positive(tracks["max_speed"], f"{where}: tracks.max_speed") if "max_speed" in tracks else None
    return out


def _masses(cfg, where, links) -> dict[str, float]:
    masses = cfg.get("masses") or {}
    if not isinstance(masses, dict):
        raise UserError(f"{where}: masses must be a mapping link -> kg")
    for name in masses:
        if name not in links:
            raise UserError(f"{where}: masses.{name}: not a link of the URDF (links: {', '.join(links)})")
    return {name: _positive(value, f"{where}: masses.{name}") for name, value in masses.items()}


def _limits(joint) -> tuple[float, float]:
    if joint.type == "continuous" or joint.limit is None or joint.limit.lower is None or joint.limit.upper is None:
        return (-math.inf, math.inf)
    return (float(joint.limit.lower), float(joint.limit.upper))


def _normalise_axis(joint, path: Path) -> None:
    if joint.type not in MOVABLE:
        return
    axis = np.array([1.0, 0.0, 0.0]) if joint.axis is None else np.asarray(joint.axis, float)
    norm = float(np.linalg.norm(axis))
    if not np.isfinite(norm) or norm < 1e-12:
        raise UserError(f"{path}: joint {joint.name!r} has a zero-length axis {axis.tolist()}")
    joint.axis = axis / norm        # OPERA writes swing_joint's axis as "0 0 2"


def _write_actuator_limit(joint, actuator: Actuator) -> None:
    if joint.limit is None:
        joint.limit = yourdfpy.Limit()
    joint.limit.velocity = actuator.max_speed
    joint.limit.effort = actuator.max_torque


# ----------------------------------------------------------------------------------------- meshes
class _MeshCache:
    """Resolves mesh URIs, converts what PyBullet cannot read to OBJ in the cache (keyed by file hash),
    and loads each file at most once per load_machine call."""

    def __init__(self, urdf_path: Path):
        self.urdf_path = urdf_path
        self.loaded: dict[str, trimesh.Trimesh] = {}

    def resolve_element(self, element, link_name: str) -> None:
        mesh = element.geometry.mesh if element.geometry is not None else None
        if mesh is None:
            return
        source = self._find(mesh.filename, link_name)
        mesh.filename = str(self._pybullet_file(source, mesh.filename))

    def _find(self, uri: str, link_name: str) -> Path:
        base = self.urdf_path.parent
        if uri.startswith("package://"):
            package, _, rest = uri[len("package://"):].partition("/")
            candidates = []
            for folder in [base, *base.parents]:
                if folder.name == package:
                    candidates.append(folder / rest)
                candidates.append(folder / package / rest)
            for root in filter(None, os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep)):
                candidates.append(Path(root) / package / rest)
            found = next((c for c in candidates if c.is_file()), None)
            if found is None:
                raise UserError(f"{self.urdf_path}: mesh {uri!r} of link {link_name!r} not found (looked for "
                                f"a folder {package!r} in {base} and its parents, and in ROS_PACKAGE_PATH)")
            return found.resolve()
        path = Path(uri[len("file://"):]) if uri.startswith("file://") else Path(uri)
        path = path if path.is_absolute() else base / path
        if not path.is_file():
            raise UserError(f"{self.urdf_path}: mesh {uri!r} of link {link_name!r} not found (looked at {path})")
        return path.resolve()

    def _pybullet_file(self, source: Path, uri: str) -> Path:
        if source.suffix.lower() in PYBULLET_MESH_SUFFIXES:
            return source
        digest = hashlib.sha256(source.read_bytes()).hexdigest()[:24]
        target = paths.cache_dir() / "meshes" / f"{source.stem}-{digest}.obj"
        if not target.is_file():
            mesh = self._read(source, uri)
            plain = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, process=False)
            atomic_write(target, trimesh.exchange.obj.export_obj(
                plain, include_normals=False, include_color=False, include_texture=False, header=None))
            self.loaded[str(target)] = plain          # the mass and soil geometry read it from here
        return target

    def _read(self, path: Path, uri: str) -> trimesh.Trimesh:
        key = str(path)
        if key not in self.loaded:
            try:
                mesh = trimesh.load(key, force="mesh", process=False)
            except Exception as exc:
                raise UserError(f"{self.urdf_path}: mesh {uri!r} could not be read ({type(exc).__name__}: "
                                f"{' '.join(str(exc).split())})") from None
            if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
                raise UserError(f"{self.urdf_path}: mesh {uri!r} has no triangles")
            self.loaded[key] = mesh
        return self.loaded[key]

    def geometry_mesh(self, geometry) -> trimesh.Trimesh | None:
        """The element's geometry as a mesh in its own frame (mesh scale applied)."""
        if geometry is None:
            return None
        if geometry.mesh is not None:
            mesh = self._read(Path(geometry.mesh.filename), geometry.mesh.filename).copy()
            if geometry.mesh.scale is not None:
                mesh.apply_scale(geometry.mesh.scale)
            return mesh
        if geometry.box is not None:
            return trimesh.creation.box(extents=geometry.box.size)
        if geometry.cylinder is not None:
            return trimesh.creation.cylinder(radius=geometry.cylinder.radius, height=geometry.cylinder.length)
        if geometry.sphere is not None:
            return trimesh.creation.icosphere(radius=geometry.sphere.radius)
        return None

    def link_mesh(self, link, collision: bool) -> trimesh.Trimesh | None:
        """All collision (or visual) geometry of a link, in the link frame (element origins applied)."""
        parts = []
        for element in (link.collisions if collision else link.visuals):
            mesh = self.geometry_mesh(element.geometry)
            if mesh is not None:
                if element.origin is not None:
                    mesh.apply_transform(element.origin)
                parts.append(mesh)
        if not parts:
            return None
        return parts[0] if len(parts) == 1 else trimesh.util.concatenate(parts)


def mass_properties(mesh: trimesh.Trimesh, mass: float) -> tuple[np.ndarray, np.ndarray]:
    """(centre of mass, inertia about it) of `mesh` carrying `mass`, link-frame axes. A closed mesh is a
    solid of uniform density; an open one (CAD surfaces) a thin shell of uniform areal density, since a
    solid needs a volume that an open surface does not have."""
    mesh = mesh.copy()
    mesh.merge_vertices()               # exporters (COLLADA) split vertices per face; closedness needs them shared
    if mesh.is_watertight and mesh.volume > 0:
        solid = mesh
        solid.density = mass / solid.volume
        return np.asarray(solid.center_mass), np.asarray(solid.moment_inertia)
    triangles = mesh.triangles                              # (n, 3, 3)
    areas = mesh.area_faces
    density = mass / areas.sum()
    vertex_sum = triangles.sum(axis=1)                      # a + b + c per triangle
    com = (areas[:, None] * vertex_sum).sum(axis=0) / 3.0 / areas.sum()
    # integral of x x^T over a triangle: A/12 (sum of v v^T over its vertices + s s^T), s = a + b + c
    second = np.einsum("n,nvi,nvj->ij", areas, triangles, triangles) + np.einsum("n,ni,nj->ij", areas, vertex_sum,
                                                                                  vertex_sum)
    second = density * second / 12.0 - mass * np.outer(com, com)
    inertia = np.trace(second) * np.eye(3) - second
    return com, inertia


def _is_placeholder(inertial) -> bool:
    """OPERA's description gives every link 0.03 kg (track 10 kg) and an identity inertia."""
    if inertial is None or inertial.mass is None:
        return True
    identity = inertial.inertia is not None and np.allclose(inertial.inertia, np.eye(3))
    return inertial.mass < PLACEHOLDER_MASS or identity


def _fix_masses(robot, masses, meshes: _MeshCache, urdf_path, config_path, warnings) -> None:
    # only links with collision geometry are machine parts; a frame marker (OPERA's 1 g bucket_end_link) is not
    placeholders = [link for link in robot.links if link.collisions and _is_placeholder(link.inertial)]
    found = sorted({f"{link.inertial.mass:g}" for link in placeholders
                    if link.inertial is not None and link.inertial.mass is not None}, key=float)
    # what stands in for the masses: the placeholder figures, and/or links without any (no <inertial>)
    stand_ins = [f"{', '.join(found)} kg"] if found else []
    if any(link.inertial is None or link.inertial.mass is None for link in placeholders):
        stand_ins.append("no <inertial>")
    stand_ins = "; ".join(stand_ins)
    replaced, kept = [], []
    for link in robot.links:
        if link.name not in masses:
            if link in placeholders:
                kept.append(link.name)
            continue
        mass = masses[link.name]
        old = link.inertial
        if link in placeholders or old is None:
            mesh = meshes.link_mesh(link, collision=True) or meshes.link_mesh(link, collision=False)
            if mesh is None:
                raise UserError(f"{config_path}: masses.{link.name}: the link has no geometry to place the mass "
                                "in and no <inertial> in the URDF")
            com, inertia = mass_properties(mesh, mass)
            origin = np.eye(4)
            origin[:3, 3] = com
            link.inertial = yourdfpy.Inertial(origin=origin, mass=mass, inertia=inertia)
            replaced.append(f"{link.name} {mass:g} kg")
        elif not math.isclose(old.mass, mass, rel_tol=1e-3):
            # a real inertial with another mass: keep its COM and shape, scale it
            link.inertial = yourdfpy.Inertial(origin=old.origin, mass=mass, inertia=np.asarray(old.inertia) * mass / old.mass)
            warnings.append(f"{urdf_path.name}: mass of {link.name} {old.mass:g} kg replaced by {mass:g} kg "
                            f"from {config_path.name}")
    if replaced:
        warnings.append(f"placeholder masses ({stand_ins}) in {urdf_path}; replaced from "
                        f"{config_path.name} with inertia from the link meshes: {', '.join(replaced)}")
    if kept:
        warnings.append(f"placeholder masses ({stand_ins}) in {urdf_path} kept for {', '.join(kept)}: "
                        "no masses for them in a machine config, so the dynamics of those links are wrong")


def _warn_misaligned_soil_geometry(links, soil_links, urdf_path, warnings) -> None:
    for name in soil_links:
        link = links[name]
        if not link.visuals or not link.collisions:
            continue
        visual, collision = link.visuals[0].origin, link.collisions[0].origin
        visual = np.eye(4) if visual is None else visual
        collision = np.eye(4) if collision is None else collision
        if not np.allclose(visual, collision, atol=1e-6):
            rpy = [round(float(v), 4) + 0.0 for v in trimesh.transformations.euler_from_matrix(collision)]
            vrpy = [round(float(v), 4) + 0.0 for v in trimesh.transformations.euler_from_matrix(visual)]
            warnings.append(f"{urdf_path.name}: link {name}: collision origin (rpy {rpy}) differs from its visual "
                            f"origin (rpy {vrpy}); the soil and PyBullet use the collision geometry")


# ----------------------------------------------------------------------------------------- output
def atomic_write(path: Path, text: str) -> None:
    """Write via a temporary file and rename, so concurrent processes never read half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _write_cached_urdf(robot) -> Path:
    tree = yourdfpy.URDF(robot=robot, build_scene_graph=False, load_meshes=False).write_xml()
    text = etree.tostring(tree, xml_declaration=True, encoding="utf-8", pretty_print=True).decode()
    digest = hashlib.sha256(text.encode()).hexdigest()[:16]
    target = paths.cache_dir() / "urdf" / f"{robot.name}-{digest}.urdf"
    if not target.is_file():
        atomic_write(target, text)
    return target
