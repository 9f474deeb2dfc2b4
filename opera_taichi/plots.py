"""PNG plots for the run folder: what a person would rather look at than read."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .recorders import read_csv_columns  # noqa: E402


def plot_joints(csv_path: Path, joints: list[str], png_path: Path) -> None:
    cols = read_csv_columns(csv_path)
    t = cols["t"]
    fig, axes = plt.subplots(len(joints), 1, figsize=(9, 2.2 * len(joints)), sharex=True, squeeze=False)
    for ax, joint in zip(axes[:, 0], joints):
        ax.plot(t, np.degrees(cols[f"{joint}.q_cmd"]), "--", color="tab:gray", label="commanded")
        ax.plot(t, np.degrees(cols[f"{joint}.q"]), color="tab:blue", label="actual")
        ax.set_ylabel(f"{joint}\n(deg)")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("simulated time (s)")
    fig.suptitle("Joint angles: commanded vs actual")
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    plt.close(fig)


def plot_tool_wrench(csv_path: Path, png_path: Path) -> None:
    cols = read_csv_columns(csv_path)
    tools = sorted(set(cols["tool"]))
    if not tools:  # a soil scene without tools has nothing to plot
        return
    fig, axes = plt.subplots(len(tools), 1, figsize=(9, 3 * len(tools)), sharex=True, squeeze=False)
    tool_col = np.asarray(cols["tool"])
    for ax, tool in zip(axes[:, 0], tools):
        sel = tool_col == tool
        for comp in ("fx", "fy", "fz"):
            ax.plot(cols["t"][sel], cols[comp][sel] / 1e3, label=comp)
        ax.set_ylabel(f"{tool}\nforce (kN)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("simulated time (s)")
    fig.suptitle("Force of the soil on each tool (world frame)")
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    plt.close(fig)


def plot_terrain(initial: dict, final: dict, png_path: Path) -> None:
    x, y = initial["x"], initial["y"]
    z0, z1 = initial["z"], final["z"]
    extent = [x[0], x[-1], y[0], y[-1]]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    lo, hi = float(min(z0.min(), z1.min())), float(max(z0.max(), z1.max()))
    for ax, z, title in ((axes[0], z0, "initial surface z (m)"), (axes[1], z1, "final surface z (m)")):
        im = ax.imshow(z.T, origin="lower", extent=extent, vmin=lo, vmax=hi, cmap="terrain", aspect="equal")
        ax.set_title(title)
        fig.colorbar(im, ax=ax, shrink=0.8)
    dz = z1 - z0
    lim = max(float(np.abs(dz).max()), 1e-6)
    im = axes[2].imshow(dz.T, origin="lower", extent=extent, vmin=-lim, vmax=lim, cmap="RdBu_r", aspect="equal")
    axes[2].set_title("final - initial (m): blue dug, red heaped")
    fig.colorbar(im, ax=axes[2], shrink=0.8)
    for ax in axes:
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    plt.close(fig)


def plot_soil_mass(csv_path: Path, png_path: Path) -> None:
    cols = read_csv_columns(csv_path)
    fig, ax = plt.subplots(figsize=(8, 3))
    for name in ("mass_kg", "particles_kg", "out_of_domain_kg"):
        if name in cols:
            ax.plot(cols["t"], cols[name], label=name)
    ax.set_xlabel("simulated time (s)")
    ax.set_ylabel("kg")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    plt.close(fig)
