"""An installed (non-editable) copy ships what the scenes and machines need: pyproject's package-data covers every
file under scenes/ and machines/."""
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("package", ["opera_taichi.scenes", "opera_taichi.machines"])
def test_package_data_covers_every_data_file(package):
    tool = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    folder = REPO / tool["package-dir"][package]
    shipped = {path for pattern in tool["package-data"][package] for path in folder.glob(pattern) if path.is_file()}
    # scripts (machines/zx120/build_zx120.py writes the URDF) and caches are not data
    data = {path for path in folder.rglob("*") if path.is_file() and path.suffix not in (".py", ".pyc")}
    missing = sorted(str(path.relative_to(folder)) for path in data - shipped)
    assert missing == [], f"not in [tool.setuptools.package-data] {package}: {missing}"
