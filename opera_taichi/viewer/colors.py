"""Particle colours by a chosen quantity, with fixed ranges per run (colours mean the same thing all run long) and the
colour bar that explains them."""
from __future__ import annotations

import numpy as np

from .frames import Frame, SceneInfo

QUANTITIES = ("height", "speed", "displacement", "in-bucket")
SOIL_RGB = (150, 110, 70)          # in-bucket: soil left on the ground
CARRIED_RGB = (40, 140, 255)       # in-bucket: soil inside a machine's tool
UNKNOWN_RGB = (160, 160, 160)      # displacement after grains left the domain (no longer matched to the start)
MAP = "viridis"                    # no orange in it: the machine stays the only orange thing in the view


def _lut(name: str = MAP) -> np.ndarray:
    from matplotlib import colormaps

    return (colormaps[name](np.linspace(0.0, 1.0, 256))[:, :3] * 255).round().astype(np.uint8)


_LUTS: dict[str, np.ndarray] = {}


def lut() -> np.ndarray:
    if MAP not in _LUTS:
        _LUTS[MAP] = _lut()
    return _LUTS[MAP]


def value_range(quantity: str, info: SceneInfo) -> tuple[float, float, str]:
    """(lo, hi, unit) of a quantity's colour bar; fixed for the run."""
    if quantity == "height":
        lo = min([b[0][2] for b in info.beds], default=float(info.domain_min[2]))
        top = float(np.max(info.initial_positions[:, 2] + info.radii)) if info.n_particles else 0.0
        return float(lo), max(top, float(lo) + 0.1) + 0.5, "m"
    if quantity == "speed":
        return 0.0, 1.0, "m/s"
    if quantity == "displacement":
        return 0.0, 1.0, "m"
    return 0.0, 1.0, ""


def values(quantity: str, info: SceneInfo, frame: Frame, carried: np.ndarray | None) -> np.ndarray | None:
    if quantity == "height":
        return frame.positions[:, 2]
    if quantity == "speed":
        return frame.speeds
    if quantity == "displacement":
        if len(frame.positions) != info.n_particles:
            return None
        return np.linalg.norm(frame.positions - info.initial_positions, axis=1)
    return None


def colorize(quantity: str, info: SceneInfo, frame: Frame, carried: np.ndarray | None = None) -> np.ndarray:
    """(N, 3) uint8 colours of the particles."""
    n = len(frame.positions)
    if quantity == "in-bucket":
        out = np.empty((n, 3), np.uint8)
        out[:] = SOIL_RGB
        if carried is not None and len(carried) == n:
            out[carried] = CARRIED_RGB
        return out
    v = values(quantity, info, frame, carried)
    if v is None:
        out = np.empty((n, 3), np.uint8)
        out[:] = UNKNOWN_RGB
        return out
    lo, hi, _ = value_range(quantity, info)
    k = np.clip(((np.asarray(v, float) - lo) / (hi - lo) * 255).astype(int), 0, 255)
    return lut()[k]


def colorbar(quantity: str, info: SceneInfo, width: int = 256, height: int = 18) -> tuple[np.ndarray, str]:
    """An RGB image of the colour bar and its caption (range and unit)."""
    if quantity == "in-bucket":
        img = np.empty((height, width, 3), np.uint8)
        img[:, : width // 2] = SOIL_RGB
        img[:, width // 2:] = CARRIED_RGB
        return img, "brown: on the ground, blue: inside the bucket"
    lo, hi, unit = value_range(quantity, info)
    row = lut()[np.linspace(0, 255, width).astype(int)]
    caption = f"{quantity}: {lo:.2f} {unit} (left) to {hi:.2f} {unit} (right)"
    return np.repeat(row[None], height, axis=0), caption
