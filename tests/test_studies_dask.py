"""study and calibrate on a real Dask LocalCluster (2 worker processes, each its own Taichi runtime; one cluster for
the whole file, reached with --scheduler, so each worker starts Taichi and loads its kernels once): a 4-point
friction study of a small blade cut (resumed: finished simulations are kept and measured again for the study file as
it is now; a point that fails, in its simulation or in its comparison, is a row, not the end), and a
4-trial calibration (3 sampled, 1 refined) that recovers the friction angle of its own reference run from the run's
draft-force curve.

Each run is a 1.2 m x 0.4 m x 0.35 m sand bed of 4 cm grains (about 2,400 particles) cut 0.2 m deep at 1 m/s for
0.6 s: the blade enters the bed at about 0.1 s, and the draft is read from 0.25 s on, once the cut is under way."""
from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import pytest

pytest.importorskip("dask.distributed")
pytest.importorskip("optuna")
pytest.importorskip("pyarrow")

from opera_taichi.cli import main  # noqa: E402

pytestmark = pytest.mark.slow  # minutes: 10 DEM runs on a 2-worker cluster

ROOT = Path(__file__).resolve().parents[1]
TRUE_FRICTION_DEG = 32.0
BASE = f"""
scene: {ROOT / 'scenes' / 'blade_cut.yaml'}
set:
  sim.duration: 0.6
  soil.overrides.radius: 0.02
  soil.settle_time: 0.5
  soil.bed: [{{min: [0.0, -0.2, -0.35], max: [1.2, 0.2, 0.0]}}]
  soil.domain: {{min: [-0.3, -0.2, -0.4], max: [1.6, 0.2, 0.8]}}
  tools.0.start: [1.3, 0.0, 0.2]
  tools.0.velocity: [-1.0, 0.0, 0.0]
  output.plots: false
  output.wrench_rate: 100
"""


@pytest.fixture(scope="module")
def scheduler():
    """The address of a LocalCluster of 2 single-threaded worker processes, shared by this file's commands (a command
    making its own LocalCluster, --workers, is run by test_studies_calibrate.py)."""
    import logging

    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.ERROR) as cluster:
        yield cluster.scheduler_address


@pytest.fixture(scope="module")
def study_dir(tmp_path_factory, scheduler):
    """The 4-point study, run once for this file's tests."""
    folder = tmp_path_factory.mktemp("study")
    (folder / "friction.yaml").write_text(BASE + f"""
name: friction
parameters:
  soil.overrides.friction_angle_deg: [26, 29, {TRUE_FRICTION_DEG:g}, 35]
sampling: grid
metrics: [wrench.blade.fx.mean, manifest.particles, manifest.real_time_factor,
          {{name: draft_N, file: tool_wrench.csv, column: fx, where: {{tool: blade}}, stat: mean, t: [0.25, 0.6]}}]
""")
    code = main(["study", str(folder / "friction.yaml"), "--scheduler", scheduler, "--out", str(folder / "out"),
                 "--quiet"])
    assert code == 0
    return folder


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_study_on_a_local_cluster_table_plots_and_resume(study_dir, scheduler, capsys):
    import pyarrow.parquet as pq

    out = study_dir / "out"
    rows = _rows(out / "study.csv")
    assert [r["status"] for r in rows] == ["done"] * 4
    draft = [float(r["draft_N"]) for r in rows]
    assert draft[0] < draft[3]  # 35 deg sand pushes back harder than 26 deg sand
    assert all(int(float(r["manifest.particles"])) > 1500 for r in rows)
    table = pq.read_table(out / "study.parquet")
    assert table.num_rows == 4 and table.column("draft_N").to_pylist() == pytest.approx(draft)
    assert (out / "study.png").stat().st_size > 10_000
    for r in rows:  # each a real run folder, its row beside it
        assert json.loads((Path(r["run_dir"]) / "manifest.json").read_text())["status"] == "done"
    # resume with one more point, a new metric and a reference: the four finished simulations are kept (not run
    # again) and measured again for this file's metrics; the comparison fails (a scan far from the run), which
    # costs no simulation: each row says why, and its simulation stays finished
    (study_dir / "far.xyz").write_text("x y z\n" + "".join(f"{500 + 0.1 * i:.1f} {0.1 * j - 0.2:.1f} 0\n"
                                                          for i in range(16) for j in range(5)))
    spec = (study_dir / "friction.yaml").read_text()
    spec = spec.replace(f"{TRUE_FRICTION_DEG:g}, 35]", f"{TRUE_FRICTION_DEG:g}, 35, 38]")
    spec = spec.replace("metrics: [", "metrics: [compare.terrain_rmse_m, ")
    (study_dir / "more.yaml").write_text(spec + "reference: {terrain: far.xyz}\n")
    simulated = {r["point"]: (Path(r["run_dir"]) / "manifest.json").stat().st_mtime_ns for r in rows}
    code = main(["study", str(study_dir / "more.yaml"), "--scheduler", scheduler, "--out", str(out)])
    assert code == 1  # no point could be measured
    err = capsys.readouterr().err
    assert "5 points, 4 finished before, 1 to run" in err and "error: study: all 5 points failed" in err
    rows2 = _rows(out / "study.csv")
    assert [r["status"] for r in rows2] == ["bad input"] * 5
    assert all(r["error"].startswith("compare.terrain_rmse_m: reference.terrain: far.xyz is far from the run")
               for r in rows2), rows2[0]["error"]
    assert [float(r["draft_N"]) for r in rows2[:4]] == pytest.approx(draft)  # the other metrics still measured
    for r in rows2[:4]:
        assert (Path(r["run_dir"]) / "manifest.json").stat().st_mtime_ns == simulated[r["point"]]
    simulated[rows2[4]["point"]] = (Path(rows2[4]["run_dir"]) / "manifest.json").stat().st_mtime_ns
    # the reference fixed (the 26 deg run itself): all five measured again, none simulated again
    (study_dir / "fixed.yaml").write_text(spec + f"reference: {{against: {rows[0]['run_dir']}}}\n")
    assert main(["study", str(study_dir / "fixed.yaml"), "--out", str(out)]) == 0  # no cluster: nothing to run
    assert "5 points, 5 finished before, 0 to run" in capsys.readouterr().err
    rows3 = _rows(out / "study.csv")
    assert [r["status"] for r in rows3] == ["done"] * 5
    rmse = [float(r["compare.terrain_rmse_m"]) for r in rows3]
    assert rmse[0] == 0.0 and min(rmse[1:]) > 0.0  # against itself, and against the others
    for r in rows3:
        assert (Path(r["run_dir"]) / "manifest.json").stat().st_mtime_ns == simulated[r["point"]]
        assert json.loads((Path(r["run_dir"]) / "point.json").read_text())["row"]["status"] == "done"


def test_a_study_none_of_whose_points_finished_exits_1(study_dir, scheduler, capsys):
    # its table says why: here the bed of the 32 deg point, from the cache, is stopped by a speed limit its settled
    # grains exceed at once
    spec = (study_dir / "friction.yaml").read_text().replace(f"[26, 29, {TRUE_FRICTION_DEG:g}, 35]",
                                                              f"[{TRUE_FRICTION_DEG:g}]\n  soil.max_speed: [1e-6]")
    (study_dir / "none.yaml").write_text(spec.replace("name: friction", "name: none"))
    code = main(["study", str(study_dir / "none.yaml"), "--scheduler", scheduler, "--out", str(study_dir / "none")])
    assert code == 1
    assert "error: study: all 1 points failed" in capsys.readouterr().err
    assert [r["status"] for r in _rows(study_dir / "none" / "study.csv")] == ["diverged"]


def test_study_bad_input_is_one_line(tmp_path, capsys):
    (tmp_path / "bad.yaml").write_text(BASE + "parameters:\n  soil.overides.radius: [0.02, 0.03]\n")
    assert main(["study", str(tmp_path / "bad.yaml")]) == 2
    err = capsys.readouterr().err.strip()
    assert "soil.overides" in err and "did you mean 'overrides'" in err and "\n" not in err
    (tmp_path / "bad2.yaml").write_text(BASE + "parameters:\n  sim.duration: {low: 1}\nsampling: lhs\n")
    assert main(["study", str(tmp_path / "bad2.yaml")]) == 2
    assert "parameters.sim.duration: expected low < high" in capsys.readouterr().err
    (tmp_path / "bad3.yaml").write_text(BASE + "parameters:\n  sim.duration: [1]\nmetrics: [wrench.blade.fx]\n")
    assert main(["study", str(tmp_path / "bad3.yaml")]) == 2
    assert "metrics.0: expected wrench.<tool>.<column>.<stat>" in capsys.readouterr().err
    # what the runs would only find at their end is refused before any of them: files, tools and columns the
    # scene's runs do not write, and an actuator of a joint the machine does not have
    for i, (metric, words) in enumerate([
            ("joints.boom_joint.q.max", "metrics.0: 'joints.boom_joint.q.max': this scene's runs write no joints.csv"),
            ("wrench.bucket.fx.mean", "metrics.0: tool_wrench.csv has no tool 'bucket' (tools: blade)"),
            ("wrench.blade.fxx.mean", "metrics.0: tool_wrench.csv has no column 'fxx' (columns: t, tool, fx,"),
            ("{name: d, file: soil_mass.csv, column: in_bucket_kg}", "soil_mass.csv has no column 'in_bucket_kg'")]):
        (tmp_path / f"m{i}.yaml").write_text(BASE + f"parameters:\n  sim.duration: [1]\nmetrics: [{metric}]\n")
        assert main(["study", str(tmp_path / f"m{i}.yaml")]) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and "\n" not in err, err
    dig = ROOT / "scenes" / "zx120_dig_cycle.yaml"
    (tmp_path / "joint.yaml").write_text(f"scene: {dig}\nparameters:\n  machine.actuators.bom_joint.max_speed: [0.1]\n"
                                         "metrics: [joints.boom_joint.qdd.abs_max]\n")
    assert main(["study", str(tmp_path / "joint.yaml")]) == 2
    err = capsys.readouterr().err.strip()
    assert "parameters:" in err and "bom_joint" in err and "\n" not in err, err
    (tmp_path / "joint.yaml").write_text(f"scene: {dig}\nparameters:\n  machine.actuators.boom_joint.max_speed: [0.1]\n"
                                         "metrics: [joints.boom_joint.qdd.abs_max]\n")
    assert main(["study", str(tmp_path / "joint.yaml")]) == 2
    assert "joints.csv has no column 'boom_joint.qdd'" in capsys.readouterr().err
    # calibrate: what no trial could change is refused before the first one
    (tmp_path / "force.csv").write_text("t,tool,fx,fy,fz,tx,ty,tz\n" + "".join(
        f"{0.1 * i:.1f},blade,{100 * i},0,0,0,0,0\n" for i in range(6)))
    for i, (calibrate, words) in enumerate([
            ("parameters: {soil.overrides.nosuch: {low: 0, high: 1}}\n  objective: force\n  force: {file: force.csv, "
             "tool: blade}", "soil.overrides.nosuch: unknown key"),
            ("parameters: {soil.overrides.friction_angle_deg: {low: 24, high: 40}}\n  objective: force\n  force: "
             "{file: force.csv, tool: blade, t: [5, 9]}", "calibrate.force.t: 0 measured samples in [5, 9] (the file "
             "spans 0-0.5 s)"),
            ("parameters: {soil.overrides.friction_angle_deg: {low: 24, high: 40}}\n  objective: metric\n  metric: "
             "{name: wrench.blade.fx.mean, target: .nan}", "calibrate.metric.target: expected a finite number")]):
        (tmp_path / f"c{i}.yaml").write_text(BASE + f"calibrate:\n  {calibrate}\n")
        assert main(["calibrate", str(tmp_path / f"c{i}.yaml")]) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and "\n" not in err, err


def test_calibration_recovers_the_friction_angle_of_its_reference(study_dir, scheduler, tmp_path):
    reference = Path(_rows(study_dir / "out" / "study.csv")[2]["run_dir"])  # the 32 deg point
    shutil.copy(reference / "tool_wrench.csv", tmp_path / "measured_force.csv")
    (tmp_path / "calibrate.yaml").write_text(BASE + """
name: friction_fit
calibrate:
  parameters:
    soil.overrides.friction_angle_deg: {low: 24, high: 40}
  trials: 4
  sampler: qmc
  objective: force
  force: {file: measured_force.csv, tool: blade, column: fx, t: [0.25, 0.6], smooth_s: 0.2}
  preset_file: fitted_sand.yaml
""")
    code = main(["calibrate", str(tmp_path / "calibrate.yaml"), "--scheduler", scheduler, "--out",
                 str(tmp_path / "out")])
    assert code == 0
    result = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert result["trials"] == 4
    fitted = result["best_parameters"]["soil.overrides.friction_angle_deg"]
    assert abs(fitted - TRUE_FRICTION_DEG) <= 3.0, result
    # the objective tells the angles apart: every trial more than 3 deg off loses to the best (the sampler's first
    # draw, 32.8 deg, is near the truth already, so the fit alone would not show it)
    trials = [(float(r["soil.overrides.friction_angle_deg"]), float(r["loss"]))
              for r in _rows(tmp_path / "out" / "calibration.csv")]
    far = [loss for angle, loss in trials if abs(angle - TRUE_FRICTION_DEG) > 3.0]
    assert far and min(far) > result["best_loss"], trials
    import yaml

    preset = yaml.safe_load((tmp_path / "fitted_sand.yaml").read_text())
    assert preset["preset"] == "sand" and preset["friction_angle_deg"] == pytest.approx(fitted)
    assert "radius" not in preset and preset["calibration"]["objective"] == "force"
    # the preset file works in a scene: soil.preset_file gives the fitted angle
    from opera_taichi.model import soil_parameters
    from opera_taichi.scene import load_scene

    scene = load_scene(ROOT / "scenes" / "blade_cut.yaml", [f"soil.preset_file={tmp_path / 'fitted_sand.yaml'}"])
    bulk, _ = soil_parameters(scene.soil)
    assert math.degrees(bulk.friction_angle) == pytest.approx(fitted)
