"""Run-folder writers. CSVs are streamed and flushed as the run goes, so a run that diverges or is
interrupted keeps everything it recorded up to then."""
from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import numpy as np


class CsvStream:
    """A CSV file written row by row at a fixed sample rate (Hz) of simulated time."""

    FLUSH_EVERY = 200  # rows; keeps the file useful while a long run is still going

    def __init__(self, path: Path, header: list[str], rate: float):
        self.path = path
        self._fh = open(path, "w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._fh)
        self._writer.writerow(header)
        self._period = 1.0 / rate
        self._next_t = 0.0
        self._rows = 0

    def due(self, t: float) -> bool:
        # Half a rigid step of tolerance so 100 Hz on a 1 ms step samples every 10th step, not drifting.
        return t + 1e-9 >= self._next_t

    def write(self, t: float, values) -> None:
        self._writer.writerow([_fmt(t)] + [_fmt(v) for v in values])
        self._next_t = (math.floor(t / self._period + 1e-6) + 1) * self._period
        self._rows += 1
        if self._rows % self.FLUSH_EVERY == 0:
            self._fh.flush()

    def write_rows(self, t: float, rows) -> None:
        """Several rows for the same instant (e.g. one per tool)."""
        for row in rows:
            self._writer.writerow([_fmt(t)] + [_fmt(v) if not isinstance(v, str) else v for v in row])
        self._next_t = (math.floor(t / self._period + 1e-6) + 1) * self._period
        self._rows += 1
        if self._rows % self.FLUSH_EVERY == 0:
            self._fh.flush()

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()


def _fmt(v) -> str:
    return f"{float(v):.9g}"


def write_json(path: Path, data: dict) -> None:
    """Write atomically: a reader never sees half a manifest."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2, default=_json_default)
        fh.write("\n")
    os.replace(tmp, path)


def _json_default(obj):
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_terrain(path: Path, x: np.ndarray, y: np.ndarray, z: np.ndarray, t: float) -> None:
    """Heightmap z[ix, iy] (m) of the soil surface on the x, y axes (m)."""
    np.savez_compressed(path, x=x, y=y, z=z, t=np.float64(t))


def read_csv_columns(path: Path) -> dict[str, np.ndarray | list[str]]:
    """Columns of a run-folder CSV by name (numbers as float arrays, text as lists)."""
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    header, body = rows[0], rows[1:]
    out = {}
    for i, name in enumerate(header):
        col = [r[i] for r in body]
        try:
            out[name] = np.asarray(col, dtype=float)
        except ValueError:
            out[name] = col
    return out
