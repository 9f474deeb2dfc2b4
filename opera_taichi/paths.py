"""Where shipped data lives: a source checkout or an installed copy."""
from pathlib import Path

_PKG = Path(__file__).resolve().parent
_CHECKOUT = _PKG.parent


def _data_dir(name: str) -> Path:
    checkout = _CHECKOUT / name
    if checkout.is_dir():
        return checkout
    import importlib.resources

    return Path(str(importlib.resources.files(f"opera_taichi.{name}")))


def machines_dir() -> Path:
    return _data_dir("machines")


def scenes_dir() -> Path:
    return _data_dir("scenes")


def cache_dir() -> Path:
    """Disk cache for settled beds, SDFs and converted meshes (OPERA_TAICHI_CACHE overrides)."""
    import os

    root = os.environ.get("OPERA_TAICHI_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "opera-taichi")
    path = Path(root)
    path.mkdir(parents=True, exist_ok=True)
    return path
