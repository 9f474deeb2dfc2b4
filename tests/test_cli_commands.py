"""The CLI's commands and exit codes, with the simulation replaced by a stand-in (no Taichi here)."""
import types
from pathlib import Path

import pytest

from opera_taichi import __version__, cli
from opera_taichi.errors import DivergenceError, UserError


@pytest.fixture
def scene_file(tmp_path) -> Path:
    path = tmp_path / "dig.yaml"
    path.write_text("sim: {duration: 2.0, arch: cpu}\n")
    return path


@pytest.fixture
def fake_simulation(monkeypatch):
    """Stands in for opera_taichi.simulation; records what the CLI passes and can be told to fail."""
    calls = {}

    def run_scene(scene, out_dir=None, arch=None, quiet=False, **kwargs):
        calls.update(scene=scene, out_dir=out_dir, arch=arch, quiet=quiet, **kwargs)
        if "raise" in calls:
            raise calls["raise"]
        return types.SimpleNamespace(out_dir=Path(out_dir))

    def check_scene(scene):
        calls["checked"] = scene
        if "raise" in calls:
            raise calls["raise"]
        return types.SimpleNamespace(warnings=())

    from opera_taichi import model, runner

    monkeypatch.setattr(runner, "run_scene", run_scene)
    monkeypatch.setattr(model, "check_scene", check_scene)
    return calls


def test_validate_prints_ok_and_runs_the_simulation_checks(scene_file, fake_simulation, capsys):
    assert cli.main(["validate", str(scene_file), "--set", "sim.duration=3"]) == 0
    assert capsys.readouterr().out == f"{scene_file}: ok\n"
    assert fake_simulation["checked"].sim.duration == 3.0


def test_validate_of_a_scene_without_machine_or_soil(scene_file, capsys):
    assert cli.main(["validate", str(scene_file)]) == 0
    assert capsys.readouterr().out.endswith(": ok\n")


def test_validate_reports_a_check_failure_as_one_line(scene_file, fake_simulation, capsys):
    fake_simulation["raise"] = UserError("machine.initial_joints.foo: not an actuated joint\nof zx120")
    assert cli.main(["validate", str(scene_file)]) == 2
    err = capsys.readouterr().err
    assert err == f"error: {scene_file}: machine.initial_joints.foo: not an actuated joint of zx120\n"
    # an error about something other than a scene key is passed on as it is
    fake_simulation["raise"] = UserError("--out: runs/x is a file, not a folder")
    assert cli.main(["validate", str(scene_file)]) == 2
    assert capsys.readouterr().err == "error: --out: runs/x is a file, not a folder\n"


def test_run_passes_out_dir_arch_and_quiet(scene_file, fake_simulation, tmp_path, capsys):
    out = tmp_path / "run1"
    assert cli.main(["run", str(scene_file), "--out", str(out), "--arch", "auto"]) == 0
    assert fake_simulation["out_dir"] == str(out) and fake_simulation["arch"] == "auto"
    assert fake_simulation["scene"].sim.arch == "auto"  # the manifest records the backend asked for
    assert fake_simulation["quiet"] is False
    assert capsys.readouterr().out == f"{out}\n"


def test_run_quiet_prints_nothing(scene_file, fake_simulation, capsys, tmp_path):
    assert cli.main(["run", str(scene_file), "--quiet", "--out", str(tmp_path / "r")]) == 0
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""
    assert fake_simulation["arch"] == "cpu" and fake_simulation["quiet"] is True


def test_default_run_folders_are_timestamped_and_never_collide(scene_file, tmp_path, monkeypatch):
    from opera_taichi.runner import claim_run_folder
    from opera_taichi.scene import load_scene

    monkeypatch.chdir(tmp_path)
    scene = load_scene(scene_file)
    first, second = claim_run_folder(scene, None), claim_run_folder(scene, None)  # within the same second
    assert first.parent == second.parent == Path("runs") and first.name.startswith("dig-")
    assert first != second and first.is_dir() and second.is_dir()


def test_divergence_exits_3_with_one_line(scene_file, fake_simulation, capsys):
    fake_simulation["raise"] = DivergenceError("particle speed 412 m/s > soil.max_speed 30 m/s at t = 1.234 s")
    assert cli.main(["run", str(scene_file), "--quiet"]) == 3
    assert capsys.readouterr().err == "diverged: particle speed 412 m/s > soil.max_speed 30 m/s at t = 1.234 s\n"


def test_interrupt_exits_130_with_one_line(scene_file, fake_simulation, capsys):
    fake_simulation["raise"] = KeyboardInterrupt()
    assert cli.main(["run", str(scene_file)]) == 130
    assert capsys.readouterr().err == "interrupted\n"


def test_sigterm_exits_143_with_one_line_and_restores_the_handler(scene_file, monkeypatch, capsys):
    import os
    import signal

    before = signal.getsignal(signal.SIGTERM)
    seen = {}

    def terminated_run(scene, out_dir=None, arch=None, quiet=False, **kwargs):
        seen["handler"] = signal.getsignal(signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGTERM)  # as a job manager or `timeout` would
        raise AssertionError("SIGTERM did not stop the run")

    from opera_taichi import runner

    monkeypatch.setattr(runner, "run_scene", terminated_run)
    assert cli.main(["run", str(scene_file), "--quiet"]) == 143
    assert capsys.readouterr().err == "terminated (SIGTERM)\n"
    assert seen["handler"] is not before            # the run was covered by the CLI's handler
    assert signal.getsignal(signal.SIGTERM) is before  # and the caller's handler is back


def test_a_bug_exits_1_with_a_traceback(scene_file, fake_simulation, capsys):
    fake_simulation["raise"] = ZeroDivisionError("oops")
    assert cli.main(["run", str(scene_file)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and "ZeroDivisionError: oops" in err


def test_version_help_and_usage_errors(capsys):
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"opera-taichi {__version__}"
    assert cli.main(["run", "--help"]) == 0
    assert "--set" in capsys.readouterr().out
    # usage errors are one line each, as all bad input (the usage is in --help)
    for argv, words in [([], "command is required"), (["run", "x.yaml", "--arch", "tpu"], "invalid choice: 'tpu'"),
                        (["frobnicate"], "invalid choice: 'frobnicate'"),
                        (["run", "x.yaml", "--bogus"], "unrecognized arguments: --bogus")]:
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and words in err[0] and "--help" in err[0], err


@pytest.mark.parametrize("passed, code", [(True, 0), (False, 1), (None, 0)])
def test_validate_physics_exits_1_when_its_gate_fails(monkeypatch, capsys, passed, code, tmp_path):
    """A FAIL is an exit status a script can see; a run shown without a gate is not a failure. Below the gate's
    calibrated resolution the command says so."""
    from opera_taichi.validation import cases

    def fake_run_case(case, params, resolution, out_dir, arch, quiet):
        return dict(case=case, metric="draft", measured=2.0, reference=1.0, relative_error=1.0, passed=passed,
                    run_dir=str(tmp_path / "run"))

    monkeypatch.setattr(cases, "run_case", fake_run_case)
    assert cli.main(["validate-physics", "blade_cut", "--resolution", "coarse"]) == code
    captured = capsys.readouterr()
    assert ("FAIL" in captured.out) == (passed is False)
    assert "coarser than the 20 the blade_cut gate is calibrated at" in captured.err


def test_runs_in_a_fresh_checkout_lists_none_and_a_named_folder_must_exist(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)   # no runs/ yet
    assert cli.main(["runs"]) == 0
    assert capsys.readouterr().err == "no runs under runs\n"
    assert cli.main(["runs", "nope"]) == 2
    assert capsys.readouterr().err == "error: runs: nope is not a folder\n"
