"""The 3-D viewer without a browser: the replay file (what is recorded is what comes back; a killed run keeps its
frames; a torn tail is skipped), the MP4, the teleop controller and the viewer's Pause, and bad input (exit 2, one
line). The browser tests are in test_viewer_browser.py."""
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("viser")

from opera_taichi import cli  # noqa: E402
from opera_taichi.recorders import read_csv_columns  # noqa: E402
from opera_taichi.viewer.replay import REPLAY_FILE, ReplayReader, open_run  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "zx120_excavation.yaml"
COARSE = ["--set", "soil.overrides.radius=0.12", "--set", "output.plots=false"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A coarse excavation, 3 s simulated, recorded with --replay at 10 Hz, with its final particles."""
    out = tmp_path_factory.mktemp("viewer") / "run"
    rc = cli.main(["run", str(SCENE), "--out", str(out), "--quiet", "--replay", *COARSE, "--set", "sim.duration=3",
                   "--set", "output.particles_final=true"])
    assert rc == 0
    return out


def test_replay_holds_every_frame_as_recorded(run):
    reader = open_run(run)
    assert len(reader) == 31                                   # t = 0, 0.1, ..., 3.0
    assert np.allclose(reader.times, np.arange(31) * 0.1)
    manifest = json.loads((run / "manifest.json").read_text())
    assert reader.info.n_particles == manifest["particles"]
    assert [m.name for m in reader.info.machines] == ["zx120"]
    assert reader.info.tools[0].name == "bucket_link" and reader.info.tools[0].owner == "zx120"
    # particles: the last frame is the final state, to the uint16 quantisation step (domain span / 65535)
    final = np.load(run / "particles_final.npz")
    last = reader.frame(len(reader) - 1)
    step = reader.box.span / 65535
    assert np.all(np.abs(last.positions - final["positions"]) <= step * 0.5 + 1e-6)
    assert np.allclose(last.speeds, np.linalg.norm(final["velocities"], axis=1), rtol=2e-3, atol=1e-4)
    # joints: what joints.csv says at the same instants
    cols = read_csv_columns(run / "joints.csv")
    for i in (0, 15, 30):
        row = int(np.argmin(np.abs(cols["t"] - reader.times[i])))
        frame = reader.frame(i)
        q = frame.machines["zx120"]["q"]
        for k, joint in enumerate(reader.info.machines[0].joints):
            assert q[k] == pytest.approx(cols[f"{joint}.q"][row], abs=1e-6)
    # the arm moved: the recorded frames are not all the same pose
    assert abs(reader.frame(30).machines["zx120"]["q"][2] - reader.frame(0).machines["zx120"]["q"][2]) > 0.05


def test_a_torn_last_record_is_skipped(run, tmp_path):
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    path = copy / REPLAY_FILE
    data = path.read_bytes()
    full = len(ReplayReader(path))
    path.write_bytes(data[:-100])                       # killed in the middle of writing the last frame
    assert len(ReplayReader(path)) == full - 1
    path.write_bytes(data + b"OTRP" + b"\x00" * 7)       # a record header with nothing after it
    assert len(ReplayReader(path)) == full


def test_a_killed_run_keeps_its_frames(tmp_path):
    out = tmp_path / "killed"
    cmd = [sys.executable, str(ROOT / "cli.py"), "run", str(SCENE), "--out", str(out), "--quiet", "--replay",
           *COARSE, "--set", "sim.duration=30"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 600  # (a guard against a hung run only: it compiles and settles first)
        frames = 0
        while time.monotonic() < deadline and proc.poll() is None:
            if (out / REPLAY_FILE).is_file():
                frames = len(ReplayReader(out / REPLAY_FILE))
                if frames >= 8:
                    break
            time.sleep(0.2)
        assert frames >= 8, proc.stderr.read().decode() if proc.poll() is not None else "no frames in 600 s"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    reader = open_run(out)                     # the process died: the manifest still says running
    assert len(reader) >= 8
    assert reader.frame(len(reader) - 1).t == pytest.approx(0.1 * (len(reader) - 1))


def test_mp4_has_one_frame_per_recorded_frame(run, tmp_path):
    import imageio_ffmpeg

    out = tmp_path / "run.mp4"
    assert cli.main(["view", str(run), "--mp4", str(out), "--quiet"]) == 0
    frames, seconds = imageio_ffmpeg.count_frames_and_secs(str(out))
    assert frames == len(open_run(run))
    assert seconds == pytest.approx(3.1, abs=0.15)     # played at the recording rate: real time


def test_mp4_axes_hold_a_machine_far_from_the_bed(run):
    """The video's axes come from what it draws: the same replay with the machine parked 15 m beside the bed keeps
    every frame's machine inside them (the axes were the bed's x and 4 m either side of its middle)."""
    from opera_taichi.viewer import video

    reader = open_run(run)
    machines = [(m.name, video._MachineMesh(m.urdf, m.joints)) for m in reader.info.machines]

    class Parked:
        def __len__(self):
            return len(reader)

        def frame(self, i):
            frame = reader.frame(i)
            for state in frame.machines.values():
                state["base"] = np.asarray(state["base"], float) + [0.0, 15.0, 0.0, 0.0, 0.0, 0.0, 0.0]
            return frame

    lo, hi = video._extent(Parked(), reader.info, machines, [])
    assert hi[1] > 15.0
    for i in range(len(reader)):
        drawn = list(video._meshes(Parked().frame(i), machines, []))
        assert drawn and all((tris >= lo).all() and (tris <= hi).all() for tris, _ in drawn)


def test_teleop_sliders_command_the_machine_and_pause_holds_the_loop():
    import opera_taichi as ot
    from opera_taichi.observers import RunContext
    from opera_taichi.viewer.live import LiveView, ViewerController

    sim = ot.Simulation.from_scene(SCENE, overrides={"soil.overrides.radius": 0.12, "motion": None})
    view = LiveView(port=free_port(), teleop=True, quiet=True)
    try:
        view.start(sim, RunContext(out=None))
        controller = ViewerController(view)
        boom = sim.machine.joint_names.index("boom_joint")
        q0 = sim.machine.joint_states()[0][boom]
        assert view.sliders[("zx120", "boom_joint")].value == pytest.approx(np.degrees(q0), abs=0.5)
        target = q0 + 0.3                                           # lower the boom by 0.3 rad
        view.sliders[("zx120", "boom_joint")].value = float(np.degrees(target))
        ctrl = controller.control(sim, sim.t_next)
        assert ctrl.source == "teleop"
        assert ctrl.machines["zx120"].q_target["boom_joint"] == pytest.approx(target)
        view.sliders[("zx120", "boom_joint")].value = float("nan")   # what a browser may send: the last good
        assert controller.control(sim, sim.t_next).machines["zx120"].q_target["boom_joint"] == pytest.approx(target)
        for _ in range(400):                                        # 0.4 s: the boom follows the slider
            sim.step(controller.control(sim, sim.t_next))
        assert sim.machine.joint_states()[0][boom] > q0 + 0.05

        view.running.clear()                                        # the viewer's Pause
        done = threading.Event()
        worker = threading.Thread(target=lambda: (controller.control(sim, sim.t_next), done.set()))
        worker.start()
        worker.join(timeout=0.5)
        assert worker.is_alive() and not done.is_set()              # the loop waits for its next command
        view.running.set()                                          # Resume
        assert done.wait(timeout=10)
        worker.join()
    finally:
        view.close(sim, "done", "")
        sim.close()


def test_with_no_browser_connected_the_live_view_keeps_the_history_and_draws_nothing(monkeypatch):
    """Drawing a frame (the machine's links, the grains, the tools' hulls) took the view's thread about 6 ms, which
    slowed the run by 6% on two cores with nobody watching. Without a browser the frames only go into the plots'
    history; the first browser to connect is drawn the last frame at once (test_viewer_browser)."""
    import opera_taichi as ot
    from opera_taichi.observers import RunContext
    from opera_taichi.viewer.live import LiveView
    from opera_taichi.viewer.view import SceneView

    drawn = []
    show = SceneView.show
    monkeypatch.setattr(SceneView, "show", lambda self, frame, **kw: (drawn.append(kw.get("append", True)),
                                                                      show(self, frame, **kw))[1])
    sim = ot.Simulation.from_scene(SCENE, overrides={"soil.overrides.radius": 0.16})
    view = LiveView(port=free_port(), quiet=True)
    try:
        view.start(sim, RunContext(out=None))
        for _ in range(20):
            sim.step()
            view.publish(view.snapshot(sim))   # (what the view's thread does with each sample, here in order)
    finally:
        view.close(sim, "done", "")
        sim.close()
    assert len(view.view.history.arrays()) == 20
    assert True not in drawn      # (close() draws the final status once: append=False)
    assert view.view.force_plot.data is None or len(view.view.force_plot.data[0]) < 20
    view.view.refresh(plots=True)  # what a browser that connects is drawn: the frame and the whole history
    assert len(view.view.force_plot.data[0]) == 20


def test_a_run_dug_by_hand_keeps_to_the_wall_clock(tmp_path):
    """`--view` with sliders (no motion, no bridge) is paced: the sleeping pacer keeps simulated time at most the
    wall time since the first step (the machine alone would run several times faster than real time)."""
    dig = ROOT / "scenes" / "zx120_dig_cycle.yaml"
    for pace, out in ((None, tmp_path / "hand"), ("fast", tmp_path / "fast")):
        argv = ["run", str(dig), "--out", str(out), "--quiet", "--set", "motion=null", "--set", "sim.duration=0.6",
                "--view", "--view-port", str(free_port())] + (["--pace", pace] if pace else [])
        assert cli.main(argv) == 0
    paced = json.loads((tmp_path / "hand" / "manifest.json").read_text())
    assert paced["sim_time"] == pytest.approx(0.6) and paced["real_time_factor"] <= 1.01
    assert json.loads((tmp_path / "fast" / "manifest.json").read_text())["status"] == "done"


# ---------------------------------------------------------------------------------------------- bad input
def _one_line_exit_2(capsys, argv, *must):
    rc = cli.main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    for text in must:
        assert text in err, (text, err)


def test_view_refuses_what_is_not_a_recorded_run(run, tmp_path, capsys):
    _one_line_exit_2(capsys, ["view", str(tmp_path / "absent")], "is not a folder")
    (tmp_path / "empty").mkdir()
    _one_line_exit_2(capsys, ["view", str(tmp_path / "empty")], "not a run folder", "manifest.json")
    (tmp_path / "garbled").mkdir()
    (tmp_path / "garbled" / "manifest.json").write_text("{not json")
    _one_line_exit_2(capsys, ["view", str(tmp_path / "garbled")], "unreadable manifest")
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "manifest.json").write_text('{"name": "somebody else\'s"}')
    _one_line_exit_2(capsys, ["view", str(tmp_path / "foreign")], "not an opera-taichi run manifest")
    no_replay = tmp_path / "no_replay"
    shutil.copytree(run, no_replay)
    (no_replay / REPLAY_FILE).unlink()
    _one_line_exit_2(capsys, ["view", str(no_replay)], f"has no {REPLAY_FILE}, which its run recorded")
    record = json.loads((no_replay / "manifest.json").read_text())
    record["status"] = "interrupted"    # Ctrl-C while it set up: no frame yet
    (no_replay / "manifest.json").write_text(json.dumps(record))
    _one_line_exit_2(capsys, ["view", str(no_replay)], "stopped (status interrupted) before its first replay frame")
    record["scene"]["output"]["replay"] = False
    (no_replay / "manifest.json").write_text(json.dumps(record))
    _one_line_exit_2(capsys, ["view", str(no_replay)], "recorded without a replay", "--replay")
    bad = tmp_path / "bad_replay"
    shutil.copytree(run, bad)
    (bad / REPLAY_FILE).write_bytes(b"this is not a replay")
    _one_line_exit_2(capsys, ["view", str(bad), "--html", str(tmp_path / "x.html")], "not an opera-taichi replay")
    manifest = (run / "manifest.json").read_bytes()   # a slip of the tab key must not overwrite the run's own files
    _one_line_exit_2(capsys, ["view", str(run), "--html", str(run / "manifest.json")], "ending in .html or .htm")
    _one_line_exit_2(capsys, ["view", str(run), "--mp4", str(run / "joints.csv")], "ending in .mp4")
    assert (run / "manifest.json").read_bytes() == manifest
    if os.geteuid() != 0:  # root reads any file
        locked = tmp_path / "locked"
        shutil.copytree(run, locked)
        (locked / REPLAY_FILE).chmod(0)
        _one_line_exit_2(capsys, ["view", str(locked)], "cannot read the replay")


def test_a_port_in_use_is_one_line_exit_2(run, capsys, tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        _one_line_exit_2(capsys, ["view", str(run), "--port", str(port)], f"--port: port {port}", "in use")
        # run --view fails at once, before the soil is built and nothing is written
        _one_line_exit_2(capsys, ["run", str(SCENE), "--view", "--view-port", str(port), "--out",
                                  str(tmp_path / "never")], f"--view-port: port {port}", "in use")
        assert not (tmp_path / "never" / "manifest.json").exists()
    _one_line_exit_2(capsys, ["run", str(SCENE), "--view-port", "8080"], "--view-port: only with --view")
    _one_line_exit_2(capsys, ["view", str(run), "--port", "70000"], "not a TCP port")
    _one_line_exit_2(capsys, ["view", str(run), "--host", "192.0.2.1"], "--host: 192.0.2.1 is not an address of "
                     "this machine")   # TEST-NET-1: documentation only, never a local address


def test_a_scene_with_only_a_tool_is_shown_and_an_unwritable_video_is_one_line(tmp_path, capsys):
    """The blade scene has no machine: its view has no joints to plot (the panel's plot was refused by viser and
    the run ended in a traceback). An MP4 whose folder is a file: one line, exit 2 (was a traceback)."""
    from opera_taichi.viewer.live import start_server
    from opera_taichi.viewer.view import SceneView

    out = tmp_path / "blade"
    assert cli.main(["run", str(ROOT / "scenes" / "blade_cut.yaml"), "--out", str(out), "--quiet", "--replay",
                     "--set", "soil.overrides.radius=0.08", "--set", "sim.duration=0.2",
                     "--set", "output.plots=false"]) == 0
    capsys.readouterr()   # (Taichi's banner, where this test started it)
    server = start_server("127.0.0.1", free_port())
    try:
        reader = open_run(out)
        view = SceneView(server, reader.info)
        view.show(reader.frame(len(reader) - 1))
        assert view.joint_plot is None
    finally:
        server.stop()
    from opera_taichi.geometry import quat_to_matrix
    from opera_taichi.viewer import video

    blade = reader.info.tools[0]
    tools = [(0, video._ToolMesh(blade.vertices, blade.faces))]
    last = reader.frame(len(reader) - 1)
    (tris, _), = video._meshes(last, [], tools)           # the video draws the blade, where it was recorded
    pose = last.tool_poses[0]
    posed = blade.vertices @ quat_to_matrix(pose[3:]).T + pose[:3]
    np.testing.assert_allclose(tris.reshape(-1, 3).min(axis=0), posed.min(axis=0), atol=1e-5)
    np.testing.assert_allclose(tris.reshape(-1, 3).max(axis=0), posed.max(axis=0), atol=1e-5)
    lo, hi = video._extent(reader, reader.info, [], tools)
    assert (posed >= lo).all() and (posed <= hi).all()
    (tmp_path / "afile").write_text("")
    _one_line_exit_2(capsys, ["view", str(out), "--mp4", str(tmp_path / "afile" / "x.mp4")], "--mp4: cannot write")
