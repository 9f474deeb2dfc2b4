"""Coarse runs of every validation case (CI): the physics with bands wider than the default-resolution gates.

Each band's reason is next to it. The gates themselves (docs/validation.md) are checked at the default resolution
by `opera-taichi validate-physics all`.
"""
import json
import math

import pytest

from opera_taichi.validation import cases, references as ref

# Known gaps, tracked in the validation issue: with friction-poured beds and rolling resistance 0.3 the coarse
# column collapse (run-out 1.22 at a = 1), passive wall and vertical cuts pass and are asserted; the blade draft
# is still 2.5-3 x the FEE at coarse resolution (3 grains across the cut; 1.7 x at 6, 1.6 x at 8; the over-strength
# falls with resolution, as the passive wall's does: 1.15 / 1.09 / 1.02 x Rankine at 5 / 10 / 15 across H), and the
# coarse poured heap (~500 grains, an outlet 5 grains across) stands at ~25 deg where the default one stands at
# 32.6. Those two run and print XFAIL/XPASS in CI, so progress is visible; not strict, because coarse runs near a
# band edge may flip.
CALIBRATION_PENDING = pytest.mark.xfail(reason="DEM calibration pending (validation issue)", strict=False)


@pytest.fixture(scope="module", autouse=True)
def _taichi():
    from opera_taichi.backend import init_taichi

    init_taichi("cpu")


def _run(tmp_path, case, params):
    m = cases.run_case(case, params, "coarse", tmp_path / case, arch="cpu")
    on_disk = json.loads((tmp_path / case / "metrics.json").read_text())
    assert on_disk["case"] == case and on_disk["resolution"] == "coarse"
    assert (tmp_path / case / "run" / "manifest.json").is_file()
    return m


@pytest.mark.slow
def test_column_collapse_runout_coarse(tmp_path):
    m = _run(tmp_path, "column_collapse", {"aspect_ratio": "1"})
    lo, hi = ref.runout_band(1.0, widen=0.30)
    # coarse: 8 diameters across L0 (soil.md asks 15-20), so the band is widened 30% instead of 15%
    assert lo <= m["measured"] <= hi
    assert m["extra"]["final_height_m"] < 0.4  # the column did collapse (H0 = 0.4 m)


@pytest.mark.slow
def test_passive_wall_peak_coarse(tmp_path):
    m = _run(tmp_path, "passive_wall", {"height": "0.2"})
    # 5 grains across H: the peak (thrust averaged over one grain diameter of travel, up to 0.2 H) reads 1.09 x
    # Rankine here and 1.15 x at H = 0.3 m (1.09 x at the default 10 grains, 1.02 x at 15): 35% leaves room for the
    # round-off spread (~2%) and still fails a bed that is half again too strong or never builds past the at-rest
    # thrust (K0 = 1 - sin phi: 12% of Kp)
    assert abs(m["relative_error"]) <= 0.35


@pytest.mark.slow
@CALIBRATION_PENDING
def test_blade_cut_draft_coarse(tmp_path):
    m = _run(tmp_path, "blade_cut", {"depth": "0.15", "width": "0.75", "speed": "0.3"})
    # 3 diameters across the cut (soil.md: 8-10 for tens of percent) and 0.3 m/s (inertia rho v^2 d = 2% of the
    # force): +-50% of the FEE draft; the vertical force on a smooth vertical blade is small next to the draft
    assert abs(m["relative_error"]) <= 0.5
    assert abs(m["extra"]["vertical_force_per_width"]) < 0.5 * m["measured"]


@pytest.mark.slow
@CALIBRATION_PENDING
def test_repose_angle_coarse(tmp_path):
    m = _run(tmp_path, "repose", {"preset": "sand"})
    # ~600 particles, 8 across the column: flank fits are noisy, so +-5 deg instead of +-2 deg
    assert abs(m["measured"] - m["reference"]) <= 5.0
    spread = max(m["extra"]["flank_angles_deg"]) - min(m["extra"]["flank_angles_deg"])
    assert spread < 10.0  # four flanks of one heap agree (symmetry)


@pytest.mark.slow
@pytest.mark.parametrize("factor, stands", [(0.6, True), (2.0, False)])
def test_vertical_cut_coarse(tmp_path, factor, stands):
    hc = cases.culmann_height("dirt")
    m = _run(tmp_path, "vertical_cut", {"height": str(factor * hc)})
    # no band to widen: the factor 0.6 / 2 margin around the Culmann height is already the tolerance
    assert m["measured"] is stands, m["extra"]
