"""study: what a study file gets wrong is refused before any simulation (every point and both ends of a random or lhs
range, the reference, CSV metrics), and study.png plots parameters that are not numbers. No simulation runs here:
each refusal is checked by load_study first (an old study tool that let one through would start running it)."""
from __future__ import annotations

from pathlib import Path

import pytest

from conftest import a_file_a_run_folder_and
from opera_taichi.cli import main
from opera_taichi.errors import UserError
from opera_taichi.studies.study import load_study

ROOT = Path(__file__).resolve().parents[1]
BASE = f"""
scene: {ROOT / 'scenes' / 'blade_cut.yaml'}
set: {{sim.duration: 0.5, soil.overrides.radius: 0.04, output.plots: false}}
"""


def _refused(tmp_path, capsys, body: str, words: str) -> None:
    """The study file is refused by load_study and by `study` (exit 2, one line naming the key), and no study
    folder is made."""
    path = tmp_path / "s.yaml"
    path.write_text(BASE + body)
    with pytest.raises(UserError) as exc:
        load_study(path)
    assert words in str(exc.value), str(exc.value)
    capsys.readouterr()
    assert main(["study", str(path), "--out", str(tmp_path / "out"), "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and "\n" not in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("body, words", [
    # a later point's soil value (the first point's is fine: it was the only one checked)
    ("parameters: {soil.overrides.friction_angle_deg: [30, 95]}\n",
     "parameters: soil.overrides.friction_angle_deg=95 (point 2 of 2): soil.overrides.friction_angle_deg: expected "
     "0 < angle < 90 degrees, got 95"),
    ("parameters: {soil.overrides.friction_angle_deg: [30, 35], soil.overrides.cohesion: [0, -100]}\n",
     "(point 2 of 4): soil.overrides.cohesion: expected cohesion >= 0 Pa, got -100"),
    # both ends of a random / lhs range, whichever values the samples happen to take
    ("parameters: {soil.overrides.friction_angle_deg: {low: 30, high: 95}}\nsampling: lhs\nsamples: 2\n",
     "parameters.soil.overrides.friction_angle_deg.high: 95: soil.overrides.friction_angle_deg: expected"),
    ("parameters: {soil.overrides.cohesion: {low: -100, high: 1000}}\nsampling: random\nsamples: 3\n",
     "parameters.soil.overrides.cohesion.low: -100: soil.overrides.cohesion: expected cohesion >= 0 Pa"),
])
def test_every_point_and_both_ends_of_a_range_are_checked_before_any_run(tmp_path, capsys, body, words):
    _refused(tmp_path, capsys, body + "metrics: [manifest.particles]\n", words)


def test_an_integer_key_is_sampled_as_integers_within_its_bounds(tmp_path):
    """sim.seed (an integer in the scene schema) sampled by random or lhs: whole numbers low..high inclusive, each
    point's scene loads with its own seed (a sampled float was refused: "expected an integer, got 2.0"); a float key
    beside it stays a float."""
    from opera_taichi.scene import load_scene
    from opera_taichi.studies.study import make_task

    path = tmp_path / "s.yaml"
    path.write_text(BASE + "parameters: {sim.seed: {low: 2, high: 5}, soil.settle_time: {low: 0.2, high: 0.3}}\n"
                           "sampling: random\nsamples: 24\nmetrics: [manifest.particles]\n")
    study = load_study(path, tmp_path / "out")
    seeds = [p["sim.seed"] for p in study.points]
    assert all(type(s) is int for s in seeds) and set(seeds) == {2, 3, 4, 5}  # both ends drawn, nothing outside
    assert all(type(p["soil.settle_time"]) is float for p in study.points)
    assert len({p["soil.settle_time"] for p in study.points}) == 24
    # lhs: one point per stratum, so 4 samples over 4 integers take each once
    path.write_text(path.read_text().replace("sampling: random", "sampling: lhs").replace("samples: 24", "samples: 4"))
    study = load_study(path, tmp_path / "out")
    assert sorted(p["sim.seed"] for p in study.points) == [2, 3, 4, 5]
    tasks = [make_task(study, i, p, tmp_path / "runs") for i, p in enumerate(study.points)]
    assert len({t["id"] for t in tasks}) == len({t["run_dir"] for t in tasks}) == 4  # four distinct runs
    for point, task in zip(study.points, tasks):
        assert f"sim.seed={point['sim.seed']}" in task["overrides"]
        assert load_scene(task["scene"], task["overrides"]).sim.seed == point["sim.seed"]
    # a grid range over it: whole steps as integers
    from opera_taichi.studies.study import _parameter

    assert [(v, type(v)) for v in _parameter("sim.seed", {"range": [0, 4], "num": 3}, "s").values] == \
        [(0, int), (2, int), (4, int)]
    # ... and a list of whole numbers written as floats (YAML's 1.0), as its bounds are
    for spec in ([1.0, 2], {"values": [0, 2.0]}):
        assert [type(v) for v in _parameter("sim.seed", spec, "s").values] == [int, int]


def test_random_draws_that_repeat_an_integer_point_run_it_once(tmp_path):
    """Six random draws of a seed in 0..1 are at most two points: each runs once (six tasks were four identical,
    deterministic simulations), and the study says how many draws repeated one."""
    path = tmp_path / "s.yaml"
    path.write_text(BASE + "parameters: {sim.seed: {low: 0, high: 1}}\nsampling: random\nsamples: 6\n"
                           "metrics: [manifest.particles]\n")
    study = load_study(path, tmp_path / "out")
    assert sorted(p["sim.seed"] for p in study.points) == [0, 1] and study.repeats == 4


@pytest.mark.parametrize("body, words", [
    ("parameters: {sim.seed: {low: 0, high: 2.5}}\nsampling: random\nsamples: 2\n",
     "parameters.sim.seed: the scene takes integers here; expected whole-number low and high, got 2.5"),
    ("parameters: {sim.seed: {low: 0.5, high: 3}}\nsampling: lhs\nsamples: 2\n",
     "parameters.sim.seed: the scene takes integers here; expected whole-number low and high, got 0.5"),
    ("parameters: {sim.seed: {range: [0, 4], num: 4}}\n",
     "parameters.sim.seed.range: the scene takes integers here; expected whole-number steps (range [0, 4] with num 4), "
     "got 1.33"),
])
def test_an_integer_key_with_bounds_that_are_not_integers_is_refused(tmp_path, capsys, body, words):
    _refused(tmp_path, capsys, body + "metrics: [manifest.particles]\n", words)


@pytest.mark.parametrize("extra, words", [
    ("reference: {terrain: scan.xyz, transform: '1,2'}",
     "reference.transform: expected x,y,z,yaw_deg[,roll_deg,pitch_deg] (m, degrees), got '1,2'"),
    ("reference: {terrain: scan.xyz, transform: {xyz: [1, 2]}}", "reference.transform.xyz: expected [x, y, z]"),
    ("reference: {terrain: scan.xyz, fit_transform: yes}",   # (YAML 1.2: the word yes, not a boolean)
     "reference.fit_transform: expected auto, plane or rigid (as compare --fit-transform), got 'yes'"),
    ("reference: {terrain: scan.xyz, fit_transform: true}",
     "reference.fit_transform: expected auto, plane or rigid (as compare --fit-transform), got True"),
    ("reference: {joints: scan.xyz, fit_transform: auto}", "reference: transform, fit_transform and terrain_before "
                                                           "place a scan of the terrain; give reference.terrain"),
    ("reference: {against: .}", "is not a run folder (no manifest.json)"),
    # the files themselves, read before the runs (they were read only when the first run was measured)
    ("reference: {joints: empty.csv}", "reference.joints: " + "{tmp}/empty.csv: empty; expected a header"),
    ("reference: {terrain: empty.csv}", "reference.terrain: " + "{tmp}/empty.csv: holds 0 usable points"),
])
def test_a_bad_reference_is_refused_before_any_run(tmp_path, capsys, extra, words):
    (tmp_path / "scan.xyz").write_text("0 0 0\n1 0 0\n0 1 0\n")
    (tmp_path / "empty.csv").write_text("")
    words = words.replace("{tmp}", str(tmp_path))
    _refused(tmp_path, capsys, "parameters: {soil.overrides.friction_angle_deg: [30, 35]}\n"
                               f"metrics: [compare.cut_volume_m3]\n{extra}\n", words)  # a key of any reference


@pytest.mark.parametrize("metrics, reference, words", [
    ("[compare.terrain_rmse]", "{terrain: scan.xyz}",
     "metrics.0: compare.terrain_rmse: comparison.json has no 'terrain_rmse' with reference terrain; its keys: run,"),
    ("[manifest.particles, compare.joints_rmse_rad]", "{terrain: scan.xyz}",  # a key of another reference
     "metrics.1: compare.joints_rmse_rad: comparison.json has no 'joints_rmse_rad' with reference terrain;"),
])
def test_a_compare_metric_comparison_json_cannot_hold_is_refused_before_any_run(tmp_path, capsys, metrics,
                                                                                reference, words):
    """A misspelt compare.<key> (terrain_rmse for terrain_rmse_m) was an empty column and a blank panel."""
    (tmp_path / "scan.xyz").write_text("0 0 0\n1 0 0\n0 1 0\n")
    _refused(tmp_path, capsys, "parameters: {soil.overrides.friction_angle_deg: [30, 35]}\n"
                               f"metrics: {metrics}\nreference: {reference}\n", words)


def test_a_compare_sub_key_the_comparison_lacks_is_an_error_naming_what_it_holds(tmp_path, monkeypatch):
    """compare.joints.<joint>.<key> with a misspelt joint was an empty cell of a row marked done; a key comparison.json
    may leave out (no second deepest point to measure between) stays an empty cell."""
    from opera_taichi.studies import compare
    from opera_taichi.studies.study import collect_metrics

    result = {"run": "x", "joints": {"boom_joint": {"rate_ratio": 0.9, "lag_s": None}}, "joints_rmse_rad": 0.1,
              "terrain_rmse_m": 0.05}
    monkeypatch.setattr(compare, "compare", lambda *a, **k: result)
    errors = {}
    names = ["compare.joints.boom_joint.rate_ratio", "compare.joints.boom_joint.lag_s",
             "compare.joints.boom_jiont.rate_ratio", "compare.max_depth_position_error_m"]
    row = collect_metrics(tmp_path, names, {"against": str(tmp_path)}, errors)
    assert row["compare.joints.boom_joint.rate_ratio"] == 0.9 and row["compare.joints.boom_joint.lag_s"] is None
    assert row["compare.max_depth_position_error_m"] is None
    assert set(errors) == {"compare.joints.boom_jiont.rate_ratio"}
    assert "comparison.json has no 'joints.boom_jiont.rate_ratio': its joints holds boom_joint" in \
        str(errors["compare.joints.boom_jiont.rate_ratio"])


def test_a_reference_joint_log_is_read_on_the_machines_joints_only(tmp_path, capsys):
    """A joint log with a `mode` column of text was refused by the study before any run (as by compare); its
    columns that name no joint of the scene's machine are not read, with a warning."""
    log = tmp_path / "log.csv"
    log.write_text("t,boom_joint,mode\n0,0.1,dig\n0.5,0.2,dig\n1.0,0.3,dump\n")
    path = tmp_path / "s.yaml"
    path.write_text(f"scene: {ROOT / 'scenes' / 'zx120_dig_cycle.yaml'}\n"
                    "set: {sim.duration: 0.5, soil.overrides.radius: 0.16, output.plots: false}\n"
                    "parameters: {soil.overrides.friction_angle_deg: [30, 35]}\n"
                    "metrics: [compare.joints_rmse_rad]\nreference: {joints: log.csv}\n")
    assert len(load_study(path).points) == 2
    assert "warning: reference.joints: log.csv: column mode names no joint of the run (swing_joint, boom_joint," \
        in capsys.readouterr().err


@pytest.mark.parametrize("metric, words", [
    ("{name: x, file: forces.csv, column: fx}",
     "metrics.0.file: expected a CSV file the runs write (soil_mass.csv, tool_wrench.csv), got 'forces.csv'"),
    ("{name: x, file: tool_wrench.csv, column: fx, t: [5, 1]}",
     "metrics.0.t: expected [t0, t1] in s with t0 < t1, got [5, 1]"),
])
def test_a_csv_metric_the_runs_cannot_give_is_refused_before_any_run(tmp_path, capsys, metric, words):
    _refused(tmp_path, capsys, f"parameters: {{soil.overrides.friction_angle_deg: [30, 35]}}\nmetrics: [{metric}]\n",
             words)


def test_study_png_plots_a_parameter_that_is_not_a_number_as_categories(tmp_path, monkeypatch):
    from opera_taichi.studies import figures

    figs = []
    monkeypatch.setattr(figures, "_save", lambda fig, path: figs.append(fig))  # keep the figure to look at it
    rows = [{"soil.preset": "dirt", "m": 2.0, "status": "done"}, {"soil.preset": "gravel", "m": 3.0, "status": "done"},
            {"soil.preset": "sand", "m": None, "status": "diverged"}]
    figures.plot_study(rows, ["soil.preset"], ["m"], tmp_path / "study.png")
    ax = figs[0].axes[0]
    points, failed = ax.lines
    assert list(points.get_xdata()) == [0, 1] and list(points.get_ydata()) == [2.0, 3.0]
    assert list(failed.get_xdata()) == [2]
    assert [t.get_text() for t in ax.get_xticklabels()] == ["dirt", "gravel", "sand"]


def test_study_png_draws_failed_points_on_the_x_axis_not_on_the_data(tmp_path, monkeypatch):
    """A diverged point's red x was drawn at the lowest finished point's value (with one finished point, on it), so
    it read as a measurement; it sits on the x axis (axes fraction 0), and the y limits are the finished points'."""
    from opera_taichi.studies import figures

    figs = []
    monkeypatch.setattr(figures, "_save", lambda fig, path: figs.append(fig))
    rows = [{"p": 1.0, "m": 5.0, "status": "done"}, {"p": 2.0, "m": None, "status": "diverged"}]
    figures.plot_study(rows, ["p"], ["m"], tmp_path / "study.png")
    ax = figs[0].axes[0]
    points, failed = ax.lines
    assert failed.get_label() == "failed" and list(failed.get_xdata()) == [2.0]
    # where the marker lands, in axes fractions: the bottom edge
    display = failed.get_transform().transform([[2.0, failed.get_ydata()[0]]])
    assert ax.transAxes.inverted().transform(display)[0][1] == pytest.approx(0.0)
    lo, hi = ax.get_ylim()
    assert lo < 5.0 < hi


def test_study_png_colours_each_parameters_points_by_the_other(tmp_path, monkeypatch):
    """With two parameters, a grid's points at one value of the first differ in the second: each column's points are
    coloured by the other parameter, on a colour bar named after it (they were all one blue, the second parameter's
    values nowhere in the first one's column); a parameter of categories gets one colour per category."""
    from opera_taichi.studies import figures

    figs = []
    monkeypatch.setattr(figures, "_save", lambda fig, path: figs.append(fig))
    rows = [{"soil.preset": s, "p": p, "m": i * 1.0, "status": "done"}
            for i, (s, p) in enumerate([("dirt", 0.1), ("dirt", 0.2), ("sand", 0.1), ("sand", 0.2)])]
    figures.plot_study(rows, ["soil.preset", "p"], ["m"], tmp_path / "study.png")
    fig = figs[0]
    fig.canvas.draw()
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    panels = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    assert [ax.get_ylabel() for ax in bars] == ["colour: p", "colour: soil.preset"]
    by_preset, by_p = (ax.collections[0] for ax in panels)
    assert list(by_preset.get_offsets()[:, 0]) == [0, 0, 1, 1] and list(by_preset.get_array()) == [0.1, 0.2, 0.1, 0.2]
    assert list(by_p.get_offsets()[:, 0]) == [0.1, 0.2, 0.1, 0.2] and list(by_p.get_array()) == [0, 0, 1, 1]
    for points in (by_preset, by_p):   # the two points at one x are told apart, and a colour means one value
        colours = [tuple(c) for c in points.get_facecolors()]
        values = list(points.get_array())
        for i, j in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]:
            assert (colours[i] == colours[j]) == (values[i] == values[j])
    assert [t.get_text() for t in bars[1].get_yticklabels()] == ["dirt", "sand"]


def test_study_png_title_is_clear_of_the_panels(tmp_path, monkeypatch):
    from opera_taichi.studies import figures

    figs = []
    monkeypatch.setattr(figures, "_save", lambda fig, path: figs.append(fig))
    metrics = [f"metric_{i}" for i in range(8)]  # one parameter column, many metric rows: a tall, narrow figure
    rows = [{"p": p, **{m: p * 2 for m in metrics}, "status": "done"} for p in (1.0, 2.0)]
    figures.plot_study(rows, ["p"], metrics, tmp_path / "study.png")
    fig = figs[0]
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    assert fig._suptitle.get_window_extent(renderer).y0 >= fig.axes[0].get_tightbbox(renderer).y1


def test_a_finished_run_is_kept_only_for_the_scene_as_it_was(tmp_path):
    """A point's finished run is reused for the same overrides of the same scene content: after the base scene or
    its soil preset file is edited, the old run no longer counts as that point's (it would mix two scenes)."""
    import json
    import shutil

    from opera_taichi.studies.study import finished_row, make_task

    scene = tmp_path / "blade.yaml"
    shutil.copy(ROOT / "scenes" / "blade_cut.yaml", scene)
    preset = tmp_path / "soil.yaml"
    preset.write_text("preset: sand\nfriction_angle_deg: 33\n")
    path = tmp_path / "s.yaml"
    path.write_text(f"scene: {scene}\nset: {{sim.duration: 0.5, soil.preset_file: {preset}}}\n"
                    "parameters: {soil.overrides.cohesion: [0, 10]}\nmetrics: [manifest.particles]\n")

    def task():
        study = load_study(path, tmp_path / "out")
        return make_task(study, 0, study.points[0], tmp_path / "out" / "runs")

    first = task()
    folder = Path(first["run_dir"])
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_text(json.dumps({"status": "done"}))
    (folder / "point.json").write_text(json.dumps({"overrides": first["overrides"], "scene": first["scene_sha"],
                                                   "row": {"status": "done"}}))
    assert finished_row(folder, first["overrides"], task()["scene_sha"]) == {"status": "done"}
    preset.write_text("preset: sand\nfriction_angle_deg: 36\n")      # the preset's content, not its name
    assert finished_row(folder, first["overrides"], task()["scene_sha"]) is None
    preset.write_text("preset: sand\nfriction_angle_deg: 33\n")
    scene.write_text(scene.read_text().replace("velocity: [-0.3, 0.0, 0.0]", "velocity: [-0.2, 0.0, 0.0]"))
    again = task()
    assert again["overrides"] == first["overrides"] and finished_row(folder, first["overrides"],
                                                                       again["scene_sha"]) is None
    # a file the scene names, by content: the motion CSV
    motion = tmp_path / "motion.csv"
    motion.write_text("t,boom_joint\n0,0\n1,0.1\n")
    excavation = tmp_path / "dig.yaml"
    shutil.copy(ROOT / "scenes" / "zx120_dig_cycle.yaml", excavation)
    text = excavation.read_text()
    excavation.write_text(text[:text.index("motion:")] + "motion: {type: csv, file: motion.csv}\n"
                          + text[text.index("output:"):])
    from opera_taichi.studies.study import scene_fingerprint

    before = scene_fingerprint(excavation, [])
    assert scene_fingerprint(excavation, []) == before
    motion.write_text("t,boom_joint\n0,0\n1,0.2\n")
    assert scene_fingerprint(excavation, []) != before


def test_a_metric_the_run_has_no_value_for_is_an_error_not_an_empty_cell(tmp_path):
    """A misspelt summary or manifest key, or a CSV window without samples, leaves the row failed with its reason
    (a study read them as empty cells of rows marked done); a key that is there is measured."""
    import json

    from opera_taichi.studies.study import collect_metrics

    run = tmp_path / "run"
    run.mkdir()
    (run / "manifest.json").write_text(json.dumps({"status": "done", "particles": 991}))
    (run / "summary.json").write_text(json.dumps({"tools": {"bucket_link": {"soil_held_kg": 12.5}}}))
    (run / "tool_wrench.csv").write_text("t,tool,fx,fy,fz,tx,ty,tz\n0.5,blade,10,0,0,0,0,0\n1.0,blade,20,0,0,0,0,0\n")
    errors = {}
    window = {"name": "late", "file": "tool_wrench.csv", "column": "fx", "stat": "mean", "t": [5, 10]}
    row = collect_metrics(run, ["manifest.particles", "summary.tools.bucket_link.soil_held_kg",
                                "summary.tools.bucket.soil_held_kg", "manifest.nonexistent", window], {}, errors)
    assert row["manifest.particles"] == 991 and row["summary.tools.bucket_link.soil_held_kg"] == 12.5
    assert set(errors) == {"summary.tools.bucket.soil_held_kg", "manifest.nonexistent", "late"}
    assert "summary.json has no 'tools.bucket.soil_held_kg'" in str(errors["summary.tools.bucket.soil_held_kg"])
    assert "no fx samples" in str(errors["late"])


def test_a_study_writes_only_into_a_folder_of_its_own(tmp_path, capsys):
    """--out a file, a run folder or another study's folder: refused in one line before any run, nothing in that
    folder touched (a second study's points and tables went in among the first's)."""
    path = tmp_path / "s.yaml"
    path.write_text(BASE + "name: mine\nparameters: {soil.overrides.friction_angle_deg: [30, 35]}\n")
    cases, other = a_file_a_run_folder_and(tmp_path, "other", "study.json", '{"name": "theirs"}')
    for out, words in cases + [(other, "holds study 'theirs', not 'mine'")]:
        before = sorted(p.name for p in tmp_path.rglob("*"))
        assert main(["study", str(path), "--out", str(out), "--workers", "1"]) == 2
        err = capsys.readouterr().err.strip()
        assert f"out: {out} {words}" in err and "\n" not in err, err
        assert sorted(p.name for p in tmp_path.rglob("*")) == before
