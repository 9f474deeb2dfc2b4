"""The analytic references of the validation suite, against the oracles in reference/soil.md."""
import math

import numpy as np
import pytest

from opera_taichi.validation import references as ref

SAND = dict(phi=math.radians(35.0), density=1700.0)


def test_vertical_smooth_blade_matches_oracle_and_rankine():
    r = ref.earthmoving_force(0.3, 1.0, math.radians(90.0), delta=0.0, **SAND)
    assert r.P == pytest.approx(2769.3, abs=0.1)
    assert r.draft == pytest.approx(2769.3, abs=0.1)
    assert math.degrees(r.beta) == pytest.approx(27.5, abs=0.05)
    # a smooth vertical blade is Rankine's passive wall: beta* = 45 - phi/2, H = 0.5 Kp gamma g d^2
    assert math.degrees(r.beta) == pytest.approx(45.0 - 35.0 / 2, abs=1e-3)
    assert r.draft == pytest.approx(ref.rankine_passive_thrust(0.3, **SAND), rel=1e-6)
    assert r.vertical == pytest.approx(0.0, abs=1e-6)


def test_raked_rough_blade_matches_oracle():
    r = ref.earthmoving_force(0.3, 1.0, math.radians(60.0), delta=math.radians(20.0), **SAND)
    assert r.P == pytest.approx(2731.1, abs=0.1)
    assert r.draft == pytest.approx(2689.6, abs=0.1)
    assert math.degrees(r.beta) == pytest.approx(28.1, abs=0.05)
    assert r.vertical > 0  # a forward-raked rough blade pushes the soil down


def test_beta_is_the_minimum():
    alpha, delta = math.radians(60.0), math.radians(20.0)
    r = ref.earthmoving_force(0.3, 1.0, alpha, delta=delta, **SAND)
    for db in (-0.02, 0.02):
        n_g = ref._fee_factors(r.beta + db, alpha, delta, SAND["phi"])[0]
        assert 1700 * 9.81 * 0.09 * float(n_g) > r.P


def test_cohesionless_force_scales_with_depth_squared_and_width():
    base = ref.earthmoving_force(0.3, 1.0, math.radians(60.0), delta=math.radians(20.0), **SAND)
    deeper = ref.earthmoving_force(0.6, 1.0, math.radians(60.0), delta=math.radians(20.0), **SAND)
    wider = ref.earthmoving_force(0.3, 2.5, math.radians(60.0), delta=math.radians(20.0), **SAND)
    assert deeper.draft == pytest.approx(4.0 * base.draft, rel=1e-9)
    assert wider.draft == pytest.approx(2.5 * base.draft, rel=1e-9)
    assert deeper.beta == pytest.approx(base.beta, abs=1e-6)


def test_cohesion_and_adhesion_add_force():
    kw = dict(delta=math.radians(20.0), **SAND)
    dry = ref.earthmoving_force(0.3, 1.0, math.radians(60.0), **kw)
    wet = ref.earthmoving_force(0.3, 1.0, math.radians(60.0), cohesion=2000.0, adhesion=500.0, **kw)
    assert wet.draft > dry.draft + 2000.0 * 0.3  # at least c d w more: N_c > 1 for these angles


def test_bad_angles_are_refused():
    with pytest.raises(ValueError):
        ref.earthmoving_force(0.3, 1.0, 0.0, SAND["phi"], 0.0, 1700.0)
    with pytest.raises(ValueError):
        ref.earthmoving_force(-0.3, 1.0, 1.0, SAND["phi"], 0.0, 1700.0)


def test_rankine_coefficients():
    phi = math.radians(35.0)
    assert ref.rankine_ka(phi) == pytest.approx(0.2710, abs=1e-4)
    assert ref.rankine_kp(phi) == pytest.approx(3.6902, abs=1e-4)
    assert ref.rankine_ka(phi) * ref.rankine_kp(phi) == pytest.approx(1.0)
    h, rho, c = 2.0, 1500.0, 3000.0
    dry = ref.rankine_passive_thrust(h, phi, rho)
    assert ref.rankine_passive_thrust(h, phi, rho, c) - dry == pytest.approx(2 * c * h * math.sqrt(3.6902), rel=1e-4)
    assert ref.rankine_active_thrust(h, phi, rho) == pytest.approx(0.5 * 0.27099 * rho * 9.81 * h * h, rel=1e-4)
    assert ref.rankine_active_thrust(0.5, phi, rho, cohesion=1e5) == 0.0  # tension crack, no negative thrust


def test_runout_laws_match_the_table():
    # soil.md: a = 0.5 -> 0.60-0.90, a = 1 -> 1.20-1.80, a = 2 -> 2.40-3.60
    for a, lo, hi in ((0.5, 0.60, 0.90), (1.0, 1.20, 1.80), (2.0, 2.40, 3.60)):
        assert float(ref.runout_lube(a)) == pytest.approx(lo)
        assert float(ref.runout_lajeunesse(a)) == pytest.approx(hi)
        band = ref.runout_band(a)
        assert band == pytest.approx((0.85 * lo, 1.15 * hi))
    # large-a branches: 2/3 power
    assert float(ref.runout_lube(8.0)) == pytest.approx(1.9 * 4.0)
    assert float(ref.runout_lajeunesse(8.0)) == pytest.approx(2.3 * 4.0)
    a = np.array([0.25, 0.5, 1.0])
    assert ref.loglog_slope(a, ref.runout_lube(a)) == pytest.approx(1.0)
    big = np.array([4.0, 8.0, 16.0])
    assert ref.loglog_slope(big, ref.runout_lajeunesse(big)) == pytest.approx(2.0 / 3.0)


def test_culmann_height():
    # dirt: c = 2100 Pa, phi = 0.6978 rad, 1474 kg/m3 -> 4c/(gamma g) tan(45 + phi/2) = 1.245 m
    hc = ref.culmann_critical_height(2100.0, 0.6978, 1474.0)
    assert hc == pytest.approx(4 * 2100 / (1474 * 9.81) * math.tan(math.pi / 4 + 0.6978 / 2), rel=1e-12)
    assert hc == pytest.approx(1.245, abs=1e-3)
    assert ref.culmann_critical_height(4200.0, 0.6978, 1474.0) == pytest.approx(2 * hc)
