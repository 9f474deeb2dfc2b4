"""The run folders under a folder, one row each: what `runs` lists.

A run folder is a folder with a manifest.json; `list_runs` looks at the folder itself and two levels below it
(runs/<name>/ and runs/<group>/<name>/), and never inside a run folder. Nothing here imports Taichi or PyBullet.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from .errors import UserError
from .recorders import read_csv_columns

FIELDS = ("name", "folder", "scene", "status", "sim_time_s", "real_time_factor", "bucket", "bucket_kg",
          "peak_force_N", "started")


def _run_folders(folder: Path, depth: int = 2) -> list[Path]:
    if (folder / "manifest.json").is_file():
        return [folder]
    if depth == 0:
        return []
    found = []
    try:
        children = sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))
    except OSError:
        return []
    for child in children:
        found += _run_folders(child, depth - 1)
    return found


def _float(value):
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    return value if np.isfinite(value) else None


def _from_files(run_dir: Path) -> tuple[str | None, float | None, float | None]:
    """(first tool, its soil at the end kg, its peak |F| N) from soil_mass.csv and tool_wrench.csv."""
    tool = kg = peak = None
    try:
        cols = read_csv_columns(run_dir / "soil_mass.csv")
        tools = [k for k in cols if k.startswith("in_") and k.endswith("_kg")]
        if tools and len(cols[tools[0]]):
            tool, kg = tools[0][3:-3], float(cols[tools[0]][-1])
    except (OSError, IndexError, ValueError):
        pass
    try:
        cols = read_csv_columns(run_dir / "tool_wrench.csv")
        names = np.asarray(cols.get("tool", []))
        if len(names):
            tool = tool or str(names[0])
            sel = names == tool
            if np.any(sel):
                f = np.sqrt(cols["fx"][sel] ** 2 + cols["fy"][sel] ** 2 + cols["fz"][sel] ** 2)
                peak = float(f.max())
    except (OSError, IndexError, ValueError, KeyError):
        pass
    return tool, kg, peak


def run_row(run_dir) -> dict:
    """One run folder's row (see FIELDS). The bucket is the first tool; its soil at the end and its peak force come
    from summary.json when the run has one, else from soil_mass.csv and tool_wrench.csv."""
    from .runner import run_folder_status

    run_dir = Path(run_dir)
    row = dict.fromkeys(FIELDS)
    row.update(name=run_dir.name, folder=str(run_dir))
    try:
        status, manifest = run_folder_status(run_dir)
    except UserError:
        status, manifest = "unreadable", {}
    scene = manifest.get("scene") if isinstance(manifest.get("scene"), dict) else {}
    row.update(scene=scene.get("name") or manifest.get("name"), status=status,
               sim_time_s=_float(manifest.get("sim_time")), real_time_factor=_float(manifest.get("real_time_factor")),
               started=manifest.get("started"))
    summary = None
    try:
        summary = json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError):
        pass
    tools = summary.get("tools") if isinstance(summary, dict) else None
    if isinstance(tools, dict) and tools:  # (a summary of something else, or damaged: read from the CSVs)
        name, entry = next(iter(tools.items()))
        if isinstance(entry, dict):
            row.update(bucket=name, bucket_kg=_float(entry.get("soil_held_kg")),
                       peak_force_N=_float(entry.get("peak_force_N")))
    if row["bucket_kg"] is None or row["peak_force_N"] is None:
        tool, kg, peak = _from_files(run_dir)
        row["bucket"] = row["bucket"] or tool
        if row["bucket_kg"] is None:
            row["bucket_kg"] = kg
        if row["peak_force_N"] is None:
            row["peak_force_N"] = peak
    return row


def list_runs(folder) -> list[dict]:
    """A row (dict with FIELDS) for every run folder in `folder` (itself, or up to two levels below), oldest start
    first. status is the manifest's, or 'died' for a run that says running whose process is gone, or 'unreadable'."""
    folder = Path(folder)
    rows = [run_row(p) for p in _run_folders(folder)]
    rows.sort(key=lambda r: (str(r["started"] or ""), r["folder"]))
    return rows


COLUMNS = (("name", "NAME", "{}"), ("scene", "SCENE", "{}"), ("status", "STATUS", "{}"),
           ("sim_time_s", "SIM s", "{:.2f}"), ("real_time_factor", "RTF", "{:.3g}"),
           ("bucket_kg", "BUCKET kg", "{:.1f}"), ("peak_force_N", "PEAK kN", "{:.1f}"), ("started", "STARTED", "{}"),
           ("folder", "FOLDER", "{}"))
NUMERIC = {"sim_time_s", "real_time_factor", "bucket_kg", "peak_force_N"}


def format_table(rows: list[dict]) -> str:
    """An aligned text table of list_runs rows (numbers right-aligned; '-' where a value is missing)."""
    if not rows:
        return "no run folders found"
    cells = []
    for r in rows:
        line = []
        for key, _, fmt in COLUMNS:
            v = r.get(key)
            if key == "peak_force_N" and v is not None:
                v = v / 1e3
            line.append("-" if v is None else fmt.format(v))
        cells.append(line)
    heads = [h for _, h, _ in COLUMNS]
    widths = [max(len(h), *(len(c[i]) for c in cells)) for i, h in enumerate(heads)]
    just = [(str.rjust if key in NUMERIC else str.ljust) for key, _, _ in COLUMNS]
    out = ["  ".join(j(h, w) for j, h, w in zip(just, heads, widths)).rstrip()]
    for c in cells:
        out.append("  ".join(j(v, w) for j, v, w in zip(just, c, widths)).rstrip())
    return "\n".join(out)


def write_csv(rows: list[dict], stream) -> None:
    """list_runs rows as CSV (header FIELDS, SI units as the names say) to a text stream."""
    writer = csv.DictWriter(stream, fieldnames=list(FIELDS), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in FIELDS})


__all__ = ["list_runs", "run_row", "format_table", "write_csv", "FIELDS"]
