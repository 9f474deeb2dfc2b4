"""DEM contact physics on small particle sets: ground contact, restitution, conservation, mass budget."""
import numpy as np
import pytest

from opera_taichi.backend import current_arch, init_taichi
from opera_taichi.errors import DivergenceError
from opera_taichi.soil import STEP_FRACTION, bulk_to_micro, resolve_soil


@pytest.fixture(scope="module", autouse=True)
def taichi_cpu():
    if current_arch() is None:
        init_taichi("cpu")


def make_soil(preset="sand", overrides=None, gravity=(0.0, 0.0, -9.81), domain=((-1, -1, -1), (1, 1, 2)), **kw):
    from opera_taichi.dem_soil import DemSoil

    over = {"radius": 0.02, "polydispersity": 0.0}
    over.update(overrides or {})
    micro = bulk_to_micro(resolve_soil(preset, over))
    return DemSoil(micro, domain_min=domain[0], domain_max=domain[1], beds=[], gravity=gravity, **kw)


def random_cloud(rng, n, centre, half, r):
    """n non-overlapping sphere centres in a box: a random subset of a jittered lattice of spacing 2.4 r."""
    spacing = 2.4 * r
    axes = [c + np.arange(-h, h + 1e-12, spacing) for c, h in zip(centre, half)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    assert len(grid) >= n
    grid += rng.uniform(-1, 1, grid.shape) * 0.15 * r
    return grid[rng.permutation(len(grid))[:n]]


def test_particle_resting_on_the_ground_penetrates_less_than_one_percent():
    soil = make_soil()
    r = soil.micro.radius
    soil.set_particles([[0.1, -0.2, 3 * r]])
    soil.advance(1.0)
    p = soil.particles()
    z = p["positions"][0, 2]
    assert 0 < (r - z) / r < 0.01
    assert np.abs(p["velocities"]).max() < 1e-3
    # it stayed where it was dropped (no spurious tangential force)
    assert np.allclose(p["positions"][0, :2], [0.1, -0.2], atol=1e-6)


def test_stack_on_the_ground_carries_its_weight():
    soil = make_soil(overrides={"youngs_modulus": 2e6})
    r = soil.micro.radius
    n = 8
    soil.set_particles([[0, 0, r + 2 * r * k * 1.001] for k in range(n)])
    soil.advance(1.0)
    z = np.sort(soil.particles()["positions"][:, 2])
    m, k_n, k_wall = soil.micro.particle_mass, soil.micro.k_n, soil.micro.k_wall
    # bottom overlap with the ground carries the whole column; each contact above carries what lies over it
    assert (r - z[0]) == pytest.approx(n * m * 9.81 / k_wall, rel=0.02)
    gaps = 2 * r - np.diff(z)
    expected = m * 9.81 * np.arange(n - 1, 0, -1) / k_n
    assert np.allclose(gaps, expected, rtol=0.02)


@pytest.mark.parametrize("restitution", [0.3, 0.5, 0.8])
def test_head_on_collision_restitution(restitution):
    """Rebound speed ratio = e, averaged over where the impact falls within a step. One collision's ratio varies
    with that phase, an error of first order in the step: from end to end 0.17 e at e = 0.3 with dt = t_c / 15, 0.25 e
    with t_c / 10."""
    soil = make_soil(overrides={"restitution": restitution, "friction_angle_deg": 30}, gravity=(0, 0, 0))
    r = soil.micro.radius
    v = 0.5
    ratios = []
    for phase in (0.125, 0.375, 0.625, 0.875):
        gap = 0.01 * r + phase * 2 * v * soil.dt
        soil.set_particles([[-r - gap / 2, 0, 1], [r + gap / 2, 0, 1]], velocities=[[v, 0, 0], [-v, 0, 0]])
        soil.advance(0.05)
        vel = soil.particles()["velocities"]
        assert vel[0, 0] == pytest.approx(-vel[1, 0], rel=1e-12)
        assert np.abs(vel[:, 1:]).max() < 1e-12
        ratios.append(vel[1, 0] / v)
    assert np.mean(ratios) == pytest.approx(restitution, rel=0.03)
    assert np.ptp(ratios) < 3.75 / STEP_FRACTION * restitution  # 0.25 e at t_c / 15


def test_ground_bounce_restitution():
    """The ground (k = 2 k_n against one sphere) has the same contact period as a sphere pair, so the same e."""
    soil = make_soil(overrides={"restitution": 0.5}, gravity=(0, 0, 0))
    r = soil.micro.radius
    ratios = []
    for phase in (0.125, 0.375, 0.625, 0.875):
        soil.set_particles([[0, 0, r * 1.01 + phase * soil.dt]], velocities=[[0, 0, -1.0]])
        soil.advance(0.02)
        ratios.append(soil.particles()["velocities"][0, 2])
    assert np.mean(ratios) == pytest.approx(0.5, rel=0.03)


@pytest.mark.parametrize("preset", ["sand", "dirt"])
def test_momentum_conserved_in_free_collisions(preset):
    """No gravity, no walls in reach: particle-particle forces (contact, friction, rolling resistance, cohesion)
    must leave the total momentum unchanged to round-off."""
    rng = np.random.default_rng(3)
    soil = make_soil(preset, overrides={"polydispersity": 0.1}, gravity=(0, 0, 0), domain=((-2, -2, -2), (2, 2, 2)))
    r = soil.micro.radius
    n = 300
    centre = np.array([0.0, 0.0, 1.0])  # well above the ground (z = 0)
    pos = random_cloud(rng, n, centre, (0.2, 0.2, 0.2), r * 1.1)
    vel = rng.normal(0, 0.5, (n, 3)) + [0.3, -0.1, 0.2]
    vel -= 1.5 * (pos - centre) / 0.2  # converge towards the centre: many collisions, lasting contacts
    radii = r * (1 + 0.1 * rng.uniform(-1, 1, n))
    soil.set_particles(pos, velocities=vel, radii=radii, angular_velocities=rng.normal(0, 5, (n, 3)))
    p0 = soil.momentum()
    scale = np.sum(soil.particles()["masses"][:, None] * np.abs(vel))
    soil.advance(0.15)
    p1 = soil.momentum()
    assert soil.n_particles == n
    assert np.max(np.abs(soil.particles()["positions"] - centre)) < 0.8  # nothing reached a wall or the ground
    assert np.abs(p1 - p0).max() < 1e-6 * np.abs(p0).max()
    assert np.abs(p1 - p0).max() < 1e-9 * scale
    assert soil.kinetic_energy() < 0.9 * 0.5 * np.sum(soil.particles()["masses"][:, None] * vel ** 2)  # they did collide


def test_mass_budget_books_particles_that_leave():
    rng = np.random.default_rng(1)
    soil = make_soil(domain=((-0.5, -0.5, -0.2), (0.5, 0.5, 0.6)), overrides={"polydispersity": 0.1})
    r = soil.micro.radius
    n = 120
    pos = random_cloud(rng, n, (0, 0, 0.15), (0.3, 0.3, 0.1), r * 1.1)
    vel = rng.normal(0, 0.3, (n, 3))
    vel[: n // 3, 2] = 6.0             # thrown above the domain top
    pos[n // 3] = [0.7, 0.0, 0.2]      # already through a side wall
    radii = r * (1 + 0.1 * rng.uniform(-1, 1, n))
    soil.set_particles(pos, velocities=vel, radii=radii)
    total = soil.mass_budget()["particles"]
    assert soil.mass_budget()["out_of_domain"] == 0.0
    for _ in range(5):
        soil.advance(0.1)
        budget = soil.mass_budget()
        assert budget["particles"] + budget["out_of_domain"] == pytest.approx(total, rel=1e-9)
    lost = n - soil.n_particles
    assert lost >= n // 4  # most of the thrown ones, and the one beyond the wall
    m = soil.micro.particle_mass
    assert lost * 0.9 ** 3 * m <= budget["out_of_domain"] <= lost * 1.1 ** 3 * m


def test_divergence_is_reported_with_the_limit_that_tripped():
    soil = make_soil(gravity=(0, 0, 0), max_speed=30.0)
    soil.set_particles([[0, 0, 1]], velocities=[[40.0, 0, 0]])
    with pytest.raises(DivergenceError, match=r"^soil diverged at t = 0.001 s: particle speed 40 m/s above the limit "
                                              r"30 m/s \(soil.max_speed\)$"):
        soil.advance(0.001)


def test_a_rebuild_marks_the_blocks_of_the_particles_it_leaves_active():
    """A rebuild ends by finding each block's box and whether it takes part in the next substep, in blocks sized
    for the particles the rebuild leaves active (larger past 32,768): the same blocks as finding them afresh."""
    from kernels import dem

    soil = make_soil()
    r = soil.micro.radius
    soil.set_particles(random_cloud(np.random.default_rng(3), 40_000, (0.0, 0.0, 1.0), (0.85, 0.85, 0.85), r))
    assert soil.n_act == 40_000 and soil._block > dem.MIN_STEP_BLOCK
    hot, box = soil._blk_hot.to_numpy(), soil._blk_box.to_numpy()
    soil._blocks_changed()
    assert np.array_equal(hot, soil._blk_hot.to_numpy())
    assert np.array_equal(box, soil._blk_box.to_numpy())
