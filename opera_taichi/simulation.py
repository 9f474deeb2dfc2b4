"""The coupled simulation: Model (what does not change), State (what does), Control (this step's
commands) and one `step`, plus `run_scene`, which drives a scene to its end and writes the run folder.

One step (DESIGN.md):
  1. the motion script gives joint targets (Control);
  2. PyBullet advances the machine one rigid step with the soil wrench of the previous step applied to
     each soil-touching link;
  3. the poses and velocities of the soil-touching links and standalone tools go to the soil solver;
  4. the soil takes its substeps with the tools kinematic and returns the averaged wrench per tool;
  5. recorders sample at their own rates.
"""
from __future__ import annotations

import math
import platform
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from . import __version__
from .errors import DivergenceError, UserError
from .motion import Control, JointProfile, bucket_tip_path, joint_waypoints, read_joint_csv


# ----------------------------------------------------------------------------------------------- model
@dataclass
class KinematicTool:
    """A standalone rigid tool moving on a straight line at constant velocity (validation scenes)."""

    name: str
    mesh: object  # trimesh.Trimesh in the tool frame
    start: np.ndarray
    quat_xyzw: np.ndarray
    velocity: np.ndarray
    start_time: float
    stop_time: float | None

    def state(self, t: float):
        t_end = t if self.stop_time is None else min(t, self.stop_time)
        moving_time = max(0.0, t_end - self.start_time)
        moving = self.start_time <= t and (self.stop_time is None or t < self.stop_time)
        v = self.velocity if moving else np.zeros(3)
        return self.start + self.velocity * moving_time, self.quat_xyzw, v, np.zeros(3)


@dataclass
class Model:
    scene: object
    dt: float
    machine: object | None = None          # MachineDescription
    kinematics: object | None = None
    motion: JointProfile | None = None
    soil_bulk: object | None = None
    soil_micro: object | None = None
    soil_dt: float | None = None
    tools: list[KinematicTool] = field(default_factory=list)
    initial_q: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def joints(self) -> list[str]:
        return list(self.machine.actuated_joints) if self.machine else []


def _rpy_to_quat(rpy) -> np.ndarray:
    r, p, y = (float(a) for a in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r / 2), math.sin(r / 2), math.cos(p / 2), math.sin(p / 2), \
        math.cos(y / 2), math.sin(y / 2)
    return np.array([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy])


def _build_tools(scene) -> list[KinematicTool]:
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
        tools.append(KinematicTool(cfg.name, mesh, np.asarray(cfg.start, float), _rpy_to_quat(cfg.rpy),
                                   np.asarray(cfg.velocity, float), float(cfg.start_time),
                                   None if cfg.stop_time is None else float(cfg.stop_time)))
    return tools


def _build_motion(scene, machine, kinematics, initial_q) -> JointProfile | None:
    motion = scene.motion
    if motion is None:
        return None
    joints = list(machine.actuated_joints) if machine else []
    if machine is None:
        raise UserError("motion: a motion script needs a machine (add a `machine` section)")
    if motion.type == "joint_waypoints":
        points = []
        for i, wp in enumerate(motion.waypoints):
            for j in wp.q:
                if j not in joints:
                    raise UserError(f"motion.waypoints.{i}.q.{j}: not an actuated joint of {machine.name} "
                                    f"(joints: {', '.join(joints)})")
            points.append((wp.t, dict(wp.q)))
        return joint_waypoints(points, {j: initial_q[j] for j in joints})
    if motion.type == "csv":
        return read_joint_csv(Path(motion.file), joints, motion.time_offset)
    if motion.type == "bucket_tip_path":
        points = [(wp.t, np.asarray(wp.xyz, float), wp.bucket_angle) for wp in motion.waypoints]
        return bucket_tip_path(points, kinematics, initial_q, joints)
    raise UserError(f"motion.type: unknown motion type {motion.type!r}")


def soil_parameters(soil):
    """(SoilBulk, SoilMicro) of a scene's soil section: the preset with its overrides, and the micro-parameters
    the bulk-to-micro mapping gives them for the deepest bed."""
    from .soil import bulk_to_micro, resolve_soil

    bulk = resolve_soil(soil.preset, dict(soil.overrides or {}))
    bed_depth = max((-float(b.min[2]) for b in soil.bed), default=1.0)
    return bulk, bulk_to_micro(bulk, bed_depth=max(bed_depth, 4 * bulk.radius))


def build_model(scene) -> Model:
    """Everything that does not change during the run, checked: raises UserError on bad input.
    Needs no Taichi and no PyBullet, so `validate` is quick."""
    model = Model(scene=scene, dt=float(scene.sim.dt))
    if scene.machine is not None:
        from .kinematics import Kinematics
        from .machine_description import load_machine

        mcfg = scene.machine
        overrides = {j: a.model_dump(exclude_none=True) if hasattr(a, "model_dump") else dict(a)
                     for j, a in (mcfg.actuators or {}).items()}
        model.machine = load_machine(mcfg.urdf, mcfg.config, overrides)
        model.warnings += list(model.machine.warnings)
        model.kinematics = Kinematics(model.machine)
        joints = model.machine.actuated_joints
        for j in mcfg.initial_joints:
            if j not in joints:
                raise UserError(f"machine.initial_joints.{j}: not an actuated joint of {model.machine.name} "
                                f"(joints: {', '.join(joints)})")
        model.initial_q = {j: float(mcfg.initial_joints.get(j, 0.0)) for j in joints}
        for j, q in model.initial_q.items():
            lo, hi = model.machine.joint_limits.get(j, (-math.inf, math.inf))
            if not lo - 1e-9 <= q <= hi + 1e-9:
                raise UserError(f"machine.initial_joints.{j}: {q:.4f} rad is outside the joint's limits "
                                f"[{lo:.4f}, {hi:.4f}] rad")
        model.motion = _build_motion(scene, model.machine, model.kinematics, model.initial_q)
    elif scene.motion is not None:
        raise UserError("motion: a motion script needs a machine (add a `machine` section)")
    model.tools = _build_tools(scene)
    if scene.soil is not None:
        from .soil import check_dt

        soil = scene.soil
        model.soil_bulk, model.soil_micro = soil_parameters(soil)
        if scene.sim.soil_dt is not None:
            check_dt(model.soil_micro, float(scene.sim.soil_dt))
            model.soil_dt = float(scene.sim.soil_dt)
        else:
            model.soil_dt = float(model.soil_micro.dt_limit)
        lo, hi = np.asarray(soil.domain.min, float), np.asarray(soil.domain.max, float)
        for i, bed in enumerate(soil.bed):
            bmin, bmax = np.asarray(bed.min, float), np.asarray(bed.max, float)
            if np.any(bmin < lo - 1e-9) or np.any(bmax > hi + 1e-9):
                raise UserError(f"soil.bed.{i}: box {bmin.tolist()}..{bmax.tolist()} is not inside soil.domain "
                                f"{lo.tolist()}..{hi.tolist()}")
    return model


def check_scene(scene) -> Model:
    """`validate`: build the model (files, joints, soil parameters, time steps) without running."""
    return build_model(scene)


# ----------------------------------------------------------------------------------------------- state
@dataclass
class State:
    t: float = 0.0
    machine: object | None = None       # BulletMachine
    soil: object | None = None          # DemSoil
    tool_wrench: np.ndarray | None = None   # (n_tools, 6): soil on tool, last step, world frame
    tool_names: list[str] = field(default_factory=list)


class Simulation:
    """Owns the model and state; `step(control)` advances both by one rigid step."""

    def __init__(self, model: Model, arch: str = "cpu"):
        self.model = model
        self.state = State()
        scene = model.scene
        self.arch = None
        if model.machine is not None:
            from .machine import BulletMachine

            pose = scene.machine.base_pose
            self.state.machine = BulletMachine(model.machine, dt=model.dt, base_xyz=tuple(pose.xyz),
                                               base_yaw=float(pose.yaw), fixed_base=scene.machine.fixed_base,
                                               initial_q=model.initial_q)
        if model.soil_micro is not None:
            from .backend import init_taichi
            from .dem_soil import DemSoil

            self.arch = init_taichi(arch)
            soil = scene.soil
            self.state.soil = DemSoil(model.soil_micro, domain_min=tuple(soil.domain.min),
                                      domain_max=tuple(soil.domain.max),
                                      beds=[(tuple(b.min), tuple(b.max)) for b in soil.bed],
                                      seed=int(scene.sim.seed), dt=model.soil_dt,
                                      max_speed=float(soil.max_speed), settle_time=float(soil.settle_time))
            shift = np.asarray(soil.bed_shift, float)
            if np.any(shift != 0.0):  # a settled block released above the ground (the pits stay, empty)
                parts = self.state.soil.particles()
                self.state.soil.set_particles(parts["positions"] + shift, radii=parts["radii"])
            if soil.clear_above is not None:
                self.state.soil.clear_above(float(soil.clear_above))
            names = []
            if model.machine is not None:
                for link in model.machine.soil_links:
                    self.state.soil.add_tool(link, model.machine.collision_meshes[link])
                    names.append(link)
            for tool in model.tools:
                self.state.soil.add_tool(tool.name, tool.mesh)
                names.append(tool.name)
            self.state.tool_names = names
            self.state.tool_wrench = np.zeros((len(names), 6))
            self._push_tool_states()

    @property
    def soil_link_count(self) -> int:
        return len(self.model.machine.soil_links) if self.model.machine is not None else 0

    def control_at(self, t: float) -> Control:
        motion = self.model.motion
        return Control(q_cmd=motion.targets(t) if motion is not None else dict(self.model.initial_q))

    def _push_tool_states(self) -> None:
        st = self.state
        i = 0
        if st.machine is not None:
            for link in self.model.machine.soil_links:
                st.soil.set_tool_state(i, *st.machine.link_state(link))
                i += 1
        for tool in self.model.tools:
            st.soil.set_tool_state(i, *tool.state(st.t))
            i += 1

    def step(self, control: Control) -> None:
        st = self.state
        if st.machine is not None:
            st.machine.set_targets(control.q_cmd)
            if not self.model.scene.machine.fixed_base:
                st.machine.set_track_speeds(*control.track_speeds)
            if st.soil is not None:
                for i, link in enumerate(self.model.machine.soil_links):
                    st.machine.apply_link_wrench(link, st.tool_wrench[i, :3], st.tool_wrench[i, 3:])
            st.machine.step()
            q, qd, _ = st.machine.joint_states()
            if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))):
                raise DivergenceError(f"machine diverged at t = {st.t + self.model.dt:.4f} s: "
                                      f"non-finite joint state")
        if st.soil is not None:
            self._push_tool_states()
            st.tool_wrench = st.soil.advance(self.model.dt)
        st.t += self.model.dt


# ----------------------------------------------------------------------------------------------- run
@dataclass
class RunResult:
    out_dir: Path
    status: str
    sim_time: float
    wall_time: float
    real_time_factor: float
    particles: int
    message: str = ""


def _versions() -> dict:
    """Versions of what produced the run; read from package metadata so nothing heavy is imported."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"opera_taichi": __version__, "python": platform.python_version()}
    for dist in ("taichi", "pybullet", "numpy", "trimesh", "yourdfpy", "pydantic"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = None
    return out


def _terrain_axes(scene) -> tuple[np.ndarray, np.ndarray]:
    soil = scene.soil
    cell = float(soil.heightmap_cell)
    lo, hi = np.asarray(soil.domain.min, float), np.asarray(soil.domain.max, float)
    nx = max(1, int(round((hi[0] - lo[0]) / cell)))
    ny = max(1, int(round((hi[1] - lo[1]) / cell)))
    x = lo[0] + (np.arange(nx) + 0.5) * (hi[0] - lo[0]) / nx
    y = lo[1] + (np.arange(ny) + 0.5) * (hi[1] - lo[1]) / ny
    return x, y


def _hull_halfspaces(mesh) -> np.ndarray:
    """(n, 4) plane equations of the convex hull of a tool mesh: inside when n.x + d <= 0 for all.
    The hull of an open bucket is its struck volume (the opening closed by the strike plane)."""
    hull = mesh.convex_hull
    normals = hull.face_normals
    d = -np.einsum("ij,ij->i", normals, hull.triangles[:, 0, :])
    return np.hstack([normals, d[:, None]])


def _quat_to_matrix(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def run_scene(scene, out_dir: str | Path | None = None, arch: str | None = None, quiet: bool = False) -> RunResult:
    """Run a scene to its end and write the run folder. Raises UserError (bad input) or DivergenceError
    (after writing what was recorded)."""
    from . import plots, recorders
    from .progress import Progress
    from .scene import scene_to_dict

    model = build_model(scene)
    from .scene import resolve_out_dir

    out = resolve_out_dir(scene, out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out: cannot create the run folder {out} ({exc.strerror})") from None
    if not quiet:
        for w in model.warnings:
            print(f"warning: {w}", file=sys.stderr)

    arch = arch or scene.sim.arch
    manifest = {"name": scene.name, "status": "running", "scene": scene_to_dict(scene), "versions": _versions(),
                "seed": int(scene.sim.seed), "started": datetime.now().isoformat(timespec="seconds"),
                "command": " ".join(sys.argv), "warnings": model.warnings}
    recorders.write_json(out / "manifest.json", manifest)

    wall0 = time.perf_counter()
    sim = Simulation(model, arch=arch)
    setup_wall = time.perf_counter() - wall0
    st, joints = sim.state, model.joints
    streams = []
    joints_csv = wrench_csv = mass_csv = None
    if st.machine is not None:
        header = ["t"] + [f"{j}.{k}" for j in joints for k in ("q", "qd", "q_cmd", "effort")]
        joints_csv = recorders.CsvStream(out / "joints.csv", header, scene.output.joints_rate)
        streams.append(joints_csv)
    fill_tools = []
    if st.soil is not None:
        wrench_csv = recorders.CsvStream(out / "tool_wrench.csv", ["t", "tool", "fx", "fy", "fz", "tx", "ty", "tz"],
                                         scene.output.wrench_rate)
        meshes = ([model.machine.collision_meshes[link] for link in model.machine.soil_links]
                  if model.machine is not None else []) + [tool.mesh for tool in model.tools]
        fill_tools = [(name, _hull_halfspaces(mesh)) for name, mesh in zip(st.tool_names, meshes)]
        mass_csv = recorders.CsvStream(out / "soil_mass.csv",
                                       ["t", "mass_kg", "particles_kg", "out_of_domain_kg"]
                                       + [f"in_{name}_kg" for name, _ in fill_tools], scene.output.mass_rate)
        streams += [wrench_csv, mass_csv]
        tx, ty = _terrain_axes(scene)
        recorders.write_terrain(out / "terrain_initial.npz", tx, ty, st.soil.heightmap(tx, ty), st.t)
        manifest["particles"] = int(st.soil.n_particles)
        packing = getattr(st.soil, "bed_packing", None)
        # micro.solid_density is the mapping's first guess; the settled beds' masses were scaled to the bulk density
        manifest["soil"] = {"bulk": vars(model.soil_bulk).copy(), "micro": vars(model.soil_micro).copy(),
                            "solver_version": st.soil.solver_version, "bed_packing": packing,
                            "solid_density_effective": model.soil_bulk.density / packing if packing else None,
                            "soil_dt": st.soil.dt, "substeps_per_step": int(math.ceil(model.dt / st.soil.dt - 1e-9))}
    manifest["arch"] = sim.arch
    if sim.arch == "x64":  # the soil's CPU threads (results do not depend on them; speed does)
        import taichi as ti

        manifest["cpu_threads"] = int(ti.lang.impl.current_cfg().cpu_max_num_threads)
    manifest["setup_wall_time_s"] = round(setup_wall, 3)

    def mass_in_tools() -> list[float]:
        if not fill_tools:
            return []
        parts = st.soil.particles()
        pos, mass = parts["positions"], parts.get("masses")
        out_kg = []
        for i, (name, planes) in enumerate(fill_tools):
            if st.machine is not None and i < sim.soil_link_count:
                p, q, _, _ = st.machine.link_state(name)
            else:
                p, q, _, _ = model.tools[i - sim.soil_link_count].state(st.t)
            local = (pos - p) @ _quat_to_matrix(q)
            inside = np.all(local @ planes[:, :3].T + planes[:, 3] <= 0.0, axis=1)
            out_kg.append(float(mass[inside].sum()) if mass is not None else
                          float(inside.sum() * st.soil.particle_mass))
        return out_kg

    def record() -> None:
        t = st.t
        if joints_csv is not None and joints_csv.due(t):
            q, qd, eff = st.machine.joint_states()
            cmd = sim.control_at(t).q_cmd
            row = []
            for k, j in enumerate(joints):
                row += [q[k], qd[k], cmd.get(j, q[k]), eff[k]]
            joints_csv.write(t, row)
        if wrench_csv is not None and wrench_csv.due(t):
            wrench_csv.write_rows(t, [[name] + list(st.tool_wrench[i]) for i, name in enumerate(st.tool_names)])
        if mass_csv is not None and mass_csv.due(t):
            budget = st.soil.mass_budget()
            mass_csv.write(t, [sum(budget.values()), budget["particles"], budget["out_of_domain"]] + mass_in_tools())

    duration = float(scene.sim.duration)
    n_steps = int(round(duration / model.dt))
    status, message = "done", ""
    wall_start = time.perf_counter()
    try:
        with Progress(duration, quiet=quiet) as progress:
            record()
            for k in range(n_steps):
                sim.step(sim.control_at(st.t + model.dt))
                record()
                if k % 50 == 0:
                    progress.update(st.t, time.perf_counter() - wall_start)
    except DivergenceError as exc:
        status, message = "diverged", str(exc)
        raise
    except KeyboardInterrupt as exc:
        status, message = "interrupted", str(exc) or "interrupted by the user"
        raise
    except UserError as exc:  # e.g. a soil dt problem found while running
        status, message = "bad input", str(exc)
        raise
    except Exception as exc:
        status, message = "error", f"{type(exc).__name__}: {exc}"
        raise
    finally:
        wall = time.perf_counter() - wall_start
        for s in streams:
            s.close()
        if st.soil is not None:
            tx, ty = _terrain_axes(scene)
            try:
                recorders.write_terrain(out / "terrain_final.npz", tx, ty, st.soil.heightmap(tx, ty), st.t)
                if scene.output.particles_final:
                    parts = st.soil.particles()
                    np.savez_compressed(out / "particles_final.npz", **parts)
            except Exception as exc:  # state may be non-finite after a divergence; keep the rest
                message += f" (final terrain not written: {exc})"
        manifest.update(status=status, message=message, sim_time=round(st.t, 9), wall_time_s=round(wall, 3),
                        real_time_factor=(st.t / wall) if wall > 0 else None,
                        finished=datetime.now().isoformat(timespec="seconds"))
        if st.soil is not None:
            manifest["particle_steps_per_s"] = (st.soil.n_particles * st.t / st.soil.dt / wall) if wall > 0 else None
            manifest["soil_mass_final"] = st.soil.mass_budget()
        recorders.write_json(out / "manifest.json", manifest)
        if scene.output.plots:
            _write_plots(out, joints, st, plots)
        if st.machine is not None:
            st.machine.close()
    return RunResult(out, status, st.t, wall, manifest["real_time_factor"] or 0.0,
                     int(st.soil.n_particles) if st.soil is not None else 0, message)


def _write_plots(out: Path, joints, st, plots) -> None:
    try:
        if (out / "joints.csv").is_file() and joints:
            plots.plot_joints(out / "joints.csv", joints, out / "joints.png")
        if (out / "tool_wrench.csv").is_file():
            plots.plot_tool_wrench(out / "tool_wrench.csv", out / "tool_wrench.png")
        if (out / "soil_mass.csv").is_file():
            plots.plot_soil_mass(out / "soil_mass.csv", out / "soil_mass.png")
        if (out / "terrain_initial.npz").is_file() and (out / "terrain_final.npz").is_file():
            plots.plot_terrain(dict(np.load(out / "terrain_initial.npz")), dict(np.load(out / "terrain_final.npz")),
                               out / "terrain.png")
    except Exception as exc:  # a plot must never cost the data
        print(f"warning: plots not written ({type(exc).__name__}: {exc})", file=sys.stderr)
