"""The study commands of the CLI: compare, study, calibrate (parsers and handlers; the work is in this package)."""
from __future__ import annotations

import argparse
import json
import sys


def _cmd_compare(args) -> int:
    from .compare import COMPARISON_FILE, compare

    result = compare(args.run_dir, terrain=args.terrain, terrain_before=args.terrain_before, joints=args.joints,
                     against=args.against, transform=args.transform, fit=args.fit_transform, out=args.out,
                     change_threshold=args.change_threshold, margin_m=args.margin)
    if not args.quiet:
        keys = ("terrain_rmse_m", "terrain_bias_m", "cut_volume_m3", "reference_cut_volume_m3", "fill_volume_m3",
                "reference_fill_volume_m3", "max_depth_m", "reference_max_depth_m", "joints_rmse_rad",
                "joints_lag_s", "joints_rate_ratio")
        shown = {k: result[k] for k in keys if result.get(k) is not None}
        for k, v in shown.items():
            print(f"{k}: {v:.4g}" if isinstance(v, float) else f"{k}: {v}")
        if "transform" in result:
            t = result["transform"]
            print("transform: " + json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in t.items()
                                              if k.endswith(("_m", "_deg")) or k == "mode"}))
        from pathlib import Path

        print(Path(args.out or args.run_dir) / COMPARISON_FILE)
    return 0


def _cmd_study(args) -> int:
    from .study import run_study

    table, failed, points = run_study(args.study, scheduler=args.scheduler, workers=args.workers, out=args.out,
                                      quiet=args.quiet)
    if not args.quiet:
        print(table)
    if points and failed == points:  # nothing to read in the table: say so to a script too
        print(f"error: study: all {points} points failed (their errors: {table})", file=sys.stderr)
        return 1
    return 0


def _cmd_calibrate(args) -> int:
    from .calibrate import calibrate

    result = calibrate(args.study, scheduler=args.scheduler, workers=args.workers, out=args.out, quiet=args.quiet,
                       trials=args.trials)
    if not args.quiet:
        best = ", ".join(f"{k} = {v:.5g}" for k, v in result["best_parameters"].items())
        print(f"best (loss {result['best_loss']:.4g}): {best}")
        print(result["preset_file"])
    return 0


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def add_commands(commands) -> None:
    cmp = commands.add_parser(
        "compare", help="compare a run with a terrain scan, a joint log or another run",
        description="Compare a run folder with a terrain scan (LAS/LAZ, PLY, XYZ/CSV, GeoTIFF, NPZ) taken after the "
                    "dig (and before it), a joint log (CSV or ROS bag) or another run; writes comparison.json, "
                    "profile.csv and comparison_*.png (keys and units: README, 'Comparing with the field').")
    cmp.add_argument("run_dir", metavar="RUN_DIR", help="the run folder")
    cmp.add_argument("--terrain", metavar="SCAN", help="scan of the terrain after the dig")
    cmp.add_argument("--terrain-before", metavar="SCAN", help="scan before the dig (default: the run's own initial "
                                                              "terrain is the reference's initial surface)")
    cmp.add_argument("--joints", metavar="LOG", help="joint log: CSV with t and <joint> (rad) or <joint>_deg "
                                                     "columns, or a ROS bag with sensor_msgs/JointState")
    cmp.add_argument("--against", metavar="RUN_DIR2", help="another run folder (coarse against fine, ...)")
    cmp.add_argument("--transform", metavar="X,Y,Z,YAW_DEG[,ROLL_DEG,PITCH_DEG]",
                     help="scan frame -> machine frame: rotate (roll, pitch, yaw about fixed x, y, z), then translate "
                          "(write --transform=-12.5,... when it starts with a minus)")
    cmp.add_argument("--fit-transform", nargs="?", const="auto", choices=("auto", "plane", "rigid"),
                     help="estimate the transform from the undisturbed ground against the run's initial terrain "
                          "(starting from --transform, else from the scan's centre); auto: rigid where the terrain "
                          "has relief, plane (z, roll, pitch) where it is flat")
    cmp.add_argument("--change-threshold", type=float, default=0.02, metavar="M",
                     help="a cell changed by more than this (m) belongs to the dig area (default 0.02)")
    cmp.add_argument("--margin", type=float, default=0.25, metavar="M",
                     help="the dig area reaches this far (m) beyond the changed cells (default 0.25)")
    cmp.add_argument("--out", metavar="DIR", help="where comparison.json and the figures go (default: RUN_DIR)")
    cmp.add_argument("--quiet", action="store_true", help="print nothing")
    cmp.set_defaults(handler=_cmd_compare)

    for name, text in (("study", "run a parameter study on a Dask cluster (a LocalCluster by default)"),
                       ("calibrate", "fit soil parameters to a reference with Optuna; writes a soil preset file")):
        sub = commands.add_parser(name, help=text, description=text + "; README, 'Studies and calibration'.")
        sub.add_argument("study", metavar="STUDY.yaml", help="study file")
        sub.add_argument("--scheduler", metavar="ADDRESS", help="an existing Dask scheduler, e.g. tcp://host:8786 "
                                                                "(default: a LocalCluster on this machine)")
        sub.add_argument("--workers", type=_positive_int, metavar="N",
                         help="LocalCluster worker processes (default: one per core)")
        sub.add_argument("--out", metavar="DIR", help="study folder (default: the study's `out`, else "
                                                      "studies/<name>)")
        sub.add_argument("--quiet", action="store_true", help="no progress lines")
        if name == "calibrate":
            sub.add_argument("--trials", type=_positive_int, metavar="N", help="number of trials (overrides the "
                                                                               "study's calibrate.trials)")
        sub.set_defaults(handler=_cmd_study if name == "study" else _cmd_calibrate)


__all__ = ["add_commands"]
