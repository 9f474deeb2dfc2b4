"""`validate-physics resolution`: the soil at the grain sizes people run, against the same references.

The gate set (report.py) is calibrated at the default resolution (20 grains across the blade's cut); a user who digs
at 3-8 grains across wants to know what the forces are worth there. This study runs, at the coarse resolutions the
issue "accurate at the speed people use it" asks for:

- the plane-strain blade (a90 delta0, d 0.3 m) at 3, 4, 6, 8, 12 and 20 grains across the cut (the grains alone at
  20: the gate run of `validate-physics all`, taken from its folder when it is there): the convergence table and
  plot;
- the gates at operating resolution: a90 and a60 delta20 within 25% of the FEE at 4 grains across, 15% at 8; draft
  ~ d^2 within 10% at 4; the passive wall within 20% of Rankine at 4 grains across H (the mean of WALL_SEEDS
  packings: one packing's peak spreads by +-20% at 4 across);
- the critical height of a vertical cut, bisected, within 25% of Culmann's for dirt and kanto_loam at the coarse
  and default resolutions;
- the column run-outs (at a <= 1 the mean of the gate set's packings) and both heaps at their coarse
  resolutions, in the default gate set's bands, and the run-out's slope;
- the blade and wall runs with the soil wedge at the tool's cutting edge (`--param wedge=1`, tools.cutting_edge: the
  earthmoving equation's wedge, AGX Terrain's aggregate), the model that takes the resolution out of the forces and
  the one these gates hold to; the grains alone (the bulk-to-micro mapping by itself) run beside it, shown and not
  gated.

`validate-physics all` runs it after the gate set and puts its section in docs/validation.md; `validate-physics
resolution` runs it alone into docs/resolution.md. Each run keeps its folder under --out and `--resume` keeps the
runs that this code would make again (same parameters, mapping and solver version).
"""
from __future__ import annotations

import json
import math
from datetime import datetime
from pathlib import Path

from ..errors import DivergenceError, UserError
from .cases import check_case_folder, finished_metrics, run_case
from .report import PACKINGS, SAND, packing_lines, runout_plot, solver_label, warned_runs

CONVERGENCE_ACROSS = (3, 4, 6, 8, 12)
GATE_RUN_20 = Path("runs/validation-default/blade_a90_d0.3")   # the default gate run: 20 across
STUDY_FOLDER = "resolution"   # the study's runs, inside the gate set's folder: `all` and `resolution` share them
# the wall at 4 grains across H read 1.17, 0.77 and 0.99 x Rankine on seeds 0, 1 and 2 (2026-11-26): its gate takes
# the mean of three packings, as the run-out slope takes the means of its packings
WALL_SEEDS = (0, 1, 2)


MODELS = ("", "_wedge")  # label suffix: the grains alone, then the soil wedge at the cutting edge
GATED_MODEL = "_wedge"    # the model the blade and wall gates hold to; the grains alone are shown beside it
COARSE_CASES = ("column_collapse", "repose")


def study_set() -> list[tuple[str, str, dict, str]]:
    """(label, case, parameters, resolution) of every run of the study."""
    runs = []
    for model in MODELS:
        tool = {"wedge": 1.0} if model else {}
        a90 = {**SAND, "depth": 0.3, "rake_deg": 90.0, "delta_deg": 0.0, **tool}
        a60 = {**SAND, "depth": 0.3, "rake_deg": 60.0, "delta_deg": 20.0, **tool}
        runs += [(f"blade_a90_d0.3_n{n}{model}", "blade_cut", a90, str(n)) for n in CONVERGENCE_ACROSS]
        if model:  # the grains alone at 20 across are the default gate set's run
            runs += [(f"blade_a90_d0.3_n20{model}", "blade_cut", a90, "20")]
        runs += [(f"blade_a60_delta20_d0.3_n{n}{model}", "blade_cut", a60, str(n)) for n in (4, 8)]
        runs += [(f"blade_a90_d0.2_n4{model}", "blade_cut", {**a90, "depth": 0.2}, "4")]
        runs += [(f"passive_wall_H0.3_n4_seed{s}{model}", "passive_wall",
                  {**SAND, "height": 0.3, "seed": s, **tool}, "4") for s in WALL_SEEDS]
    runs += [(f"critical_height_{preset}_{res}", "critical_height", {"preset": preset}, res)
             for preset in ("dirt", "kanto_loam") for res in ("coarse", "default")]
    return runs + coarse_set()


def coarse_set() -> list[tuple[str, str, dict, str]]:
    """The default gate set's column collapses and heaps at their coarse resolution (no tool: one model for both)."""
    from .report import gate_set

    return [(f"{label}_coarse", case, params, "coarse") for label, case, params in gate_set()
            if case in COARSE_CASES]


def run_study(out_dir=None, report_path="docs/resolution.md", arch=None, quiet: bool = True, resume: bool = False,
              report_only: bool = False) -> tuple[Path, list[str]]:
    out = Path(out_dir) if out_dir is not None else GATE_RUN_20.parent / STUDY_FOLDER
    twenty = finished_metrics("blade_cut", {k: str(v) for k, v in {**SAND, "depth": 0.3, "rake_deg": 90.0,
                                                                     "delta_deg": 0.0}.items()}, "default",
                              GATE_RUN_20)
    results = collect(out, arch=arch, quiet=quiet, resume=resume, report_only=report_only, twenty=twenty)
    if report_only and not any(k != "blade_a90_d0.3_n20" for k in results):  # a report of nothing would replace one
        raise UserError(f"--report-only: no finished run of the study in {out}; nothing to report")
    command = f"opera-taichi validate-physics resolution --out {out}"
    gates = study_gates(results)
    path = write_study(results, gates, Path(report_path), command)
    return path, failed(gates)


def collect(out: Path, arch=None, quiet: bool = True, resume: bool = False, report_only: bool = False,
            twenty: dict | None = None) -> dict[str, dict]:
    """The study's runs by label, run into OUT/<label>/ unless finished there (resume, report_only); twenty: the
    20-across blade of the default gate set, for the convergence table's last row."""
    out = Path(out)
    check_case_folder(out)
    results: dict[str, dict] = {}
    for label, case, params, res in study_set():
        params = {k: str(v) for k, v in params.items()}
        m = finished_metrics(case, params, res, out / label) if resume or report_only else None
        if m is None and not report_only:
            try:
                m = run_case(case, params, res, out / label, arch=arch, quiet=quiet)
            except DivergenceError as exc:  # a failed gate, not the end of the study: the others still run
                m = {"case": case, "parameters": params, "resolution": res, "diverged": str(exc)}
                if not quiet:
                    print(f"{label}: {exc}")
        if m is not None:
            results[label] = m
    if twenty is not None:
        results["blade_a90_d0.3_n20"] = twenty
    return results


def failed(gates: list[dict]) -> list[str]:
    """The gated rows that failed (the grains alone are shown, not gated)."""
    return [g["label"] for g in gates if g["passed"] is False and g["gated"]]


def _ratio(m: dict) -> float:
    return m["measured"] / m["reference"]


def study_gates(results: dict[str, dict]) -> list[dict]:
    """The issue's gates at operating resolution, on the runs there are (a gate without its runs: not run)."""
    gates = []

    def gate(label, labels, value, reference, tolerance, text, gated=True):
        if not all(k in results for k in labels):
            gates.append(dict(label=label, measured=None, reference=reference, passed=None, gate=text, gated=gated))
            return
        if any("diverged" in results[k] for k in labels):
            gates.append(dict(label=label, measured=None, reference=reference, passed=False, gate=text,
                              diverged=True, gated=gated))
            return
        v = value()
        gates.append(dict(label=label, measured=v, reference=reference, relative_error=v / reference - 1,
                          passed=bool(abs(v / reference - 1) <= tolerance), gate=text, gated=gated))

    for model in sorted(MODELS, key=lambda m: m != GATED_MODEL):  # the gated model's rows first
        by = ", soil wedge" if model else ""
        gated = model == GATED_MODEL
        for n, tol in ((4, 0.25), (8, 0.15)):
            for name in ("a90", "a60_delta20"):
                key = f"blade_{name}_d0.3_n{n}{model}"
                gate(f"blade {name} d0.3, {n} grains across d{by}: draft / FEE", [key],
                     lambda k=key: _ratio(results[k]), 1.0, tol, f"within {tol:.0%}", gated)
        deep, shallow = f"blade_a90_d0.3_n4{model}", f"blade_a90_d0.2_n4{model}"
        gate(f"blade draft ~ d^2 (d 0.3 vs 0.2), 4 grains across d{by}", [deep, shallow],
             lambda a=deep, b=shallow: results[a]["measured"] / results[b]["measured"], (0.3 / 0.2) ** 2, 0.10,
             "within 10%", gated)
        walls = [f"passive_wall_H0.3_n4_seed{s}{model}" for s in WALL_SEEDS]
        gate(f"passive wall H0.3, 4 grains across H{by}: thrust / Rankine, mean of {len(walls)} packings", walls,
             lambda w=walls: sum(_ratio(results[k]) for k in w) / len(w), 1.0, 0.20, "within 20%", gated)
    for preset in ("dirt", "kanto_loam"):
        for res in ("coarse", "default"):
            key = f"critical_height_{preset}_{res}"
            gate(f"critical height, {preset}, {res}: / Culmann", [key], lambda k=key: _ratio(results[k]), 1.0,
                 0.25, "within 25%")
    gates += coarse_gates(results)
    return gates


def coarse_gates(results: dict[str, dict]) -> list[dict]:
    """Each coarse heap and column in its own band (the run's gate, as in the default gate set; a column at a <= 1 on
    the mean of its packings) and the run-out's log-log slope on the coarse columns."""
    from .cases import ACROSS
    from .report import derived_gates

    gates, columns, diverged = [], [], False
    for label, case, _, _ in coarse_set():
        m = results.get(label)
        name = f"{label.removesuffix('_coarse')}, coarse ({ACROSS[case]['coarse']} grains across)"
        packing = label.removesuffix("_coarse") in PACKINGS
        if m is None or "diverged" in m:
            diverged = diverged or (m is not None and case == "column_collapse")
            if not packing:  # a packing that is missing or diverged shows in its mean's gate
                gates.append(dict(label=name, measured=None, reference=None, passed=None if m is None else False,
                                  gate="its case's band", gated=True, diverged=m is not None))
            continue
        if case == "column_collapse":
            columns.append({**m, "label": label.removesuffix("_coarse")})
        if not packing:
            gates.append(dict(label=f"{name}: {m['metric']}", measured=m["measured"], reference=m["reference"],
                              relative_error=m["relative_error"], passed=bool(m["passed"]), gate=m["gate"],
                              gated=True))
    for row in derived_gates(columns):
        if row["label"].startswith(("column run-out", "run-out")):
            if diverged:
                row.update(measured=None, passed=False, diverged=True)
            gates.append({**row, "label": row["label"] + f", coarse ({ACROSS['column_collapse']['coarse']} grains "
                                                           "across)", "gated": True})
    return gates


def write_study(results: dict[str, dict], gates: list[dict], report_path: Path, command: str) -> Path:
    """docs/resolution.md: the study alone (`validate-physics resolution`)."""
    report_path = Path(report_path)
    plot_dir = report_path.parent / report_path.stem
    plot_dir.mkdir(parents=True, exist_ok=True)
    lines = ["# The soil at operating resolution", "",
             f"Generated {datetime.now().isoformat(timespec='seconds')}, {solver_label()}. Regenerate with:", "",
             "```", command, "```", "",
             "The same section closes docs/validation.md, which `validate-physics all` writes with the gate set.", ""]
    lines += study_section(results, gates, plot_dir, level=2)
    report_path.write_text("\n".join(lines) + "\n")
    (plot_dir / "metrics.json").write_text(json.dumps(
        {"runs": {k: {kk: vv for kk, vv in m.items() if kk != "extra"} for k, m in results.items()},
         "gates": gates}, indent=1, default=float) + "\n")
    return report_path


def _verdict(g: dict) -> str:
    if g["measured"] is None:
        verdict = "FAIL" if g.get("diverged") else "not run"
    else:
        verdict = "pass" if g["passed"] else "FAIL"
    return verdict if g["gated"] else f"{verdict.lower()}, not gated"


def study_section(results: dict[str, dict], gates: list[dict], plot_dir: Path, level: int) -> list[str]:
    """The study's tables and plot as markdown lines, its headings at `level` (# count); the plot goes in plot_dir."""
    h = "#" * level
    lines = ["The default gate set is calibrated at 20 grains across the blade's cut; the main job digs at about 3 "
             "(8 cm grains, a 0.5 m cut). This study runs the plane-strain blade, the wall, the vertical cut, the "
             "column collapses and the heaps at the grain sizes people run and compares them with the same "
             "references: the earthmoving equation (FEE), Rankine, Culmann, Lube / Lajeunesse and the repose "
             "angles. Its blade and wall gates hold the soil wedge at the tool's cutting edge (a tool's "
             "`cutting_edge`, a machine's `soil_wedge`; `validate-physics blade_cut|passive_wall --param wedge=1`), "
             "the model that takes the grain size out of the tool's force; the grains alone (the bulk-to-micro "
             "mapping by itself) run beside it, shown and not gated. The heaps, the columns and the cuts have no "
             "tool: one model for both.", "",
             f"{h} Blade draft against grains across the cut", "",
             "Plane strain (a slab between smooth symmetry walls), a90 delta0, d 0.3 m, sand phi 35 deg, draft "
             "averaged over d to 3d of travel, against the FEE's 2,769 N/m.", "",
             "| grains across d | particles | grains alone: draft N/m | draft / FEE | wall time s | soil wedge: "
             "draft N/m | draft / FEE | wall time s |", "|---|---|---|---|---|---|---|---|"]
    conv, conv_wedge = [], []
    for n in (*CONVERGENCE_ACROSS, 20):
        row = f"| {n} |"
        for model, series in zip(MODELS, (conv, conv_wedge)):
            m = results.get(f"blade_a90_d0.3_n{n}{model}")
            if m is None or "diverged" in m:
                row += (" - |" if not model else "") + (" not run" if m is None else " diverged") + " | - | - |"
                continue
            series.append((n, _ratio(m)))
            row += (f" {m['particles']:,} |" if not model else "") + \
                f" {m['measured']:.0f} | {_ratio(m):.3f} | {m['wall_time_s']:.0f} |"
        lines.append(row)
    if len(conv) >= 3:
        # draft = FEE at depth d + k D (a layer k grain diameters thick dragged under the edge): ratio = (1 + k/n)^2
        ks = [n * (math.sqrt(r) - 1.0) for n, r in conv]
        lines += ["", "Read as a layer under the edge (draft = the FEE's at depth d + k D, i.e. (1 + k/n)^2): k = "
                  + ", ".join(f"{k:.2f}" for k in ks) + " grain diameters at "
                  + ", ".join(str(n) for n, _ in conv) + " across."]
    lines += ["", f"{h} Gates at operating resolution", "", "| gate | measured | reference | error | pass |",
              "|---|---|---|---|---|"]
    for g in gates:
        reference = "-" if g["reference"] is None else f"{g['reference']:.3f}"
        if g["measured"] is None:
            state = "diverged" if g.get("diverged") else "not run"
            lines.append(f"| {g['label']} ({g['gate']}) | {state} | {reference} | - | {_verdict(g)} |")
            continue
        lines.append(f"| {g['label']} ({g['gate']}) | {g['measured']:.3f} | {reference} | "
                     f"{g['relative_error']:+.1%} | {_verdict(g)} |")
    walls = [(k, m) for k, m in results.items() if k.startswith("passive_wall") and "diverged" not in m]
    if walls:
        lines += ["", "Passive wall at 4 grains across H, peak thrust up to 0.2 H over Rankine's 2,769 N/m, by packing "
                      "(the bed poured with another seed):", "", "| model | seed | particles | thrust N/m | / Rankine |",
                  "|---|---|---|---|---|"]
        lines += [f"| {'soil wedge' if k.endswith('_wedge') else 'grains alone'} | {float(m['parameters'].get('seed', 0)):g} "
                  f"| {m['particles']:,} | {m['measured']:.0f} | {_ratio(m):.3f} |" for k, m in walls]
    crit = [(k, m) for k, m in results.items() if k.startswith("critical_height")]
    if crit:
        lines += ["", "Critical heights (bisected between a cut that stands 5 s and one that falls; the bracket is "
                      "the last pair):", "", "| soil | resolution | grains across Hc | critical height m | bracket m | "
                      "Culmann m | ratio |", "|---|---|---|---|---|---|---|"]
        for k, m in crit:
            lo, hi = m["bracket_m"]
            lines.append(f"| {m['parameters']['preset']} | {m['resolution']} | {m['n_across']} | {m['measured']:.3f} | "
                         f"{lo:.3f}-{hi:.3f} | {m['reference']:.3f} | {_ratio(m):.3f} |")
    lines += packing_lines([{**m, "label": k.removesuffix("_coarse")} for k, m in results.items()
                            if "diverged" not in m and k.removesuffix("_coarse") in PACKINGS])
    lines += warned_runs(list(results.items()))
    plot = _plot(conv, conv_wedge, plot_dir)
    if plot is not None:
        lines += ["", f"![draft over FEE against grains across the cut]({plot_dir.name}/{plot.name})"]
    columns = [{**m, "label": k.removesuffix("_coarse")} for k, m in results.items()
               if k.startswith("column_") and k.endswith("_coarse") and "diverged" not in m]
    if columns:
        from .cases import ACROSS

        across = ACROSS["column_collapse"]["coarse"]
        plot = runout_plot(columns, plot_dir / "runout_coarse.png",
                           f"Column collapse, coarse ({across} grains across L0)")
        lines += ["", f"![run-out vs aspect ratio, coarse]({plot_dir.name}/{plot.name})"]
    return lines


def _plot(conv: list[tuple[int, float]], conv_wedge: list[tuple[int, float]], plot_dir: Path):
    if not conv and not conv_wedge:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.0, 4.0))
    ns, ratios = [], []
    for series, style, label in ((conv, "o-", "grains alone (the mapping)"),
                                 (conv_wedge, "s-", "soil wedge at the edge (--param wedge=1)")):
        if series:
            x, y = zip(*series)
            ax.plot(x, y, style, label=label)
            ns += x
            ratios += y
    ns = sorted(set(ns))
    ax.axhline(1.0, color="k", lw=0.8, label="earthmoving equation")
    ax.fill_between([3.5, 4.5], 0.75, 1.25, color="tab:green", alpha=0.15, label="gate at 4 (25%)")
    ax.fill_between([7.5, 8.5], 0.85, 1.15, color="tab:olive", alpha=0.15, label="gate at 8 (15%)")
    ax.set_xlabel("grains across the cut d (d / 2R)")
    ax.set_ylabel("draft / FEE (plane strain, a90, d 0.3 m)")
    ax.set_xscale("log")
    ax.set_xticks(list(ns))
    ax.set_xticklabels([str(n) for n in ns])
    ax.set_ylim(0.0, max(2.6, max(ratios) + 0.1))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = plot_dir / "blade_convergence.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
