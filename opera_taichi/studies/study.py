"""`study STUDY.yaml`: a base scene run at many parameter points on a Dask cluster, one table of metrics out.

A study file (paths relative to it; every key checked, errors one line naming the key):

    name: blade_depth                  # default: the file's stem
    scene: ../scenes/blade_cut.yaml    # the base scene
    set: {sim.duration: 1.5}           # --set overrides for every point
    parameters:                        # --set paths to vary
      tools.0.start.2: [0.0, 0.1]                 # a list of values
      soil.overrides.friction_angle_deg: {range: [28, 36], num: 3}   # evenly spaced, ends included
      soil.overrides.cohesion: {low: 0, high: 4000}                  # bounds, for random / lhs
    sampling: grid                     # grid (every combination) | zip (lists side by side) | random | lhs
    samples: 8                         # random / lhs
    seed: 0
    metrics: [manifest.real_time_factor, wrench.blade.fx.mean, compare.terrain_rmse_m]
    reference: {terrain: scan.las, terrain_before: null, transform: null, fit_transform: null, joints: null,
                against: null}         # what compare.* metrics compare against
    out: studies/blade_depth           # the study folder (relative to the current directory); --out overrides

A key the scene types as an integer (sim.seed) is sampled as integers, low..high inclusive (each integer an equal
share of the draws, or of lhs's strata; with log: true, shares that shrink as log(1 + 1/k)); its values, low, high
and range steps must be whole numbers. Draws that repeat a point run it once (the study says how many did).

The study folder holds runs/<point>/ (a run folder each, with point.json: the point's row), study.csv,
study.parquet and study.png (each metric against each parameter). When the study runs again, a point whose
simulation finished (point.json with the same overrides of the same scene content, every file it names included;
manifest.json status done) is not simulated again, but its metrics and comparison are measured again from its run
folder for the study file as it is now (metrics or reference changed); points whose simulation failed are run again. A failed run is a row with its status (bad input, diverged,
error) and its one-line error; it never stops the study. A metric that cannot be measured (a comparison that fails)
makes its row failed too, but keeps the simulation.

Refused before any run (one line naming the key, exit 2): every point's values (and, for random / lhs, each
parameter's low and high) that its scene would refuse, a bad reference (transform, fit_transform, a key that needs
terrain), a CSV metric naming a file, tool or column its runs do not write, a compare.<key> metric naming a key
comparison.json cannot hold with the reference (compare.comparison_keys), and a time window t: [t0, t1] without
t0 < t1.

Metrics (columns of the table):
- `manifest.<key>[.<key>...]`, `summary.<key>...`, `comparison.<key>`: values from manifest.json, summary.json,
  or `compare.<key>` from comparing the run with `reference` (comparison.json in the run folder);
- `wrench.<tool>.<column>.<stat>`, `joints.<column>.<stat>`, `mass.<column>.<stat>`: a statistic of a CSV column
  of tool_wrench.csv (rows of that tool), joints.csv, soil_mass.csv; stat: mean, median, max, min, abs_max, rms,
  std, final;
- a mapping {name, file, column, where: {column: value}, stat, t: [t0, t1]} for any CSV of the run folder, over a
  time window.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import UserError

STATS = ("mean", "median", "max", "min", "abs_max", "rms", "std", "final")
CSV_SHORT = {"wrench": "tool_wrench.csv", "joints": "joints.csv", "mass": "soil_mass.csv"}
CSV_FILES = frozenset(CSV_SHORT.values())
POINT_FILE = "point.json"
REFERENCE_KEYS = ("terrain", "terrain_before", "transform", "fit_transform", "joints", "against")
STUDY_KEYS = ("name", "scene", "set", "parameters", "sampling", "samples", "seed", "metrics", "reference", "out",
              "calibrate")


@dataclass
class Parameter:
    path: str
    values: list | None = None    # a list (or an expanded range)
    low: float | None = None
    high: float | None = None
    log: bool = False
    integer: bool = False         # the scene types the key as an integer (sim.seed): sampled as integers


@dataclass
class Study:
    source: Path
    name: str
    scene: Path
    fixed: dict
    parameters: list[Parameter]
    sampling: str
    samples: int
    seed: int
    metrics: list
    reference: dict
    out: Path
    calibrate: dict | None = None
    points: list[dict] = field(default_factory=list)
    repeats: int = 0    # random / lhs draws that repeated a point (integer keys only): each point runs once

    def metric_names(self) -> list[str]:
        return [m if isinstance(m, str) else m["name"] for m in self.metrics]


# ----------------------------------------------------------------------------------------------- the file
def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _path(base: Path, value, key: str, label: str, must_exist: bool = True) -> Path:
    if not isinstance(value, str) or not value.strip():
        raise UserError(f"{label}: {key}: expected a file path, got {value!r}")
    p = Path(value).expanduser()
    p = p if p.is_absolute() else base / p
    if must_exist and not p.exists():
        raise UserError(f"{label}: {key}: no file at {p}")
    return p.resolve()


def integer_key(path: str) -> bool:
    """Whether the scene schema types this --set path as an integer (sim.seed), read from its pydantic models."""
    from ..scene import Scene, _child, _strip, _union_members

    annotation = Scene
    for part in path.split("."):
        members = _union_members(annotation)
        if members:  # motion: whichever member has the key
            annotation = next((m for m in members.values() if part in m.model_fields), None)
            if annotation is None:
                return False
        annotation = _child(annotation, int(part) if part.isdigit() else part)
        if annotation is None:
            return False  # not a key of the scene: loading the scene says so, naming it
    return _strip(annotation) is int


def _whole(key: str, what: str, values: list, label: str) -> list[int]:
    """An integer key's bounds or range values as ints (2.0 is 2); anything else is refused naming the key."""
    bad = [v for v in values if not float(v).is_integer()]
    if bad:
        raise UserError(f"{label}: {key}: the scene takes integers here; expected whole-number {what}, "
                        f"got {bad[0]!r}")
    return [int(v) for v in values]


def _parameter(path: str, spec, label: str, bounds_only: bool = False) -> Parameter:
    key = f"parameters.{path}"
    integer = integer_key(path)
    if isinstance(spec, list):
        if not spec:
            raise UserError(f"{label}: {key}: an empty list")
        if integer:  # 2.0 is 2 for an integer key, as in its bounds; what is no number is the scene check's
            spec = [_whole(key, "values", [v], label)[0] if _is_num(v) else v for v in spec]
        return Parameter(path, values=list(spec))
    if not isinstance(spec, dict):
        raise UserError(f"{label}: {key}: expected a list of values, {{range: [a, b], num: n}} or {{low: a, high: b}}, "
                        f"got {spec!r}")
    allowed = {"values", "range", "num", "low", "high", "log"}
    bad = sorted(set(spec) - allowed)
    if bad:
        raise UserError(f"{label}: {key}.{bad[0]}: unknown key; allowed: {', '.join(sorted(allowed))}")
    if "values" in spec:
        return _parameter(path, spec["values"], label)
    if "range" in spec:
        rng = spec["range"]
        if not (isinstance(rng, list) and len(rng) == 2 and all(_is_num(v) for v in rng) and rng[1] > rng[0]):
            raise UserError(f"{label}: {key}.range: expected [low, high] with low < high, got {rng!r}")
        num = spec.get("num", 3)
        if not (isinstance(num, int) and not isinstance(num, bool) and num >= 2):
            raise UserError(f"{label}: {key}.num: expected an integer >= 2, got {num!r}")
        if integer:
            values = _whole(f"{key}.range", f"steps (range {rng} with num {num})",
                            [float(v) for v in np.linspace(rng[0], rng[1], num)], label)
            return Parameter(path, values=values, low=values[0], high=values[-1], integer=True)
        return Parameter(path, values=[float(v) for v in np.linspace(rng[0], rng[1], num)], low=float(rng[0]),
                         high=float(rng[1]))
    lo, hi = spec.get("low"), spec.get("high")
    if not (_is_num(lo) and _is_num(hi) and hi > lo):
        raise UserError(f"{label}: {key}: expected low < high (numbers), got low {lo!r} high {hi!r}")
    log = spec.get("log", False)
    if not isinstance(log, bool) or (log and lo <= 0):
        raise UserError(f"{label}: {key}.log: expected true or false (true needs low > 0), got {log!r}")
    if integer:
        lo, hi = _whole(key, "low and high", [lo, hi], label)
        return Parameter(path, low=lo, high=hi, log=log, integer=True)
    return Parameter(path, low=float(lo), high=float(hi), log=log)


def _metric(spec, label: str, i: int):
    key = f"metrics.{i}"
    if isinstance(spec, str):
        head, _, rest = spec.partition(".")
        if head in ("manifest", "summary", "compare") and rest:
            return spec
        if head in CSV_SHORT:
            parts = rest.split(".")
            need = 3 if head == "wrench" else 2
            if len(parts) >= need and parts[-1] in STATS:
                return spec
            form = "wrench.<tool>.<column>.<stat>" if head == "wrench" else f"{head}.<column>.<stat>"
            raise UserError(f"{label}: {key}: expected {form} (stat: {', '.join(STATS)}), got {spec!r}")
        raise UserError(f"{label}: {key}: expected manifest.<key>, summary.<key>, compare.<key>, "
                        f"wrench.<tool>.<column>.<stat>, joints.<column>.<stat>, mass.<column>.<stat> or a mapping "
                        f"{{name, file, column, stat}}, got {spec!r}")
    if isinstance(spec, dict):
        allowed = {"name", "file", "column", "where", "stat", "t"}
        bad = sorted(set(spec) - allowed)
        if bad:
            raise UserError(f"{label}: {key}.{bad[0]}: unknown key; allowed: {', '.join(sorted(allowed))}")
        for k in ("name", "file", "column"):
            if not isinstance(spec.get(k), str):
                raise UserError(f"{label}: {key}.{k}: required, a string")
        if spec.get("stat", "mean") not in STATS:
            raise UserError(f"{label}: {key}.stat: expected one of {', '.join(STATS)}, got {spec.get('stat')!r}")
        where = spec.get("where")
        if where is not None and not isinstance(where, dict):
            raise UserError(f"{label}: {key}.where: expected a mapping {{column: value}}, got {where!r}")
        t = spec.get("t")
        if t is not None and not (isinstance(t, list) and len(t) == 2 and all(_is_num(v) for v in t) and t[0] < t[1]):
            raise UserError(f"{label}: {key}.t: expected [t0, t1] in s with t0 < t1, got {t!r}")
        return dict(spec)
    raise UserError(f"{label}: {key}: expected a string or a mapping, got {spec!r}")


def check_out_folder(out: Path, name: str, label: str, calibrate: bool = False) -> None:
    """A study's or a calibration's folder: new, or its own from an earlier session (to go on from); not a file, not
    a run folder or inside one, not another study's (their tables and runs would mix; a calibration's journal
    guards its own trials, calibrate.open_study)."""
    from ..runner import is_run_folder

    if out.exists() and not out.is_dir():
        raise UserError(f"{label}: out: {out} is a file, not a folder")
    holder = next((p for p in (out, *out.parents) if is_run_folder(p)), None)
    if holder is not None:
        raise UserError(f"{label}: out: {out} {'is' if holder == out else 'lies inside'} the run folder {holder}; "
                        f"give a folder of its own")
    try:
        recorded = json.loads((out / "study.json").read_text()).get("name") if not calibrate else None
    except (OSError, ValueError, AttributeError):
        recorded = None
    if recorded is not None and recorded != name:
        raise UserError(f"{label}: out: {out} holds study {recorded!r}, not {name!r}; give another folder (or "
                        f"remove it)")


def load_study(path, out=None) -> Study:
    """Reads and checks a study file, expands its points and checks each point's scene (UserError, one line)."""
    from ..scene import _parse_yaml, _read_scene_text

    label = str(path)
    path = Path(path)
    data = _parse_yaml(_read_scene_text(path, label), label)
    if not isinstance(data, dict):
        raise UserError(f"{label}: expected a mapping of study keys ({', '.join(STUDY_KEYS)})")
    bad = sorted(set(data) - set(STUDY_KEYS))
    if bad:
        raise UserError(f"{label}: {bad[0]}: unknown key; allowed: {', '.join(STUDY_KEYS)}")
    base = path.resolve().parent
    if "scene" not in data:
        raise UserError(f"{label}: scene: required, the base scene file")
    scene = _path(base, data["scene"], "scene", label)
    fixed = data.get("set") or {}
    if not isinstance(fixed, dict):
        raise UserError(f"{label}: set: expected a mapping of --set paths to values, got {fixed!r}")
    params_in = data.get("parameters") or {}
    calibrate = data.get("calibrate")
    if not isinstance(params_in, dict) or (not params_in and calibrate is None):
        raise UserError(f"{label}: parameters: expected a mapping of --set paths to values or ranges")
    params = [_parameter(str(k), v, label) for k, v in params_in.items()]
    sampling = data.get("sampling", "grid")
    if sampling not in ("grid", "zip", "random", "lhs"):
        raise UserError(f"{label}: sampling: expected grid, zip, random or lhs, got {sampling!r}")
    samples = data.get("samples", 8)
    if not (isinstance(samples, int) and not isinstance(samples, bool) and samples >= 1):
        raise UserError(f"{label}: samples: expected a positive integer, got {samples!r}")
    seed = data.get("seed", 0)
    if not (isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0):
        raise UserError(f"{label}: seed: expected an integer >= 0, got {seed!r}")
    metrics = data.get("metrics") or []
    if not isinstance(metrics, list):
        raise UserError(f"{label}: metrics: expected a list")
    metrics = [_metric(m, label, i) for i, m in enumerate(metrics)]
    reference = data.get("reference") or {}
    if not isinstance(reference, dict):
        raise UserError(f"{label}: reference: expected a mapping ({', '.join(REFERENCE_KEYS)})")
    bad = sorted(set(reference) - set(REFERENCE_KEYS))
    if bad:
        raise UserError(f"{label}: reference.{bad[0]}: unknown key; allowed: {', '.join(REFERENCE_KEYS)}")
    reference = {k: v for k, v in reference.items() if v is not None}
    for k in ("terrain", "terrain_before", "joints", "against"):
        if k in reference:
            reference[k] = str(_path(base, reference[k], f"reference.{k}", label))
    check_reference(reference, label)
    if any(isinstance(m, str) and m.startswith("compare.") for m in metrics) and not reference:
        raise UserError(f"{label}: metrics: compare.* metrics need a `reference` (terrain, joints or against)")
    for i, m in enumerate(metrics):
        if isinstance(m, str) and m.startswith("compare."):
            check_compare_metric(m, reference, f"{label}: metrics.{i}")
    name = data.get("name") or path.stem
    out_dir = Path(out) if out is not None else Path(data["out"]) if data.get("out") else Path("studies") / name
    study = Study(path.resolve(), str(name), scene, fixed, params, sampling, samples, seed, metrics, reference,
                  out_dir.resolve(), calibrate)
    if params_in:
        study.points = expand_points(study, label)
        ends, names = bound_points(study)
        n = len(study.points)
        names += [f"parameters: {', '.join(f'{k}={json.dumps(v)}' for k, v in p.items())} (point {i + 1} of {n})"
                  for i, p in enumerate(study.points)]
        check_points(study, ends + study.points, label, names)
    return study


FIT_MODES = ("auto", "plane", "rigid")   # compare's --fit-transform choices


def check_reference(reference: dict, label: str) -> None:
    """What compare would refuse only after every simulation ran, refused here naming the study key."""
    from .scan import Transform

    if "transform" in reference:
        try:
            t = Transform.parse(reference["transform"], key="reference.transform")
        except UserError as exc:
            raise UserError(f"{label}: {' '.join(str(exc).split())}") from None
        if not isinstance(reference["transform"], str):  # compare parses the string form only
            d = t.describe()
            reference["transform"] = ",".join(repr(float(d[k])) for k in ("x_m", "y_m", "z_m", "yaw_deg", "roll_deg",
                                                                          "pitch_deg"))
    fit = reference.get("fit_transform")
    if fit is not None and (not isinstance(fit, str) or fit not in FIT_MODES):
        raise UserError(f"{label}: reference.fit_transform: expected {', '.join(FIT_MODES[:-1])} or {FIT_MODES[-1]} "
                        f"(as compare --fit-transform), got {fit!r}")
    if ("transform" in reference or fit is not None or "terrain_before" in reference) and "terrain" not in reference:
        raise UserError(f"{label}: reference: transform, fit_transform and terrain_before place a scan of the terrain; "
                        f"give reference.terrain (the scan after the dig)")
    # the files themselves: an empty scan is refused now, not after every run (a joint log: check_points, which
    # knows the machine's joints, the only columns of it that are read)
    from .scan import read_scan

    for key in ("terrain", "terrain_before"):
        if key in reference:
            try:
                read_scan(reference[key], key=f"reference.{key}")
            except UserError as exc:
                raise UserError(f"{label}: {' '.join(str(exc).split())}") from None
    if "against" in reference:
        if any(k in reference for k in ("terrain", "terrain_before", "joints")):
            raise UserError(f"{label}: reference.against: compares with another run; give it without terrain, "
                            f"terrain_before and joints")
        if not (Path(reference["against"]) / "manifest.json").is_file():
            raise UserError(f"{label}: reference.against: {reference['against']} is not a run folder (no "
                            f"manifest.json)")


def check_compare_metric(name: str, reference: dict, where: str) -> None:
    """A compare.<key> metric names a key comparison.json can hold with this reference (a misspelt one was an empty
    column, and a calibration on it simulated every trial before failing each); its sub-keys (a joint's name) are
    checked when the first run is measured."""
    from .compare import comparison_keys

    keys = comparison_keys(reference)
    top = name.split(".")[1]
    if top not in keys:
        kinds = ", ".join(k for k in reference if k in ("terrain", "terrain_before", "joints", "against"))
        raise UserError(f"{where}: {name}: comparison.json has no {top!r} with reference {kinds}; its keys: "
                        f"{', '.join(keys)}")


def expand_points(study: Study, label: str) -> list[dict]:
    ps = study.parameters
    if study.sampling in ("grid", "zip"):
        missing = [p.path for p in ps if p.values is None]
        if missing:
            raise UserError(f"{label}: parameters.{missing[0]}: sampling {study.sampling} needs a list or a range "
                            f"with num (low/high bounds are for random or lhs)")
        if study.sampling == "zip":
            lengths = {len(p.values) for p in ps}
            if len(lengths) > 1:
                raise UserError(f"{label}: parameters: sampling zip needs lists of one length, got "
                                f"{', '.join(f'{p.path}: {len(p.values)}' for p in ps)}")
            combos = list(zip(*(p.values for p in ps)))
        else:
            combos = list(itertools.product(*(p.values for p in ps)))
        return [dict(zip((p.path for p in ps), c)) for c in combos]
    missing = [p.path for p in ps if p.low is None]
    if missing:
        raise UserError(f"{label}: parameters.{missing[0]}: sampling {study.sampling} needs low and high (or a range)")
    if study.sampling == "lhs":
        from scipy.stats import qmc

        unit = qmc.LatinHypercube(d=len(ps), seed=study.seed).random(study.samples)
    else:
        unit = np.random.default_rng(study.seed).random((study.samples, len(ps)))
    points = [{p.path: scale(p, u[k]) for k, p in enumerate(ps)} for u in unit]
    unique = list({json.dumps(pt, sort_keys=True): pt for pt in points}.values())
    study.repeats = len(points) - len(unique)
    return unique


def scale(p: Parameter, u: float) -> float | int:
    """The value at u in [0, 1) of the parameter's range; an integer key's over low..high inclusive, each integer an
    equal share of u (so lhs strata stay strata; log: the share of [k, k + 1) in log space)."""
    if p.integer:
        lo, hi = p.low, p.high + 1  # floor() of [low, high + 1) is low..high
        x = math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo))) if p.log else lo + u * (hi - lo)
        return int(min(p.high, max(p.low, math.floor(x))))  # u = 1 (a bound) is high
    if p.log:
        return float(math.exp(math.log(p.low) + u * (math.log(p.high) - math.log(p.low))))
    return float(p.low + u * (p.high - p.low))


def overrides(study: Study, point: dict) -> list[str]:
    """The --set strings of a point (the study's fixed ones first, the point's after)."""
    return [f"{k}={json.dumps(v)}" for k, v in {**study.fixed, **point}.items()]


MODEL_KEYS = ("machine", "machines", "tools", "motion")   # what a --set path can change of the machines and tools


def check_points(study: Study, points: list[dict], label: str, names: list[str] | None = None) -> None:
    """Every point's scene loads and builds (a parameter path that does not exist, a soil value out of range, an
    actuator of a joint the machine lacks, fail here, before any run), and its CSV metrics name columns its runs
    write. The whole model is built once per distinct set of machine, tool and motion values (about a second each);
    every other point has its soil built (a millisecond). names: how an error names each point (default: its
    values)."""
    from ..model import _build_soil, build_model
    from ..observers import csv_columns
    from ..scene import load_scene

    built: set[str] = set()
    for i, point in enumerate(points):
        sets = overrides(study, point)
        shape = json.dumps([o for o in sets if o.split(".", 1)[0].split("=", 1)[0] in MODEL_KEYS])
        model = None
        try:
            scene = load_scene(study.scene, sets)
            if shape not in built:
                built.add(shape)
                model = build_model(scene)
            elif scene.soil is not None:  # the same machines and tools: only the soil can differ (its values checked)
                _build_soil(scene)
        except UserError as exc:
            name = names[i] if names else "parameters: " + ", ".join(f"{k}={json.dumps(v)}" for k, v in point.items())
            raise UserError(f"{label}: {name}: {' '.join(str(exc).split())}") from None
        if model is not None:
            columns = csv_columns(model)
            check_metric_columns(study.metrics, columns, [b.name for b in model.bindings], label)
            if "joints" in study.reference:  # the log, read as compare reads it against these runs' joints
                from .compare import read_joint_log

                names = [c[:-2] for c in columns.get("joints.csv", ()) if c.endswith(".q")]
                try:
                    read_joint_log(study.reference["joints"], "reference.joints", names or None)
                except UserError as exc:
                    raise UserError(f"{label}: {' '.join(str(exc).split())}") from None


def bound_points(study: Study) -> tuple[list[dict], list[str]]:
    """random / lhs: each parameter at its low and at its high end, the others at their middle (sampled points
    fall between the bounds, so a bound a run would refuse is refused before any), with the study key of each."""
    if study.sampling not in ("random", "lhs"):
        return [], []
    points, names = [], []
    for p in study.parameters:
        for end in ("low", "high"):
            points.append({**{q.path: scale(q, 0.5) for q in study.parameters}, p.path: getattr(p, end)})
            names.append(f"parameters.{p.path}.{end}: {getattr(p, end):g}")
    return points, names


def check_metric_columns(metrics: list, columns: dict[str, list[str]], tools: list[str], label: str) -> None:
    """The CSV metrics name files, tools and columns a run writes (columns: csv_columns of its model)."""
    for i, spec in enumerate(metrics):
        key = f"metrics.{i}"
        if isinstance(spec, str):
            head, _, rest = spec.partition(".")
            if head not in CSV_SHORT:
                continue
            parts = rest.split(".")
            file, where = CSV_SHORT[head], {}
            if head == "wrench":
                where, column = {"tool": parts[0]}, ".".join(parts[1:-1])
            else:
                column = ".".join(parts[:-1])
        else:
            file, column, where = spec["file"], spec["column"], spec.get("where") or {}
            if file not in CSV_FILES:
                raise UserError(f"{label}: {key}.file: expected a CSV file the runs write ({', '.join(sorted(columns))}"
                                f"), got {file!r}")
        if file not in columns:
            raise UserError(f"{label}: {key}: {spec!r}: this scene's runs write no {file} (it has no "
                            f"{'machine' if file == 'joints.csv' else 'soil'})")
        for name in (column, *where):
            if name not in columns[file]:
                raise UserError(f"{label}: {key}: {file} has no column {name!r} (columns: {', '.join(columns[file])})")
        if file == CSV_SHORT["wrench"] and "tool" in where and str(where["tool"]) not in tools:
            raise UserError(f"{label}: {key}: {file} has no tool {where['tool']!r} (tools: {', '.join(tools)})")


def scene_fingerprint(scene_path, sets: list[str]) -> str:
    """What a run of the scene under these overrides depends on, by content: the resolved scene and every file it
    names (soil preset, motion CSV, terrain scan, URDF, machine config): an edited one is not the run kept from
    before it."""
    from ..scene import load_scene, scene_to_dict

    data = scene_to_dict(load_scene(scene_path, sets))
    digest = hashlib.sha256(json.dumps(data, sort_keys=True).encode())
    for path in sorted(set(_named_files(data))):
        digest.update(path.encode() + Path(path).read_bytes())
    return digest.hexdigest()[:16]


def _named_files(value):
    """The files a resolved scene names (its paths are absolute)."""
    if isinstance(value, dict):
        for v in value.values():
            yield from _named_files(v)
    elif isinstance(value, list):
        for v in value:
            yield from _named_files(v)
    elif isinstance(value, str) and value.startswith("/") and len(value) < 4096 and Path(value).is_file():
        yield value


def point_id(index: int, study: Study, point: dict) -> str:
    text = json.dumps({"scene": str(study.scene), "set": overrides(study, point)}, sort_keys=True)
    return f"p{index:03d}-{hashlib.sha256(text.encode()).hexdigest()[:8]}"


# ----------------------------------------------------------------------------------------------- metrics
def _dig(data, keys: list[str]):
    for k in keys:
        if isinstance(data, dict) and k in data:
            data = data[k]
        else:
            return None
    return data


def _dig_comparison(data: dict, keys: list[str], allowed: list[str]):
    """comparison.json's value at keys: None where the comparison leaves out a key it can hold (`allowed`: no depth
    to place, no warnings), a UserError naming what is there for a key it does not hold (a misspelt metric or joint
    was an empty column)."""
    for depth, k in enumerate(keys):
        if isinstance(data, dict) and k in data:
            data = data[k]
        elif depth == 0 and k in allowed:
            return None
        else:
            where = f"its {'.'.join(keys[:depth])}" if depth else "it"
            has = f"holds {', '.join(map(str, data))}" if isinstance(data, dict) else f"is {data!r}"
            raise UserError(f"comparison.json has no {'.'.join(keys)!r}: {where} {has}")
    return data


def _stat(values: np.ndarray, stat: str):
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None
    return float({"mean": np.mean, "median": np.median, "max": np.max, "min": np.min,
                  "abs_max": lambda a: np.max(np.abs(a)), "rms": lambda a: np.sqrt(np.mean(a ** 2)),
                  "std": np.std, "final": lambda a: a[-1]}[stat](v))


def csv_metric(run_dir: Path, file: str, column: str, stat: str, where: dict | None = None, t=None):
    from ..recorders import read_csv_columns

    path = run_dir / file
    if not path.is_file():
        return None
    cols = read_csv_columns(path)
    if column not in cols:
        raise UserError(f"{file}: no column {column!r} (columns: {', '.join(cols)})")
    keep = np.ones(len(cols[column]), bool)
    for k, v in (where or {}).items():
        if k not in cols:
            raise UserError(f"{file}: no column {k!r} to select rows by")
        keep &= np.array([str(c) == str(v) for c in cols[k]]) if isinstance(cols[k], list) else \
            np.asarray(cols[k], float) == float(v)
    if t is not None and "t" in cols:
        tt = np.asarray(cols["t"], float)
        keep &= (tt >= t[0]) & (tt <= t[1])
    return _stat(np.asarray(cols[column], float)[keep], stat)


def collect_metrics(run_dir: Path, metrics: list, reference: dict, errors: dict | None = None) -> dict:
    """The metrics of a finished run folder (None where a file or key is missing). A metric that cannot be measured
    (a comparison that fails, an unreadable file) raises, or with `errors` given is None and its exception goes
    into errors[name] (the other metrics are still measured)."""
    run_dir = Path(run_dir)
    out = {}
    cache: dict = {}

    def json_file(name):
        if name not in cache:
            try:
                cache[name] = json.loads((run_dir / name).read_text())
            except (OSError, ValueError):
                cache[name] = None
        return cache[name]

    def comparison():
        if "compare" not in cache:  # once for all compare.* metrics, a failure included
            from .compare import compare

            try:
                cache["compare"] = compare(run_dir, terrain=reference.get("terrain"),
                                           terrain_before=reference.get("terrain_before"),
                                           joints=reference.get("joints"), against=reference.get("against"),
                                           transform=reference.get("transform"),
                                           fit=reference.get("fit_transform"), figures=False)
            except Exception as exc:  # noqa: BLE001 - raised again below for each compare.* metric
                cache["compare"] = exc
        if isinstance(cache["compare"], Exception):
            raise cache["compare"]
        return cache["compare"]

    def one(m):
        if isinstance(m, dict):
            value = csv_metric(run_dir, m["file"], m["column"], m.get("stat", "mean"), m.get("where"), m.get("t"))
            if value is None and (run_dir / m["file"]).is_file():
                raise UserError(f"{m['file']}: no {m['column']} samples in the rows the metric selects (its `where` "
                                f"and its window t {m.get('t')})")
            return value
        head, _, rest = m.partition(".")
        if head in ("manifest", "summary"):
            name = f"{head}.json"
            value = _dig(json_file(name), rest.split("."))
            if value is None and json_file(name) is not None:  # (a misspelt key reads as nothing, not as a value)
                raise UserError(f"{name} has no {rest!r}")
            return value
        if head == "compare":
            from .compare import comparison_keys

            return _dig_comparison(comparison(), rest.split("."), comparison_keys(reference))
        parts = rest.split(".")
        if head == "wrench":
            return csv_metric(run_dir, CSV_SHORT[head], ".".join(parts[1:-1]), parts[-1], {"tool": parts[0]})
        return csv_metric(run_dir, CSV_SHORT[head], ".".join(parts[:-1]), parts[-1])

    for m in metrics:
        name = m if isinstance(m, str) else m["name"]
        try:
            out[name] = one(m)
        except Exception as exc:  # noqa: BLE001 - with `errors`, one metric's failure is its own
            if errors is None:
                raise
            errors[name], out[name] = exc, None
    return {k: (v if v is None or isinstance(v, (int, float, str, bool)) else json.dumps(v)) for k, v in out.items()}


# compare's messages name its command-line options; in a study the same things are `reference` keys
_COMPARE_FLAGS = {"--terrain-before": "reference.terrain_before", "--terrain": "reference.terrain",
                  "--transform": "reference.transform", "--fit-transform": "reference.fit_transform",
                  "--joints": "reference.joints", "--against": "reference.against"}


def measure(row: dict, run_dir: Path, metrics: list, reference: dict, objective=None) -> dict:
    """The metrics (and a calibration's objective) of a finished simulation, into its row: status done, or the
    status and one-line error of the first metric that could not be measured (the others still are). The
    simulation stays finished: the next run of the study measures it again, without simulating it again."""
    import re

    errors: dict = {}
    row.update(collect_metrics(run_dir, metrics, reference, errors))
    if objective and not errors:
        try:
            from .calibrate import objective_value

            row.update(objective_value(run_dir, objective))
        except Exception as exc:  # noqa: BLE001 - the row says why
            errors["objective"] = exc
    if not errors:
        row.update(status="done", error="")
        return row
    name, exc = next(iter(errors.items()))
    text = " ".join(str(exc).split())
    text = re.sub("|".join(map(re.escape, _COMPARE_FLAGS)), lambda m: _COMPARE_FLAGS[m.group(0)], text)
    if not isinstance(exc, UserError):
        text = f"{type(exc).__name__}: {text}"
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    row.update(status="bad input" if isinstance(exc, UserError) else "error",
               error=f"{name}{more}: {text} (the simulation finished; its folder is measured again when the study "
                     f"runs again)"[:500])
    return row


# ----------------------------------------------------------------------------------------------- one point
def run_point(task: dict) -> dict:
    """Runs one point in this process (a Dask worker), measures it and returns its row; never raises for a failed
    run."""
    os.environ.setdefault("TI_CPU_MAX_NUM_THREADS", str(task.get("threads", 1)))
    _own_kernel_cache()
    from ..errors import DivergenceError
    from ..recorders import write_json
    from ..runner import run_scene
    from ..scene import load_scene

    run_dir = Path(task["run_dir"])
    row = {"point": task["id"], **task["point"], "status": "error", "error": "", "wall_s": None,
           "run_dir": str(run_dir)}
    t0 = time.perf_counter()
    simulated = False
    try:
        scene = load_scene(task["scene"], task["overrides"])
        run_scene(scene, out_dir=run_dir, quiet=True, overwrite=True)
        simulated = True
    except UserError as exc:
        row.update(status="bad input", error=" ".join(str(exc).split()))
    except DivergenceError as exc:
        row.update(status="diverged", error=" ".join(str(exc).split()))
    except Exception as exc:  # noqa: BLE001 - any failure is the point's row, never the study's end
        row.update(status="error", error=f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:500])
    row["wall_s"] = round(time.perf_counter() - t0, 3)  # the simulation's (kept when the point is measured again)
    if simulated:
        measure(row, run_dir, task["metrics"], task["reference"], task.get("objective"))
    run_dir.mkdir(parents=True, exist_ok=True)
    write_json(run_dir / POINT_FILE, {"overrides": task["overrides"], "scene": task["scene_sha"], "row": row})
    return row


def _own_kernel_cache() -> None:
    """Each Dask worker its own Taichi offline cache (named by the worker, so it stays warm from one study to the
    next): workers compiling into one cache at once can read each other's half-written kernels (tests/conftest.py)."""
    try:
        from dask.distributed import get_worker

        name = str(get_worker().name)
    except (ImportError, ValueError):
        return  # not on a Dask worker
    if os.environ.get("OPERA_TAICHI_WORKER_CACHE") == name:
        return
    base = os.environ.get("TI_OFFLINE_CACHE_FILE_PATH") or str(Path.home() / ".cache" / "taichi" / "ticache")
    os.environ["TI_OFFLINE_CACHE_FILE_PATH"] = f"{base}-dask-{''.join(c if c.isalnum() else '_' for c in name)}"
    os.environ["OPERA_TAICHI_WORKER_CACHE"] = name


def _stored_scene(run_dir: Path):
    """The scene fingerprint a run folder's point.json recorded (None: none, or no readable point.json)."""
    try:
        data = json.loads((run_dir / POINT_FILE).read_text())
    except (OSError, ValueError):
        return None
    return data.get("scene") if isinstance(data, dict) else None


def finished_row(run_dir: Path, sets: list[str], scene_sha: str) -> dict | None:
    """The stored row of a run folder whose simulation of these overrides, of the scene as it is now
    (scene_fingerprint), finished (its manifest says done, whatever its metrics gave: they are measured again), else
    None."""
    from ..runner import run_folder_status

    try:
        data = json.loads((run_dir / POINT_FILE).read_text())
        status, _ = run_folder_status(run_dir)
    except (OSError, ValueError, UserError):
        return None
    if not isinstance(data, dict) or data.get("overrides") != sets or data.get("scene") != scene_sha \
            or status != "done":
        return None
    return data.get("row") if isinstance(data.get("row"), dict) else {}


# ----------------------------------------------------------------------------------------------- the cluster
class Cluster:
    """A Dask client on an existing scheduler, or on a LocalCluster of one single-threaded worker process per core
    (each its own Taichi runtime, one CPU thread)."""

    def __init__(self, scheduler: str | None, workers: int | None, quiet: bool = True):
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError:
            raise UserError("study: needs dask[distributed] (pip install 'opera-taichi[studies]')") from None
        import logging

        self.cluster = None
        if scheduler:
            if workers is not None:
                raise UserError("--workers: only for the local cluster; an existing cluster (--scheduler) has its own")
            try:
                self.client = Client(scheduler, timeout="20s")
            except (OSError, TimeoutError, ValueError) as exc:
                raise UserError(f"--scheduler: cannot reach {scheduler} ({type(exc).__name__}: {exc})") from None
        else:
            n = workers or os.cpu_count() or 1
            self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                                        silence_logs=logging.ERROR)
            self.client = Client(self.cluster)
        info = self.client.scheduler_info()
        self.workers = max(1, sum(w.get("nthreads", 1) for w in info.get("workers", {}).values()))

    def close(self):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def make_task(study: Study, index: int, point: dict, runs: Path, objective=None, sub: str = "runs") -> dict:
    pid = point_id(index, study, point)
    sets = overrides(study, point)
    return {"id": pid, "point": point, "scene": str(study.scene), "overrides": sets,
            "scene_sha": scene_fingerprint(study.scene, sets), "run_dir": str(runs / pid), "metrics": study.metrics,
            "reference": study.reference, "threads": 1, "objective": objective}


def run_study(path, scheduler: str | None = None, workers: int | None = None, out=None,
              quiet: bool = False) -> tuple[Path, int, int]:
    """Runs a study (resumable) and writes its table and plots; returns the path of study.csv, how many of its
    points failed and how many it has."""
    study = load_study(path, out)
    check_out_folder(study.out, study.name, str(path))
    if study.calibrate is not None and not study.parameters:
        raise UserError(f"{path}: parameters: none to study (a calibration: `calibrate {path}`)")
    runs = study.out / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    tasks = [make_task(study, i, p, runs) for i, p in enumerate(study.points)]
    rows: dict[str, dict] = {}
    todo, finished, changed = [], [], 0
    for task in tasks:
        folders = sorted(runs.glob("*-" + task["id"].rsplit("-", 1)[1]))  # by content: an index may move
        for folder in folders:
            stored = finished_row(folder, task["overrides"], task["scene_sha"])
            if stored is not None:
                finished.append((task, folder, stored))
                break
        else:
            todo.append(task)
            changed += any(finished_row(f, task["overrides"], _stored_scene(f)) is not None for f in folders)
    say = (lambda *a: None) if quiet else (lambda text: print(text, file=sys.stderr, flush=True))
    say(f"study {study.name}: {len(tasks)} points, {len(finished)} finished before, {len(todo)} to run -> {study.out}")
    if study.repeats:
        say(f"  {study.repeats} of the {study.samples} {study.sampling} samples repeated a point (integer keys take "
            f"few values): each point runs once")
    if changed:
        say(f"  {changed} of them finished before with another content of the scene or a file it names (or "
            f"recorded without it by an older version): simulated again")
    wall0 = time.perf_counter()
    if finished:  # their simulations are kept; their metrics and comparison are this study file's, measured again
        from ..recorders import write_json

        say(f"  measuring the {len(finished)} finished run(s) again (this file's metrics and reference)")
        for task, folder, stored in finished:
            row = {"point": task["id"], **task["point"], "status": "error", "error": "",
                   "wall_s": stored.get("wall_s"), "run_dir": str(folder)}
            rows[task["id"]] = measure(row, folder, study.metrics, study.reference)
            write_json(folder / POINT_FILE, {"overrides": task["overrides"], "scene": task["scene_sha"], "row": row})
            if row["status"] != "done":
                say(f"  {task['id']} {row['status']}: {row['error']}")
    if todo:
        cluster = Cluster(scheduler, workers)
        try:
            from dask.distributed import as_completed

            say(f"  on {cluster.workers} worker(s)")
            futures = {cluster.client.submit(run_point, t, key=f"{study.name}-{t['id']}-{time.time_ns()}", pure=False):
                       t for t in todo}
            for k, fut in enumerate(as_completed(futures), start=1):
                task = futures[fut]
                try:
                    row = fut.result()
                except Exception as exc:  # noqa: BLE001 - a worker lost (killed, out of memory): the row says so
                    row = {"point": task["id"], **task["point"], "status": "error", "run_dir": task["run_dir"],
                           "error": f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:500], "wall_s": None}
                rows[task["id"]] = row
                say(f"  [{k}/{len(todo)}] {task['id']} {row['status']} ({row.get('wall_s')} s)"
                    + (f": {row['error']}" if row.get("error") else ""))
        finally:
            cluster.close()
    wall = time.perf_counter() - wall0
    ordered = [rows[t["id"]] for t in tasks]
    names = [p.path for p in study.parameters]
    csv_path = write_table(study.out / "study", ordered, names, study.metric_names())
    write_study_meta(study, wall, len(todo), len(finished))
    from .figures import plot_study

    try:
        plot_study(ordered, names, study.metric_names(), study.out / "study.png")
    except Exception as exc:  # noqa: BLE001 - a plot must never cost the table
        say(f"warning: study.png not written ({type(exc).__name__}: {exc})")
    failed = sum(r["status"] != "done" for r in ordered)
    say(f"study {study.name}: {len(ordered) - failed} done, {failed} failed, {wall:.1f} s")
    return csv_path, failed, len(ordered)


def write_study_meta(study: Study, wall: float, ran: int, measured_again: int = 0) -> None:
    from ..recorders import write_json

    write_json(study.out / "study.json", {"name": study.name, "study_file": str(study.source),
                                          "scene": str(study.scene), "set": study.fixed,
                                          "parameters": [p.__dict__ for p in study.parameters],
                                          "sampling": study.sampling, "metrics": study.metric_names(),
                                          "reference": study.reference, "points_run_now": ran,
                                          "points_measured_again": measured_again,
                                          "wall_time_s": round(wall, 3)})


def write_table(stem: Path, rows: list[dict], params: list[str], metrics: list[str],
                lead: tuple = ("point",), status: str = "status") -> Path:
    """stem.csv and stem.parquet: point, parameters, status, metrics, error, wall_s, run_dir."""
    import csv

    extra = [k for r in rows for k in r if k not in params + metrics]
    cols = [*lead, *params, status, *metrics]
    cols += [k for k in dict.fromkeys(extra) if k not in cols]
    csv_path = stem.with_suffix(".csv")
    with open(csv_path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in rows:
            w.writerow(["" if r.get(c) is None else r.get(c) for c in cols])
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = {}
        for c in cols:
            values = [r.get(c) for r in rows]
            if all(v is None or (_is_num(v) or isinstance(v, float)) for v in values):
                values = [None if v is None else float(v) for v in values]
            elif not all(v is None or isinstance(v, str) for v in values):
                values = [None if v is None else str(v) for v in values]
            table[c] = values
        pq.write_table(pa.table(table), stem.with_suffix(".parquet"))
    except ImportError:
        print("warning: study.parquet not written (pip install pyarrow)", file=sys.stderr)
    return csv_path
