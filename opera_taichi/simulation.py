"""The coupled simulation: a Model (what does not change), the engines that hold the State (what does), and one
`step(control)`.

One step (DESIGN.md):
  1. the Control's commands go to the machines' actuators (clipped to the joint limits; what was applied is state);
  2. the rigid world advances one step with the soil wrench of the previous step applied to each soil-touching link;
  3. the poses and velocities of the bound links and standalone tools go to the soil solver;
  4. the soil takes its substeps with the tools kinematic and returns the averaged wrench per tool.
Controllers give the Control; observers read the state after the step (runner.py drives both).
"""
from __future__ import annotations

import contextlib
import json
import os
import sys
import zipfile
from pathlib import Path

import numpy as np

from .control import Control, as_control
from .errors import DivergenceError, UserError
from .model import Model, build_model, check_scene, soil_parameters  # noqa: F401  (the public names live here too)
from .recorders import json_default
from .state import MachineState, State

CHECKPOINT_SUFFIX = ".ckpt.npz"


class Simulation:
    """Owns the engines (a rigid world with its machines, a soil solver) for one Model.

    Several simulations live side by side in one process: each owns its PyBullet client and its soil arrays;
    Taichi is started once (backend.init_taichi)."""

    def __init__(self, model: Model, arch: str = "cpu", *, build_beds: bool = True, quiet: bool = False,
                 on_settle=None, spin_wait: bool | str = False):
        self.model = model
        self.quiet = quiet
        self.arch = None
        self.step_count = 0
        self.t = 0.0
        self.rng = np.random.default_rng(model.seed)
        self.applied: Control = Control({}, 0.0, "initial")
        self.warnings: list[str] = []
        self.world = None
        self.machines: dict = {}
        if model.machines:
            from .rigid import RigidWorld

            self.world = RigidWorld(dt=model.dt, gravity=model.gravity)
            for m in model.machines:
                self.machines[m.name] = self.world.add_machine(
                    m.description, name=m.name, base_xyz=m.base_xyz, base_yaw=m.base_yaw, fixed_base=m.fixed_base,
                    initial_q=m.initial_q, warn=self._warn)
        self.soil = None
        self._spin = None  # the spin-wait helpers (sim.spin_wait), shared by the process
        self.tool_wrench = np.zeros((0, 6))
        self._hull_planes = None  # each soil tool's convex hull as half-spaces (soil_in_tools)
        self._bound: list = []
        if model.soil is not None:
            from .backend import init_taichi
            from .soil_solver import solver_class

            self.arch = init_taichi(arch)
            self.soil = solver_class(model.soil.solver).from_model(model.soil, build_beds=build_beds,
                                                                   on_settle=on_settle)
            for text in getattr(self.soil, "warnings", ()):
                self._warn(text)
            for binding in model.bindings:
                index = self.soil.add_tool(binding.name, binding.mesh)
                edge = binding.cutting_edge
                if edge is not None:
                    if not hasattr(self.soil, "set_cutting_edge"):
                        raise UserError(f"tools.{binding.name}.cutting_edge: the {model.soil.solver} soil has no "
                                        f"soil wedge (a DEM soil has)")
                    key = None
                    if binding.owner is not None:
                        key = f"machine {binding.owner}: cutting_edges.{binding.link}"
                    self.soil.set_cutting_edge(index, edge.centre, edge.face_normal, edge.face_up, edge.width, key,
                                               opening=edge.opening)
            for tool in model.tools:
                if tool.cutting_edge is not None:
                    self._check_edge_acts(tool)
            self.tool_wrench = np.zeros((len(model.bindings), 6))
            # (machine, link) of each machine-bound tool, in soil tool order; standalone tools follow
            self._bound = [(self.machines[b.owner], b.link) for b in model.bindings if b.owner is not None]
            self._push_tool_states()
            from .spin_wait import spin_wait as helpers, wanted

            if self.arch in ("x64", "arm64") and wanted(spin_wait):  # (a GPU's threads are not the pool's)
                import taichi as ti

                self._spin = helpers(int(ti.lang.impl.current_cfg().cpu_max_num_threads))
            warm_up = getattr(self.soil, "warm_up", None)  # (optional for a solver: compiles, runs nothing)
            if warm_up is not None:
                warm_up(model.dt)

    def _check_edge_acts(self, tool) -> None:
        """A standalone tool keeps its orientation and velocity: say so when its wedge can never act."""
        from .geometry import quat_to_matrix

        rot = quat_to_matrix(np.asarray(tool.quat_xyzw, dtype=float))
        edge = tool.cutting_edge
        normal, up = rot @ np.asarray(edge.face_normal, float), rot @ np.asarray(edge.face_up, float)
        if not float(np.dot(tool.velocity, normal)) > 0.0:
            self._warn(f"tools.{tool.name}.cutting_edge: the tool never moves into its face (velocity . face_normal "
                       f"<= 0 in the world), so its soil wedge never acts and the grains push on it alone")
        elif not up[2] > 0.0:
            self._warn(f"tools.{tool.name}.cutting_edge: face_up points down in the tool's pose (the face does not "
                       f"rise from the edge), so its soil wedge never acts and the grains push on it alone")

    @classmethod
    def from_scene(cls, scene, overrides: dict | list | None = None, arch: str | None = None,
                   quiet: bool = True) -> "Simulation":
        """A simulation of a scene file (or a loaded Scene), with `--set`-style overrides given as a dict
        {"soil.overrides.radius": 0.12} or a list of "key.path=value" strings."""
        from .scene import load_scene, naming_the_scene

        path = None
        if not hasattr(scene, "sim"):
            path, scene = scene, load_scene(scene, overrides or ())
        elif overrides:
            raise ValueError("overrides go with a scene file path; a loaded Scene already has its values")
        with naming_the_scene(path) if path is not None else contextlib.nullcontext():
            sim = cls(build_model(scene), arch=arch or scene.sim.arch, quiet=quiet, spin_wait=scene.sim.spin_wait)
        sim.scene = scene
        return sim

    # ------------------------------------------------------------------------------------------ properties
    @property
    def machine_names(self) -> list[str]:
        return list(self.machines)

    @property
    def t_next(self) -> float:
        """The time the next step ends at, as step() computes it ((steps + 1) dt, not t + dt, which rounds
        differently): the t a controller is asked for, `controller.control(sim, sim.t_next)`."""
        return (self.step_count + 1) * self.model.dt

    @property
    def spin_wait_helpers(self) -> int:
        """How many processes keep the other cores running while this simulation steps (sim.spin_wait)."""
        return len(self._spin.processes) if self._spin is not None else 0

    @property
    def machine(self):
        """The only machine (BulletMachine), or None."""
        if len(self.machines) > 1:
            raise AttributeError("the scene has several machines: use sim.machines[name]")
        return next(iter(self.machines.values()), None)

    @property
    def state(self) -> State:
        """The state without the soil's arrays (cheap: for control loops); get_state() copies everything."""
        return self.get_state(soil=False)

    def _warn(self, text: str) -> None:
        if text not in self.warnings:
            self.warnings.append(text)
            if not self.quiet:
                print(f"warning: {text}", file=sys.stderr)

    # ------------------------------------------------------------------------------------------ step
    def _push_tool_states(self) -> None:
        soil, i = self.soil, 0
        for machine, link in self._bound:
            soil.set_tool_state(i, *machine.link_state(link))
            i += 1
        for tool in self.model.tools:
            soil.set_tool_state(i, *tool.pose_twist(self.t))
            i += 1

    def apply(self, control: Control) -> None:
        """Give each machine its commands (clipped to its limits); joints not named keep their last command."""
        for name, mc in control.machines.items():
            machine = self.machines.get(name)
            if machine is None:
                raise UserError(f"control: no machine {name!r} in this scene (machines: "
                                f"{', '.join(self.machines) or 'none'})")
            machine.command(mc.q_target, mc.qd_target, mc.track_speeds, mc.hold)
        self.applied = control

    def step(self, control=None) -> None:
        """Advance by one rigid step (model.dt) under `control` (a Control, a {joint: rad} dict for the only
        machine, or None to keep the last commands)."""
        if getattr(self, "_closed", False):
            raise RuntimeError("the simulation was closed")
        if self._spin is not None:
            self._spin.touch()
        t_next = self.t_next
        self.apply(as_control(control, self.machine_names, t_next))
        if self.world is not None:
            for i, (machine, link) in enumerate(self._bound):
                w = self.tool_wrench[i]
                machine.apply_link_wrench(link, w[:3], w[3:])
            self.world.step()
            for machine in self.machines.values():
                if not (np.all(np.isfinite(machine._q)) and np.all(np.isfinite(machine._qd))):
                    raise DivergenceError(f"machine {machine.name} diverged at t = {t_next:.4f} s: "
                                          f"non-finite joint state")
        self.step_count += 1
        self.t = t_next
        if self.soil is not None:
            self._push_tool_states()
            self.tool_wrench = self.soil.advance(self.model.dt)

    # ------------------------------------------------------------------------------------------ state
    def get_state(self, soil: bool = True) -> State:
        """A copy of everything that changes. soil=False, for control loops, leaves out the soil's arrays and
        Bullet's contact caches: set back, such a state goes on exactly only where no machine stands on tracks."""
        return State(t=self.t, step=self.step_count,
                     machines={name: m.get_state() for name, m in self.machines.items()},
                     soil=self.soil.get_state() if (soil and self.soil is not None) else None,
                     tool_wrench=self.tool_wrench.copy(),
                     control=Control.from_dict(self.applied.to_dict()), rng=self.rng.bit_generator.state,
                     model=self.model.fingerprint,
                     rigid=self.world.save_state() if soil and self.world is not None else None)

    def set_state(self, state: State) -> None:
        """Put a State back; the simulation then goes on exactly as the one it was taken from."""
        # every check before anything is set: a refused state leaves the simulation as it was
        if state.model is not None and state.model != self.model.fingerprint:
            raise ValueError(f"the state was taken from another model (another scene, grain size or step: model "
                             f"{state.model}, this one {self.model.fingerprint})")
        if set(state.machines) != set(self.machines):
            raise ValueError(f"the state's machines {sorted(state.machines)} are not this model's "
                             f"{sorted(self.machines)}")
        for name, ms in state.machines.items():
            if list(ms.joints) != self.machines[name].joint_names:
                raise ValueError(f"machine {name}: the state's joints {list(ms.joints)} are not this machine's "
                                 f"{self.machines[name].joint_names}")
            for key in ("q", "qd", "effort", "q_target", "qd_target", "velocity_mode", "speed_cmd"):
                if np.shape(getattr(ms, key)) != (len(ms.joints),):
                    raise ValueError(f"machine {name}: the state's {key} has shape {np.shape(getattr(ms, key))}, "
                                     f"expected ({len(ms.joints)},), one value per joint")
        if np.size(state.tool_wrench) != self.tool_wrench.size:
            raise ValueError(f"the state's tool_wrench has shape {np.shape(state.tool_wrench)}, expected "
                             f"{self.tool_wrench.shape}, a row per tool")
        if self.soil is not None and state.soil is None:
            raise ValueError("the state carries no soil arrays (taken with get_state(soil=False))")
        if self.soil is not None:
            self.soil.set_state(state.soil)  # (refuses another solver layout before it writes anything)
        for name, ms in state.machines.items():
            self.machines[name].set_state(ms)
        if state.rigid is not None and self.world is not None:
            self.world.restore_state(state.rigid)  # after the machines' resets, which would clear its contacts
            for name, ms in state.machines.items():  # a pose edited into the state wins over the saved world's
                if not self.machines[name].in_world(ms):
                    self.machines[name].set_state(ms)
        self.step_count, self.t = int(state.step), float(state.t)
        self.tool_wrench = np.array(state.tool_wrench, dtype=np.float64).reshape(-1, 6)
        self.applied = Control.from_dict(state.control.to_dict()) if state.control is not None \
            else Control({}, self.t, "restored")
        if state.rng is not None:
            self.rng.bit_generator.state = state.rng
        if self.soil is not None:
            self._push_tool_states()

    def save_checkpoint(self, path, extra: dict | None = None) -> Path:
        """Write the whole state to one .npz file, atomically (a crash leaves the old file or the new one)."""
        return save_checkpoint(path, self.get_state(), self.model, self.soil, extra)

    def load_checkpoint(self, path) -> dict:
        """Set the state from a checkpoint file; refused with a UserError when it belongs to another model or
        solver version. Returns the checkpoint's extra data (the run's observers keep theirs there)."""
        state, extra = load_checkpoint(path, self.model, self.soil)
        self.set_state(state)
        return extra

    # ------------------------------------------------------------------------------------------ outputs
    def observe(self) -> dict:
        """What a controller or an agent sees now, as numbers: time, each machine's joints (q, qd, effort,
        q_cmd), each tool's wrench (soil on tool, world frame) and the soil mass budget."""
        if getattr(self, "_closed", False):
            raise RuntimeError("the simulation was closed")
        out = {"t": self.t, "machines": {}, "tools": {}}
        for name, m in self.machines.items():
            q, qd, effort = m.joint_states()
            out["machines"][name] = {"joints": list(m.joint_names), "q": q, "qd": qd, "effort": effort,
                                     "q_cmd": m.applied_targets, "hold": m._hold}
        for i, b in enumerate(self.model.bindings):
            out["tools"][b.name] = self.tool_wrench[i].copy()
        if self.soil is not None:
            out["soil_mass"] = self.soil.mass_budget()
        return out

    def soil_in_tools(self) -> dict[str, float]:
        """Soil mass (kg) whose grain centres lie inside each soil tool's convex hull, by tool name: what
        soil_mass.csv's `in_<tool>_kg`, summary.json's `soil_held_kg` and the gym env's `bucket_mass` read. A bucket's
        hull is its struck volume and the wedge above the opening up to its pin lugs (the ZX120's: 0.38 and 0.15
        m3), so a load heaped over the opening within that wedge counts, and soil heaped beyond the hull does not;
        while the bucket is buried, the bed soil in that wedge counts too."""
        from .observers import hull_halfspaces, mass_in_tools

        if getattr(self, "_closed", False):
            raise RuntimeError("the simulation was closed")
        names = [b.name for b in self.model.bindings]
        if self.soil is None or not names:
            return {name: 0.0 for name in names}
        if self._hull_planes is None:
            self._hull_planes = [hull_halfspaces(b.mesh) for b in self.model.bindings]
        return dict(zip(names, mass_in_tools(self, self._hull_planes)))

    def tool_pose(self, i: int):
        """Pose and twist of soil tool i (binding order) now."""
        b = self.model.bindings[i]
        if b.owner is not None:
            return self.machines[b.owner].link_state(b.link)
        tool = self.model.tools[i - len(self._bound)]
        return tool.pose_twist(self.t)

    def close(self) -> None:
        """Free the engines (the PyBullet client, the soil's arrays); the simulation cannot step after it."""
        if self.world is not None:
            self.world.close()
            self.world = None
        self.machines, self.soil, self._closed = {}, None, True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ---------------------------------------------------------------------------------------------- checkpoints
def save_checkpoint(path, state: State, model: Model, soil, extra: dict | None = None) -> Path:
    from . import __version__

    path = Path(path)
    header = {"format": "opera-taichi checkpoint", "opera_taichi": __version__, "model": model.fingerprint,
              "solver": None if soil is None else [soil.name, soil.version], "t": state.t, "step": state.step,
              "machines": sorted(state.machines), "control": None if state.control is None else state.control.to_dict(),
              "rng": state.rng, "extra": extra or {}}
    arrays = {"header": np.array(json.dumps(header, default=json_default))}
    arrays["tool_wrench"] = state.tool_wrench
    if state.rigid is not None:
        arrays["rigid"] = np.frombuffer(state.rigid, dtype=np.uint8)
    for name, ms in state.machines.items():
        for key, value in ms.arrays().items():
            arrays[f"machine/{name}/{key}"] = value
    for key, value in (state.soil or {}).items():
        arrays[f"soil/{key}"] = value
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)
    return path


def read_checkpoint_header(path) -> dict:
    try:
        with np.load(path, allow_pickle=False) as f:
            return json.loads(str(f["header"]))
    except OSError as exc:
        raise UserError(f"{path}: cannot read the checkpoint ({exc.strerror or exc})") from None
    except (KeyError, ValueError, EOFError, zipfile.BadZipFile):  # (NumPy's reason, e.g. its pickle refusal, misleads)
        raise UserError(f"{path}: not an opera-taichi checkpoint (an .npz written by save_checkpoint or "
                        f"run --checkpoint-every)") from None


def load_checkpoint(path, model: Model, soil) -> tuple[State, dict]:
    header = read_checkpoint_header(path)
    if header.get("model") != model.fingerprint:
        raise UserError(f"{path}: the checkpoint belongs to another scene or checkpoint format (model "
                        f"{header.get('model')}, this scene {model.fingerprint}); resume it with the scene it was "
                        f"written by")
    want = None if soil is None else [soil.name, soil.version]
    if header.get("solver") != want:
        raise UserError(f"{path}: written by soil solver {header.get('solver')}, this build has {want}; "
                        f"a checkpoint resumes only with the solver version that wrote it")
    with np.load(path, allow_pickle=False) as f:
        machines: dict[str, dict] = {}
        soil_arrays: dict[str, np.ndarray] = {}
        for key in f.files:
            if key.startswith("machine/"):
                _, name, field_ = key.split("/", 2)
                machines.setdefault(name, {})[field_] = f[key]
            elif key.startswith("soil/"):
                soil_arrays[key[5:]] = f[key]
        tool_wrench = f["tool_wrench"]
        rigid = f["rigid"].tobytes() if "rigid" in f.files else None
    state = State(t=float(header["t"]), step=int(header["step"]),
                  machines={k: MachineState.from_arrays(v) for k, v in machines.items()},
                  soil=soil_arrays or None, tool_wrench=tool_wrench,
                  control=None if header.get("control") is None else Control.from_dict(header["control"]),
                  rng=_rng_state(header.get("rng")), model=header.get("model"), rigid=rigid)
    return state, header.get("extra") or {}


def _rng_state(data):
    if data is None:
        return None
    state = dict(data)
    inner = state.get("state")
    if isinstance(inner, dict):
        state["state"] = {k: int(v) for k, v in inner.items()}
    return state


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def run_scene(*args, **kwargs):
    """Run a scene to its end and write the run folder (see runner.run_scene)."""
    from .runner import run_scene as _run

    return _run(*args, **kwargs)


def __getattr__(name):  # RunResult moved to runner.py
    if name == "RunResult":
        from .runner import RunResult

        return RunResult
    raise AttributeError(name)
