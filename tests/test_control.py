"""Control modes through the Python API: position targets, velocity targets, the emergency stop, and what the
state records as applied."""
import re
from pathlib import Path

import numpy as np
import pytest

import opera_taichi as ot
from opera_taichi.errors import UserError

ROOT = Path(__file__).resolve().parent.parent
DIG_CYCLE = ROOT / "scenes" / "zx120_dig_cycle.yaml"


@pytest.fixture
def sim():
    s = ot.Simulation.from_scene(DIG_CYCLE, {"motion": None})
    yield s
    s.close()


def _run(sim, seconds, control=None):
    for _ in range(int(round(seconds / sim.model.dt))):
        sim.step(control)


def test_velocity_targets_move_a_joint_at_that_speed(sim):
    boom = sim.machine.joint_names.index("boom_joint")
    q0 = sim.state.machines["zx120"].q[boom]
    _run(sim, 1.0, ot.MachineControl(qd_target={"boom_joint": 0.1}))
    ms = sim.state.machines["zx120"]
    assert ms.velocity_mode[boom] and np.isnan(ms.q_cmd[boom])        # recorded as velocity mode
    assert ms.qd[boom] == pytest.approx(0.1, rel=0.02)
    assert ms.q[boom] - q0 == pytest.approx(0.1, rel=0.05)
    # a speed beyond the actuator's limit is capped by it
    limit = sim.machine.max_speed[boom]
    _run(sim, 0.5, ot.MachineControl(qd_target={"boom_joint": -10 * limit}))
    assert abs(sim.state.machines["zx120"].qd[boom]) <= limit * 1.01


def test_emergency_stop_holds_the_machine_where_it_is(sim):
    arm = sim.machine.joint_names.index("arm_joint")
    _run(sim, 0.5, {"arm_joint": 2.5})          # crowding toward 2.5 rad
    moving = sim.state.machines["zx120"]
    assert abs(moving.qd[arm]) > 0.1
    _run(sim, 0.5, ot.MachineControl(q_target={"arm_joint": 2.5}, hold=True))   # stop; the command is ignored
    held = sim.state.machines["zx120"]
    assert held.hold
    _run(sim, 1.0, {"arm_joint": 2.5})
    still = sim.state.machines["zx120"]
    assert abs(still.q[arm] - held.q[arm]) < 1e-3 and abs(still.qd[arm]) < 1e-2
    assert abs(held.q[arm] - moving.q[arm]) < 0.1   # stopped within the arm's speed x a few gain periods
    _run(sim, 1.0, ot.MachineControl(q_target={"arm_joint": 2.5}, hold=False))  # released: it goes on
    assert sim.state.machines["zx120"].q[arm] > still.q[arm] + 0.1


def test_targets_beyond_a_joint_limit_are_clipped_with_one_warning(sim, capsys):
    sim.quiet = False
    _run(sim, 0.01, {"bucket_joint": 10.0})
    _run(sim, 0.01, {"bucket_joint": 11.0})
    err = [line for line in capsys.readouterr().err.splitlines() if "bucket_joint" in line]
    assert len(err) == 1 and "clipped" in err[0]
    upper = sim.machine.joint_limits[1][sim.machine.joint_names.index("bucket_joint")]
    assert sim.state.machines["zx120"].q_cmd[sim.machine.joint_names.index("bucket_joint")] == upper


def test_a_control_for_an_unknown_machine_or_joint_is_a_clear_error(sim):
    with pytest.raises(UserError, match="no machine 'digger'"):
        sim.step(ot.Control({"digger": ot.MachineControl(q_target={"boom_joint": 0.0})}))
    with pytest.raises(UserError, match="unknown joint 'stick'"):
        sim.step({"stick": 0.0})


def test_a_target_that_is_no_number_is_refused_and_the_machine_goes_on(sim):
    """NaN would enter PyBullet's state for good (every later step diverging): refused before it is applied."""
    _run(sim, 0.05)
    before = sim.get_state()
    for control in ({"boom_joint": float("nan")}, ot.MachineControl(qd_target={"arm_joint": float("inf")}),
                    {"boom_joint": -0.5, "arm_joint": "high"}, {"boom_joint": True}, {"boom_joint": "0.1"},
                    {"boom_joint": np.array([0.1, 0.2])}, ot.MachineControl(q_target={"boom_joint": np.zeros(4)}),
                    {"boom_joint": np.True_}):
        with pytest.raises(UserError, match=r"is not a finite number \(rad"):
            sim.step(control)
    # commands of the wrong shape: one line saying what is expected, not a Python error from inside
    for control, message in ((ot.MachineControl(qd_target=[0.1, 0.2, 0.3, 0.4]), r"speed targets: a \{joint name"),
                             (ot.MachineControl(q_target=np.zeros(4)), r"joint targets: a \{joint name"),
                             (ot.MachineControl(track_speeds=(0.5,)), r"track speeds: \(left, right\)"),
                             (ot.MachineControl(hold="yes"), r"hold: True")):
        with pytest.raises(UserError, match=message):
            sim.step(control)
    after = sim.get_state()
    assert after.t == before.t and np.array_equal(after.machines["zx120"].q, before.machines["zx120"].q)
    # one number however it comes: a NumPy scalar or a 0-d array, keyed by joint or inside a MachineControl
    for value in (np.float32(-0.4), np.array(-0.4)):
        for control in ({"boom_joint": value}, ot.MachineControl(q_target={"boom_joint": value})):
            sim.step(control)
            assert sim.applied.machines["zx120"].q_target["boom_joint"] == pytest.approx(-0.4)
    _run(sim, 0.05, {"boom_joint": -0.5})   # and it steps on
    assert np.all(np.isfinite(sim.machine.joint_states()[0]))


def test_the_applied_control_is_part_of_the_state(sim):
    sim.step(ot.Control({"zx120": ot.MachineControl(q_target={"swing_joint": 0.2})}, source="test"))
    state = sim.get_state()
    assert state.control.source == "test" and state.control.t == pytest.approx(sim.model.dt)
    swing = sim.machine.joint_names.index("swing_joint")
    assert state.machines["zx120"].q_target[swing] == 0.2
    sim.step(None)   # no command: the last ones stay
    assert sim.state.machines["zx120"].q_target[swing] == 0.2


def test_a_machines_control_that_is_neither_a_machine_control_nor_a_dict_is_named(sim):
    """{machine: value} or Control(machines={...}) with a value that is no MachineControl: one line naming the
    machine (was an AttributeError or TypeError from inside); a {joint: rad} dict there is taken as targets."""
    for control in ({"zx120": 0.5}, ot.Control(machines={"zx120": [0.1, 0.2]})):
        with pytest.raises(UserError, match=r"control of machine 'zx120': expected a MachineControl or a \{joint: "):
            sim.step(control)
    sim.step(ot.Control(machines={"zx120": {"boom_joint": -0.45}}))
    assert sim.applied.machines["zx120"].q_target["boom_joint"] == pytest.approx(-0.45)


def test_set_state_refuses_a_state_that_does_not_fit_and_changes_nothing(sim):
    """Arrays of another length, a wrench of another shape, a state of another model: refused before anything is
    set (each was taken, and the next step failed or went on with another model's state)."""
    _run(sim, 0.02, {"boom_joint": -0.5})
    good = sim.get_state()
    short = good.copy()
    short.machines["zx120"].q = np.zeros(2)
    wrench = good.copy()
    wrench.tool_wrench = np.zeros((len(good.tool_wrench) + 2, 6))
    foreign = good.copy()
    foreign.model = "0" * 16
    for state, words in [(short, "machine zx120: the state's q has shape (2,), expected (4,)"),
                         (wrench, "the state's tool_wrench has shape"),
                         (foreign, "the state was taken from another model")]:
        with pytest.raises(ValueError, match=re.escape(words)):
            sim.set_state(state)
    after = sim.get_state()
    assert after.t == good.t and np.array_equal(after.machines["zx120"].q, good.machines["zx120"].q)
    other = ot.Simulation.from_scene(DIG_CYCLE, {"motion": None, "sim.dt": 0.002})
    try:
        with pytest.raises(ValueError, match="another model"):
            other.set_state(good)
    finally:
        other.close()
    sim.set_state(good)   # its own state, as taken
