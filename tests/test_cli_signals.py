"""A Ctrl-C or SIGTERM at any moment of a run's start ends it as an interrupt (exit 130 / 143), never lost."""
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# A signal that arrives while Taichi's decorators read their source, where a bare `except` in Taichi swallows the
# exception the handler raises (inspect.getframeinfo is what they call there).
_SIGNAL_IN_TAICHIS_IMPORT = """
import inspect, os, signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)   # (a background job inherits SIGINT ignored)
signal.signal(signal.SIGTERM, signal.SIG_DFL)
from opera_taichi.cli import main
which = getattr(signal, sys.argv[2])
original = inspect.getframeinfo
def once(*args, **kwargs):
    inspect.getframeinfo = original
    os.kill(os.getpid(), which)
    return original(*args, **kwargs)
inspect.getframeinfo = once
sys.exit(main(["run", "scenes/blade_cut.yaml", "--quiet", "--out", sys.argv[1], "--set", "soil.overrides.radius=0.12",
               "--set", "sim.duration=0.05", "--set", "output.plots=false"]))
"""


@pytest.mark.parametrize("which, code, said", [("SIGINT", 130, "interrupted"), ("SIGTERM", 143, "terminated")])
def test_a_signal_while_taichi_loads_interrupts_the_run(tmp_path, which, code, said):
    """It was swallowed: the run went on to its end and exited 0 (with --ros1 and a long duration, the machine ran
    for an hour). Taichi now loads with the signals held, and one that came meanwhile is taken when it is done."""
    done = subprocess.run([sys.executable, "-c", _SIGNAL_IN_TAICHIS_IMPORT, str(tmp_path / "run"), which], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == code, done.stderr[-2000:]
    assert said in done.stderr
    assert not (tmp_path / "run" / "manifest.json").exists()   # it stopped before the run began
