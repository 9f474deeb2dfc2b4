"""Loading machines: our ZX120, OPERA's URDF unchanged, and the errors a user can cause."""
import hashlib
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from opera_taichi.errors import UserError
from opera_taichi.kinematics import Kinematics
from opera_taichi.machine_description import joint_specs, load_machine, mass_properties
from opera_taichi.paths import machines_dir

from conftest import ON_CI, SHARED

OPERA_URDF = SHARED / "opera" / "zx120_description" / "urdf" / "zx120.urdf"
needs_opera = pytest.mark.skipif(not OPERA_URDF.is_file() and not ON_CI,
                                 reason="OPERA's zx120_description is not in ../shared (OPERA_TAICHI_SHARED)")
MASSES = {"track_link": 3816, "body_link": 6514, "boom_link": 992, "arm_link": 392, "bucket_link": 386}


@pytest.fixture(scope="module", autouse=True)
def private_cache(tmp_path_factory):
    """A fresh cache, so mesh conversion and the cleaned URDF are exercised, not found from an earlier run."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("OPERA_TAICHI_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield


def _inertials(desc):
    import yourdfpy
    robot = yourdfpy.URDF.load(str(desc.bullet_urdf_path), build_scene_graph=False, load_meshes=False).robot
    return {link.name: link.inertial for link in robot.links}


def _assert_physical_inertia(inertia):
    principal = np.linalg.eigvalsh(inertia)
    assert principal.min() > 0
    # a rigid body's principal moments obey the triangle inequality
    assert principal[0] + principal[1] >= principal[2] * (1 - 1e-9)


# ----------------------------------------------------------------------------------------- our ZX120
def test_builtin_zx120_loads_cleanly_with_the_config_beside_it():
    desc = load_machine("zx120")
    assert desc.warnings == []
    assert desc.actuated_joints == ["swing_joint", "boom_joint", "arm_joint", "bucket_joint"]
    assert desc.tip_link == "bucket_end_link" and desc.soil_links == ["bucket_link"]
    assert desc.joint_limits["swing_joint"] == (-math.inf, math.inf)
    assert desc.joint_limits["boom_joint"] == pytest.approx((math.radians(-70), math.radians(44)))
    assert desc.joint_limits["arm_joint"] == pytest.approx((math.radians(30), math.radians(152)))
    assert desc.joint_limits["bucket_joint"] == pytest.approx((math.radians(-33), math.radians(143)))
    assert desc.actuators["arm_joint"].max_torque == pytest.approx(2.36e5)
    assert desc.tracks["gauge"] == 2.0 and desc.tracks["x"] == [1.5, 0.0, -1.5]
    inertials = _inertials(desc)
    for link, mass in MASSES.items():
        assert inertials[link].mass == pytest.approx(mass)
        _assert_physical_inertia(inertials[link].inertia)


def test_urdf_limits_carry_the_actuator_limits_of_machine_yaml():
    import yourdfpy
    config = yaml.safe_load((machines_dir() / "zx120" / "machine.yaml").read_text())
    robot = yourdfpy.URDF.load(str(machines_dir() / "zx120" / "zx120.urdf"), build_scene_graph=False,
                               load_meshes=False).robot
    joints = {j.name: j for j in robot.joints}
    for name, actuator in config["joints"].items():
        assert joints[name].limit.velocity == pytest.approx(float(actuator["max_speed"]))
        assert joints[name].limit.effort == pytest.approx(float(actuator["max_torque"]))
    assert np.linalg.norm(joints["swing_joint"].axis) == pytest.approx(1.0)


def test_meshes_are_small_and_each_part_is_closed():
    for obj in (machines_dir() / "zx120" / "meshes").glob("*.obj"):
        assert obj.stat().st_size < 200_000, obj
        mesh = trimesh.load(obj, force="mesh", process=False)
        assert all(part.is_watertight for part in mesh.split(only_watertight=False)), obj


def test_bucket_is_an_open_shell_facing_the_soil_it_curls_into():
    desc = load_machine("zx120")
    bucket = desc.collision_meshes["bucket_link"]
    lo, hi = bucket.bounds
    assert hi[1] - lo[1] == pytest.approx(0.70, abs=1e-6)          # outer width
    assert hi[2] == pytest.approx(1.23, abs=0.025)                 # the cutting edge is the far end along +z
    plates = bucket.split(only_watertight=False)
    assert len(plates) >= 9 and all(plate.is_watertight for plate in plates)
    assert all(2 * plate.volume / plate.area < 0.06 for plate in plates)     # plates 3.5-5 cm thick

    # curling (positive bucket_joint) moves the edge, in the bucket frame, towards the side opposite the
    # shell: soil enters through the mouth, not through the back of the bucket
    kin = Kinematics(desc)
    h = 1e-6
    world_velocity = (kin.tip_position({"bucket_joint": 0.3 + h}) - kin.tip_position({"bucket_joint": 0.3})) / h
    velocity_in_bucket = kin.link_pose({"bucket_joint": 0.3}, "bucket_link")[:3, :3].T @ world_velocity
    chord = np.array([0.0, 0.0, 1.0])                              # pin -> edge
    shell_side = bucket.center_mass - chord * (bucket.center_mass @ chord)
    shell_side[1] = 0.0
    assert velocity_in_bucket @ shell_side < -0.5 * np.linalg.norm(velocity_in_bucket) * np.linalg.norm(shell_side)


def test_shell_mass_properties_match_a_thin_spherical_shell():
    # open surfaces (CAD meshes) are thin shells: a sphere's surface has I = 2/3 m r^2 about its centre
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=2.0)
    sphere.apply_translation((1.0, -2.0, 3.0))
    open_surface = trimesh.Trimesh(sphere.vertices, sphere.faces[1:], process=False)
    com, inertia = mass_properties(open_surface, 10.0)
    assert com == pytest.approx([1.0, -2.0, 3.0], abs=5e-3)
    assert np.diag(inertia) == pytest.approx([2 / 3 * 10.0 * 4.0] * 3, rel=5e-3)


# ----------------------------------------------------------------------------------------- OPERA's URDF
@needs_opera
def test_opera_urdf_loads_unchanged_with_real_masses():
    before = hashlib.sha256(OPERA_URDF.read_bytes()).hexdigest()
    desc = load_machine(OPERA_URDF)
    assert hashlib.sha256(OPERA_URDF.read_bytes()).hexdigest() == before
    text = " | ".join(desc.warnings)
    assert "placeholder masses (0.03, 10 kg)" in text and "replaced from machine.yaml" in text
    assert "built-in machine 'zx120'" in text                      # config found by the robot's name
    assert desc.actuated_joints == ["swing_joint", "boom_joint", "arm_joint", "bucket_joint"]
    assert desc.movable_joints == [*desc.actuated_joints, "bucket_end_joint"]   # what joint_states carries
    inertials = _inertials(desc)
    for link, mass in MASSES.items():
        assert inertials[link].mass == pytest.approx(mass)
        _assert_physical_inertia(inertials[link].inertia)
    # the cleaned copy: absolute OBJ meshes that exist, unit axes, no package:// left
    cleaned = desc.bullet_urdf_path.read_text()
    assert "package://" not in cleaned and ".dae" not in cleaned
    import yourdfpy
    robot = yourdfpy.URDF.load(str(desc.bullet_urdf_path), build_scene_graph=False, load_meshes=False).robot
    for link in robot.links:
        for element in [*link.visuals, *link.collisions]:
            if element.geometry.mesh is not None:
                assert Path(element.geometry.mesh.filename).is_file()
    swing = next(j for j in robot.joints if j.name == "swing_joint")
    assert swing.axis == pytest.approx([0.0, 0.0, 1.0])
    # the boom's centre of mass lies between its pins, above the pin line (-x is up in the boom frame)
    boom_com = inertials["boom_link"].origin[:3, 3]
    assert 1.0 < boom_com[2] < 3.6 and boom_com[0] < 0.0


@needs_opera
def test_opera_without_masses_keeps_placeholders_and_says_so(tmp_path):
    config = tmp_path / "nomass.yaml"
    settings = yaml.safe_load((machines_dir() / "zx120" / "machine.yaml").read_text())
    del settings["masses"]
    config.write_text(yaml.safe_dump(settings))
    desc = load_machine(OPERA_URDF, config=config)
    assert any("placeholder masses" in w and "kept" in w and "wrong" in w for w in desc.warnings)
    assert _inertials(desc)["boom_link"].mass == pytest.approx(0.03)


# ----------------------------------------------------------------------------------------- resolution
def _write_package(root: Path, mesh_uri: str, robot_name="tiny") -> Path:
    """A two-link robot in root/tiny_pkg/urdf/, with a COLLADA mesh in root/tiny_pkg/meshes/."""
    (root / "tiny_pkg" / "meshes").mkdir(parents=True)
    (root / "tiny_pkg" / "urdf").mkdir()
    trimesh.creation.box(extents=(0.2, 0.4, 1.0)).export(root / "tiny_pkg" / "meshes" / "arm.dae")
    urdf = root / "tiny_pkg" / "urdf" / "tiny.urdf"
    urdf.write_text(f"""<?xml version="1.0"?>
<robot name="{robot_name}">
  <link name="base"/>
  <joint name="hinge" type="revolute"><parent link="base"/><child link="arm"/><origin xyz="0 0 1"/>
    <axis xyz="0 3 0"/><limit lower="-1" upper="1" velocity="0.5" effort="100"/></joint>
  <link name="arm">
    <visual><geometry><mesh filename="{mesh_uri}"/></geometry>
      <material name="m"><texture filename="package://tiny_pkg/missing.png"/></material></visual>
    <collision><origin xyz="0 0 0.5"/><geometry><mesh filename="{mesh_uri}"/></geometry></collision>
    <inertial><mass value="0.03"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial>
  </link>
  <gazebo reference="arm"><material>x</material></gazebo>
</robot>""")
    return urdf


def test_package_uris_dae_and_defaults_without_a_config(tmp_path):
    urdf = _write_package(tmp_path, "package://tiny_pkg/meshes/arm.dae")
    desc = load_machine(urdf)
    assert desc.actuated_joints == ["hinge"]
    assert desc.actuators["hinge"].max_speed == 0.5 and desc.actuators["hinge"].max_torque == 100
    assert desc.tip_link == "arm" and desc.soil_links == ["arm"]
    assert any("no machine config" in w for w in desc.warnings)
    assert any("placeholder masses (0.03 kg)" in w and "kept" in w for w in desc.warnings)
    # the collision origin is applied: the box now spans z 0..1 in the link frame
    assert desc.collision_meshes["arm"].bounds[:, 2] == pytest.approx([0.0, 1.0])
    assert Kinematics(desc).link_pose({"hinge": 0.5}, "arm")[:3, :3] @ [1, 0, 0] == pytest.approx(
        [math.cos(0.5), 0, -math.sin(0.5)])                       # axis "0 3 0" taken as unit y


def test_masses_from_a_config_replace_placeholders(tmp_path):
    urdf = _write_package(tmp_path, "../meshes/arm.dae")           # a relative URI this time
    (urdf.parent / "machine.yaml").write_text("masses: {arm: 80}\njoints: {hinge: {max_speed: 1, max_torque: 5e+3, gain: 4}}\n")
    desc = load_machine(urdf)
    inertial = _inertials(desc)["arm"]
    assert inertial.mass == 80
    # a solid 0.2 x 0.4 x 1.0 box, centre at z = 0.5 (from the collision origin)
    assert inertial.origin[:3, 3] == pytest.approx([0, 0, 0.5], abs=1e-9)
    assert np.diag(inertial.inertia) == pytest.approx([80 / 12 * (0.16 + 1), 80 / 12 * (0.04 + 1),
                                                       80 / 12 * (0.04 + 0.16)])
    assert desc.actuators["hinge"].gain == 4


def test_joint_specs_tell_a_joint_that_turns_from_one_with_limits(tmp_path):
    """What compare checks a joint log by: a continuous joint, or a revolute one whose limits span more than a turn,
    turns (its unwrapped angle has no bound); the speed limit is the actuator's, as load_machine reads it."""
    zx = joint_specs("zx120")
    assert zx["swing_joint"].type == "continuous" and zx["swing_joint"].turns
    assert not any(zx[j].turns for j in ("boom_joint", "arm_joint", "bucket_joint"))
    # machines/zx120/machine.yaml's joints section
    assert {j: zx[j].max_speed for j in ("swing_joint", "boom_joint", "arm_joint", "bucket_joint")} == \
        {"swing_joint": 1.2, "boom_joint": 0.7, "arm_joint": 0.75, "bucket_joint": 1.1}
    assert joint_specs("zx120", actuator_overrides={"swing_joint": {"max_speed": 2.0}})["swing_joint"].max_speed == 2.0
    urdf = _write_package(tmp_path, "../meshes/arm.dae")
    wide = urdf.with_name("wide.urdf")
    wide.write_text(urdf.read_text().replace('lower="-1" upper="1"', 'lower="-10" upper="10"'))
    assert not joint_specs(urdf)["hinge"].turns and joint_specs(wide)["hinge"].turns
    half = urdf.with_name("turn.urdf")  # exactly one turn: bounded, a log beyond it is out of the joint's range
    half.write_text(urdf.read_text().replace('lower="-1" upper="1"', 'lower="-3.14159265" upper="3.14159265"'))
    assert not joint_specs(half)["hinge"].turns


# ----------------------------------------------------------------------------------------- errors
def _one_line_error(*args, **kwargs) -> str:
    with pytest.raises(UserError) as info:
        load_machine(*args, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_errors_name_the_file_and_what_is_wrong(tmp_path):
    assert "no_such.urdf" in _one_line_error(tmp_path / "no_such.urdf")
    assert "built-in" in _one_line_error("no_such_machine")

    broken = tmp_path / "broken.urdf"
    broken.write_text("<robot name='x'><link name='a'></robot>")
    assert "broken.urdf" in _one_line_error(broken) and "XML" in _one_line_error(broken)

    urdf = _write_package(tmp_path, "package://tiny_pkg/meshes/gone.stl")
    message = _one_line_error(urdf)
    assert "tiny.urdf" in message and "package://tiny_pkg/meshes/gone.stl" in message and "tiny_pkg" in message

    good = _write_package(tmp_path / "b", "package://tiny_pkg/meshes/arm.dae")
    config = tmp_path / "bad.yaml"
    config.write_text("actuated_joints: [hinge, wrist]\n")
    message = _one_line_error(good, config=config)
    assert "bad.yaml" in message and "wrist" in message
    config.write_text("joints: {hinge: {max_speed: -1, max_torque: 10, gain: 5}}\n")
    message = _one_line_error(good, config=config)
    assert "joints.hinge.max_speed" in message and "positive" in message
    config.write_text("masses: {elbow: 10}\n")
    assert "masses.elbow" in _one_line_error(good, config=config)
    config.write_text("joint: {}\n")
    assert "unknown key 'joint'" in _one_line_error(good, config=config)
    # overrides are named as the scene's machine.actuators keys (model.py puts the machine's key in front)
    assert _one_line_error(good, actuator_overrides={"hinge": {"max_torque": 0}}).startswith(
        "actuators.hinge.max_torque")
    assert "(did you mean 'hinge'?)" in _one_line_error(good, actuator_overrides={"hinje": {"max_torque": 1}})


def test_tracks_lateral_friction_defaults_below_the_tractive_and_a_higher_one_is_warned(tmp_path):
    settings = yaml.safe_load((machines_dir() / "zx120" / "machine.yaml").read_text())
    urdf = machines_dir() / "zx120" / "zx120.urdf"
    del settings["tracks"]["lateral_friction"]
    (tmp_path / "default.yaml").write_text(yaml.safe_dump(settings))
    desc = load_machine(urdf, config=tmp_path / "default.yaml")
    assert desc.tracks["lateral_friction"] == pytest.approx(0.6 * desc.tracks["friction"])
    assert not any("lateral_friction" in w for w in desc.warnings)
    settings["tracks"]["lateral_friction"] = settings["tracks"]["friction"]
    (tmp_path / "grippy.yaml").write_text(yaml.safe_dump(settings))
    desc = load_machine(urdf, config=tmp_path / "grippy.yaml")
    assert any("tracks.lateral_friction 0.8 >= tracks.friction 0.8" in w and "turn" in w for w in desc.warnings)


def test_machine_yaml_is_read_as_a_scene_is(tmp_path):
    """Through the scene's YAML reader: YAML 1.2 numbers, one line for a duplicate key or a non-UTF-8 byte, and a
    quoted number is a string, refused as in a scene."""
    urdf = _write_package(tmp_path, "../meshes/arm.dae")
    config = urdf.with_name("machine.yaml")
    config.write_text("command_latency: 1e-3\n")            # YAML 1.1 (PyYAML) read this as the string '1e-3'
    assert load_machine(urdf).command_latency == 0.001
    config.write_text('struck_volume: {arm: "1e3"}\n')
    assert "struck_volume.arm must be a positive number, got '1e3'" in _one_line_error(urdf)
    config.write_text("masses: {arm: 80}\nmasses: {arm: 90}\n")
    assert "masses: duplicate key (lines 1 and 2)" in _one_line_error(urdf)
    config.write_bytes("name: caf\xe9\n".encode("latin-1"))
    message = _one_line_error(urdf)
    assert "machine.yaml" in message and "not UTF-8" in message


def test_track_positions_are_finite_and_latency_has_the_scene_keys_bound(tmp_path):
    settings = yaml.safe_load((machines_dir() / "zx120" / "machine.yaml").read_text())
    urdf = machines_dir() / "zx120" / "zx120.urdf"
    config = tmp_path / "machine.yaml"
    settings["tracks"]["x"] = [float("nan"), float("inf"), -1.5]
    config.write_text(yaml.safe_dump(settings))
    assert "tracks.x must be a list of finite wheel positions" in _one_line_error(urdf, config=config)
    settings["tracks"]["x"] = [1.5, 0.0, -1.5]
    settings["command_latency"] = 5000.0                    # the scene's machine.command_latency stops at 10 s
    config.write_text(yaml.safe_dump(settings))
    assert "command_latency must be a number of seconds >= 0 and <= 10, got 5000.0" in _one_line_error(
        urdf, config=config)
    settings["command_latency"] = 10.0
    config.write_text(yaml.safe_dump(settings))
    assert load_machine(urdf, config=config).command_latency == 10.0


@pytest.mark.parametrize("geometry, named", [
    ('<box size="1 1"/>', '<box size="1 1">: expected 3 finite positive numbers'),
    ('<box size="0 0 0"/>', '<box size="0 0 0">: expected 3 finite positive numbers'),
    ('<cylinder radius="0.1" length="-1"/>', '<cylinder length="-1">: expected a finite positive number'),
    ('<sphere radius="nan"/>', '<sphere radius="nan">: expected a finite positive number')])
def test_urdf_shapes_need_finite_positive_sizes(tmp_path, geometry, named):
    """trimesh failed on a two-number box with a traceback; a zero box was taken as an empty shape."""
    urdf = tmp_path / "shape.urdf"
    urdf.write_text(f'<robot name="r"><link name="a"><collision><geometry>{geometry}</geometry></collision></link>'
                    '</robot>')
    assert f"shape.urdf: link 'a' {named}" in _one_line_error(urdf)


@pytest.mark.parametrize("lower, upper", [("1", "-1"), ("nan", "1"), ("-1", "inf")])
def test_urdf_joint_limits_must_be_finite_and_ordered(tmp_path, lower, upper):
    urdf = _write_package(tmp_path, "../meshes/arm.dae")
    urdf.write_text(urdf.read_text().replace('lower="-1" upper="1"', f'lower="{lower}" upper="{upper}"'))
    with pytest.raises(UserError, match=rf"tiny.urdf: joint 'hinge' <limit> lower={lower} upper={upper}: expected "
                                        "finite numbers with lower <= upper"):
        joint_specs(urdf)


def test_a_tip_no_actuated_joint_moves_is_named(tmp_path):
    """Kinematics failed on it with a ValueError traceback when the model was built."""
    urdf = _write_package(tmp_path, "../meshes/arm.dae")
    # a sensor on a longer fixed chain off the base becomes the default tip
    urdf.write_text(urdf.read_text().replace('<gazebo', '<joint name="m" type="fixed"><parent link="base"/>'
                                             '<child link="mast"/></joint><link name="mast"/><joint name="s" '
                                             'type="fixed"><parent link="mast"/><child link="sensor"/></joint>'
                                             '<link name="sensor"/><gazebo'))
    message = _one_line_error(urdf)
    assert "tiny.urdf: no actuated joint moves link 'sensor'" in message and "(actuated joints: hinge)" in message
    (urdf.parent / "machine.yaml").write_text("tip_link: mast\n")
    assert "machine.yaml: tip_link 'mast': no actuated joint moves this link" in _one_line_error(urdf)
    (urdf.parent / "machine.yaml").write_text("tip_link: arm\n")
    assert load_machine(urdf).tip_link == "arm"


def test_links_without_inertial_are_said_as_such(tmp_path):
    """The warning printed an empty list of masses, "placeholder masses ( kg)", for links without <inertial>."""
    urdf = _write_package(tmp_path, "../meshes/arm.dae")
    text = urdf.read_text()
    urdf.write_text(text[:text.index("<inertial>")] + text[text.index("</inertial>") + len("</inertial>"):])
    kept = [w for w in load_machine(urdf).warnings if w.startswith("placeholder masses")]
    assert len(kept) == 1 and kept[0].startswith("placeholder masses (no <inertial>) in ") and "kept for arm" in kept[0]
    (urdf.parent / "machine.yaml").write_text("masses: {arm: 80}\n")
    replaced = [w for w in load_machine(urdf).warnings if w.startswith("placeholder masses")]
    assert len(replaced) == 1 and replaced[0].startswith("placeholder masses (no <inertial>) in ")


def test_track_max_speed_is_read_checked_and_its_absence_said(tmp_path):
    settings = yaml.safe_load((machines_dir() / "zx120" / "machine.yaml").read_text())
    urdf = machines_dir() / "zx120" / "zx120.urdf"
    config = tmp_path / "machine.yaml"
    settings["tracks"]["max_speed"] = 0
    config.write_text(yaml.safe_dump(settings))
    assert "tracks.max_speed must be a positive number, got 0" in _one_line_error(urdf, config=config)
    del settings["tracks"]["max_speed"]
    config.write_text(yaml.safe_dump(settings))
    desc = load_machine(urdf, config=config)
    assert desc.tracks["max_speed"] is None and any("no tracks.max_speed" in w for w in desc.warnings)


def test_the_bucket_has_its_cutting_edge_and_bad_edges_are_one_line(tmp_path):
    """machine.yaml's cutting_edges: the ZX120 bucket's edge lies on the edge's end face and its face (the opening's
    plane, edge to top edge, an opening) faces the mouth; it acts where a scene sets machine.soil_wedge: true, and by
    default where fewer than 4 grain diameters span the edge (asking a machine without edges for its wedge is an
    error); a bad edge is one line naming the file and the key."""
    from opera_taichi.model import build_model
    from opera_taichi.scene import load_scene

    desc = load_machine("zx120")
    edge = desc.cutting_edges["bucket_link"]
    mesh = desc.collision_meshes["bucket_link"]
    _, distance, _ = mesh.nearest.on_surface([edge.centre])
    assert distance[0] < 1e-6
    normal, up = np.asarray(edge.face_normal, float), np.asarray(edge.face_up, float)
    assert abs(normal @ up) < 1e-9 and normal[0] > 0.0  # the mouth faces +x of bucket_link
    assert edge.opening  # (no plate: the soil over the edge passes into the bucket)
    scene = Path(__file__).resolve().parents[1] / "scenes" / "zx120_excavation.yaml"

    def cuts_with_wedge(*sets):
        binding = build_model(load_scene(scene, list(sets))).bindings[0]
        assert binding.cutting_edge in (edge, None)
        return binding.cutting_edge is not None

    # by default on where the grains are coarse for the 0.70 m edge: 4 diameters across at a radius of 8.75 cm
    assert edge.width == pytest.approx(0.70)
    assert not cuts_with_wedge() and not cuts_with_wedge("soil.overrides.radius=0.0874")   # the scene's 8 cm
    assert cuts_with_wedge("soil.overrides.radius=0.0876") and cuts_with_wedge("soil.overrides.radius=0.12")
    assert cuts_with_wedge("machine.soil_wedge=true")
    assert not cuts_with_wedge("machine.soil_wedge=false", "soil.overrides.radius=0.12")
    with pytest.raises(UserError) as info:
        load_scene(scene, ["machine.soil_wedge=maybe"])
    assert "machine.soil_wedge" in str(info.value) and "true, false or null" in str(info.value)

    settings = yaml.safe_load((machines_dir() / "zx120" / "machine.yaml").read_text())
    bare = tmp_path / "bare" / "machine.yaml"  # a machine without edges: asking for its wedge is an error
    bare.parent.mkdir()
    bare.write_text(yaml.safe_dump({k: v for k, v in settings.items() if k != "cutting_edges"}))
    assert build_model(load_scene(scene, [f"machine.config={bare}", "soil.overrides.radius=0.12"])
                       ).bindings[0].cutting_edge is None
    with pytest.raises(UserError) as info:
        build_model(load_scene(scene, ["machine.soil_wedge=true", f"machine.config={bare}"]))
    assert str(info.value).startswith("machine.soil_wedge:") and "no cutting_edges" in str(info.value)

    urdf = machines_dir() / "zx120" / "zx120.urdf"
    config = tmp_path / "machine.yaml"
    for bad, words in (({"arm_link": settings["cutting_edges"]["bucket_link"]}, ["cutting_edges", "'arm_link'",
                                                                                  "not a soil link"]),
                       ({"bucket_link": {**settings["cutting_edges"]["bucket_link"], "face_normal": [0, 0, 0]}},
                        ["cutting_edges.bucket_link.face_normal", "not all zero"]),
                       ({"bucket_link": {**settings["cutting_edges"]["bucket_link"], "width": -1}},
                        ["cutting_edges.bucket_link.width"]),
                       ({"bucket_link": {**settings["cutting_edges"]["bucket_link"], "opening": "maybe"}},
                        ["cutting_edges.bucket_link.opening", "maybe"])):
        config.write_text(yaml.safe_dump({**settings, "cutting_edges": bad}))
        message = _one_line_error(urdf, config=config)
        assert "machine.yaml" in message and all(w in message for w in words), message
