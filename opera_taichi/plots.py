"""PNG plots for the run folder: what a person would rather look at than read.

plot_joints      joints.png       angle, speed and effort of each joint; shaded where the actuator is at a limit
plot_tool_wrench tool_wrench.png  |F| and fx, fy, fz of the soil on each tool
plot_soil_mass   soil_mass.png    soil held in each tool; the total's change and the soil lost out of the domain
plot_terrain     terrain.png      ground-only heightmaps, their difference on a fixed scale, the carried soil, and a
                                  side profile along the dig line
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import TwoSlopeNorm  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from .recorders import read_csv_columns  # noqa: E402

LIMIT_RATIO = 0.99           # at a limit: within 1 % of it (as summary.py)
TORQUE_SHADE = dict(color="tab:red", alpha=0.18, lw=0)
SPEED_SHADE = dict(color="tab:orange", alpha=0.25, lw=0)
DPI = 110


def _shade(ax, t, mask, style) -> None:
    """Shade the time spans where mask holds (each sample stands for the interval to the next one)."""
    if not np.any(mask):
        return
    mask = np.asarray(mask, bool)
    edges = np.flatnonzero(np.diff(np.concatenate([[False], mask, [False]]).astype(int)))
    t_end = np.append(t[1:], t[-1])
    for start, stop in zip(edges[::2], edges[1::2]):
        ax.axvspan(t[start], t_end[stop - 1] if t_end[stop - 1] > t[start] else t[start] + 1e-3, **style)


def _save(fig, png_path) -> None:
    fig.savefig(png_path, dpi=DPI)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------- joints
def plot_joints(csv_path: Path, joints: list[str], png_path: Path,
                limits: dict[str, tuple[float, float]] | None = None) -> None:
    """One row per joint (a joints.csv column prefix): angle commanded vs actual (deg), speed (deg/s) and effort
    (kN m). `limits` = {prefix: (max_speed rad/s, max_torque N m)} draws the limits and shades the time spent at the
    torque limit (red) and at the speed limit (orange) in every panel of the row."""
    cols = read_csv_columns(csv_path)
    t = cols["t"]
    limits = limits or {}
    n = len(joints)
    fig, axes = plt.subplots(n, 3, figsize=(15, 2.3 * n + 0.9), sharex=True, squeeze=False)
    for row, joint in zip(axes, joints):
        ax_q, ax_v, ax_e = row
        q, qd, effort = cols[f"{joint}.q"], cols[f"{joint}.qd"], cols[f"{joint}.effort"]
        q_cmd = cols.get(f"{joint}.q_cmd")
        if q_cmd is not None and np.any(np.isfinite(q_cmd)):
            ax_q.plot(t, np.degrees(q_cmd), "--", color="tab:gray", lw=1.2, label="commanded")
        ax_q.plot(t, np.degrees(q), color="tab:blue", lw=1.4, label="actual")
        ax_q.set_ylabel(f"{joint}\nangle (deg)")
        qd_cmd = cols.get(f"{joint}.qd_cmd")
        if qd_cmd is not None:
            ax_v.plot(t, np.degrees(qd_cmd), "--", color="tab:gray", lw=1.0, label="speed command")
        ax_v.plot(t, np.degrees(qd), color="tab:green", lw=1.3, label="speed")
        ax_v.set_ylabel("speed (deg/s)")
        ax_e.plot(t, effort / 1e3, color="tab:purple", lw=1.3, label="effort")
        ax_e.set_ylabel("effort (kN m)")
        if joint in limits:
            max_speed, max_torque = limits[joint]
            at_torque = np.abs(effort) >= LIMIT_RATIO * max_torque
            at_speed = np.abs(qd) >= LIMIT_RATIO * max_speed
            for ax in row:
                _shade(ax, t, at_torque, TORQUE_SHADE)
                _shade(ax, t, at_speed, SPEED_SHADE)
            for sign in (-1, 1):
                ax_v.axhline(sign * np.degrees(max_speed), color="tab:orange", ls=":", lw=1.2)
                ax_e.axhline(sign * max_torque / 1e3, color="tab:red", ls=":", lw=1.2)
            w = np.zeros_like(t)
            w[:-1] = np.diff(t)
            span = float(t[-1] - t[0]) or 1.0
            tt, ts = float(w[at_torque].sum()), float(w[at_speed].sum())
            ax_e.set_title(f"at torque limit {tt:.2f} s ({tt / span:.0%}), at speed limit {ts:.2f} s "
                           f"({ts / span:.0%})", fontsize=8, loc="right")
            # keep the curve readable: show the limits only when the joint comes within reach of them
            peak_e, peak_v = float(np.abs(effort).max()), float(np.abs(qd).max())
            if peak_e < 0.4 * max_torque:
                ax_e.set_ylim(*_padded(effort / 1e3))
            if peak_v < 0.4 * max_speed:
                ax_v.set_ylim(*_padded(np.degrees(qd)))
        for ax in row:
            ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("simulated time (s)")
    handles = [plt.Line2D([], [], ls="--", color="tab:gray", label="commanded"),
               plt.Line2D([], [], color="tab:blue", label="angle"),
               plt.Line2D([], [], color="tab:green", label="speed"),
               plt.Line2D([], [], color="tab:purple", label="effort")]
    if limits:
        handles += [plt.Line2D([], [], ls=":", color="tab:red", label="torque limit"),
                    plt.Line2D([], [], ls=":", color="tab:orange", label="speed limit"),
                    Patch(label=f"at torque limit (|effort| >= {LIMIT_RATIO:.0%})", **TORQUE_SHADE),
                    Patch(label=f"at speed limit (|speed| >= {LIMIT_RATIO:.0%})", **SPEED_SHADE)]
    fig.legend(handles=handles, loc="upper center", ncol=len(handles), fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, 1.0 - 0.25 / fig.get_figheight()))
    fig.suptitle("Joints: angle, speed and effort" + (" (shaded: actuator at its limit)" if limits else ""),
                 y=1.0 - 0.05 / fig.get_figheight(), va="top")
    fig.tight_layout(rect=(0, 0, 1, 1.0 - 0.45 / fig.get_figheight()))
    _save(fig, png_path)


def _padded(values) -> tuple[float, float]:
    lo, hi = float(np.nanmin(values)), float(np.nanmax(values))
    pad = max(0.08 * (hi - lo), 1e-3 * max(abs(lo), abs(hi)), 1e-6)
    return lo - pad, hi + pad


# ---------------------------------------------------------------------------------------------- wrench
def plot_tool_wrench(csv_path: Path, png_path: Path) -> None:
    """One panel per tool: |F| (bold, peak marked) and fx, fy, fz of the soil on the tool, world frame, kN."""
    cols = read_csv_columns(csv_path)
    tools = list(dict.fromkeys(cols.get("tool", [])))
    if not tools:  # a soil scene without tools has nothing to plot
        return
    fig, axes = plt.subplots(len(tools), 1, figsize=(10, 3.2 * len(tools) + 0.6), sharex=True, squeeze=False)
    tool_col = np.asarray(cols["tool"])
    for ax, tool in zip(axes[:, 0], tools):
        sel = tool_col == tool
        t = cols["t"][sel]
        comps = {c: cols[c][sel] / 1e3 for c in ("fx", "fy", "fz")}
        mag = np.sqrt(sum(v ** 2 for v in comps.values()))
        ax.plot(t, mag, color="black", lw=2.0, label="|F|")
        for (c, v), colour in zip(comps.items(), ("tab:red", "tab:green", "tab:blue")):
            ax.plot(t, v, color=colour, lw=1.0, alpha=0.85, label=c)
        i = int(np.argmax(mag))
        ax.plot(t[i], mag[i], "o", color="black", ms=6)
        late = t[i] > 0.5 * (t[0] + t[-1])  # the label reads away from the panel's right edge and the legend there
        ax.annotate(f"peak |F| {mag[i]:.1f} kN at {t[i]:.2f} s", (t[i], mag[i]), xytext=(-10 if late else 10, -2),
                    textcoords="offset points", fontsize=8, va="top", ha="right" if late else "left",
                    bbox=dict(facecolor="white", alpha=0.85, lw=0))
        ax.axhline(0.0, color="gray", lw=0.8)
        ax.set_ylabel(f"{tool}\nforce (kN)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8, frameon=False)
    axes[-1, 0].set_xlabel("simulated time (s)")
    fig.suptitle("Force of the soil on each tool (world frame; z up)")
    fig.tight_layout()
    _save(fig, png_path)


# ---------------------------------------------------------------------------------------------- soil mass
def plot_soil_mass(csv_path: Path, png_path: Path, density: float | None = None) -> None:
    """Top: soil inside each tool's hull (kg; m3 on the right axis at the bulk `density` kg/m3 when given).
    Bottom: the total's change since the start and the soil that left the domain (kg)."""
    cols = read_csv_columns(csv_path)
    t = cols["t"]
    tools = [k for k in cols if k.startswith("in_") and k.endswith("_kg")]
    n = 2 if tools else 1
    fig, axes = plt.subplots(n, 1, figsize=(9, 2.9 * n + 0.4), sharex=True, squeeze=False,
                             gridspec_kw={"height_ratios": [2, 1][:n]})
    if tools:
        ax = axes[0, 0]
        for name in tools:
            ax.plot(t, cols[name], lw=1.8, label=f"{name[3:-3]}: {cols[name][-1]:.1f} kg at the end")
        ax.set_ylabel("soil in tool (kg)")
        ax.set_ylim(bottom=0.0, top=max(1.0, 1.1 * max(float(np.max(cols[k])) for k in tools)))
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
        ax.set_title("Soil held in each tool (grain centres inside its convex hull)", fontsize=10)
        if density:
            sec = ax.secondary_yaxis("right", functions=(lambda m: m / density, lambda v: v * density))
            sec.set_ylabel(f"m3 at {density:g} kg/m3")
    ax = axes[-1, 0]
    if "mass_kg" in cols:
        total = cols["mass_kg"]
        change = total - total[0]
        ax.plot(t, change, color="black", lw=1.5, label="total - initial")
        drift = float(change[-1] / total[0]) if total[0] else float("nan")
        ax.set_title(f"Soil mass balance: {total[0]:.1f} kg at the start, {total[-1]:.1f} kg at the end "
                     f"(relative drift {drift:.1e})", fontsize=10)
    if "out_of_domain_kg" in cols:
        ood = cols["out_of_domain_kg"]
        ax.fill_between(t, 0.0, ood, color="tab:red", alpha=0.3, step="post",
                        label=f"out of domain ({ood[-1]:.1f} kg at the end)")
    lo, hi = ax.get_ylim()
    if hi - lo < 1.0:  # all zero: show a scale of +-1 kg rather than a line on a meaningless axis
        ax.set_ylim(-1.0, 1.0)
    ax.set_ylabel("kg")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_xlabel("simulated time (s)")
    fig.tight_layout()
    _save(fig, png_path)


# ---------------------------------------------------------------------------------------------- terrain
def _side_axis(ax):
    """A colour bar axis as tall as the (aspect-equal) map beside it."""
    from mpl_toolkits.axes_grid1 import make_axes_locatable

    return make_axes_locatable(ax).append_axes("right", size="4%", pad=0.08)


def plot_terrain(initial: dict, final: dict, png_path: Path, *, dz_limit: float = 1.0,
                 profile_y: float | None = None, carried_threshold: float = 0.05) -> None:
    """Maps of the ground-only heightmap `z` at the start and at the end and of their difference on a fixed
    +-dz_limit (m) scale (blue dug, red heaped); hatched where the final `z_all` (every grain) stands more than
    carried_threshold (m) above `z` (soil carried by a tool); and a side profile along x at profile_y (m; default
    the row of the map that lost the most soil: the trench's axis)."""
    x, y = np.asarray(initial["x"], float), np.asarray(initial["y"], float)
    z0, z1 = np.asarray(initial["z"], float), np.asarray(final["z"], float)
    z_all = np.asarray(final["z_all"], float) if "z_all" in final else None
    dz = z1 - z0
    dx = x[1] - x[0] if len(x) > 1 else 1.0
    dy = y[1] - y[0] if len(y) > 1 else 1.0
    extent = [x[0] - dx / 2, x[-1] + dx / 2, y[0] - dy / 2, y[-1] + dy / 2]
    if profile_y is None:
        # the row that lost the most soil: the trench's axis (a single deepest cell can be a gap at a pit wall)
        dug_per_row = np.clip(-dz, 0.0, None).sum(axis=0)
        j = int(np.argmax(dug_per_row)) if dug_per_row.max() > 0 else len(y) // 2
        how = "most soil dug" if dug_per_row.max() > 0 else "middle of the domain"
    else:
        j = int(np.argmin(np.abs(y - profile_y)))
        how = "given"
    carried = None
    if z_all is not None and z_all.shape == z1.shape:
        carried = (z_all - z1) > carried_threshold

    aspect = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9)
    map_h = min(4.5, 4.3 * aspect)          # inches of a map 4.3 in wide
    fig = plt.figure(figsize=(16, map_h + 4.6))
    grid = fig.add_gridspec(2, 3, height_ratios=[map_h + 0.9, 3.7])
    maps = [fig.add_subplot(grid[0, k]) for k in range(3)]
    prof = fig.add_subplot(grid[1, :])
    lo, hi = float(min(z0.min(), z1.min())), float(max(z0.max(), z1.max()))
    for ax, z, title in ((maps[0], z0, "initial ground z (m)"), (maps[1], z1, "final ground z (m)")):
        im = ax.imshow(z.T, origin="lower", extent=extent, vmin=lo, vmax=hi, cmap="terrain", aspect="equal")
        ax.set_title(title, fontsize=10)
        fig.colorbar(im, cax=_side_axis(ax), label="z (m)")
    norm = TwoSlopeNorm(vmin=-dz_limit, vcenter=0.0, vmax=dz_limit)
    im = maps[2].imshow(dz.T, origin="lower", extent=extent, norm=norm, cmap="RdBu_r", aspect="equal")
    maps[2].set_title(f"final - initial (m): blue dug, red heaped (scale +-{dz_limit:g} m)", fontsize=10)
    fig.colorbar(im, cax=_side_axis(maps[2]), extend="both", label="dz (m)")
    handles = [plt.Line2D([], [], color="black", ls="--", lw=1.0, label=f"profile y = {y[j]:.2f} m ({how})")]
    if carried is not None and np.any(carried):
        for ax in maps[1:]:
            ax.contourf(x, y, carried.T.astype(float), levels=[0.5, 1.5], colors="none", hatches=["////"])
            ax.contour(x, y, carried.T.astype(float), levels=[0.5], colors="black", linewidths=0.9)
        handles.append(Patch(facecolor="none", edgecolor="black", hatch="////",
                             label=f"soil carried by a tool (z_all > z + {carried_threshold:g} m)"))
    for ax in maps:
        ax.axhline(y[j], color="black", ls="--", lw=1.0)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    fig.legend(handles=handles, loc="upper center", ncol=len(handles), fontsize=9, frameon=False)

    prof.plot(x, z0[:, j], color="tab:brown", lw=1.5, ls="--", label="initial z")
    prof.plot(x, z1[:, j], color="black", lw=1.8, label="final z (soil on the ground)")
    prof.fill_between(x, z0[:, j], z1[:, j], where=z1[:, j] < z0[:, j], color="tab:blue", alpha=0.35, lw=0,
                      interpolate=True, label="dug")
    prof.fill_between(x, z0[:, j], z1[:, j], where=z1[:, j] > z0[:, j], color="tab:red", alpha=0.35, lw=0,
                      interpolate=True, label="heaped")
    if carried is not None and np.any(carried[:, j]):
        za = np.where(carried[:, j], z_all[:, j], np.nan)
        prof.plot(x, za, color="tab:purple", lw=2.0, label="top of the soil carried by a tool (z_all)")
    cell = abs(dx * dy)
    prof.set_title(f"Side profile along x at y = {y[j]:.2f} m ({how});  whole map: dug "
                   f"{np.maximum(0, -dz).sum() * cell:.2f} m3, heaped {np.maximum(0, dz).sum() * cell:.2f} m3",
                   fontsize=10)
    prof.set_xlabel("x (m)")
    prof.set_ylabel("z (m)")
    prof.set_xlim(extent[0], extent[1])
    prof.grid(alpha=0.3)
    prof.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=5, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 1.0 - 0.3 / fig.get_figheight()))
    _save(fig, png_path)
