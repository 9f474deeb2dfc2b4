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


def _roles(soil):
    """The wedge's and the layer's grains, found from the tool's row as the kernels find them (_wedge_role)."""
    p = soil.particles(["positions", "velocities", "radii", "masses"])
    x, r = p["positions"], p["radii"]
    row = soil._tools_host[0]
    rel = x - row[dem.T_WG_EW:dem.T_WG_EW + 3]
    s_f = rel @ row[dem.T_WG_NW:dem.T_WG_NW + 3]
    band = (s_f > -r) & (np.abs(rel @ row[dem.T_WG_YW:dem.T_WG_YW + 3]) < row[dem.T_WG_HW])
    low = row[dem.T_WG_EW + 2] - dem.WG_LOW * r
    s_g = (rel + np.outer(dem.WG_LOW * r, [0.0, 0.0, 1.0])) @ row[dem.T_WG_MG:dem.T_WG_MG + 3]
    wedge = band & (s_g < 0) & (x[:, 2] > low) & (x[:, 2] < row[dem.T_WG_TOP])
    layer = band & (s_g >= 0) & (s_g < dem.WG_LAYER_R * r) & (x[:, 2] > low - 2 * r)
    return p, wedge, layer, row


def test_the_wedge_moves_its_grains_pushes_the_tool_back_and_keeps_the_mass():
    sim = _blade()
    soil = sim.soil
    before = sum(soil.mass_budget().values())
    wrench = _run(sim, 900)  # 0.9 s: 0.19 m into the bed
    p, wedge, layer, row = _roles(soil)
    assert row[dem.T_WG_LIVE] == 1.0 and wedge.sum() >= 20 and layer.sum() >= 10
    # every grain of the wedge moves with it, exactly: along the failure plane, as fast into the soil as the face
    assert np.array_equal(p["velocities"][wedge], np.broadcast_to(row[dem.T_WG_VW:dem.T_WG_VW + 3], (wedge.sum(), 3)))
    v_w = row[dem.T_WG_VW:dem.T_WG_VW + 3]
    assert v_w[0] == pytest.approx(-0.3) and v_w[2] > 0.0  # forward with the blade, up the plane
    # the wedge's push holds the blade back (+x on a blade driven along -x) and is part of the wrench
    push = row[dem.T_WG_PUSH:dem.T_WG_PUSH + 3]
    assert push[0] > 0.0 and wrench[-100:, 0, 0].mean() > 0.0
    after = sum(soil.mass_budget().values())
    assert after == pytest.approx(before, rel=1e-9)


def test_a_tool_that_does_not_cut_is_left_to_the_grains():
    # the same edge on the blade's back face: moving away from that face, the wedge never acts, and the run is the
    # run without an edge, bit for bit
    back = EDGE.replace("face_normal: [-1, 0, 0]", "face_normal: [1, 0, 0]").replace("-0.02", "0.02")
    with_back_edge = _run(_blade(back), 700)
    without = _run(_blade(None), 700)
    assert np.array_equal(with_back_edge, without)
    assert np.abs(without[-50:, 0, 0]).max() > 0.0  # (the blade did touch the soil)


def test_a_resumed_wedge_goes_on_bit_for_bit():
    sim = _blade()
    _run(sim, 600)
    state = sim.get_state()
    ahead = _run(sim, 200)
    again = _blade()
    again.set_state(state)
    assert np.array_equal(_run(again, 200), ahead)


GOOD = "{centre: [0, 0, -0.4], face_normal: [-1, 0, 0], face_up: [0, 0, 1], width: 1.0}"


@pytest.mark.parametrize("edge, extra, words", [
    (GOOD.replace("face_normal: [-1, 0, 0]", "face_normal: [0, 0, 0]"), [],
     ["tools.blade.cutting_edge.face_normal", "zero vector"]),
    (GOOD.replace("face_up: [0, 0, 1]", "face_up: [2, 0, 0]"), [], ["tools.blade.cutting_edge.face_up", "parallel"]),
    (GOOD.replace("width: 1.0", "width: -1"), [], ["tools.0.cutting_edge.width", "> 0"]),
    (GOOD.replace(", width: 1.0", ""), [], ["tools.0.cutting_edge.width"]),
    (GOOD, ["soil.sleep=true"], ["tools.blade.cutting_edge", "soil.sleep"]),
], ids=["zero normal", "up along the normal", "negative width", "no width", "on a sleeping soil"])
def test_a_bad_cutting_edge_is_one_line_and_exit_2(edge, extra, words, capsys, tmp_path):
    sets = [a for s in COARSE + [f"tools.0.cutting_edge={edge}", *extra] for a in ("--set", s)]
    rc = cli.main(["run", str(SCENE), "--out", str(tmp_path / "run"), "--quiet", *sets])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    for w in words:
        assert w in err[0], err[0]


@pytest.mark.slow
def test_at_4_grains_across_the_wedge_reads_the_earthmoving_equation(tmp_path):
    # plane strain a90 d0.15 at 4 grains across the cut, 0.3 m/s: the grains alone push back about 1.8 x the
    # equation (docs/validation.md); the wedge, whose strength is the equation's, within the 25% the issue asks
    params = {"depth": "0.15", "speed": "0.3"}
    grains = cases.run_case("blade_cut", params, "4", tmp_path / "grains", arch="cpu")
    wedge = cases.run_case("blade_cut", {**params, "wedge": "1"}, "4", tmp_path / "wedge", arch="cpu")
    assert grains["measured"] / grains["reference"] > 1.5
    assert abs(wedge["measured"] / wedge["reference"] - 1.0) <= 0.25
