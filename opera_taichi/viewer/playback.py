"""`view RUN_DIR`: a recorded run (replay.bin) served in the browser with a time slider, play/pause and speed; and
`view RUN_DIR --html FILE`: the same scene as one self-contained HTML file that plays with no server (viser's scene
serializer: every frame's messages with their timing, played by viser's own embedded client)."""
from __future__ import annotations

import contextlib
import io
import math
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ..errors import UserError
from .live import start_server, stop_server
from .replay import ReplayReader, open_run
from .view import SceneView, require_viser

SPEEDS = ("0.25x", "0.5x", "1x", "2x", "4x", "8x")
HTML_PARTICLE_FRAMES = 3_000_000   # particles x frames in one HTML file (frames are thinned past it: ~50 MB)


def _forces(reader: ReplayReader) -> np.ndarray:
    k = reader.info.bucket_index()
    if k is None:
        return np.zeros(len(reader))
    return np.array([np.linalg.norm(np.nan_to_num(np.asarray(m["wrench"][k][:3], float))) for m in reader.metas])


class Player:
    """The replay's own controls: a time slider, play/pause, speed, loop; a thread plays in wall-clock time."""

    def __init__(self, view: SceneView, reader: ReplayReader):
        self.view, self.reader = view, reader
        self.forces = _forces(reader)
        self.peaks = np.maximum.accumulate(self.forces) if len(self.forces) else self.forces
        self.shown = -1
        self.t = float(reader.times[0])
        self.playing = threading.Event()
        self.stopping = threading.Event()
        self._setting = False
        gui = view.server.gui
        t0, t1 = float(reader.times[0]), float(reader.times[-1])
        step = float(np.median(np.diff(reader.times))) if len(reader) > 1 else 0.1
        with view.controls:
            self.button = gui.add_button("Play")
            self.slider = gui.add_slider("Time (s)", min=round(t0, 3), max=round(max(t1, t0 + step), 3),
                                         step=round(step, 4), initial_value=round(t0, 3))
            self.speed = gui.add_dropdown("Speed", options=SPEEDS, initial_value="1x")
            self.loop = gui.add_checkbox("Loop", initial_value=True)

        @self.button.on_click
        def _(_):
            if self.playing.is_set():
                self.pause()
            else:
                if self.shown >= len(self.reader) - 1:
                    self.t = float(self.reader.times[0])
                self.playing.set()
                self.button.label, self.view.status = "Pause", "playing"

        @self.slider.on_update
        def _(_):
            if self._setting:
                return
            self.pause()
            self.t = float(self.slider.value)
            self.goto(self.reader.index_at(self.t))

        self.goto(0)
        self.playing.set()   # plays on opening, in a loop, as a video player would
        self.button.label, view.status = "Pause", "playing"
        self.thread = threading.Thread(target=self._play, name="replay-player", daemon=True)
        self.thread.start()

    def pause(self) -> None:
        self.playing.clear()
        self.button.label, self.view.status = "Play", "paused"
        self.view.refresh()

    def goto(self, i: int) -> None:
        """Show frame i; the plots show the run up to it."""
        reader, view = self.reader, self.view
        i = int(np.clip(i, 0, len(reader) - 1))
        if i == self.shown:
            return
        if i == 0 or i != self.shown + 1:   # the start or a jump: rebuild the plotted history up to i
            view.history.clear()
            for k in range(max(0, i - view.history.rows.maxlen + 1), i):
                q, q_cmd = view.machine_history_row(reader.machines_at(k))
                view.history.append(float(reader.times[k]), q, q_cmd, self.forces[k])
        j = max(0, i - 10)
        rtf = None
        if i > j and reader.metas[i]["wall"] > reader.metas[j]["wall"]:
            rtf = (reader.times[i] - reader.times[j]) / (reader.metas[i]["wall"] - reader.metas[j]["wall"])
        view.show(reader.frame(i), peak=float(self.peaks[i]), rtf=rtf,
                  note=f"recorded, run status {getattr(reader, 'status', 'unknown')}")
        self.shown = i
        self._setting = True
        try:
            self.slider.value = round(float(reader.times[i]), 3)
        finally:
            self._setting = False

    def _play(self) -> None:
        last = time.perf_counter()
        while not self.stopping.is_set():
            if not self.playing.wait(0.1):
                last = time.perf_counter()
                continue
            now = time.perf_counter()
            self.t += (now - last) * float(self.speed.value.rstrip("x"))
            last = now
            if self.t > self.reader.times[-1]:
                if self.loop.value and self.reader.times[-1] > self.reader.times[0]:  # (one frame: nothing to loop)
                    self.t = float(self.reader.times[0])
                    self.shown = -1
                else:
                    self.goto(len(self.reader) - 1)
                    self.pause()
                    continue
            self.goto(self.reader.index_at(self.t))
            time.sleep(0.02)


def serve(run_dir, host: str = "127.0.0.1", port: int = 8080, quiet: bool = False) -> None:
    """Serve a run's replay until Ctrl-C."""
    reader = open_run(run_dir)
    server = start_server(host, port, "--port")
    try:
        view = SceneView(server, reader.info, title=f"{reader.info.name} (replay)")
        player = Player(view, reader)
        if not quiet:
            print(f"view: http://{host}:{port} ({len(reader)} frames, {reader.times[-1]:.1f} s simulated; "
                  f"Ctrl-C stops)", file=sys.stderr, flush=True)
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:   # Ctrl-C (or SIGTERM) is how a server is stopped: not an error
            pass
        finally:
            player.stopping.set()
    finally:
        stop_server(server)


def write_html(run_dir, out, quiet: bool = False) -> Path:
    """One self-contained HTML file that plays the replay with viser's embedded client, no server needed."""
    viser = require_viser()
    reader = open_run(run_dir)
    out = Path(out)
    if out.is_dir():
        raise UserError(f"--html: {out} is a folder; give a file name such as run.html")
    every = max(1, math.ceil(reader.info.n_particles * len(reader) / HTML_PARTICLE_FRAMES))
    with contextlib.redirect_stdout(io.StringIO()):   # viser's banner; stdout carries our output
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)   # a scene to record; no one connects
    try:
        view = SceneView(server, reader.info, panel=False, title=reader.info.name)
        forces = _forces(reader)
        peaks = np.maximum.accumulate(forces) if len(forces) else forces
        view.show(reader.frame(0), peak=float(peaks[0]))
        serializer = server.get_scene_serializer()
        indices = list(range(0, len(reader), every))
        for n, i in enumerate(indices):
            view.show(reader.frame(i), peak=float(peaks[i]))
            if n + 1 < len(indices):
                serializer.insert_sleep(float(reader.times[indices[n + 1]] - reader.times[i]))
        html = serializer.as_html()
    finally:
        stop_server(server)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(html, encoding="utf-8")
    except OSError as exc:
        raise UserError(f"--html: cannot write {out} ({exc.strerror})") from None
    if not quiet:
        note = f", every {every}th frame" if every > 1 else ""
        print(f"{out} ({len(html) / 1e6:.1f} MB, {len(indices)} frames{note})", file=sys.stderr)
    return out
