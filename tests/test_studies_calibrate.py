"""calibrate: what it refuses before the first trial (each check stops before a trial would start)."""
from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("dask.distributed")
pytest.importorskip("optuna")

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


def _calibration(folder: Path, name: str, calibrate: str, set_extra: str = "") -> Path:
    (folder / "force.csv").write_text("t,tool,fx\n" + "".join(f"{0.02 * i:.2f},blade,{500 + 40 * i}\n"
                                                              for i in range(16)))
    (folder / "plain.csv").write_text("t,fx\n" + "".join(f"{0.02 * i:.2f},{500 + 40 * i}\n" for i in range(16)))
    path = folder / f"{name}.yaml"
    path.write_text(BASE + set_extra.replace("{folder}", str(folder)) + f"calibrate:\n  {calibrate}\n")
    return path


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


def test_refine_by_default_with_too_few_trials_says_it_is_off(tmp_path, capsys, no_trials):
    from opera_taichi.studies.calibrate import calibrate

    path = _calibration(tmp_path, "three", "parameters: {soil.overrides.friction_angle_deg: {low: 30, high: 40}}\n"
                        f"  trials: 3\n  objective: force\n  force: {FORCE}")
    with pytest.raises(_TrialStarted):
        calibrate(path, out=tmp_path / "out")
    assert "note: refine off: 3 trial(s), refining needs 4" in capsys.readouterr().err
