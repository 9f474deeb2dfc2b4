"""`validate-physics resolution`'s report: the grains alone and the soil wedge side by side against the issue's gates
at operating resolution (the wedge gated, the grains shown), the coarse heaps and columns in their bands, and the
study as the closing section of `validate-physics all`'s report (runs faked here; the study itself takes about an
hour on two cores)."""
from opera_taichi.validation import report, resolution


def _fake(case, ratio, reference=2769.3, **params):
    return {"case": case, "measured": ratio * reference, "reference": reference, "particles": 1000,
            "wall_time_s": 10.0, "parameters": params, "resolution": "4"}


def _results(blade_grains, blade_wedge, wall_wedge):
    out = {}
    for label, case, params, res in resolution.study_set():
        if case not in ("blade_cut", "passive_wall"):
            continue
        wedge = params.get("wedge") == 1.0
        if case == "passive_wall":
            out[label] = _fake(case, wall_wedge if wedge else 0.96, seed=params["seed"])
        elif params["depth"] == 0.2:  # the d^2 pair: the deep cut's draft over 2.25 on the shallow one
            ratio = blade_wedge if wedge else blade_grains
            out[label] = _fake(case, ratio * 2769.3 / 2.25 / 1230.8, reference=1230.8)
        else:
            out[label] = _fake(case, blade_wedge if wedge else blade_grains)
    return out


def test_the_study_runs_both_models_once_each():
    labels = [label for label, *_ in resolution.study_set()]
    assert len(labels) == len(set(labels))
    tool = [(label, p) for label, case, p, _ in resolution.study_set() if case in ("blade_cut", "passive_wall")]
    wedge = {label.removesuffix("_wedge") for label, p in tool if p.get("wedge") == 1.0}
    grains = {label for label, p in tool if "wedge" not in p}
    assert len(wedge) + len(grains) == len(tool) and all(label.endswith("_wedge") == ("wedge" in p) for label, p in tool)
    assert wedge == grains | {"blade_a90_d0.3_n20"}  # the grains alone at 20 across: the default gate set's run
    # the heaps and the columns of the default gate set, each again at its coarse resolution
    coarse = [(label, case, p, res) for label, case, p, res in resolution.study_set() if case in ("column_collapse",
                                                                                                 "repose")]
    assert [(label, case, p, res) for label, case, p, res in coarse] == \
        [(f"{label}_coarse", case, p, "coarse") for label, case, p in report.gate_set()
         if case in ("column_collapse", "repose")]


def test_each_model_is_gated_on_its_own_runs(tmp_path):
    gates = {g["label"]: g for g in resolution.study_gates(_results(1.79, 1.15, 1.30))}
    grains = gates["blade a90 d0.3, 4 grains across d: draft / FEE"]
    assert grains["passed"] is False and grains["gated"] is False  # shown beside the wedge: not a failure
    assert grains["label"] not in resolution.failed(list(gates.values()))
    assert gates["blade a90 d0.3, 4 grains across d, soil wedge: draft / FEE"]["passed"] is True
    assert gates["blade a90 d0.3, 8 grains across d, soil wedge: draft / FEE"]["passed"] is True
    # the wall's mean of three packings at 1.30 x is outside its 20%
    wall = "passive wall H0.3, 4 grains across H, soil wedge: thrust / Rankine, mean of 3 packings"
    assert gates[wall]["passed"] is False and abs(gates[wall]["measured"] - 1.30) < 1e-9
    assert wall in resolution.failed(list(gates.values()))
    d2 = gates["blade draft ~ d^2 (d 0.3 vs 0.2), 4 grains across d, soil wedge"]
    assert d2["passed"] is True and abs(d2["measured"] - 2.25) < 1e-9


def test_the_report_has_both_columns_and_the_plot(tmp_path):
    results = _results(1.79, 1.15, 1.10)
    del results["blade_a90_d0.3_n12_wedge"]
    stacked = "soil: 77% of the settled bed's grains rest straight on the grain beneath"
    results["passive_wall_H0.3_n4_seed1"]["warnings"] = [stacked]
    path = resolution.write_study(results, resolution.study_gates(results), tmp_path / "resolution.md", "cmd")
    text = path.read_text()
    assert f"\n- passive_wall_H0.3_n4_seed1: {stacked}\n" in text and text.count("\n- ") == 1  # the run that warned
    assert "| 4 | 1,000 | 4957 | 1.790 | 10 | 3185 | 1.150 | 10 |" in text
    assert "| 12 | 1,000 | 4957 | 1.790 | 10 | not run | - | - |" in text
    assert "soil wedge: draft / FEE (within 25%) | 1.150 | 1.000 | +15.0% | pass |" in text
    assert "4 grains across d: draft / FEE (within 25%) | 1.790 | 1.000 | +79.0% | fail, not gated |" in text
    assert "| grains alone | 2 | 1,000 | 2659 | 0.960 |" in text and "| soil wedge | 2 | 1,000 | 3046 | 1.100 |" in text
    png = tmp_path / "resolution" / "blade_convergence.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_diverged_run_fails_its_gates_and_the_study_goes_on(tmp_path, monkeypatch):
    from opera_taichi.errors import DivergenceError

    faked = _results(1.79, 1.15, 1.10)
    ran = []

    def run_case(case, params, res, out, **_):
        label = out.name
        ran.append(label)
        if label == "blade_a60_delta20_d0.3_n8_wedge":
            raise DivergenceError("soil diverged at t = 3.891 s: particle speed 30.8 m/s above the limit 30 m/s")
        if case == "critical_height":
            return {**_fake(case, 1.0, reference=1.245), "n_across": 8, "bracket_m": [1.2, 1.3],
                    "parameters": {"preset": params["preset"]}, "resolution": res}
        if case in ("column_collapse", "repose"):
            return _band(case, 1.0, True, params)
        return faked[label]

    monkeypatch.setattr(resolution, "run_case", run_case)
    monkeypatch.setattr(resolution, "GATE_RUN_20", tmp_path / "none")
    path, failed = resolution.run_study(out_dir=tmp_path / "runs", report_path=tmp_path / "resolution.md")
    assert ran == [label for label, *_ in resolution.study_set()]  # every run after the diverged one ran too
    assert [g for g in failed if "soil wedge" in g] == ["blade a60_delta20 d0.3, 8 grains across d, soil wedge: draft / FEE"]
    text = path.read_text()
    assert ("| blade a60_delta20 d0.3, 8 grains across d, soil wedge: draft / FEE (within 15%) | diverged | 1.000 | - "
            "| FAIL |") in text
    assert "soil wedge: draft / FEE (within 25%) | 1.150 | 1.000 | +15.0% | pass |" in text


def _band(case, measured, passed, params):
    """A coarse heap's or column's metrics as its case writes them: its own band's verdict."""
    return {**_fake(case, measured, reference=1.0), "metric": "runout_ratio" if case == "column_collapse" else
            "angle_deg", "relative_error": measured - 1.0, "passed": passed, "gate": "its band",
            "parameters": {k: float(v) if k != "preset" else v for k, v in params.items()}, "resolution": "coarse"}


def test_the_coarse_heaps_and_columns_are_gated_in_their_bands_and_by_the_slope():
    results = {}
    for label, case, params, _ in resolution.coarse_set():
        a = params.get("aspect_ratio", 1.0)
        results[label] = _band(case, 1.32 * a, True, params)  # run-out ~ a: slope 1
    gates = {g["label"]: g for g in resolution.coarse_gates(results)}
    slope = gates["run-out log-log slope, a <= 1, coarse (8 grains across)"]
    assert abs(slope["measured"] - 1.0) < 1e-9 and slope["passed"] is True and slope["gated"] is True
    sand = gates["repose_sand, coarse (12 grains across): angle_deg"]
    assert sand["passed"] is True and sand["gated"] is True
    # a heap outside its band fails the study; a column not run leaves its gate and the slope not run
    results["repose_glass_beads_coarse"] = _band("repose", 1.4, False, {"preset": "glass_beads"})
    del results["column_a1_seed2_coarse"]
    gates = resolution.coarse_gates(results)
    failed = resolution.failed(gates)
    assert len(failed) == 1 and failed[0].startswith("repose_glass_beads, coarse")
    by = {g["label"]: g for g in gates}
    packings = f"mean of {len(report.COLUMN_SEEDS)} packings, coarse (8 grains across)"
    assert by[f"column run-out, a = 1, {packings}"]["passed"] is None
    assert by[f"column run-out, a = 0.5, {packings}"]["passed"] is True
    assert by["run-out log-log slope, a <= 1, coarse (8 grains across)"]["passed"] is None
    assert not any(g["label"].startswith("column_a0.5_seed") for g in gates)  # a packing is gated through its mean


def test_all_closes_its_report_with_the_study_and_fails_on_its_gated_rows(tmp_path, monkeypatch):
    """`validate-physics all` at the default resolution: the gate set, then the study into OUT/resolution/; the
    report has both, and a study gate that fails (the wedge's, not the grains') fails the command."""
    faked = _results(1.79, 1.50, 1.00)   # the wedge's blades at 1.50 x fail at 4 and 8 across (the grains too)
    ran = []

    def run_case(case, params, res, out, **_):
        ran.append(str(out.relative_to(tmp_path)))
        if case == "critical_height":
            return {**_fake(case, 1.0, reference=1.245), "n_across": 8, "bracket_m": [1.2, 1.3],
                    "parameters": {"preset": params["preset"]}, "resolution": res}
        if case == "column_collapse":  # in the band: the columns' gates take the mean of the packings' run-outs
            return _band(case, 1.32 * float(params["aspect_ratio"]), True, params)
        if case == "repose":
            return _band(case, 1.0, True, params)
        if out.name in faked:
            return faked[out.name]
        m = {**_fake(case, 1.0), "metric": "x", "relative_error": 0.0, "passed": True, "gate": "g",
             "parameters": {k: float(v) if k != "preset" else v for k, v in params.items()}, "resolution": res}
        m["parameters"].setdefault("width", 1.0)
        return m

    monkeypatch.setattr(report, "run_case", run_case)
    monkeypatch.setattr(resolution, "run_case", run_case)
    monkeypatch.setattr(report, "_plots", lambda results, plot_dir: [])  # the gate set's plots need whole runs
    path, failed = report.run_all("default", tmp_path, tmp_path / "v.md", with_failures=True)
    assert ran == [label for label, *_ in report.gate_set()] + \
        [f"resolution/{label}" for label, *_ in resolution.study_set()]
    # (the faked gate set fails its ratio gates: the faked runs are all 1 x their references)
    study = [f for f in failed if "grains across" in f or "coarse" in f or "critical" in f]
    assert study == [f"blade {name} d0.3, {n} grains across d, soil wedge: draft / FEE" for n in (4, 8)
                     for name in ("a90", "a60_delta20")]
    text = path.read_text()
    assert "## At operating resolution" in text and "### Gates at operating resolution" in text
    assert "| 20 | 1,000 | 2769 | 1.000 | 10 |" in text   # the gate set's 20-across blade closes the grains' column
    assert (tmp_path / "v" / "blade_convergence.png").read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "v" / "runout_coarse.png").read_bytes()[:4] == b"\x89PNG"  # the coarse columns' packings
    assert "![run-out vs aspect ratio, coarse](v/runout_coarse.png)" in text
    # at another resolution the study does not run
    ran.clear()
    report.run_all("coarse", tmp_path / "coarse", tmp_path / "c.md")
    assert not any(r.startswith("coarse/resolution") for r in ran) and "## At operating resolution" not in \
        (tmp_path / "c.md").read_text()
