"""Scouting run for docs/validation.md (not part of the package, not tested): does a continuum read the earthmoving
equation at a few cells across the cut, where the DEM reads 1.8 x at 4 grains across?

2-D (plane-strain) MLS-MPM (APIC, quadratic B-splines, 2 x 2 particles a cell), Drucker-Prager sand after Klar et
al. 2016 with the cone matched to Mohr-Coulomb in plane strain (alpha = sin(phi) / sqrt(2); no dilation). A smooth
vertical blade (a90 delta0, a separable grid boundary) cuts d = 0.3 m deep with d of soil below its edge, a rough
floor under that, at 0.1 m/s; spoil rising above the surface is removed (the FEE without surcharge). Prints the
draft per metre over travel d..3d against Rankine (= the FEE's 2,769 N/m for phi 35 deg, 1700 kg/m3).

    python docs/experiments/mpm_blade_2d.py N [EDGE_ROW] [CLEAR] [E]

N cells across d. EDGE_ROW (0 or 1): the blade's lowest constrained node row at the cut depth (0) or a cell above
it (1); the soil left behind the blade reaches the cut depth either way. CLEAR (cells, default 0.1): how far above
the surface spoil is removed. E: Young's modulus, Pa (default 5e6). It also prints the depth of the floor the blade
left behind: the FEE goes as the depth squared, so draft / FEE at the depth actually cut is ratio / (floor / d)^2.

2026-11-26, 2-vCPU Intel Xeon, EDGE_ROW 0 / 1: N 4: 1.61 / 1.08 x, floor 1.12 / 0.89 d (8 s each); N 8: 1.25 /
1.00 x, floor 1.06 / 0.94 d (31 s); N 16: 1.08 / 0.96 x, floor 1.03 / 0.97 d (185 s). With E 2e7: N 4: 1.72 /
1.17 x, floor 1.11 / 0.88 d; N 8, EDGE_ROW 1: 1.05 x, floor 0.94 d.
"""
import math
import sys
import time

import numpy as np
import taichi as ti

try:
    n = int(sys.argv[1])
    edge_row = int(sys.argv[2]) if len(sys.argv) > 2 else 0
    clear_cells = float(sys.argv[3]) if len(sys.argv) > 3 else 0.1
    E = float(sys.argv[4]) if len(sys.argv) > 4 else 5e6
    if not (2 <= n <= 64 and edge_row in (0, 1) and 0.0 <= clear_cells < 10.0 and 1e5 <= E <= 1e9):
        raise ValueError
except (IndexError, ValueError):
    print("usage: mpm_blade_2d.py N (2-64) [EDGE_ROW 0|1] [CLEAR cells, 0-10] [E Pa, 1e5-1e9]", file=sys.stderr)
    sys.exit(2)
ti.init(arch=ti.cpu, default_fp=ti.f64, log_level="error")
d = 0.3
dx = d / n
inv_dx = 1.0 / dx
phi = math.radians(35.0)
rho = 1700.0
nu = 0.3
mu0, lam0 = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
alpha = math.sin(phi) / math.sqrt(2.0)
g = 9.81
speed = 0.1
L, Hdom = 2.7, 1.1
nx, ny = int(L / dx) + 4, int(Hdom / dx) + 4
pad = 3
y0 = pad * dx
ys = (pad + 2 * n) * dx              # surface (whole cells: no rounding of the rows below)
ye = (pad + n) * dx                  # cut depth: the soil behind the blade reaches it
je = pad + n + edge_row              # the blade's lowest constrained node row
x0 = 0.35
tb = max(2 * dx, 0.06)
xr = L - 0.05

# particles: 2 x 2 per cell, below the edge everywhere, above it ahead of the blade
pts = []
for (xa, xb, ya, yb) in ((pad * dx, xr, y0, ye), (x0, xr, ye, ys)):
    ii = np.arange(int(round((xa) / dx * 2)), int(round(xb / dx * 2)))
    jj = np.arange(int(round(ya / dx * 2)), int(round(yb / dx * 2)))
    X, Y = np.meshgrid((ii + 0.5) * dx / 2, (jj + 0.5) * dx / 2, indexing="ij")
    pts.append(np.stack([X.ravel(), Y.ravel()], 1))
P = np.concatenate(pts)
npart = len(P)
p_vol = (dx / 2) ** 2
p_mass0 = rho * p_vol

x = ti.Vector.field(2, float, npart)
v = ti.Vector.field(2, float, npart)
C = ti.Matrix.field(2, 2, float, npart)
F = ti.Matrix.field(2, 2, float, npart)
pm = ti.field(float, npart)
gv = ti.Vector.field(2, float, (nx, ny))
gm = ti.field(float, (nx, ny))
imp = ti.field(float, 2)
x.from_numpy(P)
F.from_numpy(np.tile(np.eye(2), (npart, 1, 1)))
pm.fill(p_mass0)

c_wave = math.sqrt((lam0 + 2 * mu0) / rho)
dt = 0.3 * dx / c_wave


@ti.func
def project(Fp):
    U, sig, V = ti.svd(Fp)
    e = ti.Vector([ti.log(ti.max(sig[0, 0], 1e-8)), ti.log(ti.max(sig[1, 1], 1e-8))])
    tr = e[0] + e[1]
    eh = e - tr / 2.0
    nh = eh.norm()
    if tr >= 0.0:
        e = ti.Vector([0.0, 0.0])
    else:
        dg = nh + (2.0 * lam0 + 2.0 * mu0) / (2.0 * mu0) * tr * alpha
        if dg > 0.0:
            e = e - dg * eh / ti.max(nh, 1e-30)
    return U @ ti.Matrix([[ti.exp(e[0]), 0.0], [0.0, ti.exp(e[1])]]) @ V.transpose(), U, e, V


@ti.func
def stencil(xp):
    """The particle's lower grid node, its offset from it in cells and the quadratic B-spline weights."""
    base = (xp * inv_dx - 0.5).cast(int)
    fx = xp * inv_dx - base.cast(float)
    return base, fx, [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]


@ti.kernel
def substep(xb: float, vb: float, damp: float, clear: int):
    for i, j in gm:
        gv[i, j] = [0.0, 0.0]
        gm[i, j] = 0.0
    for p in x:
        if pm[p] == 0.0:
            continue
        base, fx, w = stencil(x[p])
        Fn, U, e, V = project(F[p])
        F[p] = Fn
        tau = U @ ti.Matrix([[2 * mu0 * e[0] + lam0 * (e[0] + e[1]), 0.0],
                             [0.0, 2 * mu0 * e[1] + lam0 * (e[0] + e[1])]]) @ U.transpose()
        stress = -dt * p_vol * 4 * inv_dx * inv_dx * tau
        affine = stress + pm[p] * C[p]
        for a, b in ti.static(ti.ndrange(3, 3)):
            off = ti.Vector([a, b])
            dpos = (off.cast(float) - fx) * dx
            wt = w[a][0] * w[b][1]
            gv[base + off] += wt * (pm[p] * v[p] + affine @ dpos)
            gm[base + off] += wt * pm[p]
    for i, j in gm:
        if gm[i, j] > 0:
            gv[i, j] = gv[i, j] / gm[i, j] * damp
            gv[i, j][1] -= dt * g
            if j < pad:
                gv[i, j] = [0.0, 0.0]            # rough floor
            if i < pad and gv[i, j][0] < 0:
                gv[i, j][0] = 0.0                # smooth end walls
            if i > nx - pad - 1 and gv[i, j][0] > 0:
                gv[i, j][0] = 0.0
            xn = i * dx
            if j >= je and xn <= xb and xn >= xb - tb and gv[i, j][0] < vb:
                imp[0] += gm[i, j] * (vb - gv[i, j][0])   # smooth blade, separable: normal velocity only
                gv[i, j][0] = vb
    for p in x:
        if pm[p] == 0.0:
            continue
        base, fx, w = stencil(x[p])
        nv = ti.Vector.zero(float, 2)
        nC = ti.Matrix.zero(float, 2, 2)
        for a, b in ti.static(ti.ndrange(3, 3)):
            off = ti.Vector([a, b])
            dpos = off.cast(float) - fx
            wt = w[a][0] * w[b][1]
            gvv = gv[base + off]
            nv += wt * gvv
            nC += 4 * inv_dx * wt * gvv.outer_product(dpos)
        v[p], C[p] = nv, nC
        x[p] += dt * nv
        F[p] = (ti.Matrix.identity(float, 2) + dt * nC) @ F[p]
        if clear != 0 and x[p][1] > ys + clear_cells * dx and x[p][0] > xb - tb:
            pm[p] = 0.0                          # spoil above the surface: the FEE without surcharge


t0 = time.time()
# settle under gravity, blade still, damped
t = 0.0
while t < 0.6:
    substep(x0, 0.0, 0.995, 0)
    t += dt
imp[0] = 0.0
travel, samples = 0.0, []
acc, acc_t = 0.0, 0.0
while travel < 3 * d:
    imp[0] = 0.0
    substep(x0 + travel, speed, 1.0, 1)
    acc += imp[0] / dt
    acc_t += 1
    travel += speed * dt
    if acc_t >= 50:
        samples.append((travel, acc / acc_t))
        acc, acc_t = 0.0, 0.0
s = np.array(samples)
win = (s[:, 0] >= d) & (s[:, 0] <= 3 * d)
draft = s[win, 1].mean()
kp = math.tan(math.pi / 4 + phi / 2) ** 2
rankine = 0.5 * kp * rho * g * d ** 2
prof = [round(float(s[(s[:, 0] >= a) & (s[:, 0] < a + d / 2), 1].mean() / rankine), 2)
        for a in np.arange(0, 3 * d, d / 2)]
# the floor left behind the blade: the highest particle per cell column over the cut, below the surface
xs, ms = x.to_numpy(), pm.to_numpy()
keep = (ms > 0) & (xs[:, 0] > x0 + 0.1) & (xs[:, 0] < x0 + travel - 0.3)
cols = np.floor(xs[keep, 0] / dx).astype(int)
tops = np.full(cols.max() + 1, -np.inf)
np.maximum.at(tops, cols, xs[keep, 1] + 0.25 * dx)
floor_depth = float(ys - tops[np.isfinite(tops)].mean())
print(f"n={n} edge_row={edge_row} clear={clear_cells} E={E:.0e} particles={npart} dt={dt:.2e} draft={draft:.0f} N/m "
      f"ratio={draft / rankine:.3f} per d/2 of travel {prof} floor depth / d {floor_depth / d:.3f} "
      f"wall {time.time() - t0:.0f} s")
