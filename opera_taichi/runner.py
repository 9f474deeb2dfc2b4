"""run_scene: drive a scene to its end and write its run folder. The whole loop is

    while sim.step_count < n_steps:
        sim.step(controller.control(sim, sim.t_next))
        bus.after_step(sim)

controllers in, observers out: the files of the run folder, the manifest's heartbeat, the progress bar,
checkpoints, and whatever the caller adds (a ROS bridge, a viewer) are observers; a bridge or a script is the
controller. Adding either changes nothing here.
"""
from __future__ import annotations

import json
import math
import os
import platform
import shutil
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import __version__
from .control import ScriptController, as_controller, driver_of
from .errors import DivergenceError, UserError
from .model import build_model
from .observers import (Checkpointer, Heartbeat, JointsCsv, Observer, ObserverBus, RunContext, SoilMassCsv,
                        TerrainNpz, WrenchCsv, joint_columns, latest_checkpoint, now_iso)
from .recorders import write_json
from .simulation import Simulation, read_checkpoint_header


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


class Manifest(Observer):
    """manifest.json: written when the run starts, kept fresh by the heartbeat, closed with the run's status."""

    rate = 1e-9
    closes_unstarted = True

    def __init__(self, path: Path, data: dict):
        self.path, self.data = path, data

    def write(self) -> None:
        write_json(self.path, self.data)

    def beat(self, sim) -> None:
        self.data.update(heartbeat=now_iso(), sim_time=round(sim.t, 9))
        self.write()

    def close(self, sim, status, message) -> None:
        self.data.update(status=status, message=message, finished=now_iso(), heartbeat=now_iso())
        self.data.pop("status_before_resume", None)
        if sim is not None and sim.warnings:  # with what the observers closed before it said (a bridge's lost peer)
            self.data["run_warnings"] = list(sim.warnings)
        self.write()


class ProgressBar(Observer):
    """Simulated time, real-time factor and ETA; the pace is measured from the end of the first step, so the
    kernels' compilation (a phase of its own) does not count."""

    def __init__(self, progress):
        self._bar = progress

    def start(self, sim, run):
        self.rate = 1.0 / (50 * sim.model.dt)
        self._t0, self._wall0 = None, None
        self._bar.phase("compiling the soil kernels" if sim.soil is not None else "starting")

    def sample(self, sim):
        if self._t0 is None:
            if sim.step_count == 0:
                return
            self._t0, self._wall0 = sim.t, time.perf_counter()
            self._bar.begin_run(sim.t)
        self._bar.update(sim.t, time.perf_counter() - self._wall0, start=self._t0)

    def close(self, sim, status, message):
        if self._wall0 is not None:
            self._bar.update(sim.t, time.perf_counter() - self._wall0, start=self._t0, final=True)


def _soil_block(sim) -> dict:
    block = sim.soil.describe()
    block["bulk"] = vars(sim.model.soil.bulk).copy()
    block["substeps_per_step"] = int(math.ceil(sim.model.dt / sim.soil.dt - 1e-9))
    block["wedges"] = [b.name for b in sim.model.bindings if b.cutting_edge is not None]  # tools cutting with one
    return block


def _new_manifest(scene, model) -> dict:
    from .scene import scene_to_dict

    return {"name": scene.name, "status": "running", "scene": scene_to_dict(scene), "versions": _versions(),
            "seed": int(scene.sim.seed), "started": now_iso(), "heartbeat": now_iso(), "pid": os.getpid(),
            "pid_start": process_start(os.getpid()), "host": socket.gethostname(), "command": " ".join(sys.argv),
            "warnings": list(model.warnings), "machines": [m.name for m in model.machines]}


def _engine_block(sim) -> dict:
    data = {"arch": sim.arch}
    if sim.soil is not None:
        data["particles"] = int(sim.soil.n_particles)
        data["soil"] = _soil_block(sim)
    if sim.arch == "x64":  # the soil's CPU threads (results do not depend on them; speed does)
        import taichi as ti

        data["cpu_threads"] = int(ti.lang.impl.current_cfg().cpu_max_num_threads)
        data["spin_wait_helpers"] = sim.spin_wait_helpers
    return data


def default_observers(scene, sim, manifest: Manifest, quiet: bool, progress) -> list[Observer]:
    """The run folder's own observers; closed in this order (the manifest last, with the final status)."""
    out = [Heartbeat(manifest)]
    if sim.machines:
        out.append(JointsCsv(scene.output.joints_rate))
    if sim.soil is not None:
        out += [WrenchCsv(scene.output.wrench_rate), SoilMassCsv(scene.output.mass_rate),
                TerrainNpz(scene.output.particles_final)]
    if scene.output.plots:
        out.append(Plots())
    if scene.output.bag is not None:  # run.mcap / run.bag: the ROS topics (ros/bag.py)
        from .ros.bag import BagObserver

        out.append(BagObserver(scene.output.bag, scene.bridge))
    if scene.output.replay:  # replay.bin: frames for `view RUN_DIR` (viewer/replay.py; numpy only)
        from .viewer.replay import ReplayRecorder

        out.append(ReplayRecorder(scene.output.replay_rate))
    out += [ProgressBar(progress), manifest, Summary(quiet)]
    return out


def claim_run_folder(scene, out_dir, *, overwrite: bool = False, resume: bool = False) -> Path:
    """The run folder, made ready: never another run's folder unless overwrite (emptied first) or resume.
    Without out_dir: output.dir, else runs/<name>-<time>, with -2, -3 ... so two runs never share one."""
    from .scene import resolve_out_dir

    explicit = out_dir is not None or scene.output.dir is not None
    out = resolve_out_dir(scene, out_dir)
    key = "--out" if out_dir is not None else "output.dir"
    if resume:
        return out
    holder = next((p for p in Path(out).resolve().parents if is_run_folder(p)), None)
    if holder is not None:  # its --overwrite would delete this run, `runs` would not list it
        raise UserError(f"{key}: {out} lies inside the run folder {holder}; give a folder outside it")
    if not explicit:
        base, k = out, 1
        while True:
            try:
                out.mkdir(parents=True, exist_ok=False)
                return out
            except FileExistsError:
                k += 1
                out = base.with_name(f"{base.name}-{k}")
            except OSError as exc:
                raise UserError(f"cannot create the run folder {out} ({exc.strerror})") from None
    if out.exists() and not out.is_dir():
        raise UserError(f"{key}: {out} is a file, not a folder")
    if (out / "manifest.json").is_file():
        try:
            status, manifest = run_folder_status(out)
        except UserError:
            status, manifest = "unreadable", {}
        if not overwrite:
            raise UserError(f"{key}: {out} holds a run already (status {status}); use --overwrite to replace it, "
                            f"--resume {out} to continue it, or another folder")
        if status == "running":  # emptied under it, its files and the new run's would mix
            raise UserError(f"--overwrite: {out} is still running (pid {manifest.get('pid')}); stop it first")
        for item in out.iterdir():
            shutil.rmtree(item) if item.is_dir() and not item.is_symlink() else item.unlink()
    elif out.is_dir() and any(out.iterdir()):
        raise UserError(f"{key}: {out} is not empty and holds no run; give a new or empty folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{key}: cannot create the run folder {out} ({exc.strerror})") from None
    return out


class Plots(Observer):
    """The PNGs, drawn from the closed run folder's files when the run ends."""

    rate = 1e-9

    def start(self, sim, run):
        self.out = run.out

    def close(self, sim, status, message):
        density = sim.model.soil.bulk.density if sim.model.soil is not None else None
        write_plots(self.out, joint_columns(sim.model), _limits(sim), density)


class Summary(Observer):
    """summary.json when the run ends (soil in each tool, dug and heaped volume, forces, actuator saturation,
    real-time factor, mass balance), printed unless quiet."""

    rate = 1e-9

    def __init__(self, quiet: bool):
        self.quiet = quiet

    def start(self, sim, run):
        self.out = run.out

    def close(self, sim, status, message):
        from .summary import format_summary, write_summary

        summary = write_summary(self.out, sim.model)
        if not self.quiet:
            print(format_summary(summary))


def _limits(sim) -> dict:
    several = len(sim.machines) > 1
    out = {}
    for name, m in sim.machines.items():
        for j in m.joint_names:
            act = m.desc.actuators[j]
            out[f"{name}.{j}" if several else j] = (act.max_speed, act.max_torque)
    return out


def steps_to_cover(duration: float, dt: float) -> int:
    """Rigid steps a run of `duration` takes: a whole number of steps as such (float noise aside, 0.3 / 0.1 is 3),
    else one more, so the run never ends short of its duration (0.025 s at dt 0.01: 3 steps, to 0.03 s)."""
    x = duration / dt
    n = round(x)
    return max(1, n if abs(x - n) <= 1e-9 * max(1.0, x) else math.ceil(x))


def run_scene(scene, out_dir: str | Path | None = None, arch: str | None = None, quiet: bool = False, *,
              controller=None, observers=(), checkpoint_every: float | None = None, resume: bool = False,
              overwrite: bool = False) -> RunResult:
    """Run a scene to its end and write the run folder. `controller` replaces the scene's motion scripts;
    `observers` are added to the run folder's own. With resume=True, out_dir is a run folder to continue from its
    newest checkpoint. Raises UserError (bad input) or DivergenceError (after writing what was recorded)."""
    from .progress import Progress

    controller = as_controller(controller)  # (a wrong one refused before any folder or kernel)
    if not hasattr(scene, "sim"):  # a path: load it as `run` does
        from .scene import load_scene

        scene = load_scene(scene)
    model = build_model(scene)
    out = claim_run_folder(scene, out_dir, overwrite=overwrite, resume=resume)
    scene.output.dir = out  # the manifest's resolved scene names the folder actually written
    if not quiet and not resume:
        for w in model.warnings:
            print(f"warning: {w}", file=sys.stderr)
    arch = arch or scene.sim.arch
    record_before = None  # a resume's manifest as it was: put back if the resume fails before its checkpoint loads
    if resume:
        record_before = (out / "manifest.json").read_bytes()
        previous, data = run_folder_status(out)
        driven = data.get("driver", "script")
        if driven != "script" and driver_of(controller) == "script":
            raise UserError(f"--resume: {out} was driven by {driven}, not its scene's motion script; resume it with "
                            f"that driver (a ROS bridge: --ros1 or --ros-tcp; the sliders: --view; Python: "
                            f"run_scene(..., controller=..., resume=True))")
        data["driver"] = driver_of(controller)  # what drives it from here (a later resume checks against it)
        manifest = Manifest(out / "manifest.json", data)
        manifest.data.update(status="running", pid=os.getpid(), pid_start=process_start(os.getpid()),
                             host=socket.gethostname(), heartbeat=now_iso(),
                             status_before_resume=previous)
    else:
        manifest = Manifest(out / "manifest.json", _new_manifest(scene, model))
        manifest.data["driver"] = driver_of(controller)
    if checkpoint_every is not None:
        manifest.data["checkpoint_every"] = float(checkpoint_every)
    manifest.write()

    status, message, sim, bus = "done", "", None, None
    wall0 = time.perf_counter()
    wall_start = wall0
    t_start = 0.0
    try:
        with Progress(float(scene.sim.duration), quiet=quiet) as progress:
            ckpt = latest_checkpoint(out) if resume else None
            if resume and ckpt is None:
                raise UserError(f"--resume: {out} has no checkpoint (run it with --checkpoint-every SECONDS)")
            progress.phase("preparing: machine, soil bed (poured and settled once, then cached), kernels")
            sim = Simulation(model, arch=arch, build_beds=ckpt is None, quiet=quiet,
                             on_settle=progress.settling, spin_wait=scene.sim.spin_wait)
            states = {}
            if resume:
                states = sim.load_checkpoint(ckpt).get("observers", {})
                record_before = None  # from here on the folder is this process's to record
                manifest.data.setdefault("resumed", []).append(
                    {"at": now_iso(), "from_checkpoint": ckpt.name, "sim_time": sim.t, "pid": os.getpid(),
                     "previous_status": manifest.data.get("status_before_resume", "running")})
            else:
                manifest.data.update(_engine_block(sim))
            manifest.data["setup_wall_time_s"] = round(time.perf_counter() - wall0, 3)
            manifest.write()

            controller = controller or ScriptController(model)
            # a caller's observers (a bridge, a view: what talks to a network) start first: one that cannot start
            # ends the run before the run folder's files do
            parts = list(observers) + default_observers(scene, sim, manifest, quiet, progress)
            every = checkpoint_every if checkpoint_every is not None else manifest.data.get("checkpoint_every")
            if every:
                parts.append(Checkpointer(float(every)))  # last: it saves the others' states after they sampled
            bus = ObserverBus(parts)
            run = RunContext(out=out, scene=scene, quiet=quiet, resumed=resume, states=states)
            n_steps = steps_to_cover(float(scene.sim.duration), model.dt)
            t_start = sim.t
            wall_start = time.perf_counter()
            bus.start(sim, run)
            # the observers' start (a view's server, a bridge's connection) is set-up, not stepping
            manifest.data["setup_wall_time_s"] = round(time.perf_counter() - wall0, 3)
            wall_start = time.perf_counter()
            while sim.step_count < n_steps:
                sim.step(controller.control(sim, sim.t_next))
                bus.after_step(sim)
    except DivergenceError as exc:
        status, message = "diverged", str(exc)
        raise
    except KeyboardInterrupt as exc:
        status, message = "interrupted", str(exc) or "interrupted by the user"
        raise
    except UserError as exc:  # e.g. a bed that does not fit, found while building the soil
        status, message = "bad input", str(exc)
        raise
    except BaseException as exc:
        status, message = "error", f"{type(exc).__name__}: {exc}"
        raise
    finally:
        if record_before is not None:
            # the resume failed before its checkpoint loaded (another scene's checkpoint, no GPU, Ctrl-C while it
            # set up): nothing of the run changed, so its record stays as it was
            (out / "manifest.json").write_bytes(record_before)
            if sim is not None:
                sim.close()
        else:
            wall = time.perf_counter() - wall_start
            done = (sim.t - t_start) if sim is not None else 0.0
            # wall time and real-time factor are this process's: a resumed run's simulated time so far is sim_time,
            # of which this process ran sim_time_this_run_s
            manifest.data.update(sim_time=round(sim.t, 9) if sim is not None else 0.0, wall_time_s=round(wall, 3),
                                 sim_time_this_run_s=round(done, 9),
                                 real_time_factor=(done / wall) if wall > 0 and done > 0 else None)
            if sim is not None and sim.soil is not None:
                manifest.data["particle_steps_per_s"] = (sim.soil.n_particles * done / sim.soil.dt / wall) \
                    if wall > 0 else None
                manifest.data["soil_mass_final"] = sim.soil.mass_budget()
            if sim is not None and sim.warnings:
                manifest.data["run_warnings"] = list(sim.warnings)
            try:
                if bus is not None:
                    bus.close(sim, status, message)
                else:
                    manifest.close(sim, status, message)
            finally:
                if sim is not None:
                    sim.close()
    return RunResult(out, status, sim.t, wall, manifest.data["real_time_factor"] or 0.0,
                     int(manifest.data.get("particles") or 0), message)


def write_plots(out: Path, joints, limits=None, density=None) -> None:
    from . import plots

    def sampled(name: str) -> bool:  # a header and at least one row (a run that ended at once has none)
        try:
            with open(out / name, "rb") as fh:
                return sum(1 for _ in zip(range(2), fh)) == 2
        except OSError:
            return False

    try:
        if sampled("joints.csv") and joints:
            plots.plot_joints(out / "joints.csv", joints, out / "joints.png", limits=limits)
        if sampled("tool_wrench.csv"):
            plots.plot_tool_wrench(out / "tool_wrench.csv", out / "tool_wrench.png")
        if sampled("soil_mass.csv"):
            plots.plot_soil_mass(out / "soil_mass.csv", out / "soil_mass.png", density=density)
        if (out / "terrain_initial.npz").is_file() and (out / "terrain_final.npz").is_file():
            plots.plot_terrain(dict(np.load(out / "terrain_initial.npz")), dict(np.load(out / "terrain_final.npz")),
                               out / "terrain.png")
    except Exception as exc:  # a plot must never cost the data
        print(f"warning: plots not written ({type(exc).__name__}: {exc})", file=sys.stderr)


# ---------------------------------------------------------------------------------------------- resume
def process_alive(pid) -> bool:
    if not isinstance(pid, int) or isinstance(pid, bool) or not 0 < pid < 2 ** 31:
        return False  # (0 and -1 would ask about a process group; no process has such a pid)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def process_start(pid: int) -> str | None:
    """When the kernel started the process (Linux: /proc/PID/stat's starttime, clock ticks since boot), so that a
    pid the system gave to another process after the run's died is not taken for the run; None elsewhere."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (OSError, ValueError):
        return None
    fields = stat.rsplit(")", 1)[-1].split()  # after the command name, which may hold spaces and parentheses
    return fields[19] if len(fields) > 19 else None  # field 22 of proc(5); the split starts at field 3


def is_run_folder(folder: Path) -> bool:
    """Whether the folder holds a run's manifest (not another tool's manifest.json)."""
    try:
        manifest = json.loads((folder / "manifest.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(manifest, dict) and "status" in manifest and "scene" in manifest


def run_folder_status(run_dir: Path) -> tuple[str, dict]:
    """('done' | 'running' | 'died' | 'diverged' | ..., manifest): `died` is a manifest that says running whose
    process is gone (killed, out of memory, power loss)."""
    path = Path(run_dir) / "manifest.json"
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"--resume: {run_dir} is not a run folder (no manifest.json)") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"--resume: {path}: unreadable manifest ({exc})") from None
    if not isinstance(manifest, dict):
        raise UserError(f"--resume: {path}: unreadable manifest (not a JSON object)")
    status = manifest.get("status", "unknown")
    if status == "running":
        same_host = manifest.get("host") in (None, socket.gethostname())
        pid = manifest.get("pid")
        if same_host and not (process_alive(pid) and _same_process(pid, manifest.get("pid_start"))):
            status = "died"
    return status, manifest


def _same_process(pid: int, recorded_start) -> bool:
    if recorded_start is None:
        return True  # a manifest written before the start time was recorded, or off Linux: the pid alone
    now = process_start(pid)
    return now is None or now == recorded_start


def resume_scene(run_dir: Path):
    """The resolved scene a run folder was started with, to continue it."""
    from pydantic import ValidationError

    from .scene import Scene

    status, manifest = run_folder_status(run_dir)
    if status == "running":
        raise UserError(f"--resume: {run_dir} is still running (pid {manifest.get('pid')} on "
                        f"{manifest.get('host')}); stop it first")
    if status == "done":
        raise UserError(f"--resume: {run_dir} finished already (status done); nothing to resume")
    ckpt = latest_checkpoint(run_dir)
    if ckpt is None:
        every = manifest.get("checkpoint_every")
        why = (f"it stopped at {manifest.get('sim_time', 0):g} s, before its first checkpoint (every {every:g} s)"
               if isinstance(every, (int, float)) else "it was run without --checkpoint-every")
        raise UserError(f"--resume: {run_dir} ({status}) has no checkpoint to resume from; {why}")
    read_checkpoint_header(ckpt)
    data = dict(manifest["scene"])
    try:
        scene = Scene.model_validate(data, context={"base_dir": Path(run_dir).resolve(), "source": None})
    except ValidationError as exc:
        raise UserError(f"--resume: {run_dir}/manifest.json: its scene no longer loads "
                        f"({' '.join(str(exc).split())[:200]})") from None
    return scene, status, ckpt
