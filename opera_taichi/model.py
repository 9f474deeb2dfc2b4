"""Model: what does not change during a run, built once from a scene and then free of it.

`build_model(scene)` checks every cross-file fact (joint names against the URDF, beds inside the domain, the soil
time step against its stability limit) and raises UserError naming the scene key. It needs neither Taichi nor
PyBullet, so `validate` is quick. The engines are started by `Simulation(model)`.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import numpy as np

from .errors import UserError
from .geometry import rpy_to_quat
from .motion import JointProfile, bucket_tip_path, joint_waypoints, read_joint_csv

if TYPE_CHECKING:
    import trimesh

    from .kinematics import Kinematics
    from .machine_description import MachineDescription
    from .soil import SoilBulk, SoilMicro

# Bumped when the meaning of a checkpoint's arrays changes: an older checkpoint is then refused, not misread.
CHECKPOINT_FORMAT = 2   # 2: MachineState.track_stick
MIN_SOIL_DT = 1e-7   # s: a finer soil substep takes hours of wall time per simulated second (a stiffness typo)


@dataclass(frozen=True)
class Grid2D:
    """Heightmap nodes: cell centres on the axes x (nx,) and y (ny,), metres, uniformly spaced."""

    x: np.ndarray
    y: np.ndarray


@dataclass(frozen=True)
class KinematicTool:
    """A standalone rigid tool moving on a straight line at constant velocity (validation scenes)."""

    name: str
    mesh: "trimesh.Trimesh"     # tool frame, m
    start: np.ndarray           # (3,) m, origin at start_time
    quat_xyzw: np.ndarray       # (4,) orientation
    velocity: np.ndarray        # (3,) m/s
    start_time: float           # s
    stop_time: float | None     # s; None = never stops
    cutting_edge: object = None  # scene.CuttingEdgeConfig or None

    def pose_twist(self, t: float):
        """Position, quaternion (x, y, z, w), linear and angular velocity of the tool origin at time t."""
        t_end = t if self.stop_time is None else min(t, self.stop_time)
        moving_time = max(0.0, t_end - self.start_time)
        moving = self.start_time <= t and (self.stop_time is None or t < self.stop_time)
        v = self.velocity if moving else np.zeros(3)
        return self.start + self.velocity * moving_time, self.quat_xyzw, v, np.zeros(3)

    state = pose_twist  # earlier name, kept for scripts


@dataclass(frozen=True)
class MachineModel:
    """One machine of the scene: its description, where it stands and how it starts."""

    name: str                            # unique in the scene; the ROS namespace and joints.csv prefix
    description: "MachineDescription"    # URDF, actuators, soil links, collision meshes
    kinematics: "Kinematics"
    base_xyz: tuple[float, float, float]  # m, base_link origin in the world
    base_yaw: float                      # rad
    fixed_base: bool
    initial_q: dict[str, float]          # rad, every actuated joint
    motion: Optional[JointProfile]       # the scene's motion script (None = hold the initial pose)
    command_latency: float = 0.0         # s, dead time of commands from a ROS bridge (scene, else machine.yaml)
    soil_wedge: Optional[bool] = None    # cut with the soil wedge at the description's cutting edges (None: where
                                         # the grains are coarse for the edge, _cuts_with_wedge)

    @property
    def joints(self) -> list[str]:
        return list(self.description.actuated_joints)


@dataclass(frozen=True)
class SoilModel:
    """The soil's solver, parameters and geometry."""

    solver: str                          # registry key (soil.model)
    bulk: "SoilBulk"                     # what the user gave (preset + overrides)
    params: "SoilMicro"                  # the solver's own parameters from its bulk-to-micro mapping
    dt: float                            # s, soil substep
    domain_min: tuple[float, float, float]
    domain_max: tuple[float, float, float]
    beds: tuple                          # ((min xyz), (max xyz)) pits cut into the ground, m
    seed: int
    settle_time: float                   # s
    max_speed: float                     # m/s, divergence guard
    bed_shift: tuple[float, float, float]
    clear_above: float | None            # m
    grid: Grid2D                         # heightmap nodes of the run folder's terrain files
    sleep: bool = False                  # particles at rest far from every tool sleep
    surface: tuple | None = None         # (x, y, z[ix, iy]) m: top of the fill (soil.terrain); None = level beds


@dataclass(frozen=True)
class ToolBinding:
    """One soil tool, in the soil's tool-index order: a machine link or a standalone kinematic tool."""

    name: str                 # tool name in tool_wrench.csv and soil_mass.csv
    owner: str | None         # machine name; None for a standalone tool
    link: str | None          # the machine link it is bound to
    mesh: "trimesh.Trimesh"   # collision mesh in the link (tool) frame
    cutting_edge: object = None  # scene.CuttingEdgeConfig: the soil wedge at its edge; None: grain by grain


@dataclass(frozen=True)
class Model:
    name: str
    dt: float                             # s, rigid step
    duration: float                       # s, the scene's sim.duration
    seed: int
    machines: tuple[MachineModel, ...]
    soil: SoilModel | None
    tools: tuple[KinematicTool, ...]
    bindings: tuple[ToolBinding, ...]
    warnings: tuple[str, ...] = ()
    fingerprint: str = ""                 # hash of everything the physics depends on (checkpoint compatibility)
    gravity: float = 9.81                 # m/s2

    def machine(self, name: str | None = None) -> MachineModel:
        """The machine called `name`, or the only one."""
        if name is None:
            if len(self.machines) != 1:
                raise KeyError(f"the scene has {len(self.machines)} machines; name one of "
                               f"{[m.name for m in self.machines]}")
            return self.machines[0]
        for m in self.machines:
            if m.name == name:
                return m
        raise KeyError(f"no machine {name!r}; machines: {[m.name for m in self.machines]}")

    @property
    def tool_names(self) -> list[str]:
        return [b.name for b in self.bindings]


# ------------------------------------------------------------------------------------------ building
def _build_tools(scene) -> tuple[KinematicTool, ...]:
    import trimesh

    tools = []
    for i, cfg in enumerate(scene.tools or []):
        if cfg.box is not None:
            mesh = trimesh.creation.box(extents=[float(s) for s in cfg.box])
        else:
            try:
                mesh = trimesh.load(str(cfg.mesh), force="mesh")
            except Exception as exc:  # trimesh raises many types for unreadable files
                raise UserError(f"tools.{i}.mesh: cannot read {cfg.mesh} ({exc})") from None
            if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
                raise UserError(f"tools.{i}.mesh: {cfg.mesh} holds no triangles")
        tools.append(KinematicTool(cfg.name, mesh, np.asarray(cfg.start, float), rpy_to_quat(cfg.rpy),
                                   np.asarray(cfg.velocity, float), float(cfg.start_time),
                                   None if cfg.stop_time is None else float(cfg.stop_time), cfg.cutting_edge))
    return tuple(tools)


def _build_motion(motion, key: str, machine, kinematics, initial_q, name: str = "") -> JointProfile | None:
    if motion is None:
        return None
    joints = list(machine.actuated_joints)
    if motion.type == "joint_waypoints":
        points = []
        for i, wp in enumerate(motion.waypoints):
            for j in wp.q:
                if j not in joints:
                    raise UserError(f"{key}.waypoints.{i}.q.{j}: not an actuated joint of {machine.name} "
                                    f"(joints: {', '.join(joints)})")
            points.append((wp.t, dict(wp.q)))
        return joint_waypoints(points, {j: initial_q[j] for j in joints})
    if motion.type == "csv":
        try:
            return read_joint_csv(Path(motion.file), joints, motion.time_offset, machine=name)
        except UserError as exc:
            raise UserError(f"{key}.file: {exc}") from None
    if motion.type == "bucket_tip_path":
        points = [(wp.t, np.asarray(wp.xyz, float), wp.bucket_angle) for wp in motion.waypoints]
        try:
            return bucket_tip_path(points, kinematics, initial_q, joints)
        except UserError as exc:
            raise UserError(str(exc).replace("motion.", f"{key}.", 1)) from None
    raise UserError(f"{key}.type: unknown motion type {motion.type!r}")


def _beyond_limits(key: str, machine: MachineModel) -> list[str]:
    """A motion script that asks a joint past its limits (the run clips the targets) is said when it is checked."""
    if machine.motion is None:
        return []
    motion_key = "motion" if key == "machine" else f"{key}.motion"
    out = []
    for joint, (low, high) in machine.motion.extremes().items():
        lo, hi = machine.description.joint_limits.get(joint, (-math.inf, math.inf))
        if low < lo - 1e-9 or high > hi + 1e-9:
            out.append(f"{motion_key}: {joint} is asked {low:.4f}..{high:.4f} rad, beyond its limits "
                       f"[{lo:.4f}, {hi:.4f}] rad; the run clips its targets to them")
    return out


def machine_entries(scene) -> list[tuple[str, object, object]]:
    """(key prefix, MachineConfig, motion) of every machine: `machine:` + `motion:`, or each of `machines:`."""
    if scene.machine is not None:
        return [("machine", scene.machine, scene.motion)]
    return [(f"machines.{i}", m, m.motion) for i, m in enumerate(scene.machines or [])]


def _build_machine(key: str, cfg, motion, motion_key: str) -> MachineModel:
    from .kinematics import Kinematics
    from .machine_description import description_source, load_machine

    try:
        desc = load_machine(*description_source(cfg.model_dump()))
    except UserError as exc:  # an actuator override names its scene key
        if str(exc).startswith("actuators."):
            raise UserError(f"{key}.{exc}") from None
        raise
    joints = desc.actuated_joints
    for j in cfg.initial_joints:
        if j not in joints:
            raise UserError(f"{key}.initial_joints.{j}: not an actuated joint of {desc.name} "
                            f"(joints: {', '.join(joints)})")
    initial_q = {}
    for j in joints:
        lo, hi = desc.joint_limits.get(j, (-math.inf, math.inf))
        if j not in cfg.initial_joints:  # a joint not given starts at 0, or at its limit nearest to 0
            initial_q[j] = min(max(0.0, lo), hi)
            continue
        q = initial_q[j] = float(cfg.initial_joints[j])
        if not lo - 1e-9 <= q <= hi + 1e-9:
            raise UserError(f"{key}.initial_joints.{j} (or initial_joints_deg): {q:.4f} rad ({math.degrees(q):.1f} "
                            f"deg) is outside the joint's limits [{lo:.4f}, {hi:.4f}] rad ([{math.degrees(lo):.1f}, "
                            f"{math.degrees(hi):.1f}] deg)")
    wedge = getattr(cfg, "soil_wedge", None)
    if wedge and not desc.cutting_edges:
        raise UserError(f"{key}.soil_wedge: machine {desc.name}'s config gives no cutting_edges (machine.yaml: "
                        f"cutting_edges: {{<soil link>: {{centre, face_normal, face_up, width}}}}, in the link's frame)")
    kin = Kinematics(desc)
    name = getattr(cfg, "name", None) or desc.name
    return MachineModel(name=name, description=desc, kinematics=kin,
                        base_xyz=tuple(float(v) for v in cfg.base_pose.xyz), base_yaw=float(cfg.base_pose.yaw),
                        fixed_base=bool(cfg.fixed_base), initial_q=initial_q,
                        motion=_build_motion(motion, motion_key, desc, kin, initial_q, name),
                        command_latency=float(cfg.command_latency if cfg.command_latency is not None
                                              else desc.command_latency),
                        soil_wedge=None if wedge is None else bool(wedge))


def soil_parameters(soil):
    """(SoilBulk, SoilMicro) of a scene's soil section: the preset with its overrides, and the micro-parameters
    the solver's bulk-to-micro mapping gives them for the deepest bed."""
    from .soil_solver import solver_class

    return solver_class(soil.model).map_parameters(soil)


MAX_HEIGHTMAP_CELLS = 4_000_000   # a terrain file of 32 MB a heightmap (z and z_all), written twice a run


def terrain_grid(soil) -> Grid2D:
    cell = float(soil.heightmap_cell)
    lo, hi = np.asarray(soil.domain.min, float), np.asarray(soil.domain.max, float)
    extent = hi[:2] - lo[:2]
    if cell > float(np.min(extent)) / 2:
        raise UserError(f"soil.heightmap_cell: {cell:g} m leaves the domain ({extent[0]:g} x {extent[1]:g} m) fewer "
                        f"than 2 cells across; at most {float(np.min(extent)) / 2:g} m")
    nx = max(1, int(round((hi[0] - lo[0]) / cell)))
    ny = max(1, int(round((hi[1] - lo[1]) / cell)))
    if nx * ny > MAX_HEIGHTMAP_CELLS:
        finest = math.sqrt(float(np.prod(extent)) / MAX_HEIGHTMAP_CELLS)
        raise UserError(f"soil.heightmap_cell: {cell:g} m makes {nx * ny:,} cells over the domain, at most "
                        f"{MAX_HEIGHTMAP_CELLS:,}; the finest cell is about {math.ceil(finest * 1e4) / 1e4:g} m")
    x = lo[0] + (np.arange(nx) + 0.5) * (hi[0] - lo[0]) / nx
    y = lo[1] + (np.arange(ny) + 0.5) * (hi[1] - lo[1]) / ny
    return Grid2D(x, y)


def _build_soil(scene) -> SoilModel:
    from .soil import check_dt

    soil = scene.soil
    surface = None
    if soil.terrain is not None:  # beds filled to a scanned surface: their floors follow from it
        from .terrain_bed import terrain_beds

        beds, surface = terrain_beds(soil, terrain_grid(soil))
        soil = soil.model_copy(update={"bed": beds})
    bulk, micro = soil_parameters(soil)
    if scene.sim.soil_dt is not None:
        check_dt(micro, float(scene.sim.soil_dt))
        dt = float(scene.sim.soil_dt)
    else:
        dt = float(micro.dt_limit)
    if dt < MIN_SOIL_DT and scene.sim.soil_dt is not None:
        raise UserError(f"sim.soil_dt: {dt:g} s means {1.0 / dt:.3g} substeps per simulated second, at most "
                        f"{1.0 / MIN_SOIL_DT:.0e} (hours of wall time per second); null takes the soil's own limit")
    if dt < MIN_SOIL_DT:
        raise UserError(f"soil.overrides: these grains need a soil substep of {dt:.3g} s, {1.0 / dt:.3g} substeps per "
                        f"simulated second (at most {1.0 / MIN_SOIL_DT:.0e}): lower youngs_modulus "
                        f"({bulk.youngs_modulus:g} Pa), or raise density ({bulk.density:g} kg/m3) or radius "
                        f"({bulk.radius:g} m)")
    lo, hi = np.asarray(soil.domain.min, float), np.asarray(soil.domain.max, float)
    for i, bed in enumerate(soil.bed):
        bmin, bmax = np.asarray(bed.min, float), np.asarray(bed.max, float)
        if np.any(bmin < lo - 1e-9) or np.any(bmax > hi + 1e-9):
            raise UserError(f"soil.bed.{i}: box {bmin.tolist()}..{bmax.tolist()} is not inside soil.domain "
                            f"{lo.tolist()}..{hi.tolist()}")
        shift = np.asarray(soil.bed_shift, float)
        if np.any(bmin + shift >= hi) or np.any(bmax + shift <= lo):  # every grain would leave at once
            raise UserError(f"soil.bed_shift: {shift.tolist()} moves soil.bed.{i} wholly out of soil.domain "
                            f"{lo.tolist()}..{hi.tolist()}")
    model = SoilModel(solver=soil.model, bulk=bulk, params=micro, dt=dt, domain_min=tuple(map(float, lo)),
                     domain_max=tuple(map(float, hi)),
                     beds=tuple((tuple(map(float, b.min)), tuple(map(float, b.max))) for b in soil.bed),
                     seed=int(scene.sim.seed), settle_time=float(soil.settle_time), max_speed=float(soil.max_speed),
                     bed_shift=tuple(map(float, soil.bed_shift)),
                     clear_above=None if soil.clear_above is None else float(soil.clear_above),
                     grid=terrain_grid(soil), sleep=bool(soil.sleep), surface=surface)
    from .soil_solver import solver_class

    solver = solver_class(soil.model)
    if hasattr(solver, "check_model"):
        solver.check_model(model)
    return model


# A machine's edge cuts with its soil wedge by default where fewer grain diameters than this span the edge's width:
# there the grains alone push back with a layer of grains under the edge (the main job's drag at 12 cm grains, 2.9
# across the ZX120's 0.70 m edge, 1.74 x its 5 cm drag; with the wedge 0.99 x), and the wedge's cost leaves those
# coarse digs well above real time. From 8 cm (4.4 across) down the grains alone drag within the seeds' spread of the
# wedge, and they keep the fine digs' speed, which the wedge does not yet (docs/dig_path.md).
WEDGE_GRAINS_ACROSS = 4.0


def _cuts_with_wedge(machine: MachineModel, edge, radius: float) -> bool:
    """Whether a machine's soil link cuts with the soil wedge at its cutting edge: as the scene's machine.soil_wedge
    says, and where it says nothing (null), where the grains are coarse for the edge (WEDGE_GRAINS_ACROSS)."""
    if edge is None or machine.soil_wedge is False:
        return False
    return machine.soil_wedge is True or edge.width < WEDGE_GRAINS_ACROSS * 2.0 * radius


def _bindings(machines, tools, soil) -> tuple[ToolBinding, ...]:
    rows = []
    for m in machines:
        for link in m.description.soil_links:
            name = link if len(machines) == 1 else f"{m.name}.{link}"
            edge = m.description.cutting_edges.get(link)
            edge = edge if _cuts_with_wedge(m, edge, float(soil.bulk.radius)) else None
            rows.append(ToolBinding(name, m.name, link, m.description.collision_meshes[link], edge))
    for tool in tools:
        rows.append(ToolBinding(tool.name, None, None, tool.mesh, tool.cutting_edge))
    names = [r.name for r in rows]
    for name in names:
        if names.count(name) > 1:
            raise UserError(f"tools: the name {name!r} is used twice (a standalone tool named like a machine's "
                            f"soil link); rename the tool")
    return tuple(rows)


def _fingerprint(scene) -> str:
    """What a checkpoint must share with the scene that resumes it: everything but the output and the duration."""
    from .scene import scene_to_dict

    data = scene_to_dict(scene)
    data.pop("output", None)
    data.pop("bridge", None)     # how the machine is commanded, not what it is
    data.get("sim", {}).pop("duration", None)
    data.get("sim", {}).pop("arch", None)
    data.pop("name", None)
    text = json.dumps(data, sort_keys=True, default=str)
    return hashlib.sha256(f"{CHECKPOINT_FORMAT}:{text}".encode()).hexdigest()[:24]


def build_model(scene) -> Model:
    """Everything that does not change during the run, checked: raises UserError on bad input."""
    machines = []
    names: dict[str, str] = {}
    for key, cfg, motion in machine_entries(scene):
        m = _build_machine(key, cfg, motion, "motion" if key == "machine" else f"{key}.motion")
        if m.name in names:
            raise UserError(f"{key}.name: {m.name!r} is already the name of {names[m.name]}; machines need "
                            f"unique names")
        names[m.name] = key
        machines.append(m)
    if scene.motion is not None and scene.machine is None:
        raise UserError("motion: a motion script needs a machine (add a `machine` section)")
    tools = _build_tools(scene)
    soil = _build_soil(scene) if scene.soil is not None else None
    warnings = tuple(w for m in machines for w in m.description.warnings)
    warnings += tuple(w for (key, _, _), m in zip(machine_entries(scene), machines) for w in _beyond_limits(key, m))
    warnings += _stiffness_floor(scene, soil)
    return Model(name=scene.name, dt=float(scene.sim.dt), duration=float(scene.sim.duration),
                 seed=int(scene.sim.seed), machines=tuple(machines), soil=soil, tools=tools,
                 bindings=_bindings(machines, tools, soil) if soil is not None else (), warnings=warnings,
                 fingerprint=_fingerprint(scene))


def _stiffness_floor(scene, soil) -> tuple[str, ...]:
    """A youngs_modulus override below the contact stiffness the bed's weight needs (soil.OVERLAP_RULE) does not set
    the contacts: say so rather than let a calibration or a study vary it for nothing."""
    from .soil import STIFFNESS_SCALE

    asked = (scene.soil.overrides or {}).get("youngs_modulus") if scene.soil is not None else None
    if soil is None or asked is None or not hasattr(soil.params, "k_n"):
        return ()
    from_e = STIFFNESS_SCALE * float(soil.bulk.youngs_modulus) * 2.0 * float(soil.bulk.radius)
    if soil.params.k_n <= from_e * (1.0 + 1e-9):
        return ()
    floor = soil.params.k_n / (STIFFNESS_SCALE * 2.0 * float(soil.bulk.radius))
    return (f"soil.overrides.youngs_modulus: {float(asked):g} Pa is below the stiffness the bed's weight needs for "
            f"these grains (overlaps under 1% of the radius); the contacts take {floor:.3g} Pa's, so a lower value "
            f"changes nothing",)


def check_scene(scene) -> Model:
    """`validate`: build the model (files, joints, soil parameters, time steps) without running."""
    return build_model(scene)


__all__ = ["Grid2D", "KinematicTool", "MachineModel", "SoilModel", "ToolBinding", "Model", "build_model",
           "check_scene", "soil_parameters", "terrain_grid", "CHECKPOINT_FORMAT"]
