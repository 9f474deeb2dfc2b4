"""Figures of a comparison (as PWRI 2023's Fig. 5 and 6) and of a study (metric against parameter)."""
from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import BoundaryNorm, ListedColormap, Normalize, TwoSlopeNorm  # noqa: E402

from ..plots import _save, _side_axis  # noqa: E402


def _extent(x, y):
    dx = x[1] - x[0] if len(x) > 1 else 1.0
    dy = y[1] - y[0] if len(y) > 1 else 1.0
    return [x[0] - dx / 2, x[-1] + dx / 2, y[0] - dy / 2, y[-1] + dy / 2]


def _crop(arrays) -> tuple[slice, slice]:
    """The dig area's bounding box with a margin (the maps show the dig, not the whole domain)."""
    mask = arrays["mask"]
    if not mask.any():
        return slice(None), slice(None)
    ii, jj = np.nonzero(mask)
    pad = max(4, int(0.15 * max(np.ptp(ii), np.ptp(jj))))
    return (slice(max(0, ii.min() - pad), ii.max() + pad + 1), slice(max(0, jj.min() - pad), jj.max() + pad + 1))


def plot_terrain_comparison(arrays: dict, png_path: Path) -> None:
    """Elevation of the run and of the reference after the dig on one colour scale, and run minus reference on a
    symmetric scale; the dig line dashed. Without a reference: initial, final and their change."""
    sx, sy = _crop(arrays)
    x, y = arrays["x"][sx], arrays["y"][sy]
    z0, z1 = arrays["z0"][sx, sy], arrays["z1"][sx, sy]
    ref1 = arrays["ref1"][sx, sy] if arrays.get("ref1") is not None else None
    label = arrays.get("label") or "reference"
    extent = _extent(x, y)
    if ref1 is not None:
        panels = [(z1, "run after the dig: z (m)"), (ref1, f"{label} after the dig: z (m)")]
        diff, diff_title = z1 - ref1, "run - reference (m): red the run is higher"
    else:
        panels = [(z0, "run before: z (m)"), (z1, "run after: z (m)")]
        diff, diff_title = z1 - z0, "after - before (m): blue dug, red heaped"
    both = np.concatenate([p[0][np.isfinite(p[0])] for p in panels])
    lo, hi = (float(both.min()), float(both.max())) if both.size else (-1.0, 1.0)
    aspect = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9)
    fig, axes = plt.subplots(1, 3, figsize=(16, min(6.0, 4.6 * aspect) + 1.4))
    for ax, (z, title) in zip(axes[:2], panels):
        im = ax.imshow(np.ma.masked_invalid(z).T, origin="lower", extent=extent, vmin=lo, vmax=hi, cmap="viridis",
                       aspect="equal")
        ax.set_title(title, fontsize=10)
        fig.colorbar(im, cax=_side_axis(ax), label="z (m)")
    finite = np.abs(diff[np.isfinite(diff)])
    lim = max(float(np.percentile(finite, 99)) if finite.size else 0.1, 0.02)
    im = axes[2].imshow(np.ma.masked_invalid(diff).T, origin="lower", extent=extent,
                        norm=TwoSlopeNorm(vmin=-lim, vcenter=0.0, vmax=lim), cmap="RdBu_r", aspect="equal")
    axes[2].set_title(diff_title, fontsize=10)
    fig.colorbar(im, cax=_side_axis(axes[2]), extend="both", label="dz (m)")
    prof = arrays.get("profile")
    for ax in axes:
        if prof is not None:
            ax.plot(prof["x_m"], prof["y_m"], "k--", lw=1.0)
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    fig.suptitle("Terrain after the dig (grey: no data; dashed: the dig line)", fontsize=11)
    fig.tight_layout()
    _save(fig, png_path)


def plot_profile(arrays: dict, png_path: Path) -> None:
    prof = arrays["profile"]
    s = prof["s_m"]
    fig, ax = plt.subplots(figsize=(10, 4))
    ax.plot(s, prof["initial_z_m"], color="tab:brown", ls="--", lw=1.3, label="run before")
    if "reference_initial_z_m" in prof:
        ax.plot(s, prof["reference_initial_z_m"], color="0.5", ls=":", lw=1.3, label="reference before")
    ax.plot(s, prof["run_z_m"], color="tab:blue", lw=1.8, label="run after")
    if "reference_z_m" in prof:
        ax.plot(s, prof["reference_z_m"], color="black", lw=1.8, label=f"{arrays.get('label') or 'reference'} after")
    # s = 0 is the line's origin, the centre of the cut (not its first sample)
    o = arrays["dig_line_origin"]
    ax.set_title(f"Profile along the dig line through the centre of the cut at x {o[0]:.2f}, y {o[1]:.2f} m "
                 f"(s < 0: toward the machine)", fontsize=10)
    ax.set_xlabel("s along the dig line from the centre of the cut (m)")
    ax.set_ylabel("z (m)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, png_path)


def plot_joint_comparison(arrays: dict, png_path: Path) -> None:
    """Joint angles of the run and the reference overlaid, one panel per joint."""
    joints = list(arrays["joints"])
    t = arrays["t"]
    fig, axes = plt.subplots(len(joints), 1, figsize=(10, 2.2 * len(joints) + 0.6), sharex=True, squeeze=False)
    for ax, j in zip(axes[:, 0], joints):
        a, b = arrays["joints"][j]
        ax.plot(t, np.degrees(b), color="black", lw=1.6, label=arrays.get("label") or "reference")
        ax.plot(t, np.degrees(a), color="tab:blue", lw=1.4, ls="--", label="run")
        ax.set_ylabel(f"{j} (deg)", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8, loc="best")
    axes[-1, 0].set_xlabel("t (s)")
    fig.suptitle("Joint angles: run against reference", fontsize=11)
    fig.tight_layout()
    _save(fig, png_path)


def plot_study(rows: list[dict], parameters: list[str], metrics: list[str], png_path: Path) -> None:
    """Each metric (rows) against each parameter (columns); failed points marked on the axis in red. A parameter
    whose values are not all numbers (a preset name, a flag, a vector) is plotted as categories, in study order. With
    several parameters, a column's points are coloured by the next parameter (the first's column by the second), its
    scale beside the column."""
    nr, nc = max(1, len(metrics)), max(1, len(parameters))
    # constrained layout keeps the title clear of the panels (tight_layout ignores a suptitle)
    fig, axes = plt.subplots(nr, nc, figsize=(3.6 * nc + 0.8 + 1.0 * (len(parameters) > 1), 2.8 * nr + 0.6),
                             squeeze=False, layout="constrained")
    done = np.array([row.get("status") == "done" for row in rows], bool)
    columns = [_axis_values([row.get(p) for row in rows]) for p in parameters]
    for c, p in enumerate(parameters):
        px, labels = columns[c]
        # points at one x differ in the other parameters: without a colour, the second one's values were nowhere in
        # the first one's column (a grid's points at one x were indistinguishable)
        other = parameters[(c + 1) % nc] if len(parameters) > 1 else None
        shade = _colour_scale(*columns[(c + 1) % nc]) if other else None
        for r, m in enumerate(metrics):
            ax = axes[r, c]
            my = np.array([_num(row.get(m)) for row in rows])
            ok = done & np.isfinite(px) & np.isfinite(my)
            if shade is None:
                ax.plot(px[ok], my[ok], "o", color="tab:blue", ms=5)
            else:
                ax.scatter(px[ok], my[ok], c=shade[0][ok], cmap=shade[1], norm=shade[2], s=25, zorder=2)
            failed = ~done & np.isfinite(px)
            if failed.any():
                # on the x axis (axes fraction 0), not at a metric value: drawn at the lowest finished point it read
                # as a measurement; this transform leaves the y limits to the finished points
                ax.plot(px[failed], np.zeros(failed.sum()), "x", color="tab:red", ms=7, label="failed",
                        transform=ax.get_xaxis_transform(), clip_on=False)
                ax.legend(fontsize=7)
            if labels is not None:
                ax.set_xticks(range(len(labels)), labels, fontsize=8, rotation=30 if len(labels) > 4 else 0)
                ax.set_xlim(-0.5, len(labels) - 0.5)
            ax.grid(alpha=0.3)
            if r == nr - 1:
                ax.set_xlabel(p, fontsize=8)
            if c == 0:
                ax.set_ylabel(m, fontsize=8)
        if shade is not None:
            bar = fig.colorbar(matplotlib.cm.ScalarMappable(norm=shade[2], cmap=shade[1]), ax=axes[:, c],
                               shrink=0.9, aspect=30)
            bar.set_label(f"colour: {other}", fontsize=8)
            if shade[3] is not None:
                bar.set_ticks(range(len(shade[3])), labels=shade[3], fontsize=7)
    fig.suptitle(f"{len(rows)} points, {int(done.sum())} done", fontsize=10)
    _save(fig, png_path)


def _colour_scale(values: np.ndarray, labels: list[str] | None):
    """(values, colormap, norm, tick labels or None) to colour points by a parameter: a continuous scale for numbers,
    one colour per category otherwise; a point without a value is grey."""
    if labels is not None:
        n = len(labels)
        # tab10's first n colours (resampling it would spread them over all ten)
        cmap = ListedColormap(matplotlib.colormaps["tab10"].colors[:n]) if n <= 10 else \
            matplotlib.colormaps["viridis"].resampled(n)
        return values, cmap.with_extremes(bad="0.5"), BoundaryNorm(np.arange(n + 1) - 0.5, n), labels
    finite = values[np.isfinite(values)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    return values, matplotlib.colormaps["viridis"].with_extremes(bad="0.5"), Normalize(lo, hi), None


def _axis_values(values: list) -> tuple[np.ndarray, list[str] | None]:
    """(x of each value, None) for numbers; (index of each value's category, category labels) otherwise."""
    if all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)) for v in values):
        return np.array([_num(v) for v in values]), None
    labels = list(dict.fromkeys("" if v is None else str(v) for v in values))
    return np.array([labels.index("" if v is None else str(v)) for v in values], float), labels


def plot_calibration(trials: list[dict], parameters: list[str], best: dict, png_path: Path) -> None:
    """Loss of each trial against each calibrated parameter; the best marked."""
    fig, axes = plt.subplots(1, max(1, len(parameters)), figsize=(4.5 * max(1, len(parameters)), 3.6), squeeze=False)
    for ax, p in zip(axes[0], parameters):
        xs = np.array([_num(t.get(p)) for t in trials])
        ls = np.array([_num(t.get("loss")) for t in trials])
        ok = np.isfinite(xs) & np.isfinite(ls)
        ax.plot(xs[ok], ls[ok], "o", color="tab:blue")
        if best and p in best:
            ax.axvline(best[p], color="tab:green", ls="--", label=f"best {best[p]:.4g}")
            ax.legend(fontsize=8)
        ax.set_xlabel(p, fontsize=8)
        ax.set_ylabel("loss")
        ax.set_yscale("log" if ok.any() and np.all(ls[ok] > 0) else "linear")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(fig, png_path)


def _num(v) -> float:
    try:
        v = float(v)
    except (TypeError, ValueError):
        return math.nan
    return v
