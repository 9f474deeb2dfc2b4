"""Observers: receive the simulation after a step, each at its own rate, and never own the loop.

An observer has a `rate` (Hz of simulated time; None = after every step) and `start`, `sample`, `close`. What it
needs to continue after a resume it returns from `get_state` (saved in each checkpoint) and takes back in
`set_state` before `start`. An observer that talks to a network subclasses ThreadedObserver: `snapshot` runs in the
simulation's thread and must be cheap, `publish` runs on the observer's own thread, and only the latest snapshot
waits there (a slow client skips snapshots, it never slows the simulation).

The run folder's files are observers too (this module); runner.py puts them together.
"""
from __future__ import annotations

import csv
import math
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from .errors import UserError
from .geometry import quat_to_matrix, quat_to_rpy
from .recorders import write_terrain


@dataclass
class RunContext:
    """What observers know about the run they record."""

    out: Path | None                         # run folder (None: no folder, e.g. the Python API)
    scene: object = None                     # the resolved Scene
    quiet: bool = False
    resumed: bool = False                    # continuing a run folder from a checkpoint
    states: dict = field(default_factory=dict)  # observer key -> state saved in the checkpoint


class Observer:
    rate: float | None = None
    closes_unstarted = False  # closed even when the run ended before it started (the manifest's status)

    @property
    def key(self) -> str:
        """Name under which the checkpoint keeps this observer's state."""
        return type(self).__name__

    def start(self, sim, run: RunContext) -> None: ...

    def sample(self, sim) -> None: ...

    def flush(self) -> None:
        """Make everything sampled so far durable (called before a checkpoint is written)."""

    def get_state(self) -> dict:
        return {}

    def set_state(self, state: dict) -> None: ...

    def close(self, sim, status: str, message: str) -> None: ...


class ThreadedObserver(Observer):
    """Latest wins: `snapshot(sim)` in the simulation's thread (None: nothing this step), `publish(snapshot)` on this
    observer's thread."""

    def snapshot(self, sim):
        raise NotImplementedError

    def publish(self, snapshot) -> None:
        raise NotImplementedError

    def start(self, sim, run: RunContext) -> None:
        self._latest = None
        self._wake = threading.Condition()
        self._stopping = False
        self.published = 0
        self.skipped = 0
        self._thread = threading.Thread(target=self._work, name=f"observer-{self.key}", daemon=True)
        self._thread.start()

    def merge(self, older, newer):
        """The snapshot that waits when `newer` comes before `older` was published: the newer (latest wins). A
        publisher of several topics at their own rates merges them (latest wins per topic)."""
        return newer

    def sample(self, sim) -> None:
        snap = self.snapshot(sim)
        if snap is None:  # nothing to publish after this step
            return
        with self._wake:
            if self._latest is not None:
                self.skipped += 1
                snap = self.merge(self._latest, snap)
            self._latest = snap
            self._wake.notify()

    def _work(self) -> None:
        while True:
            with self._wake:
                while self._latest is None and not self._stopping:
                    self._wake.wait()
                if self._latest is None and self._stopping:
                    return
                snap, self._latest = self._latest, None
            try:
                self.publish(snap)
                self.published += 1
            except Exception as exc:  # a sink's failure is logged, never the simulation's
                print(f"warning: observer {self.key}: {type(exc).__name__}: {exc}", file=sys.stderr)

    def close(self, sim, status: str, message: str) -> None:
        with self._wake:
            self._stopping = True
            self._wake.notify()
        self._thread.join(timeout=10.0)


class ObserverBus:
    """Calls each observer when its rate says it is due (half a step of tolerance, no drift)."""

    def __init__(self, observers):
        self.observers = list(observers)
        self._next = [0.0] * len(self.observers)
        self._started = 0  # how many (in order) have started
        self._period = [None] * len(self.observers)
        keys = [o.key for o in self.observers]
        for k in keys:
            if keys.count(k) > 1:
                raise ValueError(f"two observers share the key {k!r}; give one a `key` of its own")

    def start(self, sim, run: RunContext) -> None:
        self._started = 0
        for i, obs in enumerate(self.observers):
            saved = run.states.get(obs.key)
            if run.resumed and saved is not None:
                obs.set_state(saved.get("observer", {}))
                self._next[i] = float(saved.get("next_t", 0.0))
            if isinstance(obs, Checkpointer):
                obs.bus = self
            obs.start(sim, run)
            self._period[i] = None if obs.rate is None else 1.0 / float(obs.rate)  # (start may set the rate)
            self._started = i + 1
        if not run.resumed:
            self.after_step(sim)  # the initial state, at t = 0

    def after_step(self, sim) -> None:
        t = sim.t
        nxt = self._next
        for i, obs in enumerate(self.observers):
            if t + 1e-9 >= nxt[i]:
                obs.sample(sim)
                period = self._period[i]
                if period is not None:
                    nxt[i] = (math.floor(t / period + 1e-6) + 1) * period

    def flush(self) -> None:
        for obs in self.observers:
            obs.flush()

    def states(self) -> dict:
        return {obs.key: {"observer": obs.get_state(), "next_t": nxt} for obs, nxt in zip(self.observers, self._next)}

    def close(self, sim, status: str, message: str) -> None:
        interrupted = None
        for i, obs in enumerate(self.observers):
            if i >= self._started and not obs.closes_unstarted:  # one before it failed to start: nothing to close
                continue
            try:
                obs.close(sim, status, message)
            except KeyboardInterrupt as exc:  # a second Ctrl-C skips what is closing (plots...), not the manifest
                interrupted = exc
                message = f"{message}; closing interrupted: {obs.key} not closed".lstrip("; ")
                print(f"warning: {obs.key} not closed (interrupted)", file=sys.stderr)
            except Exception as exc:  # one observer's failure must not cost the others' files
                print(f"warning: {obs.key} not closed ({type(exc).__name__}: {exc})", file=sys.stderr)
        if interrupted is not None:
            raise interrupted


# ---------------------------------------------------------------------------------------------- run-folder files
def _fmt(v) -> str:
    return f"{float(v):.9g}"


def _exact(v) -> str:
    return repr(float(v))  # the shortest text that reads back as the same double


class CsvObserver(Observer):
    """A CSV file in the run folder, one row per sample (several for per-tool files), flushed as the run goes;
    a resumed run truncates it to the bytes of its checkpoint and appends."""

    FLUSH_EVERY = 200
    filename = ""
    fmt = staticmethod(_fmt)  # a number's text: 9 significant digits

    def header(self, sim) -> list[str]:
        raise NotImplementedError

    def rows(self, sim) -> list[list]:
        raise NotImplementedError

    def start(self, sim, run: RunContext) -> None:
        self.path = run.out / self.filename
        self._offset = getattr(self, "_offset", None)
        if run.resumed and self._offset is not None and self.path.is_file():
            with open(self.path, newline="", encoding="utf-8") as fh:
                header = next(csv.reader(fh), [])
            if header != self.header(sim):  # a checkpoint of another version: appending would mix two layouts
                raise UserError(f"--resume: {self.path} has the columns of another version of opera-taichi "
                                f"({len(header)}, this one writes {len(self.header(sim))}); start the run again")
            self._fh = open(self.path, "r+", newline="", encoding="utf-8")
            self._fh.truncate(self._offset)
            self._fh.seek(self._offset)
            self._writer = csv.writer(self._fh)
        else:
            self._fh = open(self.path, "w", newline="", encoding="utf-8")
            self._writer = csv.writer(self._fh)
            self._writer.writerow(self.header(sim))
        self._rows = 0

    def sample(self, sim) -> None:
        t = _fmt(sim.t)
        fmt = self.fmt
        for row in self.rows(sim):
            self._writer.writerow([t] + [v if isinstance(v, str) else fmt(v) for v in row])
        self._rows += 1
        if self._rows % self.FLUSH_EVERY == 0:
            self._fh.flush()

    def flush(self) -> None:
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def get_state(self) -> dict:
        return {"offset": self._fh.tell()}

    def set_state(self, state: dict) -> None:
        self._offset = state.get("offset")

    def close(self, sim, status, message) -> None:
        if not self._fh.closed:
            self._fh.close()


class JointsCsv(CsvObserver):
    """joints.csv: per joint q, qd, q_cmd (the applied position target; NaN in velocity mode), qd_cmd (the motor's
    speed command) and effort; then, for a machine on tracks (fixed_base false), its base_link pose. Columns are
    `<joint>.q` and `base.x` for one machine, `<machine>.<joint>.q` and `<machine>.base.x` for several."""

    filename = "joints.csv"

    def __init__(self, rate: float):
        self.rate = rate
        self._yaw: dict[str, float] = {}   # the last yaw written per machine on tracks: the column is unwrapped

    def header(self, sim) -> list[str]:
        return csv_columns(sim.model)[self.filename]

    def rows(self, sim):
        row = []
        for m in sim.machines.values():
            q, qd, effort, cmd, speed = m._q, m._qd, m._effort, m.applied_targets, m._speed_cmd
            for k in range(len(q)):
                row += [q[k], qd[k], cmd[k], speed[k], effort[k]]
        for m in sim.model.machines:
            if not m.fixed_base:
                xyz, quat = sim.machines[m.name].base_pose()
                roll, pitch, yaw = quat_to_rpy(quat)
                last = self._yaw.get(m.name)
                if last is not None:  # continuous through +-pi, so a turn reads as one (means, plots, studies)
                    yaw = last + math.remainder(yaw - last, 2.0 * math.pi)
                self._yaw[m.name] = yaw
                row += [*xyz, roll, pitch, yaw]
        return [row]

    def get_state(self) -> dict:
        return {**super().get_state(), "yaw": dict(self._yaw)}

    def set_state(self, state: dict) -> None:
        super().set_state(state)
        self._yaw = {k: float(v) for k, v in state.get("yaw", {}).items()}


# m and rad (fixed-axis), base_link in the world; yaw is unwrapped (it goes on past +-pi as the machine turns)
BASE_POSE_COLUMNS = ("x", "y", "z", "roll", "pitch", "yaw")


def joint_columns(model) -> list[str]:
    """The machines' joints as joints.csv names them: `<joint>`, or `<machine>.<joint>` for several machines."""
    several = len(model.machines) > 1
    return [f"{m.name}.{j}" if several else j for m in model.machines for j in m.description.actuated_joints]


def csv_columns(model) -> dict[str, list[str]]:
    """The header of each CSV file a run of this model writes (a study checks its metrics against them)."""
    out = {}
    if model.machines:
        several = len(model.machines) > 1
        out[JointsCsv.filename] = ["t"] + [f"{c}.{k}" for c in joint_columns(model)
                                           for k in ("q", "qd", "q_cmd", "qd_cmd", "effort")] + \
            [f"{m.name + '.' if several else ''}base.{k}" for m in model.machines if not m.fixed_base
             for k in BASE_POSE_COLUMNS]
    if model.soil is not None:
        out[WrenchCsv.filename] = ["t", "tool", "fx", "fy", "fz", "tx", "ty", "tz"]
        out[SoilMassCsv.filename] = ["t", "mass_kg", "particles_kg", "out_of_domain_kg"] + \
            [f"in_{b.name}_kg" for b in model.bindings]
    return out


class WrenchCsv(CsvObserver):
    """tool_wrench.csv: t, tool, fx, fy, fz, tx, ty, tz: the soil's force and torque on each tool."""

    filename = "tool_wrench.csv"

    def __init__(self, rate: float):
        self.rate = rate

    def header(self, sim):
        return csv_columns(sim.model)[self.filename]

    def rows(self, sim):
        return [[b.name] + list(sim.tool_wrench[i]) for i, b in enumerate(sim.model.bindings)]


def hull_halfspaces(mesh) -> np.ndarray:
    """(n, 4) plane equations of the convex hull of a tool mesh: inside when n.x + d <= 0 for all.
    The hull of an open bucket is its struck volume and the wedge between its opening and its highest points (a
    ZX120's pin lugs), where a heaped load sits."""
    hull = mesh.convex_hull
    normals = hull.face_normals
    d = -np.einsum("ij,ij->i", normals, hull.triangles[:, 0, :])
    return np.hstack([normals, d[:, None]])


_HULL_SPHERES: dict[int, tuple] = {}


def _hull_sphere(mesh) -> tuple[np.ndarray, float]:
    """A sphere (link frame) holding the mesh's convex hull: the hull test runs only on the grains inside it."""
    entry = _HULL_SPHERES.get(id(mesh))
    if entry is None or entry[0] is not mesh:
        v = np.asarray(mesh.convex_hull.vertices, dtype=np.float64)
        centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        entry = _HULL_SPHERES[id(mesh)] = (mesh, centre, float(np.linalg.norm(v - centre, axis=1).max()) * (1 + 1e-9))
    return entry[1], entry[2]


def inside_tools(sim, planes: list[np.ndarray], positions: np.ndarray) -> list[np.ndarray]:
    """Per tool (binding order), a mask of the positions inside its convex hull now."""
    out = []
    for i, hull in enumerate(planes):
        p, q, _, _ = sim.tool_pose(i)
        rot = quat_to_matrix(q)
        centre, radius = _hull_sphere(sim.model.bindings[i].mesh)
        near = np.nonzero(np.sum((positions - (p + rot @ centre)) ** 2, axis=1) <= radius * radius)[0]
        mask = np.zeros(len(positions), bool)
        local = (positions[near] - p) @ rot
        mask[near] = np.all(local @ hull[:, :3].T + hull[:, 3] <= 0.0, axis=1)
        out.append(mask)
    return out


def mass_in_tools(sim, planes: list[np.ndarray]) -> list[float]:
    """Soil mass (kg) whose centres lie inside each tool's convex hull (binding order)."""
    parts = sim.soil.particles(("positions", "masses"))
    return [float(parts["masses"][m].sum()) for m in inside_tools(sim, planes, parts["positions"])]


def carried_by_tools(sim, positions: np.ndarray, reach: float = 0.0) -> np.ndarray:
    """Grains a tool carries: inside its convex hull, or heaped on it (above its lowest point, within its outline
    seen from above, or within `reach` of it: a grain resting on the rim has its centre a radius outside). Soil
    under a tool, or beside it, is not carried."""
    from scipy.spatial import ConvexHull

    carried = np.zeros(len(positions), bool)
    for i, b in enumerate(sim.model.bindings):
        p, q, _, _ = sim.tool_pose(i)
        hull = b.mesh.convex_hull.vertices @ quat_to_matrix(q).T + p
        above = np.nonzero(positions[:, 2] > hull[:, 2].min())[0]
        if len(above):
            outline = ConvexHull(hull[:, :2])
            carried[above[_within_polygon(positions[above, :2], outline, reach)]] = True
    return carried


def _within_polygon(xy: np.ndarray, outline, reach: float) -> np.ndarray:
    """Which points lie inside a convex outline (scipy ConvexHull in 2-D) or within `reach` of its edges."""
    inside = np.all(xy @ outline.equations[:, :2].T + outline.equations[:, 2] <= 0.0, axis=1)
    if reach > 0.0:
        corners = outline.points[outline.vertices]           # (counter-clockwise)
        near = np.nonzero(~inside & np.all((xy >= corners.min(axis=0) - reach) & (xy <= corners.max(axis=0) + reach),
                                           axis=1))[0]        # (only these can be within reach: a big bed's others)
        a, edge = corners, np.roll(corners, -1, axis=0) - corners
        rel = xy[near, None, :] - a[None, :, :]               # each point against each edge's start
        s = np.clip(np.einsum("ped,ed->pe", rel, edge) / np.einsum("ed,ed->e", edge, edge), 0.0, 1.0)
        gap = np.linalg.norm(rel - s[..., None] * edge[None, :, :], axis=2).min(axis=1)
        inside[near[gap <= reach]] = True
    return inside


def in_flight(velocities: np.ndarray, radii: np.ndarray, gravity: float = 9.81) -> np.ndarray:
    """Grains faster than a fall of one diameter gives (sqrt(2 g 2r): 1.8 m/s at 8 cm): spilling from a bucket or
    thrown, not resting on the ground; soil creeping or flowing down a heap is slower."""
    return np.einsum("ij,ij->i", velocities, velocities) > 4.0 * gravity * np.asarray(radii)


def ground_and_all_heightmaps(sim, planes: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(z, z_all) on the model's terrain grid: soil resting on the ground (what tools carry and the grains in flight
    left out, so a loaded bucket over the trench, or the soil spilling from it, is not read as a heap), and every
    grain."""
    grid, soil = sim.model.soil.grid, sim.soil
    z_all = soil.heightmap(grid.x, grid.y)
    parts = soil.particles(("positions", "velocities", "radii"))
    away = in_flight(parts["velocities"], parts["radii"], float(sim.model.gravity))
    if sim.model.bindings:
        away |= carried_by_tools(sim, parts["positions"], reach=float(np.max(parts["radii"], initial=0.0)))
    if not np.any(away):
        return z_all, z_all
    return soil.heightmap(grid.x, grid.y, exclude=away), z_all


class SoilMassCsv(CsvObserver):
    """soil_mass.csv: t, mass_kg, particles_kg, out_of_domain_kg, in_<tool>_kg (mass inside each tool's hull)."""

    filename = "soil_mass.csv"
    fmt = staticmethod(_exact)  # every digit: the mass balance holds to round-off in the file too

    def __init__(self, rate: float):
        self.rate = rate

    def header(self, sim):
        self._planes = [hull_halfspaces(b.mesh) for b in sim.model.bindings]
        return csv_columns(sim.model)[self.filename]

    def start(self, sim, run):
        self._planes = [hull_halfspaces(b.mesh) for b in sim.model.bindings]
        super().start(sim, run)

    def rows(self, sim):
        budget = sim.soil.mass_budget()
        return [[sum(budget.values()), budget["particles"], budget["out_of_domain"]] + mass_in_tools(sim, self._planes)]


class TerrainNpz(Observer):
    """terrain_initial.npz at the start, terrain_final.npz at the end (and particles_final.npz when asked)."""

    rate = 1e-9  # only the initial sample; the final one is written at close

    def __init__(self, particles_final: bool = False):
        self.particles_final = particles_final

    def start(self, sim, run):
        self.out = run.out
        self.planes = [hull_halfspaces(b.mesh) for b in sim.model.bindings]
        if not run.resumed:
            self._write(sim, "terrain_initial.npz")

    def _write(self, sim, name):
        grid = sim.model.soil.grid
        z, z_all = ground_and_all_heightmaps(sim, self.planes)
        write_terrain(self.out / name, grid.x, grid.y, z, sim.t, z_all=z_all)

    def close(self, sim, status, message):
        self._write(sim, "terrain_final.npz")
        if self.particles_final:
            np.savez_compressed(self.out / "particles_final.npz", **sim.soil.particles())


class Checkpointer(Observer):
    """checkpoints/step-<n>.ckpt.npz every `every` simulated seconds, with every other observer's state; the
    newest `keep` are kept."""

    def __init__(self, every: float, keep: int = 2):
        self.rate = 1.0 / float(every)
        self.keep = keep
        self.bus: ObserverBus | None = None   # set by the bus

    def start(self, sim, run):
        self.dir = run.out / "checkpoints"
        self.dir.mkdir(exist_ok=True)
        self._first = not run.resumed

    def sample(self, sim):
        if self._first:  # t = 0 needs no checkpoint: a run killed before the first one starts again
            self._first = False
            return
        self.bus.flush()
        states = {k: v for k, v in self.bus.states().items() if k != self.key}
        sim.save_checkpoint(self.dir / f"step-{sim.step_count:09d}.ckpt.npz", extra={"observers": states})
        for old in sorted(self.dir.glob("step-*.ckpt.npz"))[:-self.keep]:
            old.unlink(missing_ok=True)


def latest_checkpoint(run_dir: Path) -> Path | None:
    found = sorted((Path(run_dir) / "checkpoints").glob("step-*.ckpt.npz"))
    return found[-1] if found else None


class Heartbeat(Observer):
    """Keeps manifest.json's `heartbeat` (wall clock) fresh while the run goes, every `interval` wall seconds, so a
    run whose process died can be told from one still running."""

    def __init__(self, manifest, interval: float = 5.0):
        self.manifest, self.interval = manifest, interval
        self._last = time.monotonic()

    def sample(self, sim):
        now = time.monotonic()
        if now - self._last >= self.interval:
            self._last = now
            self.manifest.beat(sim)


def now_iso() -> str:
    return datetime.now().isoformat(timespec="seconds")
