"""Settled DEM beds in pits: rest, caching, bulk density, terrain heightmap."""
import numpy as np
import pytest
import trimesh

from opera_taichi.backend import current_arch, init_taichi
from opera_taichi.soil import bulk_to_micro, resolve_soil

PIT = ((-0.2, -0.2, -0.16), (0.2, 0.2, 0.0))
DOMAIN = ((-0.4, -0.4, -0.3), (0.4, 0.4, 0.6))


@pytest.fixture(scope="module", autouse=True)
def taichi_cpu():
    if current_arch() is None:
        init_taichi("cpu")


def make_bed(pit=PIT, **kw):
    from opera_taichi.dem_soil import DemSoil

    micro = bulk_to_micro(resolve_soil("sand", {"radius": 0.02, "youngs_modulus": 2e6}), bed_depth=0.16)
    kw.setdefault("seed", 7)
    return DemSoil(micro, domain_min=DOMAIN[0], domain_max=DOMAIN[1], beds=[pit], **kw)


@pytest.fixture(scope="module")
def bed():
    return make_bed(settle_time=2.0)  # (at 1 s a grain by the pit wall had not landed: the bed warned and crept)


def test_settled_bed_fills_its_pit_at_the_bulk_density(bed):
    p = bed.particles()
    lo, hi = np.array(PIT[0]), np.array(PIT[1])
    r = p["radii"][:, None]
    assert np.all(p["positions"] - r >= lo - 1e-3) and np.all(p["positions"][:, :2] + r[:, 0:1] <= hi[:2] + 1e-3)
    assert np.max(p["positions"][:, 2] + 0.5 * p["radii"]) <= 1e-3
    density = bed.mass_budget()["particles"] / np.prod(hi - lo)
    # however loosely the spheres packed, DemSoil matched their masses to the bulk density of the levelled pit
    # (single-precision masses)
    assert density == pytest.approx(bed.micro.bulk_density, rel=1e-5)
    assert 0.3 < bed.bed_packing < 0.65


def test_settled_bed_drifts_less_than_a_millimetre_in_a_second(bed):
    assert bed.warnings == []  # it came to rest
    p0 = bed.particles()["positions"]
    bed.advance(1.0)
    p1 = bed.particles()["positions"]
    assert bed.n_particles == len(p0)
    assert np.linalg.norm(p1 - p0, axis=1).max() < 1e-3


def test_heightmap_is_the_soil_surface_or_the_static_ground(bed):
    r = bed.micro.radius
    xs = np.arange(-0.35, 0.351, 0.01)  # finer than a grain: the terrain is the envelope of the sphere caps
    z = bed.heightmap(xs, xs)
    inner = np.abs(xs) < 0.18
    outside = np.abs(xs) > 0.2 + 1.2 * r
    surface = z[np.ix_(inner, inner)]
    # a bed trimmed level with the pit top, rough at the grain scale: no grain stands more than r/2 above the
    # top, no hole reaches the floor, and on average within a radius
    assert np.all(surface <= 0.5 * r + 1e-3)
    # a friction-poured (loose) bed has gaps between its top grains up to ~1.5 diameters deep; the floor is 8 below
    assert np.all(surface > -4.0 * r) and -r < surface.mean() < 0.5 * r
    assert np.all(z[outside, :] == 0.0) and np.all(z[:, outside] == 0.0)
    # just outside the pit's wall the ground is solid to the rim: grains inside the wall do not reach under it
    off_pit = (np.abs(xs)[:, None] > 0.2) | (np.abs(xs)[None, :] > 0.2)
    assert np.all(z[off_pit] >= 0.0)
    # each node carries the highest point a ball of the grain radius resting on the grains reaches, less r
    p = bed.particles()
    for i, j in [(30, 30), (35, 41), (20, 47)]:
        d2 = (p["positions"][:, 0] - xs[i]) ** 2 + (p["positions"][:, 1] - xs[j]) ** 2
        reach = 2 * p["radii"]
        over = d2 <= reach ** 2
        expected = np.max(p["positions"][over, 2] - p["radii"][over] + np.sqrt(reach[over] ** 2 - d2[over]))
        assert z[i, j] == pytest.approx(expected, abs=1e-12)
    # right above a grain standing alone, the terrain is its top
    top = np.argmax(p["positions"][:, 2] + p["radii"])
    assert bed.heightmap([p["positions"][top, 0]], [p["positions"][top, 1]])[0, 0] == pytest.approx(
        p["positions"][top, 2] + p["radii"][top], abs=1e-12)


def test_empty_pit_reads_as_its_floor():
    soil = make_bed(settle_time=0.02, use_cache=False)
    soil.set_particles(np.zeros((0, 3)))
    xs = np.array([-0.3, -0.1, 0.1, 0.3])
    z = soil.heightmap(xs, xs)
    expected = np.where((np.abs(xs)[:, None] <= 0.2) & (np.abs(xs)[None, :] <= 0.2), PIT[0][2], 0.0)
    assert np.array_equal(z, expected)
    assert soil.mass_budget() == {"particles": 0.0, "out_of_domain": 0.0}


def test_second_construction_loads_the_settled_bed_from_the_cache(tmp_path, monkeypatch):
    """The run that settles a bed and every later run from its cache give the same numbers, bit for bit.

    This pit pours 800 grains and keeps 444: a bed that went on with the poured arrays (its neighbour hash table
    sized for 800) summed the forces in another order than one loaded from the cache, and the two drifted apart
    (2% in the passive wall's peak thrust)."""
    monkeypatch.setenv("OPERA_TAICHI_CACHE", str(tmp_path))
    pit = ((-0.24, -0.24, -0.16), (0.24, 0.24, 0.0))
    first = make_bed(pit, settle_time=0.3)
    files = list((tmp_path / "dem_beds").glob("*.npz"))
    assert len(files) == 1
    second = make_bed(pit, settle_time=0.3)
    a, b = first.particles(), second.particles()
    for key in a:
        assert np.array_equal(a[key], b[key])
    assert first.bed_packing == second.bed_packing
    # the contact history came back too, and the neighbour lists are the same: both continue identically
    blade = trimesh.creation.box([0.04, 0.3, 0.3])
    for soil in (first, second):
        soil.set_tool_state(soil.add_tool("blade", blade), [-0.2, 0.0, 0.1], [0, 0, 0, 1], [1.0, 0, 0], [0, 0, 0])
        soil.advance(0.05)
    assert np.array_equal(first.particles()["positions"], second.particles()["positions"])
    other_seed = make_bed(settle_time=0.3, seed=8)
    assert len(list((tmp_path / "dem_beds").glob("*.npz"))) == 2
    assert not np.array_equal(other_seed.particles()["positions"][:10], a["positions"][:10])


def test_a_bed_settled_on_another_backend_is_settled_again(tmp_path, monkeypatch):
    """A settled bed's bits depend on the backend that settled it (the GPU's layout sums forces in another order):
    a CPU run does not start from a bed a GPU run cached, or two runs of one scene on one machine would differ by
    what ran before them."""
    import opera_taichi.dem_soil as dem_soil

    monkeypatch.setenv("OPERA_TAICHI_CACHE", str(tmp_path))
    pit = ((-0.24, -0.24, -0.16), (0.24, 0.24, 0.0))
    real = dem_soil.compiled_for
    monkeypatch.setattr(dem_soil, "compiled_for", lambda: {**real(), "arch": "cuda"})
    make_bed(pit, settle_time=0.3)
    monkeypatch.setattr(dem_soil, "compiled_for", lambda: {**real(), "fast_math": True})
    make_bed(pit, settle_time=0.3)
    monkeypatch.setattr(dem_soil, "compiled_for", real)
    make_bed(pit, settle_time=0.3)
    assert len(list((tmp_path / "dem_beds").glob("*.npz"))) == 3
    make_bed(pit, settle_time=0.3)  # this backend's bed is found again
    assert len(list((tmp_path / "dem_beds").glob("*.npz"))) == 3


def test_contact_springs_survive_neighbour_rebuilds():
    """A neighbour-list rebuild at every substep (a skin of ~0) must carry every spring over exactly: the
    loaded bed then evolves as with the usual skin (a lost tangential spring would let it creep)."""
    usual = make_bed()
    every_step = make_bed(skin=1e-9)
    usual.advance(0.2)
    every_step.advance(0.2)
    assert every_step.rebuilds > 0.9 * 0.2 / every_step.dt
    a, b = usual.particles()["positions"], every_step.particles()["positions"]
    order_a, order_b = np.lexsort(a.T), np.lexsort(b.T)  # particle order follows the cell order
    assert np.abs(a[order_a] - b[order_b]).max() < 1e-7


def test_bed_lighter_than_the_time_step_assumed_is_a_time_step_error(tmp_path, monkeypatch):
    # The masses of a settled bed are scaled to its bulk density. A bed packed denser than the mapping's solid
    # fraction gets lighter grains than dt_limit was computed for; here the bulk density is cut to a third after the
    # mapping, which scales the grains the same way, and a run at the mapping's limit must stop with exit 2.
    import dataclasses

    from opera_taichi.dem_soil import DemSoil
    from opera_taichi.errors import UserError

    monkeypatch.setenv("OPERA_TAICHI_CACHE", str(tmp_path))
    micro = bulk_to_micro(resolve_soil("sand", {"radius": 0.025, "youngs_modulus": 2e6}), bed_depth=0.15)
    light = dataclasses.replace(micro, bulk_density=micro.bulk_density / 3.0)
    with pytest.raises(UserError, match=r"sim\.soil_dt: .* lighter"):
        DemSoil(light, domain_min=DOMAIN[0], domain_max=DOMAIN[1], beds=[((-0.12, -0.12, -0.15), (0.12, 0.12, 0.0))],
                settle_time=0.3)


def test_a_bed_that_did_not_come_to_rest_says_so(tmp_path, monkeypatch):
    """Settling stops at soil.settle_time: a bed still moving then gets a warning naming the key (also when it comes
    from the cache), and one given the time to come to rest gets none."""
    monkeypatch.setenv("OPERA_TAICHI_CACHE", str(tmp_path))
    short = make_bed(settle_time=0.2)
    assert short.settle_speed > 0.0
    assert len(short.warnings) == 1 and "soil.settle_time = 0.2 s" in short.warnings[0]
    assert make_bed(settle_time=0.2).warnings == short.warnings
    rested = make_bed(settle_time=2.0)
    assert rested.settle_speed == 0.0 and rested.warnings == []


def test_stacked_fraction_tells_a_cubic_stack_from_a_nested_or_random_packing():
    from opera_taichi.dem_soil import stacked_fraction

    r = 0.01
    cubic = np.stack(np.meshgrid(*(2 * r * np.arange(6),) * 2, r + 2 * r * np.arange(5), indexing="ij"),
                     -1).reshape(-1, 3)
    floors = np.zeros(len(cubic))
    assert stacked_fraction(cubic, np.full(len(cubic), r), floors) == 1.0
    # every other layer shifted by half a spacing sits in the hollows of the one beneath: nothing straight on a grain
    nested = np.concatenate([np.stack(np.meshgrid(*(2 * r * np.arange(6) + (k % 2) * r,) * 2, [r + k * r * 2 ** 0.5],
                                                  indexing="ij"), -1).reshape(-1, 3) for k in range(5)])
    assert stacked_fraction(nested, np.full(len(nested), r), floors) == 0.0
    # the third of five layers moved sideways by 0.4 diameters: of the four above the floor's, the second stands
    # beside the grains beneath it, the third beside those of the moved layer, the first and the fourth on them
    moved = cubic.copy()
    moved[np.isclose(moved[:, 2], 5 * r), 0] += 0.8 * r
    assert stacked_fraction(moved, np.full(len(moved), r), floors) == pytest.approx(0.5, abs=0.05)
    bottom = cubic[:, 2] < 2 * r
    assert stacked_fraction(cubic[bottom], np.full(36, r), floors[bottom]) is None  # one layer: nothing above it


def test_a_bed_poured_grain_on_grain_says_so(bed, tmp_path, monkeypatch):
    """A pit 8 grains across and 4 deep keeps the pour's cubic lattice, each grain settled on the one beneath
    (docs/validation.md, calibration note 1): the bed reports that share (the manifest's bed_stacked) and warns. The
    module's pit, 10 grains across and also 4 deep, settles into a random packing and does not."""
    monkeypatch.setenv("OPERA_TAICHI_CACHE", str(tmp_path))
    d = 0.04
    narrow = make_bed(pit=((0.0, 0.0, -4 * d), (8 * d, 8 * d, 0.0)), settle_time=2.0, seed=1)
    assert narrow.bed_stacked > 0.4 and narrow.describe()["bed_stacked"] == narrow.bed_stacked
    assert [w for w in narrow.warnings if "rest straight on the grain beneath" in w] == [
        f"soil: {narrow.bed_stacked:.0%} of the settled bed's grains rest straight on the grain beneath, as the pour's "
        "cubic lattice stacked them (beds a few grains deep or across keep it): such a stack stands steeper and "
        "spreads less than loose soil (docs/validation.md, calibration note 1); finer grains "
        "(soil.overrides.radius) settle into a random packing"]
    assert bed.bed_stacked < 0.15 and bed.warnings == []


def test_a_scattered_pour_breaks_the_stacks_of_a_narrow_pit(tmp_path, monkeypatch):
    """dem_soil.POUR_SCATTER, the calibration's knob (off): the same pit poured with a random sideways start settles
    into a random packing, cached under its own key."""
    from opera_taichi import dem_soil

    monkeypatch.setenv("OPERA_TAICHI_CACHE", str(tmp_path))
    d = 0.04
    pit = ((0.0, 0.0, -4 * d), (8 * d, 8 * d, 0.0))
    monkeypatch.setattr(dem_soil, "POUR_SCATTER", 1.5)
    scattered = make_bed(pit=pit, settle_time=2.0, seed=1)
    assert scattered.bed_stacked < 0.2 and scattered.warnings == []
    key = scattered._cache_key(2.0)
    monkeypatch.setattr(dem_soil, "POUR_SCATTER", 0.0)
    assert scattered._cache_key(2.0) != key


def test_a_shifted_bed_is_the_settled_bed_moved():
    # soil.bed_shift releases a settled block (vertical cut, column, heap): every grain keeps its mass, matched to the
    # bulk density, and its springs with the grains it touches; only the positions move
    from opera_taichi.dem_soil import DemSoil
    from opera_taichi.model import build_model
    from opera_taichi.scene import load_scene
    from opera_taichi.validation import cases

    sets, _ = cases.build_overrides("vertical_cut", cases.parse_params("vertical_cut", ["preset=dirt", "height=0.5"]),
                                    "coarse")
    built = {}
    for name, extra in (("shifted", []), ("in place", ["soil.bed_shift=[0, 0, 0]"])):
        model = build_model(load_scene(cases.scene_file("vertical_cut"), sets + extra))
        soil = DemSoil.from_model(model.soil)
        built[name] = soil, soil.particles(), soil._state_arrays()["nbr_h"], np.asarray(model.soil.bed_shift)
    (moved, a, springs_a, shift), (settled, b, springs_b, _) = built["shifted"], built["in place"]
    assert np.any(shift != 0)
    gap = np.linalg.norm(a["positions"][:, None] - (b["positions"][None] + shift), axis=2)
    same = gap.argmin(axis=1)
    assert sorted(same) == list(range(settled.n_particles))  # one-to-one
    assert gap.min(axis=1).max() < 1e-9
    assert np.array_equal(a["masses"], b["masses"][same])
    assert moved.mass_budget()["particles"] == pytest.approx(settled.micro.bulk_density * np.prod(
        np.subtract(*reversed(settled.beds[0]))), rel=1e-5)
    assert np.abs(springs_a).sum() > 0 and np.abs(springs_a).sum() == pytest.approx(np.abs(springs_b).sum(), rel=1e-6)
