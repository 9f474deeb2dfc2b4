"""`validate-physics resolution`'s report: the grains alone and the soil wedge side by side, each against the issue's
gates at operating resolution (runs faked here; the study itself takes about 35 min on two cores)."""
from opera_taichi.validation import resolution


def _fake(case, ratio, reference=2769.3, **params):
    return {"case": case, "measured": ratio * reference, "reference": reference, "particles": 1000,
            "wall_time_s": 10.0, "parameters": params, "resolution": "4"}


def _results(blade_grains, blade_wedge, wall_wedge):
    out = {}
    for label, case, params, res in resolution.study_set():
        if case == "critical_height":
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
    wedge = [(label, p) for label, case, p, _ in resolution.study_set() if label.endswith("_wedge")]
    grains = [label for label in labels if not label.endswith("_wedge") and not label.startswith("critical")]
    assert len(wedge) == len(grains) and all(p["wedge"] == 1.0 for _, p in wedge)


def test_each_model_is_gated_on_its_own_runs(tmp_path):
    gates = {g["label"]: g for g in resolution.study_gates(_results(1.79, 1.15, 1.30))}
    assert gates["blade a90 d0.3, 4 grains across d: draft / FEE"]["passed"] is False
    assert gates["blade a90 d0.3, 4 grains across d, soil wedge: draft / FEE"]["passed"] is True
    assert gates["blade a90 d0.3, 8 grains across d, soil wedge: draft / FEE"]["passed"] is True
    # the wall's mean of three packings at 1.30 x is outside its 20%
    wall = "passive wall H0.3, 4 grains across H, soil wedge: thrust / Rankine, mean of 3 packings"
    assert gates[wall]["passed"] is False and abs(gates[wall]["measured"] - 1.30) < 1e-9
    d2 = gates["blade draft ~ d^2 (d 0.3 vs 0.2), 4 grains across d, soil wedge"]
    assert d2["passed"] is True and abs(d2["measured"] - 2.25) < 1e-9


def test_the_report_has_both_columns_and_the_plot(tmp_path):
    results = _results(1.79, 1.15, 1.10)
    del results["blade_a90_d0.3_n12_wedge"]
    path = resolution.write_study(results, resolution.study_gates(results), tmp_path / "resolution.md", "cmd")
    text = path.read_text()
    assert "| 4 | 1,000 | 4957 | 1.790 | 10 | 3185 | 1.150 | 10 |" in text
    assert "| 12 | 1,000 | 4957 | 1.790 | 10 | not run | - | - |" in text
    assert "soil wedge: draft / FEE (within 25%) | 1.150 | 1.000 | +15.0% | pass |" in text
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
