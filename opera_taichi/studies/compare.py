"""`compare`: a run against a terrain scan, a joint log or another run; comparison.json, profile.csv and figures.

Terrain (all on the run's heightmap grid, the ground-only `z` of terrain_initial.npz / terrain_final.npz):
- the reference final surface is the scan (gridded at the run's cell size, in the machine frame) or the other run's
  final terrain; its initial surface is the scan taken before the dig, else the run's own initial terrain;
- the dig area: the cells where the run or the reference changed by more than `change_threshold` (m), grown by
  `margin_m`; volumes and errors are summed over it, so scan noise far from the dig adds nothing. Against a
  reference, the run's and the reference's volumes and depths are both taken over the part of the dig area the
  reference covers (`compared_area_m2`), so a partial scan is compared like for like; a reference that covers less
  than MIN_DIG_COVERAGE of the dig area is refused, less than WARN_DIG_COVERAGE gets a warning;
- a reference that differs from its initial surface by more than the threshold over the ground the run left
  undisturbed (median) is not placed vertically (every cell would count as dug) and is refused;
- cut / fill: the volume below / above the initial surface, sum of max(0, -dz) dA and max(0, dz) dA;
- max depth: the largest drop below the initial surface, and where; heave: the largest rise (the spoil beside
  the trench), where, and on which side of the trench as seen from the machine (left, right, front = beyond the
  trench, back = between the trench and the machine); the cells where the initial surface was a gap between grains
  (summary.grain_gaps, with the run's grain radius) are left out of it;
- the dig line runs from the machine's base through the centre of the run's cut (cut-weighted); profile.csv samples
  it.
Joints (a log with `t` and joints in rad or `_deg`, its columns naming no joint of the run left unread with a
warning; a ROS bag's sensor_msgs/JointState, or the other run's joints.csv), on their common time span resampled at
`JOINT_DT`:
- a log in degrees under radian names is refused: a joint with limits (boom, arm, bucket) that reaches beyond a full
  turn and far beyond the run; any rotating joint that moves faster than RATE_MARGIN x its actuator's limit (the run's
  machine description, read from the files its manifest names; a joint with a speed limit, so not a prismatic one). A
  joint that turns without limit (a swing, continuous in the URDF) has no bound: unwrapped over several turns, it is
  judged by its rate and by what it sweeps over the run's time span (SWEEP_FACTOR x the run's); a run against
  another run is not checked (its joints.csv is in radians); a log of such a joint is unwrapped (unwrap_swing) and
  put on the run's turn at the start of the common span. A run whose machine cannot be read gets the range check
  for every joint, with a warning;
- rmse_rad: RMS of run minus reference; lag_s: the shift that best aligns the two (cross-correlation of the
  mean-removed angles, positive = the run is late); rate_ratio: the 90th percentile of the run's |angular rate| over
  the reference's (0.5 = the run moves at half the real rate), both rated over the span they share once the
  reference is shifted by the lag: the same motion (a log longer than the run is rated over the part the run did).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..recorders import read_csv_columns, write_json
from ..summary import grain_gaps, grain_radius
from . import scan as scans

COMPARISON_FILE = "comparison.json"
PROFILE_FILE = "profile.csv"
JOINT_DT = 0.01            # s, resampling step of joint profiles
RATE_SMOOTHING_S = 0.3     # s: joint rates are differences over this of angles averaged over it (a 0.1 s average
                           # differentiated per sample read 0.2 deg of sensor noise as 15% more speed)
MAX_LAG_S = 5.0            # s, the largest lag searched
STILL_RATE = 1e-3          # rad/s: a reference joint this slow (90th percentile) stands still: no rate ratio
STILL_RANGE = math.radians(2.0)  # rad: a joint whose log moves less than this (5-95th percentile) stands still: its
                                 # rate and lag would be its sensor noise's (0.2 deg of noise read a ratio of 1e-4)
RATE_MARGIN = 3.0          # a joint a log shows moving faster than this many times its actuator's limit (the median
                           # while it moves) is not in rad/s: degrees read 57 x; a machine quicker than its catalogue
                           # figure stays well under
MOVING_SHARE = 0.5         # ...over the samples faster than this share of the limit: a still joint's sensor noise of
                           # 0.2 deg, read as rad, moves it at ~0.2 rad/s (a floor of 0.24 rad/s for the swing let a
                           # log in degrees that stood still for most of it through)
SWEEP_FACTOR = 20.0        # a swing's log sweeping more than this many times the run's angle over the run's span
                           # (and more than a turn) is in degrees (57 x); the same motion sweeps about 1 x
MIN_MOVING_S = 1.0         # s: a joint that moves for less than this in the log gives no evidence of its units
CLOCK_TIME_S = 1e6         # s: a CSV log whose t starts later than this (11.6 days) holds clock time (epoch seconds)
FAR_FACTOR = 50.0          # a scan this many times larger (or smaller) than the run's terrain is in another unit
MIN_RELIEF_M = 0.1          # the run's terrain's height spread, at least, that a scan's is held against (a flat bed)
MAX_VERTICAL_OFFSET_M = 2.0  # a placed scan this far above/below the run's terrain has not been placed
MISPLACED_SHARE = 0.8      # a scan off the run's undisturbed ground by more than the change threshold on this share of
                           # it, one way, is misplaced vertically
MIN_DIG_COVERAGE = 0.5     # a reference covering less of the dig area than this is refused...
WARN_DIG_COVERAGE = 0.9    # ...less than this gets a warning (its volumes miss part of the dig)
FIT_WARN_RESIDUAL_M = 0.05  # a fitted placement with a larger residual (good fits: ~0.02 m on DEM grain)...
FIT_WARN_INLIERS = 0.5      # ...or fewer inliers than this (good fits: ~0.75) probably went wrong
# the top-level keys comparison.json can hold (a study's compare.<key> metric is checked against them before any run;
# test_studies_compare checks them against what compare writes)
SURFACE_KEYS = ("cut_volume_m3", "fill_volume_m3", "max_depth_m", "max_depth_xy_m", "cut_centre_xy_m",  # of
                "heave_height_m", "heave_xy_m", "heave_side", "heave_offset_m")  # surface_metrics: run, reference
TERRAIN_KEYS = ("cell_m", "change_threshold_m", "margin_m", "dig_area_m2", "dig_line", *SURFACE_KEYS)  # any run
REFERENCE_TERRAIN_KEYS = ("compared_area_m2", *(f"reference_{k}" for k in SURFACE_KEYS), "terrain_rmse_m",
                          "terrain_bias_m", "terrain_max_abs_error_m", "reference_empty_cells",
                          "reference_coverage_of_dig_area", "cut_volume_relative_error", "fill_volume_relative_error",
                          "max_depth_relative_error", "heave_height_relative_error", "max_depth_position_error_m")
JOINT_KEYS = ("joints", "joints_common_span_s", "joints_rmse_rad", "joints_lag_s", "joints_rate_ratio")
OUTPUT_FILES = (COMPARISON_FILE, PROFILE_FILE, "comparison_terrain.png", "comparison_profile.png",
                "comparison_joints.png")  # all a compare writes: replaced together, never left from an earlier one


def comparison_keys(reference: dict) -> list[str]:
    """The top-level keys comparison.json can hold for a study's `reference` (its keys terrain, terrain_before,
    joints, against): a run's own terrain block always (a run with soil), the reference's and the joints' blocks
    when the reference has them."""
    keys = ["run", "warnings", *TERRAIN_KEYS]
    if "terrain" in reference or "against" in reference:
        keys += REFERENCE_TERRAIN_KEYS
    if "terrain" in reference:
        keys += ["terrain_scan", "transform"] + (["terrain_scan_before"] if "terrain_before" in reference else [])
    if "against" in reference:
        keys.append("against")
    if "joints" in reference or "against" in reference:
        keys += [*JOINT_KEYS, *(["joint_log"] if "joints" in reference else [])]
    return keys


# ----------------------------------------------------------------------------------------------- run folders
def read_terrain(path: Path, key: str) -> dict:
    if not path.is_file():
        raise UserError(f"{key}: {path.parent} has no {path.name} (a run folder of a run with soil?)")
    try:
        with np.load(path) as f:
            return {k: np.asarray(f[k], float) for k in ("x", "y", "z")}
    except (OSError, ValueError, KeyError) as exc:
        raise UserError(f"{key}: {path}: unreadable terrain file ({type(exc).__name__}: {exc})") from None


def run_folder(path, key: str) -> Path:
    path = Path(path)
    if not (path / "manifest.json").is_file():
        raise UserError(f"{key}: {path} is not a run folder (no manifest.json)")
    return path


def _manifest(run_dir: Path) -> dict:
    try:
        data = json.loads((run_dir / "manifest.json").read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def machine_pose(run_dir: Path) -> tuple[np.ndarray | None, float]:
    """(base xy, yaw) of the run's (first) machine from its manifest; (None, 0) without a machine."""
    scene = _manifest(run_dir).get("scene") or {}
    machine = scene.get("machine") or (scene.get("machines") or [None])[0]
    if not machine:
        return None, 0.0
    pose = machine.get("base_pose") or {}
    xyz = pose.get("xyz") or [0.0, 0.0, 0.0]
    return np.array(xyz[:2], float), float(pose.get("yaw") or 0.0)


# ----------------------------------------------------------------------------------------------- terrain
def dig_area(changes, threshold: float, margin_cells: int) -> np.ndarray:
    """Cells where any change map exceeds the threshold, grown by margin_cells (a disc)."""
    from scipy.ndimage import distance_transform_edt

    mask = np.zeros(changes[0].shape, bool)
    for dz in changes:
        mask |= np.nan_to_num(np.abs(dz), nan=0.0) > threshold
    if margin_cells > 0 and mask.any():  # (the distance to the nearest changed cell: linear in the grid's size)
        mask = distance_transform_edt(~mask) <= margin_cells
    return mask


def surface_metrics(z0, z1, x, y, mask, base_xy, yaw, gaps=None) -> dict:
    """Cut, fill, max depth and heave of z1 against z0 over the mask (NaN cells skipped); the heave leaves out `gaps`
    (summary.grain_gaps of z0: cells where the bed floor showed through between grains, one of which rolled in)."""
    cell = abs((x[1] - x[0]) * (y[1] - y[0])) if len(x) > 1 and len(y) > 1 else 0.0
    dz = np.where(mask, z1 - z0, np.nan)
    valid = np.isfinite(dz)
    out = {"cut_volume_m3": float(np.sum(np.maximum(0.0, -dz[valid])) * cell),
           "fill_volume_m3": float(np.sum(np.maximum(0.0, dz[valid])) * cell),
           "max_depth_m": 0.0, "max_depth_xy_m": None, "cut_centre_xy_m": None, "heave_height_m": 0.0,
           "heave_xy_m": None,
           "heave_side": None, "heave_offset_m": None}
    if not valid.any():
        return out
    gx, gy = np.meshgrid(x, y, indexing="ij")
    filled = np.where(valid, dz, 0.0)
    i = np.unravel_index(int(np.argmin(filled)), dz.shape)
    if filled[i] < 0:
        out.update(max_depth_m=float(-filled[i]), max_depth_xy_m=[float(gx[i]), float(gy[i])])
        cut = np.maximum(0.0, -filled)
        out["cut_centre_xy_m"] = [float(np.sum(cut * gx) / cut.sum()), float(np.sum(cut * gy) / cut.sum())]
    risen = filled if gaps is None else np.where(gaps, 0.0, filled)
    k = np.unravel_index(int(np.argmax(risen)), dz.shape)
    if risen[k] > 0:
        out.update(heave_height_m=float(risen[k]), heave_xy_m=[float(gx[k]), float(gy[k])])
        cut = np.maximum(0.0, -filled)
        if cut.sum() > 0:  # side of the heave from the trench's centre, in the machine's frame
            centre = np.array([np.sum(cut * gx), np.sum(cut * gy)]) / cut.sum()
            d = np.array([gx[k], gy[k]]) - centre
            c, s = math.cos(yaw), math.sin(yaw)
            fwd, left = c * d[0] + s * d[1], -s * d[0] + c * d[1]
            side = ("left" if left > 0 else "right") if abs(left) > abs(fwd) else ("front" if fwd > 0 else "back")
            out.update(heave_side=side, heave_offset_m=[float(fwd), float(left)])
    return out


def dig_line(x, y, depth_xy, base_xy, yaw) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origin, unit direction, s) of the dig line: from the machine's base through the deepest point (the
    machine's heading through the deepest point when it stands on it, x through the middle without either)."""
    heading = np.array([math.cos(yaw), math.sin(yaw)])
    if depth_xy is None:
        origin = np.array([x[0], (y[0] + y[-1]) / 2]) if base_xy is None else base_xy
        direction = heading
    else:
        origin = np.asarray(depth_xy, float)
        d = origin - base_xy if base_xy is not None else heading
        direction = d / np.linalg.norm(d) if np.linalg.norm(d) > 1e-6 else heading
    # the part of the line inside the grid
    lo, hi = np.array([x[0], y[0]]), np.array([x[-1], y[-1]])
    ts = []
    for a in range(2):
        if abs(direction[a]) > 1e-12:
            ts += [(lo[a] - origin[a]) / direction[a], (hi[a] - origin[a]) / direction[a]]
    ts = np.sort(ts)
    t0, t1 = (ts[1], ts[2]) if len(ts) == 4 else (ts[0], ts[1])
    cell = abs(x[1] - x[0]) if len(x) > 1 else 0.05
    s = np.arange(t0, t1 + 1e-9, cell)
    return origin, direction, s


def sample(x, y, z, points) -> np.ndarray:
    from scipy.interpolate import RegularGridInterpolator

    return RegularGridInterpolator((x, y), z, bounds_error=False, fill_value=np.nan)(points)


def place_scan(scan: "scans.Scan", grid: dict, transform: "scans.Transform | None", fit: str | None,
               fit_against: dict | None = None, key: str = "--terrain"):
    """The scan on the run's grid: (Gridded, FitResult | None, Transform). Checks units and placement first."""
    x, y, z_run = grid["x"], grid["y"], grid["z"]
    pts = scans.densify_raster(scan, abs(x[1] - x[0]))
    ext_scan = np.ptp(pts[:, :2], axis=0)
    ext_run = np.array([np.ptp(x), np.ptp(y)]) + abs(x[1] - x[0])
    size_s, size_r = float(np.max(ext_scan)), float(np.max(ext_run))
    what = f"{scan.path.name} spans {ext_scan[0]:.4g} x {ext_scan[1]:.4g} (x, y) and {np.ptp(pts[:, 2]):.4g} in z"
    if size_s > FAR_FACTOR * size_r:
        raise UserError(f"{key}: {what}, {size_s / size_r:.0f} x the run's {ext_run[0]:.3g} x {ext_run[1]:.3g} m "
                        f"terrain: a scan in millimetres or another unit? give it in metres")
    if size_s < size_r / FAR_FACTOR:
        raise UserError(f"{key}: {what}, 1/{size_r / max(size_s, 1e-12):.0f} of the run's {ext_run[0]:.3g} x "
                        f"{ext_run[1]:.3g} m terrain: a scan in kilometres or another unit? give it in metres")
    spread_z = float(np.subtract(*np.percentile(pts[:, 2], [99, 1])))
    if spread_z > size_s:  # soil cannot stand steeper than 45 deg across a whole scan
        raise UserError(f"{key}: {what}: its heights span more than it is wide (1st to 99th percentile "
                        f"{spread_z:.4g}): heights in centimetres or another unit? give them in metres")
    fit_result = None
    if fit:
        start = transform or scans.initial_guess(pts, x, y, z_run)
        ref = fit_against or grid
        fit_result = scans.fit_transform(pts, ref["x"], ref["y"], ref["z"], start, mode=fit)
        transform = fit_result.transform
    transform = transform or scans.Transform()
    gridded, placed = scans.grid_scan(scan, transform, x, y)
    common = np.isfinite(gridded.z) & np.isfinite(z_run)
    lo, hi = placed.min(axis=0), placed.max(axis=0)
    if common.sum() < max(3, 0.05 * min(z_run.size, len(placed))):
        raise UserError(f"{key}: {scan.path.name} is far from the run: placed in the machine frame its points lie at "
                        f"x {lo[0]:.4g}..{hi[0]:.4g}, y {lo[1]:.4g}..{hi[1]:.4g}, z {lo[2]:.4g}..{hi[2]:.4g} m, the "
                        f"run's terrain covers x {x[0]:.3g}..{x[-1]:.3g}, y {y[0]:.3g}..{y[-1]:.3g} m "
                        f"({int(common.sum())} common cells); give --transform x,y,z,yaw_deg or --fit-transform")
    spread_s, spread_r = (float(np.subtract(*np.percentile(v[common], [99, 1]))) for v in (gridded.z, z_run))
    if spread_s > FAR_FACTOR * max(spread_r, MIN_RELIEF_M):
        raise UserError(f"{key}: {scan.path.name} spans {spread_s:.4g} in height over the run's terrain (1st to 99th "
                        f"percentile over {int(common.sum())} common cells), {spread_s / max(spread_r, MIN_RELIEF_M):.0f}"
                        f" x the run's {spread_r:.3g} m: heights in centimetres or another unit? give them in metres")
    offset = float(np.median(gridded.z[common] - z_run[common]))
    if abs(offset) > MAX_VERTICAL_OFFSET_M:
        raise UserError(f"{key}: {scan.path.name} lies {abs(offset):.3g} m {'above' if offset > 0 else 'below'} the run's "
                        f"terrain (median over {int(common.sum())} common cells); give --transform with its z or "
                        f"--fit-transform")
    return gridded, fit_result, transform


def terrain_comparison(run_dir: Path, *, reference_final: dict | None, reference_initial: dict | None,
                       label: str, change_threshold: float, margin_m: float, key: str = "--terrain",
                       warnings: list | None = None, fitted: bool = False) -> tuple[dict, dict]:
    """The terrain block of comparison.json and the arrays the figures need. UserError (naming `key`) when the
    reference cannot be compared: not placed vertically, no dig area, too little of the dig area covered; a partial
    cover is appended to `warnings`."""
    initial = read_terrain(run_dir / "terrain_initial.npz", "RUN_DIR")
    final = read_terrain(run_dir / "terrain_final.npz", "RUN_DIR")
    x, y, z0, z1 = initial["x"], initial["y"], initial["z"], final["z"]
    base_xy, yaw = machine_pose(run_dir)
    changes = [z1 - z0]
    ref0 = ref1 = None
    if reference_final is not None:
        ref1 = reference_final
        ref0 = reference_initial if reference_initial is not None else z0
        changes.append(ref1 - ref0)
    margin_cells = int(round(margin_m / abs(x[1] - x[0])))
    mask = dig_area(changes, change_threshold, margin_cells)
    cell = abs((x[1] - x[0]) * (y[1] - y[0]))
    out = {"cell_m": float(abs(x[1] - x[0])), "change_threshold_m": change_threshold, "margin_m": margin_m,
           "dig_area_m2": float(mask.sum() * cell)}
    compared = mask
    if ref1 is not None:
        covered = np.isfinite(ref1) & np.isfinite(ref0)
        # the ground the run left alone: there the reference must match its initial surface, or it is misplaced
        still = covered & ~dig_area(changes[:1], change_threshold, margin_cells)
        if still.sum() >= 10:
            dz = (ref1 - ref0)[still]
            offset = float(np.median(dz))
            # misplaced: nearly all that ground off by more than the threshold, the same way (a field dig wider than
            # the run's, or its spoil, puts part of the reference's trench there: not a misplacement)
            shifted = max(np.mean(dz > change_threshold), np.mean(dz < -change_threshold))
            if shifted > MISPLACED_SHARE:
                initial = "the run's initial terrain" if reference_initial is None else "its scan before the dig"
                raise UserError(
                    f"{key}: {label} lies {abs(offset):.3g} m {'above' if offset > 0 else 'below'} {initial} "
                    f"over {100 * shifted:.0f}% of the ground the run left undisturbed (median over "
                    f"{int(still.sum())} cells), more than "
                    f"--change-threshold {change_threshold:g} m: every cell would count as dug; "
                    + ("the fitted placement left it there: give --transform, or --terrain-before (a scan before "
                       "the dig fits on undisturbed ground)" if fitted else
                       "place it with --transform (its z) or --fit-transform, or give --terrain-before"))
        if not mask.any():
            largest = max(float(np.nanmax(np.abs(dz), initial=0.0)) for dz in changes)
            raise UserError(f"--change-threshold: neither the run nor {label} changed by more than "
                            f"{change_threshold:g} m anywhere (largest change {largest:.3g} m): no dig area to "
                            f"compare; give a smaller --change-threshold")
        compared = mask & covered
        coverage = float(compared.sum() / mask.sum())
        if coverage < WARN_DIG_COVERAGE:
            gx, gy = np.meshgrid(x, y, indexing="ij")
            where = (f"the dig area spans x {gx[mask].min():.3g}..{gx[mask].max():.3g}, y {gy[mask].min():.3g}.."
                     f"{gy[mask].max():.3g} m ({mask.sum() * cell:.3g} m2)")
            if coverage < MIN_DIG_COVERAGE:
                raise UserError(f"{key}: {label} covers {100 * coverage:.0f}% of the dig area ({where}); a comparison "
                                f"needs at least {100 * MIN_DIG_COVERAGE:.0f}%: give a scan of the dig or check its "
                                f"placement and its units (metres; a scan in feet spreads 3.28 x too wide)")
            if warnings is not None:
                _warn(warnings, f"{key}: {label} covers only {100 * coverage:.0f}% of the dig area ({where}): "
                                f"volumes and depths are compared over the covered part only")
        out["compared_area_m2"] = float(compared.sum() * cell)
    radius = grain_radius(None, _manifest(run_dir))
    run = surface_metrics(z0, z1, x, y, compared, base_xy, yaw, grain_gaps(z0, abs(x[1] - x[0]), radius))
    out.update(run)
    arrays = dict(x=x, y=y, z0=z0, z1=z1, mask=mask, ref0=ref0, ref1=ref1, label=label)
    if ref1 is not None:
        ref = surface_metrics(ref0, ref1, x, y, compared, base_xy, yaw, grain_gaps(ref0, abs(x[1] - x[0]), radius))
        out.update({f"reference_{k}": v for k, v in ref.items()})
        both = mask & np.isfinite(ref1) & np.isfinite(z1)
        err = (z1 - ref1)[both]
        covered = mask & np.isfinite(ref1)
        out.update(
            terrain_rmse_m=float(np.sqrt(np.mean(err ** 2))) if err.size else None,
            terrain_bias_m=float(np.mean(err)) if err.size else None,
            terrain_max_abs_error_m=float(np.max(np.abs(err))) if err.size else None,
            reference_empty_cells=int(np.sum(~np.isfinite(ref1))),
            reference_coverage_of_dig_area=float(covered.sum() / mask.sum()) if mask.any() else None)
        for name in ("cut_volume_m3", "fill_volume_m3", "max_depth_m", "heave_height_m"):
            r = ref[name]
            out[name.replace("_m3", "").replace("_m", "") + "_relative_error"] = \
                (run[name] - r) / r if r else None
        if run["max_depth_xy_m"] and ref["max_depth_xy_m"]:
            out["max_depth_position_error_m"] = float(np.hypot(*np.subtract(run["max_depth_xy_m"],
                                                                             ref["max_depth_xy_m"])))
    # the dig line runs through the middle of the run's whole cut (not only the part a partial scan covers)
    depth_xy = surface_metrics(z0, z1, x, y, mask, base_xy, yaw)["cut_centre_xy_m"]
    if depth_xy is None and ref1 is not None:
        depth_xy = ref["cut_centre_xy_m"]
    origin, direction, s = dig_line(x, y, depth_xy, base_xy, yaw)
    pts = origin[None] + s[:, None] * direction[None]
    profile = {"s_m": s, "x_m": pts[:, 0], "y_m": pts[:, 1], "initial_z_m": sample(x, y, z0, pts),
               "run_z_m": sample(x, y, z1, pts)}
    if ref1 is not None:
        profile["reference_z_m"] = sample(x, y, ref1, pts)
        if reference_initial is not None:
            profile["reference_initial_z_m"] = sample(x, y, ref0, pts)
    out["dig_line"] = {"origin_xy_m": origin.tolist(), "direction_xy": direction.tolist()}
    arrays["profile"] = profile
    arrays["dig_line_origin"] = origin
    return out, arrays


# ----------------------------------------------------------------------------------------------- joints
def read_joint_log(path, key: str = "--joints", joints=None,
                   warnings: list | None = None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(t, {joint: rad}) of a joint log: a CSV (`t` plus `<joint>` rad or `<joint>_deg`; a run's joints.csv too) or
    a ROS bag (ROS 1 .bag, ROS 2 folder or .mcap/.db3) with sensor_msgs/JointState messages. `joints`: the run's
    joint names; a CSV's columns that name none of them (a `mode` column of text) are not read, with a warning."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{key}: {path}: file not found")
    if path.is_dir() or path.suffix.lower() in (".bag", ".mcap", ".db3"):
        return _read_bag(path, key)
    from ..scene import CsvProblem, read_motion_csv

    try:
        kept = _joint_columns_only(path, key, joints, warnings)
        if kept is None:
            times, angles = read_motion_csv(path)
        else:
            import tempfile

            with tempfile.TemporaryDirectory() as tmp:
                (Path(tmp) / path.name).write_text(kept, encoding="utf-8")
                times, angles = read_motion_csv(Path(tmp) / path.name)
    except CsvProblem as exc:
        raise UserError(f"{key}: {path}: {exc}") from None
    except OSError as exc:
        raise UserError(f"{key}: {path}: cannot read ({exc.strerror})") from None
    if not angles:
        raise UserError(f"{key}: {path}: no joint columns besides t")
    t = np.asarray(times, float)
    if t[0] > CLOCK_TIME_S:  # clock time: compared from its first sample, as a bag's times are
        t = t - t[0]
    return t, {j: np.asarray(v, float) for j, v in angles.items()}


def _joint_columns_only(path: Path, key: str, joints, warnings: list | None) -> str | None:
    """The CSV's text with t and the columns of the run's `joints` only (scene.read_motion_csv reads every column:
    a log's `mode` column of text was refused), and a warning naming the others; None to read the file as it is
    (nothing to leave out, no joints known, or a problem read_motion_csv names: size, encoding, no t)."""
    import csv
    import io

    from ..scene import MAX_CSV_BYTES

    if joints is None or path.stat().st_size > MAX_CSV_BYTES:
        return None
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError:
        return None
    try:
        rows = [row for row in csv.reader(text.splitlines()) if row and any(c.strip() for c in row)]
    except csv.Error:  # (a cell over csv's field limit, a stray quote: read_motion_csv names it)
        return None
    header = [c.strip() for c in rows[0]] if rows else []
    if "t" not in header:
        return None
    recorded = any(n.endswith(".q") for n in header)  # a run's joints.csv: its other <joint>.* columns go unread
    names = {}
    for i, n in enumerate(header):
        if n == "t" or (recorded and "." in n and not n.endswith(".q")):
            continue
        base = n[:-2] if recorded and n.endswith(".q") else n
        names[i] = base[:-4] if base.endswith("_deg") else base
    ignored = [header[i] for i, j in names.items() if j not in joints]
    if not ignored:
        return None
    if len(ignored) == len(names):
        raise UserError(f"{key}: {path} names no joint of the run (run: {', '.join(joints)}; log: "
                        f"{', '.join(header[i] for i in names)})")
    _warn(warnings if warnings is not None else [],
          f"{key}: {path.name}: column{'s' * (len(ignored) > 1)} {', '.join(ignored)} name{'s' * (len(ignored) == 1)} "
          f"no joint of the run ({', '.join(joints)}): not read")
    keep = [i for i, n in enumerate(header) if n not in ignored]
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    for line, row in enumerate(rows, start=1):
        if len(row) != len(header):  # as read_motion_csv counts and says it, for the whole row
            raise UserError(f"{key}: {path}: line {line}: expected {len(header)} fields, got {len(row)}")
        writer.writerow([row[i] for i in keep])
    return out.getvalue()


def run_joint_names(run_dir: Path) -> list[str] | None:
    """The joints of a run's joints.csv (its `<joint>.q` columns), from its header; None without one."""
    import csv

    try:
        with open(run_dir / "joints.csv", newline="", encoding="utf-8") as fh:
            header = next(csv.reader(fh), [])
    except (OSError, UnicodeDecodeError):
        return None
    names = [n[:-2] for n in header if n.endswith(".q")]
    return names or None


def _read_bag(path: Path, key: str):
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise UserError(f"{key}: {path}: reading ROS bags needs rosbags (pip install 'opera-taichi[studies]')") \
            from None
    rows: dict[str, list] = {}
    times: list[float] = []
    try:
        # a file of a ROS 2 bag folder (beside its metadata.yaml) opens as the folder; a run's own run.mcap alone
        in_folder = path.suffix.lower() in (".mcap", ".db3") and (path.parent / "metadata.yaml").is_file()
        bag_paths = [path.parent if in_folder else path]
        if not in_folder and path.name in ("run.mcap", "run.bag"):  # a run's bag, in parts with checkpoints
            from ..ros.bag import bag_parts

            bag_paths = bag_parts(path.parent, path.suffix) or bag_paths
        from rosbags.typesys import Stores, get_typestore

        # a bag without its message definitions (ROS 2 before Iron) reads with the standard ones
        with AnyReader(bag_paths, default_typestore=get_typestore(Stores.LATEST)) as reader:
            conns = [c for c in reader.connections if c.msgtype.endswith("JointState")]
            if not conns:
                found = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
                raise UserError(f"{key}: {path}: no sensor_msgs/JointState topic (topics: "
                                f"{', '.join(found)[:200] or 'none'})")
            named = [c for c in conns if c.topic.endswith("joint_states")] or conns
            topic = named[0].topic
            for conn, stamp, raw in reader.messages(connections=[c for c in named if c.topic == topic]):
                msg = reader.deserialize(raw, conn.msgtype)
                times.append(stamp * 1e-9)
                for name, q in zip(msg.name, msg.position):
                    rows.setdefault(name, []).append((len(times) - 1, float(q)))
    except UserError:
        raise
    except Exception as exc:  # noqa: BLE001 - a broken bag
        raise UserError(f"{key}: {path}: cannot read the bag ({type(exc).__name__}: {exc})") from None
    t = np.asarray(times) - (times[0] if times else 0.0)
    out = {}
    for name, vals in rows.items():
        idx = np.array([i for i, _ in vals])
        out[name] = np.interp(t, t[idx], np.array([q for _, q in vals]))
    if len(t) < 2 or not out:
        raise UserError(f"{key}: {path}: fewer than two joint-state messages")
    return t, out


def run_joints(run_dir: Path, key: str = "RUN_DIR") -> tuple[np.ndarray, dict[str, np.ndarray]]:
    path = run_dir / "joints.csv"
    if not path.is_file():
        raise UserError(f"{key}: {run_dir} has no joints.csv (a run without a machine?)")
    cols = read_csv_columns(path)
    if not cols:
        raise UserError(f"{key}: {path}: empty (a run that ended before its first rows were written?)")
    try:
        t = np.asarray(cols["t"], float)
        joints = {name[:-2]: np.asarray(v, float) for name, v in cols.items() if name.endswith(".q")}
    except (KeyError, ValueError):
        raise UserError(f"{key}: {path}: not a run's joints.csv (no t and <joint>.q columns of numbers)") from None
    if len(t) < 2 or not joints:
        raise UserError(f"{key}: {path}: fewer than two rows of joint angles (a run that ended at once?)")
    return t, joints


def machine_joints(run_dir: Path) -> tuple[dict | None, str | None]:
    """({joints.csv column prefix: JointSpec}, None) of the run's machines, from the URDF and config its manifest's
    scene names (with the scene's actuator overrides); (None, why) when they cannot be read (a run folder moved to
    another install, a manifest without a scene)."""
    from ..machine_description import description_source, joint_specs

    try:
        manifest = json.loads((run_dir / "manifest.json").read_text())
        scene = manifest.get("scene") or {}
        entries = [scene["machine"]] if scene.get("machine") else list(scene.get("machines") or [])
        names = list(manifest.get("machines") or [])
        out = {}
        for i, m in enumerate(entries):
            specs = joint_specs(*description_source(m))
            if len(entries) > 1:  # joints.csv's columns are <machine>.<joint> with several machines
                name = names[i] if i < len(names) else m.get("name")
                if not name:
                    continue
                specs = {f"{name}.{j}": v for j, v in specs.items()}
            out.update(specs)
    except UserError as exc:
        return None, str(exc)
    except (OSError, ValueError, AttributeError, TypeError, KeyError) as exc:
        return None, f"{run_dir / 'manifest.json'}: no machine in its scene ({type(exc).__name__}: {exc})"
    return out, None


def unwrap_swing(q: np.ndarray) -> np.ndarray:
    """A swing's log unwrapped. Within one turn of values (a log wrapped to +-pi, whatever it does at the wrap:
    parked on it with noise, or a wrap resampled over two samples) numpy's unwrap; a log in degrees there moves less
    than 6.3 deg, never a step of half a turn. A log spanning more than a turn is unwrapped already or in degrees:
    only its isolated steps of about a turn are wraps (_unwrap_isolated)."""
    q = np.asarray(q, float)
    if q.size and float(np.ptp(q)) <= 2 * math.pi + 1e-6:
        return np.unwrap(q)
    return _unwrap_isolated(q)


def _unwrap_isolated(q: np.ndarray) -> np.ndarray:
    """q with its isolated steps of about a turn taken out: a swing logged wrapped to +-pi steps 2 pi in one sample
    between small steps (2 pi in 0.3 s reads 21 rad/s). A log in degrees stepping 6 deg a sample steps about as much
    in the samples beside it (a swing cannot start or stop within a sample): it keeps its steps."""
    d = np.diff(q)
    if d.size < 2:
        return q
    a = np.abs(d)
    beside = np.maximum(np.r_[0.0, a[:-1]], np.r_[a[1:], 0.0])
    wrap = (np.abs(a - 2 * math.pi) < math.pi / 2) & (beside < a / 4)
    if not wrap.any():
        return q
    return np.r_[q[0], q[0] + np.cumsum(np.where(wrap, d - np.sign(d) * 2 * math.pi, d))]


def moving_rate(t: np.ndarray, q: np.ndarray, floor: float) -> tuple[float, float]:
    """(median |rate| over the samples faster than floor, seconds of them) of a log's joint, rated as the comparison
    rates it (RATE_SMOOTHING_S) on a regular grid (at most 2e6 samples: a long log in milliseconds stays cheap)."""
    span = float(t[-1] - t[0])
    dt = max(JOINT_DT, span / 2e6)
    grid = np.arange(t[0], t[-1] + 1e-12, dt)
    rate = _rate(np.interp(grid, t, q), max(1, int(round(RATE_SMOOTHING_S / dt))), dt)
    fast = rate[rate > floor]
    return (float(np.median(fast)) if fast.size else 0.0), fast.size * dt


def check_units(j: str, t_ref, q_ref, t_run, q_run, spec, label: str) -> None:
    """UserError when the log's joint j reads as degrees under a radian name: a joint with limits (or of unknown
    kind) beyond a full turn and far beyond the run's angles; a revolute joint of known speed limit moving faster
    than RATE_MARGIN x that limit. A joint that turns without limit (a swing) has no bound: unwrapped over several
    turns, 7 rad is a turn and a bit, not 7 degrees; over the run's time span it sweeps what the run does, where in
    degrees it sweeps 57 x (beyond a turn), however slowly."""
    turns = spec is not None and spec.turns
    if not turns:
        # a log in degrees under radian names reads about 57 x the run's angles, beyond a full turn
        big, run_big = float(np.max(np.abs(q_ref))), float(np.max(np.abs(q_run)))
        if big > max(2 * math.pi, 3 * run_big + 1.0):
            raise UserError(f"--joints: {label}: {j} reaches {big:.4g} rad (the run at most {run_big:.3g} rad): "
                            f"a log in degrees? name its column {j}_deg")
    if spec is not None and spec.type != "prismatic" and spec.max_speed:
        rate, moving_s = moving_rate(t_ref, unwrap_swing(q_ref) if turns else q_ref, MOVING_SHARE * spec.max_speed)
        if moving_s >= MIN_MOVING_S and rate > RATE_MARGIN * spec.max_speed:
            raise UserError(f"--joints: {label}: {j} moves at {rate:.4g} rad/s (median over the {moving_s:.3g} s it "
                            f"moves), {rate / spec.max_speed:.0f} x the machine's limit of {spec.max_speed:.3g} "
                            f"rad/s: a log in degrees? name its column {j}_deg (or is its t not in seconds?)")
    span = (t_ref >= t_run[0]) & (t_ref <= t_run[-1])
    if turns and span.sum() >= 2:  # too slow for the rate check, a swing in degrees still sweeps 57 x the run's
        swept, run_swept = float(np.ptp(unwrap_swing(q_ref[span]))), float(np.ptp(q_run))
        if swept > max(2 * math.pi, SWEEP_FACTOR * run_swept + 1.0):
            raise UserError(f"--joints: {label}: {j} sweeps {swept:.4g} rad over the run's {t_run[0]:.4g}-"
                            f"{t_run[-1]:.4g} s (the run {run_swept:.3g} rad): a log in degrees? name its column "
                            f"{j}_deg")


def _smooth(v: np.ndarray, n: int) -> np.ndarray:
    if n <= 1:
        return v
    return np.convolve(np.pad(v, (n // 2, n - 1 - n // 2), mode="edge"), np.ones(n) / n, mode="valid")


def _rate(v: np.ndarray, n: int, dt: float = JOINT_DT) -> np.ndarray:
    """|dv/dt| of v sampled every dt, as the difference over n samples of v averaged over n samples (the noise of a
    per-sample derivative is what it measures otherwise)."""
    sm = _smooth(v, n)
    if len(sm) <= n:
        return np.abs(np.gradient(sm, dt)) if len(sm) > 1 else np.zeros_like(sm)
    return np.abs(sm[n:] - sm[:-n]) / (n * dt)


def best_lag(a: np.ndarray, b: np.ndarray, max_lag: int) -> int:
    """The shift k (samples) with a[i + k] best matching b[i]: the largest correlation coefficient over the
    overlapping parts (normalised per shift, so a short overlap is not favoured or penalised). k > 0: a is late."""
    best, lag = -np.inf, 0
    n = len(a)
    for k in range(-max_lag, max_lag + 1):
        x, y = (a[k:], b[:n - k]) if k >= 0 else (a[:n + k], b[-k:])
        if len(x) < 3 or np.ptp(x) == 0 or np.ptp(y) == 0:
            continue
        r = np.corrcoef(x, y)[0, 1]
        if r > best + 1e-12 or (abs(r - best) <= 1e-12 and abs(k) < abs(lag)):
            best, lag = r, k
    return lag


def aligned_rates(t_run, q_run, t_ref, q_ref, lag_s: float, n_smooth: int):
    """(run's |rate|, reference's |rate|) resampled at JOINT_DT over the span both cover once the reference is
    shifted by lag_s (its t + lag_s: a lag > 0, a late run, moves the reference later); None when that span is too
    short to rate."""
    t0, t1 = max(t_run[0], t_ref[0] + lag_s), min(t_run[-1], t_ref[-1] + lag_s)
    t = np.arange(t0, t1 + 1e-12, JOINT_DT)
    if len(t) <= 2 * n_smooth:
        return None
    a, b = np.interp(t, t_run, q_run), np.interp(t, np.asarray(t_ref) + lag_s, q_ref)
    return _rate(a, n_smooth), _rate(b, n_smooth)


def joint_comparison(t_run, run: dict, t_ref, ref: dict, ref_label: str,
                     warnings: list | None = None, specs: dict | None = None,
                     check: bool = True) -> tuple[dict, dict]:
    """Per-joint rmse and lag on the common time span, rate ratio on the span shared once aligned by the lag (the
    common one for a joint without a lag); the arrays for the figure. A log in other units
    than the run's (degrees under radian names) is refused (check_units; `specs`: the run's machine_joints, None
    when unknown; check=False for another run's joints.csv, radians by the run folder's contract); one whose time
    looks like milliseconds is warned of."""
    joints = [j for j in run if j in ref]
    if not joints:
        raise UserError(f"--joints: {ref_label} names no joint of the run (run: {', '.join(run)}; log: "
                        f"{', '.join(ref)})")
    for j in joints if check else ():
        check_units(j, t_ref, ref[j], t_run, run[j], (specs or {}).get(j), ref_label)
    t0, t1 = max(t_run[0], t_ref[0]), min(t_run[-1], t_ref[-1])
    if not t1 - t0 > 2 * JOINT_DT:
        raise UserError(f"--joints: {ref_label} spans t {t_ref[0]:.6g}..{t_ref[-1]:.6g} s, the run "
                        f"{t_run[0]:.6g}..{t_run[-1]:.6g} s: no common time span (the log's t is compared as "
                        f"written, in seconds)")
    span_ref, span_run = t_ref[-1] - t_ref[0], t_run[-1] - t_run[0]
    if warnings is not None and span_run > 0 and span_ref > 100 * span_run and np.median(np.diff(t_ref)) > 0.5:
        _warn(warnings, f"--joints: {ref_label} spans {span_ref:.4g} s against the run's {span_run:.4g} s, with a "
                        f"median step of {np.median(np.diff(t_ref)):.3g} s: is its t in milliseconds? Only its first "
                        f"{t1 - t0:.4g} s are compared")
    t = np.arange(t0, t1 + 1e-12, JOINT_DT)
    n_smooth = max(1, int(round(RATE_SMOOTHING_S / JOINT_DT)))
    max_lag = int(min(MAX_LAG_S, (t1 - t0) / 3) / JOINT_DT)
    per = {}
    arrays = {"t": t, "joints": {}}
    for j in joints:
        a = np.interp(t, t_run, run[j])
        spec = (specs or {}).get(j)
        if spec is not None and spec.turns:
            # a swing logged wrapped to +-pi, or from another zero turn: unwrapped and put on the run's turn
            b = np.interp(t, t_ref, unwrap_swing(ref[j]))
            b += 2 * math.pi * round(float(a[0] - b[0]) / (2 * math.pi))
        else:
            b = np.interp(t, t_ref, ref[j])
        moving = float(np.percentile(b, 95) - np.percentile(b, 5)) > STILL_RANGE
        lag = best_lag(a, b, max_lag) if moving else None
        ra, rb = _rate(a, n_smooth), _rate(b, n_smooth)
        if lag:
            # the rates of the same motion: the reference shifted by the lag, over the span both cover then (on the
            # common span before the shift, a lag cut part of a fast phase out of one of them: 0.22 for 1)
            turns = spec is not None and spec.turns
            ra, rb = aligned_rates(t_run, run[j], t_ref, unwrap_swing(ref[j]) if turns else ref[j],
                                   lag * JOINT_DT, n_smooth) or (ra, rb)
        pa, pb = float(np.percentile(ra, 90)), float(np.percentile(rb, 90))
        per[j] = {"rmse_rad": float(np.sqrt(np.mean((a - b) ** 2))), "rmse_deg": math.degrees(
            float(np.sqrt(np.mean((a - b) ** 2)))), "lag_s": None if lag is None else lag * JOINT_DT,
            "rate_ratio": pa / pb if moving and pb > STILL_RATE else None, "moving": moving,
            "run_rate_p90_rad_s": pa, "reference_rate_p90_rad_s": pb}
        arrays["joints"][j] = (a, b)
    ratios = [v["rate_ratio"] for v in per.values() if v["rate_ratio"] is not None]
    lags = [v["lag_s"] for v in per.values() if v["lag_s"] is not None]
    out = {"joints": per, "joints_common_span_s": [float(t0), float(t1)],
           "joints_rmse_rad": float(np.mean([v["rmse_rad"] for v in per.values()])),
           "joints_lag_s": float(np.median(lags)) if lags else None,
           "joints_rate_ratio": float(np.median(ratios)) if ratios else None}
    return out, arrays


# ----------------------------------------------------------------------------------------------- the command
def compare(run_dir, *, terrain=None, terrain_before=None, joints=None, against=None, transform=None,
            fit: str | None = None, out=None, change_threshold: float = 0.02, margin_m: float = 0.25,
            figures: bool = True) -> dict:
    """Compare a run folder with a scan and/or a joint log, or with another run; write comparison.json,
    profile.csv and the figures into `out` (default: the run folder). Returns the comparison."""
    run_dir = run_folder(run_dir, "RUN_DIR")
    if against is not None and (terrain or terrain_before or joints):
        raise UserError("--against: compares two runs; give it without --terrain, --terrain-before and --joints")
    if terrain_before is not None and terrain is None:
        raise UserError("--terrain-before: needs --terrain (the scan after the dig)")
    if against is None and terrain is None and joints is None:
        raise UserError("compare: nothing to compare the run with; give --terrain SCAN, --joints LOG or --against "
                        "RUN_DIR")
    if (transform is not None or fit) and terrain is None:
        raise UserError("--transform / --fit-transform: place a scan; give --terrain")
    if not change_threshold > 0:
        raise UserError(f"--change-threshold: expected a positive height in m, got {change_threshold!r}")
    if not 0 <= margin_m < math.inf:
        raise UserError(f"--margin: expected a finite distance in m >= 0, got {margin_m!r}")
    if isinstance(transform, str):
        transform = scans.Transform.parse(transform)
    out_dir = Path(out) if out is not None else run_dir
    _check_out(out_dir, run_dir)
    result: dict = {"run": str(run_dir.resolve())}
    warnings: list[str] = []
    figs: dict = {}
    has_terrain = (run_dir / "terrain_final.npz").is_file()
    ref_final = ref_initial = None
    label = None
    if against is not None:
        other = run_folder(against, "--against")
        result["against"] = str(Path(other).resolve())
        label = f"run {other.name}"
        if has_terrain:  # (a run without soil is compared by its joints)
            grid = read_terrain(run_dir / "terrain_initial.npz", "RUN_DIR")
            o0 = read_terrain(other / "terrain_initial.npz", "--against")
            o1 = read_terrain(other / "terrain_final.npz", "--against")
            pts = np.stack(np.meshgrid(grid["x"], grid["y"], indexing="ij"), axis=-1).reshape(-1, 2)
            ref_final = sample(o1["x"], o1["y"], o1["z"], pts).reshape(grid["z"].shape)
            ref_initial = sample(o0["x"], o0["y"], o0["z"], pts).reshape(grid["z"].shape)
    elif terrain is not None:
        grid = read_terrain(run_dir / "terrain_initial.npz", "RUN_DIR")
        label = f"scan {Path(terrain).name}"
        result["terrain_scan"] = str(Path(terrain).resolve())
        fit_against = None
        placement = {}
        if terrain_before is not None:
            before = scans.read_scan(terrain_before, "--terrain-before")
            result["terrain_scan_before"] = str(Path(terrain_before).resolve())
            g0, fit0, transform = place_scan(before, grid, transform, fit, key="--terrain-before")
            ref_initial = g0.z
            placement["fitted_on"] = "scan before the dig against the run's initial terrain" if fit else None
            fit = None  # the same placement for the scan after the dig
            if fit0 is not None:
                placement.update(fit0.describe())
                _fit_warning(fit0, "--terrain-before", warnings)
            placement["before_empty_cells"] = g0.empty_cells
        after = scans.read_scan(terrain, "--terrain")
        g1, fit1, transform = place_scan(after, grid, transform, fit, fit_against, key="--terrain")
        if fit1 is not None:
            placement.update(fit1.describe())
            _fit_warning(fit1, "--terrain", warnings)
            placement["fitted_on"] = "scan after the dig against the run's initial terrain (dug area left out)"
        if "mode" not in placement:
            placement.update(transform.describe(), mode="given" if transform != scans.Transform() else "identity")
        placement["empty_cells"] = g1.empty_cells
        placement["points"] = int(len(after.points))
        result["transform"] = placement
        ref_final = g1.z
    if has_terrain:
        block, figs["terrain"] = terrain_comparison(run_dir, reference_final=ref_final, reference_initial=ref_initial,
                                                    label=label or "", change_threshold=change_threshold,
                                                    margin_m=margin_m, key="--against" if against else "--terrain",
                                                    warnings=warnings, fitted=bool(fit) and against is None)
        result.update(block)
    elif terrain is not None or against is not None:
        if terrain is not None:
            raise UserError(f"RUN_DIR: {run_dir} has no terrain_final.npz to compare the scan with")
    if joints is not None or (against is not None and (run_dir / "joints.csv").is_file()):
        if joints is not None:  # the user's file first: its problems are the ones to hear about
            t_ref, q_ref = read_joint_log(joints, joints=run_joint_names(run_dir), warnings=warnings)
            ref_label = Path(joints).name
            result["joint_log"] = str(Path(joints).resolve())
        else:
            t_ref, q_ref = run_joints(Path(against), "--against")
            ref_label = f"run {Path(against).name}"
        t_run, q_run = run_joints(run_dir)
        specs = None
        if joints is not None:
            specs, why = machine_joints(run_dir)
            if specs is None:
                _warn(warnings, f"RUN_DIR: the run's machine description cannot be read ({why}): {ref_label} is "
                                f"checked for degrees by its angles' range only (a swing over a full turn reads as "
                                f"degrees)")
        block, figs["joints"] = joint_comparison(t_run, q_run, t_ref, q_ref, ref_label, warnings, specs,
                                                 check=joints is not None)
        figs["joints"]["label"] = ref_label
        result.update(block)
    if warnings:
        result["warnings"] = warnings
    # everything computed: now replace the previous compare's outputs as a whole (none of them left stale)
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in OUTPUT_FILES:
        (out_dir / name).unlink(missing_ok=True)
    profile = figs.get("terrain", {}).get("profile")
    if profile is not None:
        _write_profile(out_dir / PROFILE_FILE, profile)
    write_json(out_dir / COMPARISON_FILE, _clean(result))
    if figures:
        from . import figures as fig

        try:
            if "terrain" in figs:
                fig.plot_terrain_comparison(figs["terrain"], out_dir / "comparison_terrain.png")
                fig.plot_profile(figs["terrain"], out_dir / "comparison_profile.png")
            if "joints" in figs:
                fig.plot_joint_comparison(figs["joints"], out_dir / "comparison_joints.png")
        except Exception as exc:  # noqa: BLE001 - a figure must never cost the numbers
            import sys

            print(f"warning: comparison figures not written ({type(exc).__name__}: {exc})", file=sys.stderr)
    return result


def _check_out(out_dir: Path, run_dir: Path) -> None:
    """--out must not be another run's folder, nor hold another run's comparison (it would be replaced)."""
    from ..runner import is_run_folder

    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"--out: {out_dir} is a file; give a folder")
    holder = next((p for p in out_dir.resolve().parents if is_run_folder(p)), None)
    if holder is not None and holder != run_dir.resolve():  # (the compared run's own subfolders are its files)
        raise UserError(f"--out: {out_dir} lies inside the run folder {holder}; give a folder outside it, or leave "
                        f"--out out to write into {run_dir}")
    if not out_dir.is_dir() or out_dir.resolve() == run_dir.resolve():
        return
    if (out_dir / "manifest.json").is_file():
        raise UserError(f"--out: {out_dir} is the run folder of another run; give a folder of its own, or leave "
                        f"--out out to write into {run_dir}")
    try:
        previous = json.loads((out_dir / COMPARISON_FILE).read_text()).get("run")
    except (OSError, ValueError, AttributeError):
        previous = None
    if previous and Path(previous) != run_dir.resolve():
        raise UserError(f"--out: {out_dir} holds the comparison of another run ({previous}); give another folder")


def _fit_warning(fit, key: str, warnings: list) -> None:
    if fit.residual_rms_m > FIT_WARN_RESIDUAL_M or fit.inlier_fraction < FIT_WARN_INLIERS:
        _warn(warnings, f"{key}: the fitted placement looks wrong: residual {fit.residual_rms_m:.3g} m over "
                        f"{100 * fit.inlier_fraction:.0f}% inliers (a good fit: under {FIT_WARN_RESIDUAL_M:g} m, over "
                        f"{100 * FIT_WARN_INLIERS:.0f}%); give --transform close to the scan's placement to start "
                        f"from")


def _warn(warnings: list, text: str) -> None:
    """Into comparison.json, and on stderr at once (before any refusal it may explain)."""
    import sys

    warnings.append(text)
    print(f"warning: {text}", file=sys.stderr)


def _write_profile(path: Path, profile: dict) -> None:
    names = list(profile)
    data = np.column_stack([profile[n] for n in names])
    np.savetxt(path, data, delimiter=",", header=",".join(names), comments="", fmt="%.6g")


def _clean(value):
    """JSON-safe: NaN and inf as null."""
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value
