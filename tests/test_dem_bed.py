"""Settled DEM beds in pits: rest, caching, bulk density, terrain heightmap."""
import numpy as np
import pytest

from opera_taichi.backend import current_arch, init_taichi
from opera_taichi.soil import bulk_to_micro, resolve_soil

PIT = ((-0.2, -0.2, -0.16), (0.2, 0.2, 0.0))
DOMAIN = ((-0.4, -0.4, -0.3), (0.4, 0.4, 0.6))


@pytest.fixture(scope="module", autouse=True)
def taichi_cpu():
    if current_arch() is None:
        init_taichi("cpu")


def make_bed(**kw):
    from opera_taichi.dem_soil import DemSoil

    micro = bulk_to_micro(resolve_soil("sand", {"radius": 0.02, "youngs_modulus": 2e6}), bed_depth=0.16)
    kw.setdefault("seed", 7)
    return DemSoil(micro, domain_min=DOMAIN[0], domain_max=DOMAIN[1], beds=[PIT], **kw)


@pytest.fixture(scope="module")
def bed():
    return make_bed()


def test_settled_bed_fills_its_pit_at_the_bulk_density(bed):
    p = bed.particles()
    lo, hi = np.array(PIT[0]), np.array(PIT[1])
    r = p["radii"][:, None]
    assert np.all(p["positions"] - r >= lo - 1e-3) and np.all(p["positions"][:, :2] + r[:, 0:1] <= hi[:2] + 1e-3)
    assert np.max(p["positions"][:, 2] + p["radii"]) <= 0.0
    density = bed.mass_budget()["particles"] / np.prod(hi - lo)
    # 0.4 x 0.4 m is only 10 diameters: the wall and surface layers pack looser than the 0.6 assumed inside
    assert 0.8 * bed.micro.bulk_density < density <= 1.02 * bed.micro.bulk_density


def test_settled_bed_drifts_less_than_a_millimetre_in_a_second(bed):
    p0 = bed.particles()["positions"]
    bed.advance(1.0)
    p1 = bed.particles()["positions"]
    assert bed.n_particles == len(p0)
    assert np.linalg.norm(p1 - p0, axis=1).max() < 1e-3


def test_heightmap_is_the_soil_surface_or_the_static_ground(bed):
    r = bed.micro.radius
    xs = np.arange(-0.35, 0.351, 0.1)  # cells of 2.5 particle diameters: each holds part of the top layer
    z = bed.heightmap(xs, xs)
    inner = (np.abs(xs) < 0.2)
    outside = (np.abs(xs) > 0.2)
    surface = z[np.ix_(inner, inner)]
    assert np.all(surface <= 1e-9)
    assert np.all(surface > -2.0 * r)  # a level bed, trimmed at the pit top
    assert np.all(z[outside, :] == 0.0) and np.all(z[:, outside] == 0.0)
    # the surface is the highest particle top in each cell
    p = bed.particles()
    cell = np.floor((p["positions"][:, :2] - xs[0]) / 0.1 + 0.5).astype(int)
    top = p["positions"][:, 2] + p["radii"]
    for i, j in [(2, 2), (3, 4), (5, 3)]:
        assert z[i, j] == top[(cell[:, 0] == i) & (cell[:, 1] == j)].max()


def test_empty_pit_reads_as_its_floor():
    soil = make_bed(settle_time=0.02, use_cache=False)
    soil.set_particles(np.zeros((0, 3)))
    xs = np.array([-0.3, -0.1, 0.1, 0.3])
    z = soil.heightmap(xs, xs)
    expected = np.where((np.abs(xs)[:, None] <= 0.2) & (np.abs(xs)[None, :] <= 0.2), PIT[0][2], 0.0)
    assert np.array_equal(z, expected)
    assert soil.mass_budget() == {"particles": 0.0, "out_of_domain": 0.0}


def test_second_construction_loads_the_settled_bed_from_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("OPERA_TAICHI_CACHE", str(tmp_path))
    first = make_bed(settle_time=0.3)
    files = list((tmp_path / "dem_beds").glob("*.npz"))
    assert len(files) == 1
    second = make_bed(settle_time=0.3)
    a, b = first.particles(), second.particles()
    for key in a:
        assert np.array_equal(a[key], b[key])
    # the contact history came back too: both continue identically
    first.advance(0.05)
    second.advance(0.05)
    assert np.array_equal(first.particles()["positions"], second.particles()["positions"])
    other_seed = make_bed(settle_time=0.3, seed=8)
    assert len(list((tmp_path / "dem_beds").glob("*.npz"))) == 2
    assert not np.array_equal(other_seed.particles()["positions"][:10], a["positions"][:10])
