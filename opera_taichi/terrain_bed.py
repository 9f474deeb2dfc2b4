"""Beds from real terrain (soil.terrain): a scan placed in the world, gridded on the terrain heightmap's nodes, gives
each bed its fill surface and its floor (depth below the lowest scanned point of its footprint). The DEM bed builder
pours and settles the bed as any pit and trims it to that surface instead of level with its top."""
from __future__ import annotations

import math

import numpy as np

from .errors import UserError


def terrain_beds(soil, grid) -> tuple[list, tuple]:
    """(beds with their floors set, (x, y, z[ix, iy]) fill surface) of a soil section with `terrain`. UserError
    (naming the key) for an unreadable scan or one that does not cover a bed."""
    from .scene import Box
    from .studies import scan as scans

    t = soil.terrain
    scan = scans.read_scan(t.file, "soil.terrain.file")
    x, y = np.asarray(grid.x, float), np.asarray(grid.y, float)
    cell = float(abs(x[1] - x[0])) if len(x) > 1 else float(soil.heightmap_cell)
    place = scans.Transform(*map(float, t.xyz), roll=float(t.roll), pitch=float(t.pitch), yaw=float(t.yaw))
    gridded = scans.grid_points(place.apply(scans.densify_raster(scan, cell)), x, y)
    z = gridded.z
    gx, gy = np.meshgrid(x, y, indexing="ij")
    beds = []
    for i, bed in enumerate(soil.bed):
        inside = (gx >= bed.min[0]) & (gx <= bed.max[0]) & (gy >= bed.min[1]) & (gy <= bed.max[1])
        if not inside.any():
            raise UserError(f"soil.bed.{i}: its footprint holds no heightmap node (soil.heightmap_cell {cell:g} m)")
        hole = inside & ~np.isfinite(z)
        if hole.any():
            lo = (max(gx[hole].min() - cell / 2, bed.min[0]), max(gy[hole].min() - cell / 2, bed.min[1]))
            hi = (min(gx[hole].max() + cell / 2, bed.max[0]), min(gy[hole].max() + cell / 2, bed.max[1]))
            raise UserError(f"soil.terrain.file: {t.file.name} does not cover soil.bed.{i}: no scan points in "
                            f"{int(hole.sum())} of its {int(inside.sum())} cells, within x {lo[0]:.3g}..{hi[0]:.3g}, "
                            f"y {lo[1]:.3g}..{hi[1]:.3g} m (world frame); check soil.terrain's placement or the bed, "
                            f"or, for a scan sparser than soil.heightmap_cell ({cell:g} m), a larger cell")
        floor = float(np.min(z[inside])) - float(t.depth)
        if floor < soil.domain.min[2]:
            raise UserError(f"soil.terrain.depth: soil.bed.{i}'s floor, {t.depth:g} m below its lowest scanned point, "
                            f"is at z = {floor:.3g} m, below soil.domain.min z = {soil.domain.min[2]:g}")
        if floor >= bed.max[2]:
            raise UserError(f"soil.terrain: soil.bed.{i}'s floor, soil.terrain.depth {t.depth:g} m below its lowest "
                            f"scanned point, is at z = {floor:.3g} m, not below the bed's top soil.bed.{i}.max z = "
                            f"{bed.max[2]:g}: lower the scan (soil.terrain.xyz) or raise soil.bed.{i}.max")
        top = float(np.max(z[inside]))
        if top > soil.domain.max[2] - 0.1:
            raise UserError(f"soil.terrain.file: the scanned surface over soil.bed.{i} reaches z = {top:.3g} m, at "
                            f"or above soil.domain.max z = {soil.domain.max[2]:g} (less 0.1 m)")
        beds.append(Box(min=(bed.min[0], bed.min[1], math.floor(floor * 1e6) / 1e6), max=tuple(bed.max)))
    return beds, (x, y, z)


def surface_at(surface, xy: np.ndarray) -> np.ndarray:
    """Fill height at points (N, 2): the nearest node's (NaN where the scan had none)."""
    x, y, z = surface
    dx = x[1] - x[0] if len(x) > 1 else 1.0
    dy = y[1] - y[0] if len(y) > 1 else 1.0
    ix = np.clip(np.round((xy[:, 0] - x[0]) / dx).astype(int), 0, len(x) - 1)
    iy = np.clip(np.round((xy[:, 1] - y[0]) / dy).astype(int), 0, len(y) - 1)
    return z[ix, iy]
