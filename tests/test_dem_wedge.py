"""The soil wedge at a tool's cutting edge (tools.cutting_edge; AGX Terrain's soil aggregate): its grains move with
it, a tool that does not cut is left to the grains, the push reads the earthmoving equation at a few grains across
the cut where the grains alone read far more, a resumed state goes on bit for bit, and bad edges are refused."""
from pathlib import Path

import numpy as np
import pytest

from opera_taichi import cli
from opera_taichi.kernels import dem
from opera_taichi.simulation import Simulation
from opera_taichi.validation import cases

REPO = Path(__file__).resolve().parents[1]
SCENE = REPO / "scenes" / "blade_cut.yaml"
# the blade travels toward -x at 0.3 m/s, 0.3 m deep: its soil face looks along -x; 6 cm grains, a short cut
EDGE = "{centre: [-0.02, 0.0, -0.4], face_normal: [-1, 0, 0], face_up: [0, 0, 1], width: 1.0}"
COARSE = ["soil.overrides.radius=0.06", "sim.duration=1.5"]


@pytest.fixture(scope="module", autouse=True)
def _taichi():
    from opera_taichi.backend import init_taichi

    init_taichi("cpu")


def _blade(edge: str | None = EDGE, *extra):
    sets = COARSE + list(extra) + ([f"tools.0.cutting_edge={edge}"] if edge else [])
    return Simulation.from_scene(SCENE, overrides=sets, arch="cpu")


def _run(sim, steps):
    wrenches = []
    for _ in range(steps):
        sim.step()
        wrenches.append(sim.tool_wrench.copy())
    return np.array(wrenches)


def _roles(soil, margin=0.5):
    """The wedge's and the layer's grains, found from the tool's row as the kernels find them (_wedge_role), each at
    least `margin` radii inside its region (the row is the one after the last substep, the roles were found before)."""
    p = soil.particles(["positions", "velocities", "radii", "masses"])
    x, r = p["positions"], p["radii"]
    row = soil._tools_host[0]
    rel = x - row[dem.T_WG_EW:dem.T_WG_EW + 3]
    s_f = rel @ row[dem.T_WG_NW:dem.T_WG_NW + 3]
    a = margin * r
    band = (s_f > -r + a) & (np.abs(rel @ row[dem.T_WG_YW:dem.T_WG_YW + 3]) < row[dem.T_WG_HW] - a)
    low = row[dem.T_WG_EW + 2] - dem.WG_LOW * r
    s_g = (rel + np.outer(dem.WG_LOW * r, [0.0, 0.0, 1.0])) @ row[dem.T_WG_MG:dem.T_WG_MG + 3]
    wedge = band & (s_g < -a) & (x[:, 2] > low + a) & (x[:, 2] < row[dem.T_WG_TOP] - a)
    layer = band & (s_g >= a) & (s_g < dem.WG_LAYER_R * r - a) & (x[:, 2] > low - 2 * r + a)
    return p, wedge, layer, row


def test_the_wedge_moves_its_grains_pushes_the_tool_back_and_keeps_the_mass():
    sim = _blade()
    soil = sim.soil
    before = sum(soil.mass_budget().values())
    wrench = _run(sim, 900)  # 0.9 s: 0.19 m into the bed
    p, wedge, layer, row = _roles(soil)
    assert row[dem.T_WG_ENGAGED] == 1.0 and wedge.sum() >= 20 and layer.sum() >= 10
    # every grain of the wedge moves with it: along the failure plane, as fast into the soil as the face (to the
    # last substep's failure angle, which the next one refines by ~1e-10)
    assert np.allclose(p["velocities"][wedge], row[dem.T_WG_VW:dem.T_WG_VW + 3], rtol=0, atol=1e-8)
    assert not np.allclose(p["velocities"][layer], row[dem.T_WG_VW:dem.T_WG_VW + 3], rtol=0, atol=1e-3)
    v_w = row[dem.T_WG_VW:dem.T_WG_VW + 3]
    assert v_w[0] == pytest.approx(-0.3) and v_w[2] > 0.0  # forward with the blade, up the plane
    # the wedge's push holds the blade back (+x on a blade driven along -x) and is part of the wrench
    push = row[dem.T_WG_PUSH:dem.T_WG_PUSH + 3]
    assert push[0] > 0.0 and wrench[-100:, 0, 0].mean() > 0.0
    after = sum(soil.mass_budget().values())
    assert after == pytest.approx(before, rel=1e-9)


def test_the_layer_beyond_the_plane_does_not_outrun_the_wedge():
    """The layer beyond the failure plane takes the plane's reaction only while it moves slower than the wedge that
    drives it: left to the push alone, a layer at the verge of sliding ran away along the plane (here its fastest
    grain reached 12.3 x the wedge's speed; at 20 grains across d the blade diverged)."""
    sim = _blade(EDGE, "sim.duration=3.0")
    soil = sim.soil
    worst = []
    while sim.t < 2.95:
        sim.step()
        p, _, layer, row = _roles(soil, margin=0.0)
        if row[dem.T_WG_ENGAGED] > 0.0 and layer.any():
            speed = np.linalg.norm(p["velocities"][layer], axis=1).max()
            worst.append(speed / np.linalg.norm(row[dem.T_WG_VW:dem.T_WG_VW + 3]))
    assert len(worst) > 1000 and max(worst) < 6.0, max(worst)  # (3.9 with the rule)


@pytest.mark.parametrize("edge, warning", [
    # the same edge on the blade's back face: the blade moves away from that face
    (EDGE.replace("face_normal: [-1, 0, 0]", "face_normal: [1, 0, 0]").replace("-0.02", "0.02"), "never moves into"),
    # a face that falls from its edge (up the face is down): no wedge is cut under the tool
    (EDGE.replace("face_up: [0, 0, 1]", "face_up: [0, 0, -1]"), "face_up points down"),
], ids=["moving away from its face", "face falling from the edge"])
def test_an_edge_that_cannot_cut_leaves_the_tool_to_the_grains_and_says_so(edge, warning):
    # bit for bit the run without an edge, and a warning that names the key
    sim = _blade(edge)
    with_edge = _run(sim, 700)
    without = _run(_blade(None), 700)
    assert np.array_equal(with_edge, without)
    assert np.abs(without[-50:, 0, 0]).max() > 0.0  # (the blade did touch the soil)
    assert any("tools.blade.cutting_edge" in w and warning in w for w in sim.warnings), sim.warnings


def test_the_wedge_waits_for_the_soil_to_touch_the_face():
    # the blade starts 8 cm short of the soil: nothing may push it until its face meets the grains (the wedge's
    # region reaches a metre ahead of the edge, beyond that gap)
    sim = _blade()
    early = _run(sim, 150)  # 0.15 s: 4.5 cm of the gap closed
    assert sim.soil._tools_host[0, dem.T_WG_ENGAGED] == 0.0
    assert not np.any(early)
    later = _run(sim, 500)
    assert sim.soil._tools_host[0, dem.T_WG_ENGAGED] == 1.0 and later[-100:, 0, 0].mean() > 0.0


def test_a_resumed_wedge_goes_on_bit_for_bit():
    sim = _blade()
    _run(sim, 600)
    state = sim.get_state()
    ahead = _run(sim, 200)
    again = _blade()
    again.set_state(state)
    assert np.array_equal(_run(again, 200), ahead)


GOOD = "{centre: [-0.02, 0, -0.4], face_normal: [-1, 0, 0], face_up: [0, 0, 1], width: 1.0}"


@pytest.mark.parametrize("edge, extra, words, schema", [
    (GOOD.replace("face_normal: [-1, 0, 0]", "face_normal: [0, 0, 0]"), [],
     ["tools.0.cutting_edge.face_normal", "a direction (not all zero)"], True),
    (GOOD.replace("face_up: [0, 0, 1]", "face_up: [-2e-300, 0, 0]"), [],
     ["tools.0.cutting_edge.face_up", "across face_normal"], True),
    (GOOD.replace("width: 1.0", "width: -1"), [], ["tools.0.cutting_edge.width", "> 0"], True),
    (GOOD.replace(", width: 1.0", ""), [], ["tools.0.cutting_edge.width"], True),
    (GOOD.replace("width: 1.0", "width: 3.0"), [], ["tools.blade.cutting_edge.width", "runs past the tool"], False),
    (GOOD.replace("centre: [-0.02, 0, -0.4]", "centre: [-2.0, 0, -0.4]"), [],
     ["tools.blade.cutting_edge.centre", "off the tool"], False),
], ids=["zero normal", "up along the normal", "negative width", "no width", "wider than the tool",
        "off the tool"])
def test_a_bad_cutting_edge_is_one_line_and_exit_2(edge, extra, words, schema, capsys, tmp_path):
    sets = [a for s in COARSE + [f"tools.0.cutting_edge={edge}", *extra] for a in ("--set", s)]
    rc = cli.main(["run", str(SCENE), "--out", str(tmp_path / "run"), "--quiet", *sets])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    for w in words:
        assert w in err[0], err[0]
    # what the schema can tell, `validate` tells too, before any soil is built
    assert cli.main(["validate", str(SCENE), *sets]) == (2 if schema else 0)
    capsys.readouterr()


@pytest.mark.slow
def test_at_4_grains_across_the_wedge_reads_the_earthmoving_equation(tmp_path):
    # plane strain a90 d0.15 at 4 grains across the cut, 0.3 m/s: the grains alone push back about 1.8 x the
    # equation (docs/validation.md); the wedge, whose strength is the equation's, within the 25% the issue asks
    params = {"depth": "0.15", "speed": "0.3"}
    grains = cases.run_case("blade_cut", params, "4", tmp_path / "grains", arch="cpu")
    wedge = cases.run_case("blade_cut", {**params, "wedge": "1"}, "4", tmp_path / "wedge", arch="cpu")
    assert grains["measured"] / grains["reference"] > 1.5
    assert abs(wedge["measured"] / wedge["reference"] - 1.0) <= 0.25


@pytest.mark.slow
def test_a_wedge_cuts_sleeping_and_frozen_soil_as_it_cuts_awake_soil(monkeypatch, tmp_path):
    """The blade with its edge through an awake bed, a sleeping one and one whose far soil is frozen (beds of any
    size, one live layer), on twelve packings: the wedge's grains, the layer beyond its plane and the ground ahead it
    reads wake or are read asleep, so the mean steady draft is the same within 5%, and the mass is kept to round-off.
    (One cut is one sample of a chaotic path, 6-7% apart from seed to seed at 6 cm, so it takes many: sleeping and
    frozen minus awake read +3.4 / +4.2% over seeds 0-11, +6.0 / +7.2% over 0-5 and +0.7 / +1.4% over 6-11; before
    the layer beyond the plane was held to the wedge's speed, +0.9 / -0.6% over 0-2 and +6.9 / +2.8% over 3-5. A
    wedge blind to the sleeping ground ahead would not engage, and the grains alone read about twice the draft.)"""
    from opera_taichi import dem_soil
    from opera_taichi.recorders import read_csv_columns

    drafts = {}
    for sleep, freeze in (("false", False), ("true", False), ("true", True)):
        if freeze:
            monkeypatch.setattr(dem_soil, "FREEZE_MIN", 0)
            monkeypatch.setattr(dem_soil, "FREEZE_FEWEST", 0)
            monkeypatch.setattr(dem_soil, "FREEZE_LAYERS", 1)
        for seed in range(12):
            out = tmp_path / f"{sleep}_{freeze}_{seed}"
            sets = COARSE[:1] + ["sim.duration=3.0", f"soil.sleep={sleep}", f"tools.0.cutting_edge={EDGE}",
                                 f"sim.seed={seed}", "output.plots=false"]
            assert cli.main(["run", str(SCENE), "--quiet", "--out", str(out),
                             *[a for s in sets for a in ("--set", s)]]) == 0
            mass = read_csv_columns(out / "soil_mass.csv")["mass_kg"]
            assert np.all(np.abs(mass - mass[0]) <= 1e-9 * mass[0])
            w = read_csv_columns(out / "tool_wrench.csv")
            drafts.setdefault((sleep, freeze), []).append(float(w["fx"][w["t"] > 1.0].mean()))
    awake = np.mean(drafts[("false", False)])
    assert awake > 1000.0
    assert np.mean(drafts[("true", False)]) == pytest.approx(awake, rel=0.05), drafts
    assert np.mean(drafts[("true", True)]) == pytest.approx(awake, rel=0.05), drafts


def _scoop_scene(tmp_path, opening: bool) -> Path:
    """The blade scene with an open scoop instead of the blade: floor, back and two sides, 0.6 m wide inside, its mouth
    (the floor's front edge up to the sides' tops) looking along -x, the edge 0.3 m deep."""
    import trimesh

    length, width, height, t = 0.6, 0.6, 0.5, 0.02
    parts = [trimesh.creation.box((length, width + 2 * t, t)).apply_translation((length / 2, 0, t / 2)),
             trimesh.creation.box((t, width + 2 * t, height)).apply_translation((length - t / 2, 0, height / 2))]
    for side in (1, -1):
        parts.append(trimesh.creation.box((length, t, height)).apply_translation(
            (length / 2, side * (width + t) / 2, height / 2)))
    trimesh.util.concatenate(parts).export(tmp_path / "scoop.obj")
    text = SCENE.read_text()
    for old, new in (("box: [0.04, 1.0, 0.8]", "mesh: scoop.obj"), ("start: [2.6, 0.0, 0.1]", "start: [2.55, 0.0, -0.3]")):
        assert old in text
        text = text.replace(old, new)
    text = text.replace("    start_time: 0.0\n", "    start_time: 0.0\n    cutting_edge: {centre: [0, 0, 0], face_normal: "
                        f"[-1, 0, 0], face_up: [0, 0, 1], width: 0.64, opening: {str(opening).lower()}}}\n")
    path = tmp_path / f"scoop_{opening}.yaml"
    path.write_text(text)
    return path


def test_an_opening_takes_in_the_soil_over_its_edge_where_a_face_pushes_it_ahead(tmp_path):
    """A scoop cutting 0.3 m deep at 6 cm grains (2.5 across the cut). With its mouth an opening (a bucket's,
    machine.yaml's cutting_edges), its wedge is the soil its edge meets: every grain of it lies within a grain radius
    of the edge up the mouth (and a substep's moves), the soil over the edge is free, the scoop fills and the wedge
    still holds the scoop back, and the scoop slides under the soil it cuts: it takes in more than half of what its
    mouth swept (the edge's soil sliding along the failure plane, as a plate's wedge does, shoved the soil ahead of the
    mouth: 0.40 of it). With the mouth a plate (a blade's face) the whole wedge slides up it, ahead of the scoop, which
    stays empty. The mass is kept to round-off either way."""
    held = {}
    for opening in (True, False):
        sim = Simulation.from_scene(_scoop_scene(tmp_path, opening), overrides=["soil.overrides.radius=0.06"],
                                    arch="cpu")
        soil = sim.soil
        before = sum(soil.mass_budget().values())
        push, seen, high = [], 0, 0
        for k in range(1500):  # 1.5 s: 0.45 m of travel, 0.4 m of it in the soil
            sim.step()
            row = soil._tools_host[0]
            push.append(row[dem.T_WG_PUSH])
            if k % 50 == 49 and row[dem.T_WG_ENGAGED] == 1.0:
                p = soil.particles(["positions", "velocities", "radii"])
                # the wedge's grains move exactly as the wedge does (the tool only translates: no turn about the
                # edge); how far up the mouth (+z) each lies above the edge, against its radius
                moving = np.all(np.abs(p["velocities"] - row[dem.T_WG_VW:dem.T_WG_VW + 3]) < 1e-8, axis=1)
                up = (p["positions"] - row[dem.T_WG_EW:dem.T_WG_EW + 3])[moving, 2] - p["radii"][moving]
                seen += int(moving.sum())
                high += int(np.sum(up > 1e-3))  # (1 mm: a substep's moves)
        assert soil._tools_host[0, dem.T_WG_ON] == (dem.WG_OPENING if opening else dem.WG_PLATE) and seen >= 20
        if opening:
            assert high == 0
        else:
            assert high >= 0.5 * seen  # (the wedge reaches up to the ground ahead)
        assert np.mean(push[500:]) > 0.0  # the wedge holds the scoop back (it travels along -x)
        held[opening] = sim.soil_in_tools()[sim.model.bindings[0].name]
        assert sum(soil.mass_budget().values()) == pytest.approx(before, rel=1e-9)
    # the mouth, 0.6 m wide inside, swept 0.4 m of the bed 0.3 m deep
    swept = 0.4 * 0.3 * 0.6 * soil.bulk.density
    assert held[True] > 0.5 * swept and held[False] < 0.2 * held[True], (held, swept)
