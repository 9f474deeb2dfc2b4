"""The progress bar: silent off a terminal or when quiet, and its real-time factor and ETA are right."""
import io

import pytest

from opera_taichi.progress import Progress


class FakeTerminal(io.StringIO):
    def isatty(self):
        return True


def _drive(bar: Progress, duration: float):
    with bar:
        bar.phase("compiling the soil kernels")
        bar.begin_run(0.0)
        for i in range(1, 11):
            bar.update(sim_time=duration * i / 10, wall_time=float(i))  # 1 wall second per tenth


def test_no_output_when_not_a_terminal():
    stream = io.StringIO()
    _drive(Progress(20.0, stream=stream), 20.0)
    assert stream.getvalue() == ""


def test_no_output_when_quiet_even_on_a_terminal():
    stream = FakeTerminal()
    _drive(Progress(20.0, quiet=True, stream=stream), 20.0)
    assert stream.getvalue() == ""


def test_terminal_bar_shows_simulated_time_and_real_time_factor():
    stream = FakeTerminal()
    _drive(Progress(20.0, stream=stream), 20.0)
    text = stream.getvalue()
    assert "100%" in text and "20.00/20.00 s simulated" in text
    assert "RTF 2x" in text  # 20 s simulated in 10 s wall


@pytest.mark.parametrize("sim, wall, expected", [
    (10.0, 5.0, "RTF 2x, ETA 00:05"),     # 10 s left at 2x real time
    (5.0, 20.0, "RTF 0.25x, ETA 01:00"),  # 15 s left at a quarter of real time
    (20.0, 8.0, "RTF 2.5x, ETA 00:00"),
    (0.0, 0.0, "RTF ?, ETA ?"),
])
def test_real_time_factor_and_eta(sim, wall, expected):
    assert Progress(20.0, quiet=True).describe(sim, wall) == expected


def test_setup_phases_show_and_a_run_ends_at_100_percent():
    stream = FakeTerminal()
    with Progress(1.0, stream=stream) as bar:
        bar.phase("preparing")
        for k in range(1, 5):
            bar.settling(0.5 * k, 2.0)
        bar.begin_run(0.0)
        bar.update(0.5, 1.0)
        bar.update(1.0, 1.01, final=True)  # sooner than a redraw would be due: the last one is always drawn
    text = stream.getvalue()
    assert "settling the soil bed" in text and "2.00/2.00 s simulated" in text
    assert "100%" in text and "1.00/1.00 s simulated" in text


def test_a_run_that_cannot_keep_the_pace_says_so_once_and_keeps_it_in_its_warnings(monkeypatch):
    """--pace realtime on a run at half real time (a wall clock made to run twice as fast as the simulated one): two
    slow 2-second windows in a row, then one warning through the simulation, so the manifest's run_warnings keep it;
    a run that keeps the pace says nothing."""
    from opera_taichi import pacing

    for wall_per_sim, said in ((2.0, 1), (1.0, 0)):
        clock = [0.0]
        monkeypatch.setattr(pacing.time, "perf_counter", lambda: clock[0])
        monkeypatch.setattr(pacing.time, "sleep", lambda seconds: clock.__setitem__(0, clock[0] + seconds))

        class Sim:
            t, step_count, warnings = 0.0, 0, []

            def _warn(self, text):
                self.warnings.append(text)

        sim = Sim()
        pacer = pacing.RealTimePacer(quiet=True)
        pacer.start(sim, None)
        for k in range(1, 1001):  # 10 s of simulated time in 10 ms steps
            sim.t, sim.step_count = 0.01 * k, k
            clock[0] += 0.01 * wall_per_sim
            pacer.sample(sim)
        assert len(sim.warnings) == said
        if said:
            assert "--pace realtime: the simulation cannot keep up" in sim.warnings[0]
            assert "real-time factor 0.50" in sim.warnings[0]


def test_a_quiet_run_writes_nothing_to_stdout(tmp_path):
    """`run --quiet` from a shell: stdout stays empty (Taichi's start line goes to stderr), so a script can pipe
    it; the run folder is made."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    out = subprocess.run([sys.executable, "cli.py", "run", "scenes/blade_cut.yaml", "--quiet", "--out",
                          str(tmp_path / "run"), "--set", "sim.duration=0.01", "--set", "soil.overrides.radius=0.08",
                          "--set", "output.plots=false"], cwd=root, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout == ""
    assert (tmp_path / "run" / "manifest.json").exists()
