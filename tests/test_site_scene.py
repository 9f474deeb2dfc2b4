"""scenes/zx120_site.yaml at a coarse setting (12 cm grains, about 22,000 in its 20 m x 20 m x 1 m bed): the main job's
dig in a bed 22 x larger digs, loses no mass, and leaves the soil far from the bucket exactly as it lay (asleep and
frozen, out of the work of every step). (At 16 cm, two grains across the cut, what the bucket holds is chance: on the
bed settled at rest it held none.)"""
import json
from pathlib import Path

import numpy as np

from opera_taichi.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_the_site_digs_and_the_far_bed_is_untouched(tmp_path):
    out = tmp_path / "site"
    assert main(["run", str(ROOT / "scenes" / "zx120_site.yaml"), "--out", str(out), "--quiet",
                 "--set", "soil.overrides.radius=0.12", "--set", "output.plots=false"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert abs(summary["mass_balance"]["relative_drift"]) <= 1e-12   # (the sum's round-off as grains reorder)
    assert summary["tools"]["bucket_link"]["soil_held_kg"] > 50.0
    assert summary["terrain"]["dug_m3"] > 0.5 and 3.0 < summary["terrain"]["deepest_cut_xy_m"][0] < 8.0
    before, after = np.load(out / "terrain_initial.npz"), np.load(out / "terrain_final.npz")
    far = before["x"] > 10.0   # the bucket works at x < 7.5 m; the bed reaches x = 23 m
    assert far.sum() > 200 and np.array_equal(after["z"][far], before["z"][far])
    assert not np.array_equal(after["z"][~far], before["z"][~far])
