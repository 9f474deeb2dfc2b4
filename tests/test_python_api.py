"""The README's `## Python API` examples run as printed, from the repository root, in a fresh interpreter."""
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def readme_python_blocks() -> list[str]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    start = text.index("\n## Python API\n")
    end = text.find("\n## ", start + 1)
    section = text[start:end if end != -1 else None]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def run_example(code: str, tmp_path: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1", MPLCONFIGDIR=str(tmp_path / "mpl"))
    script = tmp_path / "example.py"  # outside the repo; run with cwd = repo root as the README says
    script.write_text(code, encoding="utf-8")
    return subprocess.run([sys.executable, str(script)], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=600)


def test_readme_has_the_examples():
    blocks = readme_python_blocks()
    assert len(blocks) >= 2
    assert "ot.Simulation.from_scene" in blocks[0] and "sim.step(" in blocks[0]
    assert 'gymnasium.make("opera_taichi/ZX120Dig-v0"' in blocks[1]


def test_readme_control_loop_reaches_its_set_point(tmp_path):
    proc = run_example(readme_python_blocks()[0], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    found = re.search(r"tip height (-?[\d.]+) m, set-point (-?[\d.]+) m", proc.stdout)
    assert found, proc.stdout
    z, target = float(found.group(1)), float(found.group(2))
    start = re.search(r"t 0\.25 s\s+tip z (-?[\d.]+) m", proc.stdout)
    assert start and abs(float(start.group(1)) - target) > 0.1  # it started away from the set-point...
    assert abs(z - target) < 0.01, proc.stdout                   # ...and got there


def test_readme_gymnasium_example_runs(tmp_path):
    pytest.importorskip("gymnasium")
    code = readme_python_blocks()[1] + "\nprint('obs keys', sorted(obs), 'reward', float(reward))\n"
    proc = run_example(code, tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "obs keys ['bucket_mass', 'bucket_wrench', 'heightmap', 'q', 'qd', 'tip']" in proc.stdout, proc.stdout
