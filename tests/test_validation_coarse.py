"""Coarse runs of every validation case (CI): the physics with bands wider than the default-resolution gates.

Each band's reason is next to it. The gates themselves (docs/validation.md) are checked at the default resolution
by `opera-taichi validate-physics all`.
"""
import json
import math

import pytest

from opera_taichi.validation import cases, references as ref

# Known gap, tracked in the validation issue: the blade draft is still 2.5-3 x the FEE at coarse resolution (3 grains
# across the cut; 1.7 x at 6, 1.6 x at 8, 1.45 x at 10; the over-strength falls with resolution, as the passive
# wall's does: 1.15 / 1.09 / 1.02 x Rankine at 5 / 10 / 15 across H). It runs and prints XFAIL in CI, so progress is
# visible; not strict, because a coarse run near the band edge may flip.
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
    # 8 grains across H: the peak (thrust averaged over one grain diameter of travel, up to 0.2 H) reads 0.93-1.11 x
    # Rankine on seeds 0-3 (1.09 x at the default 10 grains, 1.02 x at 15; at 5 grains seeds 0-5 spread 0.92-1.38 x,
    # too wide for a band). 35% leaves room for that spread on another host's round-off and still fails a bed that
    # is half again too strong or never builds past the at-rest thrust (K0 = 1 - sin phi: 12% of Kp)
    assert abs(m["relative_error"]) <= 0.35


COARSE_BLADE = {"depth": "0.15", "width": "0.75", "speed": "0.3"}


@pytest.fixture(scope="module")
def coarse_blade(tmp_path_factory):
    return _run(tmp_path_factory.mktemp("blade"), "blade_cut", COARSE_BLADE)


@pytest.mark.slow
@CALIBRATION_PENDING
def test_blade_cut_draft_coarse(coarse_blade):
    m = coarse_blade
    # 3 diameters across the cut (soil.md: 8-10 for tens of percent) and 0.3 m/s (inertia rho v^2 d = 2% of the
    # force): +-50% of the FEE draft; the vertical force on a smooth vertical blade is small next to the draft
    assert abs(m["relative_error"]) <= 0.5
    assert abs(m["extra"]["vertical_force_per_width"]) < 0.5 * m["measured"]


@pytest.mark.slow
def test_blade_adhesion_adds_the_earthmoving_equations_adhesion_terms(coarse_blade, tmp_path):
    """Soil-tool adhesion c_a = 4 kPa on the smooth vertical blade: the FEE adds 856 N/m to the draft (c_a d N_ca,
    beta minimised again) and c_a d = 600 N/m of downward shear on the soil (V). Increments over the same cut without
    adhesion, on two settled beds: draft 0.55 and 0.81 x the FEE's, vertical 0.29 and 0.60 x (at 2 kPa: draft 0.35
    and 0.47 x, the vertical lost in the ~100 N/m the base cut's V varies by; at 5 grains across d: 0.94 and 0.62 x;
    at the default 6: 0.95 and 0.54 x).
    The face carries its shear through a few grains, and gains with resolution as the blade's draft does. Bands
    0.3-1.5 and 0.1-1.5 x the FEE's fail an adhesion that does not reach the blade or acts twice."""
    m = _run(tmp_path, "blade_cut", dict(COARSE_BLADE, adhesion="4000"))
    manifest = json.loads((tmp_path / "blade_cut" / "run" / "manifest.json").read_text())
    assert manifest["soil"]["bulk"]["adhesion"] == 4000.0 and manifest["soil"]["micro"]["adhesion_force"] > 0
    base = coarse_blade
    assert m["parameters"]["adhesion"] == 4000.0 and base["parameters"]["adhesion"] == 0.0
    d_draft = m["measured"] - base["measured"]
    d_draft_fee = m["reference"] - base["reference"]
    d_vertical = m["extra"]["vertical_force_per_width"] - base["extra"]["vertical_force_per_width"]
    d_vertical_fee = m["extra"]["vertical_reference"] - base["extra"]["vertical_reference"]
    assert d_vertical_fee == pytest.approx(-4000.0 * 0.15)  # alpha 90: V = -c_a d
    assert 0.3 * d_draft_fee <= d_draft <= 1.5 * d_draft_fee, (d_draft, d_draft_fee)
    assert 0.1 * d_vertical_fee >= d_vertical >= 1.5 * d_vertical_fee, (d_vertical, d_vertical_fee)


@pytest.mark.slow
def test_repose_angle_coarse(tmp_path):
    m = _run(tmp_path, "repose", {"preset": "sand"})
    # ~1,500 particles, 12 across the column: flank fits are noisier than at the default 16, so +-5 deg instead of
    # +-2 deg. This is also the DEM issue's check that a heap poured from the sand preset stands at 28-38 deg (seeds
    # 0-3 read 30.7 / 31.1 / 31.0 / 32.0 deg; 32.7 at the default resolution, docs/validation.md). At 8 across
    # (~430 particles) seeds 0-4 read 27.2-31.4 deg, too close to the band's edge for a check
    assert m["reference"] == pytest.approx(33.0)
    assert 28.0 <= m["measured"] <= 38.0
    spread = max(m["extra"]["flank_angles_deg"]) - min(m["extra"]["flank_angles_deg"])
    assert spread < 10.0  # four flanks of one heap agree (symmetry)


@pytest.mark.slow
@pytest.mark.parametrize("factor, stands", [(0.6, True), (2.0, False)])
def test_vertical_cut_coarse(tmp_path, factor, stands):
    hc = cases.culmann_height("dirt")
    m = _run(tmp_path, "vertical_cut", {"height": str(factor * hc)})
    # no band to widen: the factor 0.6 / 2 margin around the Culmann height is already the tolerance
    assert m["measured"] is stands, m["extra"]
