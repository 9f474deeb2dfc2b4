"""The loop's seams, used from outside the package as a user would: a controller and observers of their own,
several machines in one scene, several simulations in one process."""
import threading
from pathlib import Path

import numpy as np
import pytest

import opera_taichi as ot
from opera_taichi.recorders import read_csv_columns

ROOT = Path(__file__).resolve().parent.parent
DIG_CYCLE = ROOT / "scenes" / "zx120_dig_cycle.yaml"
BLADE = ROOT / "scenes" / "blade_cut.yaml"
EXCAVATION = ROOT / "scenes" / "zx120_excavation.yaml"


class BoomTo:
    """A controller of the test's own: the boom to a fixed angle, nothing else commanded."""

    def __init__(self, target):
        self.target, self.calls = target, 0

    def control(self, sim, t):
        self.calls += 1
        return ot.Control({"zx120": ot.MachineControl(q_target={"boom_joint": self.target})}, t, "test")


class BoomLog(ot.Observer):
    rate = 50.0

    def start(self, sim, run):
        self.t, self.boom, self.status = [], [], None

    def sample(self, sim):
        q, _, _ = sim.machines["zx120"].joint_states()
        self.t.append(sim.t)
        self.boom.append(q[1])

    def close(self, sim, status, message):
        self.status = status


class GatedSink(ot.ThreadedObserver):
    """A network-like sink whose first publish blocks until the run closes: the simulation must not wait for it."""

    def start(self, sim, run):
        self.gate, self.samples, self.seen = threading.Event(), 0, []
        super().start(sim, run)

    def snapshot(self, sim):
        self.samples += 1
        return sim.t

    def publish(self, t):
        self.gate.wait(timeout=120)
        self.seen.append(t)

    def close(self, sim, status, message):
        self.final_t = sim.t
        self.gate.set()
        super().close(sim, status, message)


def test_a_controller_and_observers_from_outside_drive_and_watch_a_run(tmp_path):
    scene = ot.load_scene(DIG_CYCLE, ["sim.duration=2", "output.plots=false"])
    controller, log, sink = BoomTo(-0.3), BoomLog(), GatedSink()
    result = ot.run_scene(scene, out_dir=tmp_path / "run", quiet=True, controller=controller, observers=[log, sink])
    assert result.status == "done" and log.status == "done"
    assert controller.calls == 2000                                  # one Control per rigid step
    assert len(log.t) == 101 and np.allclose(np.diff(log.t), 0.02)   # at its own rate, from t = 0
    sim_dt = 1e-3
    speed = np.abs(np.diff(log.boom)) / 0.02
    from opera_taichi.machine_description import load_machine

    limit = load_machine("zx120").actuators["boom_joint"].max_speed
    assert speed.max() <= limit * 1.02 + 1e-9                        # through the actuator's speed limit
    assert abs(log.boom[-1] - (-0.3)) < 0.01                         # and to the target
    cols = read_csv_columns(tmp_path / "run" / "joints.csv")
    assert np.all(cols["boom_joint.q_cmd"][1:] == -0.3)              # what was applied is what is recorded
    assert np.all(np.abs(cols["swing_joint.q"]) < 1e-3)              # the scene's script (a 90 deg swing) is not used
    # latest wins: the sink saw its first snapshot and, once released, only the newest; the run never waited
    assert sink.samples == 2001 and sink.seen[-1] == pytest.approx(sink.final_t)
    assert len(sink.seen) == 2 and sink.skipped == sink.samples - 2
    assert sim_dt * 2000 == pytest.approx(result.sim_time)


def _two_machines(extra=()):
    lift = {"boom_joint": -46, "arm_joint": 114, "bucket_joint": 46}
    data = ["machine=null", "motion=null", "sim.duration=3.5", "output.plots=false",
            "machines=[{name: a, urdf: zx120, initial_joints_deg: %s,"
            " motion: {type: joint_waypoints, waypoints: [{t: 0, q_deg: {swing_joint: 0}},"
            " {t: 3, q_deg: {swing_joint: 90}}]}},"
            " {name: b, urdf: zx120, base_pose: {xyz: [0.0, 4.2, 0.0]}, initial_joints_deg: %s}]"
            % (lift, lift), *extra]
    return ot.load_scene(DIG_CYCLE, [d.replace("'", "") for d in data])


def test_two_machines_in_one_scene_touch_each_other(tmp_path):
    """Machine a swings its front toward machine b standing 4.2 m to its left: the two bodies collide in one rigid
    world, so a's swing stalls against b at its torque limit, short of where it gets alone (b removed)."""
    with_b = ot.run_scene(_two_machines(), out_dir=tmp_path / "both", quiet=True)
    alone_scene = _two_machines()
    alone_scene.machines = alone_scene.machines[:1]
    alone = ot.run_scene(alone_scene, out_dir=tmp_path / "alone", quiet=True)
    assert with_b.status == alone.status == "done"
    both = read_csv_columns(tmp_path / "both" / "joints.csv")
    solo = read_csv_columns(tmp_path / "alone" / "joints.csv")
    assert "a.swing_joint.q" in both and "b.swing_joint.q" in both and "swing_joint.q" in solo
    assert solo["swing_joint.q"][-1] > np.radians(85)                   # alone it swings to the target
    assert both["a.swing_joint.q"][-1] < np.radians(75)                 # b's front stops it
    from opera_taichi.machine_description import load_machine

    limit = load_machine("zx120").actuators["swing_joint"].max_torque
    assert both["a.swing_joint.effort"][-1] == pytest.approx(limit, rel=1e-6)  # pushing with all it has
    assert np.abs(solo["swing_joint.effort"][-50:]).max() < 0.1 * limit


def test_two_machines_dig_the_same_soil(tmp_path):
    """Both buckets lowered into one bed: each is a tool of the one soil, each is pushed back by it."""
    lower = ("{type: bucket_tip_path, waypoints: [{t: 0.0, xyz: [6.4, -0.164, 0.6], bucket_angle_deg: 100},"
             " {t: 1.5, xyz: [6.4, -0.164, -0.3], bucket_angle_deg: 105}]}")
    scene = _two_machines(["sim.duration=1.5", f"machines.0.motion={lower}", f"machines.1.motion={lower}",
                           "soil={preset: dirt, overrides: {radius: 0.12}, bed: [{min: [5.4, -1.0, -0.6],"
                           " max: [7.4, 5.2, 0.0]}], domain: {min: [5.0, -1.4, -0.7], max: [7.8, 5.6, 3.0]}}"])
    result = ot.run_scene(scene, out_dir=tmp_path / "dig", quiet=True)
    assert result.status == "done"
    cols = read_csv_columns(tmp_path / "dig" / "tool_wrench.csv")
    tools = np.asarray(cols["tool"])
    assert sorted(set(tools)) == ["a.bucket_link", "b.bucket_link"]
    for name in ("a.bucket_link", "b.bucket_link"):
        assert cols["fz"][tools == name].max() > 500.0, name   # each bucket is pushed up by the soil
    mass = read_csv_columns(tmp_path / "dig" / "soil_mass.csv")["mass_kg"]
    assert np.all(np.abs(mass - mass[0]) <= 1e-9 * mass[0])


def _blade():
    return ot.Simulation.from_scene(BLADE, {"soil.overrides.radius": 0.04, "tools.0.start.2": 0.2})


def _excavator():
    return ot.Simulation.from_scene(EXCAVATION, {"soil.overrides.radius": 0.16, "motion": None})


def _final(sim, steps, control=None):
    for _ in range(steps):
        sim.step(control)
    return sim.get_state()


def test_two_simulations_stepped_alternately_give_the_same_results_as_each_alone():
    steps = 300
    push = {"boom_joint": 0.2}
    alone = [_final(_blade(), steps), _final(_excavator(), steps, push)]
    a, b = _blade(), _excavator()
    for _ in range(steps):
        a.step()
        b.step(push)
    for single, pair in zip(alone, (a.get_state(), b.get_state())):
        assert single.t == pair.t
        for key in single.soil:
            assert np.array_equal(single.soil[key], pair.soil[key]), key
        assert np.array_equal(single.tool_wrench, pair.tool_wrench)
        for name, ms in single.machines.items():
            assert np.array_equal(ms.q, pair.machines[name].q)
    assert np.abs(alone[0].tool_wrench).max() > 0  # the blade is cutting: the soils did something


def test_get_state_set_state_round_trip_continues_bit_for_bit():
    sim = _excavator()
    push = {"boom_joint": 0.3, "arm_joint": 1.2}
    _final(sim, 200, push)
    saved = sim.get_state()
    first = _final(sim, 300, push)
    sim.set_state(saved)
    again = _final(sim, 300, push)
    assert first.t == again.t
    for key in first.soil:
        assert np.array_equal(first.soil[key], again.soil[key]), key
    assert np.array_equal(first.machines["zx120"].q, again.machines["zx120"].q)
    assert np.array_equal(first.tool_wrench, again.tool_wrench)


def test_a_machine_on_its_tracks_goes_on_bit_for_bit_from_a_state_and_from_a_checkpoint(tmp_path):
    """Driving and swinging on its tracks, the machine's wheels touch the ground in Bullet's contact caches: set
    back without them (joints and bases alone) the rerun drifted from its first step, 3 cm in 0.6 s. Both in the
    same simulation and in a fresh one from a checkpoint file, the rerun is the same bits."""
    def tracked():
        return ot.Simulation.from_scene(DIG_CYCLE, overrides={"machine.fixed_base": False, "motion": None,
                                                              "sim.dt": 0.002})

    drive = ot.Control(machines={"zx120": ot.MachineControl(track_speeds=(0.8, -0.3),
                                                            qd_target={"swing_joint": 0.5})})

    def path(sim, steps):
        out = []
        for _ in range(steps):
            sim.step(drive)
            out.append(np.concatenate([sim.machine.joint_states()[0], *sim.machine.base_pose()]))
        return np.array(out)

    sim = tracked()
    path(sim, 150)
    saved = sim.get_state()
    sim.save_checkpoint(tmp_path / "tracks.ckpt.npz")
    first = path(sim, 150)
    assert np.ptp(first[:, -7:-4], axis=0).max() > 0.05   # it drove
    sim.set_state(saved)
    assert np.array_equal(path(sim, 150), first)
    fresh = tracked()
    fresh.load_checkpoint(tmp_path / "tracks.ckpt.npz")
    assert np.array_equal(path(fresh, 150), first)


def test_a_refused_state_leaves_the_simulation_as_it_was():
    """A state without the soil's arrays (get_state(soil=False)) is refused by a simulation with soil, and the
    refusal sets nothing: the machine, the time and the soil stay where the simulation had taken them."""
    sim = _excavator()
    light = sim.get_state(soil=False)
    now = _final(sim, 200, {"boom_joint": 0.5})
    with pytest.raises(ValueError, match="no soil arrays"):
        sim.set_state(light)
    after = sim.get_state()
    assert not np.array_equal(light.machines["zx120"].q, now.machines["zx120"].q)  # the boom had moved
    assert after.t == now.t and after.step == now.step
    assert np.array_equal(after.machines["zx120"].q, now.machines["zx120"].q)
    for key in now.soil:
        assert np.array_equal(after.soil[key], now.soil[key]), key


def test_run_scene_takes_a_function_as_its_controller_and_refuses_anything_else_before_it_starts(tmp_path):
    """`controller=fn(sim, t)` drives the run as a CallableController; an object that is neither a controller nor
    a function is refused before a run folder is made or the soil is built."""
    scene = ot.load_scene(DIG_CYCLE, ["sim.duration=0.5", "output.plots=false"])
    result = ot.run_scene(scene, out_dir=tmp_path / "fn", quiet=True, controller=lambda sim, t: {"boom_joint": -0.3})
    assert result.status == "done"
    cols = read_csv_columns(tmp_path / "fn" / "joints.csv")
    assert np.all(cols["boom_joint.q_cmd"][1:] == -0.3)
    with pytest.raises(TypeError, match="controller: a Controller"):
        ot.run_scene(scene, out_dir=tmp_path / "bad", quiet=True, controller=42)
    assert not (tmp_path / "bad").exists()


def test_a_closed_simulation_neither_steps_nor_observes():
    sim = _excavator()
    sim.step()
    sim.close()
    for call in (sim.step, sim.observe, sim.soil_in_tools):
        with pytest.raises(RuntimeError, match="closed"):
            call()


def test_from_scene_names_the_scene_file_for_a_key_found_wrong_when_the_model_is_built():
    """A misspelt soil override passes the scene's schema (overrides are free keys) and is found when the soil is
    resolved: the error names the scene file, as `run` does and as load_scene does for its own keys."""
    from opera_taichi.errors import UserError

    with pytest.raises(UserError, match=r"zx120_excavation.yaml: soil.overrides.raduis: unknown key \(did you "
                                           r"mean 'radius'"):
        ot.Simulation.from_scene(EXCAVATION, {"soil.overrides.raduis": 0.1})


def test_soil_in_tools_weighs_the_grains_inside_the_buckets_hull_and_no_others():
    """Grains put inside the bucket's struck volume (its hull's centroid, in the world) count with their masses;
    a grain beside the bucket does not."""
    from opera_taichi.geometry import quat_to_matrix

    sim = _excavator()
    assert sim.soil_in_tools() == {"bucket_link": 0.0}  # in the air over the bed
    p, q, _, _ = sim.tool_pose(0)
    hull = sim.model.bindings[0].mesh.convex_hull
    centre = quat_to_matrix(q) @ hull.centroid + p
    added = np.array([centre, centre + [0.0, 0.0, 0.1], centre + [0.0, 3.0, 0.0]])
    sim.soil.add_particles(added, radii=[0.05] * 3)
    parts = sim.soil.particles(("positions", "masses"))  # (in the solver's order, not the order added)
    masses = [float(parts["masses"][np.argmin(np.linalg.norm(parts["positions"] - x, axis=1))]) for x in added]
    assert min(masses) > 0.0
    assert sim.soil_in_tools()["bucket_link"] == pytest.approx(masses[0] + masses[1], rel=1e-12)



def test_a_grain_in_flight_is_no_ground_in_the_terrain():
    """The ground heightmap (terrain_*.npz's z, the summary's heaped volume, compare's heave) is the soil resting on
    the ground: a grain falling through the air 1 m above the bed (soil spilling from a bucket at the run's last
    instant had read as a heap 1.4 m high) is in z_all only; the same grain at rest there would be ground."""
    from opera_taichi.observers import ground_and_all_heightmaps

    sim = ot.Simulation.from_scene(BLADE, overrides={"soil.overrides.radius": 0.08, "sim.duration": 0.1})
    soil = sim.soil
    grid = sim.model.soil.grid
    ix, iy = len(grid.x) // 3, len(grid.y) // 2
    over = [float(grid.x[ix]), float(grid.y[iy]), 1.0]
    for speed, ground in ((-3.0, False), (0.0, True)):
        parts = soil.particles()
        soil.set_particles(np.vstack([parts["positions"], over]),
                           velocities=np.vstack([parts["velocities"], [0.0, 0.0, speed]]),
                           radii=np.append(parts["radii"], soil.micro.radius))
        z, z_all = ground_and_all_heightmaps(sim)
        assert z_all[ix, iy] == pytest.approx(1.0 + soil.micro.radius, abs=1e-9)
        assert (z[ix, iy] == z_all[ix, iy]) == ground
        assert z[ix, iy] < 0.2 or ground
        soil.set_particles(parts["positions"], velocities=parts["velocities"], radii=parts["radii"])


def test_a_grain_resting_on_a_tools_rim_is_carried_not_ground():
    """A grain on the rim of a tool has its centre up to a radius outside the tool's outline seen from above: it
    rides with the tool (one such grain on the main job's bucket read as a spike of ground 1.45 m high). Within a
    grain's reach of the outline it is carried, along the whole rim (the test moved each grain toward the
    outline's middle, which beside a long edge runs along it: only grains near the middle counted); two radii out,
    beside the tool, it is not."""
    from opera_taichi.observers import carried_by_tools
    from opera_taichi.geometry import quat_to_matrix

    sim = ot.Simulation.from_scene(BLADE, overrides={"soil.overrides.radius": 0.08, "sim.duration": 0.1})
    p, q, _, _ = sim.tool_pose(0)
    hull = sim.model.bindings[0].mesh.convex_hull.vertices @ quat_to_matrix(q).T + p
    r = sim.soil.micro.radius
    edge_x, top = hull[:, 0].max(), hull[:, 2].max()
    end_y = hull[:, 1].max()
    points = np.array([[edge_x + 0.5 * r, p[1], top + r], [edge_x + 2.0 * r, p[1], top + r],
                       [edge_x + 0.5 * r, end_y - 0.05, top + r],     # beside the face, 5 cm from the blade's end
                       [edge_x + 0.5 * r, end_y + 0.5 * r, top + r],  # off the corner, within reach
                       [edge_x + r, end_y + r, top + r]])             # off the corner, 1.41 r away
    assert carried_by_tools(sim, points, reach=r).tolist() == [True, False, True, True, False]
    assert carried_by_tools(sim, points).tolist() == [False] * 5


class SlowStart(ot.Observer):
    """An observer whose start takes 100 s of the runner's clock (a view's server, a bridge's connection)."""
    rate = 1.0

    def __init__(self, clock):
        self.clock = clock

    def start(self, sim, run):
        self.clock.now += 100.0

    def sample(self, sim):
        pass


def test_an_observers_start_counts_as_set_up_not_as_stepping(tmp_path, monkeypatch):
    import json
    import time as real_time

    from opera_taichi import runner

    class Clock:  # the runner's clock: real time plus what the observer's start adds
        now = 0.0

        def perf_counter(self):
            return real_time.perf_counter() + self.now

        def __getattr__(self, name):
            return getattr(real_time, name)

    clock = Clock()
    monkeypatch.setattr(runner, "time", clock)
    scene = ot.load_scene(DIG_CYCLE, ["sim.duration=0.2", "output.plots=false"])
    result = ot.run_scene(scene, out_dir=tmp_path / "run", quiet=True, observers=[SlowStart(clock)])
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert result.status == "done"
    assert manifest["setup_wall_time_s"] >= 100.0          # the start is the run's set-up
    assert manifest["wall_time_s"] < 100.0                 # and not in the stepping's wall time
    assert result.real_time_factor > 0.2 / 100.0           # the real-time factor is the stepping's


class SaysOnClose(ot.Observer):
    """An observer that has something to say as the run closes (a bridge whose peer went away meanwhile)."""
    rate = 1.0

    def sample(self, sim):
        pass

    def close(self, sim, status, message):
        sim._warn("the peer went away while the run closed")


def test_what_an_observer_says_as_the_run_closes_is_kept_in_the_manifest(tmp_path):
    import json

    scene = ot.load_scene(DIG_CYCLE, ["sim.duration=0.1", "output.plots=false"])
    ot.run_scene(scene, out_dir=tmp_path / "run", quiet=True, observers=[SaysOnClose()])
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert manifest["run_warnings"] == ["the peer went away while the run closed"]
