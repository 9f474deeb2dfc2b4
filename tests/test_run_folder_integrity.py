"""A run folder cannot lie: a run never writes into another run's folder, its manifest's status is always true,
and `validate` refuses what would fail at run time."""
import json
from pathlib import Path

import pytest

from opera_taichi.cli import main

ROOT = Path(__file__).resolve().parent.parent
DIG = str(ROOT / "scenes" / "zx120_dig_cycle.yaml")
EXCAVATION = str(ROOT / "scenes" / "zx120_excavation.yaml")


def _snapshot(folder: Path) -> dict:
    return {p.relative_to(folder): (p.stat().st_mtime_ns, p.read_bytes()) for p in folder.rglob("*") if p.is_file()}


def test_out_into_an_existing_run_is_refused_and_nothing_in_it_changes(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", DIG, "--out", str(out), "--quiet", "--set", "sim.duration=0.2"]) == 0
    before = _snapshot(out)
    capsys.readouterr()
    assert main(["run", EXCAVATION, "--out", str(out), "--quiet", "--set", "sim.duration=0.1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds a run already (status done)" in err[0] and "--overwrite" in err[0]
    assert _snapshot(out) == before


def test_overwrite_empties_the_folder_first(tmp_path):
    out = tmp_path / "run"
    assert main(["run", DIG, "--out", str(out), "--quiet", "--set", "sim.duration=0.2"]) == 0
    (out / "notes.txt").write_text("a file of the old run")
    assert main(["run", DIG, "--out", str(out), "--quiet", "--overwrite", "--set", "sim.duration=0.1",
                 "--set", "output.plots=false"]) == 0
    assert not (out / "notes.txt").exists() and not (out / "joints.png").exists()   # nothing stale is kept
    assert json.loads((out / "manifest.json").read_text())["sim_time"] == pytest.approx(0.1)


def test_a_non_empty_folder_that_is_no_run_is_refused(tmp_path, capsys):
    (tmp_path / "thesis.tex").write_text("x")
    assert main(["run", DIG, "--out", str(tmp_path), "--quiet", "--overwrite"]) == 2
    assert "is not empty and holds no run" in capsys.readouterr().err
    assert (tmp_path / "thesis.tex").read_text() == "x"


def test_a_run_that_fails_at_run_time_says_so_in_its_manifest(tmp_path, monkeypatch):
    """A user error found only while the soil is built (here: the validate-time checks bypassed) ends as
    `bad input`, never `running`."""
    from opera_taichi import dem_soil

    monkeypatch.setattr(dem_soil.DemSoil, "check_model", classmethod(lambda cls, soil: {}))
    out = tmp_path / "run"
    assert main(["run", EXCAVATION, "--out", str(out), "--quiet", "--set", "soil.overrides.radius=0.5"]) == 2
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "bad input" and "two particles" in manifest["message"]


@pytest.mark.parametrize("radius, words", [
    ("0.5", "the largest radius that fits is 0.2272 m"),
    ("0.002", "GiB of memory is available; the smallest radius that fits is about"),
])
def test_validate_refuses_what_would_fail_at_run_time(radius, words, capsys):
    assert main(["validate", EXCAVATION, "--set", f"soil.overrides.radius={radius}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: soil.overrides.radius: ") and words in err[0], err
