"""Angle of repose of the `sand` preset: a lifted-cylinder heap stands at 28-38 degrees (soil.md: 30-35)."""
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

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


def lifted_cylinder_heap(preset="sand", radius=0.02, seed=0, overrides=None, lift=0.2):
    from opera_taichi.dem_soil import DemSoil

    over = {"radius": radius}
    over.update(overrides or {})
    micro = bulk_to_micro(resolve_soil(preset, over))
    soil = DemSoil(micro, domain_min=(-1.2, -1.2, -0.2), domain_max=(1.2, 1.2, 1.5), beds=[], seed=seed)
    r = micro.radius
    inner, height = 10 * 2 * r, 20 * 2 * r  # a column 20 diameters across and 20 high
    tube_height = height + 0.2  # taller than the poured column: nothing rests on its rim
    tube = trimesh.creation.annulus(r_min=inner, r_max=inner + 0.03, height=tube_height, sections=64)
    t = soil.add_tool("cylinder", tube)
    soil.set_tool_state(t, [0, 0, tube_height / 2 + 0.2 * r], [0, 0, 0, 1], [0, 0, 0], [0, 0, 0])
    rng = np.random.default_rng(seed)
    s = 2.3 * r
    axis = np.arange(-inner, inner, s)
    grid = np.stack(np.meshgrid(axis, axis, 1.2 * r + s * np.arange(int(height / s)), indexing="ij"),
                    -1).reshape(-1, 3)
    grid = grid[np.hypot(grid[:, 0], grid[:, 1]) < inner - 1.2 * r]
    grid[:, :2] += rng.uniform(-0.1, 0.1, (len(grid), 2)) * r
    soil.set_particles(grid, radii=r * (1 + micro.polydispersity * rng.uniform(-1, 1, len(grid))))
    soil.advance(0.6)  # the column settles inside the cylinder
    # lift (m/s) is slow against the collapse speed sqrt(g H) ~ 2.8 m/s
    position, rotation = soil.tool_pose(t)
    soil.set_tool_state(t, position, Rotation.from_matrix(rotation).as_quat(), [0, 0, lift], [0, 0, 0])
    peak = 0.0
    elapsed = 0.0
    while True:
        soil.advance(0.05)
        elapsed += 0.05
        ke = soil.kinetic_energy()
        peak = max(peak, ke)
        if elapsed > tube_height / lift and ke < 1e-4 * peak:
            break
        assert elapsed < 8.0
    p = soil.particles()
    return heap_angle_deg(p["positions"], p["radii"], r)


@pytest.mark.slow
@pytest.mark.xfail(reason="known gap (DEM issue): rolling resistance 0.3, chosen so beds are not too strong for "
                          "walls, blades and the excavation, heaps sand at ~26 deg; 0.35 reaches 28.8 deg but "
                          "makes poured beds too loose for the bucket to fill", strict=False)
def test_sand_heap_stands_at_its_angle_of_repose():
    angle, flanks = lifted_cylinder_heap("sand")
    assert 28.0 <= angle <= 38.0, flanks
