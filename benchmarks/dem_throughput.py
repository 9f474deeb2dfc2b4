"""DEM soil throughput: particle-steps per second on a settled bed while a blade moves through it.

    python benchmarks/dem_throughput.py --sizes 10000,50000,200000 --arch cpu --steps 2000

Each size is a square pit 0.3 m deep of the `sand` preset (radius 0.02 m), filled and settled once (cached
on disk; the first run of a size takes minutes), then a 0.04 m thick blade 0.5 m wide enters it from the side
and cuts through it 0.1 m deep at 1 m/s (12 cm in 2000 substeps). Timed: `steps` substeps through
DemSoil.advance in calls of 10 substeps (neighbour rebuilds and per-call overhead included), after a warm-up
that compiles the kernels, in 5 segments: the median rate is reported with the slowest and fastest segment.
Building and settling the bed is not timed. Sizes are nominal: the particle count of the settled bed is printed.

Then the real-time factor of `scenes/zx120_excavation.yaml` at its default resolution (the whole coupled run:
PyBullet machine, soil substeps, recorders; bed settling excluded), unless `--no-excavation`. Shorter or coarser:
`--excavation-duration 5 --excavation-set soil.overrides.radius=0.08`.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench_args import at_least, host_line  # noqa: E402  (beside this script)

import numpy as np  # noqa: E402
import trimesh  # noqa: E402


SEGMENTS = 5  # timed segments per size; the median is reported (a shared 2-vCPU machine varies by +-15%)


def bed_for(n: int, radius: float) -> tuple[tuple, tuple]:
    """A pit 0.3 m deep whose settled bed holds about n particles. Beds are poured with the soil's friction
    (DemSoil.bed_packing): sand at 2 cm settles to a solid fraction of about 0.47 (measured: 0.58 gave 41k
    particles for a nominal 50k)."""
    depth = 0.3
    volume = n * 4.0 / 3.0 * math.pi * radius ** 3 / 0.475
    side = math.sqrt(volume / depth)
    return (-side / 2, -side / 2, -depth), (side / 2, side / 2, 0.0)


def run(n: int, arch_steps: int, settle_time: float, radius: float) -> dict:
    from opera_taichi.dem_soil import DemSoil
    from opera_taichi.soil import bulk_to_micro, resolve_soil

    micro = bulk_to_micro(resolve_soil("sand", {"radius": radius}), bed_depth=0.3)
    bed = bed_for(n, radius)
    side = bed[1][0] - bed[0][0]
    domain = ((bed[0][0] - 0.5, bed[0][1] - 0.5, -0.5), (bed[1][0] + 0.5, bed[1][1] + 0.5, 1.0))
    t0 = time.perf_counter()
    soil = DemSoil(micro, domain_min=domain[0], domain_max=domain[1], beds=[bed], settle_time=settle_time)
    build = time.perf_counter() - t0
    blade = soil.add_tool("blade", trimesh.creation.box([0.04, min(0.5, 0.8 * side), 0.3]))
    start = np.array([bed[0][0] - 0.03, 0.0, 0.15 - 0.1])  # 1 cm outside the pit wall, lower edge 0.1 m deep
    soil.set_tool_state(blade, start, [0, 0, 0, 1], [1.0, 0, 0], [0, 0, 0])
    soil.advance(20 * soil.dt)  # compile and warm up
    rebuilds = soil.rebuilds
    chunk = 10
    calls = max(SEGMENTS, arch_steps // chunk) // SEGMENTS
    walls = []
    for _ in range(SEGMENTS):
        t0 = time.perf_counter()
        for _ in range(calls):
            soil.advance(chunk * soil.dt)
        walls.append(time.perf_counter() - t0)
    steps = SEGMENTS * calls * chunk
    rates = sorted(soil.n_particles * calls * chunk / w for w in walls)
    return dict(n=soil.n_particles, steps=steps, wall=sum(walls), rate=float(np.median(rates)), spread=rates,
                rebuilds=soil.rebuilds - rebuilds, build=build, dt=soil.dt,
                neighbours=soil.neighbor_entries / max(soil.n_particles, 1))


def excavation(duration: float | None, sets: list[str], arch: str) -> dict:
    """Run zx120_excavation.yaml (optionally shortened / overridden) and read its manifest."""
    import json
    import tempfile

    from opera_taichi.paths import scenes_dir
    from opera_taichi.scene import load_scene
    from opera_taichi.simulation import run_scene

    sets = list(sets) + [f"sim.arch={arch}"]
    if duration is not None:
        sets.append(f"sim.duration={duration}")
    scene = load_scene(scenes_dir() / "zx120_excavation.yaml", sets)
    with tempfile.TemporaryDirectory() as tmp:
        result = run_scene(scene, out_dir=Path(tmp) / "run", arch=arch, quiet=True)
        manifest = json.loads((result.out_dir / "manifest.json").read_text())
    return dict(n=result.particles, sim=result.sim_time, wall=result.wall_time, rtf=result.real_time_factor,
                rate=manifest.get("particle_steps_per_s") or 0.0, soil_dt=manifest["soil"]["soil_dt"],
                setup=manifest.get("setup_wall_time_s", 0.0))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    def sizes(text: str) -> str:
        try:
            ok = all(int(n) >= 100 for n in text.split(","))
        except ValueError:
            ok = False
        if not ok:
            raise argparse.ArgumentTypeError(f"expected particle counts >= 100, comma separated, got {text!r}")
        return text

    parser.add_argument("--sizes", type=sizes, default="10000,50000,200000", help="particle counts, comma separated")
    parser.add_argument("--arch", default="cpu", choices=("cpu", "cuda", "auto"))
    parser.add_argument("--steps", type=at_least(1, int, "a whole number"), default=2000,
                        help="timed substeps per size")
    parser.add_argument("--settle-time", type=at_least(0.01), default=1.0, help="bed settling time, s (cached)")
    parser.add_argument("--radius", type=at_least(0.001), default=0.02, help="particle radius, m")
    parser.add_argument("--no-excavation", action="store_true", help="skip the zx120_excavation.yaml run")
    parser.add_argument("--excavation-duration", type=float, default=None,
                        help="simulated seconds of the excavation run (default: the scene's)")
    parser.add_argument("--excavation-set", action="append", default=[], metavar="KEY=VALUE",
                        help="scene override for the excavation run, as for `cli.py run --set`")
    args = parser.parse_args(argv)
    from opera_taichi.backend import init_taichi

    arch = init_taichi(args.arch)
    import taichi as ti

    threads = ti.lang.impl.current_cfg().cpu_max_num_threads if arch == "x64" else None
    print(host_line())
    print(f"arch {arch}, cpu threads {threads}, os cpus {os.cpu_count()}")
    print(f"{'particles':>10} {'substeps':>9} {'wall s':>8} {'Mparticle-steps/s':>18} {'min-max':>11} "
          f"{'rebuilds':>9} {'nbrs/particle':>14} {'dt s':>9} {'bed build s':>12}")
    for size in (int(s) for s in args.sizes.split(",") if s.strip()):
        r = run(size, args.steps, args.settle_time, args.radius)
        spread = f"{r['spread'][0] / 1e6:.2f}-{r['spread'][-1] / 1e6:.2f}"
        print(f"{r['n']:>10d} {r['steps']:>9d} {r['wall']:>8.2f} {r['rate'] / 1e6:>18.2f} {spread:>11} "
              f"{r['rebuilds']:>9d} {r['neighbours']:>14.1f} {r['dt']:>9.2e} {r['build']:>12.1f}", flush=True)
    if not args.no_excavation:
        e = excavation(args.excavation_duration, args.excavation_set, args.arch)
        print(f"\nzx120_excavation.yaml {' '.join(args.excavation_set)}".rstrip())
        print(f"{'particles':>10} {'sim s':>7} {'wall s':>8} {'real-time factor':>17} {'Mparticle-steps/s':>18} "
              f"{'soil dt s':>10} {'setup s':>8}")
        print(f"{e['n']:>10d} {e['sim']:>7.2f} {e['wall']:>8.1f} {e['rtf']:>17.3f} {e['rate'] / 1e6:>18.2f} "
              f"{e['soil_dt']:>10.2e} {e['setup']:>8.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
