"""Command line: `opera-taichi run|validate SCENE.yaml` (same as `python cli.py ...` in a checkout).

Exit codes: 0 done, 1 a bug (traceback), 2 bad input (one line), 3 the simulation diverged, 130 interrupted
(Ctrl-C), 143 terminated (SIGTERM); both keep what the run recorded.
"""
from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import threading
import traceback
from pathlib import Path

from . import __version__
from .errors import DivergenceError, Terminated, UserError
from .scene import load_scene, naming_the_scene


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _cmd_validate(args) -> int:
    from . import model

    scene = load_scene(args.scene, args.set)
    with naming_the_scene(args.scene):
        checked = model.check_scene(scene)
        if scene.bridge is not None:  # topic names and rate keys are checked against the machines
            from .ros.topics import topic_table

            topic_table(checked, scene.bridge)
            if scene.bridge.kind == "ros_tcp":  # as `run` checks it before it connects
                from .ros.bridge import DEFAULT_ENDPOINT
                from .ros.transport_tcp import parse_address

                parse_address(scene.bridge.address or DEFAULT_ENDPOINT, "bridge.address")
    for text in checked.warnings:  # what a run would warn about at its start
        print(f"warning: {text}", file=sys.stderr)
    print(f"{args.scene}: ok")
    return 0


def _cmd_run(args) -> int:
    from . import runner

    # finite: the checkpoint observer's interval is 1/rate, and inf would make its rate 0
    if args.checkpoint_every is not None and not (math.isfinite(args.checkpoint_every) and args.checkpoint_every > 0):
        raise UserError(f"--checkpoint-every: expected a finite positive number of simulated seconds, got "
                        f"{args.checkpoint_every:g}")
    if args.resume is not None:
        if args.scene is not None or args.set or args.out is not None or args.overwrite:
            raise UserError("--resume RUN_DIR: give no SCENE, --set, --out or --overwrite (the run folder holds its "
                            "scene)")
        if args.replay:
            raise UserError("--replay: not with --resume (the run folder's scene says whether it records a replay)")
        scene, status, ckpt = runner.resume_scene(Path(args.resume))
        if not args.quiet:
            print(f"resuming {args.resume} (status {status}) from {ckpt.name}", file=sys.stderr)
        controller, extra = _bridge_parts(scene, args)
        controller, extra = _view_parts(scene, args, controller, extra)
        result = runner.run_scene(scene, out_dir=Path(args.resume), arch=args.arch or scene.sim.arch,
                                  quiet=args.quiet, checkpoint_every=args.checkpoint_every, resume=True,
                                  controller=controller, observers=extra)
    else:
        if args.scene is None:
            raise UserError("run: a SCENE.yaml is required (or --resume RUN_DIR)")
        sets = list(args.set or [])
        if (args.ros1 or args.ros_tcp) and any(item.startswith("bridge.") for item in sets):
            # the flag gives the bridge its kind (run_parts), so `--set bridge.rates...` needs no bridge.kind
            sets.insert(0, f"bridge.kind={'ros1' if args.ros1 else 'ros_tcp'}")
        scene = load_scene(args.scene, sets)
        if args.arch is not None:
            scene.sim.arch = args.arch
        if args.replay:
            scene.output.replay = True
        with naming_the_scene(args.scene):
            controller, extra = _bridge_parts(scene, args)
            controller, extra = _view_parts(scene, args, controller, extra)
            result = runner.run_scene(scene, out_dir=args.out, arch=scene.sim.arch, quiet=args.quiet,
                                      checkpoint_every=args.checkpoint_every, overwrite=args.overwrite,
                                      controller=controller, observers=extra)
    if not args.quiet:
        print(result.out_dir)
    return 0


def _bridge_parts(scene, args):
    """(controller, observers) for a ROS bridge (--ros1, --ros-tcp or the scene's `bridge`) and --pace."""
    if scene.bridge is None and not (args.ros1 or args.ros_tcp or args.pace or args.bridge_after_motion):
        return None, []
    from .ros.bridge import run_parts

    return run_parts(scene, ros1=args.ros1, ros_tcp=args.ros_tcp, pace=args.pace,
                     after_motion=args.bridge_after_motion, quiet=args.quiet)


def _view_parts(scene, args, controller, observers):
    """--view: the live 3-D view (an observer) and its controller (Pause; joint sliders when nothing else commands
    the machine: no motion script, no bridge)."""
    if not args.view:
        for flag, given in (("--view-port", args.view_port), ("--view-host", args.view_host),
                            ("--view-rate", args.view_rate)):
            if given is not None:
                raise UserError(f"{flag}: only with --view")
        return controller, observers
    from .model import machine_entries
    from .viewer.live import LiveView, ViewerController

    # finite: the view's frame period is 1/rate
    if args.view_rate is not None and not (math.isfinite(args.view_rate) and args.view_rate > 0):
        raise UserError(f"--view-rate: expected a finite positive number of frames per second, got {args.view_rate:g}")
    scripted = any(motion is not None for _, _, motion in machine_entries(scene))
    teleop = controller is None and not scripted
    view = LiveView(host=args.view_host or "127.0.0.1", port=8080 if args.view_port is None else args.view_port,
                    rate=args.view_rate or 10.0, teleop=teleop, quiet=args.quiet)
    observers = list(observers) + [view]
    if teleop and args.pace is None:  # a person moves the sliders: the machine answers on the wall clock
        from .pacing import RealTimePacer

        observers.append(RealTimePacer(quiet=args.quiet))
    return ViewerController(view, controller), observers


def _cmd_view(args) -> int:
    chosen = [flag for flag, given in (("--html", args.html), ("--mp4", args.mp4)) if given]
    if len(chosen) > 1:
        raise UserError("view: give one of --html FILE or --mp4 FILE (or neither, to serve the replay)")
    for flag, target, suffixes in (("--html", args.html, (".html", ".htm")), ("--mp4", args.mp4, (".mp4",))):
        if target and Path(target).suffix.lower() not in suffixes:  # never over a run's manifest or CSV
            raise UserError(f"{flag}: {target}: expected a file name ending in {' or '.join(suffixes)}")
    if args.html:
        from .viewer.playback import write_html

        write_html(args.run_dir, args.html, quiet=args.quiet)
    elif args.mp4:
        from .viewer.video import write_mp4

        write_mp4(args.run_dir, args.mp4, quiet=args.quiet)
    else:
        from .viewer.playback import serve

        serve(args.run_dir, host=args.host, port=args.port, quiet=args.quiet)
    return 0


def _cmd_runs(args) -> int:
    from .runs import format_table, list_runs, write_csv

    folder = Path(args.folder or "runs")
    if args.folder is None and not folder.exists():  # a fresh checkout: no run yet
        rows = []
    elif not folder.is_dir():
        raise UserError(f"runs: {folder} is not a folder")
    else:
        rows = list_runs(folder)
    if args.csv:
        write_csv(rows, sys.stdout)
    elif rows:
        print(format_table(rows))
    else:
        print(f"no runs under {folder}", file=sys.stderr)
    return 0


def _cmd_validate_physics(args) -> int:
    from .validation import cases

    cases.grains_across(cases.CASES[0], args.resolution)  # a bad --resolution stops here, before any run
    if args.report is not None and args.case not in ("all", "resolution"):
        raise UserError("--report: only with `all` or `resolution` (a single case writes OUT/metrics.json)")
    if args.case == "resolution" and args.resolution != "default":
        raise UserError("--resolution: not with `resolution` (it runs each case at the grain sizes people use)")
    if args.overwrite and args.case in ("all", "resolution"):
        raise UserError(f"--overwrite: only for a single case (`{args.case}` runs again what --resume does not keep)")
    if args.resume and args.report_only:
        raise UserError("--resume, --report-only: give one (--report-only runs nothing, --resume runs what is missing)")
    for flag, given in (("--resume", args.resume), ("--report-only", args.report_only)):
        if given and args.case not in ("all", "resolution"):
            raise UserError(f"{flag}: only with `all` or `resolution` (a single case always runs)")
    if args.case in ("all", "resolution"):
        if args.param:
            raise UserError(f"--param: not allowed with `{args.case}` (it runs a fixed set of cases)")
        target = Path(args.report) if args.report is not None else None
        if target is not None and (target.is_dir() or not target.parent.is_dir()):  # now, not after hours of runs
            where = "does not exist" if not target.parent.exists() else "is not a folder"
            raise UserError(f"--report: {target} " + ("is a folder; give a file (e.g. report.md)" if target.is_dir()
                                                      else f"lies in {target.parent}, which {where}"))
        from .validation import report, resolution

        if args.case == "all":
            path, failed = report.run_all(resolution=args.resolution, out_dir=args.out,
                                          report_path=args.report or "docs/validation.md", arch=args.arch,
                                          quiet=args.quiet, resume=args.resume, report_only=args.report_only,
                                          with_failures=True)
        else:
            path, failed = resolution.run_study(out_dir=args.out, report_path=args.report or "docs/resolution.md",
                                                arch=args.arch, quiet=args.quiet, resume=args.resume,
                                                report_only=args.report_only)
        if not args.quiet:
            print(path)
        if failed:
            print(f"FAIL: {len(failed)} gate(s) failed: {'; '.join(failed)} (see {path})", file=sys.stderr)
            return 1
        return 0
    if args.out is not None and (Path(args.out) / "metrics.json").is_file() and not args.overwrite:
        raise UserError(f"--out: {args.out} holds a finished case already; use --overwrite to replace it, or another "
                        f"folder")
    metrics = cases.run_case(args.case, args.param, resolution=args.resolution, out_dir=args.out, arch=args.arch,
                             quiet=args.quiet)
    if not args.quiet:
        rel = metrics["relative_error"]
        print(f"{metrics['case']}: {metrics['metric']} = {metrics['measured']:.4g} (reference "
              f"{metrics['reference']:.4g}{'' if rel is None else f', error {rel:+.1%}'}) "
              f"{'no gate' if metrics['passed'] is None else 'PASS' if metrics['passed'] else 'FAIL'}; "
              f"{Path(metrics.get('folder') or Path(metrics['run_dir']).parent) / 'metrics.json'}")
    coarse = cases.coarser_than_gate(args.case, args.param, args.resolution)
    if coarse and not args.quiet:
        print(f"note: {coarse}", file=sys.stderr)
    return 1 if metrics["passed"] is False else 0


class _Parser(argparse.ArgumentParser):
    """Usage errors in one line, as every other bad input (the usage is in --help)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="opera-taichi", description="Headless excavation simulator: Taichi soil + PyBullet excavator.")
    parser.add_argument("--version", action="version", version=f"opera-taichi {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")

    def scene_command(name: str, help_text: str, optional: bool = False):
        sub = commands.add_parser(name, help=help_text, description=help_text)
        sub.add_argument("scene", metavar="SCENE.yaml", help="scene file", nargs="?" if optional else None)
        sub.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE",
                         help="override a scene key, value read as YAML (repeatable), "
                              "e.g. --set sim.duration=5 --set soil.bed.0.max.2=-0.5")
        return sub

    run = scene_command("run", "run a scene and write a run folder", optional=True)
    run.add_argument("--out", metavar="DIR", help="run folder (default: output.dir, else runs/<name>-<time>)")
    run.add_argument("--arch", choices=("cpu", "cuda", "auto"), help="Taichi backend (overrides sim.arch)")
    run.add_argument("--quiet", action="store_true", help="no progress bar, no final path")
    run.add_argument("--checkpoint-every", type=float, metavar="SECONDS",
                     help="write a checkpoint into RUN_DIR/checkpoints every SECONDS of simulated time")
    run.add_argument("--overwrite", action="store_true",
                     help="with --out at a folder that holds a run: empty it and run there")
    run.add_argument("--resume", metavar="RUN_DIR",
                     help="continue a run that was killed or interrupted from its newest checkpoint")
    bridge = run.add_mutually_exclusive_group()
    bridge.add_argument("--ros1", action="store_true",
                        help="ROS bridge: a ROS 1 node (rospy) on the master of ROS_MASTER_URI takes the machine's "
                             "commands and publishes its state (README: Connect your ROS stack)")
    bridge.add_argument("--ros-tcp", metavar="HOST:PORT",
                        help="ROS bridge through Unity's ROS-TCP-Endpoint (ROS 1 or ROS 2, as the endpoint says)")
    run.add_argument("--pace", choices=("realtime", "fast"),
                     help="realtime: simulated time kept to the wall clock (default with a bridge); fast: as fast "
                          "as it goes (default without)")
    run.add_argument("--bridge-after-motion", action="store_true",
                     help="with a bridge: run the scene's motion first, then take commands from ROS")
    run.add_argument("--view", action="store_true",
                     help="serve the live 3-D view at http://127.0.0.1:8080 while the run goes (needs the viewer "
                          "extra); with no motion script its panel has joint sliders")
    run.add_argument("--view-port", type=int, metavar="PORT", help="port of the live view (default 8080)")
    run.add_argument("--view-host", metavar="HOST",
                     help="address the live view listens on (default 127.0.0.1: this machine only)")
    run.add_argument("--view-rate", type=float, metavar="HZ",
                     help="live view frames per wall-clock second at most (default 10)")
    run.add_argument("--replay", action="store_true",
                     help="record replay.bin for `view RUN_DIR` (same as --set output.replay=true)")
    run.set_defaults(handler=_cmd_run)
    view = commands.add_parser("view", help="replay a run recorded with --replay in the browser, or write it as "
                                            "one HTML file or an MP4 video",
                               description="Serve a run's replay (time slider, play/pause, speed) at "
                                           "http://HOST:PORT, or write it as a self-contained HTML file (--html) "
                                           "or an MP4 video (--mp4). The run must be recorded with --replay.")
    view.add_argument("run_dir", metavar="RUN_DIR", help="run folder written by `run --replay`")
    view.add_argument("--port", type=int, default=8080, help="port to serve on (default 8080)")
    view.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    view.add_argument("--html", metavar="FILE", help="write one self-contained HTML file that plays the run "
                                                     "with no server, then exit")
    view.add_argument("--mp4", metavar="FILE", help="render the replay offscreen to an MP4 video, then exit")
    view.add_argument("--quiet", action="store_true", help="print nothing but errors")
    view.set_defaults(handler=_cmd_view)
    validate = scene_command("validate", "check a scene (files, keys, joints) without running it")
    validate.set_defaults(handler=_cmd_validate)
    runs = commands.add_parser("runs", help="list the runs under a folder (status, simulated time, real-time "
                                            "factor, bucket load, peak force)",
                               description="List the run folders under DIR (default runs/): name, scene, status "
                                           "(done, running, died, diverged, ...), simulated time, real-time factor, "
                                           "bucket load and peak force.")
    runs.add_argument("folder", metavar="DIR", nargs="?", default=None, help="folder to search (default runs)")
    runs.add_argument("--csv", action="store_true", help="CSV on stdout, for scripts")
    runs.set_defaults(handler=_cmd_runs)
    physics = commands.add_parser(
        "validate-physics", help="run a physics validation case against its analytic reference",
        description="Run a validation case (blade_cut, passive_wall, column_collapse, repose, vertical_cut, "
                    "critical_height) and write DIR/metrics.json next to the run folder DIR/run/; `all` runs the "
                    "gate set and, at the default resolution, the study at operating resolution after it (into "
                    "OUT/resolution/), and writes the report (docs/validation.md and its plots); `resolution` runs "
                    "the study alone (docs/resolution.md: blade convergence, the gates at 4 and 8 grains across, "
                    "critical heights, coarse heaps and columns).")
    physics.add_argument("case", metavar="CASE", help="blade_cut | passive_wall | column_collapse | repose | "
                                                      "vertical_cut | critical_height | all | resolution")
    physics.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                         help="case parameter (repeatable), e.g. --param depth=0.2 --param rake_deg=60")
    physics.add_argument("--resolution", default="default", metavar="coarse|default|fine|N",
                         help="particle size: a named resolution, or N particle diameters across the case's key "
                              "length (3-64; e.g. 24 for a blade convergence run on a GPU)")
    physics.add_argument("--out", metavar="DIR", help="output folder (default: runs/validate-<case>-<time>)")
    physics.add_argument("--overwrite", action="store_true",
                         help="a single case: replace the case run already in --out")
    physics.add_argument("--report", metavar="FILE",
                         help="report written by `all` (default docs/validation.md) or `resolution` (default "
                              "docs/resolution.md); plots go beside it in <stem>/")
    physics.add_argument("--resume", action="store_true",
                         help="with `all` or `resolution`: keep the runs already finished in --out with the same parameters, "
                              "resolution and solver version; run only the others")
    physics.add_argument("--report-only", action="store_true",
                         help="with `all` or `resolution`: run nothing, write the report from the runs already finished in --out "
                              "(the other gates listed as not run)")
    physics.add_argument("--arch", choices=("cpu", "cuda", "auto"), help="Taichi backend")
    physics.add_argument("--quiet", action="store_true", help="no progress bars")
    physics.set_defaults(handler=_cmd_validate_physics)
    from .studies.commands import add_commands  # compare, study, calibrate (opera_taichi/studies/)

    add_commands(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version (0) and usage errors (2)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    if args.command is None:
        print("opera-taichi: error: a command is required (run, view, validate, runs, validate-physics, compare, "
              "study or calibrate; see opera-taichi --help)", file=sys.stderr)
        return 2
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        if args.command in SOLVER_COMMANDS:
            _import_the_solver()
        return args.handler(args)
    except UserError as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return UserError.exit_code
    except DivergenceError as exc:
        print(f"diverged: {_one_line(exc)}", file=sys.stderr)
        return DivergenceError.exit_code
    except Terminated:
        print("terminated (SIGTERM)", file=sys.stderr)
        return Terminated.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception:  # anything else is a bug: show where
        traceback.print_exc()
        return 1
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


SOLVER_COMMANDS = ("run", "validate", "validate-physics", "study", "calibrate")


def _import_the_solver() -> None:
    """Import Taichi and the soil's kernels with SIGINT and SIGTERM held. Taichi's decorators swallow any exception
    while they read their source (a bare except), so a Ctrl-C or SIGTERM in that second of the start was lost and
    the run went on to its end with exit 0; held, it is taken as usual once the import is done. (Recorded by a
    handler rather than masked: a process's signal may land on any thread that does not mask it.)"""
    if "opera_taichi.kernels.dem" in sys.modules or threading.current_thread() is not threading.main_thread():
        return
    caught: list[int] = []
    held = {s: signal.signal(s, lambda signum, frame: caught.append(signum)) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        import taichi  # noqa: F401

        from .kernels import dem  # noqa: F401  (its kernels are decorated as it loads)
    finally:
        for s, handler in held.items():
            signal.signal(s, handler)
    if caught:
        handler = held[caught[0]]
        if callable(handler):
            handler(caught[0], None)       # KeyboardInterrupt, or the CLI's Terminated
        elif handler == signal.SIG_DFL:
            os.kill(os.getpid(), caught[0])


def _terminate(signum, frame):
    raise Terminated("terminated by SIGTERM")
