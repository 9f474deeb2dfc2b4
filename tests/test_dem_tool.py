"""Tool signed distance grids and particle-tool contact: geometry, statics, Newton's third law, kinematics."""
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from opera_taichi.backend import current_arch, init_taichi
from opera_taichi.soil import bulk_to_micro, resolve_soil
from opera_taichi.tool_sdf import build_sdf, tool_sdf


@pytest.fixture(scope="module", autouse=True)
def taichi_cpu():
    if current_arch() is None:
        init_taichi("cpu")


def make_soil(gravity=(0.0, 0.0, -9.81), **over):
    from opera_taichi.dem_soil import DemSoil

    overrides = {"radius": 0.02, "youngs_modulus": 2e6}
    overrides.update(over)
    micro = bulk_to_micro(resolve_soil("sand", overrides))
    return DemSoil(micro, domain_min=(-2, -2, -1), domain_max=(2, 2, 3), beds=[], gravity=gravity)


def container_mesh(inner=0.3, height=0.2, wall=0.02):
    """Open-top box of five plates (each a watertight body): floor top at z = 0.01 in the link frame."""
    half = inner / 2 + wall / 2
    parts = [trimesh.creation.box([inner + 2 * wall, inner + 2 * wall, wall])]
    for sx, sy, ex, ey in [(1, 0, wall, inner + 2 * wall), (-1, 0, wall, inner + 2 * wall),
                           (0, 1, inner, wall), (0, -1, inner, wall)]:
        plate = trimesh.creation.box([ex, ey, height])
        plate.apply_translation([sx * half, sy * half, wall / 2 + height / 2])
        parts.append(plate)
    return trimesh.util.concatenate(parts)


def test_box_sdf_is_exact_near_faces_and_signed():
    box = trimesh.creation.box([0.4, 0.3, 0.1])
    h = 0.01
    grid = build_sdf(box, h, 0.05)
    rng = np.random.default_rng(0)
    # points over the +z face, away from its edges: the exact SDF is linear there, trilinear sampling is exact
    pts = np.column_stack([rng.uniform(-0.15, 0.15, 200), rng.uniform(-0.1, 0.1, 200), rng.uniform(0.02, 0.09, 200)])
    dist, grad = grid.sample(pts)
    assert np.allclose(dist, pts[:, 2] - 0.05, atol=1e-6)
    assert np.allclose(grad, [0, 0, 1], atol=1e-6)
    # anywhere near the box, within a fraction of a cell of the exact signed distance (negative inside)
    pts = rng.uniform([-0.24, -0.19, -0.09], [0.24, 0.19, 0.09], (2000, 3))
    q = np.abs(pts) - [0.2, 0.15, 0.05]
    exact = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
    dist, grad = grid.sample(pts)
    near = exact < 0.045  # distances are exact within the band (the 0.05 margin), clamped beyond
    assert np.abs(dist - exact)[near].max() < 0.25 * h
    assert np.all(dist[~near] > 0.04)
    assert np.all(np.sign(dist[np.abs(exact) > h]) == np.sign(exact[np.abs(exact) > h]))
    outside = near & (exact > 0)  # interpolated unit normals fan out around edges, never cancel outside
    assert np.all(np.linalg.norm(grad[outside], axis=1) > 0.5)


def test_open_sheet_becomes_a_thin_plate():
    quad = trimesh.Trimesh(vertices=[[-0.2, -0.2, 0], [0.2, -0.2, 0], [0.2, 0.2, 0], [-0.2, 0.2, 0]],
                           faces=[[0, 1, 2], [0, 2, 3]])
    assert not quad.is_watertight
    h = 0.01
    grid = build_sdf(quad, h, 0.05)
    z = np.linspace(-0.04, 0.04, 9)
    dist, grad = grid.sample(np.column_stack([np.zeros(9) + 0.013, np.zeros(9) - 0.021, z]))
    assert np.allclose(dist, np.abs(z) - h, atol=0.15 * h)
    assert np.allclose(grad[z > h, 2], 1, atol=1e-3) and np.allclose(grad[z < -h, 2], -1, atol=1e-3)


def test_sdf_cache_returns_the_same_grid(tmp_path, monkeypatch):
    monkeypatch.setenv("OPERA_TAICHI_CACHE", str(tmp_path))
    mesh = trimesh.creation.box([0.2, 0.2, 0.2])
    first = tool_sdf(mesh, 0.02, 0.05)
    assert len(list((tmp_path / "sdf").glob("*.npz"))) == 1
    second = tool_sdf(mesh, 0.02, 0.05)
    assert np.array_equal(first.data, second.data) and np.array_equal(first.origin, second.origin)
    tool_sdf(mesh, 0.025, 0.05)
    assert len(list((tmp_path / "sdf").glob("*.npz"))) == 2


def test_particle_rests_on_a_tilted_plate_tool():
    """Contact through the SDF of a rotated tool: a sphere settles on the plate with < 1% of r overlap."""
    soil = make_soil(friction_angle_deg=40)
    plate = trimesh.creation.box([0.6, 0.6, 0.04])
    t = soil.add_tool("plate", plate)
    tilt = Rotation.from_euler("y", 10, degrees=True)
    soil.set_tool_state(t, [0, 0, 0.5], tilt.as_quat(), [0, 0, 0], [0, 0, 0])
    r = soil.micro.radius
    normal = tilt.apply([0, 0, 1])
    start = np.array([0, 0, 0.5]) + normal * (0.02 + r * 1.05)
    soil.set_particles([start])
    soil.advance(0.5)
    x = soil.particles()["positions"][0]
    height = np.dot(x - [0, 0, 0.5], normal)
    assert 0 < 0.02 + r - height < 0.01 * r
    # friction (tan 40 > tan 10) and rolling resistance hold it on the slope
    assert np.linalg.norm(x - start) < 0.1 * r


def _adhesive_plate(factor, g, **over):
    """A frictionless plate (top at z = 0.52) with soil-tool adhesion whose force per contact is `factor` x m |g|."""
    from opera_taichi.soil import TOOL_CONTACT_AREA

    plain = make_soil(**over)
    mass, r = plain.micro.particle_mass, plain.micro.radius
    adhesion = factor * mass * g / (TOOL_CONTACT_AREA * r * r)  # Pa; tan(delta) = 0
    soil = make_soil(adhesion=adhesion, tool_friction_angle_deg=0.0, **over)
    assert soil.micro.adhesion_force == pytest.approx(factor * mass * g)
    t = soil.add_tool("plate", trimesh.creation.box([0.6, 0.6, 0.04]))
    soil.set_tool_state(t, [0, 0, 0.5], [0, 0, 0, 1], [0, 0, 0], [0, 0, 0])
    return soil, r


@pytest.mark.parametrize("factor, holds", [(1.25, True), (0.8, False)])
def test_adhesion_holds_a_particle_under_a_plate_against_its_weight(factor, holds):
    """The attraction: a grain touching the underside of a plate hangs there if the adhesion force exceeds its
    weight, and falls if not."""
    soil, r = _adhesive_plate(factor, 9.81)
    start = np.array([0.0, 0.0, 0.48 - 0.999 * r])
    soil.set_particles([start])
    soil.advance(0.5)
    drop = start[2] - soil.particles()["positions"][0][2]
    if holds:
        assert abs(drop) < 0.01 * r
    else:
        assert drop > 0.5 * 9.81 * 0.5 ** 2 * 0.1  # falling at (1 - 0.8) g at least


@pytest.mark.parametrize("factor, holds", [(1.25, True), (0.8, False)])
def test_adhesion_grips_a_particle_on_a_frictionless_plate(factor, holds):
    """The grip: on a frictionless plate with gravity tilted 45 deg (a 45 deg slope), a grain stays put if the
    adhesion force exceeds the pull along the slope, and slides if not, still on the plate (rolling resistance 1
    keeps it from rolling, so the tangential capacity alone holds it)."""
    g = (9.81, 0.0, -9.81)
    soil, r = _adhesive_plate(factor, 9.81, gravity=g, rolling_resistance=1.0)
    start = np.array([0.0, 0.0, 0.52 + 0.999 * r])
    soil.set_particles([start])
    soil.advance(0.5)
    x = soil.particles()["positions"][0]
    assert abs(x[2] - start[2]) < 0.01 * r  # on the plate
    if holds:
        assert np.linalg.norm(x - start) < 0.05 * r
    else:
        assert x[0] - start[0] > 0.5 * 9.81 * 0.5 ** 2 * 0.1  # sliding at (1 - 0.8) g_x at least


def test_container_tool_carries_the_weight_of_the_soil_it_holds():
    soil = make_soil()
    t = soil.add_tool("bin", container_mesh())
    origin = np.array([0.1, -0.2, 0.3])
    soil.set_tool_state(t, origin, [0, 0, 0, 1], [0, 0, 0], [0, 0, 0])
    r = soil.micro.radius
    axis = np.arange(-0.12, 0.121, 0.048)
    grid = np.stack(np.meshgrid(axis, axis, 0.31 + r * 1.2 + 0.048 * np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    grid[:, 1] += 0.01 * np.sin(7 * grid[:, 0])  # break the symmetry a little
    soil.set_particles(grid + origin * [1, 1, 0])
    soil.advance(0.8)
    wrench = soil.advance(0.2)[t]
    p = soil.particles()
    weight = p["masses"].sum() * 9.81
    assert soil.n_particles == len(grid)
    assert wrench[2] == pytest.approx(-weight, rel=0.05)  # the soil presses down with its weight
    assert np.abs(wrench[:2]).max() < 0.05 * weight
    com = (p["masses"][:, None] * p["positions"]).sum(0) / p["masses"].sum()
    expected_torque = np.cross(com - origin, [0, 0, -weight])
    assert np.abs(wrench[3:] - expected_torque).max() < 0.05 * weight * 0.15
    carried = soil.mass_in_box(origin, [0, 0, 0, 1], [-0.15, -0.15, 0.0], [0.15, 0.15, 0.25])
    assert carried == pytest.approx(p["masses"].sum(), rel=1e-12)


@pytest.mark.parametrize("adhesion", [0.0, 3000.0])
def test_tool_forces_obey_newtons_third_law(adhesion):
    """No gravity, nothing else to push on: the particles' momentum change equals minus the tool impulse (with the
    soil-tool adhesion's attraction and grip too)."""
    soil = make_soil(gravity=(0, 0, 0), cohesion=2000.0, adhesion=adhesion)
    t = soil.add_tool("plate", trimesh.creation.box([0.3, 0.3, 0.04]))
    rng = np.random.default_rng(5)
    r = soil.micro.radius
    axes = [np.arange(0.05, 0.3, 2.4 * r), np.arange(-0.15, 0.15, 2.4 * r), 1.0 + np.arange(-0.15, 0.15, 2.4 * r)]
    pos = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3) + rng.uniform(-0.1, 0.1, (1, 3)) * r
    soil.set_particles(pos, velocities=rng.normal(0, 0.05, pos.shape))
    soil.set_tool_state(t, [-0.2, 0, 1.0], Rotation.from_euler("y", 80, degrees=True).as_quat(), [1.0, 0.0, 0.1],
                        [0.0, 0.0, 1.0])
    p0 = soil.momentum()
    impulse = np.zeros(3)
    for _ in range(20):
        soil.advance(0.01)
        impulse += soil.last_tool_impulse[t, :3]
    change = soil.momentum() - p0
    assert np.linalg.norm(change) > 1.0  # the plate did push a lot of soil
    assert np.abs(change + impulse).max() < 1e-6 * np.linalg.norm(change)


def test_a_grain_spinning_on_a_tool_gives_it_the_rolling_resistance_torque():
    """A grain spun about the vertical on a still plate, right above the plate's origin: the rolling resistance that
    slows it acts on the plate too, so the angular momentum the grain loses is the angular impulse the plate gets
    (the plate got none: its moment was only the contact forces' about its origin)."""
    soil = make_soil(rolling_resistance=0.5)
    t = soil.add_tool("plate", trimesh.creation.box([0.6, 0.6, 0.04]))
    soil.set_tool_state(t, [0, 0, 0.5], [0, 0, 0, 1], [0, 0, 0], [0, 0, 0])
    r = soil.micro.radius
    soil.set_particles([[0.0, 0.0, 0.52 + 0.999 * r]])
    soil.advance(0.05)
    p = soil.particles()
    soil.set_particles(p["positions"], velocities=np.zeros((1, 3)), angular_velocities=[[0.0, 0.0, 20.0]])
    inertia = 0.4 * p["masses"][0] * r * r
    spin0 = inertia * soil.particles()["angular_velocities"][0]
    impulse = np.zeros(3)
    for _ in range(20):
        soil.advance(0.002)
        impulse += soil.last_tool_impulse[t, 3:]
    change = inertia * soil.particles()["angular_velocities"][0] - spin0
    assert change[2] < -0.1 * abs(spin0[2])   # the rolling resistance did slow it
    assert abs(change[2] + impulse[2]) < 1e-3 * abs(change[2])


def test_tool_moves_kinematically_within_advance():
    soil = make_soil()
    t = soil.add_tool("plate", trimesh.creation.box([0.1, 0.1, 0.1]))
    q0 = Rotation.from_euler("xyz", [0.1, -0.2, 0.3])
    w = np.array([0.3, -0.5, 1.2])
    soil.set_tool_state(t, [0, 0, 1], q0.as_quat(), [0.2, -0.1, 0.05], w)
    soil.advance(0.3)
    pos, rot = soil.tool_pose(t)
    assert np.allclose(pos, [0.06, -0.03, 1.015], atol=1e-12)
    expected = (Rotation.from_rotvec(w * 0.3) * q0).as_matrix()
    assert np.allclose(rot, expected, atol=1e-10)


def test_runs_are_bit_for_bit_reproducible():
    """Same inputs, same thread count: identical particles and tool wrenches (no order-dependent sums)."""
    def run():
        soil = make_soil(cohesion=1000.0)
        t = soil.add_tool("plate", trimesh.creation.box([0.3, 0.3, 0.04]))
        rng = np.random.default_rng(2)
        r = soil.micro.radius
        axes = [np.arange(-0.2, 0.2, 2.3 * r), np.arange(-0.2, 0.2, 2.3 * r), r * 1.05 + 2.3 * r * np.arange(4)]
        pos = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        soil.set_particles(pos + rng.uniform(-0.05, 0.05, pos.shape) * r)
        soil.set_tool_state(t, [-0.35, 0, 0.1], [0, 0, 0, 1], [1.0, 0, 0], [0, 0, 0.5])
        wrenches = [soil.advance(0.01) for _ in range(15)]
        return soil.particles()["positions"], np.array(wrenches), soil.rebuilds

    (pos_a, wrench_a, rebuilds), (pos_b, wrench_b, _) = run(), run()
    assert rebuilds > 3 and np.abs(wrench_a).max() > 0
    assert np.array_equal(pos_a, pos_b) and np.array_equal(wrench_a, wrench_b)


def test_tool_spring_is_dropped_when_the_contact_ends():
    """A particle's tangential spring against a tool lives while they touch and is cleared (with its bit in the
    surf_id column the step kernel checks) once they part: a later contact starts from a relaxed spring."""
    from opera_taichi.kernels import dem

    soil = make_soil(friction_angle_deg=40)
    t = soil.add_tool("plate", trimesh.creation.box([0.6, 0.6, 0.04]))
    r = soil.micro.radius
    soil.set_tool_state(t, [0, 0, 0.5], [0, 0, 0, 1], [0, 0, 0], [0, 0, 0])
    soil.set_particles([[0, 0, 0.52 + 0.99 * r]])
    soil.advance(0.2)
    soil.set_tool_state(t, [0, 0, 0.5], [0, 0, 0, 1], [0.01, 0, 0], [0, 0, 0])  # drags the resting sphere along
    soil.advance(0.05)
    slot = dem.WALL_SLOTS + t
    assert np.abs(soil._surf_h.to_numpy()[0, slot][:3]).max() > 0.0  # the spring holds it by static friction
    assert soil._surf_id.to_numpy()[0, dem.TOOL_BITS] == 1 << t
    soil.set_tool_state(t, [0, 0, -0.5], [0, 0, 0, 1], [0, 0, 0], [0, 0, 0])  # the plate drops away
    soil.advance(0.01)
    assert np.all(soil._surf_h.to_numpy()[0, slot] == 0.0)
    assert soil._surf_id.to_numpy()[0, dem.TOOL_BITS] == 0


CRUSH_PIT = ((-0.16, -0.12, -0.12), (0.16, 0.12, 0.0))


def _blade_in_pit(x, width, z, max_speed=30.0):
    """A settled bed in CRUSH_PIT (stiff: E = 100 MPa, so a grain squeezed against a wall flies off well above
    30 m/s while the blade's push alone stays under 20) and a 4 cm blade at rest at (x, 0, z) in a hole cleared
    for it, after START_TIME at rest (the hint for a tool that starts inside the soil no longer applies)."""
    from opera_taichi.dem_soil import START_TIME, DemSoil

    micro = bulk_to_micro(resolve_soil("sand", {"radius": 0.02, "youngs_modulus": 1e8}), bed_depth=0.12)
    soil = DemSoil(micro, domain_min=(-0.4, -0.4, -0.3), domain_max=(0.4, 0.4, 0.6), beds=[CRUSH_PIT], seed=7,
                   settle_time=0.3, max_speed=max_speed)
    half = np.array([0.02, width / 2, 0.1])
    p = soil.particles()
    keep = np.any(np.abs(p["positions"] - [x, 0.0, z]) > half + 1.05 * p["radii"][:, None], axis=1)
    soil.set_particles(p["positions"][keep], radii=p["radii"][keep])
    blade = soil.add_tool("blade", trimesh.creation.box(2 * half))
    soil.set_tool_state(blade, [x, 0.0, z], [0, 0, 0, 1], [0, 0, 0], [0, 0, 0])
    soil.advance(START_TIME)
    return soil, blade


def _drive_until_diverged(soil, blade, speed) -> str:
    """Drive the blade along +x at `speed` in 5 ms steps until the soil diverges; its message."""
    from opera_taichi.errors import DivergenceError

    with pytest.raises(DivergenceError) as err:
        while soil.time < 1.0:
            soil.set_tool_state(blade, soil.tool_pose(blade)[0], [0, 0, 0, 1], [speed, 0, 0], [0, 0, 0])
            soil.advance(0.005)
    return str(err.value)


def test_a_divergence_names_the_tool_that_crushes_grains_against_a_pit_wall():
    """A blade spanning the pit, a few mm off its floor and side walls, driven at 2 m/s into its +x wall through the
    grains: the run holds until the blade is a grain's diameter from the wall, where a grain squeezed between them
    flies off above soil.max_speed. The message names the blade and that wall (not the floor or the side walls it
    slides along) and what to do."""
    soil, blade = _blade_in_pit(x=0.04, width=0.236, z=-0.015)
    message = _drive_until_diverged(soil, blade, 2.0)
    front = soil.tool_pose(blade)[0][0] + 0.02
    assert CRUSH_PIT[1][0] - front < 2 * soil.r_max  # (it did not diverge before the crush)
    assert message.startswith(f"soil diverged at t = {soil.time:.3f} s: particle speed ")
    assert "the tool 'blade' is " in message and " m from the +x wall of soil.bed.0, closing at 2 m/s" in message
    assert "slow the tool, keep it off the pit's walls and floor, or lower sim.soil_dt" in message
    assert "this early" not in message


@pytest.mark.parametrize("width, z", [(0.1, 0.05), (0.236, -0.015)], ids=["clear of every face", "sliding"])
def test_a_divergence_away_from_the_pit_walls_claims_no_crushing(width, z):
    """The blade mid-pit, clear of the pit's faces by more than a grain's diameter, or spanning the pit and sliding
    along its floor and side walls a few mm off, tripping a low soil.max_speed (5 m/s) by its push alone: the
    message names no tool and no wall."""
    soil, blade = _blade_in_pit(x=-0.1, width=width, z=z, max_speed=5.0)
    message = _drive_until_diverged(soil, blade, 2.0)
    assert CRUSH_PIT[1][0] - soil.tool_pose(blade)[0][0] > 0.1  # mid-pit
    assert message.startswith("soil diverged at t = ") and message.endswith("above the limit 5 m/s (soil.max_speed)")
