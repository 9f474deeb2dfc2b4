"""Validation runner without running the DEM: parameters, scene building, metric extraction, CLI errors, report."""
import math

import numpy as np
import pytest
import trimesh

from opera_taichi.cli import main
from opera_taichi.errors import UserError
from opera_taichi.scene import load_scene
from opera_taichi.validation import cases, report
from opera_taichi.validation import references as ref


@pytest.mark.parametrize("case", cases.SCENE_CASES)
def test_every_case_builds_a_valid_scene_at_every_resolution(case):
    p = cases.parse_params(case, [])
    radii = []
    for res in cases.RESOLUTIONS:
        sets, geo = cases.build_overrides(case, p, res)
        scene = load_scene(cases.scene_file(case), sets)
        assert scene.soil.overrides["radius"] == pytest.approx(geo["radius"])
        radii.append(geo["radius"])
    assert radii[0] > radii[1] > radii[2]  # finer resolution, smaller particles


def _numbers(value):
    if isinstance(value, dict):
        return [x for k in sorted(value) for x in _numbers(value[k])]
    if isinstance(value, (list, tuple)):
        return [x for v in value for x in _numbers(v)]
    return [value]


def test_shipped_scenes_are_the_default_case():
    # the YAML in scenes/validation is what `validate-physics CASE` runs at its defaults
    for case in cases.SCENE_CASES:
        sets, _ = cases.build_overrides(case, cases.parse_params(case, []), "default")
        plain = load_scene(cases.scene_file(case)).model_dump(mode="json")
        built = load_scene(cases.scene_file(case), sets).model_dump(mode="json")
        assert plain["soil"]["preset"] == built["soil"]["preset"]
        for part, key in (("soil", "bed"), ("soil", "domain"), ("soil", "bed_shift"), ("soil", "overrides"),
                          ("soil", "clear_above"), ("sim", "duration"), ("tools", None)):
            a = plain[part] if key is None else plain[part][key]
            b = built[part] if key is None else built[part][key]
            a, b = _numbers(a), _numbers(b)
            assert [type(x) for x in a if isinstance(x, str)] == [type(x) for x in b if isinstance(x, str)]
            assert np.allclose([x for x in a if not isinstance(x, str) and x is not None],
                               [x for x in b if not isinstance(x, str) and x is not None], atol=1e-5), (case, key)


def test_blade_geometry_puts_the_cutting_edge_at_depth_and_rake(tmp_path):
    p = cases.parse_params("blade_cut", ["depth=0.2", "rake_deg=60", "plane_strain=0", "width=1.0"])
    sets, geo = cases.build_overrides("blade_cut", p, "coarse", work_dir=tmp_path)
    scene = load_scene(cases.scene_file("blade_cut"), sets)
    tool = scene.tools[0]
    from opera_taichi.validation.cases import _rot_y

    rot = _rot_y(tool.rpy[1])
    mesh = trimesh.load(tool.mesh, force="mesh")
    assert mesh.is_watertight and mesh.volume > 0
    local = mesh.vertices
    world = local @ rot.T + np.asarray(tool.start)
    assert world[:, 2].min() == pytest.approx(-0.2)        # cuts at depth d
    assert world[:, 0].max() < 0.0                         # starts clear of the soil (pit starts at x = 0)
    face_normal = rot @ np.array([1.0, 0.0, 0.0])          # the face that meets the soil
    assert math.degrees(math.atan2(face_normal[0], face_normal[2])) == pytest.approx(60.0)  # 60 deg from horizontal
    lowest = np.isclose(world[:, 2], world[:, 2].min())
    assert np.allclose(local[lowest, 0], local[:, 0].max())  # the lowest points are the edge, on the soil face
    # every other bottom point (the bevel's back) clears the cut floor behind the edge
    others = world[~lowest & (local[:, 2] < 0)]
    assert np.all(others[:, 2] > -0.2 + 0.01)
    assert mesh.extents[1] == pytest.approx(1.0) and tool.velocity[0] == pytest.approx(0.1)
    assert scene.soil.clear_above == pytest.approx(cases.BLADE_CLEAR_ABOVE * geo["radius"])
    # a 3-D blade: the pit is wider than the blade by d on each side, so its edges cut free soil
    assert geo["width"] == 1.0 and scene.soil.bed[0].max[1] == pytest.approx(0.5 + 0.2 + 2 * geo["radius"])
    assert geo["radius"] == pytest.approx(0.2 / (2 * cases.ACROSS["blade_cut_3d"]["coarse"]))


@pytest.mark.parametrize("rake", [90, 45])
def test_plane_strain_blade_spans_a_slab_between_smooth_walls(tmp_path, rake):
    """The default blade: the bed and the domain are a slab SLICE_DIAMETERS grains wide, the blade reaches past
    both side walls (no edge in the soil), and the draft is divided by the slab's width."""
    p = cases.parse_params("blade_cut", [f"rake_deg={rake}"])
    assert p["plane_strain"] == 1.0 and p["width"] is None
    sets, geo = cases.build_overrides("blade_cut", p, "default", work_dir=tmp_path)
    scene = load_scene(cases.scene_file("blade_cut"), sets)
    slab = cases.SLICE_DIAMETERS * 2 * geo["radius"]
    assert geo["width"] == pytest.approx(slab) and geo["radius"] == pytest.approx(0.3 / (2 * cases.ACROSS["blade_cut"]["default"]))
    bed, domain = scene.soil.bed[0], scene.soil.domain
    assert (bed.min[1], bed.max[1]) == pytest.approx((-slab / 2, slab / 2))
    assert (domain.min[1], domain.max[1]) == pytest.approx((-slab / 2, slab / 2))
    mesh = trimesh.load(scene.tools[0].mesh, force="mesh")
    assert mesh.bounds[0][1] < -slab / 2 - geo["radius"] and mesh.bounds[1][1] > slab / 2 + geo["radius"]
    # the draft is per metre of the slab: a wrench of -1000 N in x reads 1000 / slab N/m
    run = tmp_path / "run"
    run.mkdir()
    import json
    (run / "manifest.json").write_text(json.dumps({"soil": {"bulk": {
        "density": 1700.0, "friction_angle": math.radians(35.0), "cohesion": 0.0, "tool_friction_angle": 0.0}}}))
    rows = ["t,tool,fx,fy,fz,tx,ty,tz"] + [f"{i * 0.1},blade,-1000,0,0,0,0,0" for i in range(100)]
    (run / "tool_wrench.csv").write_text("\n".join(rows) + "\n")
    m = cases.measure("blade_cut", run, p, geo)
    assert m["measured"] == pytest.approx(1000.0 / slab) and m["extra"]["width_m"] == pytest.approx(slab)
    assert "passed" not in m  # gated against the FEE
    m3 = cases.measure("blade_cut", run, cases.parse_params("blade_cut", ["plane_strain=0"]), dict(geo, width=1.5))
    assert m3["passed"] is None and m3["measured"] == pytest.approx(1000.0 / 1.5)  # a 3-D blade is shown, not gated


def test_vertical_cut_default_height_is_below_culmann():
    p = cases.parse_params("vertical_cut", [])
    hc = cases.culmann_height("dirt")
    assert hc == pytest.approx(1.245, abs=1e-3)
    assert p["height"] == pytest.approx(0.6 * hc)


@pytest.mark.parametrize("case", cases.SCENE_CASES)
def test_a_numeric_resolution_is_that_many_diameters_across_the_key_length(case):
    p = cases.parse_params(case, [])
    for name in cases.RESOLUTIONS:  # the named resolutions are numbers from ACROSS
        n = cases.ACROSS[case][name]
        assert cases.build_overrides(case, p, str(n)) == cases.build_overrides(case, p, name)
    r12 = cases.build_overrides(case, p, "12")[1]["radius"]
    r24 = cases.build_overrides(case, p, "24")[1]["radius"]
    assert r12 == pytest.approx(2.0 * r24)  # twice the grains across, half the radius
    if case == "blade_cut":
        assert r24 == pytest.approx(p["depth"] / 48.0)


@pytest.mark.parametrize("bad", ["2", "65", "1.5", "-6", "finer", "", "\u00b2"])
def test_a_bad_resolution_is_a_one_line_user_error(bad):
    with pytest.raises(UserError) as exc:
        cases.build_overrides("blade_cut", cases.parse_params("blade_cut", []), bad)
    msg = str(exc.value)
    assert msg.startswith("--resolution: expected coarse, default, fine or a whole number") and "(3-64)" in msg
    assert "\n" not in msg


@pytest.mark.parametrize("case, items, words", [
    ("blade_cut", ["depht=0.2"], "--param depht: unknown parameter of blade_cut"),
    ("blade_cut", ["depth=x"], "--param depth: expected a number"),
    ("blade_cut", ["rake_deg=120"], "--param rake_deg"),
    ("blade_cut", ["adhesion=-100"], "--param adhesion: expected a number in Pa >= 0"),
    ("blade_cut", ["width=1.0"], "--param width: only for a 3-D blade (with --param plane_strain=0)"),
    ("blade_cut", ["plane_strain=0.5"], "--param plane_strain: expected a number 0 or 1 (1, the default"),
    ("repose", ["preset=mud"], "--param preset: expected one of"),
    ("column_collapse", ["aspect_ratio"], "expected NAME=VALUE"),
    ("nope", [], "unknown case 'nope'"),
])
def test_bad_parameters_are_one_line_user_errors(case, items, words):
    with pytest.raises(UserError) as exc:
        cases.parse_params(case, items)
    assert words in str(exc.value) and "\n" not in str(exc.value)


def test_cli_bad_case_and_param_exit_2(capsys):
    assert main(["validate-physics", "nope"]) == 2
    assert main(["validate-physics", "passive_wall", "--param", "height=-1"]) == 2
    assert main(["validate-physics", "all", "--param", "height=1"]) == 2
    assert main(["validate-physics", "all", "--resolution", "100", "--report-only"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 4 and all(line.startswith("error: ") for line in err)
    assert "--resolution" in err[3]


@pytest.mark.parametrize("case", ["blade_cut", "repose", "critical_height"])
def test_a_case_writes_only_into_a_folder_of_its_own(tmp_path, capsys, case):
    """--out a file or a run folder: one line, exit 2, and nothing written there (the blade's and the hopper's
    meshes went into the run folder before it was refused; a file gave a traceback)."""
    afile = tmp_path / "a.csv"
    afile.write_text("t\n")
    run = tmp_path / "run"
    run.mkdir()
    (run / "manifest.json").write_text('{"status": "done", "scene": {}}')
    for out, words in [(afile, "is a file, not a folder"), (run, f"is the run folder {run}"),
                       (run / "case", f"lies inside the run folder {run}")]:
        before = sorted(p.name for p in tmp_path.rglob("*"))
        assert main(["validate-physics", case, "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"error: --out: {out} {words}") and "\n" not in err, err
        assert sorted(p.name for p in tmp_path.rglob("*")) == before


def test_all_and_resolution_refuse_a_report_or_out_they_cannot_write_before_any_run(tmp_path, capsys, monkeypatch):
    """--report a folder, or in a folder that does not exist or is a file; --out a file; --resume into runs of
    another resolution (a forgotten --resolution replaced them); a metrics.json that is no object: one line, exit 2,
    or run again, never a traceback (those were found after hours of runs, or lost them)."""
    import json

    def no_runs(*args, **kwargs):
        raise AssertionError("a case was about to run")

    monkeypatch.setattr(report, "run_case", no_runs)
    afile = tmp_path / "a.csv"
    afile.write_text("t\n")
    for argv, words in [(["all", "--report", str(tmp_path)], f"--report: {tmp_path} is a folder"),
                        (["all", "--report", str(tmp_path / "new" / "x.md")], "which does not exist"),
                        (["resolution", "--report", str(afile / "x.md")], "which is not a folder"),
                        (["all", "--out", str(afile)], f"--out: {afile} is a file, not a folder"),
                        (["resolution", "--out", str(afile)], f"--out: {afile} is a file, not a folder")]:
        assert main(["validate-physics", *argv, "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and "\n" not in err, err
    kept = tmp_path / "coarse" / "passive_wall_H0.3"
    kept.mkdir(parents=True)
    (kept / "metrics.json").write_text(json.dumps({"case": "passive_wall", "resolution": "coarse"}))
    assert main(["validate-physics", "all", "--out", str(tmp_path / "coarse"), "--resume", "--quiet",
                 "--report", str(tmp_path / "r.md")]) == 2
    err = capsys.readouterr().err.strip()
    assert "holds a run at resolution coarse, not default; give --resolution coarse" in err, err
    monkeypatch.chdir(tmp_path)   # the default report, docs/validation.md, from a folder without docs/
    assert main(["validate-physics", "all", "--out", str(tmp_path / "coarse"), "--resolution", "coarse",
                 "--report-only", "--quiet"]) == 2
    assert "no finished run of the gate set" in capsys.readouterr().err
    (kept / "run").mkdir()
    for metrics, manifest in (("[]", '{"status": "done", "soil": {}}'),
                              ('{"case": "passive_wall"}', '{"status": "done", "soil": []}')):
        (kept / "metrics.json").write_text(metrics)
        (kept / "run" / "manifest.json").write_text(manifest)
        assert cases.finished_metrics("passive_wall", {}, "default", kept) is None


def test_runout_length_ends_at_the_first_gap():
    rng = np.random.default_rng(0)
    pos = np.zeros((2000, 3))
    pos[:, 0] = rng.uniform(0.0, 1.5, 2000)
    pos[-1, 0] = 3.0  # one particle thrown far ahead is not the deposit
    rad = np.full(2000, 0.01)
    assert cases.runout_length(pos, rad, 0.02) == pytest.approx(1.51, abs=0.005)


def test_heap_angles_of_a_cone():
    rng = np.random.default_rng(1)
    angle = math.radians(31.0)
    n = 40000
    rho = 0.5 * np.sqrt(rng.uniform(0, 1, n))
    theta = rng.uniform(-math.pi, math.pi, n)
    top = (0.5 - rho) * math.tan(angle)
    z = rng.uniform(0, 1, n) * top  # filled cone; the highest per bin is near the surface
    pos = np.stack([rho * np.cos(theta), rho * np.sin(theta), z], axis=1)
    angles = cases.heap_angles(pos, np.full(n, 0.005), 0.01)
    assert len(angles) == 4
    assert math.degrees(np.mean(angles)) == pytest.approx(31.0, abs=1.0)


def test_the_hopper_is_the_same_at_every_resolution_down_to_its_narrowest_outlet(tmp_path):
    p = cases.parse_params("repose", {"preset": "sand"})
    outlet = {res: cases.build_overrides("repose", p, res, work_dir=tmp_path / res)[1]
              for res in ("coarse", "default", "fine", "8")}
    radius = {res: g["radius"] for res, g in outlet.items()}
    assert radius["coarse"] > radius["default"] > radius["fine"]  # the grains differ ...
    for res in ("coarse", "fine"):  # ... the hopper does not
        assert outlet[res]["outlet"] == pytest.approx(outlet["default"]["outlet"], rel=1e-12)
    assert outlet["default"]["outlet"] == pytest.approx(cases.HOPPER_OUTLET * radius["default"])
    # 8 grains across the column: the same outlet would be 5 grains across; it stays 7.5 wide against arching
    assert outlet["8"]["outlet"] == pytest.approx(cases.HOPPER_OUTLET_MIN * radius["8"])
    assert outlet["8"]["outlet"] > outlet["default"]["outlet"]


def test_report_from_metrics(tmp_path):
    def m(case, label, measured, reference, passed, **params):
        return dict(case=case, label=label, metric="x", unit="N/m", measured=measured, reference=reference,
                    relative_error=(measured - reference) / reference, passed=passed, gate="g", parameters=params,
                    resolution="coarse", particles=10, wall_time_s=1.0, extra={})
    blade = dict(rake=math.pi / 2, delta=0.0, friction=math.radians(35), density=1700.0, cohesion=0.0)
    results = [m("blade_cut", "blade_a90_d0.3", 2800.0, 2769.3, True, depth=0.3, width=None, plane_strain=1.0,
                 **blade),
               m("blade_cut", "blade_a90_d0.2", 1300.0, 1230.8, True, depth=0.2, width=None, plane_strain=1.0, **blade),
               m("blade_cut", "blade_3d_a90_d0.2_w1.5", 1200.0, 1230.8, None, depth=0.2, width=1.5, plane_strain=0.0,
                 **blade),
               m("blade_cut", "blade_3d_a90_d0.2_w1.0", 1250.0, 1230.8, None, depth=0.2, width=1.0, plane_strain=0.0,
                 **blade),
               # the gate set's packings at each a: their gates take the means, 0.7 and 1.4; one packing at a = 0.5
               # lies under the band (0.51), as a few of 24 do at every resolution
               *[m("column_collapse", f"column_a{a:g}_seed{seed}", value, 0.75 * 2 * a, 0.51 <= value, aspect_ratio=a,
                   seed=seed)
                 for a, values in ((0.5, (0.6, 0.8, 0.7, 0.65, 0.75, 0.7) * 3 + (0.45, 0.95, 0.7, 0.65, 0.75, 0.7)),
                                   (1.0, (1.3, 1.5, 1.4, 1.35, 1.45, 1.4) * 4))
                 for seed, value in zip(report.COLUMN_SEEDS, values, strict=True)]]
    unsettled = "soil: the bed did not come to rest in soil.settle_time = 1.1 s (a grain still moved at 0.181 m/s)"
    results[4]["warnings"] = [unsettled]  # column_a0.5_seed0
    path = report.write_report(results, tmp_path / "validation.md", "opera-taichi validate-physics all")
    text = path.read_text()
    assert "opera-taichi validate-physics all" in text
    # a verdict on a run that warned is listed with its warning, and only that run
    warned = text.split("Runs that warned")[1].split("\n\n")[1].splitlines()
    assert warned == [f"- column_a0.5_seed0: {unsettled}"]
    quiet = report.write_report([dict(r, warnings=[]) for r in results], tmp_path / "quiet.md", "c").read_text()
    assert "Runs that warned" not in quiet
    assert (tmp_path / "validation" / "runout.png").is_file()
    assert (tmp_path / "validation" / "blade_force_depth.png").is_file()
    gates = {g["label"]: g for g in report.derived_gates(results)}
    rows = {line.split("|")[1].strip(): line for line in text.splitlines() if line.startswith("| blade")}
    assert "| shown |" in rows["blade_3d_a90_d0.2_w1.0"] and "| pass |" in rows["blade_a90_d0.3"]
    assert gates["blade draft ~ d^2 (d 0.3 vs 0.2)"]["measured"] == pytest.approx(2800 / 1300)  # plane strain
    assert gates["blade draft ~ w (w 1.5 vs 1.0)"]["measured"] == pytest.approx(1200 * 1.5 / (1250 * 1.0))
    assert gates["run-out log-log slope, a <= 1"]["measured"] == pytest.approx(1.0)
    # the column is gated on its mean over the packings: one packing under the band fails nothing, and the report
    # shows it (in bold) beside the others, in a table of the packings instead of a row a run
    mean = gates[f"column run-out, a = 0.5, mean of {len(report.COLUMN_SEEDS)} packings"]
    assert mean["measured"] == pytest.approx(0.7) and mean["passed"] is True
    assert report.failed_gates(results) == []
    assert not any(line.startswith("| column_a") for line in text.splitlines())
    packings = text.split("one run a packing")[1]
    assert "| 0.5 | coarse | 24 of 24 | 0.700 |" in packings and "| 23 (0.51-1.03) |" in packings
    assert "/ **0.450** / 0.950 /" in packings
    # the mean is what fails: every packing at a = 0.5 a little short (the slope to 1.1 at a = 1: 1.14, in its gate)
    short = [dict(r, measured=0.5) if r["label"].startswith("column_a0.5_") else
             dict(r, measured=1.1) if r["label"].startswith("column_a1_") else r for r in results]
    assert report.failed_gates(short) == [f"column run-out, a = 0.5, mean of {len(report.COLUMN_SEEDS)} packings"]
    # a partial report: a packing and a blade missing, their ratio gates not run (a mean of fewer packings passed as
    # the gate's mean; the d^2 row was left out without a word)
    partial = [r for r in results if r["label"] not in ("column_a1_seed2", "blade_a90_d0.2")]
    gates = {g["label"]: g for g in report.derived_gates(partial)}
    assert gates["run-out log-log slope, a <= 1"]["passed"] is None
    assert "not run: column_a1_seed2" in gates["run-out log-log slope, a <= 1"]["gate"]
    assert gates[f"column run-out, a = 1, mean of {len(report.COLUMN_SEEDS)} packings"]["passed"] is None
    assert gates[f"column run-out, a = 0.5, mean of {len(report.COLUMN_SEEDS)} packings"]["passed"] is True
    assert gates["blade draft ~ d^2 (d 0.3 vs 0.2)"]["passed"] is None
    assert report.failed_gates(partial) == []
    text = report.write_report(partial, tmp_path / "partial.md", "opera-taichi validate-physics all").read_text()
    assert "| blade draft ~ d^2 (d 0.3 vs 0.2) (within 10%; not run: blade_a90_d0.2) | not run |" in text
    # every packing at a = 1 stood as a column (no run-out): the slope gate fails, it does not crash the report
    stood = [dict(r, measured=0.0) if r["label"].startswith("column_a1_") else r for r in results]
    assert {g["label"]: g for g in report.derived_gates(stood)}["run-out log-log slope, a <= 1"]["passed"] is False


def test_the_ratio_gates_find_their_runs_in_the_gate_set():
    # derived_gates looks runs up by label: a label written differently in gate_set would drop a gate silently
    results = []
    for label, case, params in report.gate_set():
        p = cases.parse_params(case, {k: str(v) for k, v in params.items()})
        results.append(dict(label=label, case=case, measured=1.0, parameters=cases._si_params(p)))
    assert {g["label"] for g in report.derived_gates(results)} == {
        "blade draft ~ d^2 (d 0.3 vs 0.2)", "blade draft ~ w (w 1.5 vs 1.0)", "run-out log-log slope, a <= 1",
        *[f"column run-out, a = {a:g}, mean of {len(report.COLUMN_SEEDS)} packings" for a in (0.5, 1.0)]}


def _finished_manifest(case: str, sets: list[str], **soil) -> dict:
    """The manifest of a finished run of these overrides, as run_scene writes it (status, soil micro, version)."""
    from opera_taichi.dem_soil import SOLVER_VERSION
    from opera_taichi.simulation import soil_parameters

    _, micro = soil_parameters(load_scene(cases.scene_file(case), sets).soil)
    return {"status": "done", "soil": {"solver_version": SOLVER_VERSION, "micro": vars(micro), **soil}}


def test_resume_reruns_only_what_changed(tmp_path, monkeypatch):
    """`all --resume` keeps a finished run made with the same overrides and solver version, and runs again a gate
    whose run is missing, unfinished, made by another solver version or with other parameters."""
    import json

    from opera_taichi.dem_soil import SOLVER_VERSION

    ran = []

    def fake_run_case(case, params, resolution, out_dir, arch=None, quiet=True):
        ran.append(out_dir.name)
        sets, _ = cases.build_overrides(case, cases.parse_params(case, params), resolution, work_dir=out_dir)
        (out_dir / "run").mkdir(parents=True, exist_ok=True)
        (out_dir / "run" / "manifest.json").write_text(json.dumps(_finished_manifest(case, sets)))
        metrics = dict(case=case, metric="x", unit="1", measured=1.0, reference=1.0, relative_error=0.0, passed=True,
                       gate="g", parameters={}, resolution=resolution, particles=1, wall_time_s=1.0,
                       run_dir=str(out_dir / "run"), overrides=sets)
        (out_dir / "metrics.json").write_text(json.dumps(metrics))
        return metrics

    monkeypatch.setattr(report, "run_case", fake_run_case)
    monkeypatch.setattr(report, "write_report", lambda results, path, command, not_run=(), study=None: path)
    monkeypatch.setattr(cases, "measure", lambda case, run_dir, p, geo: dict(metric="x", unit="1", measured=1.0,
                                                                           reference=1.0, tolerance=0.1, gate="g"))
    labels = [label for label, _, _ in report.gate_set()]
    report.run_all("coarse", tmp_path, tmp_path / "v.md", resume=True)
    assert ran == labels  # nothing to reuse yet

    def edit(label, path, change):
        data = json.loads((tmp_path / label / path).read_text())
        change(data)
        (tmp_path / label / path).write_text(json.dumps(data))

    edit(labels[0], "run/manifest.json", lambda m: m["soil"].update(solver_version=SOLVER_VERSION - 1))
    edit(labels[1], "run/manifest.json", lambda m: m.update(status="diverged"))
    edit(labels[2], "metrics.json", lambda m: m["overrides"].append("soil.overrides.radius=0.1"))
    (tmp_path / labels[3] / "metrics.json").unlink()
    edit(labels[4], "run/manifest.json", lambda m: m["soil"]["micro"].update(mu_r=0.25))  # mapping recalibrated
    ran.clear()
    report.run_all("coarse", tmp_path, tmp_path / "v.md", resume=True)
    assert ran == labels[:5]
    ran.clear()
    report.run_all("coarse", tmp_path, tmp_path / "v.md", resume=False)
    assert ran == labels  # without --resume every gate runs


def test_a_wedged_run_of_another_wedge_model_is_run_again(tmp_path, monkeypatch):
    """--resume keeps a run with the soil wedge only when the wedge's model (WEDGE_VERSION, in the manifest) is
    today's; a run without the wedge is kept whatever its manifest says of the wedge."""
    import json

    from opera_taichi.dem_soil import WEDGE_VERSION

    monkeypatch.setattr(cases, "measure", lambda case, run_dir, p, geo: dict(metric="x", unit="1", measured=1.0,
                                                                           reference=1.0, tolerance=0.1, gate="g"))

    def finished(label, params, wedge_version):
        out = tmp_path / label
        sets, _ = cases.build_overrides("passive_wall", cases.parse_params("passive_wall", params), "coarse",
                                        work_dir=out)
        manifest = _finished_manifest("passive_wall", sets)
        if wedge_version is not None:
            manifest["soil"]["wedge_version"] = wedge_version
        (out / "run").mkdir(parents=True, exist_ok=True)
        (out / "run" / "manifest.json").write_text(json.dumps(manifest))
        (out / "metrics.json").write_text(json.dumps(dict(
            case="passive_wall", metric="x", unit="1", measured=1.0, reference=1.0, relative_error=0.0, passed=True,
            gate="g", parameters={}, resolution="coarse", particles=1, wall_time_s=1.0, run_dir=str(out / "run"),
            overrides=sets)))
        return cases.finished_metrics("passive_wall", params, "coarse", out)

    wedge = {"height": "0.3", "wedge": "1"}
    assert finished("now", wedge, WEDGE_VERSION) is not None
    assert finished("older", wedge, WEDGE_VERSION - 1) is None
    assert finished("unrecorded", wedge, None) is None   # made before the wedge's model was recorded: version 1
    assert finished("grains", {"height": "0.3"}, None) is not None


def test_report_only_runs_nothing_and_lists_the_gates_without_a_run(tmp_path, monkeypatch):
    import json

    label, case, params = next(g for g in report.gate_set() if g[1] == "passive_wall")
    params = {k: str(v) for k, v in params.items()}
    out = tmp_path / "runs"
    sets, _ = cases.build_overrides(case, cases.parse_params(case, params), "coarse", work_dir=out / label)
    (out / label / "run").mkdir(parents=True)
    (out / label / "run" / "manifest.json").write_text(json.dumps(_finished_manifest(case, sets)))
    metrics = dict(case=case, metric="peak_thrust_per_width", unit="N/m", measured=3000.0, reference=2769.0,
                   relative_error=3000 / 2769 - 1, passed=True, gate="g", parameters={}, resolution="coarse",
                   particles=700, wall_time_s=20.0, run_dir=str(out / label / "run"), overrides=sets)
    (out / label / "metrics.json").write_text(json.dumps(metrics))

    def no_run(*a, **k):
        raise AssertionError("--report-only must not run a case")

    monkeypatch.setattr(report, "run_case", no_run)
    monkeypatch.setattr(cases, "measure", lambda case, run_dir, p, geo: dict(
        metric="peak_thrust_per_width", unit="N/m", measured=3000.0, reference=2769.0, tolerance=0.2, gate="g"))
    path = report.run_all("coarse", out, tmp_path / "v.md", report_only=True)
    rows = [line for line in path.read_text().splitlines() if line.startswith("| ") and "|---" not in line]
    assert any(row.startswith(f"| {label} |") and "| 3000 |" in row for row in rows)
    not_run = [row.split("|")[1].strip() for row in rows if "not run" in row]
    ratio_gates = {"blade draft ~ d^2", "blade draft ~ w", "run-out log-log slope", "column run-out"}  # and theirs
    assert [r for r in not_run if not r.startswith(tuple(ratio_gates))] == \
        [lb for lb, _, _ in report.gate_set() if lb != label]
    assert len([r for r in not_run if r.startswith(tuple(ratio_gates))]) == 5
    # with no finished run there is nothing to report: the report there is left as it is
    kept = path.read_text()
    with pytest.raises(UserError, match="--report-only: no finished run of the gate set in"):
        report.run_all("coarse", tmp_path / "empty", tmp_path / "v.md", report_only=True)
    assert path.read_text() == kept


@pytest.mark.parametrize("flag", ["--resume", "--report-only"])
def test_resume_and_report_only_are_only_for_the_gate_set(flag, capsys):
    assert main(["validate-physics", "repose", flag]) == 2
    assert f"{flag}: only with `all` or `resolution`" in capsys.readouterr().err
    assert main(["validate-physics", "all", "--resume", "--report-only"]) == 2
    assert "--resume, --report-only: give one" in capsys.readouterr().err


def test_a_kept_run_is_measured_again_with_the_current_code(tmp_path):
    """--resume / --report-only read the metric again from the run folder: a metrics.json written by older
    measuring code (here a stale peak) is replaced by what this code reads from tool_wrench.csv."""
    import json

    label, case, params = next(g for g in report.gate_set() if g[1] == "passive_wall")
    params = {k: str(v) for k, v in params.items()}
    out = tmp_path / label
    sets, geo = cases.build_overrides(case, cases.parse_params(case, params), "coarse", work_dir=out)
    run = out / "run"
    run.mkdir(parents=True)
    bulk = {"density": 1700.0, "friction_angle": math.radians(35.0), "cohesion": 0.0}
    (run / "manifest.json").write_text(json.dumps(_finished_manifest(case, sets, bulk=bulk)))
    # thrust 2000 N/m per metre of pit width with one spike of 4000 in one sample
    rows = ["t,tool,fx,fy,fz,tx,ty,tz"]
    for i in range(400):
        t = i * 0.005
        fx = -2000.0 * geo["width"] * (2.0 if i == 200 else 1.0)
        rows.append(f"{t},wall,{fx},0,0,0,0,0")
    (run / "tool_wrench.csv").write_text("\n".join(rows) + "\n")
    stale = dict(case=case, metric="peak_thrust_per_width", unit="N/m", measured=4000.0, reference=2769.0,
                 relative_error=0.44, passed=False, gate="g", parameters={}, resolution="coarse", particles=700,
                 wall_time_s=20.0, run_dir=str(run), overrides=sets)
    (out / "metrics.json").write_text(json.dumps(stale))
    m = cases.finished_metrics(case, params, "coarse", out)
    window = int(round(2.0 * geo["radius"] / (cases.WALL_SPEED * 0.005)))
    assert m["measured"] == pytest.approx(2000.0 + 2000.0 / window, rel=1e-9)  # the spike is averaged out
    assert m["reference"] == pytest.approx(ref.rankine_passive_thrust(0.3, math.radians(35.0), 1700.0), rel=1e-9)
    assert m["particles"] == 700 and m["wall_time_s"] == 20.0
    assert json.loads((out / "metrics.json").read_text())["measured"] == m["measured"]
    (run / "tool_wrench.csv").unlink()  # a kept run that lost a recorder file is run again, not a traceback
    assert cases.finished_metrics(case, params, "coarse", out) is None


def test_peak_of_travel_average_is_the_largest_window_mean():
    x = np.arange(100) * 0.001
    force = np.where(np.arange(100) % 2 == 0, 1.1, 0.9) * (1000.0 + 5000.0 * x)  # rising, +-10% grain jumps
    peak = cases.peak_of_travel_average(x, force, 0.01)
    last = force[-10:].mean()
    assert peak == pytest.approx(last, rel=1e-12)
    assert peak < force.max() * 0.95  # the top of the noise is not the peak
    assert cases.peak_of_travel_average(x, force, 1.0) == pytest.approx(force.mean(), rel=1e-12)  # window > record


def test_critical_height_bisects_between_a_cut_that_stands_and_one_that_falls(tmp_path):
    """The bisection against cuts that stand below a known height: it brackets that height, each bisection halves
    the bracket, and a height outside the first bracket is found by widening it."""
    hc = cases.culmann_height("dirt")
    for true_ratio in (0.83, 0.3, 2.9):
        tried = []

        def cut(height, folder):
            tried.append(height / hc)
            return {"measured": height < true_ratio * hc}

        found = cases.critical_height({"preset": "dirt", "steps": 4.0}, "coarse", tmp_path, cut)
        assert found["low"] <= true_ratio * hc < found["high"]
        assert found["measured"] == pytest.approx(0.5 * (found["low"] + found["high"]))
        width = (found["high"] - found["low"]) / hc
        first = 1.0 if true_ratio == 0.83 else None  # the first bracket is 0.5-1.5 x Culmann
        if first is not None:
            assert width == pytest.approx(first / 2 ** 4)
        assert len(set(tried)) == len(tried)  # no height is cut twice


def test_critical_height_needs_a_cohesive_soil(capsys):
    assert main(["validate-physics", "critical_height", "--param", "preset=sand", "--resolution", "coarse"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sand has no cohesion" in err[0]
    with pytest.raises(UserError, match="steps"):
        cases.parse_params("critical_height", ["steps=0"])


def test_resolution_study_gates_follow_the_issue(tmp_path):
    """The study's gates on synthetic runs: 4 and 8 grains across at 25% and 15%, d^2 at 10%, the wall at 20%, the
    critical heights at 25%; a gate whose runs are missing is 'not run', not a pass."""
    from opera_taichi.validation import resolution

    def run(measured, reference):
        return {"measured": measured, "reference": reference, "particles": 1000, "wall_time_s": 1.0,
                "parameters": {"preset": "dirt"}, "resolution": "coarse", "n_across": 8, "bracket_m": [0.7, 0.74]}

    results = {"blade_a90_d0.3_n4": run(1.2 * 2769, 2769), "blade_a90_d0.3_n8": run(1.2 * 2769, 2769),
               "blade_a90_d0.2_n4": run(1.2 * 2769 / 2.25 / 1.05, 1231),
               "critical_height_dirt_coarse": run(0.72, 1.0)}
    gates = {g["label"]: g for g in resolution.study_gates(results)}
    assert gates["blade a90 d0.3, 4 grains across d: draft / FEE"]["passed"] is True
    assert gates["blade a90 d0.3, 8 grains across d: draft / FEE"]["passed"] is False
    assert gates["blade draft ~ d^2 (d 0.3 vs 0.2), 4 grains across d"]["passed"] is True
    assert gates["critical height, dirt, coarse: / Culmann"]["passed"] is False
    wall = "passive wall H0.3, 4 grains across H: thrust / Rankine, mean of 3 packings"
    assert gates[wall]["passed"] is None
    # the wall gate takes the mean of its three packings: 1.25, 0.75 and 1.0 x pass (each alone would not say so)
    results.update({f"passive_wall_H0.3_n4_seed{s}": {**run(r * 2769, 2769), "parameters": {"seed": float(s)}}
                    for s, r in enumerate((1.25, 0.75, 1.0))})
    gates = {g["label"]: g for g in resolution.study_gates(results)}
    assert gates[wall]["passed"] is True and gates[wall]["measured"] == pytest.approx(1.0)
    results["passive_wall_H0.3_n4_seed2"] = {**run(0.2 * 2769, 2769), "parameters": {"seed": 2.0}}   # mean 0.73 x
    assert {g["label"]: g for g in resolution.study_gates(results)}[wall]["passed"] is False
    del results["passive_wall_H0.3_n4_seed1"]   # a packing not run: the gate is not run, not the mean of two
    gates = {g["label"]: g for g in resolution.study_gates(results)}
    assert gates[wall]["passed"] is None
    path = resolution.write_study(results, list(gates.values()), tmp_path / "r.md", "cmd")
    text = path.read_text()
    assert "| 4 |" in text and "not run" in text and "FAIL" in text
    assert "| 0 | 1,000 | 3461 | 1.250 |" in text and "| 2 | 1,000 | 554 | 0.200 |" in text  # the wall by packing


def test_the_walls_seed_sets_its_packing_and_its_default_leaves_the_overrides_as_they_were(tmp_path):
    default, _ = cases.build_overrides("passive_wall", cases.parse_params("passive_wall", []), "4", work_dir=tmp_path)
    seeded, _ = cases.build_overrides("passive_wall", cases.parse_params("passive_wall", ["seed=2"]), "4",
                                      work_dir=tmp_path)
    assert not any(x.startswith("sim.seed=") for x in default) and "sim.seed=2" in seeded
    assert sorted(set(seeded) - set(default)) == ["sim.seed=2"]
    with pytest.raises(UserError, match="seed"):
        cases.parse_params("passive_wall", ["seed=1.5"])


def test_a_preset_gives_the_blade_and_wall_its_strength_unless_given():
    """--param preset=dirt: the cut and its reference take dirt's friction, density and cohesion."""
    from opera_taichi.soil import PRESETS

    dirt = PRESETS["dirt"]
    p = cases.parse_params("blade_cut", ["preset=dirt"])
    assert (p["friction_deg"], p["density"], p["cohesion"]) == pytest.approx(
        (math.degrees(dirt["friction_angle"]), dirt["density"], dirt["cohesion"]))
    assert cases.parse_params("blade_cut", ["preset=dirt", "friction_deg=30"])["friction_deg"] == 30.0
    assert cases.parse_params("passive_wall", ["preset=gravel"])["density"] == PRESETS["gravel"]["density"]
    assert cases.parse_params("blade_cut", [])["friction_deg"] == 35.0   # the gates' sand, as before


def test_rolling_resistance_is_a_parameter_of_the_flow_and_strength_cases(tmp_path):
    """Calibration step 2 (docs/validation.md) tunes it with the heap and the column: it reaches the soil, and the
    default leaves the overrides (so kept runs) as they were."""
    for case in ("repose", "column_collapse", "blade_cut", "passive_wall"):
        sets, _ = cases.build_overrides(case, cases.parse_params(case, ["rolling_resistance=0.2"]), "coarse",
                                        work_dir=tmp_path)
        assert '"rolling_resistance": 0.2' in next(x for x in sets if x.startswith("soil.overrides=")), case
        sets, _ = cases.build_overrides(case, cases.parse_params(case, []), "coarse", work_dir=tmp_path)
        assert "rolling_resistance" not in next(x for x in sets if x.startswith("soil.overrides=")), case
    with pytest.raises(UserError, match="--param rolling_resistance: expected a number between 0 and 1"):
        cases.parse_params("repose", ["rolling_resistance=2"])


def test_a_kept_run_folder_can_be_moved(tmp_path):
    """The blade's mesh is written in its run's folder and named by its content: a moved folder is the same run."""
    p = cases.parse_params("blade_cut", [])
    here, _ = cases.build_overrides("blade_cut", p, "coarse", work_dir=tmp_path / "here")
    there, _ = cases.build_overrides("blade_cut", p, "coarse", work_dir=tmp_path / "there")
    assert here != there and cases.same_overrides(here, there)
    other, _ = cases.build_overrides("blade_cut", cases.parse_params("blade_cut", ["rake_deg=60"]), "coarse",
                                     work_dir=tmp_path / "there")
    assert not cases.same_overrides(here, other)


def test_a_single_case_does_not_replace_the_run_in_its_out_folder(tmp_path, capsys):
    (tmp_path / "metrics.json").write_text("{}")
    assert main(["validate-physics", "repose", "--out", str(tmp_path)]) == 2
    assert "holds a finished case already; use --overwrite" in capsys.readouterr().err
    assert (tmp_path / "metrics.json").read_text() == "{}"
    assert main(["validate-physics", "all", "--overwrite"]) == 2
    assert "--overwrite: only for a single case" in capsys.readouterr().err
    assert main(["validate-physics", "repose", "--report", str(tmp_path / "r.md")]) == 2
    assert "--report: only with `all` or `resolution`" in capsys.readouterr().err
    assert main(["validate-physics", "resolution", "--resolution", "fine"]) == 2
    assert "--resolution: not with `resolution`" in capsys.readouterr().err


def test_critical_height_from_the_command_line_says_its_result_and_where(tmp_path, monkeypatch, capsys):
    """The cuts stand by a rule here (below 0.8 x Culmann's), not by running them: the command's own path."""
    hc = cases.culmann_height("dirt")
    real = cases.run_case

    def run_case(case, params, resolution="default", out_dir=None, **kw):
        if case != "vertical_cut":
            return real(case, params, resolution, out_dir, **kw)
        return {"measured": float(params["height"]) < 0.8 * hc, "particles": 100, "wall_time_s": 0.1,
                "particle_radius_m": 0.05}

    monkeypatch.setattr(cases, "run_case", run_case)
    assert main(["validate-physics", "critical_height", "--resolution", "coarse", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert out[-1].startswith("critical_height: critical_height = ") and "PASS" in out[-1]
    assert out[-1].endswith(str(tmp_path / "metrics.json"))


def test_a_column_seed_is_its_runs_packing_seed():
    sets, _ = cases.build_overrides("column_collapse", cases.parse_params("column_collapse", ["seed=3"]), "coarse")
    assert load_scene(cases.scene_file("column_collapse"), sets).sim.seed == 3
    with pytest.raises(UserError, match="seed"):
        cases.parse_params("column_collapse", ["seed=1.5"])


def test_runs_that_warned_alike_share_a_line_with_the_range_of_their_figures():
    stacked = "soil: {}% of the settled bed's grains rest straight on the grain beneath (calibration note 1)"
    labelled = [(f"column_a0.5_seed{s}_coarse", {"warnings": [stacked.format(p)]}) for s, p in ((0, 54), (1, 50),
                                                                                                 (2, 71), (5, 36))]
    labelled += [("blade_a90_d0.3_n3", {"warnings": [stacked.format(30)]}),
                 ("column_a2", {"warnings": ["soil: the bed did not come to rest (a grain still moved at 0.181 m/s)"]}),
                 ("repose_sand", {"warnings": []})]
    lines = report.warned_runs(labelled)
    assert lines[3:] == [
        "- column_a0.5_coarse, seeds 0-2, 5; blade_a90_d0.3_n3: " + stacked.format("30-71"),
        "- column_a2: soil: the bed did not come to rest (a grain still moved at 0.181 m/s)"]
    assert report.warned_runs([("repose_sand", {"warnings": []})]) == []
