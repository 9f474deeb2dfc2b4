"""Soil presets, user overrides, the bulk -> micro mapping and input checks of the DEM soil."""
import math

import pytest

from opera_taichi.backend import current_arch, init_taichi
from opera_taichi.errors import UserError
from opera_taichi.soil import (GRAVITY, PRESETS, SOLID_FRACTION, STEP_FRACTION, bulk_to_micro, check_dt,
                               contact_duration, damping_factor, resolve_soil)


@pytest.fixture(scope="module")
def taichi_cpu():
    if current_arch() is None:
        init_taichi("cpu")


def test_presets_resolve_and_dirt_matches_agx_dirt_1():
    for name in PRESETS:
        bulk = resolve_soil(name, {})
        assert 0 < bulk.friction_angle < math.pi / 2 and bulk.radius > 0
    dirt = resolve_soil("dirt", None)
    assert (dirt.density, dirt.cohesion, dirt.friction_angle, dirt.youngs_modulus) == (1474.0, 2100.0, 0.6978, 6.5e6)


def test_overrides_apply_with_degrees_converted():
    bulk = resolve_soil("sand", {"friction_angle_deg": 30, "radius": 0.01, "cohesion": 500,
                                 "tool_friction_angle_deg": 10})
    assert bulk.friction_angle == pytest.approx(math.radians(30))
    assert bulk.tool_friction_angle == pytest.approx(math.radians(10))
    assert (bulk.radius, bulk.cohesion) == (0.01, 500.0)


@pytest.mark.parametrize("overrides, key", [
    ({"radius": -0.01}, "soil.overrides.radius"),
    ({"friction_angle_deg": 95}, "soil.overrides.friction_angle_deg"),
    ({"friction_angle_deg": 90}, "soil.overrides.friction_angle_deg"),
    ({"friction_angle": 1.6}, "soil.overrides.friction_angle"),
    ({"cohesion": -1.0}, "soil.overrides.cohesion"),
    ({"adhesion": -1.0}, "soil.overrides.adhesion"),
    ({"restitution": 0.0}, "soil.overrides.restitution"),
    ({"restitution": 1.5}, "soil.overrides.restitution"),
    ({"density": float("nan")}, "soil.overrides.density"),
    ({"youngs_modulus": float("inf")}, "soil.overrides.youngs_modulus"),
    ({"radius": "big"}, "soil.overrides.radius"),
    ({"colour": 3}, "soil.overrides.colour"),
    ({"friction_angle": 0.5, "friction_angle_deg": 30}, "soil.overrides.friction_angle_deg"),
])
def test_bad_overrides_are_one_line_user_errors_naming_the_key(overrides, key):
    with pytest.raises(UserError) as err:
        resolve_soil("sand", overrides)
    message = str(err.value)
    assert message.startswith(key + ":") and "\n" not in message


def test_friction_message_states_the_allowed_range():
    with pytest.raises(UserError, match=r"^soil.overrides.friction_angle_deg: expected 0 < angle < 90 degrees, got 95$"):
        resolve_soil("sand", {"friction_angle_deg": 95})


def test_unknown_preset():
    with pytest.raises(UserError, match=r"^soil.preset: expected one of .*sand.*got 'clay'$"):
        resolve_soil("clay", {})


def test_micro_mapping_follows_the_documented_rules():
    bulk = resolve_soil("dirt", {"radius": 0.02, "polydispersity": 0.0})
    micro = bulk_to_micro(bulk, bed_depth=1.0)
    d = 2 * bulk.radius
    assert micro.solid_density == pytest.approx(bulk.density / SOLID_FRACTION)
    assert micro.k_n == pytest.approx(max(bulk.youngs_modulus * d, 100 * bulk.density * GRAVITY * 1.0 * d))
    assert micro.k_t == pytest.approx(2.0 / 7.0 * micro.k_n)
    assert micro.mu == pytest.approx(math.tan(bulk.friction_angle))
    assert micro.mu_tool == pytest.approx(math.tan(2.0 / 3.0 * bulk.friction_angle))
    # Rumpf + Mohr-Coulomb inverted: c = sigma_t tan(phi), sigma_t = phi_s Z F / (pi d^2), with the calibration
    # COHESION_SCALE tan(phi)^COHESION_EXPONENT from the vertical cut's critical height
    from opera_taichi.soil import COHESION_EXPONENT, COHESION_SCALE

    sigma_t = SOLID_FRACTION * 6.0 * micro.cohesion_force / (math.pi * d ** 2)
    mu = math.tan(bulk.friction_angle)
    assert sigma_t * mu == pytest.approx(COHESION_SCALE * mu ** COHESION_EXPONENT * bulk.cohesion)
    assert 0 < micro.cohesion_range < bulk.radius
    # no adhesion unless given; c_a = F_a (1 + tan delta) / A_c with A_c = pi R^2 / 0.55 (a monolayer's contacts)
    assert micro.adhesion_force == 0.0 and micro.adhesion_range == 0.0
    sticky = bulk_to_micro(resolve_soil("dirt", {"radius": 0.02, "adhesion": 1000.0}), bed_depth=1.0)
    area = math.pi * bulk.radius ** 2 / 0.55
    assert sticky.adhesion_force * (1.0 + sticky.mu_tool) / area == pytest.approx(1000.0)
    assert sticky.adhesion_range == pytest.approx(micro.cohesion_range)
    # the stability limit is t_c / STEP_FRACTION of the lightest pair
    m_pair = 0.5 * micro.particle_mass
    assert micro.dt_limit == pytest.approx(contact_duration(micro.k_n, m_pair, micro.damping) / STEP_FRACTION)


def test_overlap_rule_stiffens_soft_soils_for_deep_beds():
    bulk = resolve_soil("sand", {"youngs_modulus": 1e4, "radius": 0.02})
    micro = bulk_to_micro(bulk, bed_depth=2.0)
    assert micro.k_n == pytest.approx(100 * bulk.density * GRAVITY * 2.0 * 0.04)


def test_damping_factor_gives_restitution_of_a_free_oscillator():
    # a linear spring-dashpot half period: the velocity ratio is exp(-zeta pi / sqrt(1 - zeta^2))
    for e in (0.1, 0.5, 0.9):
        zeta = damping_factor(e) / 2.0
        assert math.exp(-zeta * math.pi / math.sqrt(1 - zeta ** 2)) == pytest.approx(e)
    assert damping_factor(1.0) == 0.0


def test_dt_above_the_stability_limit_is_a_user_error():
    micro = bulk_to_micro(resolve_soil("sand", {"radius": 0.02}))
    check_dt(micro, micro.dt_limit)
    with pytest.raises(UserError, match=r"^sim.soil_dt: .* s is above the stability limit .* s of this soil"):
        check_dt(micro, 2 * micro.dt_limit)
    with pytest.raises(UserError, match=r"^sim.soil_dt:"):
        check_dt(micro, -1e-4)


def test_soil_rejects_bad_beds_domain_and_dt(taichi_cpu):
    from opera_taichi.dem_soil import DemSoil

    micro = bulk_to_micro(resolve_soil("sand", {"radius": 0.02}))
    domain = dict(domain_min=(-1, -1, -1), domain_max=(1, 1, 1))
    cases = [
        (dict(beds=[((-0.5, -0.5, -0.3), (1.5, 0.5, 0.0))], **domain), r"^soil.bed.0: .* not inside the domain"),
        (dict(beds=[((-0.5, -0.5, -0.3), (0.5, 0.5, 0.1))], **domain), r"^soil.bed.0.max: .*z <= 0"),
        (dict(beds=[((0, 0, -0.3), (0.5, 0.5, 0)), ((0.2, 0.2, -0.3), (0.7, 0.7, 0))], **domain),
         r"^soil.bed.1: overlaps soil.bed.0"),
        (dict(beds=[], domain_min=(0, 0, 0), domain_max=(1, -1, 1)), r"^soil.domain: expected min < max"),
        (dict(beds=[], dt=1.0, **domain), r"^sim.soil_dt: "),
        (dict(beds=[], max_speed=-1, **domain), r"^soil.max_speed: "),
    ]
    for kwargs, pattern in cases:
        with pytest.raises(UserError, match=pattern) as err:
            DemSoil(micro, **kwargs)
        assert "\n" not in str(err.value)
