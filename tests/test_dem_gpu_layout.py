"""The GPU's layout (`--arch cuda`: one iteration per particle in the substep's step loop, its sums by atomics; the
rebuilds' sort and reverse lists from parallel loops) runs on the CPU too, so CI checks it without a GPU: the same
physics as the CPU's blocks of particles and serial scans, and the same bits from run to run."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
BLADE = str(ROOT / "scenes" / "blade_cut.yaml")
STEPS = 1200  # rigid steps of 1 ms: the blade enters the sleeping bed and cuts 0.36 m of it


def _blade_cut(monkeypatch, per_particle: bool):
    from opera_taichi import dem_soil
    from opera_taichi.simulation import Simulation

    monkeypatch.setattr(dem_soil, "PER_PARTICLE_ARCHS", ("cuda", "x64", "arm64") if per_particle else ())
    # the far soil frozen at this bed's size too, so the rebuilds of the live part (lo > 0) are compared
    monkeypatch.setattr(dem_soil, "FREEZE_MIN", 0)
    monkeypatch.setattr(dem_soil, "FREEZE_FEWEST", 0)
    sim = Simulation.from_scene(BLADE, ["soil.overrides.radius=0.04", "soil.sleep=true", "tools.0.start.2=0.16"])
    soil = sim.soil
    assert soil.per_particle is per_particle
    impulses, asleep, frozen = [], [], []
    for k in range(STEPS):
        sim.step()
        impulses.append(soil.last_tool_impulse)
        if k % 100 == 0:
            asleep.append(soil.n_sleeping)
            frozen.append(soil.n_frozen)
    soil.frozen_seen = max(frozen)
    return soil, np.array(impulses), asleep


def test_the_gpu_layout_moves_every_particle_as_the_cpu_layout(monkeypatch):
    """A kinematic blade cuts a sleeping bed: the tool's force is only read out, so the particles do not feel the
    order of its sums, and every particle, spring and list is the same, bit for bit, in both layouts (the blocks
    that sleep are skipped in both: each block's box, grown particle by particle by atomics on a GPU, is the same;
    the parallel sort and reverse lists put every particle and slot where the serial ones do). The blade's force
    is the same sum taken in another order, of terms rounded to WRENCH_QUANTUM: equal within half a quantum per
    particle and substep."""
    blocks, f_blocks, asleep = _blade_cut(monkeypatch, False)
    particles, f_particles, _ = _blade_cut(monkeypatch, True)
    assert min(asleep) > 0.2 * blocks.n_particles  # a third of the bed slept throughout: blocks were skipped
    assert blocks.frozen_seen > 0 and blocks.rebuilds > 20  # the live part was rebuilt behind a frozen prefix
    assert particles.rebuilds == blocks.rebuilds
    a, b = blocks.get_state(), particles.get_state()
    for name in ("kin", "flags", "surf_id", "surf_h", "nbr_off", "nbr_j", "nbr_h", "rev_off", "rev_pos", "x_ref"):
        assert np.array_equal(a[name], b[name]), name
    scale = np.abs(f_blocks).max()
    assert scale > 0.0
    from kernels import dem

    rounding = 0.001 * blocks.n_particles * dem.WRENCH_QUANTUM / 2  # impulse over a 1 ms step: N s
    np.testing.assert_allclose(f_particles, f_blocks, rtol=0.0, atol=1e-12 * scale + rounding)

    stat_a, stat_b = a["stat"], b["stat"]
    for s in (dem.S_SPEED2, dem.S_LOST_COUNT, dem.S_NONFINITE):
        assert stat_a[s] == stat_b[s], s
    # the GPU layout books each lost grain's mass rounded to MASS_QUANTUM
    assert abs(stat_a[dem.S_LOST_MASS] - stat_b[dem.S_LOST_MASS]) <= stat_a[dem.S_LOST_COUNT] * dem.MASS_QUANTUM / 2


_IMPULSES_HASH = """
import hashlib, sys
import numpy as np
import pytest
from opera_taichi import dem_soil
from opera_taichi.simulation import Simulation
dem_soil.PER_PARTICLE_ARCHS = ("cuda", "x64", "arm64")
sim = Simulation.from_scene(sys.argv[1], ["soil.overrides.radius=0.04", "soil.sleep=true", "tools.0.start.2=0.16"])
impulses = []
for _ in range(800):
    sim.step()
    impulses.append(sim.soil.last_tool_impulse)
print(hashlib.sha256(np.array(impulses).tobytes()).hexdigest(), float(np.abs(impulses).max()))
"""


def test_the_gpu_layouts_atomic_sums_give_the_same_bits_on_one_thread_and_on_two():
    """The GPU layout sums the blade's force by atomics, in the order the threads arrive. One thread adds the
    particles' terms in index order, two interleave their tasks of 512: the impulses of 800 steps are the same bits
    (with the terms added as they are, two threads gave other bits from run to run)."""
    results = []
    for threads in (1, 2):
        env = dict(os.environ, TI_CPU_MAX_NUM_THREADS=str(threads))
        out = subprocess.run([sys.executable, "-c", _IMPULSES_HASH, BLADE], cwd=ROOT, env=env, capture_output=True,
                             text=True, timeout=600)
        assert out.returncode == 0, out.stderr[-2000:]
        digest, peak = out.stdout.split()[-2:]
        assert float(peak) > 1.0  # the blade was in the soil
        results.append(digest)
    assert results[0] == results[1]


def test_a_bed_settled_in_the_gpu_layout_is_the_cpu_layouts_bed(monkeypatch):
    """Pouring and settling a bed (no cache) trims the grains above the pit (they become inactive but stay in the
    arrays, sorted to the end at every rebuild) and rebuilds its lists many times with every grain awake: the GPU
    layout's parallel sort puts the inactive grains in the serial order too, and the settled bed is the same, bit
    for bit."""
    from opera_taichi import dem_soil
    from opera_taichi.backend import init_taichi
    from opera_taichi.soil import bulk_to_micro, resolve_soil

    init_taichi("cpu")
    micro = bulk_to_micro(resolve_soil("sand", {"radius": 0.02, "youngs_modulus": 2e6}), bed_depth=0.1)
    trim, trimmed = dem_soil.DemSoil._trim_to_beds, []

    def counting_trim(soil):
        before = soil.n_act
        trim(soil)
        trimmed.append(before - soil.n_act)

    monkeypatch.setattr(dem_soil.DemSoil, "_trim_to_beds", counting_trim)
    beds = []
    for per_particle in (False, True):
        monkeypatch.setattr(dem_soil, "PER_PARTICLE_ARCHS", ("cuda", "x64", "arm64") if per_particle else ())
        soil = dem_soil.DemSoil(micro, domain_min=(-0.25, -0.25, -0.2), domain_max=(0.25, 0.25, 0.4),
                                beds=[((-0.12, -0.12, -0.1), (0.12, 0.12, 0.0))], seed=5, use_cache=False)
        assert soil.per_particle is per_particle
        beds.append(soil)
    a, b = (soil.get_state() for soil in beds)
    assert trimmed[0] == trimmed[1] > 20  # grains were trimmed, then carried inactive through the rebuilds ...
    assert beds[0].rebuilds == beds[1].rebuilds > 10  # ... of the settling
    for name in ("kin", "flags", "prop", "surf_id", "surf_h", "nbr_off", "nbr_j", "nbr_h", "rev_off", "rev_pos"):
        assert np.array_equal(a[name], b[name]), name


def test_the_parallel_sort_and_reverse_lists_give_the_serial_loops_arrays():
    """The rebuild's counting sort and reverse lists from parallel loops against the serial ones, on random cell
    buckets (inactive grains among them, a live part behind a frozen prefix, chunk edges of the scans) and random
    neighbour lists: the same starts, order, cursors, offsets and slots, entry for entry."""
    import taichi as ti

    from kernels import dem
    from opera_taichi.backend import init_taichi

    init_taichi("cpu")
    rng = np.random.default_rng(0)

    def nd(values):
        out = ti.ndarray(ti.i32, max(len(values), 1))
        out.from_numpy(np.resize(np.asarray(values, np.int32), max(len(values), 1)))
        return out

    for lo, n, half, live, gone_share in ((0, 5000, 1024, 511, 0.1), (700, 9000, 2048, 1023, 0.3),
                                          (0, 3, 16, 7, 0.0), (40, 40, 8, 7, 0.0), (0, 600, 64, 63, 1.0),
                                          (0, dem.SCAN_CHUNK + 1, 32, 31, 0.5)):
        end = half + live + 2
        bucket = rng.integers(half if lo > 0 else 0, end - 1, n).astype(np.int32)
        bucket[rng.random(n) < gone_share] = end - 1  # the inactive grains' bucket
        counts = np.zeros(end + 1, np.int32)
        np.add.at(counts, bucket[lo:], 1)
        runs = []
        for kernel in (dem.sort_by_bucket, dem.sort_by_bucket_parallel):
            arrays = [nd(bucket), nd(counts), nd(np.full(end + 2, -7)), nd(np.full(n, -1)), nd([0, 0])]
            kernel(lo, n, arrays[0], arrays[1], arrays[2], arrays[3], half - 1, live, arrays[4])
            runs.append([a.to_numpy() for a in arrays[1:]])
        for name, serial, parallel in zip(("counts", "starts", "order", "sizes"), *runs):
            assert np.array_equal(serial, parallel), (lo, n, name)

    for lo, n_act in ((0, 3000), (400, 3000), (0, 1), (0, 0), (5, 5)):
        degree = rng.integers(0, 9, n_act)
        offsets = np.zeros(n_act + 1, np.int32)
        offsets[1:] = np.cumsum(degree)
        entries = int(offsets[-1])
        partners = rng.integers(0, max(n_act, 1), entries).astype(np.int32)
        runs = []
        for kernel in (dem.build_reverse, dem.build_reverse_parallel):
            rev_off = np.full(n_act + 2, 5, np.int32)
            rev_off[:lo + 1] = 37  # the frozen prefix's segments end at 37
            arrays = [nd(offsets), nd(partners), nd(rev_off), nd(np.full(entries, -3)), nd(np.zeros(entries + 1))]
            kernel(lo, lo, n_act, arrays[0], arrays[1], arrays[2], arrays[3], entries, arrays[4])
            runs.append((arrays[2].to_numpy()[:n_act + 1], arrays[3].to_numpy()[:entries]))
        for name, serial, parallel in zip(("rev_off", "rev_pos"), *runs):
            assert np.array_equal(serial, parallel), (lo, n_act, name)



_WEDGED_DIG_HASH = """
import hashlib, sys, tempfile
from pathlib import Path
import numpy as np
import pytest
from opera_taichi import dem_soil, runner
from opera_taichi.recorders import read_csv_columns
from opera_taichi.scene import load_scene
dem_soil.PER_PARTICLE_ARCHS = ("cuda", "x64", "arm64")
scene = load_scene(sys.argv[1], ["machine.soil_wedge=true", "sim.duration=8", "output.plots=false"])
with tempfile.TemporaryDirectory() as tmp:
    runner.run_scene(scene, out_dir=Path(tmp) / "run", quiet=True)
    wrench = Path(tmp) / "run" / "tool_wrench.csv"
    w = read_csv_columns(wrench)
    print(hashlib.sha256(wrench.read_bytes()).hexdigest(), float(np.abs(w["fx"]).max()))
"""


@pytest.mark.slow
def test_the_gpu_layouts_wedged_dig_gives_the_same_bits_on_one_thread_and_on_eight():
    """The main job with the bucket's soil wedge, in the GPU's layout: the bucket's force is the grains' terms, added
    by atomics in the threads' order, and the wedge's push from its equilibrium once a substep, which goes back into
    the machine. Kept on the grains' grid, the push leaves the sum exact in any order, and 8 s of the dig (the wedge
    cuts from about 6.5 s) write the same wrench bits on one thread and on eight (with the push added off the grid
    they differed from 7 s on, as two CUDA runs did on an H200)."""
    results = []
    for threads in (1, 8):
        env = dict(os.environ, TI_CPU_MAX_NUM_THREADS=str(threads))
        out = subprocess.run([sys.executable, "-c", _WEDGED_DIG_HASH, str(ROOT / "scenes" / "zx120_excavation.yaml")],
                             cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
        assert out.returncode == 0, out.stderr[-2000:]
        digest, peak = out.stdout.split()[-2:]
        assert float(peak) > 5000.0  # the bucket was cutting
        results.append(digest)
    assert results[0] == results[1]
