"""Checkpoint and resume: a run killed with SIGKILL mid-run and resumed from its run folder ends with the same
final state, bit for bit, as the same run left alone, and its CSVs and its bag have no duplicate or missing rows.

The excavation scene at a coarse setting (12 cm grains, the dig path compressed into 3.5 s so the bucket is in the
soil for most of it)."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import kill_after_first_checkpoint
from opera_taichi.cli import main

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "zx120_excavation.yaml"
COARSE = ["--set", "soil.overrides.radius=0.12", "--set", "sim.duration=3.5", "--set", "output.plots=false",
          "--set", "output.particles_final=true", "--set", "output.bag=mcap"]
for _i, _t in enumerate((0.0, 0.5, 1.2, 2.5, 3.0, 3.5)):
    COARSE += ["--set", f"motion.waypoints.{_i}.t={_t}"]
FILES = ("joints.csv", "tool_wrench.csv", "soil_mass.csv")


def _cli(*args):
    return [sys.executable, str(ROOT / "cli.py"), *args]


def _env():
    return dict(os.environ, TI_CPU_MAX_NUM_THREADS="1")


@pytest.fixture(scope="module")
def alone_and_resumed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("resume")
    alone, killed = tmp / "alone", tmp / "killed"
    run = ["run", str(SCENE), "--quiet", *COARSE]
    # left alone, without checkpoints: taking a checkpoint must not change the run either
    assert subprocess.run(_cli(*run, "--out", str(alone)), env=_env(), cwd=ROOT).returncode == 0
    proc = subprocess.Popen(_cli(*run, "--checkpoint-every", "0.5", "--out", str(killed)), env=_env(), cwd=ROOT)
    kill_after_first_checkpoint(proc, killed)   # (t = 0.5 s of 3.5): 3 s of digging are left to resume
    before = json.loads((killed / "manifest.json").read_text())
    resumed = subprocess.run(_cli("run", "--resume", str(killed)), env=_env(), cwd=ROOT, capture_output=True,
                             text=True)
    return alone, killed, before, resumed


def test_a_killed_run_resumes_to_the_same_final_state_bit_for_bit(alone_and_resumed):
    alone, killed, before, resumed = alone_and_resumed
    assert resumed.returncode == 0, resumed.stderr
    assert before["status"] == "running"          # SIGKILL leaves no chance to write anything else
    assert "status died" in resumed.stderr         # which resume reports as died
    a, b = np.load(alone / "particles_final.npz"), np.load(killed / "particles_final.npz")
    assert a["positions"].shape[0] > 500
    for key in a.files:
        assert np.array_equal(a[key], b[key]), key
    za, zb = np.load(alone / "terrain_final.npz")["z"], np.load(killed / "terrain_final.npz")["z"]
    assert np.array_equal(za, zb)
    manifest = json.loads((killed / "manifest.json").read_text())
    assert manifest["status"] == "done" and manifest["sim_time"] == pytest.approx(3.5)
    assert len(manifest["resumed"]) == 1 and manifest["resumed"][0]["previous_status"] == "died"


def test_resumed_csvs_have_no_duplicate_or_missing_rows(alone_and_resumed):
    alone, killed, _, _ = alone_and_resumed
    for name in FILES:
        assert (alone / name).read_bytes() == (killed / name).read_bytes(), name
    t = np.loadtxt(killed / "joints.csv", delimiter=",", skiprows=1, usecols=0)
    assert np.allclose(np.diff(t), 0.01) and t[0] == 0.0 and t[-1] == pytest.approx(3.5)
    wrench = np.loadtxt(alone / "tool_wrench.csv", delimiter=",", skiprows=1, usecols=2)
    assert np.abs(wrench).max() > 1000.0  # the bucket did dig: a resume that lost the soil would show here


def _bag_messages(paths):
    from mcap.reader import make_reader

    out = []
    for path in paths:
        with open(path, "rb") as fh:
            for schema, channel, message in make_reader(fh).iter_messages(log_time_order=False):
                out.append((channel.topic, message.log_time, message.sequence, bytes(message.data)))
    return out


def test_the_resumed_bag_holds_every_message_once(alone_and_resumed):
    """The killed run's bag was finished at its checkpoint (an MCAP is unreadable until its writer finishes it); the
    resume deleted the part the killed process had begun after it, and its own part continues exactly where the
    checkpoint left off: the parts hold the messages of the run left alone, byte for byte, each once."""
    from opera_taichi.ros.bag import bag_parts

    alone, killed, _, _ = alone_and_resumed
    assert bag_parts(alone) == [alone / "run.mcap"]
    parts = bag_parts(killed)
    assert len(parts) >= 2 and parts[0].name == "run.mcap"  # each checkpoint (every 0.5 s) begins a part
    assert all(p.name.startswith("run-from-step-") for p in parts[1:])
    expected = _bag_messages([alone / "run.mcap"])
    assert len(expected) > 500
    assert _bag_messages(parts) == expected
    # compare reads a run's own bag whole, its parts included, as the joint log
    from opera_taichi.studies.compare import read_joint_log

    t, q = read_joint_log(killed / "run.mcap")
    assert t[0] == 0.0 and t[-1] > 3.4 and "boom_joint" in q   # (the first part alone ends at 0.5 s)


def test_resume_refuses_a_finished_run_and_a_foreign_folder(alone_and_resumed, tmp_path, capsys):
    alone, _, _, _ = alone_and_resumed
    assert main(["run", "--resume", str(alone)]) == 2
    assert "finished already" in capsys.readouterr().err
    assert main(["run", "--resume", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a run folder" in err[0]


def test_a_checkpoint_of_another_scene_or_solver_version_is_refused(alone_and_resumed, tmp_path):
    from types import SimpleNamespace

    from opera_taichi.errors import UserError
    from opera_taichi.model import build_model
    from opera_taichi.observers import latest_checkpoint
    from opera_taichi.scene import load_scene
    from opera_taichi.simulation import load_checkpoint
    from opera_taichi.soil_solver import solver_class

    _, killed, _, _ = alone_and_resumed
    sets = [a for a in COARSE if a != "--set"]
    ckpt, dem = latest_checkpoint(killed), solver_class("dem")
    state, extra = load_checkpoint(ckpt, build_model(load_scene(SCENE, sets)), dem)
    assert state.t == pytest.approx(3.5) and "JointsCsv" in extra["observers"]   # the newest one, kept at the end
    other = build_model(load_scene(SCENE, sets + ["soil.overrides.cohesion=500"]))
    with pytest.raises(UserError, match="another scene"):
        load_checkpoint(ckpt, other, dem)
    newer = SimpleNamespace(name="dem", version=dem.version + 1)
    with pytest.raises(UserError, match="solver version"):
        load_checkpoint(ckpt, build_model(load_scene(SCENE, sets)), newer)
    # a file that is not a checkpoint (a script, a pickle) or is missing: one line saying so, not NumPy's reason
    script = tmp_path / "not_a_checkpoint.py"
    script.write_text("print('hello')\n")
    with pytest.raises(UserError, match=r"not_a_checkpoint.py: not an opera-taichi checkpoint \(an .npz"):
        load_checkpoint(script, build_model(load_scene(SCENE, sets)), dem)
    empty, torn = tmp_path / "empty.ckpt.npz", tmp_path / "torn.ckpt.npz"
    empty.write_bytes(b"")
    torn.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])  # a copy cut short
    for bad in (empty, torn):
        with pytest.raises(UserError, match="not an opera-taichi checkpoint"):
            load_checkpoint(bad, build_model(load_scene(SCENE, sets)), dem)
    with pytest.raises(UserError, match="cannot read the checkpoint"):
        load_checkpoint(tmp_path / "missing.ckpt.npz", build_model(load_scene(SCENE, sets)), dem)
