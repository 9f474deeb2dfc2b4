"""Analytic references the soil is held against (SI units, radians). Pure Python/numpy.

Sources (see /work/shared/reference/soil.md): Reece 1964 / McKyes 1985 fundamental earthmoving equation,
Rankine earth pressure, Lube et al. 2005 and Lajeunesse et al. 2005 column-collapse run-out laws, Culmann's
critical height of an unsupported vertical cut.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

GRAVITY = 9.81


# ----------------------------------------------------------------------------- earthmoving (blade)
@dataclass(frozen=True)
class BladeForce:
    """Reece/McKyes result for a flat blade; forces in N for the given width."""

    beta: float        # failure-plane angle that minimises P, rad
    P: float           # resultant soil reaction on the blade face (along the face normal rotated by delta)
    draft: float       # horizontal force on the blade, N
    vertical: float    # vertical force the blade puts on the soil (V > 0 pushes the soil down), N
    N_gamma: float
    N_c: float
    N_ca: float
    N_q: float


def _fee_factors(beta, alpha, delta, phi):
    """N_gamma, N_c, N_ca, N_q at failure angle(s) beta; nan where the wedge is not admissible (D <= 0)."""
    beta = np.asarray(beta, dtype=float)
    cot_a = 1.0 / math.tan(alpha)
    cot_b = 1.0 / np.tan(beta)
    cot_bp = 1.0 / np.tan(beta + phi)
    D = math.cos(alpha + delta) + math.sin(alpha + delta) * cot_bp
    D = np.where(D > 0.0, D, np.nan)
    n_g = (cot_a + cot_b) / (2.0 * D)
    n_c = (1.0 + cot_b * cot_bp) / D
    n_ca = (1.0 - cot_a * cot_bp) / D
    n_q = (cot_a + cot_b) / D
    return n_g, n_c, n_ca, n_q


def earthmoving_force(depth: float, width: float, rake: float, phi: float, delta: float, density: float,
                      cohesion: float = 0.0, adhesion: float = 0.0, surcharge: float = 0.0,
                      g: float = GRAVITY) -> BladeForce:
    """Fundamental earthmoving equation (Reece 1964, McKyes 1985) with beta chosen to minimise P.

    depth d (m), width w (m), rake alpha from the horizontal (pi/2 = vertical blade), soil friction phi,
    soil-tool friction delta, bulk density (kg/m3), cohesion c and adhesion c_a (Pa), surcharge q (Pa).
    """
    if not (depth > 0 and width > 0 and 0 < rake < math.pi and 0 < phi < math.pi / 2 and 0 <= delta < math.pi / 2
            and density > 0):
        raise ValueError("earthmoving_force: need depth, width, density > 0, 0 < rake < pi, 0 < phi < pi/2, "
                         "0 <= delta < pi/2")
    gamma = density * g

    def force(beta):
        n_g, n_c, n_ca, n_q = _fee_factors(beta, rake, delta, phi)
        return (gamma * depth ** 2 * n_g + cohesion * depth * n_c + adhesion * depth * n_ca
                + surcharge * depth * n_q) * width

    # P(beta) is smooth and unimodal on the admissible range: a fine grid, then a golden-section polish
    grid = np.linspace(1e-3, math.pi / 2 - 1e-3, 4001)
    values = force(grid)
    if not np.any(np.isfinite(values)):
        raise ValueError("earthmoving_force: no admissible failure wedge for these angles")
    k = int(np.nanargmin(values))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    for _ in range(60):
        a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
        if force(a) < force(b):
            hi = b
        else:
            lo = a
    beta = float(0.5 * (lo + hi))
    P = float(force(beta))
    n_g, n_c, n_ca, n_q = (float(v) for v in _fee_factors(beta, rake, delta, phi))
    cot_a = 1.0 / math.tan(rake)
    draft = P * math.sin(rake + delta) + adhesion * depth * width * cot_a
    vertical = P * math.cos(rake + delta) - adhesion * depth * width
    return BladeForce(beta, P, draft, vertical, n_g, n_c, n_ca, n_q)


# ----------------------------------------------------------------------------- Rankine
def rankine_ka(phi: float) -> float:
    """Active earth-pressure coefficient tan^2(45 deg - phi/2)."""
    return math.tan(math.pi / 4 - phi / 2) ** 2


def rankine_kp(phi: float) -> float:
    """Passive earth-pressure coefficient tan^2(45 deg + phi/2)."""
    return math.tan(math.pi / 4 + phi / 2) ** 2


def rankine_passive_thrust(height: float, phi: float, density: float, cohesion: float = 0.0,
                           g: float = GRAVITY) -> float:
    """Passive thrust per metre of a smooth vertical wall, N/m: 0.5 Kp gamma g H^2 + 2 c H sqrt(Kp)."""
    kp = rankine_kp(phi)
    return 0.5 * kp * density * g * height ** 2 + 2.0 * cohesion * height * math.sqrt(kp)


def rankine_active_thrust(height: float, phi: float, density: float, cohesion: float = 0.0,
                          g: float = GRAVITY) -> float:
    """Active thrust per metre, N/m: 0.5 Ka gamma g H^2 - 2 c H sqrt(Ka), not below 0 (soil takes no tension
    against a wall: a tension crack opens instead)."""
    ka = rankine_ka(phi)
    return max(0.0, 0.5 * ka * density * g * height ** 2 - 2.0 * cohesion * height * math.sqrt(ka))


# ----------------------------------------------------------------------------- column collapse
LUBE_2005 = dict(small=1.2, large=1.9, switch=2.3)        # sand, rice, sugar; Phys. Rev. E 72:041301
LAJEUNESSE_2005 = dict(small=1.8, large=2.3, switch=3.0)  # glass beads; Phys. Fluids 17:103302


def _runout(a, law):
    a = np.asarray(a, dtype=float)
    return np.where(a < law["switch"], law["small"] * a, law["large"] * a ** (2.0 / 3.0))


def runout_lube(aspect_ratio):
    """Lube et al. 2005: (L_inf - L0)/L0 = 1.2 a for a < 2.3, 1.9 a^(2/3) above."""
    return _runout(aspect_ratio, LUBE_2005)


def runout_lajeunesse(aspect_ratio):
    """Lajeunesse et al. 2005: (L_inf - L0)/L0 = 1.8 a for a < 3, 2.3 a^(2/3) above."""
    return _runout(aspect_ratio, LAJEUNESSE_2005)


def runout_band(aspect_ratio: float, widen: float = 0.15) -> tuple[float, float]:
    """Band spanned by the two laws at aspect ratio a, widened by `widen` on each side (the gate)."""
    values = (float(runout_lube(aspect_ratio)), float(runout_lajeunesse(aspect_ratio)))
    return min(values) * (1.0 - widen), max(values) * (1.0 + widen)


def loglog_slope(x, y) -> float:
    """Least-squares slope of log y against log x."""
    x, y = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    return float(np.polyfit(x, y, 1)[0])


# ----------------------------------------------------------------------------- vertical cut
def culmann_critical_height(cohesion: float, phi: float, density: float, g: float = GRAVITY) -> float:
    """Critical height of an unsupported vertical cut (Culmann planar wedge): 4c/(gamma g) tan(45 + phi/2)."""
    return 4.0 * cohesion / (density * g) * math.tan(math.pi / 4 + phi / 2)
