"""What the viewer shows, as data: the run's fixed description (SceneInfo) and one Frame per shown instant, taken
from a Simulation (live view, replay recorder) or read back from a replay file. No viser here: recording a replay
needs numpy only."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry import quat_to_matrix


@dataclass
class MachineInfo:
    name: str
    urdf: str                    # the URDF the user named (visual meshes as authored)
    joints: list[str]            # actuated joints, in the order of Frame.machines[name]["q"]
    limits: list[tuple[float, float]]   # (lower, upper) rad per joint, for teleop sliders


@dataclass
class ToolInfo:
    name: str
    owner: str | None            # machine name; None for a standalone tool
    link: str | None
    vertices: np.ndarray         # (V, 3) float32, tool frame
    faces: np.ndarray            # (F, 3) int32

    def hull_planes(self) -> np.ndarray:
        """(n, 4) half-spaces of the mesh's convex hull (inside: n.x + d <= 0), the struck volume of a bucket."""
        import trimesh

        from ..observers import hull_halfspaces

        return hull_halfspaces(trimesh.Trimesh(self.vertices, self.faces, process=False))


@dataclass
class SceneInfo:
    """What does not change during a run."""

    name: str
    duration: float
    machines: list[MachineInfo]
    tools: list[ToolInfo]                     # soil tools in binding order (tool_wrench order)
    domain_min: np.ndarray                    # (3,) m
    domain_max: np.ndarray
    beds: list[tuple[list[float], list[float]]]
    radii: np.ndarray                         # (N,) float32, m
    masses: np.ndarray                        # (N,) float32, kg
    initial_positions: np.ndarray             # (N, 3) float32, m (displacement is measured from here)
    _planes: list | None = field(default=None, repr=False)

    @property
    def n_particles(self) -> int:
        return int(len(self.radii))

    def planes(self) -> list[np.ndarray]:
        if self._planes is None:
            self._planes = [t.hull_planes() for t in self.tools]
        return self._planes

    def bucket_index(self) -> int | None:
        """The tool shown as 'the bucket': the first machine-bound soil tool, else the first tool."""
        for i, t in enumerate(self.tools):
            if t.owner is not None:
                return i
        return 0 if self.tools else None

    def centre(self) -> np.ndarray:
        """Middle of the machines and the soil beds on the ground: what the cameras look at."""
        points = [np.asarray(b[0], float) for b in self.beds] + [np.asarray(b[1], float) for b in self.beds]
        if not points:
            points = [self.domain_min, self.domain_max]
        lo, hi = np.min(points, axis=0), np.max(points, axis=0)
        return np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.0])


@dataclass
class Frame:
    t: float                                  # simulated time, s
    wall: float                               # wall-clock seconds since the run's loop started
    machines: dict                            # name -> {"q": (J,), "q_cmd": (J,) (NaN: speed mode), "base": (7,)}
    tool_poses: np.ndarray                    # (n_tools, 7): position, quaternion (x, y, z, w)
    tool_wrench: np.ndarray                   # (n_tools, 6): soil on tool, world frame
    positions: np.ndarray                     # (N, 3) float32
    speeds: np.ndarray                        # (N,) float32, m/s


def scene_info(sim) -> SceneInfo:
    """The fixed description of a running Simulation."""
    machines = []
    for name, m in sim.machines.items():
        lo, hi = m.joint_limits
        machines.append(MachineInfo(name, str(m.desc.urdf_path), list(m.joint_names),
                                    [(float(a), float(b)) for a, b in zip(lo, hi)]))
    tools = [ToolInfo(b.name, b.owner, b.link, np.asarray(b.mesh.vertices, np.float32),
                      np.asarray(b.mesh.faces, np.int32)) for b in sim.model.bindings]
    soil = sim.model.soil
    if sim.soil is not None:
        parts = sim.soil.particles()
        radii, masses, pos = parts["radii"], parts["masses"], parts["positions"]
        domain_min, domain_max = np.asarray(soil.domain_min, float), np.asarray(soil.domain_max, float)
        beds = [(list(b[0]), list(b[1])) for b in soil.beds]
    else:
        radii = masses = np.zeros(0)
        pos = np.zeros((0, 3))
        domain_min, domain_max = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0])
        beds = []
    return SceneInfo(sim.model.name, float(sim.model.duration), machines, tools, domain_min, domain_max, beds,
                     radii.astype(np.float32), masses.astype(np.float32), pos.astype(np.float32))


def capture(sim, wall: float) -> Frame:
    """The simulation now, copied (cheap: one copy of the particle arrays, no per-particle Python)."""
    machines = {}
    for name, m in sim.machines.items():
        pos, quat = m.base_pose()
        machines[name] = {"q": m.joint_states()[0], "q_cmd": m.applied_targets, "base": np.concatenate([pos, quat])}
    poses = np.zeros((len(sim.model.bindings), 7))
    for i in range(len(poses)):
        p, q, _, _ = sim.tool_pose(i)
        poses[i, :3], poses[i, 3:] = p, q
    if sim.soil is not None:
        parts = sim.soil.particles()
        positions = parts["positions"].astype(np.float32)
        speeds = np.linalg.norm(parts["velocities"], axis=1).astype(np.float32)
    else:
        positions, speeds = np.zeros((0, 3), np.float32), np.zeros(0, np.float32)
    return Frame(float(sim.t), float(wall), machines, poses, np.array(sim.tool_wrench, float).reshape(-1, 6),
                 positions, speeds)


# ---------------------------------------------------------------------------------------------- derived
def tool_masks(info: SceneInfo, frame: Frame, machine_only: bool = True) -> list[np.ndarray | None]:
    """Per tool (binding order), the mask of the particles whose centres are inside its convex hull (None for a
    standalone tool when machine_only). Only the grains inside the hull's bounding box meet its planes."""
    out: list[np.ndarray | None] = []
    for i, planes in enumerate(info.planes()):
        tool = info.tools[i]
        if machine_only and tool.owner is None:
            out.append(None)
            continue
        p, q = frame.tool_poses[i, :3], frame.tool_poses[i, 3:]
        local = (frame.positions - p) @ quat_to_matrix(q)
        lo, hi = tool.vertices.min(axis=0), tool.vertices.max(axis=0)
        near = np.flatnonzero(np.all((local >= lo) & (local <= hi), axis=1))
        mask = np.zeros(len(local), bool)
        if len(near):
            mask[near] = np.all(local[near] @ planes[:, :3].T + planes[:, 3] <= 0.0, axis=1)
        out.append(mask)
    return out


def in_tools(info: SceneInfo, frame: Frame, masks: list | None = None) -> np.ndarray:
    """Mask of the particles inside any machine-bound tool's hull (what a bucket carries)."""
    masks = tool_masks(info, frame) if masks is None else masks
    out = np.zeros(len(frame.positions), bool)
    for m in masks:
        if m is not None:
            out |= m
    return out


def bucket_mass(info: SceneInfo, frame: Frame, masks: list | None = None) -> float:
    """Soil mass (kg) inside the bucket's hull."""
    k = info.bucket_index()
    if k is None or len(frame.positions) != info.n_particles:
        return float("nan")
    mask = (tool_masks(info, frame, machine_only=False) if masks is None else masks)[k]
    if mask is None:
        mask = tool_masks(info, frame, machine_only=False)[k]
    return float(info.masses[mask].sum())


def bucket_force(info: SceneInfo, frame: Frame) -> float:
    """|F| (N) of the soil on the bucket."""
    k = info.bucket_index()
    return float(np.linalg.norm(frame.tool_wrench[k, :3])) if k is not None and len(frame.tool_wrench) else 0.0


def surface(info: SceneInfo, positions: np.ndarray, exclude: np.ndarray | None = None, cell: float | None = None):
    """Terrain heightmap from the particles: on cells of about a grain's diameter, the top (z + r) of the highest
    grain in each cell, or the static ground (0, the pit floor inside a bed) where a cell holds none; grains in
    `exclude` (carried by a tool) are left out. Returns the node axes x (nx,), y (ny,) and z (nx, ny)."""
    r = float(np.median(info.radii)) if info.n_particles else 0.1
    cell = cell or 2.0 * r
    lo, hi = info.domain_min, info.domain_max
    nx, ny = max(2, int(np.ceil((hi[0] - lo[0]) / cell))), max(2, int(np.ceil((hi[1] - lo[1]) / cell)))
    x = lo[0] + (np.arange(nx) + 0.5) * cell
    y = lo[1] + (np.arange(ny) + 0.5) * cell
    gx, gy = np.meshgrid(x, y, indexing="ij")
    ground = np.zeros((nx, ny))
    for b_min, b_max in reversed(info.beds):   # the first bed wins where footprints touch, as in the soil
        inside = (gx >= b_min[0]) & (gx <= b_max[0]) & (gy >= b_min[1]) & (gy <= b_max[1])
        ground[inside] = b_min[2]
    z = np.full((nx, ny), -np.inf)
    if len(positions) and len(positions) == info.n_particles:
        keep = np.ones(len(positions), bool) if exclude is None else ~exclude
        p = positions[keep]
        ix = np.clip(((p[:, 0] - lo[0]) / cell).astype(int), 0, nx - 1)
        iy = np.clip(((p[:, 1] - lo[1]) / cell).astype(int), 0, ny - 1)
        np.maximum.at(z, (ix, iy), p[:, 2] + info.radii[keep])
        # a cell between grains holds no centre: it takes its neighbours' top (gaps bridged, a dug trench stays)
        from scipy.ndimage import maximum_filter

        z = np.where(np.isfinite(z), z, maximum_filter(z, size=3, mode="nearest"))
    return x, y, np.where(np.isfinite(z), np.maximum(z, ground), ground)


def grid_mesh(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (nx*ny, 3) and triangles of a heightmap on the node axes x, y."""
    nx, ny = len(x), len(y)
    gx, gy = np.meshgrid(x, y, indexing="ij")
    vertices = np.stack([gx.ravel(), gy.ravel(), z.ravel()], axis=1).astype(np.float32)
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    return vertices, faces
