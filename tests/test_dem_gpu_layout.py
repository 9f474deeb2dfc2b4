"""The GPU's layout (`--arch cuda`: one iteration per particle in the substep's step loop, its sums by atomics; the
rebuilds' sort and reverse lists from parallel loops) runs on the CPU too, so CI checks it without a GPU: the same
physics as the CPU's blocks of particles and serial scans."""
from pathlib import Path

import numpy as np

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
    is the same sum taken in another order: equal to round-off."""
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
    np.testing.assert_allclose(f_particles, f_blocks, rtol=0.0, atol=1e-12 * scale)
    from kernels import dem

    stat_a, stat_b = a["stat"], b["stat"]
    for s in (dem.S_SPEED2, dem.S_LOST_MASS, dem.S_LOST_COUNT, dem.S_NONFINITE):
        assert stat_a[s] == stat_b[s], s
