"""A run folder cannot lie: a run never writes into another run's folder, its manifest's status is always true,
and `validate` refuses what would fail at run time."""
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from opera_taichi.cli import main

ROOT = Path(__file__).resolve().parent.parent
DIG = str(ROOT / "scenes" / "zx120_dig_cycle.yaml")
EXCAVATION = str(ROOT / "scenes" / "zx120_excavation.yaml")


def _snapshot(folder: Path) -> dict:
    return {p.relative_to(folder): (p.stat().st_mtime_ns, p.read_bytes()) for p in folder.rglob("*") if p.is_file()}


def test_out_into_an_existing_run_is_refused_and_nothing_in_it_changes(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", DIG, "--out", str(out), "--quiet", "--set", "sim.duration=0.2"]) == 0
    before = _snapshot(out)
    capsys.readouterr()
    assert main(["run", EXCAVATION, "--out", str(out), "--quiet", "--set", "sim.duration=0.1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds a run already (status done)" in err[0] and "--overwrite" in err[0]
    assert _snapshot(out) == before
    assert main(["run", DIG, "--out", str(out / "sub" / "run"), "--quiet", "--set", "sim.duration=0.1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"lies inside the run folder {out}" in err[0], err
    assert _snapshot(out) == before
    (tmp_path / "web").mkdir()   # another tool's manifest.json above a run folder is no run
    (tmp_path / "web" / "manifest.json").write_text('{"name": "app", "start_url": "/"}')
    assert main(["run", DIG, "--out", str(tmp_path / "web" / "run"), "--quiet", "--set", "sim.duration=0.1",
                 "--set", "output.plots=false"]) == 0


def test_overwrite_empties_the_folder_first(tmp_path):
    out = tmp_path / "run"
    assert main(["run", DIG, "--out", str(out), "--quiet", "--set", "sim.duration=0.2"]) == 0
    (out / "notes.txt").write_text("a file of the old run")
    assert main(["run", DIG, "--out", str(out), "--quiet", "--overwrite", "--set", "sim.duration=0.1",
                 "--set", "output.plots=false"]) == 0
    assert not (out / "notes.txt").exists() and not (out / "joints.png").exists()   # nothing stale is kept
    assert json.loads((out / "manifest.json").read_text())["sim_time"] == pytest.approx(0.1)


def _fake_run(folder: Path, pid: int, status: str = "running") -> None:
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_text(json.dumps({"status": status, "pid": pid, "host": socket.gethostname()}))
    (folder / "joints.csv").write_text("t\n0.0\n")


def test_overwrite_refuses_a_run_that_is_still_going_and_replaces_a_dead_one(tmp_path, capsys):
    """Emptied under a live run, the folder would mix the two runs' files (the old one writes on)."""
    live = tmp_path / "live"
    _fake_run(live, os.getpid())   # this process: alive, on this host
    before = _snapshot(live)
    assert main(["run", DIG, "--out", str(live), "--quiet", "--overwrite", "--set", "sim.duration=0.1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is still running" in err[0] and str(os.getpid()) in err[0], err
    assert _snapshot(live) == before
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    dead = tmp_path / "dead"
    _fake_run(dead, gone.pid)
    assert main(["run", DIG, "--out", str(dead), "--quiet", "--overwrite", "--set", "sim.duration=0.1",
                 "--set", "output.plots=false"]) == 0
    assert json.loads((dead / "manifest.json").read_text())["status"] == "done"


@pytest.mark.parametrize("text", ["[]", "3", "{"])
def test_a_manifest_that_is_no_json_object_reads_as_unreadable(tmp_path, capsys, text):
    from opera_taichi.runs import run_row

    (tmp_path / "manifest.json").write_text(text)
    assert run_row(tmp_path)["status"] == "unreadable"
    assert main(["run", "--resume", str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unreadable manifest" in err[0], err


def test_a_second_ctrl_c_while_the_run_folder_closes_skips_the_plots_not_the_status(tmp_path, monkeypatch, capsys):
    from opera_taichi import runner

    def interrupted(self, sim, status, message):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner.Plots, "close", interrupted)
    out = tmp_path / "run"
    assert main(["run", DIG, "--out", str(out), "--quiet", "--set", "sim.duration=0.2"]) == 130
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "done" and "closing interrupted: Plots not closed" in manifest["message"]
    assert (out / "summary.json").is_file() and not (out / "joints.png").exists()   # closed after the plots


def test_an_observer_that_cannot_start_ends_the_run_before_its_files(tmp_path):
    """A bridge whose topics do not fit the scene (found as it starts): the manifest says bad input, and no
    observer that never started is closed (no empty CSVs, no plots of nothing, no summary of no run)."""
    from opera_taichi.errors import UserError
    from opera_taichi.observers import Observer
    from opera_taichi.runner import run_scene
    from opera_taichi.scene import load_scene

    class Unplugged(Observer):
        def start(self, sim, run):
            raise UserError("bridge.rates.nosuch: no such topic in this scene")

        def close(self, sim, status, message):
            raise AssertionError("closed though it never started")

    out = tmp_path / "run"
    with pytest.raises(UserError, match="nosuch"):
        run_scene(load_scene(DIG, ["sim.duration=0.1"]), out_dir=out, quiet=True, observers=[Unplugged()])
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "bad input" and "nosuch" in manifest["message"]
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json"]


def test_a_non_empty_folder_that_is_no_run_is_refused(tmp_path, capsys):
    (tmp_path / "thesis.tex").write_text("x")
    assert main(["run", DIG, "--out", str(tmp_path), "--quiet", "--overwrite"]) == 2
    assert "is not empty and holds no run" in capsys.readouterr().err
    assert (tmp_path / "thesis.tex").read_text() == "x"


def test_a_run_that_fails_at_run_time_says_so_in_its_manifest(tmp_path, monkeypatch):
    """A user error found only while the soil is built (here: the validate-time checks bypassed) ends as
    `bad input`, never `running`."""
    from opera_taichi import dem_soil

    monkeypatch.setattr(dem_soil.DemSoil, "check_model", classmethod(lambda cls, soil: {}))
    out = tmp_path / "run"
    assert main(["run", EXCAVATION, "--out", str(out), "--quiet", "--set", "soil.overrides.radius=0.5"]) == 2
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "bad input" and "two particles" in manifest["message"]


@pytest.mark.parametrize("radius, words", [
    ("0.5", "the largest radius that fits is 0.2272 m"),
    ("0.002", "GiB of memory is available; the smallest radius that fits is about"),
])
def test_validate_refuses_what_would_fail_at_run_time(radius, words, capsys):
    assert main(["validate", EXCAVATION, "--set", f"soil.overrides.radius={radius}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {EXCAVATION}: soil.overrides.radius: ") and words in err[0], err


@pytest.mark.parametrize("every, words", [(2.0, "it stopped at 0.5 s, before its first checkpoint (every 2 s)"),
                                          (None, "it was run without --checkpoint-every")])
def test_resume_without_a_checkpoint_says_why(tmp_path, capsys, every, words):
    run = tmp_path / "run"
    _fake_run(run, os.getpid(), status="interrupted")
    manifest = json.loads((run / "manifest.json").read_text())
    manifest.update(sim_time=0.5, **({"checkpoint_every": every} if every else {}))
    (run / "manifest.json").write_text(json.dumps(manifest))
    assert main(["run", "--resume", str(run), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no checkpoint to resume from" in err[0] and words in err[0], err


def test_a_run_driven_from_python_resumes_only_with_a_driver(tmp_path, capsys):
    """Resumed by the CLI with no driver, the scene's motion script would have taken over without a word."""
    import opera_taichi as ot
    from opera_taichi.scene import load_scene

    def driver(sim, t):
        if t > 0.3:
            raise KeyboardInterrupt
        return {"boom_joint": -0.8 + 0.1 * t}

    out = tmp_path / "run"
    scene = load_scene(DIG, ["sim.duration=0.5", "output.plots=false"])
    with pytest.raises(KeyboardInterrupt):
        ot.run_scene(scene, out_dir=out, quiet=True, controller=ot.CallableController(driver), checkpoint_every=0.1)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "interrupted" and manifest["driver"] == "python"
    assert main(["run", "--resume", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "was driven by python, not its scene's motion script" in err[0], err
    steady = ot.CallableController(lambda sim, t: {"boom_joint": -0.8 + 0.1 * min(t, 0.3)})
    result = ot.run_scene(load_scene(DIG, ["sim.duration=0.5", "output.plots=false"]), out_dir=out, quiet=True,
                          controller=steady, resume=True)
    assert result.status == "done"


def test_a_tool_that_starts_inside_the_soil_is_named_as_the_likely_cause(tmp_path, capsys):
    blade = str(ROOT / "scenes" / "blade_cut.yaml")
    assert main(["run", blade, "--out", str(tmp_path / "run"), "--quiet", "--set", "soil.overrides.radius=0.04",
                 "--set", "tools.0.start=[1.0,0,-0.2]", "--set", "tools.0.velocity=[0,0,0]",
                 "--set", "sim.duration=0.2", "--set", "output.plots=false"]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "soil.max_speed" in err[0] and "starts inside the soil" in err[0], err
    assert json.loads((tmp_path / "run" / "manifest.json").read_text())["status"] == "diverged"


def test_a_refused_resume_leaves_the_run_folder_as_it_was(tmp_path, capsys):
    """The newest checkpoint is of another scene: the resume is refused in one line, and the interrupted run's
    record (its manifest's status, message and time) is what it was: nothing in the folder changed."""
    import numpy as np

    import opera_taichi as ot
    from opera_taichi.errors import UserError
    from opera_taichi.observers import latest_checkpoint
    from opera_taichi.scene import load_scene

    def driver(sim, t):
        if t > 0.3:
            raise KeyboardInterrupt
        return {"boom_joint": -0.8 + 0.1 * t}

    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        ot.run_scene(load_scene(DIG, ["sim.duration=0.5", "output.plots=false"]), out_dir=out, quiet=True,
                     controller=ot.CallableController(driver), checkpoint_every=0.1)
    ckpt = latest_checkpoint(out)
    with np.load(ckpt) as f:
        arrays = {k: f[k] for k in f.files}
    header = json.loads(str(arrays["header"]))
    header["model"] = "0" * len(str(header["model"]))  # as a checkpoint of another scene reads
    arrays["header"] = np.array(json.dumps(header))
    with open(ckpt, "wb") as fh:
        np.savez(fh, **arrays)
    before = {p: data for p, (_, data) in _snapshot(out).items()}
    steady = ot.CallableController(lambda sim, t: {"boom_joint": -0.8 + 0.1 * min(t, 0.3)})
    with pytest.raises(UserError, match="another scene"):
        ot.run_scene(load_scene(DIG, ["sim.duration=0.5", "output.plots=false"]), out_dir=out, quiet=True,
                     controller=steady, resume=True)
    assert {p: data for p, (_, data) in _snapshot(out).items()} == before   # (the manifest was "running" meanwhile)
    assert json.loads((out / "manifest.json").read_text())["status"] == "interrupted"


def test_runs_lists_damaged_and_odd_folders_with_a_true_status(tmp_path, capsys):
    """A summary.json of something else, a start time that is a number, pids no process has: every folder is listed
    (one bad folder used to cost the whole listing a traceback) and a run whose pid cannot be alive reads died."""
    from opera_taichi.runs import list_runs

    for name, pid in (("huge", 99_999_999_999_999), ("minus", -1), ("zero", 0)):
        _fake_run(tmp_path / name, pid)
    (tmp_path / "huge" / "summary.json").write_text("[1]")
    (tmp_path / "minus" / "summary.json").write_text('{"tools": [1, 2]}')
    (tmp_path / "zero" / "summary.json").write_text('{"tools": {"bucket": 3}}')
    record = json.loads((tmp_path / "zero" / "manifest.json").read_text())
    (tmp_path / "zero" / "manifest.json").write_text(json.dumps({**record, "started": 5}))
    _fake_run(tmp_path / "iso", os.getpid())
    record = json.loads((tmp_path / "iso" / "manifest.json").read_text())
    (tmp_path / "iso" / "manifest.json").write_text(json.dumps({**record, "started": "2026-11-27T06:00:00"}))
    rows = {r["name"]: r for r in list_runs(tmp_path)}
    assert {n: rows[n]["status"] for n in rows} == {"huge": "died", "minus": "died", "zero": "died", "iso": "running"}
    assert main(["runs", str(tmp_path)]) == 0
    assert capsys.readouterr().out.count("died") == 3


@pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="the process start time is read from Linux's /proc")
def test_a_run_whose_pid_another_process_has_now_reads_died(tmp_path):
    """A run killed long ago whose pid the system gave to another live process: the manifest's recorded start time
    of the run's process tells them apart (the pid alone had said running, and --resume refused)."""
    from opera_taichi.runner import process_start, run_folder_status

    _fake_run(tmp_path / "reused", os.getpid())
    record = json.loads((tmp_path / "reused" / "manifest.json").read_text())
    mine = process_start(os.getpid())
    assert mine is not None and mine.isdigit()
    (tmp_path / "reused" / "manifest.json").write_text(json.dumps({**record, "pid_start": str(int(mine) - 1)}))
    assert run_folder_status(tmp_path / "reused")[0] == "died"
    (tmp_path / "reused" / "manifest.json").write_text(json.dumps({**record, "pid_start": mine}))
    assert run_folder_status(tmp_path / "reused")[0] == "running"
