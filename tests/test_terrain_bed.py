"""soil.terrain: a bed filled to a scanned surface (an NPZ heightmap in its own frame, placed by the scene), poured,
settled and trimmed like a pit; its initial terrain follows the scan; a scan that misses part of a bed is one line,
exit 2, naming the uncovered area."""
from __future__ import annotations

import numpy as np
import pytest

from opera_taichi.cli import main

RADIUS = 0.04
SHIFT = np.array([10.0, -5.0, 2.0])  # the scan's frame = world + SHIFT


def surface(x, y):
    return -0.2 + 0.2 * x + 0.05 * np.sin(4.0 * y)   # an 11 degree slope with a ripple across it


def write_scan(path, x_max=1.4):
    x = np.arange(-0.3, x_max, 0.02) + 0.01
    y = np.arange(-0.6, 0.6, 0.02) + 0.01
    gx, gy = np.meshgrid(x, y, indexing="ij")
    np.savez(path, x=x + SHIFT[0], y=y + SHIFT[1], z=surface(gx, gy) + SHIFT[2])


def scene_text(scan):
    return f"""
name: terrain_bed
sim: {{duration: 0.02}}
soil:
  preset: sand
  overrides: {{radius: {RADIUS}}}
  bed: [{{min: [0.0, -0.4, -0.6], max: [1.0, 0.4, 0.0]}}]   # min z: replaced by the floor
  domain: {{min: [-0.3, -0.6, -0.9], max: [1.3, 0.6, 1.0]}}
  settle_time: 0.5
  heightmap_cell: 0.04
  terrain: {{file: {scan}, xyz: {(-SHIFT).tolist()}, depth: 0.3}}
output: {{plots: false}}
"""


def test_bed_follows_the_scanned_surface(tmp_path):
    write_scan(tmp_path / "scan.npz")
    (tmp_path / "scene.yaml").write_text(scene_text(tmp_path / "scan.npz"))
    assert main(["run", str(tmp_path / "scene.yaml"), "--out", str(tmp_path / "run"), "--quiet"]) == 0
    with np.load(tmp_path / "run" / "terrain_initial.npz") as f:
        x, y, z = f["x"], f["y"], f["z"]
    gx, gy = np.meshgrid(x, y, indexing="ij")
    inner = (gx > 0.15) & (gx < 0.85) & (np.abs(gy) < 0.25)  # away from the pit walls and the rim
    diff = z[inner] - surface(gx[inner], gy[inner])
    assert abs(np.mean(diff)) < RADIUS and np.sqrt(np.mean(diff ** 2)) < 0.75 * 2 * RADIUS
    slope = np.polyfit(gx[inner], z[inner], 1)[0]
    assert slope == pytest.approx(0.2, rel=0.25)  # the slope is the scan's, not level
    import json

    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    floor = -0.2 + 0.2 * 0.0 - 0.05 - 0.3   # the lowest scanned point of the footprint less the depth
    assert manifest["scene"]["soil"]["terrain"]["depth"] == 0.3
    lowest = float(np.min(z[(gx > 0) & (gx < 1.0) & (np.abs(gy) < 0.4)]))
    assert lowest > floor  # soil everywhere above the floor
    # whatever packing the spheres settled at, they weigh the bulk density times the volume between the scan and the
    # floor over the bed's 1 m x 0.8 m footprint: the scan's mean height there is -0.1 m and its lowest point -0.25 m
    # (the 4 cm cells of the heightmap it is gridded on put the floor within 0.1 mm of that); the footprint's edge
    # cuts the cells of the nodes on it in half (taken whole, the volume read 4% too big)
    volume = (-0.1 - (-0.25 - 0.3)) * 0.8
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["mass_balance"]["initial_kg"] == pytest.approx(summary["soil_bulk_density_kg_m3"] * volume,
                                                                  rel=1e-3)


def test_scan_that_misses_the_bed_is_one_line(tmp_path, capsys):
    write_scan(tmp_path / "short.npz", x_max=0.8)
    (tmp_path / "scene.yaml").write_text(scene_text(tmp_path / "short.npz"))
    assert main(["validate", str(tmp_path / "scene.yaml")]) == 2
    err = capsys.readouterr().err.strip()
    assert "short.npz does not cover soil.bed.0" in err and "x 0.82..1, y -0.4..0.4 m" in err and "\n" not in err


def test_a_scan_placed_above_the_beds_top_is_one_line(tmp_path, capsys):
    """The scan lifted so far that the bed's floor (depth below its lowest point) lies above the bed's top: one line
    naming soil.terrain and the bed (was pydantic's error about a Box, exit 1)."""
    write_scan(tmp_path / "scan.npz")
    lifted = (-SHIFT + [0.0, 0.0, 1.0]).tolist()
    (tmp_path / "scene.yaml").write_text(scene_text(tmp_path / "scan.npz").replace(str((-SHIFT).tolist()), str(lifted)))
    assert main(["validate", str(tmp_path / "scene.yaml")]) == 2
    err = capsys.readouterr().err.strip()
    assert "soil.terrain: soil.bed.0's floor" in err and "soil.bed.0.max z = 0" in err and "\n" not in err, err
