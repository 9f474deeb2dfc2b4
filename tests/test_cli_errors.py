"""Bad input never gives a traceback: exit status 2 and exactly one stderr line naming the file and the key."""
import subprocess
import sys
from pathlib import Path

import pytest

from opera_taichi import cli

REPO = Path(__file__).resolve().parents[1]


def _bomb() -> str:
    lines = ['a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, 9):
        prev, cur = chr(ord("a") + i - 1), chr(ord("a") + i)
        lines.append(f"{cur}: &{cur} [" + ", ".join([f"*{prev}"] * 9) + "]")
    return "\n".join(lines) + "\n"


MACHINE = "machine: {urdf: robot.urdf}\n"

# (id, scene text (str) or bytes, extra CLI args, substrings the one error line must contain)
CASES = [
    ("syntax", "sim:\n  dt: [0.001\n", [], ["line 3", "YAML syntax error"]),
    ("tab_indent", "sim:\n\tdt: 0.001\n", [], ["line 2"]),
    ("duplicate_key", "sim:\n  dt: 0.001\n  dt: 0.002\n", [], ["sim.dt", "duplicate key", "lines 2 and 3"]),
    ("unknown_top_key", "simm: {dt: 0.001}\n", [], ["simm", "did you mean 'sim'"]),
    ("unknown_nested_key", "sim: {duraton: 5}\n", [], ["sim.duraton", "did you mean 'duration'"]),
    ("string_for_number", MACHINE.replace("}", ", base_pose: {yaw: north}}"), [],
     ["machine.base_pose.yaw", "expected a number in rad, got 'north'"]),
    ("bool_for_number", "sim: {duration: true}\n", [], ["sim.duration", "got true"]),
    ("quoted_number", "sim: {duration: '5'}\n", [], ["sim.duration", "got '5'"]),
    ("nan", "sim: {duration: .nan}\n", [], ["sim.duration", "finite", "got nan"]),
    ("inf", "sim: {dt: .inf}\n", [], ["sim.dt", "got inf"]),
    ("quoted_exponent", "sim: {dt: '1e-4'}\n", [], ["sim.dt", "got '1e-4'"]),
    ("huge_integer", "sim: {seed: " + "1" * 5000 + "}\n", [], ["cannot read a value"]),
    ("negative", "sim: {duration: -1}\n", [], ["sim.duration", "> 0"]),
    ("too_large_dt", "sim: {dt: 0.1}\n", [], ["sim.dt", "<= 0.01"]),
    ("float_seed", "sim: {seed: 1.5}\n", [], ["sim.seed", "integer"]),
    ("bridge_without_kind", "bridge: {command_timeout: 1.0}\n", [],
     ["bridge.kind", "required key is missing (ros1 | ros_tcp); or run with --ros1 or --ros-tcp HOST:PORT"]),
    ("soil_dt_above_dt", "sim: {dt: 0.001, soil_dt: 0.002}\n", [], ["sim.soil_dt"]),
    ("arch", "sim: {arch: gpu}\n", [], ["sim.arch", "cpu, cuda, auto"]),
    ("xyz_length", MACHINE.replace("}", ", base_pose: {xyz: [1, 2]}}"), [], ["machine.base_pose.xyz", "3"]),
    ("yaw_and_yaw_deg", MACHINE.replace("}", ", base_pose: {yaw: 1, yaw_deg: 5}}"), [],
     ["machine.base_pose.yaw_deg", "not both"]),
    ("bool_as_string", MACHINE.replace("}", ", fixed_base: 'yes'}"), [], ["machine.fixed_base", "true or false"]),
    ("actuator_zero", MACHINE.replace("}", ", actuators: {boom_joint: {max_torque: 0}}}"), [],
     ["machine.actuators.boom_joint.max_torque", "> 0"]),
    ("preset_typo", "soil: {preset: snad}\n", [], ["soil.preset", "did you mean 'sand'"]),
    ("mpm", "soil: {model: mpm}\n", [], ["soil.model", "not available yet"]),
    ("bed_above_ground", "soil: {bed: [{min: [3, -1, -1], max: [5, 1, 0.5]}]}\n", [], ["soil.bed.0.max", "z <= 0"]),
    ("bed_outside_domain", "soil: {bed: [{min: [3, -1, -1], max: [50, 1, 0]}]}\n", [], ["soil.bed.0", "domain"]),
    ("clear_above_domain", "soil: {clear_above: 20}\n", [], ["soil.clear_above", "domain top"]),
    ("clear_above_negative", "soil: {clear_above: -0.1}\n", [], ["soil.clear_above"]),
    ("domain_inverted", "soil: {domain: {min: [0, 0, 0], max: [1, -1, 1]}}\n", [], ["soil.domain.max", "max > min"]),
    ("overrides_non_number", "soil: {overrides: {density: heavy}}\n", [], ["soil.overrides.density", "'heavy'"]),
    ("actuator_joint_typo", "machine: {urdf: zx120, actuators: {bom_joint: {max_speed: 0.1}}}\n", [],
     ["machine.actuators.bom_joint", "not an actuated joint", "did you mean 'boom_joint'"]),
    ("soil_dt_unstable", "soil: {overrides: {radius: 0.08}}\nsim: {dt: 0.002, soil_dt: 0.002}\n", [],
     ["sim.soil_dt", "stability"]),
    ("beds_overlap", "soil: {bed: [{min: [3, -1.6, -1], max: [6, 1.4, 0]}, {min: [5, -1, -1], max: [9, 1, 0]}]}\n", [],
     ["soil.bed.1: overlaps soil.bed.0 in plan view"]),
    ("heightmap_cell_tiny", "soil: {heightmap_cell: 0.0001}\n", [], ["soil.heightmap_cell", "the finest cell is"]),
    ("heightmap_cell_huge", "soil: {heightmap_cell: 50}\n", [], ["soil.heightmap_cell", "fewer than 2 cells"]),
    ("bed_shift_out", "soil: {bed_shift: [0, 0, 9]}\n", [], ["soil.bed_shift", "wholly out of soil.domain"]),
    ("soil_dt_tiny", "sim: {soil_dt: 1.0e-9}\nsoil: {}\n", [], ["sim.soil_dt", "substeps per simulated second"]),
    ("stiffness_typo", "soil: {overrides: {youngs_modulus: 1e20}}\n", [],
     ["soil.overrides", "substeps per simulated second", "youngs_modulus"]),
    ("overrides_typo", "soil: {overrides: {radus: 0.05}}\n", [], ["soil.overrides.radus", "did you mean 'radius'"]),
    ("empty_file", "", [], ["empty file"]),
    ("comment_only", "# nothing here\n", [], ["empty file"]),
    ("not_a_mapping", "- sim\n- soil\n", [], ["expected a mapping of scene keys"]),
    ("non_utf8", "name: caf\xe9\n".encode("latin-1"), [], ["not UTF-8", "0xe9"]),
    ("python_tag", "sim: !!python/object/apply:os.system [ls]\n", [], ["unsupported YAML", "line 1"]),
    ("anchor_bomb", _bomb(), [], ["alias"]),
    ("recursive_alias", "a: &a [*a]\n", [], ["recursive"]),
    ("missing_urdf", "machine: {urdf: nowhere/robot.urdf}\n", [], ["machine.urdf", "nowhere/robot.urdf"]),
    ("unknown_builtin", "machine: {urdf: zx12}\n", [], ["machine.urdf", "did you mean 'zx120'"]),
    ("missing_csv", MACHINE + "motion: {type: csv, file: profile.csv}\n", [], ["motion.file", "profile.csv"]),
    ("csv_unsorted", MACHINE + "motion: {type: csv, file: unsorted.csv}\n", [],
     ["motion.file", "unsorted.csv", "line 3", "strictly increasing"]),
    ("csv_nan", MACHINE + "motion: {type: csv, file: nan.csv}\n", [], ["motion.file", "nan.csv", "finite"]),
    ("csv_huge_cell", MACHINE + "motion: {type: csv, file: huge_cell.csv}\n", [],
     ["motion.file", "huge_cell.csv", "line 2", "field limit"]),
    ("csv_two_t_columns", MACHINE + "motion: {type: csv, file: two_t.csv}\n", [],
     ["motion.file", "two_t.csv", "column 't' appears more than once"]),
    ("csv_time_offset_huge", MACHINE + "motion: {type: csv, file: ok.csv}\n", ["--set", "motion.time_offset=-1e300"],
     ["motion.time_offset (from --set)", ">= -1000000 and <= 1000000", "got -1e+300"]),
    ("missing_mesh", "tools: [{name: blade, mesh: blade.stl, start: [0, 0, 0]}]\n", [], ["tools.0.mesh", "blade.stl"]),
    ("tool_box_and_mesh_missing", "tools: [{name: blade, start: [0, 0, 0]}]\n", [], ["tools.0.box", "box or mesh"]),
    ("tool_names_repeat", "tools: [{name: a, box: [1, 1, 1], start: [0, 0, 0]}, "
                          "{name: a, box: [1, 1, 1], start: [0, 0, 0]}]\n", [], ["tools.1.name", "unique"]),
    ("tool_bad_name", "tools: [{name: 'my blade', box: [1, 1, 1], start: [0, 0, 0]}]\n", [], ["tools.0.name"]),
    ("motion_type_typo", MACHINE + "motion: {type: joint_waypoint, waypoints: []}\n", [],
     ["motion.type", "did you mean 'joint_waypoints'"]),
    ("waypoints_not_increasing", MACHINE + "motion: {type: joint_waypoints, waypoints: "
                                           "[{t: 1, q: {}}, {t: 1, q: {}}]}\n", [], ["motion.waypoints.1.t"]),
    ("tip_path_needs_angle", MACHINE + "motion: {type: bucket_tip_path, waypoints: [{t: 0, xyz: [6, 0, 0]}]}\n",
     [], ["motion.waypoints.0.bucket_angle"]),
    ("rate_above_step", "output: {joints_rate: 5000}\n", [], ["output.joints_rate", "1/sim.dt"]),
    ("set_unknown_key", "sim: {}\n", ["--set", "sim.duraton=3"], ["--set sim.duraton", "did you mean 'duration'"]),
    ("set_bad_value", "sim: {}\n", ["--set", "sim.duration=soon"], ["sim.duration (from --set)", "'soon'"]),
    ("set_no_equals", "sim: {}\n", ["--set", "sim.duration"], ["--set sim.duration", "key.path=value"]),
    ("set_index_out_of_range", "soil: {}\n", ["--set", "soil.bed.3.max.2=-0.5"], ["--set soil.bed.3", "1 entries"]),
    ("set_into_scalar", "sim: {}\n", ["--set", "sim.dt.x=1"], ["--set sim.dt.x", "sim.dt is not a mapping"]),
    ("set_bad_yaml", "sim: {}\n", ["--set", "sim.duration=[1,"], ["--set sim.duration", "YAML syntax error"]),
    # YAML 1.2: `1:30` is not 90 (base 60) and `on` is not true (YAML 1.1 forms PyYAML reads by default)
    ("set_sexagesimal", "sim: {}\n", ["--set", "sim.duration=1:30"], ["sim.duration (from --set)", "got '1:30'"]),
    ("sexagesimal_float", "sim: {duration: '1'}\n", ["--set", "sim.duration=1:30.5"], ["got '1:30.5'"]),
    ("bool_on", "soil: {sleep: on}\n", [], ["soil.sleep", "expected true or false, got 'on'"]),
    ("bool_yes", MACHINE.replace("}", ", fixed_base: yes}"), [], ["machine.fixed_base", "got 'yes'"]),
    ("set_non_finite", "sim: {}\n", ["--set", "sim.duration=.inf"], ["sim.duration (from --set)", "got inf"]),
]


@pytest.fixture
def scene_dir(tmp_path):
    (tmp_path / "robot.urdf").write_text('<robot name="r"><link name="base_link"/></robot>\n')
    (tmp_path / "unsorted.csv").write_text("t,boom_joint\n0.0,0.1\n0.0,0.2\n")
    (tmp_path / "nan.csv").write_text("t,boom_joint\n0.0,0.1\n1.0,nan\n")
    (tmp_path / "huge_cell.csv").write_text("t,boom_joint\n0.0," + "1" * 200_000 + "\n")
    (tmp_path / "ok.csv").write_text("t,boom_joint\n0.0,0.1\n1.0,0.2\n")
    (tmp_path / "two_t.csv").write_text("t,boom_joint,t\n0.0,0.1,5.0\n1.0,0.2,6.0\n")
    return tmp_path


def _assert_one_line(rc, captured, must_contain):
    assert rc == 2, captured
    assert captured.out == ""
    assert captured.err.endswith("\n") and captured.err.count("\n") == 1, captured.err
    assert captured.err.startswith("error: ")
    assert "Traceback" not in captured.err
    for text in must_contain:
        assert text in captured.err, (text, captured.err)


@pytest.mark.parametrize("case_id, content, extra, must_contain", CASES, ids=[c[0] for c in CASES])
def test_malformed_scene_is_one_line_exit_2(scene_dir, capsys, case_id, content, extra, must_contain):
    path = scene_dir / "scene.yaml"
    (path.write_bytes if isinstance(content, bytes) else path.write_text)(content)
    rc = cli.main(["validate", str(path), *extra])
    _assert_one_line(rc, capsys.readouterr(), ["scene.yaml", *must_contain])


def test_missing_file_and_directory_are_named(tmp_path, capsys):
    rc = cli.main(["validate", str(tmp_path / "absent.yaml")])
    _assert_one_line(rc, capsys.readouterr(), ["absent.yaml", "file not found"])
    rc = cli.main(["run", str(tmp_path)])
    _assert_one_line(rc, capsys.readouterr(), [str(tmp_path), "is a directory"])


def test_huge_document_is_refused_before_parsing(tmp_path, capsys):
    path = tmp_path / "huge.yaml"
    path.write_text("x: [" + ",".join(["1"] * 3_000_000) + "]\n")  # ~6 MB
    rc = cli.main(["validate", str(path)])
    _assert_one_line(rc, capsys.readouterr(), ["huge.yaml", "5 MB limit"])


def test_many_values_without_aliases_are_refused(tmp_path, capsys):
    path = tmp_path / "many.yaml"
    path.write_text("x: [" + ",".join(["1"] * 25_000) + "]\n")  # under 5 MB, far beyond any scene
    rc = cli.main(["validate", str(path)])
    _assert_one_line(rc, capsys.readouterr(), ["many.yaml", "more than 20000 values"])


def test_deep_nesting_is_refused(tmp_path, capsys):
    path = tmp_path / "deep.yaml"
    path.write_text("x: " + "[" * 3000 + "]" * 3000 + "\n")
    rc = cli.main(["validate", str(path)])
    _assert_one_line(rc, capsys.readouterr(), ["deep.yaml", "nested more than 50 levels deep (line 1)"])


@pytest.mark.parametrize("content, key", [("sim: {duraton: 5}\n", "sim.duraton"),
                                          ("sim:\n  dt: [0.001\n", "line 3")])
def test_subprocess_validate_prints_one_line_and_exits_2(tmp_path, content, key):
    path = tmp_path / "bad.yaml"
    path.write_text(content)
    proc = subprocess.run([sys.executable, "cli.py", "validate", str(path)], cwd=REPO, capture_output=True,
                          text=True)
    assert proc.returncode == 2, proc.stderr
    assert proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert "bad.yaml" in proc.stderr and key in proc.stderr


def test_subprocess_run_with_bad_override_exits_2(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text("sim: {duration: 1}\n")
    proc = subprocess.run([sys.executable, "cli.py", "run", str(path), "--set", "sim.dt=fast"], cwd=REPO,
                          capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "sim.dt (from --set)" in proc.stderr and "'fast'" in proc.stderr


def test_a_bridge_flag_gives_the_bridge_its_kind_for_set_bridge_keys(monkeypatch, capsys, tmp_path):
    """`--ros1 --set bridge.rates...` on a scene without a bridge: the flag is the bridge's kind, so the scene
    loads and the run goes on to look for its ROS master (none here)."""
    monkeypatch.setenv("ROS_MASTER_URI", "http://127.0.0.1:1")
    rc = cli.main(["run", str(REPO / "scenes" / "zx120_dig_cycle.yaml"), "--ros1", "--set",
                   "bridge.rates.joint_states=50", "--out", str(tmp_path / "run")])
    _assert_one_line(rc, capsys.readouterr(), ["--ros1:"])


def test_validate_warns_of_a_motion_beyond_the_joint_limits(capsys):
    """Not an error (the run clips the targets, as a real machine's controller would), but said before the run."""
    dig = str(REPO / "scenes" / "zx120_dig_cycle.yaml")
    assert cli.main(["validate", dig]) == 0
    assert capsys.readouterr().err == ""
    assert cli.main(["validate", dig, "--set", "motion.waypoints.1.q_deg.boom_joint=300"]) == 0
    out, err = capsys.readouterr()
    assert out.strip().endswith(": ok")
    assert err.startswith("warning: motion: boom_joint is asked ") and "5.2360 rad, beyond its limits" in err


@pytest.mark.parametrize("value", ["inf", "nan", "0"])
def test_checkpoint_every_must_be_finite_and_positive(tmp_path, capsys, value):
    """`inf` passed the old `> 0` check and crashed the run at its first step (a checkpoint rate of 1/inf = 0)."""
    rc = cli.main(["run", str(tmp_path / "absent.yaml"), "--checkpoint-every", value])
    _assert_one_line(rc, capsys.readouterr(), ["--checkpoint-every", "finite positive", f"got {value}"])


@pytest.mark.parametrize("value", ["inf", "-1"])
def test_view_rate_must_be_finite_and_positive(tmp_path, capsys, value):
    """Refused before the run starts (`inf` used to crash the live view at its first frame)."""
    rc = cli.main(["run", str(REPO / "scenes" / "zx120_dig_cycle.yaml"), "--view", "--view-rate", value,
                   "--out", str(tmp_path / "run")])
    _assert_one_line(rc, capsys.readouterr(), ["--view-rate", "finite positive", f"got {value}"])
    assert not (tmp_path / "run").exists()
