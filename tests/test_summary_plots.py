"""summary.json, the run-folder plots and the run list, checked against a small real excavation run: every number
of the summary is recomputed here from the run folder's files by a route of its own."""
import csv
import io
import json
import math
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest

from opera_taichi import plots
from opera_taichi.machine_description import load_machine
from opera_taichi.model import build_model
from opera_taichi.recorders import read_csv_columns
from opera_taichi.runs import FIELDS, format_table, list_runs, run_row, write_csv
from opera_taichi.summary import format_summary, joint_limits, summarize, write_summary

ROOT = Path(__file__).resolve().parent.parent
JOINTS = ["swing_joint", "boom_joint", "arm_joint", "bucket_joint"]
# 24 cm grains (~1,000 particles) and the dig path of the scene pressed into 9 s (approach 1.5 s, enter 3 s, drag
# to 6 s, curl to 7.5 s, lift to 9 s), so the bucket cuts, loads and lifts soil in ~30 s of wall time. (With 32 cm
# grains the load was one or two grains, and whether any stayed in the bucket turned on round-off: none did with
# soil.sleep.) Its start and entry are the scene's before 2026-11-28 (docs/dig_path.md): away from the rest pose, and
# a plunge with the bucket's bottom plate flat on the soil, so the boom and the arm reach their speed and torque
# limits (the scene's own path stays within them: tests/test_excavation.py).
OVERRIDES = ["soil.overrides.radius=0.12", "sim.duration=9", "output.plots=false",
             "motion.waypoints.0.xyz=[6.5, -0.164, 1.0]", "motion.waypoints.0.bucket_angle_deg=100",
             "motion.waypoints.1.xyz=[6.5, -0.164, 0.1]", "motion.waypoints.1.bucket_angle_deg=105",
             "motion.waypoints.2.xyz=[6.2, -0.164, -0.5]", "motion.waypoints.2.bucket_angle_deg=112"] + \
    [f"motion.waypoints.{i}.t={t}" for i, t in enumerate((0.0, 1.5, 3.0, 6.0, 7.5, 9.0))]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from opera_taichi.runner import run_scene
    from opera_taichi.scene import load_scene

    parent = tmp_path_factory.mktemp("runs")
    scene = load_scene(ROOT / "scenes" / "zx120_excavation.yaml", OVERRIDES)
    result = run_scene(scene, out_dir=parent / "dig", quiet=True)
    assert result.status == "done"
    model = build_model(scene)
    return result.out_dir, model


@pytest.fixture(scope="module")
def summary(run):
    run_dir, model = run
    return summarize(run_dir, model)


def _weights(t):
    """The summary's rule, written out: sample i stands for t[i+1] - t[i]; the last sample for nothing."""
    return np.array([t[i + 1] - t[i] for i in range(len(t) - 1)] + [0.0])


def test_bucket_mass_is_the_last_row_of_soil_mass_csv(run, summary):
    run_dir, model = run
    cols = read_csv_columns(run_dir / "soil_mass.csv")
    last = float(cols["in_bucket_link_kg"][-1])
    assert last > 0.0, "the pressed dig path should leave soil in the bucket"
    bucket = summary["tools"]["bucket_link"]
    assert bucket["soil_held_kg"] == pytest.approx(last, rel=1e-12)
    assert bucket["soil_held_m3"] == pytest.approx(last / 1474.0, rel=1e-12)   # dirt preset bulk density
    declared = getattr(model.machines[0].description, "struck_volume", None) or {}
    if "bucket_link" in declared:
        assert bucket["struck_volume_m3"] == pytest.approx(declared["bucket_link"])
        assert bucket["struck_volume_source"].startswith("machine description")
    else:
        mesh = model.bindings[0].mesh
        assert bucket["struck_volume_m3"] == pytest.approx(mesh.convex_hull.volume - mesh.volume, rel=1e-9)
        assert "convex hull" in bucket["struck_volume_source"]
    assert bucket["fill_factor"] == pytest.approx(last / 1474.0 / bucket["struck_volume_m3"], rel=1e-12)


def test_a_declared_struck_volume_is_used(run):
    """machine.yaml's `struck_volume` (the ZX120 bucket's 0.38 m3) sets the fill factor; a description without one
    falls back to the hull estimate and says so."""
    from types import SimpleNamespace

    run_dir, model = run
    bucket = summarize(run_dir, model)["tools"]["bucket_link"]
    last = float(read_csv_columns(run_dir / "soil_mass.csv")["in_bucket_link_kg"][-1])
    assert bucket["struck_volume_m3"] == 0.38
    assert bucket["struck_volume_source"] == "machine description (struck_volume)"
    assert bucket["fill_factor"] == pytest.approx(last / 1474.0 / 0.38, rel=1e-12)
    assert "(hull estimate)" not in format_summary(summarize(run_dir, model))
    m = model.machines[0]
    desc = SimpleNamespace(**{**vars(m.description), "struck_volume": {}})
    stub = SimpleNamespace(machines=(SimpleNamespace(name=m.name, description=desc),), bindings=model.bindings,
                           soil=model.soil)
    hull = summarize(run_dir, stub)["tools"]["bucket_link"]
    assert hull["struck_volume_m3"] > 0.38 and "hull" in hull["struck_volume_source"]


def test_dug_and_heaped_volumes_are_the_ground_heightmap_difference(run, summary):
    run_dir, _ = run
    z0 = np.load(run_dir / "terrain_initial.npz")
    z1 = np.load(run_dir / "terrain_final.npz")
    x, y = z0["x"], z0["y"]
    cell = (x[-1] - x[0]) / (len(x) - 1) * (y[-1] - y[0]) / (len(y) - 1)
    dug = heaped = 0.0
    for a, b in zip(z0["z"].ravel(), z1["z"].ravel()):
        dug += max(0.0, a - b) * cell
        heaped += max(0.0, b - a) * cell
    terrain = summary["terrain"]
    assert terrain["dug_m3"] == pytest.approx(dug, rel=1e-9)
    assert terrain["heaped_m3"] == pytest.approx(heaped, rel=1e-9)
    assert terrain["dug_m3"] > 0.2, "the bucket cut a trench"
    assert terrain["max_cut_depth_m"] == pytest.approx(float(np.max(z0["z"] - z1["z"])))
    # the ground heightmap leaves the bucket's load out: z_all stands above z where the lifted bucket is
    assert "z_all" in z1.files
    assert np.any(z1["z_all"] > z1["z"] + 0.05)
    assert terrain["above_ground_in_tools_m3"] > 0.0


def test_the_highest_heap_leaves_out_gaps_of_the_initial_bed(tmp_path):
    """summary.json's max_heap_height_m was a grain rolled into a gap where the initial heightmap showed the bed
    floor (0.81 m with 32 cm grains); such cells (more than a grain radius below the initial surface closed over a
    grain diameter) are left out of it, not out of the heaped volume."""
    x, y = np.arange(40) * 0.05, np.arange(30) * 0.05
    z0 = np.full((40, 30), -0.2)
    z0[20:23, 14] = -1.0                      # a gap 3 cells (15 cm) long: the bed floor
    z1 = z0.copy()
    z1[20:23, 14] = -0.25                     # a grain rolled in
    z1[5:8, 5:8] += 0.12                      # a heap of a grain or so
    for name, z in (("terrain_initial.npz", z0), ("terrain_final.npz", z1)):
        np.savez(tmp_path / name, x=x, y=y, z=z, t=0.0)
    (tmp_path / "manifest.json").write_text(json.dumps({"status": "done", "soil": {"micro": {"radius": 0.16}}}))
    terrain = summarize(tmp_path)["terrain"]
    assert terrain["max_heap_height_m"] == pytest.approx(0.12)
    assert terrain["heaped_m3"] == pytest.approx((9 * 0.12 + 3 * 0.75) * 0.05 ** 2)


def test_time_at_the_actuator_limits_agrees_with_joints_csv(run, summary):
    run_dir, _ = run
    cols = read_csv_columns(run_dir / "joints.csv")
    t = cols["t"]
    w = _weights(t)
    actuators = load_machine("zx120").actuators
    assert set(summary["actuators"]) == set(JOINTS)
    saturated = 0.0
    for joint in JOINTS:
        a = actuators[joint]
        torque_s = float(w[np.abs(cols[f"{joint}.effort"]) >= 0.99 * a.max_torque].sum())
        speed_s = float(w[np.abs(cols[f"{joint}.qd"]) >= 0.99 * a.max_speed].sum())
        got = summary["actuators"][joint]
        assert got["at_torque_limit_s"] == pytest.approx(torque_s, abs=1e-9), joint
        assert got["at_speed_limit_s"] == pytest.approx(speed_s, abs=1e-9), joint
        assert got["at_torque_limit_fraction"] == pytest.approx(torque_s / 9.0, abs=1e-9), joint
        assert got["at_speed_limit_fraction"] == pytest.approx(speed_s / 9.0, abs=1e-9), joint
        assert got["max_torque_Nm"] == a.max_torque and got["max_speed_rad_s"] == a.max_speed
        saturated += torque_s + speed_s
    # the plunge runs into the limits: the boom presses the bucket into the soil at its torque limit
    assert summary["actuators"]["boom_joint"]["at_torque_limit_s"] > 0.5
    assert saturated > 1.0
    assert joint_limits(run[1]) == {j: (actuators[j].max_speed, actuators[j].max_torque) for j in JOINTS}


def test_force_peak_and_mean_in_contact(run, summary):
    run_dir, _ = run
    cols = read_csv_columns(run_dir / "tool_wrench.csv")
    assert set(cols["tool"]) == {"bucket_link"}
    f = np.hypot(np.hypot(cols["fx"], cols["fy"]), cols["fz"])
    bucket = summary["tools"]["bucket_link"]
    assert bucket["peak_force_N"] == pytest.approx(f.max(), rel=1e-12)
    assert bucket["peak_force_time_s"] == cols["t"][int(np.argmax(f))]
    in_contact = f[f > 1.0]
    assert 0 < len(in_contact) < len(f)
    assert bucket["mean_force_in_contact_N"] == pytest.approx(in_contact.mean(), rel=1e-12)
    assert bucket["mean_force_in_contact_N"] > f.mean()   # the mean over all samples would count the air


def test_mass_balance_and_run_block(run, summary):
    run_dir, _ = run
    cols = read_csv_columns(run_dir / "soil_mass.csv")
    manifest = json.loads((run_dir / "manifest.json").read_text())
    mass = summary["mass_balance"]
    assert mass["initial_kg"] == cols["mass_kg"][0] and mass["final_kg"] == cols["mass_kg"][-1]
    assert mass["initial_kg"] > 1000.0
    assert abs(mass["relative_drift"]) < 1e-9
    assert mass["out_of_domain_kg"] == cols["out_of_domain_kg"][-1]
    assert summary["run"]["sim_time_s"] == pytest.approx(9.0)
    assert summary["run"]["real_time_factor"] == manifest["real_time_factor"] > 0
    assert summary["run"]["wall_time_s"] == manifest["wall_time_s"]


def test_every_key_names_its_unit(summary):
    units = ("_kg", "_m3", "_s", "_N", "_Nm", "_m", "_m2", "_rad_s", "_fraction", "_kg_m3")
    unitless = {"name", "status", "machines", "particles", "real_time_factor", "fill_factor", "relative_drift",
                "struck_volume_source", "heightmap", "source", "contact_samples", "force_samples", "soil_wedge"}
    leaves = [(k, v) for k, v in summary.items() if not isinstance(v, dict)]
    for part in ("run", "terrain", "mass_balance"):
        leaves += list(summary[part].items())
    for part in ("tools", "actuators"):
        for entry in summary[part].values():
            leaves += list(entry.items())
    assert len(leaves) > 40
    for key, _ in leaves:
        assert key in unitless or key.endswith(units), key


def test_write_summary_and_its_text(run, tmp_path):
    run_dir, model = run
    written = write_summary(run_dir, model)
    assert json.loads((run_dir / "summary.json").read_text()) == json.loads(json.dumps(written))
    text = format_summary(written)
    bucket = written["tools"]["bucket_link"]
    assert f"{bucket['soil_held_kg']:.1f} kg" in text
    assert f"dug {written['terrain']['dug_m3']:.3f} m3" in text
    assert "boom_joint" in text and "|F| > 1 N" in text
    # (12 cm grains: the bucket cuts with its wedge, as the manifest says, and the summary says so)
    assert bucket["soil_wedge"] is True and json.loads((run_dir / "manifest.json").read_text())["soil"]["wedges"] == \
        ["bucket_link"]
    assert "cut with its soil wedge" in text
    assert len(text.splitlines()) < 20


def test_a_run_without_soil_files_keeps_the_rest(run, tmp_path):
    run_dir, model = run
    for name in ("manifest.json", "joints.csv"):
        shutil.copy(run_dir / name, tmp_path / name)
    summary = summarize(tmp_path, model)
    assert "actuators" in summary and "run" in summary
    assert not {"tools", "terrain"} & set(summary)
    # without soil_mass.csv only the manifest's final budget is known
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert summary["mass_balance"]["final_kg"] == pytest.approx(sum(manifest["soil_mass_final"].values()))
    assert "initial_kg" not in summary["mass_balance"]
    assert "actuators" not in summarize(tmp_path, None)   # no model: no limits to compare with
    format_summary(summary)


def _png(path):
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] > 300 and img.shape[1] > 600, img.shape
    assert float(img[..., :3].std()) > 0.05   # not a blank canvas
    return img


def test_plots_write_pngs(run, tmp_path):
    run_dir, model = run
    limits = joint_limits(model)
    plots.plot_joints(run_dir / "joints.csv", JOINTS, tmp_path / "joints.png", limits=limits)
    plots.plot_joints(run_dir / "joints.csv", JOINTS, tmp_path / "joints_plain.png")   # the old call still works
    plots.plot_tool_wrench(run_dir / "tool_wrench.csv", tmp_path / "tool_wrench.png")
    plots.plot_soil_mass(run_dir / "soil_mass.csv", tmp_path / "soil_mass.png", density=1474.0)
    plots.plot_soil_mass(run_dir / "soil_mass.csv", tmp_path / "soil_mass_plain.png")
    initial, final = dict(np.load(run_dir / "terrain_initial.npz")), dict(np.load(run_dir / "terrain_final.npz"))
    plots.plot_terrain(initial, final, tmp_path / "terrain.png")
    plots.plot_terrain(initial, final, tmp_path / "terrain_y.png", dz_limit=0.5, profile_y=0.0)
    for d in (initial, final):   # a terrain file from before z_all
        d.pop("z_all")
    plots.plot_terrain(initial, final, tmp_path / "terrain_old.png")
    shapes = {p.name: _png(p).shape for p in sorted(tmp_path.glob("*.png"))}
    assert len(shapes) == 8
    # a row per joint against a row per tool
    assert shapes["joints.png"][0] > 2 * shapes["tool_wrench.png"][0]


def test_list_runs_finds_the_run_and_a_dead_one(run):
    run_dir, _ = run
    parent = run_dir.parent
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    dead = parent / "older" / "killed"
    dead.mkdir(parents=True)
    (dead / "manifest.json").write_text(json.dumps(
        {"name": "zx120_excavation", "status": "running", "pid": proc.pid, "host": socket.gethostname(),
         "started": "2000-01-01T00:00:00", "sim_time": 3.5, "scene": {"name": "zx120_excavation"}}))
    (parent / "not_a_run").mkdir()

    rows = list_runs(parent)
    by_name = {r["name"]: r for r in rows}
    assert set(by_name) == {"dig", "killed"}
    assert [r["name"] for r in rows] == ["killed", "dig"]   # oldest start first
    assert by_name["killed"]["status"] == "died"
    assert by_name["killed"]["sim_time_s"] == 3.5 and by_name["killed"]["bucket_kg"] is None
    done = by_name["dig"]
    cols = read_csv_columns(run_dir / "soil_mass.csv")
    wrench = read_csv_columns(run_dir / "tool_wrench.csv")
    assert done["status"] == "done" and done["scene"] == "zx120_excavation"
    assert done["sim_time_s"] == pytest.approx(9.0)
    assert done["bucket"] == "bucket_link"
    assert done["bucket_kg"] == pytest.approx(cols["in_bucket_link_kg"][-1], rel=1e-12)
    peak = float(np.max(np.sqrt(wrench["fx"] ** 2 + wrench["fy"] ** 2 + wrench["fz"] ** 2)))
    assert done["peak_force_N"] == pytest.approx(peak, rel=1e-12)

    # without summary.json the same numbers come from the CSV files
    bare = parent / "bare_copy"
    shutil.copytree(run_dir, bare, ignore=shutil.ignore_patterns("summary.json", "*.png"))
    row = run_row(bare)
    assert row["bucket_kg"] == pytest.approx(done["bucket_kg"], rel=1e-12)
    assert row["peak_force_N"] == pytest.approx(done["peak_force_N"], rel=1e-12)
    shutil.rmtree(bare)

    table = format_table(rows).splitlines()
    assert len(table) == 3 and table[0].split()[:3] == ["NAME", "SCENE", "STATUS"]
    assert "died" in table[1] and "done" in table[2]
    assert table[2].index("done") == table[1].index("died") == table[0].index("STATUS")   # aligned columns
    assert f"{done['bucket_kg']:.1f}" in table[2] and f"{peak / 1e3:.1f}" in table[2]

    buf = io.StringIO()
    write_csv(rows, buf)
    back = list(csv.DictReader(io.StringIO(buf.getvalue())))
    assert list(back[0]) == list(FIELDS)
    assert [r["status"] for r in back] == ["died", "done"]
    assert math.isclose(float(back[1]["bucket_kg"]), done["bucket_kg"], rel_tol=1e-12)
    assert back[0]["bucket_kg"] == ""


def test_plots_of_files_with_no_rows_are_left_out_quietly(tmp_path, capsys):
    """A run that ended before its first sample (an observer that could not start): no plot, no warning."""
    from opera_taichi.runner import write_plots

    (tmp_path / "joints.csv").write_text("t,boom_joint.q\n")
    (tmp_path / "tool_wrench.csv").write_text("t,tool,fx,fy,fz,tx,ty,tz\n")
    (tmp_path / "soil_mass.csv").write_text("t,mass_kg\n")
    write_plots(tmp_path, ["boom_joint"])
    assert capsys.readouterr().err == ""
    assert not list(tmp_path.glob("*.png"))


@pytest.mark.parametrize("peak_at", [0.1, 0.99])
def test_the_wrench_peak_label_stays_inside_its_panel(tmp_path, monkeypatch, peak_at):
    """The peak's label reads into the panel wherever the peak is, so it never runs into the legend at its right."""
    t = np.linspace(0.0, 10.0, 501)
    fx = 1e3 + 4e4 * np.exp(-((t - peak_at * 10.0) / 0.3) ** 2)
    rows = "".join(f"{a:.3f},bucket,{b:.1f},0,0,0,0,0\n" for a, b in zip(t, fx))
    (tmp_path / "tool_wrench.csv").write_text("t,tool,fx,fy,fz,tx,ty,tz\n" + rows)
    saved = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: saved.append(fig))
    plots.plot_tool_wrench(tmp_path / "tool_wrench.csv", tmp_path / "tool_wrench.png")
    fig = saved[0]
    renderer = fig.canvas.get_renderer()
    ax = fig.axes[0]
    label = next(a for a in ax.texts if a.get_text().startswith("peak |F|"))
    box, panel = label.get_window_extent(renderer), ax.get_window_extent(renderer)
    assert panel.x0 <= box.x0 and box.x1 <= panel.x1, (box, panel)
    plots.plt.close(fig)
