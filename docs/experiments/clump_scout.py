"""Scouting run for docs/validation.md (not part of the package, not tested): do rigid clumps of spheres hold a
heap without rolling resistance, and does a 4-grain column of them spread, where spheres need rolling resistance
for the heap and it holds the column up? And does their blade at 4 grains across draw less than the spheres'?

A small stand-alone DEM of rigid clumps of equal spheres whose centres lie c sphere-radii from the clump's centre
(c = 0 is a single sphere): 4 at a regular tetrahedron's corners (`--shape=tetra`, the default), 2 on a line
(`dimer`, c + 1 times as long as wide) or 3 at an equilateral triangle's corners (`trimer`, touching at c 1.155).
They move as rigid bodies (principal moments of the union, angular momentum integrated in the world frame), with
the project's own contact law (kernels.dem.contact_law: linear spring-dashpot, tangential spring with history, EPSD
rolling resistance) and the sand preset's bulk-to-micro mapping (opera_taichi.soil.bulk_to_micro), so a single
sphere with the mapping's rolling resistance is the project's grain. Grain size: the clump's volume-equivalent
radius, 1 +- 0.1 uniform (polydispersity). Cell lists are rebuilt every step and atomics order them, so runs are
not bit-reproducible (a seed's grain count varies by a few).

    python docs/experiments/clump_scout.py heap|column|wall|blade C MU_R [SEED] [ACROSS] [--shape=tetra|dimer|trimer]
        [--aspect=A]

heap: a cylinder ACROSS volume-equivalent diameters across (default 12, the coarse repose case's; 0.4 m), filled
with 0.064 m3 of poured grains, is lifted at 0.05 m/s off a rough floor; the flank angle is read with the project's
heap_angles. column: a column ACROSS (default 8) diameters long and A times as tall (`--aspect=A`, default 0.5), in
a slice 8 diameters wide between smooth side walls, poured into its pit; the pit's front wall goes and the run-out
is read with the project's runout_length. wall: the passive wall case (H 0.3 m, ACROSS (default 4) diameters across
H, phi 35 deg, a smooth wall at 0.1 m/s for 0.2 H, the pit's front face holding the soil below its base), read with
the project's peak_of_travel_average over Rankine's thrust at the settled bed's density. blade: the plane-strain
blade a90 delta0 d 0.3 m (the gate's cut, ACROSS (default 4) diameters across d, phi 35 deg): the same smooth face,
its edge d deep over d of soil, 3 d of travel at 0.1 m/s through a bed 6.5 d long in a slab 8 diameters wide, spoil
whose centre rises R/2 above the ground taken out (`soil.clear_above`), the mean draft over d to 3 d of travel over
the earthmoving equation's (for this cut, Rankine's thrust). Every bed is poured as a jittered lattice of grains
turned at random. C: the clump's centre distance in sphere radii (0: spheres). MU_R: rolling resistance (the
mapping's 0.3 for sand). Prints one JSON line.

Results (2026-12-07, the 2-vCPU Intel Xeon, runs side by side): docs/validation.md, calibration note 1, "Clumps,
scouted outside the project" and "Fewer spheres a grain". A coarse heap takes 2-9 minutes, a column or a wall 15-40
s, a blade 1-3 minutes.
"""
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import taichi as ti

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
ti.init(arch=ti.cpu, default_fp=ti.f64, log_level="error")
from kernels import dem  # noqa: E402
from opera_taichi import soil as soil_model  # noqa: E402
from opera_taichi.validation import references  # noqa: E402
from opera_taichi.validation.cases import heap_angles, peak_of_travel_average, runout_length  # noqa: E402

SHAPES = ("tetra", "dimer", "trimer")
options = dict(shape="tetra", aspect="0.5")
for arg in [a for a in sys.argv[1:] if a.startswith(("--shape=", "--aspect="))]:
    key, value = arg[2:].split("=", 1)
    options[key] = value
    sys.argv.remove(arg)
try:
    shape = options["shape"]
    aspect = float(options["aspect"])
    if shape not in SHAPES or not 0.25 <= aspect <= 2.0:
        raise ValueError
    case = sys.argv[1]
    c_over_r = float(sys.argv[2])
    mu_r = float(sys.argv[3])
    seed = int(sys.argv[4]) if len(sys.argv) > 4 else 0
    across = int(sys.argv[5]) if len(sys.argv) > 5 else dict(heap=12, column=8, wall=4, blade=4).get(case, 0)
    if case not in ("heap", "column", "wall", "blade") or not (0.0 <= c_over_r <= 1.5 and 0.0 <= mu_r <= 1.0
                                                      and 4 <= across <= 24):
        raise ValueError
except (IndexError, ValueError):
    print("usage: clump_scout.py heap|column|wall|blade C (0-1.5) MU_R (0-1) [SEED] [ACROSS 4-24] "
          "[--shape=tetra|dimer|trimer] [--aspect=A (column, 0.25-2)]", file=sys.stderr)
    sys.exit(2)
rng = np.random.default_rng(seed)
FACE = case in ("wall", "blade")  # a smooth vertical face pushed into a pit of soil

# ---------------------------------------------------------------------------------------------- the grain
SHAPE_OFFSETS = dict(  # member directions from the clump's centre, in its principal frame
    tetra=np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) / math.sqrt(3.0),
    dimer=np.array([[1, 0, 0], [-1, 0, 0]], float),
    trimer=np.array([[1, 0, 0], [-0.5, math.sqrt(3.0) / 2, 0], [-0.5, -math.sqrt(3.0) / 2, 0]], float))
unit_offsets = np.zeros((1, 3)) if c_over_r == 0.0 else SHAPE_OFFSETS[shape]
MEMBERS = len(unit_offsets)
GRAIN = "sphere" if MEMBERS == 1 else shape


def clump_volume_and_gyration(c: float) -> tuple[float, np.ndarray]:
    """Volume of the union of unit spheres at c x unit_offsets, and the mean of x^2, y^2, z^2 over it in the
    clump's frame (Monte Carlo, 2e6 points)."""
    if MEMBERS == 1:
        return 4.0 / 3.0 * math.pi, np.full(3, 1.0 / 5.0)
    g = np.random.default_rng(12345)
    ext = c + 1.0
    pts = g.uniform(-ext, ext, size=(2_000_000, 3))
    inside = np.zeros(len(pts), bool)
    for o in unit_offsets:
        inside |= ((pts - c * o) ** 2).sum(1) <= 1.0
    vol = inside.mean() * (2 * ext) ** 3
    return float(vol), (pts[inside] ** 2).mean(0)


vol_unit, x2_unit = clump_volume_and_gyration(c_over_r)
r_eq_unit = (vol_unit * 3.0 / (4.0 * math.pi)) ** (1.0 / 3.0)  # volume-equivalent radius per sphere radius

bulk = soil_model.resolve_soil("sand")
if FACE:  # the passive wall's and the blade's soil: phi 35 deg, 1700 kg/m3, a smooth face
    bulk = soil_model.resolve_soil("sand", {"friction_angle_deg": 35.0, "density": 1700.0})
    H = 0.3
    R_eq = H / (2 * across)
elif case == "heap":
    D = 0.4
    R_eq = D / (2 * across)
else:
    L0 = 0.4
    R_eq = L0 / (2 * across)
r_s = R_eq / r_eq_unit  # member sphere radius
bulk.radius = r_s
micro = soil_model.bulk_to_micro(bulk, bed_depth=0.5)
k_n = micro.k_n
rho_s = micro.solid_density
mass_unit = rho_s * vol_unit * r_s ** 3
# principal moments, I_x = m <y^2 + z^2> and so on (the three equal for the sphere and the tetrahedron)
inertia_unit = mass_unit * (x2_unit.sum() - x2_unit) * r_s ** 2
m_min = mass_unit * 0.9 ** 3
t_c = soil_model.contact_duration(2.0 * k_n, m_min, micro.damping)
dt = t_c / 10.0
damping_c = soil_model.damping_for_step(micro.restitution, dt * math.sqrt(k_n / (0.5 * m_min)))
print(f"{case}: {GRAIN} C {c_over_r} ({MEMBERS} spheres), R_eq {R_eq:.4f} m, sphere r {r_s:.4f} m "
      f"(R_eq / r {r_eq_unit:.3f}), mu {micro.mu:.3f}, mu_r {mu_r}, k_n {k_n:.3g}, dt {dt:.3g} s", flush=True)

# ---------------------------------------------------------------------------------------------- geometry
if case == "heap":
    R_cyl = D / 2
    fill_volume = D ** 3
    dom_lo = np.array([-1.2, -1.2, -0.05])
    dom_hi = np.array([1.2, 1.2, 1.4])
elif FACE:
    LX, HALF_Y, DEPTH = (3.5 if case == "wall" else 6.5) * H, H, 2.0 * H
    dom_lo = np.array([-0.3, -HALF_Y - 0.01, -DEPTH - 0.05])
    dom_hi = np.array([LX + 0.05, HALF_Y + 0.01, 1.0])
else:
    W = 8 * 2 * R_eq  # the slice: 8 diameters wide at every resolution
    H0 = aspect * L0
    reach = L0 * (1.0 + 1.3 * max(references.runout_lube(aspect), references.runout_lajeunesse(aspect)))
    dom_lo = np.array([-0.05, -0.01, -0.05])
    dom_hi = np.array([L0 + reach + 0.1, W + 0.01, 4 * H0])
# planes: point, inward normal, friction (floor and back wall rough, slice sides smooth); the last is the pit's
# front wall (column) that goes at the release
planes = [((0, 0, 0), (0, 0, 1), micro.mu)]
if case == "column":
    planes += [((0, 0, 0), (1, 0, 0), micro.mu), ((0, 0, 0), (0, 1, 0), 0.0), ((0, W, 0), (0, -1, 0), 0.0),
               ((L0, 0, 0), (-1, 0, 0), micro.mu)]
if FACE:  # the pit (floor and back rough, sides smooth); its front below the face's base; the face
    planes = [((0, 0, -DEPTH), (0, 0, 1), micro.mu), ((LX, 0, 0), (-1, 0, 0), micro.mu),
              ((0, -HALF_Y, 0), (0, 1, 0), 0.0), ((0, HALF_Y, 0), (0, -1, 0), 0.0), ((0, 0, 0), (1, 0, 0), 0.0),
              ((0, 0, 0), (1, 0, 0), 0.0)]
NP = len(planes)
WALL_BASE = -0.3 - 0.5 * R_eq if FACE else 0.0  # (H - the wall's base, where its front face takes over)

# ---------------------------------------------------------------------------------------------- the pour
spacing = 2.0 * (c_over_r + 1.0) * r_s * 1.1 * 1.05


def pour() -> np.ndarray:
    """Lattice of clump centres over the container, jittered by 3% of the spacing, tall enough for the fill."""
    if case == "heap":
        n_side = int(2 * (R_cyl - 1.1 * (c_over_r + 1) * r_s) / spacing) + 1
        xs = (np.arange(n_side) - (n_side - 1) / 2) * spacing
        xx, yy = np.meshgrid(xs, xs, indexing="ij")
        keep = np.hypot(xx, yy) <= R_cyl - 1.1 * (c_over_r + 1) * r_s
        layer = np.stack([xx[keep], yy[keep]], 1)
        need = int(fill_volume * 0.55 / (vol_unit * r_s ** 3)) + 1
    elif FACE:
        margin = 1.1 * (c_over_r + 1) * r_s
        nx = int((LX - 2 * margin) / spacing) + 1
        ny = int((2 * HALF_Y - 2 * margin) / spacing) + 1
        xs = margin + np.arange(nx) * (LX - 2 * margin) / max(nx - 1, 1)
        ys = -HALF_Y + margin + np.arange(ny) * (2 * HALF_Y - 2 * margin) / max(ny - 1, 1)
        xx, yy = np.meshgrid(xs, ys, indexing="ij")
        layer = np.stack([xx.ravel(), yy.ravel()], 1)
        need = int(LX * 2 * HALF_Y * DEPTH * 0.65 / (vol_unit * r_s ** 3)) + 1
    else:
        margin = 1.1 * (c_over_r + 1) * r_s
        nx = int((L0 - 2 * margin) / spacing) + 1
        ny = int((W - 2 * margin) / spacing) + 1
        xs = margin + np.arange(nx) * (L0 - 2 * margin) / max(nx - 1, 1)
        ys = margin + np.arange(ny) * (W - 2 * margin) / max(ny - 1, 1)
        xx, yy = np.meshgrid(xs, ys, indexing="ij")
        layer = np.stack([xx.ravel(), yy.ravel()], 1)
        need = int(L0 * W * H0 * 0.65 / (vol_unit * r_s ** 3)) + 1
    layers = -(-need // len(layer))
    pts = []
    for k in range(layers):
        z = 1.2 * (c_over_r + 1) * r_s + k * spacing - (DEPTH if FACE else 0.0)
        pts.append(np.column_stack([layer, np.full(len(layer), z)]))
    pts = np.concatenate(pts)
    return pts + rng.uniform(-0.03, 0.03, pts.shape) * spacing


centres = pour()
NC = len(centres)
NS = NC * MEMBERS
scale = rng.uniform(0.9, 1.1, NC)
quats = rng.normal(size=(NC, 4))
quats /= np.linalg.norm(quats, axis=1, keepdims=True)
print(f"{NC} grains, {NS} spheres", flush=True)

# ---------------------------------------------------------------------------------------------- fields
vec3 = dem.vec3
SLOTS = 16
X = ti.Vector.field(3, ti.f64, NC)
V = ti.Vector.field(3, ti.f64, NC)
Wv = ti.Vector.field(3, ti.f64, NC)
Q = ti.Vector.field(4, ti.f64, NC)  # w, x, y, z
M = ti.field(ti.f64, NC)
I = ti.field(ti.f64, NC)  # the mean principal moment (the contact law's damping scale)
Ib = ti.Vector.field(3, ti.f64, NC)  # principal moments
Lw = ti.Vector.field(3, ti.f64, NC)  # angular momentum, world frame
F = ti.Vector.field(3, ti.f64, NC)
T = ti.Vector.field(3, ti.f64, NC)
alive = ti.field(ti.i32, NC)
body = ti.Vector.field(3, ti.f64, NS)  # member offset in the clump frame
rad = ti.field(ti.f64, NS)
xs_ = ti.Vector.field(3, ti.f64, NS)
ids = ti.field(ti.i32, (2, NS, SLOTS))
hist = ti.Vector.field(6, ti.f32, (2, NS, SLOTS))
whist = ti.Vector.field(6, ti.f32, (NS, NP))
P_pt = ti.Vector.field(3, ti.f64, NP)
P_n = ti.Vector.field(3, ti.f64, NP)
P_mu = ti.field(ti.f64, NP)
P_on = ti.field(ti.i32, NP)
P_zlo = ti.field(ti.f64, NP)  # the plane acts on sphere centres with P_zlo <= z < P_zhi
P_zhi = ti.field(ti.f64, NP)
P_v = ti.Vector.field(3, ti.f64, NP)
wall_push = ti.field(ti.f64, ())  # x force of the moving wall (the last plane) on the grains, this step
prm = ti.field(ti.f64, dem.N_PRM)
r_max = 1.1 * r_s
cell = 2.0 * r_max
dims = np.maximum(((dom_hi - dom_lo) / cell).astype(int) + 1, 1)
CELL_CAP = 24
cell_n = ti.field(ti.i32, tuple(dims))
cell_items = ti.field(ti.i32, (*dims, CELL_CAP))
home = ti.Vector.field(3, ti.i32, NS)  # each sphere's cell at the last placement (cleared there, not everywhere)
cyl = ti.field(ti.f64, 3)  # radius (0: none), bottom z, friction

X.from_numpy(centres)
Q.from_numpy(quats)
M.from_numpy(mass_unit * scale ** 3)
Ib.from_numpy(inertia_unit[None, :] * scale[:, None] ** 5)
I.from_numpy(inertia_unit.mean() * scale ** 5)
alive.fill(1)
body.from_numpy((c_over_r * r_s * unit_offsets[None, :, :] * scale[:, None, None]).reshape(-1, 3))
rad.from_numpy(np.repeat(r_s * scale, MEMBERS))
ids.fill(-1)
for p, (pt, n, mu_p) in enumerate(planes):
    P_pt[p] = pt
    P_n[p] = n
    P_mu[p] = mu_p
    P_on[p] = 1
    P_zlo[p] = -1e9
    P_zhi[p] = 1e9
prm[dem.P_DAMP] = damping_c
prm[dem.P_KT_RATIO] = soil_model.TANGENTIAL_RATIO
prm[dem.P_ETA_R] = soil_model.ROLLING_DAMPING
lo = ti.Vector(list(dom_lo))
DIMS = ti.Vector([int(v) for v in dims])
DIMS_1 = ti.Vector([int(v) - 1 for v in dims])
g = ti.Vector([0.0, 0.0, -9.81])


@ti.func
def rotate(q, v):
    u = ti.Vector([q[1], q[2], q[3]])
    return v + 2.0 * u.cross(u.cross(v) + q[0] * v)


@ti.func
def rotate_back(q, v):
    return rotate(ti.Vector([q[0], -q[1], -q[2], -q[3]]), v)


@ti.func
def cell_of(p):
    c = ti.cast(ti.floor((p - lo) / cell), ti.i32)
    return ti.max(ti.min(c, DIMS_1), 0)


@ti.kernel
def place():
    for s in range(NS):
        c = s // MEMBERS
        xs_[s] = X[c] + rotate(Q[c], body[s])
    for s in range(NS):
        cell_n[home[s]] = 0
    for s in range(NS):
        if alive[s // MEMBERS]:
            ce = cell_of(xs_[s])
            home[s] = ce
            slot = ti.atomic_add(cell_n[ce], 1)
            if slot < CELL_CAP:
                cell_items[ce, slot] = s


@ti.kernel
def forces(par: ti.i32, dt: ti.f64, mu: ti.f64, mu_rr: ti.f64, k: ti.f64):
    for s in range(NS):
        a = s // MEMBERS
        if alive[a]:
            xa = xs_[s]
            ra = rad[s]
            va = V[a] + Wv[a].cross(xa - X[a])
            f = vec3(0.0)
            tq = vec3(0.0)
            n_new = 0
            ce = cell_of(xa)
            for di, dj, dk in ti.ndrange((-1, 2), (-1, 2), (-1, 2)):
                cc = ce + ti.Vector([di, dj, dk])
                if (cc >= 0).all() and (cc < DIMS).all():
                    for e in range(ti.min(cell_n[cc], CELL_CAP)):
                        j = cell_items[cc, e]
                        b = j // MEMBERS
                        if b != a:
                            dx = xa - xs_[j]
                            rsum = ra + rad[j]
                            d2 = dx.dot(dx)
                            if d2 < rsum * rsum and d2 > 0.0:
                                d = ti.sqrt(d2)
                                n = dx / d
                                h = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0], ti.f32)
                                for q in range(SLOTS):
                                    if ids[1 - par, s, q] == j:
                                        h = hist[1 - par, s, q]
                                vb = V[b] + Wv[b].cross(xs_[j] - X[b])
                                v_c = (va - ra * Wv[a].cross(n)) - (vb + rad[j] * Wv[b].cross(n))
                                m_eff = M[a] * M[b] / (M[a] + M[b])
                                i_eff = I[a] * I[b] / (I[a] + I[b])
                                force, f_t, m_r, hn = dem.contact_law(
                                    n, rsum - d, v_c, Wv[a] - Wv[b], ti.sqrt(m_eff * k), ti.sqrt(i_eff * k),
                                    ra * rad[j] / rsum, h, k, mu, mu_rr, prm, dt)
                                f += force
                                tq += m_r - ra * n.cross(f_t)
                                if n_new < SLOTS:
                                    ids[par, s, n_new] = j
                                    hist[par, s, n_new] = hn
                                    n_new += 1
            for q in range(n_new, SLOTS):
                ids[par, s, q] = -1
            for p in range(NP):
                hp = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0], ti.f32)
                if P_on[p] and P_zlo[p] <= xa[2] < P_zhi[p]:
                    n = P_n[p]
                    gap = (xa - P_pt[p]).dot(n) - ra
                    if -ra < gap < 0.0:  # a plane has a front only: a centre behind it (under the wall's base) is free
                        v_c = va - ra * Wv[a].cross(n) - P_v[p]
                        kw = 2.0 * k
                        force, f_t, m_r, hn = dem.contact_law(
                            n, -gap, v_c, Wv[a], ti.sqrt(M[a] * kw), ti.sqrt(I[a] * kw), ra, whist[s, p], kw,
                            P_mu[p], mu_rr, prm, dt)
                        f += force
                        tq += m_r - ra * n.cross(f_t)
                        hp = hn
                        if p == NP - 1:
                            wall_push[None] += force[0]
                whist[s, p] = hp
            if cyl[0] > 0.0 and xa[2] > cyl[1]:
                rho = ti.sqrt(xa[0] * xa[0] + xa[1] * xa[1])
                gap = cyl[0] - rho - ra
                if gap < 0.0 and 0.0 < rho < cyl[0]:
                    n = -ti.Vector([xa[0], xa[1], 0.0]) / rho
                    f += 2.0 * k * (-gap) * n - damping_c * ti.sqrt(M[a] * 2.0 * k) * va.dot(n) * n
            F[a] += f
            T[a] += (xa - X[a]).cross(f) + tq


@ti.kernel
def integrate(dt: ti.f64, drag: ti.f64):
    for a in range(NC):
        if alive[a]:
            V[a] = (V[a] + (F[a] / M[a] + g) * dt) * (1.0 - drag * dt)
            Lw[a] = (Lw[a] + T[a] * dt) * (1.0 - drag * dt)
            Wv[a] = rotate(Q[a], rotate_back(Q[a], Lw[a]) / Ib[a])
            X[a] += V[a] * dt
            w = Wv[a]
            q = Q[a]
            dq = 0.5 * dt * ti.Vector([-w[0] * q[1] - w[1] * q[2] - w[2] * q[3],
                                       w[0] * q[0] + w[1] * q[3] - w[2] * q[2],
                                       -w[0] * q[3] + w[1] * q[0] + w[2] * q[1],
                                       w[0] * q[2] - w[1] * q[1] + w[2] * q[0]])
            Q[a] = (q + dq).normalized()
        F[a] = vec3(0.0)
        T[a] = vec3(0.0)


@ti.kernel
def kinetic() -> ti.f64:
    e = 0.0
    for a in range(NC):
        if alive[a]:
            e += 0.5 * M[a] * V[a].dot(V[a]) + 0.5 * Wv[a].dot(Lw[a])
    return e


step_count = 0


def run(duration: float, drag: float = 0.0, lift: float = 0.0, every=None, wall=None, clear_above=None):
    """Steps for `duration`; a lift ends early once the cylinder has cleared every grain and they are at rest.
    clear_above: grains whose centre rises above this height are taken out (the blade's spoil)."""
    global step_count
    n = int(math.ceil(duration / dt))
    for i in range(n):
        if lift and i % 2000 == 0 and cyl[1] > X.to_numpy()[:, 2].max() + 2 * r_max and kinetic() < 1e-9:
            break
        place()
        forces(step_count % 2, dt, micro.mu, mu_r, k_n)
        integrate(dt, drag)
        step_count += 1
        if lift:
            cyl[1] = cyl[1] + lift * dt
        if wall is not None:
            wall.append(wall_push[None])
            wall_push[None] = 0.0
            P_pt[NP - 1] = P_pt[NP - 1] + P_v[NP - 1] * dt
        if clear_above is not None and i % 20 == 0:
            clear(clear_above)
        if every and i % every == 0:
            print(f"  t {i * dt:.2f} s, KE {kinetic():.3g} J", flush=True)


@ti.kernel
def clear(z: ti.f64):
    for a in range(NC):
        if X[a][2] > z:
            alive[a] = 0


def out_of_domain() -> np.ndarray:
    x = X.to_numpy()
    return ((x < dom_lo) | (x > dom_hi)).any(1)


def spheres() -> tuple[np.ndarray, np.ndarray]:
    place()
    keep = np.repeat(alive.to_numpy() == 1, MEMBERS)
    return xs_.to_numpy()[keep], rad.to_numpy()[keep]


t0 = time.time()
result = dict(case=case, shape=GRAIN, aspect=aspect, c_over_r=c_over_r, members=MEMBERS, mu_r=mu_r, seed=seed,
              across=across, R_eq=R_eq, r_sphere=r_s, grains=NC, spheres=NS)
if case == "heap":
    cyl[0] = R_cyl
    cyl[1] = -1.0
    run(1.0, drag=2.0)
    run(0.5)
    x = X.to_numpy()
    top = x[:, 2].max()
    result["fill_height"] = float(top)
    cyl[1] = 0.0
    lift_time = top / 0.05 + 0.5
    run(lift_time + 2.0, lift=0.05, every=int(1.0 / dt))
    pos, r = spheres()
    ang = heap_angles(pos, r, 2.0 * R_eq)
    result["flank_angles_deg"] = [math.degrees(v) for v in ang]
    result["angle_deg"] = float(np.mean(result["flank_angles_deg"]))
elif FACE:
    run(1.5, drag=2.0)
    run(0.5)
    over = X.to_numpy()[:, 2] > -R_eq  # level with the ground
    al = alive.to_numpy()
    al[over] = 0
    alive.from_numpy(al)
    run(0.4)
    grains = int(alive.to_numpy().sum())
    bed_mass = float(M.to_numpy()[alive.to_numpy() == 1].sum())
    density = bed_mass / (LX * 2 * HALF_Y * DEPTH)
    result.update(grains=grains, bulk_density=density,
                  solid_fraction=float(grains * vol_unit * r_s ** 3 * np.mean(scale ** 3) / (LX * 2 * HALF_Y * DEPTH)))
    gap = 0.5 * R_eq
    P_zhi[NP - 2] = WALL_BASE  # the pit's front face holds the soil below the wall's base only
    P_zlo[NP - 1] = WALL_BASE
    P_pt[NP - 1] = (-gap, 0.0, 0.0)
    P_v[NP - 1] = (0.1, 0.0, 0.0)
    wall_push[None] = 0.0  # (it summed the pit's front face during the pour)
    push: list = []
    travel_to = 0.2 * H if case == "wall" else 3.0 * H
    run((travel_to + gap) / 0.1, wall=push, clear_above=0.5 * R_eq if case == "blade" else None)
    travel = np.arange(1, len(push) + 1) * dt * 0.1 - gap
    thrust = np.array(push) / (2 * HALF_Y)
    kp = math.tan(math.radians(45 + 17.5)) ** 2
    rankine = 0.5 * kp * density * 9.81 * H ** 2  # the FEE of a smooth vertical blade without surcharge too
    if case == "wall":
        peak = peak_of_travel_average(travel, thrust, 2.0 * R_eq)
        result.update(peak_thrust=peak, rankine=rankine, ratio=peak / rankine)
    else:  # the blade's gate: the mean draft over d to 3d of travel
        steady = float(thrust[(travel >= H) & (travel <= 3.0 * H)].mean())
        result.update(draft=steady, fee=rankine, ratio=steady / rankine)
    marks = np.linspace(0, len(thrust) - 1, 12).astype(int)
    result["curve"] = [(round(float(travel[i]), 4), round(float(thrust[max(0, i - 200):i + 200].mean()), 1))
                       for i in marks]  # (travel m, thrust N/m) at 12 points
else:
    run(1.0, drag=2.0)
    run(0.5)
    x = X.to_numpy()
    over = x[:, 2] > H0 - R_eq  # trim to the column's height, as the project trims a bed to its box
    al = alive.to_numpy()
    al[over] = 0
    alive.from_numpy(al)
    run(0.3)
    pos, r = spheres()
    top = pos[:, 2] + r
    sel = pos[:, 0] < L0
    result["column_height"] = float(top[sel].max())
    grains = int(alive.to_numpy().sum())
    result["grains"] = grains
    result["solid_fraction"] = float(grains * vol_unit * r_s ** 3 * np.mean(scale ** 3) / (L0 * W * H0))
    P_on[NP - 1] = 0
    run(0.5 + 6.0 * math.sqrt(H0 / 9.81))
    pos, r = spheres()
    L_inf = runout_length(pos, r, 2.0 * R_eq)
    result["runout_ratio"] = (L_inf - L0) / L0
result["lost"] = int(out_of_domain().sum())
result["wall_s"] = time.time() - t0
print(json.dumps(result))
