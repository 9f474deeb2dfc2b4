"""`run --view`: the 3-D view served while the run goes.

LiveView is a ThreadedObserver: the simulation's thread copies a Frame at most `rate` times per wall-clock second
(a cheap copy), the observer's thread builds and sends the scene, and only the newest frame waits there, so a slow
or absent browser never slows the run. ViewerController wraps the run's controller: it is where the viewer's Pause
holds the loop (the controller waits before giving the next step's commands), and, for a scene without a motion
script, where the panel's joint sliders command the machine (teleop). The run loop itself is not touched.
"""
from __future__ import annotations

import atexit
import contextlib
import errno
import io
import math
import socket
import sys
import threading
import time

import numpy as np

from ..control import Control, MachineControl, ScriptController, driver_of
from ..errors import UserError
from ..observers import ThreadedObserver
from .frames import capture, scene_info
from .view import SceneView, require_viser


def check_port(host: str, port: int, flag: str = "--view-port") -> None:
    """A one-line UserError when the port cannot be served (in use, no permission, bad host)."""
    if not 0 < int(port) < 65536:
        raise UserError(f"{flag}: {port} is not a TCP port (1-65535)")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise UserError(f"--view-host / --host: cannot resolve {host!r} ({exc.strerror})") from None
    family, _, _, _, address = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(address)
        except OSError as exc:
            if exc.errno == errno.EADDRNOTAVAIL:  # the host is none of this machine's addresses
                host_flag = "--view-host" if flag.startswith("--view") else "--host"
                raise UserError(f"{host_flag}: {host} is not an address of this machine ({exc.strerror}); give one "
                                f"of its own, 127.0.0.1 or 0.0.0.0") from None
            why = "is in use" if exc.errno == errno.EADDRINUSE else f"cannot be opened ({exc.strerror})"
            raise UserError(f"{flag}: port {port} on {host} {why}; give another port") from None


def start_server(host: str, port: int, flag: str = "--view-port"):
    """A viser server on exactly host:port (viser itself would move on to the next free port)."""
    viser = require_viser()
    check_port(host, port, flag)
    with contextlib.redirect_stdout(io.StringIO()):   # viser prints a banner on stdout, which carries our output
        server = viser.ViserServer(host=host, port=int(port), verbose=False)
    if server.get_port() != int(port):
        stop_server(server)
        raise UserError(f"{flag}: port {port} on {host} is in use; give another port")
    return server


def stop_server(server) -> None:
    with contextlib.redirect_stdout(io.StringIO()):   # and "Server stopped" on the way out
        server.stop()


class LiveView(ThreadedObserver):
    """The live browser view of a run (`run --view`)."""

    key = "LiveView"

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, rate: float = 10.0, teleop: bool = False,
                 quiet: bool = False):
        self.host, self.port, self.fps, self.teleop = host, int(port), float(rate), teleop
        self.quiet = quiet
        # The bus calls at 100 Hz of simulated time; sample() copies a frame only when 1/rate wall seconds passed.
        self.rate = max(100.0, self.fps)
        self.running = threading.Event()   # cleared while the viewer's Pause holds the run
        self.running.set()
        self.sliders: dict = {}
        self._range: dict = {}             # (machine, joint) -> the slider's (min, max), deg
        self._good: dict = {}              # (machine, joint) -> its last finite value, deg
        self.view = None
        self._bucket = None
        self.server = start_server(host, port)   # early: a port in use fails before the soil is built
        atexit.register(self._stop)              # a run that fails before its loop starts never calls close()
        self.server.gui.add_markdown("**opera-taichi**: preparing the run (machine, soil bed, kernels)...")

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def start(self, sim, run) -> None:
        self.server.gui.reset()
        self.view = SceneView(self.server, scene_info(sim))
        self.view.status = "running"
        self._wall0 = time.perf_counter()
        self._last_wall = -1e9
        self._peak = 0.0
        self._bucket = self.view.info.bucket_index()
        self._build_controls(sim)
        # (frames are not drawn while no browser is connected: one that connects gets the last frame at once)
        self.server.on_client_connect(lambda _client: self.view.refresh(plots=True))
        if not self.quiet:
            print(f"view: {self.url} (Ctrl-C ends the run)", file=sys.stderr)
        super().start(sim, run)

    def _build_controls(self, sim) -> None:
        gui = self.server.gui
        with self.view.controls:
            pause = gui.add_button("Pause", hint="hold the simulation before its next step")

            @pause.on_click
            def _(_):
                if self.running.is_set():
                    self.running.clear()
                    pause.label, self.view.status = "Resume", "paused"
                else:
                    self.running.set()
                    pause.label, self.view.status = "Pause", "running"
                self.view.refresh()

        if self.teleop:
            # right under Run, above View and Plots: on a laptop's screen the panel would hide it below the plots
            with gui.add_folder("Teleop (joint targets, deg)", order=self.view.controls.order + 0.5):
                for m in self.view.info.machines:
                    q, _, _ = sim.machines[m.name].joint_states()
                    for j, (lo, hi), value in zip(m.joints, m.limits, q):
                        lo_d = float(np.degrees(lo)) if np.isfinite(lo) else -180.0
                        hi_d = float(np.degrees(hi)) if np.isfinite(hi) else 180.0
                        label = f"{m.name}.{j}" if len(self.view.info.machines) > 1 else j
                        start = float(np.clip(round(float(np.degrees(value)), 1), lo_d, hi_d))
                        self.sliders[(m.name, j)] = gui.add_slider(
                            label, min=round(lo_d, 1), max=round(hi_d, 1), step=0.5, initial_value=start)
                        self._range[(m.name, j)] = (round(lo_d, 1), round(hi_d, 1))
                        self._good[(m.name, j)] = start

    def targets(self) -> dict[str, dict[str, float]]:
        """The teleop sliders' joint targets (rad) per machine."""
        out: dict[str, dict[str, float]] = {}
        for (machine, joint), slider in self.sliders.items():
            try:
                deg = float(slider.value)
            except (TypeError, ValueError):
                deg = math.nan
            if not math.isfinite(deg):  # a browser can send any number: the last good value stands
                deg = self._good[(machine, joint)]
            lo, hi = self._range[(machine, joint)]
            deg = min(max(deg, lo), hi)
            self._good[(machine, joint)] = deg
            out.setdefault(machine, {})[joint] = float(np.radians(deg))
        return out

    def sample(self, sim) -> None:
        if self._bucket is not None:   # the peak sees every sample, not only the frames shown
            self._peak = max(self._peak, float(np.linalg.norm(sim.tool_wrench[self._bucket, :3])))
        now = time.perf_counter()
        if now - self._last_wall < 1.0 / self.fps:
            return
        self._last_wall = now
        super().sample(sim)

    def snapshot(self, sim):
        return capture(sim, time.perf_counter() - self._wall0), self._peak

    def publish(self, snapshot) -> None:
        frame, peak = snapshot
        if not self.server.get_clients():  # nobody watches: keep the plots' history, draw when a browser connects
            self.view.record(frame, peak=max(peak, self.view.peak_force))
            return
        self.view.show(frame, peak=max(peak, self.view.peak_force))

    def close(self, sim, status, message) -> None:
        if hasattr(self, "_thread"):   # started (a run stopped while preparing never was)
            super().close(sim, status, message)
        if self.view is not None:
            self.view.status = status
            self.view.refresh()
        self.running.set()
        self.server.flush()   # the final status reaches the page before the server goes
        self._stop()

    def _stop(self) -> None:
        if not getattr(self, "_stopped", False):
            self._stopped = True
            stop_server(self.server)


class ViewerController:
    """The run's controller under a live view: waits while the view is paused; with teleop, the panel's sliders
    give the joint targets, else the wrapped controller (the scene's motion scripts by default) does."""

    source = "viewer"

    def __init__(self, view: LiveView, inner=None):
        self.view, self.inner = view, inner

    @property
    def driver(self) -> str:
        return "teleop" if self.view.teleop else driver_of(self.inner)

    def control(self, sim, t: float) -> Control:
        while not self.view.running.wait(0.1):   # wait in short slices, so Ctrl-C and SIGTERM end the run at once
            pass
        if self.view.teleop and self.view.sliders:
            return Control({name: MachineControl(q_target=q) for name, q in self.view.targets().items()}, t,
                           "teleop")
        if self.inner is None:
            self.inner = ScriptController(sim.model)
        return self.inner.control(sim, t)
