"""Soil parameters: presets, user overrides, and the bulk -> DEM micro-parameter mapping.

Users give bulk properties (what a soil report lists); the DEM kernels need contact parameters. The mapping is
in `bulk_to_micro` and is deliberately simple and documented so the validation studies can calibrate it.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from .errors import UserError, did_you_mean

GRAVITY = 9.81
SOLID_FRACTION = 0.6      # packing fraction of a settled bed; solid density = bulk density / 0.6
COORDINATION = 6.0        # mean contacts per particle in Rumpf's strength formula
STIFFNESS_SCALE = 1.0     # k_n = STIFFNESS_SCALE * E * 2R (a regular packing's modulus is ~ k_n / 2R)
OVERLAP_RULE = 100.0      # k_n >= 100 rho g H d keeps the mean overlap under the bed's weight below ~1% of R
COHESION_RANGE = 0.1      # cohesive band D = 0.1 R beyond contact (also the soil-tool adhesion band)
# The bond force from Rumpf's formula with c = sigma_t tan(phi), times COHESION_SCALE tan(phi)^COHESION_EXPONENT,
# fitted on the critical height of a vertical cut (`validate-physics critical_height`, bisected between a face that
# stands 5 s and one that falls) at the coarse and default resolutions: with 1.716 tan(phi)^0.65 it read 0.72 / 0.78 x
# Culmann's for dirt (phi 40 deg, c 2.1 kPa) and 0.91 / 0.97 x for kanto_loam (phi 20 deg, c 10 kPa). The factor that
# puts both soils at Culmann's on the geometric mean of the two resolutions (assuming the height goes as the bond
# force) is 2.40 tan(phi)^0.92; with it dirt read 1.09 / 0.97 x, kanto_loam 0.91 / 0.97 x, and 0.97 / 1.03 x since
# kanto_loam's rolling resistance rose with ROLLING_EXPONENT 1.6 (docs/validation.md, at operating resolution).
COHESION_SCALE = 2.40
COHESION_EXPONENT = 0.92
# Tool area per soil-tool contact, in R^2: the grains touching a flat face cover about 55% of it in projection (a
# random monolayer), one contact per pi R^2 / 0.55. Converts the adhesion c_a (Pa) to a force per contact.
TOOL_CONTACT_AREA = math.pi / 0.55
STEP_FRACTION = 10.0      # dt_limit = t_c / 10
ROLLING_DAMPING = 0.3     # EPSD viscous rolling damping ratio while the rolling spring is elastic
TANGENTIAL_RATIO = 2.0 / 7.0
WALL_STIFFNESS_RATIO = 2.0   # ground, walls and tools: k = 2 k_n, the same surface compliance as a sphere

# Rolling resistance (EPSD) for spheres with mu = tan(phi): mu_r = ROLLING_MAX min(1, tan(phi) / tan(33 deg))^1.6,
# 0.3 for sand at 33 deg and above. Calibrated on heaps poured through a hopper (`validate-physics repose`) at the
# default and the coarse validation resolution (16 and 12 diameters across the column): sand (33 deg) mu_r 0.3 ->
# 33.3 / 31.9 deg; glass beads (22 deg, target 22 +- 2) with the exponent 1.75 (mu_r 0.131) 20.7 / 19.5 deg, the
# coarse heap outside its band, with 1.6 (mu_r 0.140) 21.0 / 20.7 deg (21.8 / 21.8 with 0.1405 in a first probe: a
# heap reads about +-1 deg from run to run). (Earlier, from columns that soil.bed_shift
# rebuilt light: 0.187 -> 24.7 deg, 0.147 -> 24.2, 0.130 -> 21.5, 0.12 -> 20.6 at the default resolution.) The cap
# 0.3 comes from the coarse column collapse and passive wall runs (beds poured with friction, masses matched to the
# bulk density): above ~0.33 the friction pour gets very loose (solid fraction < 0.41) and weak (wall 0.92 x at 0.33,
# 0.61 x at 0.4; run-out at a = 1 1.07 at 0.35). With a dense, frictionless pour the same mu_r made beds 4-10 x too
# strong. See docs/validation.md.
ROLLING_MAX = 0.30
ROLLING_EXPONENT = 1.6
ROLLING_REFERENCE_ANGLE = math.radians(33.0)

PRESETS: dict[str, dict] = {
    # dry sand, soil.md: 1474-1700 kg/m3, 32-35 deg, repose 30-35 deg
    "sand": dict(density=1600.0, friction_angle=math.radians(33.0), cohesion=0.0, youngs_modulus=1.0e7,
                 restitution=0.5, radius=0.02),
    # AGX Terrain dirt_1 as used by OperaSim-AGX
    "dirt": dict(density=1474.0, friction_angle=0.6978, cohesion=2100.0, youngs_modulus=6.5e6,
                 restitution=0.5, radius=0.02),
    # AGX gravel reference friction; E as for sand
    "gravel": dict(density=1474.0, friction_angle=0.76, cohesion=0.0, youngs_modulus=1.0e7,
                   restitution=0.5, radius=0.02),
    # compacted Kanto loam fill (Japan Highway earthwork manual 1983); E is not tabulated, 5 MPa assumed
    "kanto_loam": dict(density=1400.0, friction_angle=math.radians(20.0), cohesion=10000.0,
                       youngs_modulus=5.0e6, restitution=0.3, radius=0.02),
    # Lajeunesse et al. 2004 ballotini: bulk 1500, solid 2450 (fraction 0.61), repose 22 deg
    "glass_beads": dict(density=1500.0, friction_angle=math.radians(22.0), cohesion=0.0, youngs_modulus=1.0e7,
                        restitution=0.9, radius=0.02),
}


@dataclass
class SoilBulk:
    """Bulk soil properties, as a user gives them (SI units, radians)."""

    density: float            # bulk density, kg/m3
    friction_angle: float     # internal friction angle, rad
    cohesion: float           # Pa
    youngs_modulus: float     # Pa
    restitution: float        # coefficient of restitution, 0 < e <= 1
    radius: float             # mean particle radius, m
    rolling_resistance: float | None = None   # None -> calibrated_rolling_resistance(friction_angle)
    tool_friction_angle: float | None = None  # soil-tool friction angle; None -> 2/3 of friction_angle
    adhesion: float = 0.0                     # soil-tool adhesion c_a, Pa (the earthmoving equation's c_a)
    polydispersity: float = 0.1               # radii uniform in R (1 +- polydispersity), against crystallisation


@dataclass(frozen=True)
class SoilMicro:
    """What the DEM kernels get. Stiffnesses N/m, forces N, lengths m, masses kg."""

    radius: float             # mean particle radius
    polydispersity: float
    solid_density: float      # kg/m3 of the spheres themselves
    particle_mass: float      # mass of a sphere of the mean radius
    k_n: float                # particle-particle normal stiffness
    k_t: float                # tangential stiffness (2/7 k_n)
    damping: float            # gamma_n = damping * sqrt(m_eff k): restitution `restitution` for any m_eff
    restitution: float
    mu: float                 # particle-particle friction coefficient
    mu_r: float               # rolling resistance coefficient (EPSD)
    rolling_damping: float    # EPSD rolling damping ratio
    cohesion_force: float     # F: attraction at contact
    cohesion_range: float     # D: attraction falls linearly to zero at this surface gap
    k_wall: float             # ground and pit walls
    mu_wall: float
    k_tool: float
    mu_tool: float
    adhesion_force: float     # soil-tool attraction at contact, and tangential capacity added to mu_tool F_n
    adhesion_range: float     # the attraction falls linearly to zero at this surface gap
    dt_limit: float           # stable substep
    youngs_modulus: float     # kept for messages
    bulk_density: float


_ALLOWED = ("density", "friction_angle", "friction_angle_deg", "cohesion", "youngs_modulus", "restitution",
            "radius", "rolling_resistance", "tool_friction_angle", "tool_friction_angle_deg", "polydispersity",
            "adhesion")


def _number(key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise UserError(f"soil.overrides.{key}: expected a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise UserError(f"soil.overrides.{key}: expected a finite number, got {value}")
    return value


def _check(key: str, ok: bool, allowed: str, value) -> None:
    if not ok:
        raise UserError(f"soil.overrides.{key}: expected {allowed}, got {value:g}")


def resolve_soil(preset: str, overrides: dict | None = None) -> SoilBulk:
    """Preset values with the user's overrides applied and checked (UserError naming the key)."""
    if preset not in PRESETS:
        raise UserError(f"soil.preset: expected one of {', '.join(sorted(PRESETS))}, got {preset!r}")
    if overrides is None:
        overrides = {}
    if not isinstance(overrides, dict):
        raise UserError(f"soil.overrides: expected a mapping of keys to numbers, got {type(overrides).__name__}")
    values = dict(PRESETS[preset])
    for key in overrides:
        if key not in _ALLOWED:
            raise UserError(f"soil.overrides.{key}: unknown key{did_you_mean(key, _ALLOWED)}; allowed: "
                            f"{', '.join(_ALLOWED)}")
    for base in ("friction_angle", "tool_friction_angle"):
        if base in overrides and base + "_deg" in overrides:
            raise UserError(f"soil.overrides.{base}_deg: give {base} (rad) or {base}_deg, not both")
    for key, raw in overrides.items():
        if key in ("rolling_resistance", "tool_friction_angle", "tool_friction_angle_deg") and raw is None:
            values[key.removesuffix("_deg")] = None
            continue
        v = _number(key, raw)
        if key == "density":
            _check(key, 0.0 < v <= 2.0e4, "0 < density <= 20000 kg/m3", v)
        elif key == "friction_angle":
            _check(key, 0.0 < v < math.pi / 2, "0 < angle < pi/2 rad", v)
        elif key == "friction_angle_deg":
            _check(key, 0.0 < v < 90.0, "0 < angle < 90 degrees", v)
            key, v = "friction_angle", math.radians(v)
        elif key == "cohesion":
            _check(key, v >= 0.0, "cohesion >= 0 Pa", v)
        elif key == "adhesion":
            _check(key, v >= 0.0, "adhesion >= 0 Pa", v)
        elif key == "youngs_modulus":
            _check(key, v > 0.0, "youngs_modulus > 0 Pa", v)
        elif key == "restitution":
            _check(key, 0.0 < v <= 1.0, "0 < restitution <= 1", v)
        elif key == "radius":
            _check(key, 0.0 < v <= 1.0, "0 < radius <= 1 m", v)
        elif key == "rolling_resistance":
            _check(key, 0.0 <= v <= 1.0, "0 <= rolling_resistance <= 1", v)
        elif key == "tool_friction_angle":
            _check(key, 0.0 <= v < math.pi / 2, "0 <= angle < pi/2 rad", v)
        elif key == "tool_friction_angle_deg":
            _check(key, 0.0 <= v < 90.0, "0 <= angle < 90 degrees", v)
            key, v = "tool_friction_angle", math.radians(v)
        elif key == "polydispersity":
            _check(key, 0.0 <= v <= 0.3, "0 <= polydispersity <= 0.3", v)
        values[key] = v
    return SoilBulk(**values)


def read_preset_file(path) -> tuple[str | None, dict]:
    """(base preset or None, bulk parameters) of a soil preset file: a YAML mapping of `soil.overrides` keys, an
    optional `preset` (the built-in preset it builds on) and an optional `calibration` block (provenance, not read).
    UserError names the file and the key."""
    from pathlib import Path

    from .scene import _parse_yaml, _read_scene_text

    label = str(path)
    data = _parse_yaml(_read_scene_text(Path(path), label), label)
    if not isinstance(data, dict):
        raise UserError(f"{label}: expected a mapping of soil parameters ({', '.join(_ALLOWED)})")
    base = data.get("preset")
    if base is not None and base not in PRESETS:
        raise UserError(f"{label}: preset: expected one of {', '.join(sorted(PRESETS))}, got {base!r}")
    values = {k: v for k, v in data.items() if k not in ("preset", "calibration")}
    try:
        resolve_soil(base or "sand", values)  # checks every key and value
    except UserError as exc:
        raise UserError(str(exc).replace("soil.overrides.", f"{label}: ", 1)) from None
    return base, values


def scene_soil_values(soil_cfg) -> tuple[str, dict]:
    """A scene's soil section as (the preset it builds on, the values given over it: the preset file's, then the
    overrides), keys and units as given; resolve_soil turns them into bulk parameters."""
    base, values = (None, {}) if getattr(soil_cfg, "preset_file", None) is None else \
        read_preset_file(soil_cfg.preset_file)
    overrides = dict(soil_cfg.overrides or {})
    for key in list(values):  # an override replaces the file's value, in whichever unit either gives it
        twin = key[:-4] if key.endswith("_deg") else key + "_deg"
        if key in overrides or twin in overrides:
            values.pop(key)
    return base or soil_cfg.preset, {**values, **overrides}


def resolve_scene_soil(soil_cfg) -> SoilBulk:
    """A scene's soil section as bulk parameters: the preset, the preset file's values, then the overrides."""
    return resolve_soil(*scene_soil_values(soil_cfg))


def calibrated_rolling_resistance(friction_angle: float) -> float:
    """Rolling resistance of the default mapping: ROLLING_MAX (tan(phi) / tan(33 deg))^ROLLING_EXPONENT, capped at
    ROLLING_MAX."""
    ratio = math.tan(friction_angle) / math.tan(ROLLING_REFERENCE_ANGLE)
    return ROLLING_MAX * min(1.0, ratio) ** ROLLING_EXPONENT


def damping_factor(restitution: float) -> float:
    """c in gamma_n = c sqrt(m_eff k): 2 (-ln e) / sqrt(pi^2 + ln^2 e) gives restitution e."""
    if restitution >= 1.0:
        return 0.0
    log_e = math.log(restitution)
    return 2.0 * -log_e / math.sqrt(math.pi ** 2 + log_e ** 2)


def _discrete_restitution(c: float, omega_dt: float, phases: int = 8) -> float:
    """Restitution of a linear spring-dashpot collision integrated as the kernels do (symplectic Euler, dashpot on
    the previous velocity), in units where omega0 = 1 and the impact speed is 1, averaged over impact phases."""
    total = 0.0
    for k in range(phases):
        u = -1.0
        overlap = omega_dt * (k + 0.5) / phases  # first step with overlap > 0
        for _ in range(int(100.0 / omega_dt) + 10):  # a collision lasts ~pi / omega0
            u += omega_dt * (overlap - c * u)
            overlap -= omega_dt * u
            if overlap <= 0.0:
                break
        total += u
    return total / phases


def damping_for_step(restitution: float, omega_dt: float) -> float:
    """Damping factor c (gamma = c sqrt(m_eff k)) whose collision, integrated with step dt (omega_dt =
    dt sqrt(k/m_eff)), rebounds with exactly `restitution`. The continuous formula (damping_factor) lags by
    half a step, which lowers e for strong damping (~0.28 instead of 0.3 on average at t_c / 15; a single
    collision still varies by ~10% (t_c / 15) to ~13% (t_c / 10) with the phase of impact at the step, less for
    larger e)."""
    if restitution >= 1.0:
        return 0.0
    lo, hi = 0.0, 2.0 * max(damping_factor(restitution), 0.05)
    while _discrete_restitution(hi, omega_dt) > restitution and hi < 50.0:
        hi *= 2.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if _discrete_restitution(mid, omega_dt) > restitution:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def contact_duration(k: float, m_eff: float, damping: float) -> float:
    """t_c = pi / sqrt(k/m_eff - (gamma/2 m_eff)^2) (soil.md), damping ratio capped at 0.8 so very low
    restitution (near-critical damping) cannot stretch it without bound."""
    zeta = min(damping / 2.0, 0.8)  # gamma / (2 sqrt(m k)) = damping / 2
    omega0 = math.sqrt(k / m_eff)
    return math.pi / (omega0 * math.sqrt(1.0 - zeta * zeta))


def tool_friction_angle(bulk: SoilBulk) -> float:
    """The soil-tool friction angle delta, rad: the given one, else 2/3 of the internal friction angle."""
    return 2.0 / 3.0 * bulk.friction_angle if bulk.tool_friction_angle is None else bulk.tool_friction_angle


def bulk_to_micro(bulk: SoilBulk, bed_depth: float = 1.0) -> SoilMicro:
    """Map bulk properties to DEM contact parameters.

    - Spheres of mean radius R, radii uniform in R (1 +- polydispersity). Solid density rho_s = rho / 0.6
      (SOLID_FRACTION: a settled bed of spheres packs at ~0.6), so a bed has the user's bulk density.
    - Normal stiffness k_n = E * 2R (STIFFNESS_SCALE = 1; a packing's modulus is ~ k_n / 2R), raised if needed
      to the overlap rule k_n >= 100 rho g H d (H = bed_depth, d = 2R) so overlaps under the bed's own weight
      stay below ~1% of R. Ground, walls and tools use 2 k_n (a wall has the surface compliance of one sphere).
    - Damping gamma_n = c sqrt(m_eff k), c = 2(-ln e)/sqrt(pi^2 + ln^2 e): restitution e for every pair
      (`damping`; DemSoil re-tunes c for its substep with damping_for_step, see there).
    - Tangential spring k_t = 2/7 k_n (same period as the normal one) with history, Coulomb cap mu F_n,
      mu = tan(phi). Rolling resistance (EPSD, type C): mu_r = 0.3 min(1, tan(phi) / tan(33 deg))^1.6
      (0.3 at 33 deg and above), calibrated on poured heaps, column collapse and passive-wall runs (see
      ROLLING_MAX).
    - Solid density rho / SOLID_FRACTION is a first guess: DemSoil scales the masses of a settled bed so that it
      has the bulk density rho at the packing it actually reached.
    - Cohesion: Rumpf sigma_t = phi_s Z F / (pi d^2) with phi_s = 0.6, Z = 6, and Mohr-Coulomb
      c = sigma_t tan(phi), so F = c pi d^2 / (phi_s Z tan(phi)), calibrated on the vertical cut's critical
      height by COHESION_SCALE tan(phi)^COHESION_EXPONENT; attraction F at contact, falling linearly to 0 at a
      gap D = 0.1 R.
    - Tool friction mu_tool = tan(delta), delta = 2/3 phi unless given; ground friction = mu (rough floor).
    - Adhesion c_a (soil-tool, Pa): each tool contact gets an attraction F_a (falling linearly to 0 at a gap of
      0.1 R, as cohesion) and F_a of tangential capacity on top of mu_tool times its normal force. The attraction
      raises the normal force by F_a, so the interface's shear strength is sigma tan(delta) + F_a (1 + tan(delta))
      / A_c (A_c = TOOL_CONTACT_AREA R^2 of tool per contact): F_a = c_a A_c / (1 + tan(delta)) gives
      tau = c_a + sigma tan(delta), the earthmoving equation's interface.
    - dt_limit = t_c / STEP_FRACTION (10) for the lightest pair (both spheres at the smallest radius), with
      t_c = pi / sqrt(k/m_eff - (gamma/2m_eff)^2).
    """
    radius = bulk.radius
    solid_density = bulk.density / SOLID_FRACTION
    diameter = 2.0 * radius
    k_n = max(STIFFNESS_SCALE * bulk.youngs_modulus * diameter,
              OVERLAP_RULE * bulk.density * GRAVITY * bed_depth * diameter)
    mu = math.tan(bulk.friction_angle)
    mu_r = bulk.rolling_resistance
    if mu_r is None:
        mu_r = calibrated_rolling_resistance(bulk.friction_angle)
    delta = tool_friction_angle(bulk)
    cohesion_force = 0.0
    cohesion_range = 0.0
    if bulk.cohesion > 0.0:
        cohesion_force = COHESION_SCALE * mu ** COHESION_EXPONENT * bulk.cohesion * math.pi * diameter ** 2 / \
            (SOLID_FRACTION * COORDINATION * mu)
        cohesion_range = COHESION_RANGE * radius
    mu_tool = math.tan(delta)
    adhesion_force = bulk.adhesion * TOOL_CONTACT_AREA * radius ** 2 / (1.0 + mu_tool)
    adhesion_range = COHESION_RANGE * radius if bulk.adhesion > 0.0 else 0.0
    damping = damping_factor(bulk.restitution)
    r_min = radius * (1.0 - bulk.polydispersity)
    m_min = solid_density * 4.0 / 3.0 * math.pi * r_min ** 3
    t_c = contact_duration(k_n, 0.5 * m_min, damping)
    return SoilMicro(
        radius=radius, polydispersity=bulk.polydispersity, solid_density=solid_density,
        particle_mass=solid_density * 4.0 / 3.0 * math.pi * radius ** 3,
        k_n=k_n, k_t=TANGENTIAL_RATIO * k_n, damping=damping, restitution=bulk.restitution,
        mu=mu, mu_r=mu_r, rolling_damping=ROLLING_DAMPING,
        cohesion_force=cohesion_force, cohesion_range=cohesion_range,
        k_wall=WALL_STIFFNESS_RATIO * k_n, mu_wall=mu,
        k_tool=WALL_STIFFNESS_RATIO * k_n, mu_tool=mu_tool, adhesion_force=adhesion_force,
        adhesion_range=adhesion_range,
        dt_limit=t_c / STEP_FRACTION, youngs_modulus=bulk.youngs_modulus, bulk_density=bulk.density)


def check_dt(micro: SoilMicro, dt: float) -> None:
    """UserError when a soil substep is not positive or above the stability limit of this soil."""
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0.0):
        raise UserError(f"sim.soil_dt: expected a positive number of seconds, got {dt!r}")
    if dt > micro.dt_limit * (1.0 + 1e-9):
        raise UserError(f"sim.soil_dt: {dt:.3g} s is above the stability limit {micro.dt_limit:.3g} s of this "
                        f"soil (radius {micro.radius:g} m, youngs_modulus {micro.youngs_modulus:.3g} Pa)")


def micro_summary(micro: SoilMicro) -> dict:
    """Plain dict of the micro-parameters (for manifests and cache keys)."""
    return asdict(micro)


__all__ = ["PRESETS", "SoilBulk", "SoilMicro", "resolve_soil", "bulk_to_micro", "check_dt",
           "calibrated_rolling_resistance", "damping_factor", "damping_for_step", "contact_duration", "micro_summary",
           "SOLID_FRACTION", "GRAVITY"]
