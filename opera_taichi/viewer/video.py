"""`view RUN_DIR --mp4 FILE`: the replay rendered offscreen to an H.264 video for slides and papers.

matplotlib's 3-D axes (Agg, no display) draw the machines' visual meshes (posed with yourdfpy's forward kinematics
from the recorded joints and base pose, shaded by a fixed light), the standalone tools (posed as recorded) and the
soil particles coloured as in the browser view (height), in axes that hold all of them over the whole replay; matplotlib's FFMpegWriter encodes with the ffmpeg binary that the imageio-ffmpeg wheel ships.
One frame per recorded frame, played at the recording rate (real time).
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..geometry import quat_to_matrix
from . import colors
from .replay import open_run
from .view import TOOL_RGB, load_visual_urdf

MAX_FACES = 4000        # per mesh: matplotlib sorts polygons in Python, so a dense mesh is drawn as its hull
LIGHT = np.array([0.3, -0.6, 0.75]) / np.linalg.norm([0.3, -0.6, 0.75])


def _ffmpeg() -> str:
    try:
        import imageio_ffmpeg
    except ImportError:
        raise UserError("--mp4 needs imageio-ffmpeg: pip install -e '.[viewer]'") from None
    return imageio_ffmpeg.get_ffmpeg_exe()


class _MachineMesh:
    """A machine's visual meshes in their URDF frames, posed per frame into world triangles and colours."""

    def __init__(self, urdf_path: str, joints: list[str]):
        import trimesh

        self.urdf = load_visual_urdf(urdf_path)
        names = list(self.urdf.actuated_joint_names)
        self.index = [names.index(j) if j in names else -1 for j in joints]
        self.n = len(names)
        self.parts = []
        for node in self.urdf.scene.graph.nodes_geometry:
            _, geom_name = self.urdf.scene.graph[node]
            mesh = self.urdf.scene.geometry[geom_name]
            if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
                continue
            if len(mesh.faces) > MAX_FACES:
                mesh = mesh.convex_hull
                rgb = np.array(colors_of(self.urdf.scene.geometry[geom_name]))
            else:
                rgb = np.array(colors_of(mesh))
            self.parts.append((node, np.asarray(mesh.vertices, float), np.asarray(mesh.faces), rgb))

    def triangles(self, q: np.ndarray, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cfg = np.zeros(self.n)
        for j, k in enumerate(self.index):
            if k >= 0:
                cfg[k] = q[j]
        self.urdf.update_cfg(cfg)
        r_base, p_base = quat_to_matrix(base[3:]), base[:3]
        tris, cols = [], []
        for node, vertices, faces, rgb in self.parts:
            T = self.urdf.scene.graph.get(node)[0]
            tri = ((vertices @ T[:3, :3].T + T[:3, 3]) @ r_base.T + p_base)[faces]
            tris.append(tri)
            cols.append(_shaded(tri, rgb))
        return np.concatenate(tris), np.concatenate(cols)


class _ToolMesh:
    """A standalone tool (one no machine carries, e.g. the validation's blade), posed per frame as recorded."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import trimesh

        mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces), process=False)
        if len(mesh.faces) > MAX_FACES:
            mesh = mesh.convex_hull
        self.vertices, self.faces = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)

    def triangles(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tri = (self.vertices @ quat_to_matrix(pose[3:]).T + pose[:3])[self.faces]
        return tri, _shaded(tri, np.array(TOOL_RGB))


def _shaded(tri: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """Face colours (0-1) of world triangles lit by the fixed light, either side alike."""
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-12
    shade = 0.45 + 0.55 * np.abs(normal @ LIGHT)
    return np.clip(rgb[None, :3] / 255.0 * shade[:, None], 0, 1)


def _meshes(frame, machines, tools):
    """Every machine's and standalone tool's (triangles, colours) in a frame."""
    for name, mm in machines:
        state = frame.machines.get(name)
        if state is not None:
            yield mm.triangles(state["q"], state["base"])
    for i, tm in tools:
        if i < len(frame.tool_poses):
            yield tm.triangles(frame.tool_poses[i])


def _extent(reader, info, machines, tools, samples: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Axes limits that hold the soil's domain and every machine and tool over the replay (a few frames sampled:
    a machine far from the bed, or one that drives away, stays in the picture)."""
    lo = np.minimum(info.domain_min, [np.inf, np.inf, -1.2])
    hi = np.array(info.domain_max, float)
    for i in np.unique(np.linspace(0, len(reader) - 1, min(samples, len(reader))).astype(int)):
        for tris, _ in _meshes(reader.frame(int(i)), machines, tools):
            lo = np.minimum(lo, tris.reshape(-1, 3).min(axis=0))
            hi = np.maximum(hi, tris.reshape(-1, 3).max(axis=0))
    return lo - 0.5, hi + 0.5


def colors_of(mesh) -> tuple:
    """The mesh's main colour (RGB 0-255)."""
    try:
        c = mesh.visual.main_color
    except Exception:
        c = (237, 140, 25, 255)
    return tuple(int(v) for v in c[:3])


def write_mp4(run_dir, out, quiet: bool = False, size=(1280, 720)) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import animation
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    reader = open_run(run_dir)
    out = Path(out)
    if out.is_dir():
        raise UserError(f"--mp4: {out} is a folder; give a file name such as run.mp4")
    matplotlib.rcParams["animation.ffmpeg_path"] = _ffmpeg()
    info = reader.info
    machines = [(m.name, _MachineMesh(m.urdf, m.joints)) for m in info.machines]
    tools = [(i, _ToolMesh(t.vertices, t.faces)) for i, t in enumerate(info.tools) if t.owner is None]
    fps = 1.0 / float(np.median(np.diff(reader.times))) if len(reader) > 1 else 10.0

    dpi = 100
    fig = plt.figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
    ax = fig.add_axes([0, 0, 1, 1], projection="3d")
    lo, hi = _extent(reader, info, machines, tools)
    x_range, y_range, z_range = (lo[0], hi[0]), (lo[1], hi[1]), (lo[2], hi[2])
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:   # a file where the folder should be, a folder it may not write
        raise UserError(f"--mp4: cannot write {out} ({type(exc).__name__}: {exc.strerror or exc})") from None
    writer = animation.FFMpegWriter(fps=fps, codec="libx264", extra_args=["-pix_fmt", "yuv420p"])
    r = float(np.median(info.radii)) if info.n_particles else 0.05
    points_per_m = 0.6 * size[0] * 72 / dpi / (x_range[1] - x_range[0])   # marker size: about a grain's diameter
    try:
        with writer.saving(fig, str(out), dpi):
            for i in range(len(reader)):
                frame = reader.frame(i)
                ax.cla()
                ax.set_xlim(*x_range)
                ax.set_ylim(*y_range)
                ax.set_zlim(*z_range)
                ax.set_box_aspect((x_range[1] - x_range[0], y_range[1] - y_range[0], z_range[1] - z_range[0]))
                ax.view_init(elev=18, azim=-70)
                ax.set_xlabel("x (m)")
                ax.set_ylabel("y (m)")
                ax.set_zlabel("z (m)")
                if info.n_particles:
                    rgb = colors.colorize("height", info, frame) / 255.0
                    p = frame.positions
                    ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=rgb, s=(2 * r * points_per_m) ** 2, depthshade=False,
                               linewidths=0)
                for tris, cols in _meshes(frame, machines, tools):
                    ax.add_collection3d(Poly3DCollection(tris, facecolors=cols, edgecolors="none"))
                ax.set_title(f"{info.name}   t = {frame.t:5.2f} s", loc="left")
                writer.grab_frame()
    except (OSError, subprocess.CalledProcessError) as exc:   # ffmpeg could not write (a bad path, a full disk)
        raise UserError(f"--mp4: cannot write {out} ({type(exc).__name__}: {' '.join(str(exc).split())})") \
            from None
    finally:
        plt.close(fig)
    if not quiet:
        print(f"{out} ({len(reader)} frames at {fps:g} fps)", file=sys.stderr)
    return out
