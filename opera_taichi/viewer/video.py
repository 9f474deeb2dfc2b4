"""`view RUN_DIR --mp4 FILE`: the replay rendered offscreen to an H.264 video for slides and papers.

matplotlib's 3-D axes (Agg, no display) draw the machines' visual meshes (posed with yourdfpy's forward kinematics
from the recorded joints and base pose, shaded by a fixed light) and the soil particles coloured as in the browser
view (height); matplotlib's FFMpegWriter encodes with the ffmpeg binary that the imageio-ffmpeg wheel ships.
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
from .view import load_visual_urdf

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
            world = (vertices @ T[:3, :3].T + T[:3, 3]) @ r_base.T + p_base
            tri = world[faces]
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-12
            shade = 0.45 + 0.55 * np.abs(normal @ LIGHT)
            tris.append(tri)
            cols.append(np.clip(rgb[None, :3] / 255.0 * shade[:, None], 0, 1))
        return np.concatenate(tris), np.concatenate(cols)


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
    fps = 1.0 / float(np.median(np.diff(reader.times))) if len(reader) > 1 else 10.0

    dpi = 100
    fig = plt.figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
    ax = fig.add_axes([0, 0, 1, 1], projection="3d")
    c = info.centre()
    lo = np.minimum(info.domain_min, [-3.0, -3.0, -1.5])
    hi = np.maximum(info.domain_max[:2], [3.0, 3.0])
    x_range, y_range = (lo[0] - 0.5, hi[0] + 0.5), (c[1] - 4.0, c[1] + 4.0)
    z_range = (min(lo[2], -1.2), 5.0)
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
                for name, mm in machines:
                    state = frame.machines.get(name)
                    if state is None:
                        continue
                    tris, cols = mm.triangles(state["q"], state["base"])
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
