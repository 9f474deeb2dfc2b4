"""The README's main job: `cli.py run scenes/zx120_excavation.yaml` digs a trench and carries soil in the bucket.

One full run (25 s simulated, ~4 min on 2 cores) at the scene's own resolution; the assertions are the issue's
acceptance: bucket load at the end of the curl, trench depth along the dig path, soil mass conserved.
"""
import json
import math
from pathlib import Path

import numpy as np
import pytest

from opera_taichi.cli import main
from opera_taichi.recorders import read_csv_columns

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "zx120_excavation.yaml"
CURL_END = 20.0         # s: the dig path's curl waypoint
PATH_X = (4.4, 6.4)     # m: the dig path's cut (the ramp in reaches 0.3 m deep at x = 6.3, the drag ends at 4.4)
PATH_Y = -0.164         # m: the boom's plane


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("excavation") / "run"
    rc = main(["run", str(SCENE), "--out", str(out), "--quiet", "--set", "output.plots=false"])
    assert rc == 0
    return out


# The ZX120 bucket's cutting edge and the back edge of its opening, in the bucket-link frame (x, z): vertices of
# the collision mesh (the shell plate's two ends)
BUCKET_EDGE_XZ = (0.0, 1.23)
BUCKET_LIP_XZ = (-0.237, -0.121)


def struck_volume(bucket) -> float:
    """Struck capacity (SAE J296 / ISO 7451): the cavity between the bucket's inner surfaces and the strike plane
    through the cutting edge and the back edge of the opening. The convex hull of the mesh cut by that plane,
    less the steel on the same side. The whole hull (0.63 m3) would also count the wedge between the opening and
    the pin lugs (0.15 m3) and the plates themselves."""
    edge = np.array([BUCKET_EDGE_XZ[0], 0.0, BUCKET_EDGE_XZ[1]])
    lip = np.array([BUCKET_LIP_XZ[0], 0.0, BUCKET_LIP_XZ[1]])
    for point in (edge, lip):  # the plane is pinned to the mesh: a changed mesh must change these constants
        assert np.min(np.linalg.norm(bucket.vertices[:, [0, 2]] - point[[0, 2]], axis=1)) < 1e-3
    normal = np.cross(edge - lip, [0.0, 1.0, 0.0])  # toward the cavity (the back of the bucket, -x)
    hull = bucket.convex_hull.slice_plane(lip, normal, cap=True)
    steel = bucket.slice_plane(lip, normal, cap=True)
    return float(hull.volume - steel.volume)


def test_struck_volume_of_the_zx120_bucket():
    """0.38 m3: the class of a ZX120's standard 0.45-0.5 m3 (heaped) bucket; the cavity is most of the hull."""
    from opera_taichi.machine_description import load_machine

    bucket = load_machine("zx120").collision_meshes["bucket_link"]
    v = struck_volume(bucket)
    assert 0.3 < v < 0.45
    assert load_machine("zx120").struck_volume["bucket_link"] == pytest.approx(v, abs=0.005)  # machine.yaml's figure
    assert v < bucket.convex_hull.volume - bucket.volume


@pytest.mark.slow
def test_bucket_carries_at_least_30_percent_of_its_struck_volume(run):
    from opera_taichi.machine_description import load_machine

    manifest = json.loads((run / "manifest.json").read_text())
    density = manifest["soil"]["bulk"]["density"]
    assert 0.3 < manifest["soil"]["bed_packing"] < 0.65  # a settled random packing of spheres, as recorded
    struck = struck_volume(load_machine("zx120").collision_meshes["bucket_link"])
    cols = read_csv_columns(run / "soil_mass.csv")
    at_curl = cols["in_bucket_link_kg"][np.argmin(np.abs(cols["t"] - CURL_END))]
    assert at_curl >= 0.3 * struck * density, (at_curl, struck, density)
    assert cols["in_bucket_link_kg"][-1] >= 0.3 * struck * density  # and it is still there after the lift


@pytest.mark.slow
def test_trench_is_at_least_0_3_m_deep_along_the_dig_path(run):
    before, after = np.load(run / "terrain_initial.npz"), np.load(run / "terrain_final.npz")
    x, y = after["x"], after["y"]
    cells = (x >= PATH_X[0]) & (x <= PATH_X[1])
    row = np.argmin(np.abs(y - PATH_Y))
    dz = (after["z"] - before["z"])[cells, row]
    # the path ends with the loaded bucket brought in over x = 3-4.2, off the trench (soil in a bucket hanging
    # over the trench would read as high ground). Measured: 0.31-0.69 m deep over all 2 m; asked: 1.5 m, leaving
    # the ends of the path (the ramp in from x = 7.0, the curl from 4.4) to the slopes of the cut
    deep = dz <= -0.3
    cell = float(x[1] - x[0])
    longest = max((len(s) for s in "".join("1" if d else "0" for d in deep).split("0")), default=0) * cell
    assert longest >= 1.5, dz


@pytest.mark.slow
def test_soil_mass_is_constant_over_the_excavation(run):
    cols = read_csv_columns(run / "soil_mass.csv")
    total = cols["mass_kg"]
    assert np.all(np.abs(total - total[0]) <= 1e-9 * total[0])


@pytest.mark.slow
def test_the_dig_path_stays_within_the_machines_torque_limits(run):
    """The path is one the machine can follow in this soil. A path that presses the bucket's flat bottom or its bowl
    into uncut soil pins the boom at its torque limit, and the bucket's force is then the machine's, whatever the soil
    (docs/dig_path.md: 32-48% of the run on the earlier path; this one 0%)."""
    summary = json.loads((run / "summary.json").read_text())
    pinned = {joint: a["at_torque_limit_fraction"] for joint, a in summary["actuators"].items()}
    assert max(pinned.values()) < 0.05, pinned


def _plate_elevation(kin, mesh, q) -> float:
    """Degrees above the horizontal at which the bucket's outer bottom rises behind the edge, away from the machine:
    the smallest elevation from the edge to the collision mesh 0.1-0.5 m behind it."""
    verts = np.c_[mesh.vertices, np.ones(len(mesh.vertices))]
    rel = (kin.link_pose(q, "bucket_link") @ verts.T).T[:, :3] - kin.tip_position(q)
    dist = np.hypot(rel[:, 0], rel[:, 2])
    behind = (dist > 0.1) & (dist < 0.5) & (rel[:, 0] > 0.0)
    return float(np.degrees(np.arctan2(rel[behind, 2], rel[behind, 0])).min())


def test_the_entry_keeps_the_buckets_flat_bottom_near_its_line():
    """Along the path's entry (waypoints 1 -> 2) the edge goes down at most 20 deg more steeply than the bucket's bottom
    plate rises behind it (the plate meets the ramp's soil at 6-18 deg), so the plate cuts in rather than bearing on
    the soil like a footing. The earlier path's plunge (63 deg with the plate at 6 to -1 deg) fails this."""
    from opera_taichi.kinematics import Kinematics
    from opera_taichi.machine_description import load_machine
    from opera_taichi.scene import load_scene

    desc = load_machine("zx120")
    kin, mesh = Kinematics(desc), desc.collision_meshes["bucket_link"]
    scene = load_scene(SCENE)
    wps = scene.motion.waypoints
    q = dict(scene.machine.initial_joints)  # rad

    def attack(a, b):
        p0, p1 = np.asarray(a.xyz, float), np.asarray(b.xyz, float)
        descent = math.degrees(math.atan2(p0[2] - p1[2], abs(p1[0] - p0[0])))
        worst, guess = -90.0, dict(q)
        for f in np.linspace(0.0, 1.0, 6):
            guess = kin.solve_tip(p0 + f * (p1 - p0), a.bucket_angle + f * (b.bucket_angle - a.bucket_angle),
                                  q_guess=guess)
            worst = max(worst, descent - _plate_elevation(kin, mesh, guess))
        return worst

    assert attack(wps[1], wps[2]) < 20.0
    plunge = [type(wps[1])(t=5.0, xyz=[6.5, -0.164, 0.1], bucket_angle_deg=105),
              type(wps[2])(t=8.0, xyz=[6.2, -0.164, -0.5], bucket_angle_deg=112)]
    assert attack(*plunge) > 50.0
