"""A run as a user starts it: the CLI writes the run folder of the contract, with data that agrees with
the scene (times, commanded angles, physical joint speeds), and a recorded log replays faithfully."""
import csv
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from opera_taichi.cli import main
from opera_taichi.recorders import read_csv_columns

ROOT = Path(__file__).resolve().parent.parent
JOINTS = ["swing_joint", "boom_joint", "arm_joint", "bucket_joint"]


@pytest.fixture(scope="module")
def dig_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("dig") / "run"
    rc = main(["run", str(ROOT / "scenes" / "zx120_dig_cycle.yaml"), "--out", str(out), "--quiet",
               "--set", "sim.duration=12"])
    assert rc == 0
    return out


def test_run_folder_holds_the_contract_files(dig_run):
    for name in ("manifest.json", "joints.csv", "joints.png"):
        assert (dig_run / name).is_file(), name
    manifest = json.loads((dig_run / "manifest.json").read_text())
    assert manifest["status"] == "done"
    assert manifest["sim_time"] == pytest.approx(12.0, abs=1e-6)
    assert manifest["seed"] == 0
    assert manifest["real_time_factor"] > 0
    assert manifest["scene"]["sim"]["duration"] == 12.0   # the resolved scene, with the --set applied
    assert manifest["versions"]["pybullet"] and manifest["versions"]["taichi"]


def test_joints_csv_columns_rate_and_units(dig_run):
    cols = read_csv_columns(dig_run / "joints.csv")
    expected = ["t"] + [f"{j}.{k}" for j in JOINTS for k in ("q", "qd", "q_cmd", "qd_cmd", "effort")]
    with open(dig_run / "joints.csv") as fh:
        assert next(csv.reader(fh)) == expected
    t = cols["t"]
    assert t[0] == 0.0 and t[-1] == pytest.approx(12.0, abs=1e-6)
    assert np.allclose(np.diff(t), 0.01, atol=1e-6)           # joints_rate 100 Hz
    # commanded angles are the scene's waypoints, in radians
    i4 = int(np.argmin(np.abs(t - 4.0)))
    assert cols["boom_joint.q_cmd"][i4] == pytest.approx(math.radians(-22), abs=1e-6)
    assert cols["arm_joint.q_cmd"][0] == pytest.approx(math.radians(114), abs=1e-6)
    # velocities agree with the angles' finite differences and never exceed the actuator limits
    for j, vmax in (("boom_joint", 0.70), ("arm_joint", 0.75), ("bucket_joint", 1.10)):
        fd = np.gradient(cols[f"{j}.q"], t)
        assert np.max(np.abs(cols[f"{j}.qd"])) <= vmax * 1.01
        assert np.max(np.abs(fd - cols[f"{j}.qd"])) < 0.05
    # holding the boom up against gravity takes effort (negative boom torque raises the boom)
    assert np.all(cols["boom_joint.effort"][100:] < 0)


def test_recorded_log_replays_through_csv_motion(dig_run, tmp_path):
    """Export the run's actual angles as a machine log, replay it, and get the same motion back."""
    cols = read_csv_columns(dig_run / "joints.csv")
    log = tmp_path / "log.csv"
    with open(log, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t"] + [f"{j}_deg" for j in JOINTS])
        for k in range(0, len(cols["t"]), 5):
            w.writerow([cols["t"][k]] + [math.degrees(cols[f"{j}.q"][k]) for j in JOINTS])
    scene = tmp_path / "replay.yaml"
    shutil.copy(ROOT / "scenes" / "zx120_dig_cycle.yaml", scene)
    text = scene.read_text()
    scene.write_text(text[:text.index("motion:")] + "motion:\n  type: csv\n  file: log.csv\n"
                     + text[text.index("output:"):])
    out = tmp_path / "replay_run"
    assert main(["run", str(scene), "--out", str(out), "--quiet", "--set", "sim.duration=12"]) == 0
    replay = read_csv_columns(out / "joints.csv")
    gains = {"swing_joint": (1.20, 3.0), "boom_joint": (0.70, 5.0), "arm_joint": (0.75, 5.0),
             "bucket_joint": (1.10, 5.0)}   # machine.yaml: max_speed, gain
    for j in JOINTS:
        # the command is the log (linear between its 20 Hz samples)...
        assert np.max(np.abs(replay[f"{j}.q_cmd"] - cols[f"{j}.q"])) < 2e-3, j
        # ...and the machine follows it with at most the hydraulic loop's lag, speed / gain
        vmax, gain = gains[j]
        assert np.max(np.abs(replay[f"{j}.q"] - replay[f"{j}.q_cmd"])) < vmax / gain + 0.01, j


def test_a_runs_own_joints_csv_replays_as_a_csv_motion(dig_run, tmp_path):
    """The run folder's joints.csv is a motion file as it stands: its `<joint>.q` columns are the positions (the
    other columns are ignored), and the replay commands the recorded profile within 1 mrad."""
    original = read_csv_columns(dig_run / "joints.csv")
    out = tmp_path / "replay"
    rc = main(["run", str(ROOT / "scenes" / "zx120_dig_cycle.yaml"), "--out", str(out), "--quiet",
               "--set", "sim.duration=12", "--set", f"motion={{type: csv, file: {dig_run / 'joints.csv'}}}"])
    assert rc == 0
    replay = read_csv_columns(out / "joints.csv")
    assert np.array_equal(replay["t"], original["t"])
    for j in JOINTS:
        assert np.max(np.abs(replay[f"{j}.q_cmd"][1:] - original[f"{j}.q"][1:])) < 1e-3, j


def _drive_ahead_on_tracks(tmp_path, yaw: float, seconds: float) -> Path:
    """The dig-cycle machine on tracks, facing `yaw`, driven straight ahead at 0.6 m/s; returns its run folder."""
    from opera_taichi.control import Control, MachineControl
    from opera_taichi.runner import run_scene
    from opera_taichi.scene import load_scene

    class DriveAhead:
        def control(self, sim, t):
            return Control({"zx120": MachineControl(track_speeds=(0.6, 0.6))}, t, "test")

    scene = load_scene(ROOT / "scenes" / "zx120_dig_cycle.yaml",
                       ["machine.fixed_base=false", f"sim.duration={seconds}", f"machine.base_pose.yaw={yaw}",
                        "output.plots=false"])
    return run_scene(scene, tmp_path / "run", quiet=True, controller=DriveAhead()).out_dir


def test_a_machine_on_tracks_logs_its_base_pose(tmp_path):
    """fixed_base false: joints.csv ends with the base_link pose, and the heading it records is the direction the
    machine drives in. The log still replays as a csv motion (the base columns are not joints)."""
    from opera_taichi.motion import read_joint_csv

    out = _drive_ahead_on_tracks(tmp_path, math.radians(30), 3.0)
    with open(out / "joints.csv") as fh:
        header = next(csv.reader(fh))
    assert header[-6:] == [f"base.{k}" for k in ("x", "y", "z", "roll", "pitch", "yaw")]
    cols = read_csv_columns(out / "joints.csv")
    x, y, yaw = cols["base.x"], cols["base.y"], cols["base.yaw"]
    assert yaw[0] == pytest.approx(math.radians(30), abs=1e-3)
    travel = np.hypot(x[-1] - x[0], y[-1] - y[0])
    assert travel > 0.5
    heading = math.atan2(y[-1] - y[0], x[-1] - x[0])
    assert abs(math.remainder(heading - yaw.mean(), 2 * math.pi)) < math.radians(3)
    assert np.abs(cols["base.roll"]).max() < 0.05 and np.abs(cols["base.pitch"]).max() < 0.05   # flat ground
    assert set(read_joint_csv(out / "joints.csv", JOINTS).joints) == set(JOINTS)


def test_base_yaw_is_continuous_through_pi(tmp_path):
    """A machine heading -x reads yaw about pi; the recorded column never jumps by 2 pi between samples."""
    yaw = read_csv_columns(_drive_ahead_on_tracks(tmp_path, math.pi, 1.5) / "joints.csv")["base.yaw"]
    assert np.abs(np.abs(yaw) - math.pi).max() < 0.05      # heading -x all along
    assert np.abs(np.diff(yaw)).max() < 0.01               # and no +-2 pi jump as it wobbles across pi


def test_a_resumed_csv_of_another_layout_is_refused_not_appended(tmp_path):
    """A checkpoint of a version whose joints.csv had other columns: appending rows of the new layout would make a
    file no reader can parse, so the resume stops first and leaves the file as it was."""
    from opera_taichi.errors import UserError
    from opera_taichi.observers import JointsCsv, RunContext
    from opera_taichi.simulation import Simulation

    sim = Simulation.from_scene(ROOT / "scenes" / "zx120_dig_cycle.yaml", {"machine.fixed_base": False})
    try:
        old = "t," + ",".join(f"{j}.{k}" for j in JOINTS for k in ("q", "qd", "q_cmd", "qd_cmd", "effort")) + "\n"
        (tmp_path / "joints.csv").write_text(old + "0" + ",0" * 20 + "\n")
        before = (tmp_path / "joints.csv").read_bytes()
        rec = JointsCsv(100.0)
        rec.set_state({"offset": len(before)})
        with pytest.raises(UserError, match="joints.csv has the columns of another version"):
            rec.start(sim, RunContext(out=tmp_path, resumed=True))
        assert (tmp_path / "joints.csv").read_bytes() == before
    finally:
        sim.close()


def test_a_run_covers_its_whole_duration():
    """The step count was int(round(duration / dt)), half to even: 0.025 s at dt 0.01 ended at 0.02 s, and 0.0005 s
    at dt 0.001 ran no step at all, both with status done."""
    from opera_taichi.runner import steps_to_cover

    assert steps_to_cover(0.025, 0.01) == 3 and steps_to_cover(0.0005, 0.001) == 1
    assert steps_to_cover(0.0151, 0.01) == 2
    # a whole number of steps is that number, float noise aside (0.3 / 0.1 = 2.9999999999999996)
    assert steps_to_cover(0.3, 0.1) == 3 and steps_to_cover(0.7, 0.1) == 7
    assert steps_to_cover(20.0, 0.001) == 20_000 and steps_to_cover(3600.0, 1e-5) == 360_000_000
