"""compare: a synthetic site with a known trench and heave, scanned with noise in another frame (LAS, PLY, GeoTIFF,
XYZ), placed back by a given or fitted transform; the volumes, depth, heave and transform recovered; a run against
itself gives zero; joint logs (rad, _deg, lag, half rate); bad input is one line, exit 2."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

laspy = pytest.importorskip("laspy")
plyfile = pytest.importorskip("plyfile")
tifffile = pytest.importorskip("tifffile")

from opera_taichi.cli import main  # noqa: E402
from opera_taichi.studies import compare as cmp  # noqa: E402
from opera_taichi.studies import scan as scans  # noqa: E402

CELL = 0.05
X = 2.0 + CELL * (np.arange(160) + 0.5)      # 2 .. 10 m
Y = -3.0 + CELL * (np.arange(120) + 0.5)     # -3 .. 3 m
TRENCH = dict(x0=4.5, x1=7.0, half_width=0.5, depth=0.5, ramp=0.3)
HEAVE = dict(xc=5.75, yc=1.2, sx=0.6, sy=0.25, h=0.3)   # a mound on the machine's left of the trench
# scan frame -> machine frame (what compare must recover)
TRUE = scans.Transform(x=-812.40, y=1533.25, z=-41.7, roll=math.radians(0.8), pitch=math.radians(-0.5),
                       yaw=math.radians(12.0))


def _smoothstep(u):
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3 - 2 * u)


def ground(x, y, relief=True):
    """The site before the dig: a gentle, irregular slope (relief that holds x, y and yaw), or flat."""
    if not relief:
        return np.zeros(np.broadcast(x, y).shape)
    return 0.18 * np.sin(0.9 * x + 0.3) * np.cos(0.7 * y) + 0.04 * x - 0.06 * y + 0.1 * np.sin(1.7 * y + 0.4 * x)


def trench(x, y):
    t = TRENCH
    fx = _smoothstep((x - t["x0"]) / t["ramp"]) * _smoothstep((t["x1"] - x) / t["ramp"])
    fy = _smoothstep((t["half_width"] - np.abs(y)) / 0.15)
    return -t["depth"] * fx * fy


def heave(x, y):
    """A smooth spoil mound of finite extent (semi-axes 2 sx, 2 sy)."""
    h = HEAVE
    r2 = ((x - h["xc"]) / (2 * h["sx"])) ** 2 + ((y - h["yc"]) / (2 * h["sy"])) ** 2
    return h["h"] * np.maximum(0.0, 1.0 - r2) ** 2


def truth():
    """Cut and fill volumes of the change, integrated on a 1 cm grid."""
    fx = np.arange(2.0, 10.0, 0.01) + 0.005
    fy = np.arange(-3.0, 3.0, 0.01) + 0.005
    gx, gy = np.meshgrid(fx, fy, indexing="ij")
    return {"cut": float(-trench(gx, gy).sum() * 1e-4), "fill": float(heave(gx, gy).sum() * 1e-4)}


def make_run(folder: Path, relief=True, joints=None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    gx, gy = np.meshgrid(X, Y, indexing="ij")
    z0 = ground(gx, gy, relief)
    z1 = z0 + trench(gx, gy) + heave(gx, gy)
    for name, z in (("terrain_initial.npz", z0), ("terrain_final.npz", z1)):
        np.savez_compressed(folder / name, x=X, y=Y, z=z, z_all=z, t=0.0)
    scene = {"name": "synthetic", "machine": {"base_pose": {"xyz": [0.0, 0.0, 0.0], "yaw": 0.0}}}
    (folder / "manifest.json").write_text(json.dumps({"name": "synthetic", "status": "done", "scene": scene}))
    if joints is not None:
        t, q = joints
        with open(folder / "joints.csv", "w") as fh:
            fh.write("t," + ",".join(f"{j}.q,{j}.qd" for j in q) + "\n")
            for i in range(len(t)):
                fh.write(f"{t[i]:.4f}," + ",".join(f"{q[j][i]:.6f},0" for j in q) + "\n")
    return folder


def scan_points(after: bool, relief=True, density=2500.0, noise=0.004, seed=1):
    """Random points of the true surface (machine frame) with noise, then put into the scan's frame."""
    rng = np.random.default_rng(seed)
    n = int(density * 8.0 * 6.0)
    x = rng.uniform(2.0, 10.0, n)
    y = rng.uniform(-3.0, 3.0, n)
    z = ground(x, y, relief) + ((trench(x, y) + heave(x, y)) if after else 0.0) + rng.normal(0, noise, n)
    machine = np.stack([x, y, z], axis=1)
    rot = TRUE.matrix()
    return (machine - [TRUE.x, TRUE.y, TRUE.z]) @ rot  # inverse: R^T (p - t)


def write_las(path: Path, pts):
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.offsets = pts.min(axis=0)
    header.scales = [0.001, 0.001, 0.001]
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.write(str(path))


def write_ply(path: Path, pts):
    v = np.array([tuple(p) for p in pts.astype(np.float32)], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    # float32 cannot hold site coordinates to the mm: a PLY scan is usually local, so keep it near its origin
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(str(path))


def write_geotiff(path: Path, after: bool, offset=(35000.0, -12000.0, 12.5), noise=0.004, units=9001):
    """A north-up raster at CELL of the true surface with noise, shifted by `offset` (no rotation: GeoTIFF's tie
    point and pixel scale carry a translation only)."""
    rng = np.random.default_rng(5)
    gx, gy = np.meshgrid(X, Y[::-1], indexing="xy")  # rows from north (max y) down
    z = ground(gx, gy) + ((trench(gx, gy) + heave(gx, gy)) if after else 0.0) + rng.normal(0, noise, gx.shape)
    z = (z + offset[2]).astype(np.float32)
    z[:3, :5] = -9999.0  # a corner of nodata
    geokeys = (1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3076, 0, 1, units)
    extratags = [(33550, "d", 3, (CELL, CELL, 0.0)),
                 (33922, "d", 6, (0.0, 0.0, 0.0, X[0] - CELL / 2 + offset[0], Y[-1] + CELL / 2 + offset[1], 0.0)),
                 (34735, "H", len(geokeys), geokeys), (42113, "s", 0, "-9999")]
    tifffile.imwrite(str(path), z, extratags=extratags)


def placement_error(placed: dict, true: scans.Transform = TRUE) -> float:
    """Largest distance (m) between where the fitted and the true transform put the site's corners and centre: the
    transform's error where it matters (its translation alone swings with the smallest yaw error when the scan's
    origin is a kilometre away, as a surveyor's site frame is)."""
    fitted = scans.Transform(placed["x_m"], placed["y_m"], placed["z_m"], math.radians(placed["roll_deg"]),
                             math.radians(placed["pitch_deg"]), math.radians(placed["yaw_deg"]))
    site = np.array([[2, -3, 0], [10, -3, 0], [2, 3, 0], [10, 3, 0], [6, 0, 0]], float)
    in_scan = (site - [true.x, true.y, true.z]) @ true.matrix()
    return float(np.max(np.linalg.norm(fitted.apply(in_scan) - site, axis=1)))


def check_terrain(result, tol=0.03):
    tr = truth()
    assert result["reference_cut_volume_m3"] == pytest.approx(tr["cut"], rel=tol)
    assert result["reference_fill_volume_m3"] == pytest.approx(tr["fill"], rel=tol)
    assert result["cut_volume_m3"] == pytest.approx(tr["cut"], rel=tol)
    # the deepest point: the trench floor is flat, so any floor cell; its depth within the noise, its place inside
    assert result["reference_max_depth_m"] == pytest.approx(TRENCH["depth"], abs=0.02)
    x, y = result["reference_max_depth_xy_m"]
    assert TRENCH["x0"] + TRENCH["ramp"] - CELL <= x <= TRENCH["x1"] - TRENCH["ramp"] + CELL and abs(y) <= 0.35 + CELL
    hx, hy = result["reference_heave_xy_m"]
    assert abs(hx - HEAVE["xc"]) <= CELL + 1e-9 and abs(hy - HEAVE["yc"]) <= CELL + 1e-9
    assert result["reference_heave_height_m"] == pytest.approx(HEAVE["h"], abs=0.01)
    assert result["reference_heave_side"] == "left" and result["heave_side"] == "left"
    assert abs(result["terrain_bias_m"]) < 0.005 and result["terrain_rmse_m"] < 0.01


def test_las_with_fitted_transform_recovers_trench_and_placement(tmp_path):
    run = make_run(tmp_path / "run")
    write_las(tmp_path / "before.las", scan_points(after=False, seed=2))
    write_las(tmp_path / "after.laz", scan_points(after=True, seed=3))
    result = cmp.compare(run, terrain=tmp_path / "after.laz", terrain_before=tmp_path / "before.las", fit="auto",
                         out=tmp_path / "cmp")
    placed = result["transform"]
    assert placed["mode"] == "rigid"
    assert placement_error(placed) < 0.02
    for angle in ("roll", "pitch", "yaw"):
        assert placed[f"{angle}_deg"] == pytest.approx(math.degrees(getattr(TRUE, angle)), abs=0.05), angle
    assert placed["residual_rms_m"] < 0.01  # the scan's noise (4 mm) and the 1 mm LAS quantum
    check_terrain(result)
    saved = json.loads((tmp_path / "cmp" / "comparison.json").read_text())
    assert saved["cut_volume_m3"] == pytest.approx(result["cut_volume_m3"])
    for png in ("comparison_terrain.png", "comparison_profile.png"):
        assert (tmp_path / "cmp" / png).stat().st_size > 10_000
    profile = np.genfromtxt(tmp_path / "cmp" / "profile.csv", delimiter=",", names=True)
    assert np.nanmin(profile["reference_z_m"] - profile["reference_initial_z_m"]) == pytest.approx(-0.5, abs=0.03)


def test_ply_with_given_transform(tmp_path):
    run = make_run(tmp_path / "run")
    local = scans.Transform(z=-3.0, yaw=math.radians(-30.0))  # a local scanner frame: small coordinates
    rng = np.random.default_rng(7)
    n = 120_000
    x, y = rng.uniform(2.0, 10.0, n), rng.uniform(-3.0, 3.0, n)
    z = ground(x, y) + trench(x, y) + heave(x, y) + rng.normal(0, 0.004, n)
    pts = (np.stack([x, y, z], axis=1) - [local.x, local.y, local.z]) @ local.matrix()
    write_ply(tmp_path / "after.ply", pts)
    result = cmp.compare(run, terrain=tmp_path / "after.ply", transform="0,0,-3,-30", out=tmp_path / "cmp")
    assert result["transform"]["mode"] == "given"
    check_terrain(result)


def test_geotiff_through_the_cli_and_a_plane_fit_on_flat_ground(tmp_path):
    """Flat ground holds only z, roll and pitch: the fit says it is a plane fit and keeps the given x, y."""
    run = make_run(tmp_path / "run")
    write_geotiff(tmp_path / "after.tif", after=True)
    out = tmp_path / "cmp"
    code = main(["compare", str(run), "--terrain", str(tmp_path / "after.tif"), "--transform=-35000,12000,0,0",
                 "--fit-transform", "--out", str(out)])
    assert code == 0
    result = json.loads((out / "comparison.json").read_text())
    assert result["transform"]["mode"] == "rigid"  # the sloped site holds a rigid fit
    assert placement_error(result["transform"], scans.Transform(-35000.0, 12000.0, -12.5)) < 0.02
    check_terrain(result)
    assert result["reference_empty_cells"] == 15  # the nodata corner, reported, not filled in
    flat = make_run(tmp_path / "flat", relief=False)
    pts = scan_points(after=True, relief=False) @ np.eye(3)
    np.savetxt(tmp_path / "flat.xyz", pts, fmt="%.4f")
    # x, y and yaw known (5 mm off at the site's centre), z 0.3 m off, roll and pitch unknown
    centre = pts.mean(axis=0)
    level = scans.Transform(yaw=TRUE.yaw)
    t0 = TRUE.apply(centre[None])[0] + [0.004, -0.003, 0.3] - level.apply(centre[None])[0]
    start = scans.Transform(*t0, 0.0, 0.0, TRUE.yaw)
    placed = cmp.compare(flat, terrain=tmp_path / "flat.xyz", transform=start, fit="auto", out=tmp_path / "f")
    assert placed["transform"]["mode"] == "plane"
    assert placed["transform"]["fitted"] == ["z", "roll", "pitch"]  # x, y, yaw kept as given (5 mm off)
    assert placement_error(placed["transform"]) < 0.02
    assert placed["transform"]["roll_deg"] == pytest.approx(math.degrees(TRUE.roll), abs=0.05)
    assert placed["transform"]["pitch_deg"] == pytest.approx(math.degrees(TRUE.pitch), abs=0.05)
    check_terrain(placed)


def test_run_against_itself_is_zero_and_joint_log_lag_and_rate(tmp_path):
    t = np.arange(0.0, 20.0, 0.01)
    q = {"boom_joint": 0.4 * np.sin(0.5 * t), "arm_joint": 1.0 + 0.3 * np.cos(0.4 * t)}
    run = make_run(tmp_path / "run", joints=(t, q))
    same = cmp.compare(run, against=run, out=tmp_path / "self")
    for key in ("terrain_rmse_m", "terrain_bias_m", "cut_volume_relative_error", "fill_volume_relative_error",
                "joints_rmse_rad", "joints_lag_s", "max_depth_position_error_m"):
        assert same[key] == 0.0, key
    assert same["joints_rate_ratio"] == pytest.approx(1.0)
    assert same["cut_volume_m3"] == pytest.approx(truth()["cut"], rel=0.03)
    # a field log: the same motion 0.7 s earlier and twice as fast in degrees (the run moves at half its rate)
    with open(tmp_path / "log.csv", "w") as fh:
        fh.write("t,boom_joint_deg,arm_joint_deg\n")
        for ti in np.arange(0.0, 20.0, 0.02):
            tr = 2 * (ti + 0.7)  # the log at ti shows what the run shows at 2 (ti + 0.7)... only the rate matters
            fh.write(f"{ti:.3f},{math.degrees(0.4 * math.sin(0.5 * tr)):.5f},"
                     f"{math.degrees(1.0 + 0.3 * math.cos(0.4 * tr)):.5f}\n")
    res = cmp.compare(run, joints=tmp_path / "log.csv", out=tmp_path / "log")
    assert res["joints"]["boom_joint"]["rate_ratio"] == pytest.approx(0.5, rel=0.05)
    assert res["joints_rate_ratio"] == pytest.approx(0.5, rel=0.05)
    assert (tmp_path / "log" / "comparison_joints.png").stat().st_size > 10_000
    # the same motion, delayed: the lag found by cross-correlation
    with open(tmp_path / "late.csv", "w") as fh:
        fh.write("t,boom_joint,arm_joint\n")
        for ti in np.arange(0.0, 20.0, 0.02):
            fh.write(f"{ti:.3f},{0.4 * math.sin(0.5 * (ti - 0.7)):.6f},{1.0 + 0.3 * math.cos(0.4 * (ti - 0.7)):.6f}\n")
    late = cmp.compare(run, joints=tmp_path / "late.csv", out=tmp_path / "late")
    assert late["joints_lag_s"] == pytest.approx(-0.7, abs=0.011)  # the run leads the log by 0.7 s
    assert late["joints_rmse_rad"] > 0.05


def test_a_run_killed_while_it_wrote_joints_csv_compares_on_its_whole_rows(tmp_path, capsys):
    """A run killed mid-row leaves joints.csv cut short: compared on its whole rows (the cut row left out); an empty
    or header-only joints.csv is one line, exit 2 (both were tracebacks)."""
    t = np.arange(0.0, 20.0, 0.01)
    q = {"boom_joint": 0.4 * np.sin(0.5 * t), "arm_joint": 1.0 + 0.3 * np.cos(0.4 * t)}
    run = make_run(tmp_path / "run", joints=(t, q))
    with open(tmp_path / "log.csv", "w") as fh:
        fh.write("t,boom_joint,arm_joint\n")
        for ti in np.arange(0.0, 20.0, 0.02):
            fh.write(f"{ti:.3f},{0.4 * math.sin(0.5 * ti):.6f},{1.0 + 0.3 * math.cos(0.4 * ti):.6f}\n")
    text = (run / "joints.csv").read_text()
    cut = text.index("\n", len(text) // 2) + 8   # a few characters into a row
    (run / "joints.csv").write_text(text[:cut])
    res = cmp.compare(run, joints=tmp_path / "log.csv", out=tmp_path / "cmp")
    assert res["joints_rmse_rad"] < 1e-3
    for content, words in [("", "empty"), (text[:text.index("\n") + 1], "fewer than two rows of joint angles")]:
        (run / "joints.csv").write_text(content)
        code, err = _cli([run, "--joints", tmp_path / "log.csv", "--out", tmp_path / "cmp2"], capsys)
        assert code == 2 and words in err and "\n" not in err, err


def test_the_rate_ratio_of_a_log_offset_in_time_compares_the_same_motion(tmp_path):
    """The run's own joints logged 0.5 s later: lag -0.5 s and rate ratio 1. The arm moves fast for its first 1.5 s
    (12% of the run), then creeps: rated on the common span before the shift, the run lost a third of its fast
    phase and its 90th percentile fell into the creep (a ratio of about 0.1)."""
    t = np.arange(0.0, 12.0, 0.01)
    fast = 1.5 * 0.5 * (1.0 - np.cos(math.pi * np.minimum(t / 1.5, 1.0)))
    q = {"arm_joint": fast + 0.02 * np.maximum(t - 1.5, 0.0)}
    run = make_run(tmp_path / "run", joints=(t, q))
    joint_log(tmp_path / "late.csv", t + 0.5, "arm_joint", q["arm_joint"])
    res = cmp.compare(run, joints=tmp_path / "late.csv", out=tmp_path / "late", figures=False)
    arm = res["joints"]["arm_joint"]
    assert arm["lag_s"] == pytest.approx(-0.5, abs=0.011)
    assert arm["rate_ratio"] == pytest.approx(1.0, abs=0.02)


def test_comparison_keys_hold_every_key_compare_writes(tmp_path):
    """A study checks compare.<key> metrics against comparison_keys before any run: every key a comparison writes
    must be there, for each kind of reference."""
    t = np.arange(0.0, 20.0, 0.01)
    q = {"boom_joint": 0.4 * np.sin(0.5 * t), "arm_joint": 1.0 + 0.3 * np.cos(0.4 * t)}
    run = make_run(tmp_path / "run", joints=(t, q))
    gx, gy = np.meshgrid(X, Y, indexing="ij")
    np.savez(tmp_path / "before.npz", x=X, y=Y, z=ground(gx, gy))
    np.savez(tmp_path / "after.npz", x=X, y=Y, z=ground(gx, gy) + trench(gx, gy))
    joint_log(tmp_path / "log.csv", t, "boom_joint", q["boom_joint"])
    cases = [({"against": run}, dict(against=run)),
             ({"terrain": 1, "terrain_before": 1, "joints": 1},
              dict(terrain=tmp_path / "after.npz", terrain_before=tmp_path / "before.npz",
                   joints=tmp_path / "log.csv")),
             ({"joints": 1}, dict(joints=tmp_path / "log.csv"))]
    for i, (reference, kwargs) in enumerate(cases):
        res = cmp.compare(run, out=tmp_path / f"c{i}", figures=False, **kwargs)
        keys = set(cmp.comparison_keys(reference))
        assert set(res) <= keys, (reference, set(res) - keys)
        if "against" in reference:  # ... and no key compare never writes (a run against itself has all but warnings)
            assert keys - set(res) == {"warnings"}


def test_a_joint_log_with_columns_that_name_no_joint_compares_on_the_joints(tmp_path, capsys):
    """A field log's extra columns (an operating `mode` of text, a pump pressure) were parsed as joints and the text
    refused the log; columns naming no joint of the run are not read, and a warning names them."""
    t = np.arange(0.0, 20.0, 0.01)
    q = {"boom_joint": 0.4 * np.sin(0.5 * t), "arm_joint": 1.0 + 0.3 * np.cos(0.4 * t)}
    run = make_run(tmp_path / "run", joints=(t, q))
    with open(tmp_path / "log.csv", "w") as fh:
        fh.write("t,mode,boom_joint,pressure_bar,arm_joint_deg\n")
        for i in range(0, len(t), 2):
            fh.write(f"{t[i]:.3f},dig,{q['boom_joint'][i]:.6f},210.5,{math.degrees(q['arm_joint'][i]):.5f}\n")
    res = cmp.compare(run, joints=tmp_path / "log.csv", out=tmp_path / "c", figures=False)
    assert set(res["joints"]) == {"boom_joint", "arm_joint"} and res["joints_rmse_rad"] < 1e-4
    assert res["warnings"] == ["--joints: log.csv: columns mode, pressure_bar name no joint of the run (boom_joint, "
                               "arm_joint): not read"]
    assert "warning: --joints: log.csv: columns mode, pressure_bar" in capsys.readouterr().err
    # a bad cell of a joint's column is still refused, on its line
    text = (tmp_path / "log.csv").read_text().splitlines()
    text[3] = text[3].replace(",dig,", ",dig,oops,", 1).replace(",210.5", "", 1)
    (tmp_path / "log.csv").write_text("\n".join(text) + "\n")
    code, err = _cli([run, "--joints", tmp_path / "log.csv", "--out", tmp_path / "c2"], capsys)
    assert code == 2 and "log.csv: line 4, column boom_joint: expected a number, got 'oops'" in err, err
    # and a cell over the csv module's field limit, in one line (it raised csv.Error: a traceback and exit 1)
    text[3] = text[3].replace(",dig,oops,", "," + "x" * 200_000 + ",", 1)
    (tmp_path / "log.csv").write_text("\n".join(text) + "\n")
    code, err = _cli([run, "--joints", tmp_path / "log.csv", "--out", tmp_path / "c3"], capsys)
    assert code == 2 and "log.csv: line 4: not readable as CSV (field larger than field limit" in err, err


def test_a_grain_rolling_into_a_gap_of_the_initial_bed_is_no_heave(tmp_path):
    """With 32 cm grains the initial heightmap drops to the bed floor (1 m down) in gaps between grains at a pit
    wall; a grain rolling in later made that cell the heave (0.81 m against a 0.17 m spoil heap). Cells more than a
    grain radius below the initial surface closed over a grain diameter are left out of the heave, for the run and
    for the reference measured from the same initial surface; the spoil mound is found."""
    run = make_run(tmp_path / "run")
    manifest = json.loads((run / "manifest.json").read_text())
    manifest["soil"] = {"micro": {"radius": 0.16}}
    (run / "manifest.json").write_text(json.dumps(manifest))
    gx, gy = np.meshgrid(X, Y, indexing="ij")
    z0, z1 = ground(gx, gy), ground(gx, gy) + trench(gx, gy) + heave(gx, gy)
    gap = (np.abs(gx - 8.0) < 0.08) & (np.abs(gy + 1.0) < 0.03)   # 3 cells along x: narrower than a grain
    z0[gap] -= 1.0
    for name, z in (("terrain_initial.npz", z0), ("terrain_final.npz", z1)):
        np.savez_compressed(run / name, x=X, y=Y, z=z, z_all=z, t=0.0)
    res = cmp.compare(run, against=run, out=tmp_path / "c", figures=False)
    for prefix in ("", "reference_"):
        assert res[f"{prefix}heave_height_m"] == pytest.approx(HEAVE["h"], abs=0.01)
        hx, hy = res[f"{prefix}heave_xy_m"]
        assert abs(hx - HEAVE["xc"]) <= CELL + 1e-9 and abs(hy - HEAVE["yc"]) <= CELL + 1e-9
    assert res["fill_volume_m3"] > truth()["fill"] + 0.9 * gap.sum() * CELL ** 2  # the volume still counts it


def _cli(args, capsys):
    code = main(["compare", *map(str, args)])
    err = capsys.readouterr().err.strip()
    return code, err


def test_bad_input_is_one_line_exit_2(tmp_path, capsys):
    run = make_run(tmp_path / "run")
    (tmp_path / "junk.las").write_bytes(b"not a las file at all" * 10)
    code, err = _cli([run, "--terrain", tmp_path / "junk.las"], capsys)
    assert code == 2 and "junk.las: cannot read it as LAS" in err and "\n" not in err
    mm = scan_points(after=True, density=50) @ TRUE.matrix().T + [TRUE.x, TRUE.y, TRUE.z]
    np.savetxt(tmp_path / "mm.csv", mm * 1000.0, delimiter=",", header="x,y,z", comments="")
    code, err = _cli([run, "--terrain", tmp_path / "mm.csv"], capsys)
    assert code == 2 and "millimetres" in err and "spans 7998 x 5995" in err
    far = scan_points(after=True, density=50)
    np.savetxt(tmp_path / "far.xyz", far)
    code, err = _cli([run, "--terrain", tmp_path / "far.xyz"], capsys)
    assert code == 2 and "far from the run" in err and "--transform" in err
    write_geotiff(tmp_path / "feet.tif", after=True, units=9002)
    code, err = _cli([run, "--terrain", tmp_path / "feet.tif"], capsys)
    assert code == 2 and "foot" in err
    (tmp_path / "notime.csv").write_text("time,boom_joint\n0,0\n1,0.1\n")
    code, err = _cli([run, "--joints", tmp_path / "notime.csv"], capsys)
    assert code == 2 and "no `t` column" in err
    code, err = _cli([run, "--terrain", tmp_path / "missing.las"], capsys)
    assert code == 2 and "file not found" in err
    code, err = _cli([run, "--terrain", tmp_path / "far.xyz", "--transform", "1,2,north"], capsys)
    assert code == 2 and "--transform: expected x,y,z,yaw_deg" in err
    code, err = _cli([tmp_path, "--terrain", tmp_path / "far.xyz"], capsys)
    assert code == 2 and "not a run folder" in err
    code, err = _cli([run], capsys)
    assert code == 2 and "nothing to compare the run with" in err and "\n" not in err


def test_compare_command_runs_as_a_program(tmp_path):
    run = make_run(tmp_path / "run")
    cli = Path(__file__).resolve().parents[1] / "cli.py"
    proc = subprocess.run([sys.executable, str(cli), "compare", str(run), "--against", str(run)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((run / "comparison.json").read_text())["terrain_rmse_m"] == 0.0


def test_soil_preset_file_in_a_scene(tmp_path, capsys):
    from opera_taichi.model import soil_parameters
    from opera_taichi.scene import load_scene

    scene_path = Path(__file__).resolve().parents[1] / "scenes" / "blade_cut.yaml"
    (tmp_path / "fitted.yaml").write_text("preset: sand\nfriction_angle_deg: 31.5\ncohesion: 500\n"
                                          "calibration: {loss: 0.1}\n")
    scene = load_scene(scene_path, [f"soil.preset_file={tmp_path / 'fitted.yaml'}",
                                    "soil.overrides={radius: 0.05, cohesion: 800}"])
    bulk, _ = soil_parameters(scene.soil)
    assert math.degrees(bulk.friction_angle) == pytest.approx(31.5)   # from the file
    assert bulk.cohesion == 800.0 and bulk.radius == 0.05           # overrides win over the file
    assert bulk.density == 1600.0                                   # the sand preset under both
    (tmp_path / "bad.yaml").write_text("preset: sand\nfriction_angel_deg: 31.5\n")
    code = main(["validate", str(scene_path), "--set", f"soil.preset_file={tmp_path / 'bad.yaml'}"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "soil.preset_file" in err and "friction_angel_deg: unknown key" in err and "\n" not in err
    code = main(["validate", str(scene_path), "--set", f"soil.preset_file={tmp_path / 'fitted.yaml'}",
                 "--set", "soil.preset=dirt"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "builds on preset 'sand'" in err


def test_joint_log_from_a_ros2_bag(tmp_path):
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    t = np.arange(0.0, 10.0, 0.01)
    q = {"boom_joint": 0.4 * np.sin(0.5 * t), "arm_joint": 1.0 + 0.3 * np.cos(0.4 * t)}
    run = make_run(tmp_path / "run", joints=(t, q))
    ts = get_typestore(Stores.ROS2_HUMBLE)
    JointState, Header, Time = (ts.types[n] for n in ("sensor_msgs/msg/JointState", "std_msgs/msg/Header",
                                                        "builtin_interfaces/msg/Time"))
    with Writer(tmp_path / "bag", version=8) as writer:
        conn = writer.add_connection("/zx120/joint_states", JointState.__msgtype__, typestore=ts)
        other = writer.add_connection("/zx120/other_joint_states_not", JointState.__msgtype__, typestore=ts)
        for ti in np.arange(0.0, 10.0, 0.02):
            stamp = int(round((1.7e9 + ti) * 1e9))
            lag = ti - 0.3   # the machine 0.3 s behind the run
            msg = JointState(header=Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=""),
                             name=["arm_joint", "boom_joint", "swing_joint"],
                             position=np.array([1.0 + 0.3 * np.cos(0.4 * lag), 0.4 * np.sin(0.5 * lag), 0.0]),
                             velocity=np.zeros(3), effort=np.zeros(3))
            writer.write(conn, stamp, ts.serialize_cdr(msg, JointState.__msgtype__))
            writer.write(other, stamp, ts.serialize_cdr(msg, JointState.__msgtype__))
    res = cmp.compare(run, joints=tmp_path / "bag", out=tmp_path / "cmp")
    assert set(res["joints"]) == {"arm_joint", "boom_joint"}  # swing_joint: not in the run
    assert res["joints_lag_s"] == pytest.approx(-0.3, abs=0.011) and res["joints_rate_ratio"] == pytest.approx(1, 0.02)


# ----------------------------------------------------------------------------------------------- QA findings
def machine_las(path: Path, after=True, keep=None, dz=0.0, density=800.0):
    """A scan already in the machine frame (no transform needed), optionally only where keep(x, y)."""
    pts = scan_points(after=after, density=density) @ TRUE.matrix().T + [TRUE.x, TRUE.y, TRUE.z]
    if keep is not None:
        pts = pts[keep(pts[:, 0], pts[:, 1])]
    write_las(path, pts + [0.0, 0.0, dz])
    return path


def test_a_scan_covering_little_of_the_dig_is_refused_a_partial_one_compared_on_what_it_covers(tmp_path, capsys):
    run = make_run(tmp_path / "run")
    strip = machine_las(tmp_path / "strip.las", keep=lambda x, y: x < 3.2)   # beside the trench, not on it
    code, err = _cli([run, "--terrain", strip, "--out", tmp_path / "strip"], capsys)
    assert code == 2 and "--terrain: scan strip.las covers" in err and "of the dig area" in err and "\n" not in err
    assert not (tmp_path / "strip" / "comparison.json").exists()
    # two thirds of the trench: its volume and the run's taken on the same cells, so they agree; a warning says so
    half = machine_las(tmp_path / "half.las", keep=lambda x, y: x < 6.2)
    res = cmp.compare(run, terrain=half, out=tmp_path / "half")
    assert 0.5 < res["reference_coverage_of_dig_area"] < 0.9
    assert res["cut_volume_relative_error"] == pytest.approx(0.0, abs=0.03)
    assert res["cut_volume_m3"] < 0.9 * truth()["cut"]  # the run's cut on the covered cells only
    assert res["compared_area_m2"] < res["dig_area_m2"]
    saved = json.loads((tmp_path / "half" / "comparison.json").read_text())
    assert any("covers only" in w for w in saved["warnings"])
    assert "covers only" in capsys.readouterr().err


def test_a_heightmap_on_the_run_grid_is_taken_exactly(tmp_path):
    run = make_run(tmp_path / "run")
    res = cmp.compare(run, terrain=run / "terrain_final.npz", terrain_before=run / "terrain_initial.npz",
                      out=tmp_path / "same")
    assert res["terrain_rmse_m"] == 0.0 and res["terrain_max_abs_error_m"] == 0.0
    assert res["reference_max_depth_m"] == res["max_depth_m"]
    assert res["reference_cut_volume_m3"] == res["cut_volume_m3"]
    # a crop of it, on the same nodes: still exact where it covers
    with np.load(run / "terrain_final.npz") as f:
        np.savez(tmp_path / "crop.npz", x=f["x"][20:150], y=f["y"][10:110], z=f["z"][20:150, 10:110])
    crop = cmp.compare(run, terrain=tmp_path / "crop.npz", out=tmp_path / "crop")
    assert crop["terrain_rmse_m"] == 0.0


def test_a_rerun_replaces_all_outputs_and_out_refuses_another_runs_folder(tmp_path, capsys):
    t = np.arange(0.0, 10.0, 0.01)
    q = {"boom_joint": 0.4 * np.sin(0.5 * t)}
    run = make_run(tmp_path / "run", joints=(t, q))
    other = make_run(tmp_path / "other")
    out = tmp_path / "cmp"
    cmp.compare(run, terrain=run / "terrain_final.npz", joints=run / "joints.csv", out=out)
    assert (out / "comparison_joints.png").is_file()
    cmp.compare(run, terrain=run / "terrain_final.npz", out=out)
    assert not (out / "comparison_joints.png").exists()  # no figure left from the earlier compare
    assert "joints" not in json.loads((out / "comparison.json").read_text())
    before = sorted(p.name for p in other.iterdir())
    code, err = _cli([run, "--joints", run / "joints.csv", "--out", other], capsys)
    assert code == 2 and "--out:" in err and "run folder of another run" in err and "\n" not in err
    assert sorted(p.name for p in other.iterdir()) == before
    code, err = _cli([other, "--against", other, "--out", out], capsys)  # out holds run's comparison
    assert code == 2 and "--out:" in err and "comparison of another run" in err
    # nor a folder inside another run's folder (it wrote there), new or one of its own; the compared run's is fine
    for inside in (other / "cmp_of_run", other / "checkpoints"):
        code, err = _cli([run, "--joints", run / "joints.csv", "--out", inside], capsys)
        assert code == 2 and f"lies inside the run folder {other.resolve()}" in err and "\n" not in err
    assert sorted(p.name for p in other.iterdir()) == before
    assert _cli([run, "--joints", run / "joints.csv", "--out", run / "cmp"], capsys)[0] == 0


def test_a_las_in_us_survey_feet_is_refused(tmp_path, capsys, monkeypatch):
    pyproj = pytest.importorskip("pyproj")  # in the studies and test extras
    run = make_run(tmp_path / "run")
    pts = scan_points(after=True, density=50) @ TRUE.matrix().T + [TRUE.x, TRUE.y, TRUE.z]
    for name, epsg in (("feet.las", 2227), ("metres.las", 32654)):
        header = laspy.LasHeader(point_format=3, version="1.4")
        header.offsets, header.scales = pts.min(axis=0), [0.001] * 3
        header.add_crs(pyproj.CRS.from_epsg(epsg))
        las = laspy.LasData(header)
        las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
        las.write(str(tmp_path / name))
    code, err = _cli([run, "--terrain", tmp_path / "feet.las", "--out", tmp_path / "f"], capsys)
    assert code == 2 and "feet.las: the file declares its units as us survey foot" in err
    assert scans.read_scan(tmp_path / "metres.las").units == "m"
    # an install without pyproj cannot check the declared units: it says so instead of reading feet as metres
    monkeypatch.setitem(sys.modules, "pyproj", None)
    code, err = _cli([run, "--terrain", tmp_path / "feet.las", "--out", tmp_path / "f"], capsys)
    assert code == 2 and "declares a coordinate system; checking its units needs pyproj" in err and "\n" not in err


def test_the_profile_title_names_the_dig_lines_origin(tmp_path, monkeypatch):
    from opera_taichi.studies import figures

    titles = []
    monkeypatch.setattr(figures, "_save", lambda fig, path: titles.append(fig.axes[0].get_title()))
    run = make_run(tmp_path / "run")
    res = cmp.compare(run, against=run, out=tmp_path / "self")
    ox, oy = res["dig_line"]["origin_xy_m"]
    assert any(f"x {ox:.2f}, y {oy:.2f} m" in t for t in titles), titles


def test_misplaced_scan_threshold_and_flag_order_are_refused(tmp_path, capsys):
    run = make_run(tmp_path / "run")
    high = machine_las(tmp_path / "high.las", dz=1.5)
    code, err = _cli([run, "--terrain", high, "--out", tmp_path / "h"], capsys)
    assert code == 2 and "lies 1.5 m above the run's initial terrain" in err and "\n" not in err
    after = machine_las(tmp_path / "after.las")
    code, err = _cli([run, "--terrain", after, "--change-threshold", "5", "--out", tmp_path / "t"], capsys)
    assert code == 2 and "--change-threshold: neither the run nor" in err and "largest change 0.5" in err
    code, err = _cli([run, "--terrain-before", after], capsys)
    assert code == 2 and err == "error: --terrain-before: needs --terrain (the scan after the dig)"


def test_a_fit_gone_wrong_is_flagged(tmp_path, capsys):
    """Started 40 deg off in yaw, the rigid fit settles on a wrong placement; its residual says so."""
    from scipy.spatial.transform import Rotation

    run = make_run(tmp_path / "run")
    write_las(tmp_path / "after.las", scan_points(after=True, seed=3, density=800))
    rz, c = Rotation.from_euler("z", 40.0, degrees=True).as_matrix(), np.array([6.0, 0.0, 0.0])
    start = scans.Transform(*(rz @ (np.array([TRUE.x, TRUE.y, TRUE.z]) - c) + c),
                            *Rotation.from_matrix(rz @ TRUE.matrix()).as_euler("xyz"))
    res = cmp.compare(run, terrain=tmp_path / "after.las", transform=start, fit="rigid", out=tmp_path / "c",
                      figures=False)
    assert placement_error(res["transform"]) > 0.5  # it did go wrong
    assert any("the fitted placement looks wrong" in w for w in res["warnings"])
    assert "warning: --terrain: the fitted placement looks wrong" in capsys.readouterr().err


def test_joint_logs_in_other_units_a_clock_time_and_a_still_noisy_joint(tmp_path, capsys):
    """Field logs as they come: degrees under radian names are refused, clock (epoch) time is compared from its
    first sample, t in milliseconds is warned of, and a joint that stands still under sensor noise gets no rate
    ratio or lag (its noise's would pull the medians: 0.2 deg of noise read a ratio of 1e-4 and a lag of 1.5 s)."""
    t = np.arange(0.0, 20.0, 0.01)
    q = {"swing_joint": np.zeros_like(t), "boom_joint": 0.4 * np.sin(0.5 * t), "arm_joint": 1.0 + 0.3 * np.cos(0.4 * t)}
    run = make_run(tmp_path / "run", joints=(t, q))
    rng = np.random.default_rng(0)

    def log(name, t_log, scale=1.0, noise=0.0):
        path = tmp_path / name
        with open(path, "w") as fh:
            fh.write("t,swing_joint,boom_joint,arm_joint\n")
            for ti, tl in zip(np.arange(0.0, 20.0, 0.02), t_log):
                vals = [0.0, 0.4 * math.sin(0.5 * ti), 1.0 + 0.3 * math.cos(0.4 * ti)]
                vals = [scale * v + noise * rng.standard_normal() for v in vals]
                fh.write(f"{tl:.6f}," + ",".join(f"{v:.6f}" for v in vals) + "\n")
        return path

    steps = np.arange(0.0, 20.0, 0.02)
    code, err = _cli([run, "--joints", log("deg.csv", steps, scale=math.degrees(1.0)), "--out", tmp_path / "c1"],
                     capsys)
    assert code == 2 and "\n" not in err and "a log in degrees? name its column" in err
    clock = cmp.compare(run, joints=log("clock.csv", steps + 1.76e9), out=tmp_path / "c2")
    assert clock["joints_rmse_rad"] < 1e-5 and clock["joints_lag_s"] == 0.0
    noisy = cmp.compare(run, joints=log("noisy.csv", steps, noise=math.radians(0.2)), out=tmp_path / "c3")
    swing = noisy["joints"]["swing_joint"]
    assert not swing["moving"] and swing["rate_ratio"] is None and swing["lag_s"] is None
    assert noisy["joints"]["boom_joint"]["moving"] and noisy["joints_lag_s"] == 0.0
    assert noisy["joints_rate_ratio"] == pytest.approx(1.0, abs=0.1)
    capsys.readouterr()
    ms = cmp.compare(run, joints=log("ms.csv", steps * 1000.0), out=tmp_path / "c4")
    assert any("milliseconds" in w for w in ms["warnings"]) and "milliseconds" in capsys.readouterr().err


def test_a_field_dig_wider_than_the_runs_is_not_taken_for_a_misplaced_scan(tmp_path):
    """The reference dug a trench twice as wide as the run's, and its scan is cropped close to the dig: most of the
    ground the run left alone is dug in the reference (the old median test read that as a scan placed 0.5 m low and
    refused it). Only a scan off nearly all that ground one way is misplaced."""
    run = make_run(tmp_path / "run", relief=False)
    gx, gy = np.meshgrid(X, Y, indexing="ij")
    t = TRENCH
    fx = _smoothstep((gx - t["x0"]) / t["ramp"]) * _smoothstep((t["x1"] - gx) / t["ramp"])
    wide = -t["depth"] * fx * _smoothstep((2 * t["half_width"] - np.abs(gy)) / 0.15)
    z = ground(gx, gy, relief=False) + wide + heave(gx, gy)
    keep = (np.abs(gy) < 1.1) & (gx > 4.4) & (gx < 7.1)           # a scan of the dig and a little around it
    np.savez(tmp_path / "wide.npz", x=X, y=Y, z=np.where(keep, z, np.nan))
    res = cmp.compare(run, terrain=tmp_path / "wide.npz", out=tmp_path / "wide")
    assert res["reference_cut_volume_m3"] > 1.5 * res["cut_volume_m3"]   # the wider dig is measured, not refused
    # ... where the median of the reference's change over the run's undisturbed ground was well below the threshold
    run_dug = np.abs(trench(gx, gy) + heave(gx, gy)) > 0.02
    still = keep & ~run_dug
    assert np.median(wide[still]) < -0.1


# ----------------------------------------------------------------------------------------------- a swing over turns
SWING_TURN = math.radians(400.0)  # one dig-and-dump cycle swings 400 deg one way (6.98 rad)


def joint_log(path, t, joint, q):
    """A field joint log: a `t` column and one joint's column (written as `joint`, rad unless named `_deg`)."""
    np.savetxt(path, np.column_stack([t, q]), delimiter=",", fmt="%.6f", header=f"t,{joint}", comments="")
    return path


def swing_cycles(t):
    """The upper structure, unwrapped: each 12 s cycle swings SWING_TURN in 8 s (cosine profile, 1.37 rad/s at
    most: a machine a little quicker than the zx120's 1.2 rad/s limit), then stands 4 s to dig."""
    k, tau = np.divmod(np.asarray(t, float), 12.0)
    return SWING_TURN * (k + 0.5 * (1.0 - np.cos(math.pi * np.minimum(tau / 8.0, 1.0))))


def test_a_swing_over_several_turns_in_radians_compares_and_in_degrees_is_refused(tmp_path, capsys):
    """The run is one cycle (swing 0..6.98 rad); the field log five (0..34.9 rad): beyond a turn and beyond the run,
    which the range check alone read as degrees. The swing is continuous in the zx120's URDF, so only its rate can
    tell: in rad/s it is the machine's, in degrees it is 57 x that."""
    t = np.arange(0.0, 12.0, 0.01)
    q = {"swing_joint": swing_cycles(t), "boom_joint": 0.4 * np.sin(0.5 * t)}
    run = make_run(tmp_path / "run", joints=(t, q))
    tl = np.arange(0.0, 60.0, 0.02)

    def log(name, swing, header="swing_joint"):
        path = tmp_path / name
        np.savetxt(path, np.column_stack([tl, swing, 0.4 * np.sin(0.5 * tl)]), delimiter=",", fmt="%.6f",
                   header=f"t,{header},boom_joint", comments="")
        return path

    assert swing_cycles(tl).max() > 3 * SWING_TURN + 1.0 > 2 * math.pi  # what the range check refused
    res = cmp.compare(run, joints=log("rad.csv", swing_cycles(tl)), out=tmp_path / "rad", figures=False)
    swing = res["joints"]["swing_joint"]
    assert swing["rmse_rad"] < 1e-4 and swing["lag_s"] == 0.0 and swing["rate_ratio"] == pytest.approx(1.0, 0.01)
    assert "warnings" not in res
    # the same log with the swing in degrees under its radian name: refused, one line naming file and column
    code, err = _cli([run, "--joints", log("deg.csv", np.degrees(swing_cycles(tl))), "--out", tmp_path / "deg"],
                     capsys)
    assert code == 2 and "\n" not in err and "deg.csv: swing_joint moves at" in err
    assert "machine's limit of 1.2 rad/s" in err and "name its column swing_joint_deg" in err
    assert not (tmp_path / "deg" / "comparison.json").exists()
    # ... and named as degrees, the same file compares as the radian one
    deg = cmp.compare(run, joints=log("named.csv", np.degrees(swing_cycles(tl)), "swing_joint_deg"),
                      out=tmp_path / "named", figures=False)
    assert deg["joints"]["swing_joint"]["rmse_rad"] < 1e-4
    # a swing logged wrapped to +-pi steps 2 pi in one sample at each half turn: a wrap, not a 21 rad/s swing
    wrapped = np.angle(np.exp(1j * swing_cycles(tl)))
    assert np.max(np.abs(np.diff(wrapped))) > 6.0
    res = cmp.compare(run, joints=log("wrapped.csv", wrapped), out=tmp_path / "wrapped", figures=False)
    # ... compared unwrapped, on the run's turn: the same motion (the CSV's 6 decimals and the wrap's rounding)
    assert res["joints"]["swing_joint"]["rmse_rad"] < 1e-4
    # a log whose zero is a turn away (an encoder counting from another turn) is the same motion too
    res = cmp.compare(run, joints=log("turn.csv", swing_cycles(tl) - 4 * math.pi), out=tmp_path / "turn",
                      figures=False)
    assert res["joints"]["swing_joint"]["rmse_rad"] < 1e-4
    # another run's joints.csv is in radians by the run folder's contract: never refused as degrees
    five = make_run(tmp_path / "five", joints=(tl, {"swing_joint": swing_cycles(tl)}))
    other = cmp.compare(run, against=five, out=tmp_path / "against", figures=False)
    assert other["joints"]["swing_joint"]["rmse_rad"] < 1e-4


def test_a_swing_wrapped_to_pi_parked_on_the_wrap_compares_and_a_slow_swing_in_degrees_is_refused(tmp_path,
                                                                                                      capsys):
    """A swing that dumps behind the machine parks at 180 deg, where a log wrapped to +-pi flips between +pi and -pi
    with its sensor's noise every sample (no isolated wrap: it read 13 rad/s, 'a log in degrees?'); a wrap resampled
    over two samples (a bag's missing message) is a wrap too. A swing in degrees too slow for the rate check (0.05
    rad/s) sweeps 57 x the run's angle over the run's span."""
    t = np.arange(0.0, 12.0, 0.01)
    swing = np.minimum(0.5 * t, math.pi)                  # to 180 deg in 6.3 s, then parked there
    run = make_run(tmp_path / "run", joints=(t, {"swing_joint": swing}))
    noisy = swing + np.random.default_rng(0).normal(0.0, 0.002, t.size)
    wrapped = np.angle(np.exp(1j * noisy))
    assert np.sum(np.abs(np.diff(wrapped)) > math.pi) > 100       # flips at nearly every sample once parked
    joint_log(tmp_path / "parked.csv", t, "swing_joint", wrapped)
    res = cmp.compare(run, joints=tmp_path / "parked.csv", out=tmp_path / "parked", figures=False)
    assert res["joints"]["swing_joint"]["rmse_rad"] < 0.01
    # a swing through the wrap and on (to 270 deg), the wrap's sample dropped and resampled in between
    through = np.minimum(0.5 * t, 1.5 * math.pi)
    run2 = make_run(tmp_path / "run2", joints=(t, {"swing_joint": through}))
    w = np.angle(np.exp(1j * through))
    k = int(np.argmax(np.abs(np.diff(w)) > math.pi)) + 1
    w[k] = 0.7 * w[k - 1] + 0.3 * w[k + 1]                     # the wrap spread over two samples
    joint_log(tmp_path / "through.csv", t, "swing_joint", w)
    res = cmp.compare(run2, joints=tmp_path / "through.csv", out=tmp_path / "through", figures=False)
    assert res["joints"]["swing_joint"]["rmse_rad"] < 0.5      # one sample off by up to pi, not 2 pi from there on
    # a slow swing (0.05 rad/s for 12 s) logged in degrees under its radian name
    slow = 0.05 * t
    run3 = make_run(tmp_path / "run3", joints=(t, {"swing_joint": slow}))
    joint_log(tmp_path / "slow.csv", t, "swing_joint", np.degrees(slow))
    code, err = _cli([run3, "--joints", tmp_path / "slow.csv", "--out", tmp_path / "c"], capsys)
    assert code == 2 and "\n" not in err and "slow.csv: swing_joint sweeps 34.3" in err
    assert "name its column swing_joint_deg" in err


def test_a_bounded_joint_in_degrees_is_refused_by_its_rate_when_its_range_cannot_tell(tmp_path, capsys):
    """A boom logged in degrees that moves within +-5 deg (at up to 10 deg/s) stays within a turn (5 'rad'), which
    the range check lets through; its rate, 57 x the boom's, does not."""
    t = np.arange(0.0, 20.0, 0.01)
    boom = math.radians(5.0) * np.sin(2.0 * t)
    run = make_run(tmp_path / "run", joints=(t, {"boom_joint": boom}))
    joint_log(tmp_path / "boom.csv", t, "boom_joint", np.degrees(boom))
    code, err = _cli([run, "--joints", tmp_path / "boom.csv", "--out", tmp_path / "c"], capsys)
    assert code == 2 and "\n" not in err and "boom.csv: boom_joint moves at" in err
    assert "machine's limit of 0.7 rad/s" in err


def test_a_run_whose_machine_cannot_be_read_falls_back_to_the_range_check_and_says_so(tmp_path, capsys):
    t = np.arange(0.0, 12.0, 0.01)
    run = make_run(tmp_path / "run", joints=(t, {"swing_joint": swing_cycles(t)}))
    manifest = json.loads((run / "manifest.json").read_text())
    manifest["scene"]["machine"]["urdf"] = str(tmp_path / "moved" / "zx120.urdf")  # a run folder from elsewhere
    (run / "manifest.json").write_text(json.dumps(manifest))
    tl = np.arange(0.0, 60.0, 0.02)
    joint_log(tmp_path / "rad.csv", tl, "swing_joint", swing_cycles(tl))
    code, err = _cli([run, "--joints", tmp_path / "rad.csv", "--out", tmp_path / "c"], capsys)
    assert code == 2 and "warning: RUN_DIR: the run's machine description cannot be read" in err
    assert "zx120.urdf does not exist" in err and "a log in degrees? name its column swing_joint_deg" in err


def test_the_fitted_placement_does_not_depend_on_the_order_of_the_points(tmp_path):
    """A scan larger than the fit's subset: its points shuffled, the same transform to the bit (the subset was
    drawn by index, so the file's order chose the points)."""
    run = make_run(tmp_path / "run")
    pts = scan_points(after=True, seed=3)
    assert len(pts) > scans.MAX_FIT_POINTS
    np.savetxt(tmp_path / "after.xyz", pts, fmt="%.6f")
    np.savetxt(tmp_path / "shuffled.xyz", pts[np.random.default_rng(0).permutation(len(pts))], fmt="%.6f")
    a, b = (cmp.compare(run, terrain=tmp_path / name, fit="auto", out=tmp_path / name[:-4], figures=False)
            for name in ("after.xyz", "shuffled.xyz"))
    assert a["transform"] == b["transform"]


def test_nodata_and_units_as_gis_tools_write_them(tmp_path):
    """A float32 GeoTIFF's nodata written as -9999.9 (no float32 holds it) or as the float's maximum (ArcGIS) is no
    height; units declared only through the coordinate system's EPSG code (a GeoTIFF's projected CRS, a LAS file's
    GeoKeyDirectory with a vertical units key) are read, so a scan in feet is refused, not taken as metres."""
    from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct

    from opera_taichi.errors import UserError

    z = np.full((6, 8), 1.5, np.float32)
    z[:2, :3] = 0.0
    place = [(33550, "d", 3, (0.1, 0.1, 0.0)), (33922, "d", 6, (0.0, 0.0, 0.0, 100.0, 200.0, 0.0))]
    # a Leica PTS file: its point count on the first line, then x y z intensity r g b
    (tmp_path / "scan.pts").write_text("3\n0 0 1.5 100 1 2 3\n1 0 1.5 100 1 2 3\n0 1 1.5 100 1 2 3\n")
    assert scans.read_scan(tmp_path / "scan.pts").points.tolist() == [[0, 0, 1.5], [1, 0, 1.5], [0, 1, 1.5]]
    for nodata in ("-9999.9", "-3.40282346639e+038"):
        z[:2, :3] = np.float32(float(nodata))
        tifffile.imwrite(str(tmp_path / "nodata.tif"), z, extratags=place + [(42113, "s", 0, nodata)])
        scan = scans.read_scan(tmp_path / "nodata.tif")
        assert len(scan.points) == 48 - 6 and np.all(scan.points[:, 2] == 1.5), nodata
    # an integer raster whose nodata no int16 holds: a height of 0 stays a height
    heights = np.full((6, 8), 7, np.int16)
    heights[0, 0] = 0
    tifffile.imwrite(str(tmp_path / "int.tif"), heights, extratags=place + [(42113, "s", 0, "-3.4e38")])
    assert len(scans.read_scan(tmp_path / "int.tif").points) == 48
    for geokeys, words in [((3072, 2229), "us survey foot"), ((3072, 32654), None)]:
        keys = (1, 1, 0, 2, 1024, 0, 1, 1, *geokeys[:1], 0, 1, geokeys[1])
        tifffile.imwrite(str(tmp_path / "crs.tif"), z, extratags=place + [(34735, "H", len(keys), keys)])
        if words is None:
            assert scans.read_scan(tmp_path / "crs.tif").units == "m"
        else:
            with pytest.raises(UserError, match=f"declares its units as {words}"):
                scans.read_scan(tmp_path / "crs.tif")
    pts = scan_points(after=True, density=20)
    for keys, words in [([(1024, 1), (3072, 32654), (4099, 9002)], "foot"), ([(1024, 1), (3072, 32654)], None)]:
        header = laspy.LasHeader(point_format=3, version="1.2")
        header.offsets, header.scales = pts.min(axis=0), [0.001] * 3
        vlr = GeoKeyDirectoryVlr()
        vlr.geo_keys_header.key_directory_version, vlr.geo_keys_header.key_revision = 1, 1
        vlr.geo_keys_header.number_of_keys = len(keys)
        entries = []
        for key, value in keys:
            entry = GeoKeyEntryStruct()
            entry.id, entry.tiff_tag_location, entry.count, entry.value_offset = key, 0, 1, value
            entries.append(entry)
        vlr.geo_keys = entries
        header.vlrs.append(vlr)
        las = laspy.LasData(header)
        las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
        las.write(str(tmp_path / "keys.las"))
        if words is None:
            assert scans.read_scan(tmp_path / "keys.las").units == "m"
        else:
            with pytest.raises(UserError, match=f"declares its units as {words}"):
                scans.read_scan(tmp_path / "keys.las")


def test_a_fit_from_the_true_placement_keeps_it_when_the_scans_grains_differ_from_the_runs():
    """A bed of grains in a pit (a run's terrain) and a scan of another realisation of the grains with a wide dig:
    every stage of the fit must keep the ground on the terrain. A point off the grid once cost nothing, so the fit
    slid the scan metres off to shed the dig's outliers."""
    from scipy.ndimage import gaussian_filter
    from scipy.interpolate import RegularGridInterpolator

    gxs, gys = 2.5 + CELL * np.arange(140), -2.0 + CELL * np.arange(80)   # 7 m x 4 m, like the main scene's pit
    gx, gy = np.meshgrid(gxs, gys, indexing="ij")

    def bed(x, y, seed):  # grains 3 cm rough, 8 cm below the pit's rim; a different seed: other grains
        g = gaussian_filter(np.random.default_rng(seed).normal(size=gx.shape), 1.2)
        g = RegularGridInterpolator((gxs, gys), 0.03 * g / g.std())(np.column_stack([x, y]))
        inside = (x > gxs[0] + 0.15) & (x < gxs[-1] - 0.15) & (y > gys[0] + 0.15) & (y < gys[-1] - 0.15)
        return np.where(inside, -0.08 + g, 0.0)

    def dig(x, y):  # 5 m x 2.2 m, half a metre deep: 40% of the scan is off the initial ground
        fx = np.clip((x - 3.5) / 0.3, 0, 1) * np.clip((8.5 - x) / 0.3, 0, 1)
        return -0.5 * fx * np.clip((1.1 - np.abs(y)) / 0.2, 0, 1)

    z0 = bed(gx.ravel(), gy.ravel(), 1).reshape(gx.shape)
    rng = np.random.default_rng(2)
    x, y = rng.uniform(gxs[0], gxs[-1], 12000), rng.uniform(gys[0], gys[-1], 12000)
    pts = np.column_stack([x, y, bed(x, y, 2) + dig(x, y)])   # in the run's frame: the truth is the identity
    ground = float(np.mean(dig(x, y) == 0))
    for start in (scans.Transform(0, 0, 0), scans.Transform(0.15, -0.1, 0.05, yaw=math.radians(2))):
        fit = scans.fit_transform(pts, gxs, gys, z0, start, mode="rigid")
        moved = float(np.abs(fit.transform.apply(pts) - pts).max())
        assert moved < 0.05, (moved, fit.describe())  # within a cell: the grains are 3 cm rough
        assert fit.inlier_fraction > 0.9 * ground, fit.describe()


def test_runs_without_soil_compare_by_their_joints(tmp_path):
    t = np.arange(0.0, 10.0, 0.01)
    q = {"boom_joint": 0.4 * np.sin(0.5 * t), "arm_joint": 1.0 + 0.3 * np.cos(0.4 * t)}
    run = make_run(tmp_path / "run", joints=(t, q))
    for name in ("terrain_initial.npz", "terrain_final.npz"):  # a scene with no soil writes no terrain
        (run / name).unlink()
    same = cmp.compare(run, against=run, out=tmp_path / "self")
    assert same["joints_rmse_rad"] == 0.0 and same["joints_lag_s"] == 0.0
    assert same["joints_rate_ratio"] == pytest.approx(1.0)
    assert "terrain_rmse_m" not in same


def test_the_dig_area_grows_by_a_disc_of_the_margin_and_an_endless_margin_is_refused(tmp_path, capsys):
    from scipy.ndimage import binary_dilation

    rng = np.random.default_rng(3)
    dz = np.where(rng.random((60, 45)) > 0.995, 0.1, 0.0)
    for m in (1, 3, 7, 200):
        k = np.arange(-m, m + 1)
        disc = (k[:, None] ** 2 + k[None, :] ** 2) <= m ** 2
        assert np.array_equal(cmp.dig_area([dz], 0.02, m), binary_dilation(np.abs(dz) > 0.02, disc)), m
    run = make_run(tmp_path / "run")
    for bad in ("inf", "nan", "-1"):
        code, err = _cli([run, "--against", run, "--margin", bad], capsys)
        assert code == 2 and "--margin: expected a finite distance" in err and "\n" not in err, bad
    res = cmp.compare(run, against=run, out=tmp_path / "wide", margin_m=1e4)  # the whole grid, at once
    assert res["dig_area_m2"] == pytest.approx(len(X) * len(Y) * CELL ** 2)


def test_a_scan_with_heights_in_centimetres_is_refused_placed_or_fitted(tmp_path, capsys):
    run = make_run(tmp_path / "run")
    gx, gy = np.meshgrid(X, Y, indexing="ij")
    z = ground(gx, gy) + trench(gx, gy) + heave(gx, gy)
    pts = np.stack([gx.ravel(), gy.ravel(), 100.0 * z.ravel()], axis=1)  # x, y in m, heights in cm
    np.savetxt(tmp_path / "cm.xyz", pts)
    for extra in ([], ["--fit-transform"]):
        code, err = _cli([run, "--terrain", tmp_path / "cm.xyz", *extra], capsys)
        assert code == 2 and "heights in centimetres" in err and "\n" not in err, extra
    # wider than its heights span (four far corners): refused on the run's terrain, where it is placed
    corners = np.array([[sx * 150.0, sy * 150.0, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    np.savetxt(tmp_path / "wide_cm.xyz", np.vstack([pts, corners]))
    code, err = _cli([run, "--terrain", tmp_path / "wide_cm.xyz"], capsys)
    assert code == 2 and "over the run's terrain" in err and "heights in centimetres" in err
    np.savetxt(tmp_path / "m.xyz", pts * [1.0, 1.0, 0.01])  # the same scan in metres compares
    assert cmp.compare(run, terrain=tmp_path / "m.xyz", out=tmp_path / "m")["terrain_rmse_m"] < 0.01
    low = pts * [1.0, 1.0, 0.01] - [0.0, 0.0, 3.0]
    np.savetxt(tmp_path / "low.xyz", low)
    code, err = _cli([run, "--terrain", tmp_path / "low.xyz"], capsys)
    assert code == 2 and "lies 3 m below" in err
