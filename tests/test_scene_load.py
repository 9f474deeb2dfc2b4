"""Scene loading: defaults, unit conversion, --set typing, path resolution, and the resolved dump."""
import json
import math
from datetime import datetime
from pathlib import Path

import pytest

from opera_taichi.errors import UserError
from opera_taichi.paths import machines_dir
from opera_taichi.scene import (BucketTipPath, CsvMotion, JointWaypoints, Scene, load_scene, read_motion_csv,
                                resolve_out_dir, scene_to_dict)


@pytest.fixture
def robot(tmp_path) -> Path:
    path = tmp_path / "robot.urdf"
    path.write_text('<robot name="r"><link name="base_link"/></robot>\n')
    return path


def _write(folder: Path, text: str, name: str = "scene.yaml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


def _all_keys(data):
    if isinstance(data, dict):
        for key, value in data.items():
            yield key
            yield from _all_keys(value)
    elif isinstance(data, list):
        for item in data:
            yield from _all_keys(item)


def test_defaults_match_the_documented_values(tmp_path, robot):
    scene = load_scene(_write(tmp_path, "sim: {}\nsoil: {}\nmachine: {urdf: robot.urdf}\n", "my_dig.yaml"))
    assert scene.name == "my_dig"
    assert (scene.sim.duration, scene.sim.dt, scene.sim.soil_dt, scene.sim.arch, scene.sim.seed) == \
        (20.0, 0.001, None, "cpu", 0)
    soil = scene.soil
    assert (soil.model, soil.preset, soil.overrides, soil.settle_time, soil.max_speed, soil.heightmap_cell) == \
        ("dem", "dirt", {}, 1.0, 30.0, 0.05)
    assert [(b.min, b.max) for b in soil.bed] == [((3.0, -1.5, -1.0), (9.0, 1.5, 0.0))]
    assert soil.domain.contains(soil.bed[0])
    machine = scene.machine
    assert machine.urdf == robot.resolve() and machine.config is None
    assert machine.base_pose.xyz == (0.0, 0.0, 0.0) and machine.base_pose.yaw == 0.0
    assert machine.fixed_base is True and machine.initial_joints == {} and machine.actuators == {}
    assert scene.tools == [] and scene.motion is None
    out = scene.output
    assert (out.dir, out.joints_rate, out.wrench_rate, out.mass_rate, out.particles_final, out.plots) == \
        (None, 100.0, 100.0, 10.0, False, True)


def test_absent_sections_mean_no_soil_no_machine(tmp_path):
    scene = load_scene(_write(tmp_path, "name: bare\n"))
    assert scene.soil is None and scene.machine is None and scene.tools == [] and scene.motion is None
    assert scene.sim.duration == 20.0  # sim and output default even when absent


def test_unquoted_exponent_notation_is_a_number(tmp_path):
    """YAML 1.1 (PyYAML) reads `1e-4` as a string; a scene reads it as the number it looks like."""
    scene = load_scene(_write(tmp_path, "sim: {dt: 1e-4, duration: 2.5E+1, soil_dt: 5e-5}\n"))
    assert (scene.sim.dt, scene.sim.duration, scene.sim.soil_dt) == (1e-4, 25.0, 5e-5)


def test_degrees_are_converted_to_radians(tmp_path, robot):
    scene = load_scene(_write(tmp_path, """
machine:
  urdf: robot.urdf
  base_pose: {yaw_deg: 90}
  initial_joints: {swing_joint: 0.25}
  initial_joints_deg: {boom_joint: -46, arm_joint: 114}
tools:
  - {name: blade, box: [0.05, 1.0, 0.6], start: [1, 0, 0.3], rpy_deg: [0, 90, 180]}
motion:
  type: joint_waypoints
  waypoints:
    - {t: 0.0, q_deg: {swing_joint: 0, boom_joint: -46, arm_joint: 114, bucket_joint: 46}}
    - {t: 4.0, q: {boom_joint: -0.3}}
"""))
    assert scene.machine.base_pose.yaw == pytest.approx(math.pi / 2)
    assert scene.machine.initial_joints == pytest.approx(
        {"swing_joint": 0.25, "boom_joint": math.radians(-46), "arm_joint": math.radians(114)})
    assert scene.tools[0].rpy == pytest.approx((0.0, math.pi / 2, math.pi))
    motion = scene.motion
    assert isinstance(motion, JointWaypoints)
    assert motion.waypoints[0].q == pytest.approx({"swing_joint": 0.0, "boom_joint": math.radians(-46),
                                                   "arm_joint": math.radians(114),
                                                   "bucket_joint": math.radians(46)})
    assert motion.waypoints[1].q == {"boom_joint": -0.3}
    assert not [key for key in _all_keys(scene_to_dict(scene)) if key.endswith("_deg")]  # radians only


def test_bucket_tip_path_angles_hold_until_changed(tmp_path, robot):
    scene = load_scene(_write(tmp_path, """
machine: {urdf: robot.urdf}
motion:
  type: bucket_tip_path
  waypoints:
    - {t: 0.0, xyz: [6.0, 0.0, 0.5], bucket_angle_deg: 60}
    - {t: 2.0, xyz: [5.0, 0.0, -0.3]}
    - {t: 4.0, xyz: [4.0, 0.0, -0.3], bucket_angle: 1.2}
"""))
    assert isinstance(scene.motion, BucketTipPath)
    angles = [wp.bucket_angle for wp in scene.motion.waypoints]
    assert angles == pytest.approx([math.radians(60), math.radians(60), 1.2])


def test_set_overrides_are_typed_as_yaml(tmp_path, robot):
    scene = load_scene(_write(tmp_path, "soil: {preset: sand}\nmachine: {urdf: robot.urdf}\n"), [
        "sim.seed=7", "sim.duration=5", "sim.arch=auto", "name=run_7",
        "machine.base_pose.xyz=[1, 2.5, 0]", "soil.bed.0.max.2=-0.5", "soil.overrides={cohesion: 1500}",
        "machine.initial_joints.boom_joint=-0.4", "machine.actuators.arm_joint.gain=2", "output.plots=false"])
    assert scene.sim.seed == 7 and isinstance(scene.sim.seed, int)
    assert scene.sim.duration == 5.0 and isinstance(scene.sim.duration, float)
    assert scene.sim.arch == "auto" and scene.name == "run_7"
    assert scene.machine.base_pose.xyz == (1.0, 2.5, 0.0)
    assert scene.soil.bed[0].max == (9.0, 1.5, -0.5)  # the default bed, one entry changed through an index
    assert scene.soil.bed[0].min == (3.0, -1.5, -1.0)
    assert scene.soil.overrides == {"cohesion": 1500.0}
    assert scene.machine.initial_joints == {"boom_joint": -0.4}
    assert scene.machine.actuators["arm_joint"].gain == 2.0
    assert scene.output.plots is False


def test_set_creates_missing_sections_the_schema_allows(tmp_path, robot):
    scene = load_scene(_write(tmp_path, "name: x\n"), ["machine.urdf=robot.urdf", "machine.base_pose.yaw_deg=45",
                                                        "soil.domain.max.2=10"])
    assert scene.machine.urdf == robot.resolve()
    assert scene.machine.base_pose.yaw == pytest.approx(math.pi / 4)
    assert scene.soil.domain.max[2] == 10.0 and scene.soil.domain.min == (-2.0, -6.0, -3.0)


def test_set_changes_one_place_even_where_yaml_aliases_share_a_list(tmp_path):
    scene = load_scene(_write(tmp_path, """
tools:
  - {name: a, box: [1, 1, 1], start: &p [1.0, 0.0, 0.5]}
  - {name: b, box: [1, 1, 1], start: *p}
"""), ["tools.0.start.0=2.0"])
    assert scene.tools[0].start == (2.0, 0.0, 0.5)
    assert scene.tools[1].start == (1.0, 0.0, 0.5)


def test_relative_paths_resolve_against_the_scene_file_not_the_cwd(tmp_path, monkeypatch):
    scenes, assets, elsewhere = tmp_path / "scenes", tmp_path / "assets", tmp_path / "elsewhere"
    for folder in (scenes, assets, elsewhere):
        folder.mkdir()
    (assets / "robot.urdf").write_text("<robot name='r'/>\n")
    (assets / "robot_machine.yaml").write_text("joints: {}\n")
    (scenes / "blade.stl").write_text("solid blade\nendsolid blade\n")
    (scenes / "profile.csv").write_text("t,boom_joint,arm_joint_deg\n0,0.1,30\n1,0.2,60\n")
    monkeypatch.chdir(elsewhere)
    scene = load_scene(_write(scenes, """
machine: {urdf: ../assets/robot.urdf, config: ../assets/robot_machine.yaml}
tools: [{name: blade, mesh: blade.stl, start: [0, 0, 0]}]
motion: {type: csv, file: profile.csv, time_offset: 1.5}
"""))
    assert scene.machine.urdf == (assets / "robot.urdf").resolve()
    assert scene.machine.config == (assets / "robot_machine.yaml").resolve()
    assert scene.tools[0].mesh == (scenes / "blade.stl").resolve()
    assert isinstance(scene.motion, CsvMotion) and scene.motion.file == (scenes / "profile.csv").resolve()
    assert scene.source == (scenes / "scene.yaml").resolve()
    with pytest.raises(UserError, match="machine.urdf"):  # the same names do not exist relative to the cwd
        load_scene(_write(elsewhere, "machine: {urdf: ../assets/robot.urdf}\n"), ["machine.urdf=robot.urdf"])


def test_machine_config_defaults_to_machine_yaml_beside_the_urdf(tmp_path, robot):
    (tmp_path / "machine.yaml").write_text("joints: {}\n")
    scene = load_scene(_write(tmp_path, "machine: {urdf: robot.urdf}\n"))
    assert scene.machine.config == (tmp_path / "machine.yaml")


def test_builtin_machine_name_resolves_into_machines_dir(tmp_path):
    if not (machines_dir() / "zx120" / "zx120.urdf").is_file():
        pytest.skip("the built-in zx120 URDF is not in this checkout yet")
    scene = load_scene(_write(tmp_path, "machine: {}\n"))
    assert scene.machine.urdf == machines_dir() / "zx120" / "zx120.urdf"


def test_motion_csv_columns_in_degrees_are_read_in_radians(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("t, boom_joint ,arm_joint_deg\n0,0.1,30\n0.5,0.2,90\n")
    times, angles = read_motion_csv(path)
    assert times == [0.0, 0.5]
    assert angles["boom_joint"] == [0.1, 0.2]
    assert angles["arm_joint"] == pytest.approx([math.pi / 6, math.pi / 2])


def test_resolved_scene_is_json_safe_and_reloads_to_the_same_scene(tmp_path, robot):
    scene = load_scene(_write(tmp_path, """
soil: {preset: gravel, overrides: {cohesion: 100}}
machine: {urdf: robot.urdf, base_pose: {yaw_deg: 30}}
tools: [{name: plate, box: [0.1, 1, 0.5], start: [4, 0, 0.2], velocity: [-0.2, 0, 0], stop_time: 5}]
output: {dir: out/here}
"""))
    data = scene_to_dict(scene)
    text = json.dumps(data, allow_nan=False)  # raises on nan/inf or non-JSON types
    assert "source" not in data and str(robot.resolve()) in text
    again = Scene.model_validate(json.loads(text))
    again.source = scene.source
    assert again == scene


def test_run_folder_priority_out_then_output_dir_then_timestamp(tmp_path):
    scene = load_scene(_write(tmp_path, "name: dig\n"))
    now = datetime(2024, 5, 6, 7, 8, 9)
    assert resolve_out_dir(scene, now=now) == Path("runs/dig-20240506-070809")
    scene.output.dir = Path("mine")
    assert resolve_out_dir(scene, now=now) == Path("mine")
    assert resolve_out_dir(scene, "cli_out", now=now) == Path("cli_out")


def test_file_stem_with_odd_characters_gives_a_safe_name(tmp_path):
    scene = load_scene(_write(tmp_path, "sim: {}\n", "my dig (v2).yaml"))
    assert scene.name == "my_dig__v2_"


def test_a_joint_without_an_initial_angle_starts_at_zero_or_its_nearest_limit(tmp_path):
    from opera_taichi.model import build_model

    scene = load_scene(_write(tmp_path, "machine: {urdf: zx120, initial_joints: {boom_joint: -0.4}}\n"))
    machine = build_model(scene).machines[0]
    limits = machine.description.joint_limits
    assert limits["arm_joint"][0] > 0.0   # the ZX120's arm cannot stand at 0
    assert machine.initial_q["arm_joint"] == limits["arm_joint"][0]
    assert machine.initial_q["swing_joint"] == 0.0 and machine.initial_q["boom_joint"] == -0.4
    # an angle given outside the limits is still refused, naming the key
    bad = load_scene(_write(tmp_path, "machine: {urdf: zx120, initial_joints: {arm_joint: 0.0}}\n", "bad.yaml"))
    with pytest.raises(UserError, match=r"^machine.initial_joints.arm_joint \(or initial_joints_deg\): 0.0000 rad "
                                        r"\(0.0 deg\) is outside the joint's limits"):
        build_model(bad)
    # given in degrees, the message gives degrees too
    deg = load_scene(_write(tmp_path, "machine: {urdf: zx120, initial_joints_deg: {boom_joint: 500}}\n", "deg.yaml"))
    with pytest.raises(UserError, match=r"initial_joints_deg\): 8.7266 rad \(500.0 deg\) is outside the joint's "
                                        r"limits \[.*\] rad \(\[-70.0, 44.0\] deg\)"):
        build_model(deg)


def test_overrides_as_a_mapping_or_as_set_strings_load_the_same_scene(tmp_path, robot):
    path = _write(tmp_path, f"machine: {{urdf: {robot.name}}}\n")
    as_dict = load_scene(path, {"sim.duration": 3, "machine.base_pose.xyz": [1, 2, 0], "motion": None})
    as_sets = load_scene(path, ["sim.duration=3", "machine.base_pose.xyz=[1, 2, 0]", "motion=null"])
    assert scene_to_dict(as_dict) == scene_to_dict(as_sets) and as_dict.sim.duration == 3.0


def test_integers_are_decimal_as_in_yaml_1_2(tmp_path):
    """YAML 1.1 (PyYAML's default) reads `010` as octal 8; a scene means ten."""
    scene = load_scene(_write(tmp_path, "sim: {seed: 010, duration: 5}\n"), ["sim.duration=010"])
    assert scene.sim.seed == 10 and scene.sim.duration == 10.0
    assert load_scene(_write(tmp_path, "sim: {seed: 0x1F}\n")).sim.seed == 31


def test_a_date_like_name_is_a_string_as_in_yaml_1_2(tmp_path):
    """YAML 1.1 reads an unquoted `2024-05-01` as a date: a legal name was refused, its message showing the text it
    refused. YAML 1.2's core schema has no timestamps."""
    path = _write(tmp_path, "name: 2024-05-01\nsim: {}\n")
    assert load_scene(path).name == "2024-05-01"
    assert load_scene(path, ["name=2024-05-02"]).name == "2024-05-02"


def test_python_api_overrides_take_paths_and_numpy_numbers_as_given(tmp_path):
    """They were written out as JSON and read back: a Path or a numpy number raised TypeError, and nan came back as
    the string 'NaN'."""
    import numpy as np

    path = _write(tmp_path, "sim: {}\n")
    scene = load_scene(path, {"machine.urdf": Path("zx120"), "sim.seed": np.int64(3), "sim.duration": np.float32(2.5),
                              "machine.base_pose.xyz": np.array([1.0, 2.0, 0.0])})
    assert scene.machine.urdf == machines_dir() / "zx120" / "zx120.urdf"
    assert scene.sim.seed == 3 and type(scene.sim.seed) is int and scene.sim.duration == 2.5
    assert scene.machine.base_pose.xyz == (1.0, 2.0, 0.0)
    with pytest.raises(UserError, match=r"sim\.duration \(from --set\): expected a finite number in s > 0 and "
                                        r"<= 3600, got nan$"):
        load_scene(path, {"sim.duration": float("nan")})


def test_a_youngs_modulus_below_the_beds_stiffness_floor_is_said():
    """Below the stiffness the bed's weight needs (soil.OVERLAP_RULE) the override sets nothing: 1e5 and 1e6 Pa gave
    the same contacts and the same substep, silently, and the manifest recorded the value asked."""
    from opera_taichi.model import build_model
    from opera_taichi.scene import load_scene

    scene = str(Path(__file__).resolve().parent.parent / "scenes" / "zx120_excavation.yaml")
    soft = [build_model(load_scene(scene, [f"soil.overrides.youngs_modulus={e}"])) for e in (1e5, 1e6)]
    assert soft[0].soil.params.k_n == soft[1].soil.params.k_n
    assert all(any("soil.overrides.youngs_modulus" in w and "changes nothing" in w for w in m.warnings) for m in soft)
    stiff = build_model(load_scene(scene, ["soil.overrides.youngs_modulus=1e8"]))
    assert not any("youngs_modulus" in w for w in stiff.warnings)
