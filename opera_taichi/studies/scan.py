"""Terrain scans as users have them, gridded onto a heightmap in the machine frame.

Readers: LAS/LAZ point clouds (laspy; LAZ through lazrs), PLY point clouds or meshes (their vertices; plyfile),
XYZ/CSV/TXT point lists (x y z columns, a header naming them or the first three columns), GeoTIFF elevation rasters
(tifffile and the GeoTIFF pixel-scale / tie-point tags; nodata cells stay empty) and our NPZ heightmaps (x, y,
z[ix, iy]). Every reader gives points (N, 3) in the scan's own frame; a raster gives its cell centres.

Gridding (`grid_points`) takes the mean height of the points in each cell; a cell with no point is NaN and counted
as empty, never filled in. A `Transform` (translation, then roll/pitch/yaw about fixed axes) takes scan points into
the machine frame; `fit_transform` estimates it from the ground around the dig against the run's initial terrain:
a plane fit (z, roll, pitch) where that terrain is flat, a rigid fit (all six) where it has relief to hold x, y and
yaw; robust to the dug area, which it leaves out as outliers, and it reports the residual.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UserError

POINT_SUFFIXES = (".las", ".laz", ".ply", ".xyz", ".csv", ".txt", ".pts")
RASTER_SUFFIXES = (".tif", ".tiff", ".npz")
MAX_FIT_POINTS = 20_000      # points used by fit_transform (a random subset of a larger scan)
RELIEF_SMOOTHING_M = 0.2     # the relief that can hold x, y, yaw is judged on the terrain smoothed at this scale,
#                              so grain-sized bumps of a DEM heightmap do not count as features
MIN_RELIEF_SLOPE = 0.03      # weakest RMS slope (x, y, yaw directions) a rigid fit needs; below it: plane fit
OFF_TERRAIN_M = 1.0          # fit residual of a scan point on a hole in the terrain: an outlier to every stage's loss


# ----------------------------------------------------------------------------------------------- transform
@dataclass
class Transform:
    """Scan frame -> machine frame: p' = Rz(yaw) Ry(pitch) Rx(roll) p + (x, y, z). Metres and radians."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0

    def matrix(self) -> np.ndarray:
        from scipy.spatial.transform import Rotation

        return Rotation.from_euler("xyz", [self.roll, self.pitch, self.yaw]).as_matrix()

    def apply(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, float) @ self.matrix().T + np.array([self.x, self.y, self.z])

    def describe(self) -> dict:
        """For comparison.json: metres and degrees."""
        return {"x_m": self.x, "y_m": self.y, "z_m": self.z, "roll_deg": math.degrees(self.roll),
                "pitch_deg": math.degrees(self.pitch), "yaw_deg": math.degrees(self.yaw)}

    @classmethod
    def parse(cls, text, key: str = "--transform") -> "Transform":
        """'x,y,z,yaw_deg' or 'x,y,z,yaw_deg,roll_deg,pitch_deg' (m, degrees), or a mapping {xyz: [..], yaw_deg,
        roll_deg, pitch_deg} (yaw/roll/pitch in rad without _deg), as a scene gives it."""
        if isinstance(text, Transform):
            return text
        if isinstance(text, dict):
            known = {"xyz", "yaw", "yaw_deg", "roll", "roll_deg", "pitch", "pitch_deg"}
            bad = sorted(set(text) - known)
            if bad:
                raise UserError(f"{key}.{bad[0]}: unknown key; allowed: {', '.join(sorted(known))}")
            xyz = text.get("xyz", [0.0, 0.0, 0.0])
            if not isinstance(xyz, (list, tuple)) or len(xyz) != 3 or not all(_is_number(v) for v in xyz):
                raise UserError(f"{key}.xyz: expected [x, y, z] in m, got {xyz!r}")
            angles = {}
            for name in ("roll", "pitch", "yaw"):
                if name in text and name + "_deg" in text:
                    raise UserError(f"{key}.{name}_deg: give {name} (rad) or {name}_deg, not both")
                raw = text.get(name + "_deg", text.get(name, 0.0))
                if not _is_number(raw):
                    raise UserError(f"{key}.{name}: expected a number, got {raw!r}")
                angles[name] = math.radians(raw) if name + "_deg" in text else float(raw)
            return cls(*(float(v) for v in xyz), **angles)
        parts = [p.strip() for p in str(text).split(",")]
        try:
            values = [float(p) for p in parts]
        except ValueError:
            values = []
        if len(values) not in (4, 6) or not all(math.isfinite(v) for v in values):
            raise UserError(f"{key}: expected x,y,z,yaw_deg[,roll_deg,pitch_deg] (m, degrees), got {text!r}")
        x, y, z, yaw = values[:4]
        roll, pitch = values[4:] if len(values) == 6 else (0.0, 0.0)
        return cls(x, y, z, math.radians(roll), math.radians(pitch), math.radians(yaw))


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


# ----------------------------------------------------------------------------------------------- readers
@dataclass
class Scan:
    """Points (N, 3) in the scan's frame and what they came from."""

    path: Path
    points: np.ndarray
    kind: str                 # 'points' | 'raster'
    cell: float | None = None  # raster cell size (scan units)
    units: str = "m"          # as the file declares it, when it does
    raster: tuple | None = None  # (z[u, v], xy(u, v)): a raster's heights by index and its index -> x, y map


def read_scan(path, key: str = "--terrain") -> Scan:
    """Reads any supported scan; UserError (one line naming the file) when it cannot."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{key}: {path}: file not found")
    if path.is_dir():
        raise UserError(f"{key}: {path}: is a folder, expected a scan file")
    suffix = path.suffix.lower()
    readers = {".las": _read_las, ".laz": _read_las, ".ply": _read_ply, ".tif": _read_geotiff,
               ".tiff": _read_geotiff, ".npz": _read_npz}
    reader = readers.get(suffix, _read_text if suffix in POINT_SUFFIXES else None)
    if reader is None:
        raise UserError(f"{key}: {path}: unknown scan format {suffix or '(no suffix)'!r}; expected one of "
                        f"{', '.join(POINT_SUFFIXES + RASTER_SUFFIXES)}")
    try:
        scan = reader(path)
    except UserError as exc:
        raise UserError(str(exc).replace("--terrain:", f"{key}:", 1)) from None
    except ImportError as exc:
        raise UserError(f"{key}: {path}: reading {suffix} needs {exc.name or exc} (pip install "
                        f"'opera-taichi[studies]')") from None
    except Exception as exc:  # noqa: BLE001 - every reader raises its own types on a broken file
        raise UserError(f"{key}: {path}: cannot read it as {suffix[1:].upper()} ({type(exc).__name__}: "
                        f"{' '.join(str(exc).split())[:160]})") from None
    pts = np.asarray(scan.points, float).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < 3:
        raise UserError(f"{key}: {path}: holds {len(pts)} usable points; a scan needs at least 3")
    if scan.units not in ("m", "metre", "meter"):
        raise UserError(f"{key}: {path}: the file declares its units as {scan.units}; give the scan in metres")
    scan.points = pts
    return scan


def _read_las(path: Path) -> Scan:
    import laspy

    las = laspy.read(str(path))
    pts = np.stack([np.asarray(las.x, float), np.asarray(las.y, float), np.asarray(las.z, float)], axis=1)
    units = "m"
    try:
        crs = las.header.parse_crs()  # None without a CRS record; pyproj only when there is one
    except ImportError:  # a declared CRS left unchecked would let a scan in feet through as metres
        raise UserError(f"--terrain: {path}: the file declares a coordinate system; checking its units needs pyproj "
                        f"(pip install 'opera-taichi[studies]')") from None
    except Exception:  # noqa: BLE001 - an unreadable CRS record: nothing declared
        crs = None
    if crs is not None:  # every axis (a compound CRS has the vertical one too) in metres
        for axis in getattr(crs, "axis_info", None) or []:
            unit = (getattr(axis, "unit_name", "") or "").lower()
            if unit not in ("metre", "meter", "m", ""):
                units = unit
                break
    if units == "m":  # a GeoKeyDirectory's own unit keys (laspy's CRS leaves out the vertical units key)
        for vlr in las.header.vlrs:
            geo_keys = getattr(vlr, "geo_keys", None)
            if geo_keys:
                units = _declared_units({int(k.id): int(k.value_offset) for k in geo_keys
                                         if int(k.tiff_tag_location) == 0}, path)
    return Scan(path, pts, "points", units=units)


def _read_ply(path: Path) -> Scan:
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise UserError(f"--terrain: {path}: a PLY without a `vertex` element (it has {', '.join(names) or 'none'})")
    v = ply["vertex"]
    fields = [p.name for p in v.properties]
    if not all(c in fields for c in "xyz"):
        raise UserError(f"--terrain: {path}: PLY vertices need x, y, z properties, got {', '.join(fields)}")
    return Scan(path, np.stack([np.asarray(v[c], float) for c in "xyz"], axis=1), "points")


def _read_text(path: Path) -> Scan:
    with open(path, encoding="utf-8-sig", errors="replace") as fh:
        first = fh.readline()
    delimiter = "," if "," in first else (";" if ";" in first else None)
    cells = [c.strip().strip('"').lower() for c in (first.split(delimiter) if delimiter else first.split())]
    count_line = len([c for c in cells if c]) == 1 and cells[0].isdigit()  # a PTS file's point count
    header = not count_line and not all(_float_or_none(c) is not None for c in cells if c)
    cols = (0, 1, 2)
    if header:
        try:
            cols = tuple(cells.index(name) for name in "xyz")
        except ValueError:
            raise UserError(f"--terrain: {path}: the header names no x, y, z columns (got "
                            f"{', '.join(cells)[:120]})") from None
    with warnings.catch_warnings():  # an empty file: read_scan says so in one line, not numpy in two
        warnings.simplefilter("ignore", UserWarning)
        data = np.loadtxt(path, delimiter=delimiter, skiprows=1 if header or count_line else 0, usecols=cols, ndmin=2,
                          encoding="utf-8-sig")
    return Scan(path, data, "points")


def _float_or_none(text: str):
    try:
        return float(text)
    except ValueError:
        return None


# GeoTIFF tags and keys (GeoTIFF 1.1 spec)
_PIXEL_SCALE, _TIEPOINT, _TRANSFORM, _GEOKEYS, _NODATA = 33550, 33922, 34264, 34735, 42113
_RASTER_TYPE_KEY, _LINEAR_UNITS_KEY, _VERTICAL_UNITS_KEY = 1025, 3076, 4099
_PROJECTED_CRS_KEY = 3072
NODATA_MAGNITUDE = 1e30  # m: a height beyond it is a fill value
_UNITS = {9001: "m", 9002: "foot", 9003: "US survey foot", 9036: "km", 9035: "mile"}


def _declared_units(keys: dict[int, int], path: Path) -> str:
    """The units GeoTIFF geokeys declare (a GeoTIFF's, or a LAS file's GeoKeyDirectory): the linear and vertical
    unit keys, else the units of the projected or geographic coordinate system their EPSG code names."""
    for key in (_LINEAR_UNITS_KEY, _VERTICAL_UNITS_KEY):
        if key in keys and keys[key] not in (9001, 32767):  # (32767: user-defined, given elsewhere)
            return _UNITS.get(keys[key], f"EPSG unit {keys[key]}")
    code = keys.get(_PROJECTED_CRS_KEY)
    if code in (None, 0, 32767):
        return "m"
    try:
        import pyproj
    except ImportError:  # a declared CRS left unchecked would let a scan in feet through as metres
        raise UserError(f"--terrain: {path}: the file declares the coordinate system EPSG:{code}; checking its "
                        f"units needs pyproj (pip install 'opera-taichi[studies]')") from None
    try:
        axes = pyproj.CRS.from_epsg(code).axis_info
    except Exception:  # noqa: BLE001 - a code pyproj does not know: its units cannot be told
        raise UserError(f"--terrain: {path}: the file declares EPSG:{code}, which pyproj does not know; give the "
                        f"scan in metres without it") from None
    for axis in axes:
        unit = (axis.unit_name or "").lower()
        if unit not in ("metre", "meter", "m", ""):
            return unit
    return "m"


def _read_geotiff(path: Path) -> Scan:
    import tifffile

    with tifffile.TiffFile(str(path)) as tif:
        page = tif.pages[0]
        stored = page.asarray()
        tags = {t.code: t.value for t in page.tags.values()}
    if stored.ndim == 3:  # one band expected; take the first
        stored = stored[..., 0] if stored.shape[-1] < stored.shape[0] else stored[0]
    if stored.ndim != 2:
        raise UserError(f"--terrain: {path}: expected a single-band elevation raster, got shape {stored.shape}")
    z = np.asarray(stored, float)
    if _NODATA in tags:
        nodata = _float_or_none(str(tags[_NODATA]).strip("\x00 "))
        if nodata is not None:
            missing = z == nodata
            if np.issubdtype(stored.dtype, np.floating):  # as stored: -9999.9 in float32 is float32(-9999.9)
                with np.errstate(over="ignore", invalid="ignore"):
                    missing |= stored == np.asarray(nodata).astype(stored.dtype)
            z[missing] = np.nan
    z[np.abs(z) > NODATA_MAGNITUDE] = np.nan  # a float's maximum, GIS tools' usual fill, is no elevation
    keys = {}
    raw = tags.get(_GEOKEYS)
    if raw is not None and len(raw) >= 4:
        for k in range(int(raw[3])):
            key_id, loc, _count, value = raw[4 + 4 * k: 8 + 4 * k]
            if loc == 0:
                keys[int(key_id)] = int(value)
    units = _declared_units(keys, path)
    half = 0.0 if keys.get(_RASTER_TYPE_KEY) == 2 else 0.5  # PixelIsPoint: the tie point is the pixel centre
    if _TRANSFORM in tags:
        m = np.asarray(tags[_TRANSFORM], float).reshape(4, 4)
        cell = float(math.hypot(m[0, 0], m[1, 0]))

        def xy(j, i):  # row j, column i (pixel-centre indices) -> model x, y
            return m[0, 0] * (i + half) + m[0, 1] * (j + half) + m[0, 3], m[1, 0] * (i + half) + m[1, 1] * (j + half) + m[1, 3]
    elif _PIXEL_SCALE in tags and _TIEPOINT in tags:
        sx, sy = (float(v) for v in tags[_PIXEL_SCALE][:2])
        ti, tj, _tk, tx, ty, _tz = (float(v) for v in tags[_TIEPOINT][:6])
        cell = sx

        def xy(j, i):
            return tx + (i + half - ti) * sx, ty - (j + half - tj) * sy
    else:
        raise UserError(f"--terrain: {path}: a TIFF without GeoTIFF georeferencing (no ModelPixelScale and "
                        f"ModelTiepoint tags, no ModelTransformation tag)")
    return _raster_scan(path, z, xy, cell, units)


def _raster_scan(path: Path, z: np.ndarray, xy, cell: float, units: str = "m") -> Scan:
    uu, vv = np.meshgrid(np.arange(z.shape[0], dtype=float), np.arange(z.shape[1], dtype=float), indexing="ij")
    x, y = xy(uu, vv)
    pts = np.stack([np.broadcast_to(x, z.shape).ravel(), np.broadcast_to(y, z.shape).ravel(), z.ravel()], axis=1)
    return Scan(path, pts[np.isfinite(pts[:, 2])], "raster", cell=cell, units=units, raster=(z, xy))


def _read_npz(path: Path) -> Scan:
    with np.load(path) as f:
        missing = [k for k in ("x", "y", "z") if k not in f.files]
        if missing:
            raise UserError(f"--terrain: {path}: an NPZ heightmap needs arrays x, y, z[ix, iy]; missing "
                            f"{', '.join(missing)} (has {', '.join(f.files) or 'none'})")
        x, y, z = (np.asarray(f[k], float) for k in ("x", "y", "z"))
    if z.shape != (len(x), len(y)):
        raise UserError(f"--terrain: {path}: z has shape {z.shape}, expected (len(x), len(y)) = ({len(x)}, {len(y)})")
    if len(x) < 2 or len(y) < 2:
        raise UserError(f"--terrain: {path}: an NPZ heightmap needs at least 2 nodes along x and y")
    dx, dy = x[1] - x[0], y[1] - y[0]
    return _raster_scan(path, z, lambda u, v: (x[0] + u * dx, y[0] + v * dy), float(abs(dx)))


# ----------------------------------------------------------------------------------------------- gridding
@dataclass
class Gridded:
    """A scan on heightmap nodes: z[ix, iy] (NaN = no point in the cell), points per cell."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    count: np.ndarray

    @property
    def empty_cells(self) -> int:
        return int(np.sum(self.count == 0))


def axes_for(points: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Cell-centre axes at `cell` spacing over the points' extent."""
    if not cell > 0:
        raise UserError(f"--cell: expected a positive cell size in m, got {cell!r}")
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    n = np.maximum(1, np.ceil((hi - lo) / cell - 1e-9).astype(int))
    return lo[0] + cell * (np.arange(n[0]) + 0.5), lo[1] + cell * (np.arange(n[1]) + 0.5)


def grid_points(points: np.ndarray, x: np.ndarray, y: np.ndarray) -> Gridded:
    """Mean z of the points in each cell of the nodes x, y (uniform cell-centre axes); empty cells NaN."""
    pts = np.asarray(points, float)
    dx = x[1] - x[0] if len(x) > 1 else 1.0
    dy = y[1] - y[0] if len(y) > 1 else 1.0
    ix = np.floor((pts[:, 0] - (x[0] - dx / 2)) / dx).astype(np.int64)
    iy = np.floor((pts[:, 1] - (y[0] - dy / 2)) / dy).astype(np.int64)
    ok = (ix >= 0) & (ix < len(x)) & (iy >= 0) & (iy < len(y))
    flat = ix[ok] * len(y) + iy[ok]
    count = np.bincount(flat, minlength=len(x) * len(y)).reshape(len(x), len(y))
    total = np.bincount(flat, weights=pts[ok, 2], minlength=len(x) * len(y)).reshape(len(x), len(y))
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return Gridded(np.asarray(x, float), np.asarray(y, float), z, count)


def grid_scan(scan: Scan, transform: Transform, x: np.ndarray, y: np.ndarray) -> tuple[Gridded, np.ndarray]:
    """The scan placed by `transform` and gridded on the nodes x, y; and its placed points. A raster whose placed
    cell centres fall on the nodes, one per cell (the run's own grid, or one aligned with it), is taken cell for
    cell, exactly; any other raster is densified first (`densify_raster`)."""
    cell = float(abs(x[1] - x[0])) if len(x) > 1 else 1.0
    if scan.raster is not None:
        placed = transform.apply(scan.points)
        if _on_nodes(placed, x, y):
            return grid_points(placed, x, y), placed
    placed = transform.apply(densify_raster(scan, cell))
    return grid_points(placed, x, y), placed


def _on_nodes(points: np.ndarray, x: np.ndarray, y: np.ndarray, tol: float = 1e-3) -> bool:
    """Every point within tol cells of a node of x, y (or off the grid), and no two in one cell."""
    if len(x) < 2 or len(y) < 2:
        return False
    dx, dy = x[1] - x[0], y[1] - y[0]
    u, v = (points[:, 0] - x[0]) / dx, (points[:, 1] - y[0]) / dy
    iu, iv = np.rint(u), np.rint(v)
    inside = (iu >= 0) & (iu < len(x)) & (iv >= 0) & (iv < len(y))
    if not inside.any() or np.max(np.abs(u - iu)[inside]) > tol or np.max(np.abs(v - iv)[inside]) > tol:
        return False
    flat = iu[inside].astype(np.int64) * len(y) + iv[inside].astype(np.int64)
    return len(np.unique(flat)) == len(flat)


def densify_raster(scan: Scan, cell: float) -> np.ndarray:
    """A raster's cell centres, or, when its cells are coarser than half the target cell, k x k points per raster cell
    interpolated bilinearly between its centre and its neighbours' (so a target cell at any angle to the raster gets
    points wherever the raster covers it). A point next to a nodata cell is nodata: nothing is made up beyond the
    raster's own cells."""
    if scan.raster is None or scan.cell is None or scan.cell <= 0.5 * cell:
        return scan.points
    from scipy.interpolate import RegularGridInterpolator

    z, xy = scan.raster
    k = int(math.ceil(scan.cell / (0.5 * cell)))
    offsets = (np.arange(k) + 0.5) / k - 0.5
    u = (np.arange(z.shape[0])[:, None] + offsets[None]).ravel()
    v = (np.arange(z.shape[1])[:, None] + offsets[None]).ravel()
    uu, vv = np.meshgrid(u, v, indexing="ij")
    interp = RegularGridInterpolator((np.arange(z.shape[0], dtype=float), np.arange(z.shape[1], dtype=float)), z,
                                     bounds_error=False, fill_value=np.nan)
    zz = interp(np.stack([uu.ravel(), vv.ravel()], axis=1))
    # (a point beyond the outer centres is NaN too: its cell still gets the points on the inner side)
    x, y = xy(uu.ravel(), vv.ravel())
    out = np.column_stack([x, y, zz])
    return out[np.isfinite(zz)]


# ----------------------------------------------------------------------------------------------- fitting
def _bilinear(x, y, z):
    """A heightmap as a function (points (N, 2) -> heights, NaN outside or on NaN) and its gradient."""
    from scipy.interpolate import RegularGridInterpolator

    interp = RegularGridInterpolator((x, y), z, bounds_error=False, fill_value=np.nan)
    gx, gy = np.gradient(z, x, y)
    grad = (RegularGridInterpolator((x, y), gx, bounds_error=False, fill_value=np.nan),
            RegularGridInterpolator((x, y), gy, bounds_error=False, fill_value=np.nan))
    return interp, grad


def _smoothed(z: np.ndarray, cell: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    sigma = max(1.0, RELIEF_SMOOTHING_M / cell)
    filled = np.where(np.isfinite(z), z, np.nanmean(z))
    return gaussian_filter(filled, sigma)


def relief_slope(x, y, z, centre: np.ndarray) -> float:
    """The weakest RMS slope of the smoothed terrain along x, along y and for a yaw about `centre` (yaw scaled by
    the terrain's radius of gyration, so all three read as slopes): how well the terrain holds a rigid fit."""
    cell = float(abs(x[1] - x[0])) if len(x) > 1 else 1.0
    zs = _smoothed(z, cell)
    gx, gy = np.gradient(zs, x, y)
    X, Y = np.meshgrid(x - centre[0], y - centre[1], indexing="ij")
    ok = np.isfinite(z)
    radius = math.sqrt(float(np.mean(X[ok] ** 2 + Y[ok] ** 2))) or 1.0
    cols = np.stack([gx[ok], gy[ok], (-Y[ok] * gx[ok] + X[ok] * gy[ok]) / radius], axis=1)
    return float(np.linalg.svd(cols / math.sqrt(len(cols)), compute_uv=False)[-1])


@dataclass
class FitResult:
    transform: Transform
    mode: str                # 'plane' | 'rigid'
    residual_rms_m: float    # over the inliers (the undisturbed ground)
    inlier_fraction: float
    points_used: int
    relief_slope: float

    def describe(self) -> dict:
        out = {"mode": self.mode, "fitted": ["z", "roll", "pitch"] + (["x", "y", "yaw"] if self.mode == "rigid" else []),
               "residual_rms_m": self.residual_rms_m, "inlier_fraction": self.inlier_fraction,
               "points_used": self.points_used, "relief_slope": self.relief_slope}
        return {**self.transform.describe(), **out}


def initial_guess(points: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> Transform:
    """No transform given: the scan's centre of extent onto the terrain's, its median height onto the terrain's."""
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    centre = (lo + hi) / 2
    target = np.array([(x[0] + x[-1]) / 2, (y[0] + y[-1]) / 2])
    dz = float(np.nanmedian(z) - np.median(points[:, 2]))
    return Transform(float(target[0] - centre[0]), float(target[1] - centre[1]), dz)


def fit_transform(points: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray, start: Transform,
                  mode: str = "auto", inlier_m: float = 0.03, seed: int = 0) -> FitResult:
    """Transform that lays the scan points on the reference heightmap (x, y, z[ix, iy], machine frame), from
    `start`. Robust: points off the reference (the dug area, the heave) are down-weighted (Cauchy loss), then points
    more than 3 robust sigmas (at least `inlier_m`) off are dropped and the fit repeated. mode: 'plane' fits z, roll
    and pitch (x, y, yaw stay as in `start`), 'rigid' all six, 'auto' rigid when the terrain has the relief to hold
    x, y and yaw (relief_slope >= MIN_RELIEF_SLOPE), else plane."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    if mode not in ("auto", "plane", "rigid"):
        raise UserError(f"--fit-transform: expected auto, plane or rigid, got {mode!r}")
    pts = np.asarray(points, float)
    if len(pts) > MAX_FIT_POINTS:  # (sorted first: the subset, and so the fit, do not depend on the file's order)
        pts = pts[np.lexsort(pts.T[::-1])]
        pts = pts[np.random.default_rng(seed).choice(len(pts), MAX_FIT_POINTS, replace=False)]
    c_scan = pts.mean(axis=0)
    local = pts - c_scan
    r0 = start.matrix()
    c0 = start.apply(c_scan[None])[0]
    cell = float(abs(x[1] - x[0])) if len(x) > 1 else 1.0
    slope = relief_slope(x, y, z, c0[:2])
    if mode == "auto":
        mode = "rigid" if slope >= MIN_RELIEF_SLOPE else "plane"
    interp, _grad = _bilinear(x, y, z)
    moved = start.apply(pts)
    first = moved[:, 2] - interp(moved[:, :2])
    if np.isfinite(first).any():  # the heights first: a robust loss has no slope to follow metres away
        c0[2] -= float(np.nanmedian(first))
    # a wide loss first (rigid: on the smoothed terrain, a wider basin), then the terrain itself, robustly
    zs = _smoothed(z, cell) if mode == "rigid" else z
    stages = [(zs, "soft_l1", 0.3), (z, "cauchy", inlier_m)]

    def unpack(p):
        # p: delta rotation vector (3) about the scan's centroid, applied after R0, and the centroid's position
        if mode == "plane":
            rot = Rotation.from_rotvec([p[0], p[1], 0.0]).as_matrix() @ r0
            centre = np.array([c0[0], c0[1], c0[2] + p[2]])
        else:
            rot = Rotation.from_rotvec(p[:3]).as_matrix() @ r0
            centre = c0 + p[3:]
        return rot, centre

    p = np.zeros(3 if mode == "plane" else 6)
    keep = np.ones(len(local), bool)
    lo, hi = np.array([min(x[0], x[-1]), min(y[0], y[-1])]), np.array([max(x[0], x[-1]), max(y[0], y[-1])])
    # a point on a hole in the terrain (NaN) counts as far off: never cheaper than lying on ground
    hole = OFF_TERRAIN_M
    for stage, (sz, loss, scale) in enumerate(stages + [(z, "linear", inlier_m)]):
        f = _bilinear(x, y, sz)[0]
        last = stage == len(stages)

        def residual(q, f=f, use=keep):
            rot, centre = unpack(q)
            moved = local[use] @ rot.T + centre
            # a point pushed off the grid is measured at the grid's edge plus the distance it has left by, so leaving
            # never costs less than staying (a residual of 0 there let the fit shed ground by sliding off it)
            inside = np.clip(moved[:, :2], lo, hi)
            out = np.hypot(*(moved[:, :2] - inside).T)
            r = moved[:, 2] - f(inside)
            return np.where(np.isfinite(r), np.copysign(np.abs(r) + out, r), hole)

        rot, centre = unpack(p)
        moved = local @ rot.T + centre
        on = np.isfinite(f(moved[:, :2]))
        if last:  # trim: drop what is clearly not undisturbed ground and refit plainly
            r = moved[:, 2] - f(moved[:, :2])
            med = np.nanmedian(r[on])
            sigma = 1.4826 * np.nanmedian(np.abs(r[on] - med))
            keep = on & (np.abs(r - med) <= max(3.0 * sigma, inlier_m))
        else:
            keep = on
        if keep.sum() < 3 * len(p):
            raise UserError(f"--fit-transform: only {int(keep.sum())} scan points fall on the run's terrain; give "
                            f"--transform x,y,z,yaw_deg close to the scan's placement")
        sol = least_squares(lambda q: residual(q, use=keep), p, loss=loss, f_scale=scale,
                            x_scale=np.full(len(p), 0.05))
        p = sol.x
    rot, centre = unpack(p)
    final = local[keep] @ rot.T + centre
    res = final[:, 2] - interp(final[:, :2])
    res = res[np.isfinite(res)]
    roll, pitch, yaw = Rotation.from_matrix(rot).as_euler("xyz")
    t = centre - rot @ c_scan
    result = Transform(float(t[0]), float(t[1]), float(t[2]), float(roll), float(pitch), float(yaw))
    return FitResult(result, mode, float(np.sqrt(np.mean(res ** 2))) if len(res) else float("nan"),
                     float(keep.mean()), int(len(local)), slope)

