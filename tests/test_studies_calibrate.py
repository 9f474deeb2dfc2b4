"""calibrate: what it refuses before the first trial, what a resume may continue, and the preset it writes.

One real calibration (a single 0.3 s trial of a coarse blade cut, about a hundred 12 cm grains, on a one-worker Dask
cluster) is run once for this file; every other check stops before a trial would start."""
from __future__ import annotations

import csv
import dataclasses
import json
import shutil
from pathlib import Path

import pytest

pytest.importorskip("dask.distributed")
pytest.importorskip("optuna")

from conftest import a_file_a_run_folder_and  # noqa: E402
from opera_taichi.cli import main  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BASE = f"""
name: fit
scene: {ROOT / 'scenes' / 'blade_cut.yaml'}
set:
  sim.duration: 0.3
  soil.overrides.radius: 0.12
  soil.settle_time: 0.2
  output.plots: false
  output.wrench_rate: 100
"""
FORCE = "{file: force.csv, tool: blade, column: fx, t: [0.05, 0.3], smooth_s: 0.05}"
# a preset file from an earlier calibration (friction, density), this one fits cohesion on top of it
EARLIER = "preset: sand\nfriction_angle_deg: 38.5\ndensity: 1700.0\ncalibration: {loss: 0.2}\n"


def _calibration(folder: Path, name: str, calibrate: str, set_extra: str = "") -> Path:
    (folder / "force.csv").write_text("t,tool,fx\n" + "".join(f"{0.02 * i:.2f},blade,{500 + 40 * i}\n"
                                                              for i in range(16)))
    (folder / "plain.csv").write_text("t,fx\n" + "".join(f"{0.02 * i:.2f},{500 + 40 * i}\n" for i in range(16)))
    (folder / "earlier.yaml").write_text(EARLIER)
    path = folder / f"{name}.yaml"
    path.write_text(BASE + set_extra.replace("{folder}", str(folder)) + f"calibrate:\n  {calibrate}\n")
    return path


COHESION = ("parameters: {soil.overrides.cohesion: {low: 0, high: 2000}}\n  trials: 1\n  refine: false\n"
            f"  sampler: random\n  objective: force\n  force: {FORCE}")
WITH_EARLIER = "  soil.preset_file: {folder}/earlier.yaml\n"  # a --set path is the scene file's: absolute


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A finished one-trial calibration of cohesion on top of earlier.yaml: (its folder, its study file)."""
    folder = tmp_path_factory.mktemp("cal")
    path = _calibration(folder, "fit", COHESION, WITH_EARLIER)
    assert main(["calibrate", str(path), "--workers", "1", "--out", str(folder / "out"), "--quiet"]) == 0
    return folder, path


class _TrialStarted(Exception):
    pass


@pytest.fixture
def no_trials(monkeypatch):
    """Starting the cluster (the first trial) fails the test at once: the checks under test come before it."""
    def refuse(*args, **kwargs):
        raise _TrialStarted("a trial was about to run")

    monkeypatch.setattr("opera_taichi.studies.study.Cluster", refuse)


@pytest.mark.parametrize("calibrate, args, words", [
    ("objective: force\n  force: {file: force.csv, tool: blade, smooth_s: fast}", [],
     "calibrate.force.smooth_s: expected a number of seconds >= 0"),
    ("objective: force\n  force: {file: plain.csv, tool: bucket}", [],  # a measured curve of no named tool
     "calibrate.force.tool: tool_wrench.csv has no tool 'bucket' (tools: blade)"),
    ("objective: metric\n  metric: {name: wrench.bucket.fx.mean, target: 1000}", [],
     "calibrate.metric.name: wrench.bucket.fx.mean: the runs have no tool 'bucket' (tools: blade)"),
    ("objective: metric\n  metric: {name: summary.tools.bucket.soil_held_kg, target: 1000}", [],
     "calibrate.metric.name: summary.tools.bucket.soil_held_kg: the runs have no tool 'bucket' (tools: blade)"),
    ("objective: metric\n  metric: {name: wrench.blade.fx, target: 1000}", [],
     "calibrate.metric.name: expected wrench.<tool>.<column>.<stat>"),
    ("objective: force\n  force: {file: force.csv, tool: blade, column: fx, t: [0.05, 0.5]}", [],  # 0.3 s trials
     "calibrate.force.t: [0.05, 0.5] ends after the trials' end at sim.duration 0.3 s"),
    (f"objective: force\n  refine: true\n  trials: 3\n  force: {FORCE}", [],
     "calibrate.refine: true needs trials >= 4 (3 to fit, then the refined one), got 3;"),
    (f"objective: force\n  refine: true\n  trials: 8\n  force: {FORCE}", ["--trials", "2"],
     "calibrate.refine: true needs trials >= 4 (3 to fit, then the refined one), got 2 (--trials)"),
])
def test_settings_no_trial_can_fix_are_refused_before_the_first(tmp_path, capsys, no_trials, calibrate, args,
                                                                 words):
    path = _calibration(tmp_path, "bad", "parameters: {soil.overrides.friction_angle_deg: {low: 30, high: 40}}\n  "
                        + calibrate)
    assert main(["calibrate", str(path), "--out", str(tmp_path / "out"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and "\n" not in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("row, words", [
    ("0.06,blade,nan", "force.csv: line 5, column fx: expected a finite number, got 'nan'"),
    ("0.06,blade,", "force.csv: line 5, column fx: expected a finite number, got ''"),
    ("0.06,blade", "force.csv: line 5: expected 3 fields (as the header), got 2"),
])
def test_a_measured_force_curve_with_a_bad_cell_is_refused_naming_its_line(tmp_path, capsys, no_trials, row, words):
    """A NaN or empty force cell passed the check and scored every trial nan ("no trial finished"), an empty one
    read as "no numeric column 'fx'", and a short row was dropped: each is refused before the first trial."""
    path = _calibration(tmp_path, "bad", COHESION)
    lines = (tmp_path / "force.csv").read_text().splitlines()
    lines[4] = row  # line 5 of the file
    (tmp_path / "force.csv").write_text("\n".join(lines) + "\n")
    assert main(["calibrate", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "calibrate.force.file: " in err and words in err and "\n" not in err, err


def test_a_measured_force_header_with_spaces_after_the_commas_is_read(tmp_path, no_trials):
    from opera_taichi.studies.calibrate import calibrate

    path = _calibration(tmp_path, "spaced", COHESION)
    text = (tmp_path / "force.csv").read_text()
    (tmp_path / "force.csv").write_text(text.replace("t,tool,fx", "t, tool, fx", 1))
    with pytest.raises(_TrialStarted):  # every check passed: the first trial was about to start
        calibrate(path, out=tmp_path / "out")


def test_a_compare_metric_objective_comparison_json_cannot_hold_is_refused_before_the_first(tmp_path, capsys,
                                                                                          no_trials):
    """objective: metric on a misspelt compare.<key> simulated every trial, then said "no trial finished"."""
    path = _calibration(tmp_path, "cmp", "parameters: {soil.overrides.cohesion: {low: 0, high: 2000}}\n  trials: 1\n"
                        "  objective: metric\n  metric: {name: compare.terrain_rmse, target: 0.0}")
    (tmp_path / "scan.xyz").write_text("0 0 0\n1 0 0\n0 1 0\n")
    path.write_text(path.read_text() + "reference: {terrain: scan.xyz}\n")
    assert main(["calibrate", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "calibrate.metric.name: compare.terrain_rmse: comparison.json has no 'terrain_rmse' with reference " \
           "terrain; its keys: " in err and "terrain_rmse_m" in err and "\n" not in err, err


def test_a_force_window_past_the_runs_end_is_not_scored(tmp_path):
    """A run whose force stops before the window does (a trial cut short, a duration the window outlasts): its force
    held at the last sample was scored as if measured; now it is refused, naming calibrate.force.t."""
    from opera_taichi.errors import UserError
    from opera_taichi.studies.calibrate import objective_value

    _calibration(tmp_path, "x", COHESION)
    run = tmp_path / "run"
    run.mkdir()
    (run / "tool_wrench.csv").write_text("t,tool,fx\n" + "".join(f"{0.02 * i:.2f},blade,{500 + 40 * i}\n"
                                                                  for i in range(11)))  # 0 .. 0.2 s
    spec = {"objective": "force", "force": {"file": str(tmp_path / "force.csv"), "tool": "blade", "column": "fx",
                                            "t": [0.05, 0.3], "smooth_s": 0.05}}
    with pytest.raises(UserError, match=r"calibrate\.force\.t: .* the run's force spans 0-0.2 s"):
        objective_value(run, spec)
    spec["force"]["t"] = [0.05, 0.2]  # within it: scored (the same curve: only the smoothing at its end differs)
    assert objective_value(run, spec)["loss"] < 0.02


def test_a_preset_file_another_calibration_wrote_is_not_overwritten(tmp_path, capsys, no_trials):
    """preset_file is the study file's, whatever --out: a second calibration into another folder overwrote the
    first's preset. It is refused before the first trial; the calibration that wrote it (same out) goes on."""
    from opera_taichi.studies.calibrate import calibrate

    path = _calibration(tmp_path, "fit", COHESION + "\n  preset_file: fitted.yaml")
    first = f"preset: sand\ncohesion: 800.0\ncalibration: {{out: {tmp_path / 'first'}, loss: 0.1}}\n"
    (tmp_path / "fitted.yaml").write_text(first)
    assert main(["calibrate", str(path), "--out", str(tmp_path / "second")]) == 2
    err = capsys.readouterr().err.strip()
    assert f"calibrate.preset_file: {tmp_path / 'fitted.yaml'} holds the preset of the calibration in " \
           f"{tmp_path / 'first'}; give another preset_file" in err and "\n" not in err, err
    assert (tmp_path / "fitted.yaml").read_text() == first and not (tmp_path / "second").exists()
    with pytest.raises(_TrialStarted):  # its own calibration's folder: every check passed
        calibrate(path, out=tmp_path / "first")


def test_refine_by_default_with_too_few_trials_says_it_is_off(tmp_path, capsys, no_trials):
    from opera_taichi.studies.calibrate import calibrate

    path = _calibration(tmp_path, "three", "parameters: {soil.overrides.friction_angle_deg: {low: 30, high: 40}}\n"
                        f"  trials: 3\n  objective: force\n  force: {FORCE}")
    with pytest.raises(_TrialStarted):
        calibrate(path, out=tmp_path / "out")
    assert "note: refine off: 3 trial(s), refining needs 4" in capsys.readouterr().err


def test_written_preset_reproduces_the_best_trials_soil(fitted):
    """The preset holds what the trial's soil.preset_file gave (friction, density), not only the fitted cohesion."""
    import yaml

    from opera_taichi.scene import load_scene
    from opera_taichi.soil import resolve_scene_soil

    folder, _ = fitted
    result = json.loads((folder / "out" / "calibration.json").read_text())
    preset = yaml.safe_load(Path(result["preset_file"]).read_text())
    assert preset["friction_angle_deg"] == 38.5 and preset["density"] == 1700.0
    assert preset["calibration"]["out"] == str((folder / "out").resolve())  # whose it is: see _check_preset
    with open(folder / "out" / "calibration.csv", newline="") as fh:
        (row,) = list(csv.DictReader(fh))
    run_dir = Path(row["run_dir"])
    trial_bulk = json.loads((run_dir / "manifest.json").read_text())["soil"]["bulk"]
    scene = load_scene(ROOT / "scenes" / "blade_cut.yaml", [f"soil.preset_file={result['preset_file']}"])
    bulk = dataclasses.asdict(resolve_scene_soil(scene.soil))
    assert bulk["cohesion"] == pytest.approx(result["best_parameters"]["soil.overrides.cohesion"])
    assert {k: v for k, v in bulk.items() if k != "radius"} == \
        pytest.approx({k: v for k, v in trial_bulk.items() if k != "radius"})


@pytest.mark.parametrize("change, words", [
    (lambda t: t.replace("t: [0.05, 0.3]", "t: [0.1, 0.3]"), "another calibrate.force.t;"),
    # (longer: a duration shorter than the force window is refused before the journal is read)
    (lambda t: t.replace("sim.duration: 0.3", "sim.duration: 0.35"), "another set.sim.duration, scene;"),
    (lambda t: t.replace("high: 2000", "high: 3000"), "another calibrate.parameters.soil.overrides.cohesion;"),
    (lambda t: t.replace("objective: force", "objective: metric\n  metric: {name: wrench.blade.fx.mean, "
                                             "target: 900}"), "another calibrate.objective, calibrate.force,"),
    (lambda t: t.replace("name: fit", "name: other"), "holds calibration 'fit', not 'other';"),
])
def test_resume_continues_only_the_same_calibration(fitted, tmp_path, capsys, no_trials, change, words):
    folder, path = fitted
    out = tmp_path / "out"
    shutil.copytree(folder / "out", out)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    other = folder / f"changed-{tmp_path.name}.yaml"
    other.write_text(change(path.read_text()))
    assert main(["calibrate", str(other), "--workers", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and "give another --out" in err and "\n" not in err, err
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before  # nothing rewritten


def test_resume_of_the_same_calibration_keeps_its_trials(fitted, tmp_path, capsys, no_trials):
    folder, path = fitted
    shutil.copytree(folder / "out", tmp_path / "out")
    # the earlier preset file is read again, not trusted by name: the same content resumes
    (folder / "earlier.yaml").write_text(EARLIER)
    assert main(["calibrate", str(path), "--out", str(tmp_path / "out")]) == 0
    assert "1 trials (1 finished before)" in capsys.readouterr().err
    # ... a changed one does not: those trials' soil is not this scene's
    (folder / "earlier.yaml").write_text(EARLIER.replace("38.5", "30.0"))
    try:
        assert main(["calibrate", str(path), "--out", str(tmp_path / "out")]) == 2
        assert "another scene;" in capsys.readouterr().err
    finally:
        (folder / "earlier.yaml").write_text(EARLIER)


def test_a_journal_without_a_record_of_its_objective_is_not_resumed(tmp_path, capsys, no_trials):
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    path = _calibration(tmp_path, "fit", COHESION)
    (tmp_path / "out").mkdir()
    storage = JournalStorage(JournalFileBackend(str(tmp_path / "out" / "optuna.journal")))
    old = optuna.create_study(study_name="fit", storage=storage)  # as an older calibrate left it
    old.add_trial(optuna.trial.create_trial(
        params={"soil.overrides.cohesion": 500.0}, value=0.3,
        distributions={"soil.overrides.cohesion": optuna.distributions.FloatDistribution(0, 2000)}))
    assert main(["calibrate", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "holds 1 trial(s) with no record of what they were scored against" in err
    assert not (tmp_path / "out" / "soil_preset.yaml").exists()


def test_a_calibration_writes_only_into_a_folder_of_its_own(tmp_path, capsys, no_trials):
    """--out a file or a run folder (or inside one): one line, exit 2, before the first trial, nothing touched."""
    path = _calibration(tmp_path, "fit", COHESION)
    cases, _ = a_file_a_run_folder_and(tmp_path, "study", "study.json", '{"name": "fit"}')
    for out, words in cases:
        before = sorted(p.name for p in tmp_path.rglob("*"))
        assert main(["calibrate", str(path), "--workers", "1", "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert f"out: {out} {words}" in err and "\n" not in err, err
        assert sorted(p.name for p in tmp_path.rglob("*")) == before
