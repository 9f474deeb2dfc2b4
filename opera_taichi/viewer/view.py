"""The 3-D scene and side panel in viser, shared by the live view, the replay server and the HTML export:
the machines from their URDFs (visual meshes as authored: ours, OPERA's COLLADA), posed from a Frame; the soil as
points coloured by a chosen quantity with a colour bar; the terrain surface; each tool's soil force as an arrow;
standalone tools; a ground grid with metre ticks; the panel with the run's figures, plots and view controls."""
from __future__ import annotations

import collections
import threading
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..geometry import quat_to_matrix
from . import colors
from .frames import Frame, SceneInfo, bucket_force, bucket_mass, grid_mesh, in_tools, surface, tool_masks

MACHINE_RGBA = (237, 140, 25, 255)     # an untextured white mesh (OPERA's COLLADA has no texture file) shows orange
TOOL_RGB = (120, 120, 130)
TERRAIN_RGB = (170, 140, 100)
FORCE_RGB = (220, 30, 30)
FORCE_SCALE = 5e-5                     # m of arrow per N of soil force: 1 m per 20 kN
PRESETS = ("side", "machine", "top")
JOINT_COLOURS = ("#1f77b4", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#7f7f7f")
HISTORY = 600                           # samples in the live plots (a minute at 10 Hz)


def require_viser():
    try:
        import viser  # noqa: F401
    except ImportError:
        raise UserError("the 3-D view needs viser: pip install -e '.[viewer]' (or pip install 'opera-taichi[viewer]')"
                        ) from None
    return viser


def load_visual_urdf(path):
    """A machine's URDF with its visual meshes, mesh URIs resolved as the simulator resolves them (package://,
    relative, file://)."""
    import trimesh
    import yourdfpy

    from ..machine_description import _MeshCache

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: the machine's URDF is not there (the run names it; view the run where its machine "
                        f"files are)")
    cache = _MeshCache(path)
    try:
        urdf = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=True,
                                  build_collision_scene_graph=False, load_collision_meshes=False,
                                  filename_handler=lambda fname: str(cache._find(fname, "visual")))
    except UserError:
        raise
    except Exception as exc:  # yourdfpy / trimesh raise many kinds for an unreadable file
        raise UserError(f"{path}: cannot load the machine's visual meshes ({type(exc).__name__}: "
                        f"{' '.join(str(exc).split())})") from None
    for name, mesh in list(urdf.scene.geometry.items()):
        if not isinstance(mesh, trimesh.Trimesh):
            continue
        material = getattr(mesh.visual, "material", None)
        image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        if mesh.visual.kind == "texture" and image is None:
            colour = np.asarray(getattr(material, "main_color", [255, 255, 255, 255]))
            if np.all(colour[:3] > 240):
                mesh.visual = trimesh.visual.ColorVisuals(mesh, face_colors=MACHINE_RGBA)
    return urdf


def _wxyz(quat_xyzw) -> tuple:
    x, y, z, w = (float(v) for v in quat_xyzw)
    return (w, x, y, z)


class History:
    """The plotted series: time, joint angles (actual, commanded) in degrees, bucket force in kN."""

    def __init__(self, joints: list[str], maxlen: int | None = HISTORY):
        self.joints = joints
        self.rows = collections.deque(maxlen=maxlen)

    def append(self, t: float, q: np.ndarray, q_cmd: np.ndarray, force: float) -> None:
        cmd = np.where(np.isfinite(q_cmd), q_cmd, q)  # a joint in speed mode has no commanded angle: show its own
        self.rows.append(np.concatenate([[t], np.degrees(q), np.degrees(cmd), [force / 1e3]]))

    def clear(self) -> None:
        self.rows.clear()

    def arrays(self) -> np.ndarray:
        if not self.rows:
            return np.zeros((0, 2 + 2 * len(self.joints)))
        return np.array(self.rows)


class SceneView:
    """Everything shown for one run; `show(frame)` poses it. `panel=False` builds the 3-D scene only (HTML export,
    where a label carries the figures)."""

    def __init__(self, server, info: SceneInfo, *, panel: bool = True, title: str = ""):
        from viser.extras import ViserUrdf

        self.server, self.info, self.panel = server, info, panel
        self.lock = threading.RLock()
        self.quantity = "height"
        self.radius = float(np.median(info.radii)) if info.n_particles else 0.05
        self.point_size = 2.0 * self.radius
        self.show_terrain = False
        self.status = "starting"
        self.last: Frame | None = None
        self.peak_force = 0.0
        self._rtf_window: collections.deque = collections.deque(maxlen=30)
        scene = server.scene
        scene.set_up_direction("+z")

        self.machines = {}
        for m in info.machines:
            root = scene.add_frame(f"/machine/{m.name}", show_axes=False)
            urdf = ViserUrdf(server, load_visual_urdf(m.urdf), root_node_name=f"/machine/{m.name}")
            names = list(urdf.get_actuated_joint_names())
            index = [names.index(j) if j in names else -1 for j in m.joints]
            self.machines[m.name] = (root, urdf, index, len(names))

        self.tool_frames = {}
        for i, t in enumerate(info.tools):
            if t.owner is None:   # a machine's tools are its URDF links, shown with it
                frame = scene.add_frame(f"/tools/{t.name}", show_axes=False)
                scene.add_mesh_simple(f"/tools/{t.name}/mesh", t.vertices, t.faces, color=TOOL_RGB)
                self.tool_frames[i] = frame
        self.centroids = [t.vertices.mean(axis=0) if len(t.vertices) else np.zeros(3) for t in info.tools]
        self.arrows = [scene.add_arrows(f"/forces/{t.name}", points=np.zeros((1, 2, 3), np.float32),
                                        colors=FORCE_RGB, shaft_radius=0.04, head_radius=0.1, head_length=0.2,
                                        visible=False) for t in info.tools]
        self._add_ground()
        self.points = None
        if info.n_particles:
            self.points = scene.add_point_cloud("/soil/particles", points=info.initial_positions.reshape(-1, 3),
                                                colors=colors.SOIL_RGB, point_size=self.point_size,
                                                point_shape="circle", precision="float32", point_shading="flat")
        self.terrain = None
        self.label = None if panel else scene.add_label("/figures", title or info.name,
                                                         position=tuple(self._label_position()),
                                                         font_screen_scale=1.2)
        self.history = History([f"{m.name}.{j}" if len(info.machines) > 1 else j
                                for m in info.machines for j in m.joints])
        self.set_initial_camera()
        if panel:
            self._build_panel(title or info.name)

    # ------------------------------------------------------------------------------------------ scene
    def _extent(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.minimum(self.info.domain_min[:2], [-3.0, -3.0])
        hi = np.maximum(self.info.domain_max[:2], [3.0, 3.0])
        return np.floor(lo) - 1, np.ceil(hi) + 1

    def _add_ground(self) -> None:
        lo, hi = self._extent()
        size, centre = hi - lo, (hi + lo) / 2
        self.server.scene.add_grid("/ground/grid", width=float(size[0]), height=float(size[1]), plane="xy",
                                   cell_size=1.0, section_size=5.0, position=(float(centre[0]), float(centre[1]), 0.0))
        for x in range(int(lo[0]), int(hi[0]) + 1):   # metre ticks along both edges nearest the default camera
            self.server.scene.add_label(f"/ground/ticks/x{x}", f"{x} m", position=(float(x), float(lo[1]), 0.0),
                                        font_screen_scale=0.6)
        for y in range(int(lo[1]) + 1, int(hi[1]) + 1):
            self.server.scene.add_label(f"/ground/ticks/y{y}", f"y {y} m", position=(float(hi[0]), float(y), 0.0),
                                        font_screen_scale=0.6)

    def _label_position(self) -> np.ndarray:
        c = self.info.centre()
        return np.array([c[0], c[1], 3.5])

    def camera_pose(self, preset: str) -> tuple[np.ndarray, np.ndarray]:
        """(position, look-at) of a camera preset: `side` (the dig plane, from the machine's right), `machine`
        (from behind the cab, over the boom), `top`."""
        c = self.info.centre()
        base = np.zeros(3)
        if self.info.machines and self.machines:
            name = self.info.machines[0].name
            root = self.machines[name][0]
            base = np.asarray(root.position, float)
        mid = (c + base) / 2
        span = max(float(np.linalg.norm(c[:2] - base[:2])), 3.0)
        if preset == "machine":
            d = c[:2] - base[:2]
            d = d / (np.linalg.norm(d) or 1.0)
            return np.array([base[0] - 2.0 * d[0], base[1] - 2.0 * d[1], 8.0]), np.array([c[0], c[1], -0.5])
        if preset == "top":
            return np.array([mid[0] - 0.01, mid[1], 1.6 * span + 4.0]), np.array([mid[0], mid[1], 0.0])
        # from the machine's right, looking a little to the right of the middle: the panel covers the right side
        return np.array([mid[0] + 1.5, mid[1] - 1.5 * span - 3.0, 4.0]), np.array([mid[0] + 2.2, mid[1], -0.3])

    def set_initial_camera(self) -> None:
        pos, look = self.camera_pose("side")
        self.server.initial_camera.position = tuple(pos)
        self.server.initial_camera.look_at = tuple(look)

    def set_camera(self, client, preset: str) -> None:
        pos, look = self.camera_pose(preset)
        with client.atomic():
            client.camera.position = tuple(pos)
            client.camera.look_at = tuple(look)

    # ------------------------------------------------------------------------------------------ panel
    def _build_panel(self, title: str) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        self.figures = gui.add_markdown(f"**{title}**  \nwaiting for the first frame")
        self.controls = gui.add_folder("Run")
        with gui.add_folder("View"):
            cams = gui.add_button_group("Camera", options=("Side", "Machine", "Top"))
            cams.on_click(lambda event: self.set_camera(event.client, str(event.target.value).lower()))
            quantity = gui.add_dropdown("Colour by", options=colors.QUANTITIES, initial_value=self.quantity)
            size = gui.add_slider("Point size (m)", min=0.01, max=0.5, step=0.01,
                                  initial_value=round(self.point_size, 2))
            show_points = gui.add_checkbox("Particles", initial_value=True)
            terrain = gui.add_checkbox("Terrain surface", initial_value=self.show_terrain)
            show_forces = gui.add_checkbox("Force arrows (1 m per 20 kN)", initial_value=True)
            img, caption = colors.colorbar(self.quantity, self.info)
            self.bar = gui.add_image(img, label="colour bar")
            self.bar_caption = gui.add_markdown(caption)
        with gui.add_folder("Plots"):
            self._build_plots()

        @quantity.on_update
        def _(_):
            self.quantity = quantity.value
            img, caption = colors.colorbar(self.quantity, self.info)
            self.bar.image, self.bar_caption.content = img, caption
            self.refresh()

        @size.on_update
        def _(_):
            self.point_size = float(size.value)
            if self.points is not None:
                self.points.point_size = self.point_size

        @show_points.on_update
        def _(_):
            if self.points is not None:
                self.points.visible = bool(show_points.value)

        @terrain.on_update
        def _(_):
            self.show_terrain = bool(terrain.value)
            if self.terrain is not None:
                self.terrain.visible = self.show_terrain
            self.refresh()

        self.forces_on = True

        @show_forces.on_update
        def _(_):
            self.forces_on = bool(show_forces.value)
            self.refresh()

    def _build_plots(self) -> None:
        from viser import uplot

        gui = self.server.gui
        joints = self.history.joints
        empty = np.zeros(1)
        series = [uplot.Series(label="t (s)")]
        for k, j in enumerate(joints):
            series.append(uplot.Series(label=f"{j}", stroke=JOINT_COLOURS[k % len(JOINT_COLOURS)], width=2))
        for k, j in enumerate(joints):
            series.append(uplot.Series(label=f"{j} cmd", stroke=JOINT_COLOURS[k % len(JOINT_COLOURS)], width=1,
                                       dash=(6.0, 4.0)))
        scales = {"x": uplot.Scale(time=False, auto=True), "y": uplot.Scale(auto=True)}
        self.joint_plot = None  # (a scene with no machine, only a tool, has no joints to plot)
        if joints:
            self.joint_plot = gui.add_uplot(data=tuple([empty] * (1 + 2 * len(joints))), series=tuple(series),
                                            scales=scales, title="joint angles (deg): actual, commanded dashed",
                                            aspect=1.4, legend=uplot.Legend(show=False))
        self.force_plot = gui.add_uplot(data=(empty, empty),
                                        series=(uplot.Series(label="t (s)"),
                                                uplot.Series(label="|F| (kN)", stroke="#d62728", width=2)),
                                        scales=scales, title="bucket force |F| (kN)", aspect=2.0,
                                        legend=uplot.Legend(show=False))

    def _update_plots(self) -> None:
        data = self.history.arrays()
        if len(data) < 2:
            return
        n = len(self.history.joints)
        if self.joint_plot is not None:
            self.joint_plot.data = tuple(np.ascontiguousarray(data[:, k]) for k in range(1 + 2 * n))
        self.force_plot.data = (np.ascontiguousarray(data[:, 0]), np.ascontiguousarray(data[:, -1]))

    # ------------------------------------------------------------------------------------------ frames
    def machine_history_row(self, machines: dict) -> tuple[np.ndarray, np.ndarray]:
        """All machines' joint angles and commands, concatenated in the plots' order."""
        q = [machines[m.name]["q"] for m in self.info.machines if m.name in machines]
        c = [machines[m.name]["q_cmd"] for m in self.info.machines if m.name in machines]
        return (np.concatenate(q) if q else np.zeros(0)), (np.concatenate(c) if c else np.zeros(0))

    def rtf(self, frame: Frame) -> float | None:
        w = self._rtf_window
        if w and frame.t < w[-1][0]:
            w.clear()
        w.append((frame.t, frame.wall))
        if len(w) < 2 or w[-1][1] <= w[0][1]:
            return None
        return (w[-1][0] - w[0][0]) / (w[-1][1] - w[0][1])

    def record(self, frame: Frame, *, peak: float | None = None, rtf: float | None = None) -> tuple[float, float]:
        """Take a frame into the plots' history, the peak force and the real-time factor without drawing it (what
        show() draws next, or refresh() when a browser connects). Returns (bucket force, real-time factor)."""
        with self.lock:
            force = bucket_force(self.info, frame)
            q, q_cmd = self.machine_history_row(frame.machines)
            self.history.append(frame.t, q, q_cmd, force)
            self._last_rtf = self.rtf(frame) if rtf is None else rtf
            self.peak_force = max(self.peak_force, force) if peak is None else peak
            self.last = frame
            return force, self._last_rtf

    def show(self, frame: Frame, *, append: bool = True, peak: float | None = None, rtf: float | None = None,
             note: str = "") -> None:
        """Pose everything from a frame. append: add it to the plots' history (False when re-drawing)."""
        with self.lock:
            info = self.info
            if append:
                force, rtf = self.record(frame, peak=peak, rtf=rtf)
            else:
                force = bucket_force(info, frame)
                rtf = getattr(self, "_last_rtf", None) if rtf is None else rtf
                self.peak_force = max(self.peak_force, force) if peak is None else peak
                self.last = frame
            masks = tool_masks(info, frame) if info.n_particles else []
            carried = in_tools(info, frame, masks) if info.n_particles else None
            mass = bucket_mass(info, frame, masks) if info.n_particles else float("nan")
            with self.server.atomic():
                for m in info.machines:
                    if m.name not in frame.machines:
                        continue
                    root, urdf, index, n = self.machines[m.name]
                    state = frame.machines[m.name]
                    cfg = np.zeros(n)
                    for j, k in enumerate(index):
                        if k >= 0:
                            cfg[k] = state["q"][j]
                    urdf.update_cfg(cfg)
                    root.position = tuple(state["base"][:3])
                    root.wxyz = _wxyz(state["base"][3:])
                for i, handle in self.tool_frames.items():
                    handle.position = tuple(frame.tool_poses[i, :3])
                    handle.wxyz = _wxyz(frame.tool_poses[i, 3:])
                for i, arrow in enumerate(self.arrows):
                    f = frame.tool_wrench[i, :3] if i < len(frame.tool_wrench) else np.zeros(3)
                    if not np.all(np.isfinite(f)) or np.linalg.norm(f) * FORCE_SCALE < 0.05 \
                            or not getattr(self, "forces_on", True):
                        arrow.visible = False
                        continue
                    p, q = frame.tool_poses[i, :3], frame.tool_poses[i, 3:]
                    start = p + quat_to_matrix(q) @ self.centroids[i]
                    arrow.points = np.array([[start, start + f * FORCE_SCALE]], np.float32)
                    arrow.visible = True
                if info.n_particles:
                    self.points.points = frame.positions
                    self.points.colors = colors.colorize(self.quantity, info, frame, carried)
                    if self.show_terrain:
                        x, y, z = surface(info, frame.positions, exclude=carried)
                        vertices, faces = grid_mesh(x, y, z)
                        if self.terrain is None:
                            self.terrain = self.server.scene.add_mesh_simple(
                                "/soil/terrain", vertices, faces, color=TERRAIN_RGB, side="double")
                        else:
                            self.terrain.vertices = vertices
                self._figures(frame, mass, force, rtf, note)
            if self.panel and append:
                self._update_plots()

    def _figures(self, frame: Frame, mass: float, force: float, rtf, note: str) -> None:
        k = self.info.bucket_index()
        where = "bucket" if k is None or self.info.tools[k].owner is not None else self.info.tools[k].name
        rtf_text = "-" if rtf is None else f"{rtf:.2f}"
        mass_text = "-" if not np.isfinite(mass) else f"{mass:,.0f} kg"
        if self.panel:
            self.figures.content = (
                f"**{self.info.name}** ({self.status}{', ' + note if note else ''})  \n"
                f"t **{frame.t:.2f}** / {self.info.duration:g} s, real-time factor **{rtf_text}**  \n"
                f"particles **{len(frame.positions):,}**, in {where} **{mass_text}**  \n"
                f"{where} force **{force / 1e3:.1f} kN**, peak **{self.peak_force / 1e3:.1f} kN**")
        elif self.label is not None:
            self.label.text = (f"{self.info.name}  t {frame.t:.1f} s  in {where} {mass_text}  "
                               f"|F| {force / 1e3:.1f} kN (peak {self.peak_force / 1e3:.1f})")

    def refresh(self, plots: bool = False) -> None:
        """Draw the last frame again (a control changed while paused or between frames); plots: the plots too (a
        browser that connects to a view that drew nothing while none was connected)."""
        with self.lock:
            if self.last is not None:
                self.show(self.last, append=False, peak=self.peak_force)
            if plots and self.panel:
                self._update_plots()
