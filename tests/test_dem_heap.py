"""Angle of repose of the `sand` preset: a heap poured through a funnel stands at 28-38 degrees (soil.md: 30-35)."""
import numpy as np
import pytest

from opera_taichi.backend import current_arch, init_taichi
from opera_taichi.soil import bulk_to_micro, resolve_soil


@pytest.fixture(scope="module", autouse=True)
def taichi_cpu():
    if current_arch() is None:
        init_taichi("cpu")


def heap_angle_deg(positions, radii, r, sectors=8):
    """Lab-style measure: per azimuthal sector, the surface (highest particle top) in radial bins of one
    diameter; a line fitted between 15% and 85% of the heap half-width; mean over sectors."""
    xy = positions[:, :2] - np.median(positions[:, :2], axis=0)
    rho = np.hypot(xy[:, 0], xy[:, 1])
    phi = np.arctan2(xy[:, 1], xy[:, 0])
    top = positions[:, 2] + radii
    edges = np.arange(0, rho.max() + 2 * r, 2 * r)
    angles = []
    for s in range(sectors):
        sel = (phi >= -np.pi + 2 * np.pi * s / sectors) & (phi < -np.pi + 2 * np.pi * (s + 1) / sectors)
        idx = np.digitize(rho[sel], edges) - 1
        height = np.full(len(edges) - 1, np.nan)
        for b in np.unique(idx):
            height[b] = top[sel][idx == b].max()
        centres = 0.5 * (edges[1:] + edges[:-1])
        covered = np.where(height > 2.5 * r)[0]  # more than one layer of grains
        half_width = centres[covered.max()]
        fit = (centres >= 0.15 * half_width) & (centres <= 0.85 * half_width) & np.isfinite(height)
        slope = np.polyfit(centres[fit], height[fit], 1)[0]
        angles.append(np.degrees(np.arctan(-slope)))
    return float(np.mean(angles)), angles


def poured_heap(preset="sand", radius=0.02, seed=0, overrides=None, lift=0.05):
    """soil.md's lab measure: pour through a funnel. A hopper (outlet 10 diameters across, 3 radii above the ground)
    filled with a loose lattice is lifted slowly, so its outlet rides on the apex of the heap it feeds; once it is
    empty and the kinetic energy is below 1e-4 of its peak, the heap's flanks are measured."""
    from opera_taichi.dem_soil import DemSoil
    from opera_taichi.validation.cases import HOPPER_WALL, hopper_mesh

    over = {"radius": radius}
    over.update(overrides or {})
    micro = bulk_to_micro(resolve_soil(preset, over))
    soil = DemSoil(micro, domain_min=(-1.2, -1.2, -0.2), domain_max=(1.2, 1.2, 2.0), beds=[], seed=seed)
    r = micro.radius
    outlet, height, z0 = 10 * r, 0.7, 3 * r
    t = soil.add_tool("hopper", hopper_mesh(outlet, height, 0.03))
    soil.set_tool_state(t, [0, 0, z0], [0, 0, 0, 1], [0, 0, lift], [0, 0, 0])
    rng = np.random.default_rng(seed)
    s = 2.3 * r
    axis = np.arange(-(outlet + height), outlet + height, s)
    grid = np.stack(np.meshgrid(axis, axis, z0 + 1.5 * r + s * np.arange(int((height - 2 * r) / s)), indexing="ij"),
                    -1).reshape(-1, 3)
    inside = outlet + (grid[:, 2] - z0) / np.tan(HOPPER_WALL) - 1.3 * r / np.sin(HOPPER_WALL)
    grid = grid[np.hypot(grid[:, 0], grid[:, 1]) < inside]  # ~2,900 grains: a heap ~0.35 m high
    grid[:, :2] += rng.uniform(-0.1, 0.1, (len(grid), 2)) * r
    soil.set_particles(grid, radii=r * (1 + micro.polydispersity * rng.uniform(-1, 1, len(grid))))
    peak = 0.0
    elapsed = 0.0
    while True:
        soil.advance(0.05)
        elapsed += 0.05
        ke = soil.kinetic_energy()
        peak = max(peak, ke)
        if ke < 1e-4 * peak:
            outlet_z = soil.tool_pose(t)[0][2]
            if not np.any(soil.particles()["positions"][:, 2] > outlet_z):  # the hopper is empty
                break
        assert elapsed < 20.0
    p = soil.particles()
    return heap_angle_deg(p["positions"], p["radii"], r)


@pytest.mark.slow
def test_sand_heap_stands_at_its_angle_of_repose():
    angle, flanks = poured_heap("sand")
    assert 28.0 <= angle <= 38.0, flanks
