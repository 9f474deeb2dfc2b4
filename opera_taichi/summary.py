"""summary.json: what a run did, in numbers an engineer reads first.

`summarize(run_dir, model)` only reads the run folder's files (manifest.json, joints.csv, tool_wrench.csv,
soil_mass.csv, terrain_initial.npz, terrain_final.npz); the model gives what those files do not hold: actuator
limits, the soil's bulk density and the tools' meshes and struck volumes. A file that is missing (a run without soil
or without a machine, a run that died before writing it) leaves its part out. Every key names its unit (`_kg`,
`_m3`, `_s`, `_N`, `_Nm`); `_fraction` and `relative_` keys are ratios.

Definitions (also written into the summary under `definitions`):
- soil held: the last `in_<tool>_kg` of soil_mass.csv (grain centres inside the tool's convex hull); m3 at the
  bulk density; a bucket's fill factor is that volume over its struck volume.
- dug / heaped: the ground-only heightmaps `z` (grains a tool carries and grains in flight left out), final minus
  initial, summed over the cells: dug = sum max(0, z0 - z1) dA, heaped = sum max(0, z1 - z0) dA. The highest heap leaves out the cells
  that were gaps between grains at the start (grain_gaps): a grain rolling into one is no heap.
- force: |F| of the soil on each tool (tool_wrench.csv); the mean is over the samples in contact (|F| > 1 N).
- time at a limit: a joints.csv sample at the limit (|effort| >= 0.99 max_torque, |qd| >= 0.99 max_speed) counts
  for the interval to the next sample (t[i+1] - t[i]); the fraction is over the recorded span t[-1] - t[0].
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .recorders import read_csv_columns, write_json

CONTACT_FORCE_N = 1.0        # |F| above this is "in contact"
LIMIT_RATIO = 0.99           # at a limit: within 1 % of it
SUMMARY_FILE = "summary.json"


# ---------------------------------------------------------------------------------------------- helpers
def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def _columns(path: Path) -> dict | None:
    """The CSV's columns, or None when it is missing, empty or has no data row."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        cols = read_csv_columns(path)
    except (OSError, IndexError, ValueError):
        return None
    t = cols.get("t")
    if t is None or not isinstance(t, np.ndarray) or len(t) == 0:
        return None
    return cols


def _terrain(path: Path) -> dict | None:
    if not Path(path).is_file():
        return None
    try:
        with np.load(path) as data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError):
        return None


def grain_radius(model, manifest: dict | None) -> float | None:
    """The soil's mean grain radius (m): the model's, else the manifest's (soil.micro.radius); None without soil."""
    radius = getattr(getattr(getattr(model, "soil", None), "params", None), "radius", None)
    if radius is None:
        try:
            radius = manifest["soil"]["micro"]["radius"]
        except (TypeError, KeyError):
            return None
    return _num(radius)


def grain_gaps(z0, cell_m: float, radius_m: float | None) -> np.ndarray:
    """Cells of an initial heightmap in a gap between grains (or between a grain and a pit wall), where the bed
    floor shows through: more than a grain radius below the surface closed over a grain diameter (a disc no grain
    enters). A grain rolling into one later rises there by most of the bed's depth, which is no heave (0.81 m with
    32 cm grains). No cell without a radius."""
    from scipy.ndimage import grey_closing

    z0 = np.asarray(z0, float)
    finite = np.isfinite(z0)
    if not (radius_m and cell_m and radius_m > 0 and finite.any()):
        return np.zeros(z0.shape, bool)
    n = max(1, int(round(radius_m / cell_m)))
    k = np.arange(-n, n + 1)
    # an empty cell (a scan's) closes as the lowest one: it never makes its neighbours look like gaps
    closed = grey_closing(np.where(finite, z0, np.nanmin(z0)), footprint=k[:, None] ** 2 + k[None, :] ** 2 <= n * n,
                          mode="nearest")
    return finite & (z0 < closed - radius_m)


def interval_weights(t: np.ndarray) -> np.ndarray:
    """Seconds each sample stands for: t[i+1] - t[i], and 0 for the last one."""
    t = np.asarray(t, dtype=float)
    w = np.zeros_like(t)
    if len(t) > 1:
        w[:-1] = np.diff(t)
    return w


def joint_limits(model) -> dict[str, tuple[float, float]]:
    """{joints.csv column prefix: (max_speed, max_torque)}: `<joint>` with one machine, `<machine>.<joint>` with
    several (rad/s and N m; m/s and N for a prismatic joint). Also what plots.plot_joints takes as `limits`."""
    machines = list(getattr(model, "machines", ()) or ())
    several = len(machines) > 1
    out = {}
    for m in machines:
        for joint in m.description.actuated_joints:
            act = m.description.actuators[joint]
            out[f"{m.name}.{joint}" if several else joint] = (float(act.max_speed), float(act.max_torque))
    return out


def struck_volume(model, binding) -> tuple[float | None, str | None]:
    """(m3, source) of a tool's struck volume: the machine description's `struck_volume` for the link when it has
    one, else the convex hull of the tool mesh less the mesh's own volume (a cavity under 1 litre: not a bucket,
    (None, None))."""
    if binding.owner is not None and binding.link is not None:
        for m in getattr(model, "machines", ()):
            if m.name == binding.owner:
                declared = getattr(m.description, "struck_volume", None) or {}
                if binding.link in declared and declared[binding.link]:
                    return float(declared[binding.link]), "machine description (struck_volume)"
    mesh = binding.mesh
    try:
        hull = float(mesh.convex_hull.volume)
        solid = float(mesh.volume) if mesh.is_watertight else 0.0
    except Exception:  # trimesh can fail on degenerate meshes
        return None, None
    cavity = hull - max(solid, 0.0)
    if cavity < 1e-3:
        return None, None
    how = "convex hull of the tool mesh minus the mesh volume" if mesh.is_watertight else \
        "convex hull of the tool mesh (mesh not watertight)"
    return cavity, how


def _bulk_density(model, manifest: dict | None) -> float | None:
    soil = getattr(model, "soil", None)
    if soil is not None:
        return float(soil.bulk.density)
    try:
        return float(manifest["soil"]["bulk"]["density"])
    except (TypeError, KeyError, ValueError):
        return None


def _num(value):
    """A JSON-friendly float (None for NaN/inf/missing)."""
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


# ---------------------------------------------------------------------------------------------- parts
def _run_part(manifest: dict) -> dict:
    out = {"name": manifest.get("name"), "status": manifest.get("status"),
           "sim_time_s": _num(manifest.get("sim_time")), "wall_time_s": _num(manifest.get("wall_time_s")),
           "real_time_factor": _num(manifest.get("real_time_factor"))}
    if manifest.get("setup_wall_time_s") is not None:
        out["setup_wall_time_s"] = _num(manifest["setup_wall_time_s"])
    if manifest.get("particles") is not None:
        out["particles"] = int(manifest["particles"])
    if manifest.get("machines"):
        out["machines"] = list(manifest["machines"])
    return out


def _tool_names(model, mass_cols: dict | None, wrench_cols: dict | None) -> list[str]:
    names = [b.name for b in getattr(model, "bindings", ())]
    if mass_cols:
        names += [k[3:-3] for k in mass_cols if k.startswith("in_") and k.endswith("_kg")]
    if wrench_cols and "tool" in wrench_cols:
        names += list(dict.fromkeys(wrench_cols["tool"]))
    return list(dict.fromkeys(names))


def _tools_part(model, mass_cols, wrench_cols, density) -> dict:
    bindings = {b.name: b for b in getattr(model, "bindings", ())}
    tools = {}
    for name in _tool_names(model, mass_cols, wrench_cols):
        entry = {}
        col = f"in_{name}_kg"
        if mass_cols and col in mass_cols:
            held = float(mass_cols[col][-1])
            entry["soil_held_kg"] = held
            entry["soil_held_time_s"] = float(mass_cols["t"][-1])
            if density:
                entry["soil_held_m3"] = held / density
                if name in bindings:
                    vol, source = struck_volume(model, bindings[name])
                    if vol is not None:
                        entry["struck_volume_m3"] = vol
                        entry["struck_volume_source"] = source
                        entry["fill_factor"] = held / density / vol
        if wrench_cols and "tool" in wrench_cols:
            sel = np.asarray(wrench_cols["tool"]) == name
            if np.any(sel):
                t = wrench_cols["t"][sel]
                f = np.sqrt(wrench_cols["fx"][sel] ** 2 + wrench_cols["fy"][sel] ** 2 + wrench_cols["fz"][sel] ** 2)
                i = int(np.argmax(f))
                contact = f > CONTACT_FORCE_N
                entry["peak_force_N"] = float(f[i])
                entry["peak_force_time_s"] = float(t[i])
                entry["mean_force_in_contact_N"] = float(f[contact].mean()) if np.any(contact) else 0.0
                entry["contact_time_s"] = float(interval_weights(t)[contact].sum())
                entry["contact_samples"] = int(contact.sum())
                entry["force_samples"] = int(len(f))
                if name in bindings:  # (a machine's soil link cuts with its wedge where the grains are coarse)
                    entry["soil_wedge"] = bindings[name].cutting_edge is not None
        if entry:
            tools[name] = entry
    return tools


def _terrain_part(initial: dict, final: dict, radius: float | None = None) -> dict | None:
    x, y = np.asarray(initial["x"], float), np.asarray(initial["y"], float)
    z0, z1 = np.asarray(initial["z"], float), np.asarray(final["z"], float)
    if z0.shape != z1.shape or z0.shape != (len(x), len(y)):
        return None
    dx = float(x[1] - x[0]) if len(x) > 1 else 0.0
    dy = float(y[1] - y[0]) if len(y) > 1 else 0.0
    cell = dx * dy
    dz = z1 - z0
    out = {"dug_m3": float(np.maximum(0.0, -dz).sum() * cell), "heaped_m3": float(np.maximum(0.0, dz).sum() * cell),
           "net_change_m3": float(dz.sum() * cell), "max_cut_depth_m": float(max(0.0, -dz.min())),
           "max_heap_height_m": float(max(0.0, np.where(grain_gaps(z0, abs(dx), radius), 0.0, dz).max())),
           "cell_m2": cell, "heightmap": "z (soil on the ground)"}
    i, j = np.unravel_index(int(np.argmin(dz)), dz.shape)
    out["deepest_cut_xy_m"] = [float(x[i]), float(y[j])]
    if "z_all" in final:
        za = np.asarray(final["z_all"], float)
        if za.shape == z1.shape:
            out["above_ground_in_tools_m3"] = float(np.maximum(0.0, za - z1).sum() * cell)
    return out


def _actuators_part(joint_cols: dict, limits: dict) -> dict:
    t = joint_cols["t"]
    w = interval_weights(t)
    span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    out = {}
    for prefix, (max_speed, max_torque) in limits.items():
        qd, effort = joint_cols.get(f"{prefix}.qd"), joint_cols.get(f"{prefix}.effort")
        if qd is None or effort is None:
            continue
        at_torque = np.abs(effort) >= LIMIT_RATIO * max_torque
        at_speed = np.abs(qd) >= LIMIT_RATIO * max_speed
        tt, ts = float(w[at_torque].sum()), float(w[at_speed].sum())
        out[prefix] = {"at_torque_limit_s": tt, "at_torque_limit_fraction": tt / span if span > 0 else 0.0,
                       "at_speed_limit_s": ts, "at_speed_limit_fraction": ts / span if span > 0 else 0.0,
                       "max_torque_Nm": float(max_torque), "max_speed_rad_s": float(max_speed),
                       "peak_effort_Nm": float(np.abs(effort).max()), "peak_speed_rad_s": float(np.abs(qd).max())}
    return out


def _mass_part(mass_cols: dict | None, manifest: dict) -> dict | None:
    if mass_cols and "mass_kg" in mass_cols:
        m = mass_cols["mass_kg"]
        initial, final = float(m[0]), float(m[-1])
        ood = float(mass_cols["out_of_domain_kg"][-1]) if "out_of_domain_kg" in mass_cols else None
        source = "soil_mass.csv"
    elif isinstance(manifest.get("soil_mass_final"), dict):  # no CSV: the manifest's final budget only
        budget = manifest["soil_mass_final"]
        final = float(sum(budget.values()))
        return {"final_kg": final, "out_of_domain_kg": _num(budget.get("out_of_domain")),
                "source": "manifest.json soil_mass_final"}
    else:
        return None
    return {"initial_kg": initial, "final_kg": final, "change_kg": final - initial,
            "relative_drift": (final - initial) / initial if initial else None, "out_of_domain_kg": ood,
            "source": source}


DEFINITIONS = {
    "soil_held": "last in_<tool>_kg of soil_mass.csv: grain centres inside the tool's convex hull; m3 at the bulk "
                 "density; fill_factor = soil_held_m3 / struck_volume_m3",
    "terrain": "ground-only heightmap z (grains inside a tool's hull left out), final minus initial: dug = sum "
               "max(0, z0 - z1) dA, heaped = sum max(0, z1 - z0) dA; max_heap_height_m leaves out the cells that "
               "were gaps between grains at the start (more than a grain radius below the initial surface closed "
               "over a grain diameter: the bed floor showing through)",
    "force": "|F| of the soil on the tool; mean_force_in_contact_N averages the samples with |F| > 1 N",
    "limits": "a joints.csv sample with |effort| >= 0.99 max_torque (|qd| >= 0.99 max_speed) counts for the "
              "interval to the next sample; fractions are of the recorded span",
    "mass_balance": "relative_drift = (final - initial) / initial of mass_kg (particles + out of domain)",
}


# ---------------------------------------------------------------------------------------------- API
def summarize(run_dir, model=None) -> dict:
    """The run's summary from its folder's files. `model` (opera_taichi.model.build_model(scene)) gives the actuator
    limits, bulk density, tool meshes and struck volumes; without it (None) the density comes from the manifest and
    the actuator limits and fill factors are left out. Pure: writes nothing."""
    run_dir = Path(run_dir)
    manifest = _read_json(run_dir / "manifest.json") or {}
    summary: dict = {"run": _run_part(manifest)}
    density = _bulk_density(model, manifest)
    if density:
        summary["soil_bulk_density_kg_m3"] = density

    mass_cols = _columns(run_dir / "soil_mass.csv")
    wrench_cols = _columns(run_dir / "tool_wrench.csv")
    tools = _tools_part(model, mass_cols, wrench_cols, density)
    if tools:
        summary["tools"] = tools

    initial, final = _terrain(run_dir / "terrain_initial.npz"), _terrain(run_dir / "terrain_final.npz")
    if initial is not None and final is not None:
        terrain = _terrain_part(initial, final, grain_radius(model, manifest))
        if terrain is not None:
            summary["terrain"] = terrain

    joint_cols = _columns(run_dir / "joints.csv")
    limits = joint_limits(model) if model is not None else {}
    if joint_cols is not None and limits:
        actuators = _actuators_part(joint_cols, limits)
        if actuators:
            summary["actuators"] = actuators
            summary["actuators_span_s"] = float(joint_cols["t"][-1] - joint_cols["t"][0])

    mass = _mass_part(mass_cols, manifest)
    if mass is not None:
        summary["mass_balance"] = mass
    parts = {"soil_held": "tools", "force": "tools", "terrain": "terrain", "limits": "actuators",
             "mass_balance": "mass_balance"}
    summary["definitions"] = {k: v for k, v in DEFINITIONS.items() if parts[k] in summary}
    return summary


def write_summary(run_dir, model=None) -> dict:
    """summarize() and write it to <run_dir>/summary.json (atomically); returns the summary."""
    summary = summarize(run_dir, model)
    write_json(Path(run_dir) / SUMMARY_FILE, summary)
    return summary


def model_for_run(run_dir):
    """The Model of the scene a run folder was started with (its manifest's resolved scene), for summarising a
    finished run; None when the manifest is missing or its scene no longer builds."""
    manifest = _read_json(Path(run_dir) / "manifest.json")
    if not manifest or not isinstance(manifest.get("scene"), dict):
        return None
    try:
        from .model import build_model
        from .scene import Scene

        scene = Scene.model_validate(dict(manifest["scene"]),
                                     context={"base_dir": Path(run_dir).resolve(), "source": None})
        return build_model(scene)
    except Exception:  # a scene from an older version, a machine file since moved: summarise without limits
        return None


def read_summary(run_dir) -> dict | None:
    """<run_dir>/summary.json, or None when there is none (or it does not parse)."""
    return _read_json(Path(run_dir) / SUMMARY_FILE)


def _f(value, fmt: str, unit: str = "") -> str:
    return "n/a" if value is None else f"{value:{fmt}}{unit}"


def format_summary(summary: dict) -> str:
    """A few lines for the end of a run."""
    lines = []
    run = summary.get("run", {})
    head = f"Run {run.get('name') or '?'}: {run.get('status') or '?'}"
    if run.get("sim_time_s") is not None:
        head += f", {run['sim_time_s']:.2f} s simulated"
        if run.get("wall_time_s") is not None:
            head += f" in {run['wall_time_s']:.1f} s wall"
        if run.get("real_time_factor") is not None:
            head += f" (real-time factor {run['real_time_factor']:.3g})"
    if run.get("particles"):
        head += f", {run['particles']} particles"
    lines.append(head)

    tools = summary.get("tools", {})
    width = max([len(n) for n in tools] + [4])
    held = {n: e for n, e in tools.items() if "soil_held_kg" in e}
    if held:
        lines.append("Soil held at the end:")
        for name, e in held.items():
            text = f"  {name:<{width}}  {e['soil_held_kg']:.1f} kg"
            if "soil_held_m3" in e:
                text += f" = {e['soil_held_m3']:.3f} m3"
            if "fill_factor" in e:
                text += f", fill factor {e['fill_factor']:.2f} of {e['struck_volume_m3']:.2f} m3 struck"
                if not e.get("struck_volume_source", "").startswith("machine description"):
                    text += " (hull estimate)"
            lines.append(text)
    terrain = summary.get("terrain")
    if terrain:
        lines.append(f"Terrain (soil on the ground): dug {terrain['dug_m3']:.3f} m3, heaped {terrain['heaped_m3']:.3f} "
                     f"m3, deepest cut {terrain['max_cut_depth_m']:.2f} m")
    forced = {n: e for n, e in tools.items() if "peak_force_N" in e}
    if forced:
        lines.append(f"Soil force on the tools (mean over samples in contact, |F| > {CONTACT_FORCE_N:g} N):")
        for name, e in forced.items():
            wedge = ", cut with its soil wedge" if e.get("soil_wedge") else ""
            lines.append(f"  {name:<{width}}  peak {e['peak_force_N'] / 1e3:.1f} kN at t = "
                         f"{e['peak_force_time_s']:.2f} s, mean {e['mean_force_in_contact_N'] / 1e3:.1f} kN over "
                         f"{e['contact_time_s']:.2f} s in contact{wedge}")
    actuators = summary.get("actuators")
    if actuators:
        jw = max(len(j) for j in actuators)
        lines.append("Time at the actuator limits (share of the run):")
        for joint, a in actuators.items():
            lines.append(f"  {joint:<{jw}}  torque {a['at_torque_limit_s']:6.2f} s "
                         f"({a['at_torque_limit_fraction']:4.0%}), speed {a['at_speed_limit_s']:6.2f} s "
                         f"({a['at_speed_limit_fraction']:4.0%})")
    mass = summary.get("mass_balance")
    if mass:
        if "initial_kg" in mass:
            drift = mass.get("relative_drift")
            lines.append(f"Soil mass: {mass['initial_kg']:.1f} kg -> {mass['final_kg']:.1f} kg "
                         f"(drift {_f(drift, '.1e')}), out of domain {_f(mass.get('out_of_domain_kg'), '.1f', ' kg')}")
        else:
            lines.append(f"Soil mass at the end: {mass['final_kg']:.1f} kg, out of domain "
                         f"{_f(mass.get('out_of_domain_kg'), '.1f', ' kg')}")
    return "\n".join(lines)


__all__ = ["summarize", "write_summary", "read_summary", "format_summary", "joint_limits", "struck_volume",
           "interval_weights", "model_for_run", "SUMMARY_FILE"]
