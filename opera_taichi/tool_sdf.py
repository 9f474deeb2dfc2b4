"""Signed distance grids of tool meshes (link frame), for particle-tool contact in the DEM kernels.

Any trimesh works. The mesh is welded and split into bodies; a watertight body gets a signed distance
(negative inside), any other piece an unsigned distance minus a small thickness (an open sheet becomes a
thin plate); the tool's field is the minimum over bodies (the union). Distances are exact (point-triangle)
within a band around the surface, which covers every distance a contact can see; deeper inside a body they
come from a Euclidean distance transform (within one grid spacing), and far outside they are clamped to the
band. Each node also stores the unit gradient: from the exact closest point in the band (smooth normals, also
on thin plates), from finite differences elsewhere. Grids are cached on disk by mesh hash and spacing.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage

from .errors import UserError
from .paths import cache_dir

SDF_VERSION = 1
MAX_NODES = 16_000_000
_PAIR_BATCH = 1_500_000


@dataclass(frozen=True)
class SdfGrid:
    origin: np.ndarray   # (3,) link-frame position of node (0, 0, 0)
    spacing: float       # node spacing, m
    data: np.ndarray     # (nx, ny, nz, 4) float32: signed distance, unit gradient (x, y, z)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.data.shape[:3])

    def sample(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Trilinear distance and gradient at link-frame points (as the kernel does); inf outside the grid."""
        pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
        u = (pts - self.origin) / self.spacing
        dims = np.array(self.shape)
        inside = np.all((u >= 0) & (u < dims - 1), axis=1)
        i0 = np.clip(np.floor(u).astype(np.int64), 0, dims - 2)
        f = u - i0
        acc = np.zeros((len(pts), 4))
        for c in range(8):
            d = np.array([c // 4, (c // 2) % 2, c % 2])
            w = np.prod(np.where(d == 1, f, 1.0 - f), axis=1)
            idx = i0 + d
            acc += w[:, None] * self.data[idx[:, 0], idx[:, 1], idx[:, 2]].astype(np.float64)
        dist = np.where(inside, acc[:, 0], np.inf)
        return dist, acc[:, 1:]


def _closest_points_on_triangles(p, a, b, c):
    """Closest point on triangle (a, b, c) to p, all (k, 3) arrays (Ericson, Real-Time Collision Detection)."""
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        out = a + ab * v[:, None] + ac * w[:, None]          # interior
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    done = np.zeros(len(p), dtype=bool)

    def put(mask, value):
        nonlocal done
        m = mask & ~done
        out[m] = value[m] if value.ndim == 2 else value
        done |= m

    put((d1 <= 0) & (d2 <= 0), a)
    put((d3 >= 0) & (d4 <= d3), b)
    put((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * t_ab[:, None])
    put((d6 >= 0) & (d5 <= d6), c)
    put((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * t_ac[:, None])
    put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), b + (c - b) * t_bc[:, None])
    degenerate = ~np.isfinite(out).all(axis=1)
    if degenerate.any():  # zero-area triangle: nearest of its vertices is close enough
        cand = np.stack([a[degenerate], b[degenerate], c[degenerate]], axis=1)
        k = np.argmin(np.linalg.norm(cand - p[degenerate][:, None], axis=2), axis=1)
        out[degenerate] = cand[np.arange(len(k)), k]
    return out


def _band_distance(body: trimesh.Trimesh, origin, h, dims, band):
    """Exact unsigned distance, closest point and triangle for nodes within `band` of any triangle's box."""
    n_nodes = int(np.prod(dims))
    best = np.full(n_nodes, np.inf)
    closest = np.zeros((n_nodes, 3))
    tri_of = np.full(n_nodes, -1, dtype=np.int64)
    tris = body.triangles
    normals = body.face_normals
    lo = np.clip(np.floor((tris.min(axis=1) - band - origin) / h).astype(np.int64), 0, dims - 1)
    hi = np.clip(np.ceil((tris.max(axis=1) + band - origin) / h).astype(np.int64), 0, dims - 1)
    ext = hi - lo + 1
    counts = np.prod(ext, axis=1)
    start = 0
    while start < len(tris):
        stop = start + max(1, int(np.searchsorted(np.cumsum(counts[start:]), _PAIR_BATCH)))
        stop = min(stop, len(tris))
        sel = np.arange(start, stop)
        cnt = counts[sel]
        tri = np.repeat(sel, cnt)
        local = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        e = ext[tri]
        iz = local % e[:, 2]
        iy = (local // e[:, 2]) % e[:, 1]
        ix = local // (e[:, 2] * e[:, 1])
        idx = lo[tri] + np.stack([ix, iy, iz], axis=1)
        flat = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
        p = origin + idx * h
        keep = np.abs(np.einsum("ij,ij->i", p - tris[tri, 0], normals[tri])) <= band  # plane far: skip
        tri, flat, p = tri[keep], flat[keep], p[keep]
        q = _closest_points_on_triangles(p, tris[tri, 0], tris[tri, 1], tris[tri, 2])
        dist = np.linalg.norm(p - q, axis=1)
        np.minimum.at(best, flat, dist)
        win = dist <= best[flat]
        closest[flat[win]] = q[win]
        tri_of[flat[win]] = tri[win]
        start = stop
    return best.reshape(dims), closest.reshape(*dims, 3), tri_of.reshape(dims)


def _inside_parity(body: trimesh.Trimesh, origin, h, dims):
    """Inside mask of a watertight body: parity of crossings of a +z ray from every node."""
    jitter = np.array([0.3183098861837907, 0.2718281828459045]) * 1e-3 * h  # keep rays off edges and vertices
    tris = body.triangles
    xy = tris[:, :, :2]
    diff = np.zeros((dims[0], dims[1], dims[2] + 1), dtype=np.int32)
    lo = np.clip(np.floor((xy.min(axis=1) - origin[:2] - jitter) / h).astype(np.int64), 0, dims[:2] - 1)
    hi = np.clip(np.ceil((xy.max(axis=1) - origin[:2] - jitter) / h).astype(np.int64), 0, dims[:2] - 1)
    ext = hi - lo + 1
    cnt = np.prod(ext, axis=1)
    tri = np.repeat(np.arange(len(tris)), cnt)
    local = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    ix = lo[tri, 0] + local // ext[tri, 1]
    iy = lo[tri, 1] + local % ext[tri, 1]
    px = origin[0] + ix * h + jitter[0]
    py = origin[1] + iy * h + jitter[1]
    a, b, c = tris[tri, 0], tris[tri, 1], tris[tri, 2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        l1 = ((px - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (py - a[:, 1])) / det
        l2 = ((b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (px - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
        hit = (det != 0) & np.isfinite(l1) & np.isfinite(l2) & (l1 >= 0) & (l2 >= 0) & (l1 + l2 <= 1)
    z_hit = a[hit, 2] + l1[hit] * (b[hit, 2] - a[hit, 2]) + l2[hit] * (c[hit, 2] - a[hit, 2])
    below = np.clip(np.ceil((z_hit - origin[2]) / h).astype(np.int64), 0, dims[2])  # nodes under the hit
    np.add.at(diff, (ix[hit], iy[hit], np.zeros_like(below)), 1)
    np.add.at(diff, (ix[hit], iy[hit], below), -1)
    return (np.cumsum(diff, axis=2)[:, :, :-1] % 2) == 1


def build_sdf(mesh: trimesh.Trimesh, spacing: float, margin: float, name: str = "tool") -> SdfGrid:
    """Signed distance grid of `mesh` (its own frame) with nodes `spacing` apart, `margin` beyond its bounds."""
    if not (spacing > 0 and np.isfinite(spacing)):
        raise UserError(f"tools.{name}.sdf_spacing: expected a positive length, got {spacing!r}")
    welded = trimesh.Trimesh(vertices=np.asarray(mesh.vertices, dtype=np.float64),
                             faces=np.asarray(mesh.faces), process=True)
    welded.merge_vertices()
    if len(welded.faces) == 0:
        raise UserError(f"tools.{name}: the mesh has no triangles")
    h = float(spacing)
    band = max(float(margin), 2.0 * h)
    origin = welded.bounds[0] - margin
    dims = np.ceil((welded.bounds[1] + margin - origin) / h).astype(np.int64) + 1
    if np.prod(dims) > MAX_NODES:
        raise UserError(f"tools.{name}.sdf_spacing: {h:g} m gives a {dims[0]}x{dims[1]}x{dims[2]} grid, more than "
                        f"{MAX_NODES} nodes; use a larger spacing")
    phi = np.full(tuple(dims), np.inf)
    grad = np.zeros((*dims, 3))
    for body in welded.split(only_watertight=False):
        solid = bool(body.is_watertight) and abs(body.volume) > 0
        if solid:
            body.fix_normals()
            if body.volume < 0:
                body.invert()
        # work on the body's own box of nodes (its bounds plus the band, plus one node for the EDT)
        lo = np.clip(np.floor((body.bounds[0] - band - origin) / h).astype(np.int64) - 1, 0, dims - 1)
        hi = np.clip(np.ceil((body.bounds[1] + band - origin) / h).astype(np.int64) + 1, 0, dims - 1)
        sub = hi - lo + 1
        sub_origin = origin + lo * h
        box = tuple(slice(lo[a], hi[a] + 1) for a in range(3))
        grid = np.stack(np.meshgrid(*[sub_origin[a] + h * np.arange(sub[a]) for a in range(3)], indexing="ij"),
                        axis=-1)
        dist, closest, tri = _band_distance(body, sub_origin, h, sub, band)
        near = np.isfinite(dist)
        if solid:
            inside = _inside_parity(body, sub_origin, h, sub)
            deep = -ndimage.distance_transform_edt(inside) * h if inside.any() else np.zeros(tuple(sub))
            signed = np.where(near, np.where(inside, -dist, dist), np.where(inside, deep, band))
            sign = np.where(inside, -1.0, 1.0)
        else:
            thickness = h
            signed = np.where(near, dist, band) - thickness
            sign = np.ones(tuple(sub))
        vec = (grid - closest) * sign[..., None]
        length = np.linalg.norm(vec, axis=-1)
        g = np.zeros((*sub, 3))
        ok = near & (length > 1e-6 * h)
        g[ok] = vec[ok] / length[ok][:, None]
        on_surface = near & ~ok
        g[on_surface] = body.face_normals[tri[on_surface]]
        far = ~near
        if far.any():
            fd = np.stack(np.gradient(signed, h), axis=-1)
            fn = np.linalg.norm(fd, axis=-1)
            fd = np.where(fn[..., None] > 0, fd / np.maximum(fn, 1e-30)[..., None], 0.0)
            g[far] = fd[far]
        better = signed < phi[box]
        phi[box] = np.where(better, signed, phi[box])
        grad[box] = np.where(better[..., None], g, grad[box])
    phi = np.minimum(phi, band)
    data = np.concatenate([phi[..., None], grad], axis=-1).astype(np.float32)
    return SdfGrid(origin=origin.astype(np.float64), spacing=h, data=data)


def mesh_key(mesh: trimesh.Trimesh, spacing: float, margin: float) -> str:
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    digest.update(f"{spacing:.12g}|{margin:.12g}|v{SDF_VERSION}".encode())
    return digest.hexdigest()[:32]


def tool_sdf(mesh: trimesh.Trimesh, spacing: float, margin: float, *, name: str = "tool",
             use_cache: bool = True) -> SdfGrid:
    """build_sdf, cached in cache_dir()/sdf by a hash of the mesh, spacing and margin."""
    path = cache_dir() / "sdf" / f"{mesh_key(mesh, spacing, margin)}.npz"
    if use_cache and path.is_file():
        try:
            with np.load(path) as f:
                return SdfGrid(origin=f["origin"], spacing=float(f["spacing"]), data=f["data"])
        except (OSError, KeyError, ValueError):
            pass  # unreadable cache entry: rebuild it
    grid = build_sdf(mesh, spacing, margin, name=name)
    if use_cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{np.random.randint(1 << 30)}.npz")
        np.savez(tmp, origin=grid.origin, spacing=grid.spacing, data=grid.data)
        tmp.replace(path)
    return grid
