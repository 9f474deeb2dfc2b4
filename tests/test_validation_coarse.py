"""Coarse runs of every validation case (CI): the physics with bands wider than the default-resolution gates.

Each band's reason is next to it. The gates themselves (docs/validation.md) are checked at the default resolution
by `opera-taichi validate-physics all`.
"""
import json
import math

import pytest

from opera_taichi.validation import cases, references as ref


@pytest.fixture(scope="module", autouse=True)
def _taichi():
    from opera_taichi.backend import init_taichi

    init_taichi("cpu")


def _run(tmp_path, case, params):
    m = cases.run_case(case, params, "coarse", tmp_path / case, arch="cpu")
    on_disk = json.loads((tmp_path / case / "metrics.json").read_text())
    assert on_disk["case"] == case and on_disk["resolution"] == "coarse"
    manifest = json.loads((tmp_path / case / "run" / "manifest.json").read_text())
    assert on_disk["warnings"] == manifest.get("run_warnings", [])  # what the report lists beside the verdict
    return m


@pytest.mark.slow
def test_column_collapse_runout_coarse(tmp_path):
    m = _run(tmp_path, "column_collapse", {"aspect_ratio": "1"})
    lo, hi = ref.runout_band(1.0, widen=0.30)
    # coarse: 8 diameters across L0 (soil.md asks 15-20), so the band is widened 30% instead of 15%
    assert lo <= m["measured"] <= hi
    assert m["extra"]["final_height_m"] < 0.4  # the column did collapse (H0 = 0.4 m)


@pytest.mark.slow
def test_the_shortest_column_is_released_at_rest(tmp_path):
    # 4 grains tall: after the pit's landing time alone its grains still moved at 0.13-0.18 m/s (seeds 0-2), and a
    # column released moving collapses by that motion, not by its weight (cases.COLUMN_SETTLE)
    m = _run(tmp_path, "column_collapse", {"aspect_ratio": "0.5"})
    assert not [w for w in m["warnings"] if "did not come to rest" in w]


@pytest.mark.slow
def test_passive_wall_peak_coarse(tmp_path):
    m = _run(tmp_path, "passive_wall", {"height": "0.2"})
    # 8 grains across H: the peak (thrust averaged over one grain diameter of travel, up to 0.2 H) reads 0.93-1.11 x
    # Rankine on seeds 0-3 (1.09 x at the default 10 grains, 1.02 x at 15; at 5 grains seeds 0-5 spread 0.92-1.38 x,
    # too wide for a band). 35% leaves room for that spread on another host's round-off and still fails a bed that
    # is half again too strong or never builds past the at-rest thrust (K0 = 1 - sin phi: 12% of Kp)
    assert abs(m["relative_error"]) <= 0.35


COARSE_BLADE = {"depth": "0.15", "speed": "0.3"}  # plane strain (the default), 6 grains across d


@pytest.fixture(scope="module")
def coarse_blade(tmp_path_factory):
    return _run(tmp_path_factory.mktemp("blade"), "blade_cut", COARSE_BLADE)


@pytest.mark.slow
def test_blade_cut_draft_coarse(coarse_blade):
    m = coarse_blade
    # Plane strain at 6 grains across the cut and 0.3 m/s (inertia rho v^2 d = 2% of the force). The draft's excess
    # over the FEE goes as 1/n with the grains across d (n): at 6 it read 1.53 / 1.65 x on two seeds here and
    # 1.42-1.59 x at d 0.2 m, against 1.15 x at the default 16. Band 0.8-1.9 x: fails a bed twice as strong or
    # markedly weaker than the equation's sand; the vertical force on a smooth vertical blade is small next to it
    assert 0.8 <= m["measured"] / m["reference"] <= 1.9
    assert abs(m["extra"]["vertical_force_per_width"]) < 0.5 * m["measured"]


@pytest.mark.slow
def test_blade_adhesion_adds_the_earthmoving_equations_adhesion_terms(coarse_blade, tmp_path):
    """Soil-tool adhesion c_a = 4 kPa on the smooth vertical blade: the FEE adds 856 N/m to the draft (c_a d N_ca,
    beta minimised again) and c_a d = 600 N/m of downward shear on the soil (V). Increments over the same cut without
    adhesion (plane strain, 6 grains across d), seeds 0 and 1: draft 0.84 and 0.60 x the FEE's, vertical 0.82 and
    0.59 x (the 3-D blade at 3 grains across: draft 0.55 and 0.81 x, vertical 0.29 and 0.60 x).
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
    # 0-3 read 33.3 / 32.6 / 32.2 / 31.9 deg through the default's hopper; 33.6 at the default resolution,
    # docs/validation.md)
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
