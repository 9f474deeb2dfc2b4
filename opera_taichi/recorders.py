"""Run-folder file helpers: atomic JSON, terrain NPZ, reading CSV columns back. The streamed CSV writers are
observers (observers.py)."""
from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np


def write_json(path: Path, data: dict) -> None:
    """Write atomically: a reader never sees half a manifest."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2, default=json_default)
        fh.write("\n")
    os.replace(tmp, path)


def json_default(obj):
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_terrain(path: Path, x: np.ndarray, y: np.ndarray, z: np.ndarray, t: float, z_all=None) -> None:
    """Heightmap z[ix, iy] (m) of the soil resting on the ground on the x, y axes (m); z_all: of every grain,
    the tools' loads included."""
    np.savez_compressed(path, x=x, y=y, z=z, z_all=z if z_all is None else z_all, t=np.float64(t))


def read_csv_columns(path: Path) -> dict[str, np.ndarray | list[str]]:
    """Columns of a run-folder CSV by name (numbers as float arrays, text as lists); {} for an empty file. A row
    with fewer cells than the header (the last row of a run killed while it wrote it) is left out."""
    with open(path, newline="", encoding="utf-8", errors="replace") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        return {}
    header = rows[0]
    body = [r for r in rows[1:] if len(r) == len(header)]
    out = {}
    for i, name in enumerate(header):
        col = [r[i] for r in body]
        try:
            out[name] = np.asarray(col, dtype=float)
        except ValueError:
            out[name] = col
    return out
