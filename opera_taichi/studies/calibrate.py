"""`calibrate STUDY.yaml`: soil parameters fitted to a reference with Optuna, trials run on the study's Dask cluster;
the best parameters written as a soil preset file (`soil.preset_file` in a scene).

The study file's `calibrate` section (its scene, set, reference and out as for `study`):

    calibrate:
      parameters:                                   # soil.overrides.* paths, with bounds
        soil.overrides.friction_angle_deg: {low: 24, high: 40}
      trials: 6
      sampler: tpe                                  # tpe | qmc | random
      refine: true                                  # the last trial at the surrogate's optimum (trials >= 4)
      objective: force                              # force | terrain | joints | metric
      force: {file: measured_force.csv, column: fx, tool: blade, t: [0.3, 1.5], smooth_s: 0.2}
      metric: {name: wrench.blade.fx.mean, target: 850.0}     # objective: metric
      preset_file: soil_preset.yaml                 # default: <out>/soil_preset.yaml

Objectives (the loss, smaller is better):
- force: RMS of the run's force curve minus the measured one (both smoothed by a moving average of smooth_s, on the
  measured samples inside t), over the measured curve's RMS. The measured CSV has `t` and `column`; a `tool` column,
  when there is one (a run's tool_wrench.csv), selects the rows of `tool`. Every row as long as the header, t and the
  force finite numbers (else refused before the first trial, naming line and column); header names are stripped.
  A window t ending after the trials' sim.duration is refused before the first trial, a run's force that stops
  before the window's measured samples do when it is scored;
- terrain: compare's terrain_rmse_m against the study's reference scan; joints: compare's joints_rmse_rad against
  its joint log; metric: |metric - target| / |target|.
Refinement: with `refine`, the last trial is not sampled but placed where a fit through the trials so far puts the
optimum: for one parameter and an objective with a sign (force: the mean of the difference; metric), the zero of a
line through the two trials that bracket the sign change; otherwise the vertex of a quadratic through the best
trials (per parameter, kept inside the bounds). The result is a trial like any other: the best trial wins. It needs
3 finished trials before it: `refine: true` with trials < 4 is refused; left unset, refine is then off.
Resumable: the trials live in <out>/optuna.journal (Optuna's journal storage); a rerun adds trials up to `trials`,
only to the same calibration (the fingerprint in the Optuna study's user attrs: set, scene, parameter space,
objective); another is refused, naming what differs.
The preset file reproduces the best trial's soil: the scene's preset file, overrides and the calibrated values. A
preset_file is relative to the study file and moves with nothing else: outside <out>, one that exists is overwritten
only when this calibration wrote it (its `calibration.out` is this <out>), else refused before the first trial.
"""
from __future__ import annotations

import hashlib
import json
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from ..errors import UserError
from .study import (CSV_SHORT, Parameter, _is_num, _metric, _parameter, check_out_folder, load_study, make_task,
                    run_point, scale)

OBJECTIVES = ("force", "terrain", "joints", "metric")
REFINE_MIN_TRIALS = 4  # refine_point fits through 3 finished trials; the 4th is the refined one


# ----------------------------------------------------------------------------------------------- objectives
def _smooth_on(t, v, t_eval, width):
    """Moving average of v(t) over `width` seconds, sampled at t_eval."""
    if width <= 0:
        return np.interp(t_eval, t, v)
    c = np.concatenate([[0.0], np.cumsum((v[1:] + v[:-1]) / 2 * np.diff(t))])  # trapezoid integral
    lo = np.clip(t_eval - width / 2, t[0], t[-1])
    hi = np.clip(t_eval + width / 2, t[0], t[-1])
    span = np.maximum(hi - lo, 1e-12)
    return (np.interp(hi, t, c) - np.interp(lo, t, c)) / span


def read_measured_csv(path: Path, numeric: tuple, text: tuple = (), key: str = "calibrate.force.file"):
    """(header, {column: values}) of a measured CSV, header names stripped of spaces: the `numeric` columns it has as
    float arrays, the `text` ones as lists. A row of another length than the header, or a cell of a numeric column
    that is not a finite number, is refused naming its line and column (a NaN or an empty force cell scored every
    trial nan; a short row was dropped)."""
    import csv

    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = [(line, row) for line, row in enumerate(csv.reader(fh), start=1) if any(c.strip() for c in row)]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise UserError(f"{key}: {path}: unreadable ({type(exc).__name__})") from None
    if not rows:
        raise UserError(f"{key}: {path}: empty; expected a header naming `t` and the force column")
    header = [c.strip() for c in rows[0][1]]
    where = {n: header.index(n) for n in (*numeric, *text) if n in header}
    cols: dict = {n: [] for n in where}
    for line, row in rows[1:]:
        if len(row) != len(header):
            raise UserError(f"{key}: {path}: line {line}: expected {len(header)} fields (as the header), got "
                            f"{len(row)}")
        for name, i in where.items():
            cell = row[i].strip()
            if name in text:
                cols[name].append(cell)
                continue
            try:
                value = float(cell)
            except ValueError:
                value = math.nan
            if not math.isfinite(value):
                raise UserError(f"{key}: {path}: line {line}, column {name}: expected a finite number, got {cell!r}")
            cols[name].append(value)
    return header, {n: v if n in text else np.asarray(v, float) for n, v in cols.items()}


def read_force_curve(path, column: str, tool: str | None, measured: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(t, force) of a force CSV: the measured one (checked cell by cell: read_measured_csv), or a run's
    tool_wrench.csv (measured=False: a row cut short by a killed run is left out, as wherever a run is read)."""
    from ..recorders import read_csv_columns

    path = Path(path)
    if measured:
        header, cols = read_measured_csv(path, ("t", column), ("tool",) if column != "tool" else ())
    else:
        try:
            cols = read_csv_columns(path)
        except (OSError, IndexError, ValueError, UnicodeDecodeError) as exc:
            raise UserError(f"calibrate.force.file: {path}: unreadable ({type(exc).__name__})") from None
        header = list(cols)
    if "t" not in cols:
        raise UserError(f"calibrate.force.file: {path}: header has no `t` column (got {', '.join(header)})")
    if column not in cols or isinstance(cols[column], list):
        raise UserError(f"calibrate.force.column: {path} has no numeric column {column!r} (got {', '.join(header)})")
    keep = np.ones(len(cols["t"]), bool)
    if tool is not None and "tool" in cols:
        keep = np.array([str(c) == tool for c in cols["tool"]])
        if not keep.any():
            raise UserError(f"calibrate.force.tool: {path} has no rows of tool {tool!r}")
    t, f = np.asarray(cols["t"], float)[keep], np.asarray(cols[column], float)[keep]
    if len(t) < 3 or np.any(np.diff(t) <= 0):
        raise UserError(f"calibrate.force.file: {path}: needs at least 3 rows with t strictly increasing")
    return t, f


def objective_value(run_dir: Path, spec: dict) -> dict:
    """{'loss': float, 'signed': float | None} of a finished run folder against the objective."""
    kind = spec["objective"]
    if kind == "force":
        f = spec["force"]
        t_ref, f_ref = read_force_curve(f["file"], f.get("column", "fx"), f.get("tool"))
        t_run, f_run = read_force_curve(run_dir / "tool_wrench.csv", f.get("column", "fx"), f.get("tool"),
                                         measured=False)
        window = f.get("t") or [max(t_ref[0], t_run[0]), min(t_ref[-1], t_run[-1])]
        te = t_ref[(t_ref >= window[0]) & (t_ref <= window[1])]
        if len(te) < 3:
            raise UserError(f"calibrate.force.t: fewer than 3 measured samples in {window}")
        step = float(np.median(np.diff(t_run)))
        if te[-1] > t_run[-1] + step or te[0] < t_run[0] - step:  # beyond them the run's force is held, not measured
            raise UserError(f"calibrate.force.t: the window {window} holds measured samples from {te[0]:g} to "
                            f"{te[-1]:g} s, the run's force spans {t_run[0]:g}-{t_run[-1]:g} s; give t within it")
        w = float(f.get("smooth_s", 0.2))
        a, b = _smooth_on(t_run, f_run, te, w), _smooth_on(t_ref, f_ref, te, w)
        scale_ = float(np.sqrt(np.mean(b ** 2))) or 1.0
        return {"loss": float(np.sqrt(np.mean((a - b) ** 2)) / scale_), "signed": float(np.mean(a - b) / scale_)}
    if kind == "metric":
        from .study import collect_metrics

        m = spec["metric"]
        value = collect_metrics(run_dir, [m["name"]], spec.get("reference") or {})[m["name"]]
        if value is None:
            raise UserError(f"calibrate.metric.name: {m['name']} has no value in {run_dir}")
        if not _is_num(value):
            raise UserError(f"calibrate.metric.name: {m['name']} is {value!r} in {run_dir}, not a number")
        target = float(m["target"])
        denom = abs(target) or 1.0
        return {"loss": abs(value - target) / denom, "signed": (value - target) / denom, m["name"]: value}
    from .compare import compare

    ref = spec.get("reference") or {}
    result = compare(run_dir, terrain=ref.get("terrain"), terrain_before=ref.get("terrain_before"),
                     joints=ref.get("joints"), against=ref.get("against"), transform=ref.get("transform"),
                     fit=ref.get("fit_transform"), figures=False)
    key = "terrain_rmse_m" if kind == "terrain" else "joints_rmse_rad"
    if result.get(key) is None:
        raise UserError(f"calibrate.objective: {kind}: compare gave no {key} for {run_dir}")
    return {"loss": float(result[key]), "signed": float(result["terrain_bias_m"]) if kind == "terrain" else None}


# ----------------------------------------------------------------------------------------------- the section
def _section(study, label: str, trials_override: int | None) -> dict:
    c = study.calibrate
    if not isinstance(c, dict):
        raise UserError(f"{label}: calibrate: required, a mapping (parameters, trials, objective, ...)")
    allowed = {"parameters", "trials", "sampler", "refine", "objective", "force", "metric", "preset_file", "seed"}
    bad = sorted(set(c) - allowed)
    if bad:
        raise UserError(f"{label}: calibrate.{bad[0]}: unknown key; allowed: {', '.join(sorted(allowed))}")
    params_in = c.get("parameters")
    if not isinstance(params_in, dict) or not params_in:
        raise UserError(f"{label}: calibrate.parameters: expected a mapping of soil.overrides.* paths to "
                        f"{{low, high}}")
    params = []
    for path, spec in params_in.items():
        if not str(path).startswith("soil.overrides."):
            raise UserError(f"{label}: calibrate.parameters.{path}: calibrates soil parameters; expected a path "
                            f"soil.overrides.<name>")
        p = _parameter(str(path), spec, label)
        if p.low is None:
            raise UserError(f"{label}: calibrate.parameters.{path}: expected {{low: a, high: b}}")
        params.append(p)
    trials = trials_override or c.get("trials", 20)
    if not (isinstance(trials, int) and not isinstance(trials, bool) and trials >= 1):
        raise UserError(f"{label}: calibrate.trials: expected a positive integer, got {trials!r}")
    sampler = c.get("sampler", "tpe")
    if sampler not in ("tpe", "qmc", "random"):
        raise UserError(f"{label}: calibrate.sampler: expected tpe, qmc or random, got {sampler!r}")
    objective = c.get("objective")
    if objective not in OBJECTIVES:
        raise UserError(f"{label}: calibrate.objective: expected one of {', '.join(OBJECTIVES)}, got {objective!r}")
    spec = {"objective": objective, "reference": study.reference}
    base = study.source.parent
    if objective == "force":
        f = c.get("force")
        if not isinstance(f, dict) or "file" not in f:
            raise UserError(f"{label}: calibrate.force: required with objective force: {{file, column, tool, t, "
                            f"smooth_s}}")
        bad = sorted(set(f) - {"file", "column", "tool", "t", "smooth_s"})
        if bad:
            raise UserError(f"{label}: calibrate.force.{bad[0]}: unknown key; allowed: column, file, smooth_s, t, tool")
        file = Path(f["file"]) if Path(f["file"]).is_absolute() else base / f["file"]
        if not file.is_file():
            raise UserError(f"{label}: calibrate.force.file: no file at {file}")
        f = {**f, "file": str(file.resolve())}
        for key in ("column", "tool"):
            if key in f and not (isinstance(f[key], str) and f[key]):
                raise UserError(f"{label}: calibrate.force.{key}: expected a name (a string), got {f[key]!r}")
        smooth = f.get("smooth_s", 0.2)
        if not (_is_num(smooth) and smooth >= 0):
            raise UserError(f"{label}: calibrate.force.smooth_s: expected a number of seconds >= 0 (0: no "
                            f"smoothing), got {smooth!r}")
        t_ref, _ = read_force_curve(f["file"], f.get("column", "fx"), f.get("tool"))  # bad files stop here
        window = f.get("t")
        if window is not None:  # the measured curve's window holds whatever a trial gives: checked once, here
            if not (isinstance(window, list) and len(window) == 2 and all(_is_num(v) for v in window)
                    and window[0] < window[1]):
                raise UserError(f"{label}: calibrate.force.t: expected [t0, t1] in s with t0 < t1, got {window!r}")
            inside = int(np.count_nonzero((t_ref >= window[0]) & (t_ref <= window[1])))
            if inside < 3:
                raise UserError(f"{label}: calibrate.force.t: {inside} measured samples in {window} (the file spans "
                                f"{t_ref[0]:g}-{t_ref[-1]:g} s); at least 3 are needed")
        spec["force"] = f
    elif objective == "metric":
        m = c.get("metric")
        if not (isinstance(m, dict) and isinstance(m.get("name"), str) and "target" in m):
            raise UserError(f"{label}: calibrate.metric: required with objective metric: {{name, target}}")
        bad = sorted(set(m) - {"name", "target"})
        if bad:
            raise UserError(f"{label}: calibrate.metric.{bad[0]}: unknown key; allowed: name, target")
        if not _is_num(m["target"]):
            raise UserError(f"{label}: calibrate.metric.target: expected a finite number, got {m['target']!r}")
        try:  # the form a study's metric has (its files, tools and columns: _check_outputs)
            _metric(m["name"], label, 0)
        except UserError as exc:
            raise UserError(str(exc).replace("metrics.0:", "calibrate.metric.name:", 1)) from None
        if m["name"].startswith("compare.") and not study.reference:
            raise UserError(f"{label}: calibrate.metric.name: compare.* metrics need a `reference` (terrain, joints "
                            f"or against)")
        if m["name"].startswith("compare."):
            from .study import check_compare_metric

            check_compare_metric(m["name"], study.reference, f"{label}: calibrate.metric.name")
        spec["metric"] = m
    elif objective == "terrain" and "terrain" not in study.reference and "against" not in study.reference:
        raise UserError(f"{label}: reference.terrain: required with objective terrain (the scan to match)")
    elif objective == "joints" and "joints" not in study.reference and "against" not in study.reference:
        raise UserError(f"{label}: reference.joints: required with objective joints (the log to match)")
    preset = c.get("preset_file")
    preset = (base / preset).resolve() if preset else study.out / "soil_preset.yaml"
    refine = c.get("refine", True)
    if not isinstance(refine, bool):
        raise UserError(f"{label}: calibrate.refine: expected true or false, got {refine!r}")
    note = None
    if refine and trials < REFINE_MIN_TRIALS:  # the fit needs 3 finished trials before the refined last one
        if "refine" in c:
            raise UserError(f"{label}: calibrate.refine: true needs trials >= {REFINE_MIN_TRIALS} (3 to fit, then "
                            f"the refined one), got {trials}{' (--trials)' if trials_override else ''}; give more "
                            f"trials or refine: false")
        refine, note = False, f"refine off: {trials} trial(s), refining needs {REFINE_MIN_TRIALS}"
    seed = c.get("seed", study.seed)
    return dict(params=params, trials=trials, sampler=sampler, spec=spec, preset=preset, refine=refine, seed=seed,
                note=note)


def _check_outputs(study, cfg: dict, points: list[dict], label: str) -> None:
    """check_points, with what the objective reads of a run as extra study metrics: a tool, column or file the runs
    do not write is refused before the first trial, under the calibrate key that names it."""
    import dataclasses
    import re

    from .study import check_points

    spec, probes = cfg["spec"], []
    if spec["objective"] == "force":
        f = spec["force"]
        where = {"tool": f["tool"]} if f.get("tool") is not None else {}
        probes.append(("calibrate.force", {"name": "force", "file": CSV_SHORT["wrench"],
                                           "column": f.get("column", "fx"), "where": where}))
    elif spec["objective"] == "metric":
        name = spec["metric"]["name"]
        parts = name.split(".")
        if parts[0] in CSV_SHORT:
            probes.append(("calibrate.metric.name", name))
        elif parts[:2] == ["summary", "tools"] and len(parts) > 2:  # summary.json has a block per tool
            probes.append(("calibrate.metric.name", {"name": name, "file": CSV_SHORT["wrench"], "column": "t",
                                                     "where": {"tool": parts[2]}}))
    n0 = len(study.metrics)
    try:
        check_points(dataclasses.replace(study, metrics=[*study.metrics, *(m for _, m in probes)]), points, label)
    except UserError as exc:
        hit = re.match(rf"{re.escape(label)}: metrics\.(\d+): (.*)$", str(exc), re.S)
        if hit is None or int(hit[1]) < n0:
            raise
        key, detail = probes[int(hit[1]) - n0][0], hit[2]
        if "this scene's runs write no" in detail:
            detail = detail[detail.index("this scene's"):]
        if key == "calibrate.force":
            key += ".tool" if " no tool " in detail else ".column" if " no column " in detail else ""
        elif " no tool " in detail:  # the tool named in a summary key
            detail = f"{spec['metric']['name']}: the runs have no tool{detail.split(' no tool', 1)[1]}"
        raise UserError(f"{label}: {key}: {detail}") from None


def _check_preset(path: Path, study, label: str) -> None:
    """A preset_file outside the calibration's folder is written only when it is new or this calibration's own (its
    `calibration.out` names this folder): a second calibration into another --out overwrote the first's preset."""
    import yaml

    if not path.exists() or study.out in path.parents:
        return
    try:
        block = yaml.safe_load(path.read_text()).get("calibration")
    except (OSError, ValueError, AttributeError, yaml.YAMLError):
        block = None
    owner = block.get("out") if isinstance(block, dict) else None
    if owner == str(study.out):
        return
    what = f"the preset of the calibration in {owner}" if owner else "a file this calibration did not write"
    raise UserError(f"{label}: calibrate.preset_file: {path} holds {what}; give another preset_file (or remove it)")


def _check_window(study, cfg: dict, label: str) -> None:
    """A force window t that ends after the trials' sim.duration is refused: the run's force would be held at its
    last sample over the rest (a loss of a curve the run never made). The calibrated soil values leave the duration
    as the study's `set` and scene give it."""
    from ..scene import load_scene
    from .study import overrides

    window = (cfg["spec"].get("force") or {}).get("t")
    if cfg["spec"]["objective"] != "force" or window is None:
        return
    duration = load_scene(study.scene, overrides(study, {})).sim.duration
    if window[1] > duration:
        raise UserError(f"{label}: calibrate.force.t: {window} ends after the trials' end at sim.duration {duration:g} "
                        f"s; give t: [t0, t1] with t1 <= {duration:g} (or a longer sim.duration in `set`)")


def _sampler(kind: str, seed: int, trials: int):
    import optuna

    if kind == "qmc":
        with warnings.catch_warnings():  # "experimental": optuna's label, not a problem of the user's
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            return optuna.samplers.QMCSampler(qmc_type="sobol", scramble=True, seed=seed,
                                              warn_independent_sampling=False)
    if kind == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    return optuna.samplers.TPESampler(seed=seed, n_startup_trials=max(2, min(10, trials // 2)))


# ----------------------------------------------------------------------------------------------- resuming
def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def fingerprint(study, cfg: dict) -> dict:
    """What a trial's loss depends on, by the study-file key that sets it: the scene (as the study's set resolves it,
    with the content of its soil preset file), the set, the parameter space and the objective (files by content).
    Kept in the Optuna study's user attrs: a resume continues only the calibration it was recorded for."""
    from .study import overrides, scene_fingerprint

    spec = cfg["spec"]
    fp = {"set": study.fixed, "scene": scene_fingerprint(study.scene, overrides(study, {})),
          "calibrate.parameters": {p.path: {"low": p.low, "high": p.high, "log": p.log} for p in cfg["params"]},
          "calibrate.objective": spec["objective"]}
    if spec["objective"] == "force":
        f = spec["force"]
        fp["calibrate.force"] = {"file": _sha(Path(f["file"]).read_bytes()), "column": f.get("column", "fx"),
                                 "tool": f.get("tool"), "t": f.get("t"), "smooth_s": float(f.get("smooth_s", 0.2))}
    elif spec["objective"] == "metric":
        fp["calibrate.metric"] = {"name": spec["metric"]["name"], "target": float(spec["metric"]["target"])}
    if spec["objective"] in ("terrain", "joints") or fp.get("calibrate.metric", {}).get("name", "").startswith(
            "compare."):
        fp["reference"] = {k: _sha(Path(v).read_bytes()) if k in ("terrain", "terrain_before", "joints") and
                           Path(v).is_file() else v for k, v in (spec.get("reference") or {}).items()}
    return json.loads(json.dumps(fp))  # as the journal gives it back (lists, not tuples)


def _differences(old: dict, new: dict) -> list[str]:
    out = []
    for key in dict.fromkeys([*old, *new]):
        a, b = old.get(key), new.get(key)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            out += [f"{key}.{k}" for k in dict.fromkeys([*a, *b]) if a.get(k) != b.get(k)]
        else:
            out.append(key)
    return out


def open_study(optuna, storage, study, cfg: dict, label: str):
    """The Optuna study of this calibration in <out>'s journal: new, or the one a previous session left there when
    it was recorded for the same scene, set, parameter space and objective (else UserError: its trials were
    scored against something else and would be taken for this one's)."""
    fp = fingerprint(study, cfg)
    again = f"give another --out (or remove {study.out})"
    for other in storage.get_all_studies():
        if other.study_name != study.name:
            raise UserError(f"{label}: out: {study.out} holds calibration {other.study_name!r}, not {study.name!r}; "
                            f"{again}")
    stored, n = None, 0
    if storage.get_all_studies():  # read, not loaded: a refused resume leaves the journal as it was
        sid = storage.get_study_id_from_name(study.name)
        stored, n = storage.get_study_user_attrs(sid).get("fingerprint"), len(storage.get_all_trials(sid))
    if stored is None and n:
        raise UserError(f"{label}: out: {study.out} holds {n} trial(s) with no record of what they were scored "
                        f"against (an older opera-taichi); {again}")
    if stored is not None and stored != fp:
        raise UserError(f"{label}: out: {study.out} holds trials of calibration {study.name!r} run with another "
                        f"{', '.join(_differences(stored, fp))}; they are not mixed with this one's: {again}")
    opt = optuna.create_study(study_name=study.name, storage=storage, direction="minimize", load_if_exists=True,
                              sampler=_sampler(cfg["sampler"], cfg["seed"], cfg["trials"]))
    if stored is None:
        opt.set_user_attr("fingerprint", fp)
    return opt


# ----------------------------------------------------------------------------------------------- refinement
def refine_point(rows: list[dict], params: list[Parameter]) -> dict | None:
    """Where a fit through the finished trials puts the optimum (None when it cannot say)."""
    done = [r for r in rows if r.get("loss") is not None and math.isfinite(r["loss"])]
    if len(done) < 3:
        return None
    if len(params) == 1:
        p = params[0]
        signed = [r for r in done if r.get("signed") is not None]
        if len(signed) == len(done):
            pts = sorted((r[p.path], r["signed"]) for r in signed)
            for (x0, s0), (x1, s1) in zip(pts, pts[1:]):
                if s0 == 0.0:
                    return {p.path: float(x0)}
                if s0 * s1 < 0:  # the sign changes between these two: its zero on the line through them
                    return {p.path: float(x0 + (x1 - x0) * s0 / (s0 - s1))}
    best = sorted(done, key=lambda r: r["loss"])
    out = {}
    for p in params:  # per parameter: the vertex of a parabola through the three best trials
        xs = np.array([r[p.path] for r in best[:3]], float)
        ys = np.array([r["loss"] for r in best[:3]], float)
        if np.ptp(xs) <= 0:
            return None
        a, b, _c = np.polyfit(xs, ys, 2)
        if not a > 0:
            return None
        out[p.path] = float(np.clip(-b / (2 * a), p.low, p.high))
    return out


# ----------------------------------------------------------------------------------------------- the command
def calibrate(path, scheduler: str | None = None, workers: int | None = None, out=None, quiet: bool = False,
              trials: int | None = None) -> dict:
    try:
        import optuna
        from optuna.storages import JournalStorage
        from optuna.storages.journal import JournalFileBackend
    except ImportError:
        raise UserError("calibrate: needs optuna (pip install 'opera-taichi[studies]')") from None
    from .study import Cluster

    label = str(path)
    study = load_study(path, out)
    check_out_folder(study.out, study.name, str(path), calibrate=True)
    cfg = _section(study, label, trials)
    _check_preset(cfg["preset"], study, label)
    params = cfg["params"]
    _check_outputs(study, cfg, [{p.path: scale(p, u) for p in params} for u in (0.0, 1.0)], label)
    _check_window(study, cfg, label)
    study.out.mkdir(parents=True, exist_ok=True)
    trials_dir = study.out / "trials"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    storage = JournalStorage(JournalFileBackend(str(study.out / "optuna.journal")))
    opt = open_study(optuna, storage, study, cfg, label)
    dists = {p.path: optuna.distributions.FloatDistribution(p.low, p.high, log=p.log) for p in params}
    rows: dict[int, dict] = {}
    for tr in opt.trials:  # a previous session's trials: finished ones count; ones it left running are settled now
        if tr.state == optuna.trial.TrialState.COMPLETE:
            rows[tr.number] = {**tr.params, "loss": tr.value, "signed": tr.user_attrs.get("signed"),
                               "status": "done", "trial": tr.number}
        elif tr.state == optuna.trial.TrialState.RUNNING:
            opt.tell(tr.number, state=optuna.trial.TrialState.FAIL)
    say = (lambda *a: None) if quiet else (lambda text: print(text, file=sys.stderr, flush=True))
    n_done = sum(1 for r in rows.values())
    todo = max(0, cfg["trials"] - n_done)
    say(f"calibrate {study.name}: {cfg['trials']} trials ({n_done} finished before), objective "
        f"{cfg['spec']['objective']} -> {study.out}")
    if cfg["note"]:
        say(f"  note: {cfg['note']}")
    wall0 = time.perf_counter()
    all_rows = list(rows.values())
    if todo:
        cluster = Cluster(scheduler, workers)
        say(f"  on {cluster.workers} worker(s)")
        from dask.distributed import as_completed

        pending = {}
        asked = 0

        def submit():
            nonlocal asked
            last = asked == todo - 1 and cfg["refine"] and not pending
            guess = refine_point(all_rows, params) if last else None
            if guess is not None:
                opt.enqueue_trial(guess)
            elif last:  # say so: a sampled last trial is not what `refine` promised
                n = sum(1 for r in all_rows if r.get("loss") is not None and math.isfinite(r["loss"]))
                say(f"  warning: refine: " + (f"{n} finished trial(s) before the last, 3 needed" if n < 3 else
                                              "the fit through the trials has no minimum") + "; the last is sampled")
            trial = opt.ask(dists)
            point = dict(trial.params)
            task = make_task(study, trial.number, point, trials_dir, objective=cfg["spec"])
            trial.set_user_attr("run_dir", task["run_dir"])
            trial.set_user_attr("refined", guess is not None)
            fut = cluster.client.submit(run_point, task, key=f"{study.name}-t{trial.number}-{time.time_ns()}",
                                        pure=False)
            pending[fut] = (trial, task)
            asked += 1

        try:
            # keep every worker busy, but hold the refined trial until all others are in
            while asked < todo and len(pending) < cluster.workers and \
                    not (cfg["refine"] and asked == todo - 1 and pending):
                submit()
            seq = as_completed(list(pending))
            for fut in seq:
                trial, task = pending.pop(fut)
                try:
                    row = fut.result()
                except Exception as exc:  # noqa: BLE001 - a lost worker: a failed trial
                    row = {"status": "error", "error": f"{type(exc).__name__}: {exc}"}
                row = {**row, "trial": trial.number, **trial.params}
                if row.get("status") == "done" and row.get("loss") is not None:
                    if row.get("signed") is not None:
                        trial.set_user_attr("signed", row["signed"])
                    opt.tell(trial, row["loss"])
                else:
                    opt.tell(trial, state=optuna.trial.TrialState.FAIL)
                all_rows.append(row)
                say(f"  trial {trial.number}: " + ", ".join(f"{k} = {v:.5g}" for k, v in trial.params.items())
                    + (f" loss {row['loss']:.4g}" if row.get("loss") is not None else f" {row.get('status')}: "
                       f"{row.get('error', '')}"))
                while asked < todo and len(pending) < cluster.workers and \
                        not (cfg["refine"] and asked == todo - 1 and pending):
                    submit()
                    seq.add(list(pending)[-1])
        finally:
            cluster.close()
    wall = time.perf_counter() - wall0
    completed = [t for t in opt.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if not completed:
        raise UserError(f"calibrate: no trial finished (see {trials_dir}/*/point.json)")
    best = opt.best_trial
    preset = write_preset(cfg["preset"], study, best.params, best.value, cfg, wall)
    names = [p.path for p in params]
    table_rows = [{"trial": t.number, **t.params, "loss": t.value, "state": t.state.name,
                   "refined": t.user_attrs.get("refined"), "run_dir": t.user_attrs.get("run_dir")}
                  for t in opt.trials]
    from .figures import plot_calibration
    from .study import write_table

    write_table(study.out / "calibration", table_rows, names, ["loss"], lead=("trial",), status="state")
    try:
        plot_calibration(table_rows, names, best.params, study.out / "calibration.png")
    except Exception as exc:  # noqa: BLE001
        say(f"warning: calibration.png not written ({type(exc).__name__}: {exc})")
    result = {"best_parameters": dict(best.params), "best_loss": best.value, "best_trial": best.number,
              "trials": len(opt.trials), "preset_file": str(preset), "wall_time_s": round(wall, 3)}
    from ..recorders import write_json

    write_json(study.out / "calibration.json", result)
    say(f"calibrate {study.name}: best loss {best.value:.4g} at trial {best.number}, {wall:.1f} s")
    return result


def write_preset(path: Path, study, best: dict, loss: float, cfg: dict, wall: float) -> Path:
    """The soil preset file: the best trial's bulk soil (its preset, the values of the soil.preset_file its scene
    used, the scene's overrides and the calibrated values; not the radius, a resolution a scene keeps), and a
    `calibration` block saying where they came from (read by nothing; provenance). A scene with this file and no
    overrides of its own resolves the best trial's soil (its radius aside)."""
    import yaml

    from ..scene import load_scene
    from ..soil import resolve_soil, scene_soil_values
    from .study import overrides

    soil = load_scene(study.scene, overrides(study, best)).soil  # the best trial's own scene
    preset, values = scene_soil_values(soil)  # the values as the trial's soil was resolved from them
    radius = resolve_soil(preset, values).radius
    values.pop("radius", None)  # a resolution, not a soil property: a scene keeps its own
    calibration = {"study": str(study.source), "out": str(study.out), "scene": str(study.scene),
                   "objective": cfg["spec"]["objective"],
                   "loss": float(loss), "trials": cfg["trials"], "radius_m": radius, "wall_time_s": round(wall, 1)}
    if soil.preset_file is not None:
        calibration["built_on"] = str(soil.preset_file)
    data = {"preset": preset, **{k: None if v is None else float(v) for k, v in values.items()},
            "calibration": calibration}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("# Soil preset written by `opera-taichi calibrate`; use it with soil.preset_file in a scene.\n"
                    + yaml.safe_dump(data, sort_keys=False))
    return path
