"""DemSoil: the cohesive DEM soil over the Taichi kernels (model + state; Python orchestrates, kernels compute).

Particles live in Taichi ndarrays between steps; Python never loops over them. A soil is built from beds
(pits cut into the ground at z = 0, filled by pouring a jittered lattice and letting it settle), or from given
particles (`set_particles`). Settled beds are cached on disk. Tools are rigid kinematic bodies given by a
signed distance grid in their link frame.

Neighbour search: particles are binned into cells of edge 2 r_max + D + skin, hashed (Morton code masked to a
table of ~2 n buckets, so memory follows the particle count, not the domain) and counting-sorted, which also
reorders the particle arrays for memory locality. Verlet lists hold every pair closer than r_i + r_j + D + skin
once (half lists, found through a half stencil of cells); they are rebuilt only when some particle has moved
more than skin / 2 (a reduction in the integration kernel) or left the domain, and contact springs are carried
over at a rebuild. One substep = one kernel of three passes (the blocks that take part; pair forces; everything
else and the integration). The substeps of one rigid step run as one Taichi compute graph, which halts itself after a substep
that needs a rebuild (the host rebuilds and runs the rest), so a rigid step costs one launch from Python; on the
CPU its tool rows and report are read and written through NumPy views of the arrays, without a copy kernel.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict

import numpy as np
import taichi as ti

from .backend import KernelSequence, compiled_for, current_arch, host_view, precompile
from .errors import DivergenceError, UserError
from .geometry import quat_to_matrix
from .kernels import dem
from .paths import cache_dir
from .soil import GRAVITY, SoilMicro, check_dt, damping_for_step, tool_friction_angle
from .tool_sdf import tool_sdf

MORTON_TABLE_PER_PARTICLE = 16
MORTON_TABLE_MAX = 1 << 21
# 19: the beds' masses matched to the bulk density after levelling (they were 2-8% light), a scanned bed's volume
# over its footprint alone (4% heavy in a test); 18: soil substep t_c / 10 (was 15), IEEE arithmetic; 17: a shifted
# bed keeps its masses and contacts; 16: a larger cell hash table, sleeping blocks skipped
SOLVER_VERSION = 19
# the soil wedge's model (tools' cutting_edge), recorded beside it: a wedged run of another is not reused. 2: the layer
# beyond a plate's failure plane takes the plane's reaction only while it moves slower than the wedge; 3: an opening's
# wedge moves with its edge and up the mouth (a plate's is as in 2, bit for bit)
WEDGE_VERSION = 3
NEIGHBORS_PER_PARTICLE = 6    # initial neighbour-entry capacity per particle (half list); grows when exceeded
SKIN_FRACTION = 0.3        # Verlet skin = 0.3 R
# Frozen soil (soil.sleep): a full rebuild moves the particles that are asleep, farther than FREEZE_MARGIN beyond
# every tool's bounding sphere and more than FREEZE_LAYERS contacts from anything awake to the front of the arrays;
# the rebuilds that the moving soil needs then sort, gather and list only the particles after them. Worth the full
# rebuilds it costs only in a big bed (FREEZE_MIN) with enough of it frozen (FREEZE_FEWEST). A frozen particle asked
# to wake, a tool's sphere come within FREEZE_MARGIN / 2 of the frozen soil, or new parameters repartition (a full
# rebuild); with nothing frozen, a big bed tries again every FREEZE_RETRY s, or after FREEZE_SOON once most of
# what was moving has fallen asleep.
FREEZE_MIN = 8192          # particles in the soil, at least, for any to freeze (the main job's 3,451 never do)
FREEZE_FEWEST = 2048       # frozen particles, at least, in a partition (fewer: none frozen); docs/performance.md
FREEZE_MARGIN = 0.5        # m, at least; and at least 4 x (r_max + skin + adhesion range)
FREEZE_RETRY = 0.5         # s
FREEZE_SOON = 0.05         # s: sooner when the substeps list less than half of what they listed at the last try
FREEZE_LAYERS = 6          # layers of particles kept live around each unfrozen one (a moving one wakes its partners)
SETTLE_DAMPING = 5.0       # 1/s, viscous damping used only while a bed settles
START_TIME = 0.05          # s: a divergence before it names what starts inside the soil as the likely cause
CRUSH_GAP = 1.0            # grain diameters: a divergence with a tool closing this near a pit's wall or floor names it
SLEEP_AFTER = 0.05         # s a particle must stay quiet before it sleeps (soil.sleep)
SLEEP_SPEED = 0.02         # x sqrt(g R): the quiet speed (what a settled bed counts as at rest)
POUR_GAP = 1.03            # lattice spacing = 2 r_max * POUR_GAP
STACKED_WARN = 0.3         # a settled bed with more of its grains straight on the one beneath is a cubic stack: warn
# Beds are poured with the soil's own friction and rolling resistance (smooth pit walls, no cohesion): a loose,
# as-deposited packing whose strength is near the critical state. A frictionless pour packs densely (~0.6) and
# that bed is several times too strong against walls and blades (peak dilatancy; see soil.py).
POUR_FRICTIONLESS = False
# Each poured grain's random sideways start, x sqrt(g d) (0: the lattice falls straight). It breaks the stacks of thin
# beds but packs deep beds denser, whose walls then read 20-30% stronger: it waits for the mapping to be recalibrated
# on such beds (docs/validation.md, calibration note 1).
POUR_SCATTER = 0.0


def stacked_fraction(positions: np.ndarray, radii: np.ndarray, floors: np.ndarray) -> float | None:
    """Share of the grains above a bed's bottom layer that rest straight on a grain beneath them: a neighbour within
    1.1 contact distances whose centre lies within 0.15 contact distances of the vertical below. About 1 in a cubic
    stack, 0.02-0.15 in a random packing. floors: the bed floor under each grain. None when no grain lies above the
    bottom layer."""
    from scipy.spatial import cKDTree

    pos = np.asarray(positions, float).reshape(-1, 3)
    rad = np.asarray(radii, float).reshape(-1)
    upper = pos[:, 2] > np.asarray(floors, float) + 2.0 * rad  # (a bottom-layer grain rests on the floor)
    if len(pos) < 2 or not np.any(upper):
        return None
    k = min(12, len(pos))
    dist, j = cKDTree(pos).query(pos[upper], k=k, distance_upper_bound=2.2 * rad.max())
    found = np.isfinite(dist)
    j = np.where(found, j, 0)
    contact = rad[upper][:, None] + rad[j]
    offset = pos[j] - pos[upper][:, None, :]
    beneath = (found & (dist > 0.0) & (dist < 1.1 * contact) & (offset[..., 2] < 0.0)
               & (np.hypot(offset[..., 0], offset[..., 1]) < 0.15 * contact))
    return float(np.mean(np.any(beneath, axis=1)))


def _vec3(value, key: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise UserError(f"{key}: expected three numbers [x, y, z], got {value!r}") from None
    if not np.all(np.isfinite(arr)):
        raise UserError(f"{key}: expected finite numbers, got {value!r}")
    return arr


def _unit(quat) -> np.ndarray:
    q = np.asarray(quat, dtype=np.float64)
    return q / math.sqrt(float(q @ q))


def _check_domain(domain_min, domain_max) -> tuple[np.ndarray, np.ndarray]:
    lo = _vec3(domain_min, "soil.domain.min")
    hi = _vec3(domain_max, "soil.domain.max")
    if not np.all(hi > lo):
        raise UserError(f"soil.domain: expected min < max on every axis, got min {lo.tolist()} max {hi.tolist()}")
    if not hi[2] > 0.0:
        raise UserError(f"soil.domain.max: z must be above the ground (z = 0), got {hi[2]:g}")
    return lo, hi


def _check_beds(beds, lo, hi, r_max) -> list[tuple[np.ndarray, np.ndarray]]:
    if len(beds) > dem.MAX_PITS:
        raise UserError(f"soil.bed: at most {dem.MAX_PITS} beds, got {len(beds)}")
    out = []
    for i, bed in enumerate(beds):
        key = f"soil.bed.{i}"
        try:
            b_min, b_max = bed
        except (TypeError, ValueError):
            raise UserError(f"{key}: expected [min, max] corners, got {bed!r}") from None
        b_min = _vec3(b_min, key + ".min")
        b_max = _vec3(b_max, key + ".max")
        if not np.all(b_max > b_min):
            raise UserError(f"{key}: expected min < max on every axis, got min {b_min.tolist()} max {b_max.tolist()}")
        if b_max[2] > 0.0:
            raise UserError(f"{key}.max: the bed is a pit below the ground, so z <= 0 is required, got {b_max[2]:g}")
        if np.any(b_min < lo) or np.any(b_max[:2] > hi[:2]):
            raise UserError(f"{key}: min {b_min.tolist()} max {b_max.tolist()} is not inside the domain "
                            f"min {lo.tolist()} max {hi.tolist()}")
        if np.any(b_max - b_min < 4.0 * r_max):
            raise UserError(f"{key}: each side must hold at least two particles (>= {4 * r_max:g} m), "
                            f"got {(b_max - b_min).tolist()}")
        for j, (o_min, o_max) in enumerate(out):
            if np.all(b_min[:2] < o_max[:2]) and np.all(o_min[:2] < b_max[:2]):
                raise UserError(f"{key}: overlaps soil.bed.{j} in plan view; beds must not overlap")
        out.append((b_min, b_max))
    return out


def _available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux MemAvailable), None where it cannot be read."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        import os

        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


_GRAPHS: dict = {}
CHUNK_MAX = 32  # longest run of substeps in one compute graph (longer advances run several)
# A run of substeps loops serially on the CPU when the last one listed fewer particle slots than this (the
# thread pool's round trips would cost more than a second core gives back; see kernels/dem.py SERIAL_LOOPS)
SERIAL_BELOW = 4096


PER_PARTICLE_ARCHS = ("cuda",)  # backends whose step loop gives each particle a thread (DemSoil._layout)


def _substep_kernel(layout: str):
    base, _, wedges = layout.partition("+")  # "+wedges": the variant with the soil wedges (a tool has an edge)
    suffix = "_wedges" if wedges else ""
    return getattr(dem, {"block": "substep", "serial": "substep_serial", "particle": "substep_per_particle"}[base]
                   + suffix)


def _of_this_runtime(cache: dict) -> dict:
    """`cache` emptied if Taichi was started anew since it was filled (its graphs belong to the old runtime)."""
    runtime = ti.lang.impl.get_runtime().prog  # (held, not its id: a restarted Taichi may reuse an id)
    if cache.get("runtime") is not runtime:
        cache.clear()
        cache["runtime"] = runtime
    return cache


def _chunk_graph(count: int, layout: str):
    """Compute graph of `count` substeps (begin_chunk, count x substep, end_chunk), built
    once per Taichi runtime and count; None if the backend cannot build graphs (then the kernels are launched
    directly). Launching an ndarray kernel from Python costs ~20 us per argument, which would dominate small soils;
    a graph binds the arguments in C++, and one graph per rigid step launches from Python once. layout: the
    substep kernel's (DemSoil._layout)."""
    _of_this_runtime(_GRAPHS)
    key = (count, layout)
    if key not in _GRAPHS:
        try:
            arg, kind = ti.graph.Arg, ti.graph.ArgKind
            sym = {name: arg(kind.NDARRAY, name, dtype=dtype, ndim=ndim) for name, (dtype, ndim) in _NDARRAYS.items()}
            sym.update({name: arg(kind.SCALAR, name, dtype) for name, dtype in _SCALARS.items()})
            builder = ti.graph.GraphBuilder()
            builder.dispatch(dem.begin_chunk, *(sym[a] for a in _BEGIN_ARGS))
            for _ in range(count):
                builder.dispatch(_substep_kernel(layout), *(sym[a] for a in _SUBSTEP_ARGS))
            builder.dispatch(dem.end_chunk, *(sym[a] for a in _END_ARGS))
            _GRAPHS[key] = builder.compile()
        except Exception:  # noqa: BLE001 - any failure here just means direct launches
            _GRAPHS[key] = None
    return _GRAPHS[key]


# A rebuild as two runs of kernels (one compute graph each on the CPU): sort the particles and count their lists;
# then, once the host has made room for the entries, fill the lists, reverse them and mark the next substep's
# blocks. Names ending in _out are the spare buffers the host swaps in after each run.
_BIN = ("lo", "n", "kin", "flags", "freeze", "use_frozen", "cell", "bucket", "counts", "prm", "mask", "live_mask")
_SORT = ("lo", "n", "bucket", "counts", "starts", "order", "mask", "live_mask", "sizes")
_MOVED = ("lo", "n", "n_listed", "kin", "flags", "x_ref", "order", "order_inv", "moved", "prm", "mask", "live_mask",
          "was_frozen", "freeze", "use_frozen")
_GATHER = ("lo", "n", "order", "kin", "kin_out", "prop", "prop_out", "flags", "flags_out", "surf_id", "surf_id_out",
           "surf_h", "surf_h_out", "cell", "cell_out")
_COUNT = ("lo", "n_frozen", "sizes", "kin_out", "prop_out", "cell_out", "starts", "nbr_off_out", "prm", "mask",
          "live_mask", "keep", "moved", "order", "nbr_off", "kept")
_FILL = ("lo", "n_frozen", "n_act", "kin", "prop", "cell", "starts", "order", "nbr_off", "nbr_j", "nbr_h",
         "nbr_off_out", "nbr_j_out", "nbr_h_out", "x_ref", "prm", "mask", "live_mask", "kept", "order_inv")
_REVERSE = ("lo", "n_frozen", "n_act", "nbr_off_out", "nbr_j_out", "rev_off", "rev_pos", "scratch", "rev_holder")
_REV_HOLDER = ("lo", "n_act", "nbr_off_out", "rev_pos", "rev_holder", "scratch")
_AWAKE = ("n_frozen", "n_act", "block", "kin", "surf_id", "prm", "blk_hot", "blk_box", "rev_off", "rev_holder",
          "tool_gap")


def _rebuild_steps(which: str, parallel: bool = False) -> KernelSequence:
    """sort: bin, sort, gather, count; sort_keep: the same, finding the cells where anything moved (the lists of
    still neighbourhoods are kept); lists: fill, reverse, blocks. parallel: the sort and the reverse lists from
    parallel loops (a GPU's; the same arrays). Built once per Taichi runtime."""
    _of_this_runtime(_REBUILDS)
    if (which, parallel) not in _REBUILDS:
        sort = dem.sort_by_bucket_parallel if parallel else dem.sort_by_bucket
        reverse = dem.build_reverse_parallel if parallel else dem.build_reverse
        steps = {"sort": [(dem.bin_particles, _BIN), (sort, _SORT),
                          (dem.gather_particles, _GATHER), (dem.count_neighbors, _COUNT)],
                 "sort_keep": [(dem.bin_particles, _BIN), (sort, _SORT),
                               (dem.mark_moved_cells, _MOVED), (dem.gather_particles, _GATHER),
                               (dem.count_neighbors, _COUNT)],
                 "lists": [(dem.fill_neighbors, _FILL), (reverse, _REVERSE),
                           (dem.fill_rev_holder, _REV_HOLDER), (dem.mark_awake_blocks, _AWAKE)]}[which]
        _REBUILDS[(which, parallel)] = KernelSequence(steps)
    return _REBUILDS[(which, parallel)]


_REBUILDS: dict = {}

# the kernels a run launches outside the substeps: rebuilds, the frozen prefix's partition, the observers' sums
WARM_KERNELS = ("bin_particles", "sort_by_bucket", "mark_moved_cells", "gather_particles", "count_neighbors",
                "fill_neighbors", "build_reverse", "fill_rev_holder", "mark_awake_blocks", "copy_i32", "mark_frozen",
                "thaw_layer", "frozen_clearance", "identity_prefix", "copy_entries", "totals", "surface_height",
                "mass_in_box")
_NDARRAYS = dict(kin=(dem.vec3, 2), prop=(dem.vec4, 1), nbr_off=(ti.i32, 1), nbr_j=(ti.i32, 1), nbr_h=(dem.vec6f, 1),
                 pair_out=(dem.vec3f, 2), own=(dem.vec3, 2), prm=(ti.f64, 1), flags=(ti.i32, 1), x_ref=(dem.vec4, 1),
                 rev_off=(ti.i32, 1), rev_pos=(ti.i32, 1), surf_id=(ti.i32, 2), surf_h=(dem.vec6f, 2),
                 tools=(ti.f64, 2), tool_acc=(ti.f64, 2), sdf=(dem.vec4f, 1), stat=(ti.f64, 1), partial=(ti.f64, 2),
                 blk_hot=(ti.i32, 1), blk_active=(ti.i32, 1), blk_box=(dem.vec3, 2), rev_holder=(ti.i32, 1),
                 blk_list=(ti.i32, 1), tools_in=(ti.f64, 2), report=(ti.f64, 1), tool_gap=(ti.f64, 1))
_SCALARS = dict(n_act=ti.i32, dt=ti.f64, bulk_damping=ti.f64, block=ti.i32, skip=ti.i32, todo=ti.i32, first=ti.i32,
                upload=ti.i32, n_frozen=ti.i32)
_BEGIN_ARGS = ("first", "upload", "tools_in", "tools", "tool_acc", "stat")
_SUBSTEP_ARGS = ("n_act", "block", "skip", "todo", "dt", "bulk_damping", "kin", "prop", "flags", "x_ref", "own",
                 "rev_off", "pair_out", "surf_id", "surf_h", "tools", "tool_acc", "sdf", "prm", "stat", "partial",
                 "blk_active", "blk_list", "blk_hot", "blk_box", "nbr_off", "nbr_j", "nbr_h", "rev_pos", "rev_holder",
                 "n_frozen", "tool_gap")
_END_ARGS = ("tools", "tool_acc", "stat", "report")


def _pit_faces(beds) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """Each bed's floor and four walls as (name, min corner, max corner, outward normal) of an axis-aligned
    rectangle: the walls span the floor to the ground (z = 0), as the kernels' pit faces do."""
    faces = []
    for k, (b_min, b_max) in enumerate(beds):
        top = np.array([b_max[0], b_max[1], 0.0])
        faces.append((f"the floor of soil.bed.{k}", b_min, np.array([b_max[0], b_max[1], b_min[2]]),
                      np.array([0.0, 0.0, -1.0])))
        for axis in (0, 1):
            for sign, corner in ((-1.0, b_min), (1.0, b_max)):
                lo, hi, out = b_min.copy(), top.copy(), np.zeros(3)
                lo[axis] = hi[axis] = corner[axis]
                out[axis] = sign
                faces.append((f"the {'-+'[sign > 0]}{'xy'[axis]} wall of soil.bed.{k}", lo, hi, out))
    return faces


class DemSoil:
    """Cohesive DEM soil in a domain with a ground plane, pits (beds) and kinematic tools."""

    name = "dem"
    version = SOLVER_VERSION
    solver_version = SOLVER_VERSION  # recorded in each run's manifest: results of another version are not reused

    def __init__(self, micro: SoilMicro, *, domain_min, domain_max, beds: list[tuple[tuple, tuple]],
                 seed: int = 0, dt: float | None = None, max_speed: float = 30.0, settle_time: float = 1.0,
                 use_cache: bool = True, gravity=(0.0, 0.0, -GRAVITY), skin: float | None = None,
                 on_settle=None, sleep: bool = False, surface=None, bulk=None):
        self.micro = micro
        self.bulk = bulk  # SoilBulk: the soil wedges' strength (set_cutting_edge); None: no wedges
        self.surface = surface  # (x, y, z[ix, iy]): fill beds to this surface instead of level (soil.terrain)
        self.sleep = bool(sleep)
        # skip whole blocks of sleeping particles (mark_blocks), keep the lists of still neighbourhoods at a
        # rebuild (count_neighbors); False does all the work, for the same bits
        self.skip_sleeping_blocks = True
        self.keep_still_lists = True
        self.freeze_far = True  # False: no frozen prefix (same physics, other particle order and round-off)
        self.n_frozen = 0
        self._forget_partition()
        self._on_settle = on_settle
        self.r_max = micro.radius * (1.0 + micro.polydispersity)
        self.domain_min, self.domain_max = _check_domain(domain_min, domain_max)
        self.beds = _check_beds(beds, self.domain_min, self.domain_max, self.r_max)
        if dt is None:
            dt = micro.dt_limit
        check_dt(micro, dt)
        self.dt = float(dt)
        if not max_speed > 0:
            raise UserError(f"soil.max_speed: expected a positive speed in m/s, got {max_speed!r}")
        self.max_speed = float(max_speed)
        self.seed = int(seed)
        self.gravity = _vec3(gravity, "soil.gravity")
        self.skin = SKIN_FRACTION * micro.radius if skin is None else float(skin)
        self.use_cache = use_cache
        self.time = 0.0
        self.n_act = 0
        self._entries = 0
        self.rebuilds = 0       # neighbour-list rebuilds so far (diagnostics)
        self.settle_speed = 0.0  # the fastest grain at the end of settling when the beds did not come to rest
        self.warnings: list[str] = []
        self.bed_packing: float | None = None  # solid fraction of the settled beds (None: no beds)
        self.bed_stacked: float | None = None  # share of their grains resting straight on the one beneath
        self._tool_names: list[str] = []
        self._tool_vertices: list[np.ndarray] = []  # each tool's mesh vertices, link frame (its cutting edge's checks)
        self._sdf_blocks: list[np.ndarray] = []
        self._tools_host = np.zeros((dem.MAX_TOOLS, dem.T_WIDTH))
        self._tools_on = np.zeros(dem.MAX_TOOLS, dtype=bool)  # which tools the kernels' rows have on
        self._tools_dirty = True
        self._last_impulse = np.zeros((0, 6))
        self._prm = ti.ndarray(ti.f64, dem.N_PRM)
        self._blk_hot = None
        self._set_prm(self._parameters())
        self._stat = ti.ndarray(ti.f64, dem.N_STAT)
        self._reset_stat()
        self._tools = ti.ndarray(ti.f64, (dem.MAX_TOOLS, dem.T_WIDTH))
        self._tool_acc = ti.ndarray(ti.f64, (dem.MAX_TOOLS, 6))
        self._sdf = ti.ndarray(dem.vec4f, 1)
        self._serial_cpu = current_arch() in ("x64", "arm64")  # serial loops for small work (CPU only)
        # the step loop's layout: blocks of particles for a CPU's few threads, one particle per thread on a GPU
        # (the same physics up to the order of the sums; the tests run it on the CPU too)
        self.per_particle = current_arch() in PER_PARTICLE_ARCHS
        self._tools_in = ti.ndarray(ti.f64, (dem.MAX_TOOLS, dem.T_WIDTH))  # the host's tool rows, uploaded
        self._report = ti.ndarray(ti.f64, dem.REPORT_SIZE)  # written by end_chunk, read once per run of substeps
        # (zero-copy views of both on the CPU; None on a GPU, where they are copied)
        self._tools_in_view, self._report_view = host_view(self._tools_in), host_view(self._report)
        self._sizes = ti.ndarray(ti.i32, dem.N_SIZES)  # a rebuild's counts (dem.SZ_*), read once per rebuild
        self._sizes_view = host_view(self._sizes)
        self._allocate(0)
        if self.beds:
            self._build_beds(settle_time)

    # ------------------------------------------------------------------------------------------- solver protocol
    @classmethod
    def map_parameters(cls, soil_cfg):
        """(SoilBulk, SoilMicro) of a scene's soil section: the preset with its overrides and the bulk-to-micro
        mapping (soil.py) for the deepest bed."""
        from .soil import bulk_to_micro, resolve_scene_soil

        bulk = resolve_scene_soil(soil_cfg)  # preset, preset file, overrides
        bed_depth = max((-float(b.min[2]) for b in soil_cfg.bed), default=1.0)
        return bulk, bulk_to_micro(bulk, bed_depth=max(bed_depth, 4 * bulk.radius))

    @classmethod
    def from_model(cls, soil, *, build_beds: bool = True, on_settle=None) -> "DemSoil":
        """The soil of a Model's SoilModel: beds poured and settled (or read from the cache), shifted and cleared
        as the scene says. build_beds=False leaves it empty, for a state that is about to be set.
        on_settle(simulated_s, of_at_most_s) is called as a bed settles (progress)."""
        self = cls(soil.params, domain_min=soil.domain_min, domain_max=soil.domain_max,
                   beds=[b for b in soil.beds] if build_beds else [], seed=soil.seed, dt=soil.dt,
                   max_speed=soil.max_speed, settle_time=soil.settle_time, on_settle=on_settle,
                   sleep=getattr(soil, "sleep", False), surface=getattr(soil, "surface", None),
                   bulk=getattr(soil, "bulk", None))
        if not build_beds:  # the kernels still need the pits as static geometry
            self.beds = _check_beds(list(soil.beds), self.domain_min, self.domain_max, self.r_max)
            self._set_prm(self._parameters())
        shift = np.asarray(soil.bed_shift, float)
        if build_beds and np.any(shift != 0.0):  # a settled block released above the ground (the pits stay, empty)
            self._shift_particles(shift)
        if soil.clear_above is not None:
            self.clear_above(float(soil.clear_above))
        return self

    # bytes per particle: the arrays of _allocate (both halves of the double buffers, ~0.8 kB) and ~8 neighbour
    # entries of ~84 B (1.45 kB), plus the host copies made while a bed settles
    BYTES_PER_PARTICLE = 2048

    @classmethod
    def check_model(cls, soil) -> dict:
        """What would fail when the soil is built, found before: beds too small for the grains, a domain too large
        for the cell hash, more particles than memory holds. Raises UserError naming the scene key; returns
        {'particles': estimated count, 'memory_bytes': estimated need}."""
        m = soil.params
        r_max = m.radius * (1.0 + m.polydispersity)
        lo, hi = np.asarray(soil.domain_min, float), np.asarray(soil.domain_max, float)
        for i, (b_min, b_max) in enumerate(soil.beds):
            side = float(np.min(np.asarray(b_max) - np.asarray(b_min)))
            if side < 4.0 * r_max:
                largest = side / (4.0 * (1.0 + m.polydispersity))
                raise UserError(f"soil.overrides.radius: {m.radius:g} m grains do not fit soil.bed.{i} (its "
                                f"smallest side, {side:g} m, must hold two grains of up to {r_max:g} m radius); the "
                                f"largest radius that fits is {math.floor(largest * 1e4) / 1e4:g} m")
        _check_beds(list(soil.beds), lo, hi, r_max)  # (overlaps, counts: what building the soil would refuse)
        cell = 2.0 * r_max + m.cohesion_range + SKIN_FRACTION * m.radius
        cells = float(np.max((hi - lo) / cell))
        if cells > dem.CELL_LIMIT:
            raise UserError(f"soil.domain: {cells:.3g} neighbour cells along one axis at {m.radius:g} m grains, at "
                            f"most {dem.CELL_LIMIT}; shrink the domain or use larger grains")
        v_mean = 4.0 / 3.0 * math.pi * m.radius ** 3 * (1.0 + m.polydispersity ** 2)
        volume = sum(float(np.prod(np.asarray(b) - np.asarray(a))) for a, b in soil.beds)
        particles = int(0.66 * volume / v_mean)  # the pour lattice (_pour_lattice) before trimming
        need = particles * cls.BYTES_PER_PARTICLE
        available = _available_memory()
        if available is not None and need > 0.8 * available:
            fits = m.radius * (need / (0.8 * available)) ** (1.0 / 3.0)
            raise UserError(f"soil.overrides.radius: {m.radius:g} m grains make about {particles:,} particles, "
                            f"which need about {need / 2**30:.1f} GiB; {available / 2**30:.1f} GiB of memory is "
                            f"available; the smallest radius that fits is about {math.ceil(fits * 1e4) / 1e4:g} m")
        return {"particles": particles, "memory_bytes": need}

    def describe(self) -> dict:
        """The manifest's soil block: solver, parameters, the settled bed's packing."""
        packing = self.bed_packing
        return {"solver": self.name, "solver_version": self.version, "wedge_version": WEDGE_VERSION, "sleep": self.sleep,
                "micro": asdict(self.micro),
                "bed_packing": packing, "bed_stacked": self.bed_stacked, "soil_dt": self.dt,
                "solid_density_effective": self.micro.bulk_density / packing if packing else None}

    _EXACT = ("kin", "prop", "flags", "x_ref", "surf_id", "surf_h", "nbr_off", "nbr_j", "nbr_h", "rev_off", "rev_pos",
              "stat", "prm")

    def get_state(self) -> dict[str, np.ndarray]:
        """Every array and counter the next substeps read, copied out: with set_state, a soil goes on bit for bit
        (the particle order, the neighbour lists with their springs and the Verlet reference positions included)."""
        n, e = self._n, self._entries
        size = dict(nbr_off=n + 1, rev_off=n + 1, nbr_j=e, nbr_h=e, rev_pos=e, stat=None, prm=None)
        out = {}
        for name in self._EXACT:
            arr = getattr(self, "_" + name).to_numpy()
            out[name] = arr if size.get(name, n) is None else arr[:size.get(name, n)].copy()
        out["tools_host"] = self._tools_host.copy()
        out["tools_host"][:, dem.T_TRAVEL] = 0.0  # (a bound the kernels keep for tool_gap, which a rebuild resets)
        out["counters"] = np.array([n, self.n_act, e, self.n_frozen, self._live_mask],  # (rebuilds: a diagnostic)
                                   dtype=np.int64)
        # the frozen prefix: its half of the cell table, and what decides the next partition
        nf = self.n_frozen
        out["frozen_starts"] = self._starts.to_numpy()[:self._mask + 2].copy() if nf else np.zeros(0, np.int32)
        out["frozen_cells"] = self._cell.to_numpy()[:nf].copy()
        out["partition"] = np.concatenate([self._partition.ravel(), self._clearance,
                                           [self._partition_time, float(self._repartition_due),
                                            float(self._slots_at_try)]])
        out["time"] = np.array(self.time, dtype=np.float64)
        out["bed_packing"] = np.array(np.nan if self.bed_packing is None else self.bed_packing)
        out["bed_stacked"] = np.array(np.nan if self.bed_stacked is None else self.bed_stacked)
        return out

    def set_state(self, state: dict[str, np.ndarray]) -> None:
        n, n_act, e = (int(v) for v in state["counters"][:3])
        if state["tools_host"].shape != self._tools_host.shape or len(state["prm"]) != dem.N_PRM:
            raise ValueError("the soil state was written by another layout of the DEM solver")
        self._allocate(n)
        if e > self._nbr_j.shape[0]:
            self._allocate_neighbors(e)
        for name in self._EXACT:
            target = getattr(self, "_" + name)
            value = np.asarray(state[name])
            if value.shape == tuple(target.shape) + tuple(getattr(target, "element_shape", ()) or ()):
                target.from_numpy(value)
                continue
            full = target.to_numpy()
            full[:len(value)] = value
            target.from_numpy(full)
        self.n_act, self._entries = n_act, e
        self._active_slots = int(self._stat.to_numpy()[dem.S_ACTIVE])  # (the last run of substeps': layout, freezing)
        self._lists_built = self._lists_keepable = True  # (the lists of a build, with their reference positions)
        self.n_frozen = int(state["counters"][3]) if len(state["counters"]) > 3 else 0
        self._live_mask = int(state["counters"][4]) if len(state["counters"]) > 4 else self._mask
        if "partition" in state:
            part = np.asarray(state["partition"], dtype=np.float64)
            self._partition = part[:dem.MAX_TOOLS * 4].reshape(dem.MAX_TOOLS, 4).copy()
            self._clearance = part[dem.MAX_TOOLS * 4:dem.MAX_TOOLS * 5].copy()
            self._partition_time, self._repartition_due = float(part[-3]), bool(part[-2])
            self._slots_at_try = int(part[-1])
        if self.n_frozen:
            starts = self._starts.to_numpy()
            starts[:self._mask + 2] = state["frozen_starts"]
            self._starts.from_numpy(starts)
            cells = self._cell.to_numpy()
            cells[:self.n_frozen] = state["frozen_cells"]
            self._cell.from_numpy(cells)
            self._mirror_frozen()
        self._rebuilt_from = 0
        self._blocks_changed()
        self.time = float(state["time"])
        packing = float(state["bed_packing"])
        self.bed_packing = None if np.isnan(packing) else packing
        stacked = float(state.get("bed_stacked", np.nan))  # (a state written before it was measured: unknown)
        self.bed_stacked = None if np.isnan(stacked) else stacked
        spheres = self._tools_host[:, dem.T_BS:dem.T_BS + 4].copy()  # (the registered tools', not the state's)
        self._tools_host[:] = state["tools_host"]
        self._tools_host[:, dem.T_BS:dem.T_BS + 4] = spheres
        self._tools_dirty = True

    # ------------------------------------------------------------------------------------------- set-up
    def _parameters(self) -> np.ndarray:
        m = self.micro
        prm = np.zeros(dem.N_PRM)
        prm[dem.P_KN] = m.k_n
        # dashpot tuned so a collision of two mean spheres integrated with this dt rebounds with e exactly
        prm[dem.P_DAMP] = damping_for_step(m.restitution, self.dt * math.sqrt(2.0 * m.k_n / m.particle_mass))
        prm[dem.P_MU] = m.mu
        prm[dem.P_MU_R] = m.mu_r
        prm[dem.P_COH_F] = m.cohesion_force
        prm[dem.P_COH_D] = m.cohesion_range
        prm[dem.P_K_WALL] = m.k_wall
        prm[dem.P_MU_WALL] = m.mu_wall
        prm[dem.P_K_TOOL] = m.k_tool
        prm[dem.P_MU_TOOL] = m.mu_tool
        prm[dem.P_ADH_F] = m.adhesion_force
        prm[dem.P_ADH_D] = m.adhesion_range
        prm[dem.P_G:dem.P_G + 3] = self.gravity
        prm[dem.P_DMIN:dem.P_DMIN + 3] = self.domain_min
        prm[dem.P_DMAX:dem.P_DMAX + 3] = self.domain_max
        prm[dem.P_CELL] = 2.0 * self.r_max + m.cohesion_range + self.skin
        prm[dem.P_SKIN] = self.skin
        prm[dem.P_NPITS] = len(self.beds)
        prm[dem.P_ETA_R] = m.rolling_damping
        prm[dem.P_KT_RATIO] = m.k_t / m.k_n
        prm[dem.P_SQRT_KN] = math.sqrt(m.k_n)
        prm[dem.P_SQRT_KWALL] = math.sqrt(m.k_wall)
        prm[dem.P_SQRT_KTOOL] = math.sqrt(m.k_tool)
        if self.sleep:  # quiet: below the speed a settled bed counts as at rest, for SLEEP_AFTER of simulated time
            prm[dem.P_SLEEP_STEPS] = max(1, int(round(SLEEP_AFTER / self.dt)))
            prm[dem.P_SLEEP_V2] = (SLEEP_SPEED * math.sqrt(GRAVITY * m.radius)) ** 2
        for k, (b_min, b_max) in enumerate(self.beds):
            prm[dem.P_PITS + 6 * k:dem.P_PITS + 6 * k + 6] = np.concatenate([b_min, b_max])
        if self.bulk is not None:  # the soil wedges' strength: the bulk soil's, as the earthmoving equation takes it
            b = self.bulk
            prm[dem.P_WG_PHI] = b.friction_angle
            prm[dem.P_WG_DELTA] = tool_friction_angle(b)
            prm[dem.P_WG_C] = b.cohesion
            prm[dem.P_WG_CA] = b.adhesion
            prm[dem.P_WG_GAMMA] = b.density * float(np.linalg.norm(self.gravity))
        return prm

    def _allocate(self, n: int) -> None:
        cap = max(n, 1)
        table = 64
        while table < 2 * cap:
            table *= 2
        # Buckets are the low bits of the cells' Morton codes: in a table that spans fewer cells than the domain,
        # distant cells share buckets, the sort interleaves them and a block of particles spans the domain (and
        # cannot be skipped while anything near either end moves). Grow it to the domain's extent where that costs
        # at most MORTON_TABLE_PER_PARTICLE entries per particle.
        cell = 2.0 * self.r_max + self.micro.cohesion_range + self.skin
        cells = int(np.max(np.ceil((self.domain_max - self.domain_min) / cell))) + 3
        extent = 1 << (3 * max(1, math.ceil(math.log2(cells))))
        while table < min(extent, MORTON_TABLE_PER_PARTICLE * cap, MORTON_TABLE_MAX):
            table *= 2
        self._n = n
        self._mask = table - 1
        self._live_mask = self._mask  # the live particles' part of the table (smaller while a prefix is frozen)
        nd = ti.ndarray
        self._kin, self._kin2 = (nd(dem.vec3, (cap, 3)) for _ in range(2))
        self._prop, self._prop2 = (nd(dem.vec4, cap) for _ in range(2))
        self._flags, self._flags2 = (nd(ti.i32, cap) for _ in range(2))
        self._cell, self._cell2 = (nd(ti.i64, cap) for _ in range(2))
        self._surf_id, self._surf_id2 = (nd(ti.i32, (cap, dem.SURF_ID_WIDTH)) for _ in range(2))
        self._surf_h, self._surf_h2 = (nd(dem.vec6f, (cap, dem.SURF_SLOTS)) for _ in range(2))
        self._x_ref = nd(dem.vec4, cap)
        self._tool_gap = nd(ti.f64, cap)
        self._tool_gap.fill(-dem.HUGE)
        self._own = nd(dem.vec3, (cap, 4))  # (2, 3: a wedge grain's way out of its overlaps, the wedge roles)
        blocks = max(min(cap, dem.STEP_BLOCKS), cap // dem.BLOCK) + 1
        self._partial = nd(ti.f64, (blocks, dem.PART_WIDTH))
        self._blk_hot, self._blk_active = nd(ti.i32, blocks), nd(ti.i32, blocks)
        self._blk_box = nd(dem.vec3, (blocks, 2))
        self._blk_list = nd(ti.i32, blocks + 1)
        self._blk_hot.fill(1)
        self._rev_off = nd(ti.i32, cap + 1)
        self._bucket = nd(ti.i32, cap)
        self._order = nd(ti.i32, cap)
        self._order_inv = nd(ti.i32, cap)
        self._kept = nd(ti.i32, cap)
        self._moved = nd(ti.i32, 2 * table + 2)   # (two halves: the frozen prefix's cells, the live particles')
        self._lists_built = False
        self._lists_keepable = False
        self._counts = nd(ti.i32, 2 * table + 1)
        self._starts = nd(ti.i32, 2 * table + 2)
        self._freeze = nd(ti.i32, cap)
        self._rebuilt_from = 0
        self.n_frozen = 0
        self._nbr_off, self._nbr_off2 = (nd(ti.i32, cap + 1) for _ in range(2))
        self._allocate_neighbors(NEIGHBORS_PER_PARTICLE * cap)
        self._nbr_off.fill(0)
        self._flags.fill(0)
        self.n_act = 0

    def _allocate_neighbors(self, entries: int) -> None:
        entries = max(entries, 1)
        self._nbr_j, self._nbr_j2 = (ti.ndarray(ti.i32, entries) for _ in range(2))
        self._nbr_h, self._nbr_h2 = (ti.ndarray(dem.vec6f, entries) for _ in range(2))
        self._rev_pos = ti.ndarray(ti.i32, entries)
        self._rev_holder = ti.ndarray(ti.i32, entries)
        self._pair_out = ti.ndarray(dem.vec3f, (entries + 1, 2))  # + the scratch slot (build_reverse)

    def set_particles(self, positions, velocities=None, radii=None, angular_velocities=None) -> None:
        """Replace every particle (state only; contact history starts empty) and restart the mass budget.

        radii default to the soil's mean radius; masses follow from the solid density.
        """
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        n = len(pos)
        vel = np.zeros((n, 3)) if velocities is None else np.asarray(velocities, dtype=np.float64).reshape(n, 3)
        omg = np.zeros((n, 3)) if angular_velocities is None else \
            np.asarray(angular_velocities, dtype=np.float64).reshape(n, 3)
        rad = np.full(n, self.micro.radius) if radii is None else np.asarray(radii, dtype=np.float64).reshape(n)
        if n and (not np.all(rad > 0) or rad.max() > self.r_max * (1 + 1e-9)):
            raise ValueError(f"radii must lie in (0, {self.r_max:g}] (the soil's largest radius)")
        self._allocate(n)
        if n == 0:
            self._reset_stat()
            return
        mass = self.micro.solid_density * 4.0 / 3.0 * math.pi * rad ** 3
        prop = np.stack([rad, mass, 1.0 / mass, mass ** 0.25], axis=1)
        self._kin.from_numpy(np.stack([pos, vel, omg], axis=1))
        self._prop.from_numpy(prop)
        self._flags.fill(1)
        dem.reset_contacts(n, self._nbr_off, self._surf_id, self._surf_h)
        self._reset_stat()
        self._rebuild()

    def add_particles(self, positions, velocities=None, radii=None) -> None:
        """Add particles (masses from the solid density of the settled beds) and keep every existing particle's
        state and contact history, sleep included; the new ones start awake, without contacts."""
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        k = len(pos)
        vel = np.zeros((k, 3)) if velocities is None else np.asarray(velocities, dtype=np.float64).reshape(k, 3)
        rad = np.full(k, self.micro.radius) if radii is None else np.asarray(radii, dtype=np.float64).reshape(k)
        if k and (not np.all(rad > 0) or rad.max() > self.r_max * (1 + 1e-9)):
            raise ValueError(f"radii must lie in (0, {self.r_max:g}] (the soil's largest radius)")
        st = self.get_state()
        n, n_act, e = (int(v) for v in st["counters"][:3])
        if n != n_act:
            self._rebuild()  # drop the particles that left the domain first, so the active ones come first
            st = self.get_state()
            n, n_act, e = (int(v) for v in st["counters"][:3])
        prop = st["prop"]
        scale = prop[0, 1] / (self.micro.solid_density * 4.0 / 3.0 * math.pi * prop[0, 0] ** 3) if n else 1.0
        mass = scale * self.micro.solid_density * 4.0 / 3.0 * math.pi * rad ** 3
        st["kin"] = np.concatenate([st["kin"], np.stack([pos, vel, np.zeros((k, 3))], axis=1)])
        st["prop"] = np.concatenate([prop, np.stack([rad, mass, 1.0 / mass, mass ** 0.25], axis=1)])
        st["flags"] = np.concatenate([st["flags"], np.ones(k, st["flags"].dtype)])
        st["x_ref"] = np.concatenate([st["x_ref"], np.concatenate([pos, np.zeros((k, 1))], axis=1)])
        free = np.full((k, dem.SURF_ID_WIDTH), -1, st["surf_id"].dtype)
        free[:, dem.TOOL_BITS] = 0
        st["surf_id"] = np.concatenate([st["surf_id"], free])
        st["surf_h"] = np.concatenate([st["surf_h"], np.zeros((k,) + st["surf_h"].shape[1:], st["surf_h"].dtype)])
        for name in ("nbr_off", "rev_off"):
            st[name] = np.concatenate([st[name], np.full(k, st[name][-1], st[name].dtype)])
        st["counters"] = np.array([n + k, n_act + k, e], dtype=np.int64)
        self.set_state(st)
        self._lists_keepable = False  # (the new particles have no lists yet)
        self._rebuild()  # the new particles' pairs

    def _rebuild(self, keep_still: bool = False) -> None:
        """Sort particles by cell, drop inactive ones to the end, rebuild the neighbour lists (history kept).

        keep_still: the lists were built by the last rebuild and only the motion since has made this one needed
        (not new or replaced particles): only the particles after the frozen prefix are rebuilt, and those around
        which nothing moved keep their lists (the same lists, without the search). Otherwise the whole soil is
        rebuilt and partitioned anew (the frozen prefix: FREEZE_MIN, FREEZE_FEWEST), the lists of still
        neighbourhoods kept as well unless particles or parameters changed since the last build."""
        n = self._n
        if n == 0:
            self.n_act = 0
            self.n_frozen = 0
            return
        self.rebuilds += 1
        keep = self.keep_still_lists and self._lists_built and self._lists_keepable
        if keep_still and self._lists_built:
            self._rebuild_live(keep=keep)
        else:
            self._rebuild_all(keep=keep)
        self._lists_built = True
        self._lists_keepable = True
        if not self.n_act:
            self._blk_hot.fill(1)  # (the lists' kernels marked the blocks of the particles there are)

    def _swap_particles(self) -> None:
        self._kin, self._kin2 = self._kin2, self._kin
        self._prop, self._prop2 = self._prop2, self._prop
        self._flags, self._flags2 = self._flags2, self._flags
        self._surf_id, self._surf_id2 = self._surf_id2, self._surf_id
        self._surf_h, self._surf_h2 = self._surf_h2, self._surf_h
        self._cell, self._cell2 = self._cell2, self._cell

    def _sort_args(self, lo: int, keep: bool) -> dict:
        """The arguments of a rebuild's first run of kernels (bin, sort, gather, count) by name; `*_out` the spare
        buffers they write into. What the sort changes (the active count, the blocks) is not among them."""
        return dict(lo=int(lo), n=int(self._n), n_frozen=int(self.n_frozen), n_listed=int(self.n_act),
                    keep=int(keep), use_frozen=0, was_frozen=int(self.n_frozen), kin=self._kin, kin_out=self._kin2,
                    prop=self._prop, prop_out=self._prop2, flags=self._flags, flags_out=self._flags2,
                    surf_id=self._surf_id, surf_id_out=self._surf_id2, surf_h=self._surf_h, surf_h_out=self._surf_h2,
                    cell=self._cell, cell_out=self._cell2, freeze=self._freeze, bucket=self._bucket,
                    counts=self._counts, starts=self._starts, order=self._order, order_inv=self._order_inv,
                    moved=self._moved, kept=self._kept, x_ref=self._x_ref, prm=self._prm, mask=self._mask,
                    live_mask=self._live_mask, sizes=self._sizes, nbr_off=self._nbr_off, nbr_off_out=self._nbr_off2)

    def _lists_args(self, lo: int, n_act: int) -> dict:
        """The arguments of its second run (fill, reverse, blocks), once the sort and count are read back and the
        spare lists have room."""
        return dict(lo=int(lo), n_frozen=int(self.n_frozen), n_act=int(n_act),
                    block=dem.reduction_block(n_act - self.n_frozen), kin=self._kin, prop=self._prop,
                    cell=self._cell, surf_id=self._surf_id, starts=self._starts, order=self._order,
                    order_inv=self._order_inv, kept=self._kept, x_ref=self._x_ref, prm=self._prm, mask=self._mask,
                    live_mask=self._live_mask, nbr_off=self._nbr_off, nbr_off_out=self._nbr_off2,
                    nbr_j=self._nbr_j, nbr_j_out=self._nbr_j2, nbr_h=self._nbr_h, nbr_h_out=self._nbr_h2,
                    rev_off=self._rev_off, rev_pos=self._rev_pos, rev_holder=self._rev_holder,
                    scratch=self._scratch, blk_hot=self._blk_hot, blk_box=self._blk_box, tool_gap=self._tool_gap)

    def _read_sizes(self) -> tuple[int, int]:
        """(active particles, list entries) as the last sort and count left them."""
        sizes = self._sizes_view if self._sizes_view is not None else self._sizes.to_numpy()
        return int(sizes[dem.SZ_ACTIVE]), int(sizes[dem.SZ_ENTRIES])

    def _list_neighbors(self, lo: int) -> None:
        """After count_neighbors (the lists of particles lo..n_act counted into the spare offsets): grow the spare
        lists if they are short, fill them, swap, reverse lists, and the blocks of the next substep."""
        nf = self.n_frozen
        n_act, entries = self._read_sizes()
        if entries > self._nbr_j2.shape[0]:
            # a denser packing than the lists were sized for: grow the spare lists (the old ones stay intact), and
            # keep what the frozen prefix's entries and reverse slots hold
            grown = int(entries * 1.25) + 64
            frozen_entries = int(self._nbr_off[nf]) if lo > 0 else 0
            frozen_slots = int(self._rev_off[nf]) if lo > 0 else 0
            nbr_j2, nbr_h2 = ti.ndarray(ti.i32, grown), ti.ndarray(dem.vec6f, grown)
            rev_pos, rev_holder = ti.ndarray(ti.i32, grown), ti.ndarray(ti.i32, grown)
            if frozen_entries:
                dem.copy_entries(nf, frozen_entries, self._nbr_off, self._nbr_j, self._nbr_h, self._nbr_off2, nbr_j2,
                                 nbr_h2)
                dem.copy_i32(frozen_entries, self._rev_pos, rev_pos)
                dem.copy_i32(frozen_slots, self._rev_holder, rev_holder)
            self._nbr_j2, self._nbr_h2, self._rev_pos, self._rev_holder = nbr_j2, nbr_h2, rev_pos, rev_holder
            self._pair_out = ti.ndarray(dem.vec3f, (grown + 1, 2))
        _rebuild_steps("lists", self.per_particle).run(self._lists_args(lo, n_act))
        self._nbr_off, self._nbr_off2 = self._nbr_off2, self._nbr_off
        self._nbr_j, self._nbr_j2 = self._nbr_j2, self._nbr_j
        self._nbr_h, self._nbr_h2 = self._nbr_h2, self._nbr_h
        self.n_act = n_act
        self._entries = entries
        self._rebuilt_from = lo

    @property
    def _scratch(self) -> int:
        return self._pair_out.shape[0] - 1

    def _rebuild_all(self, keep: bool) -> None:
        """keep: the lists of the particles around which nothing moved, joined or left the frozen prefix are kept."""
        n = self._n
        was_frozen = self.n_frozen
        nf = 0
        if self.freeze_far and self.sleep and self._lists_built and self.skip_sleeping_blocks and n >= FREEZE_MIN:
            self._upload_tool_rows()
            nf = int(dem.mark_frozen(n, self.n_act, self._kin, self._flags, self._surf_id, self._prm, self._tools_in,
                                     self._freeze_margin(), self._freeze))
            for _ in range(FREEZE_LAYERS):  # (_kept: scratch until the lists are counted)
                nf = int(dem.thaw_layer(self.n_act, self._freeze, self._kept, self._nbr_off, self._nbr_j,
                                        self._rev_off, self._rev_holder))
                self._freeze, self._kept = self._kept, self._freeze
            clearance = ti.ndarray(ti.f64, dem.MAX_TOOLS)
            dem.frozen_clearance(self.n_act, self._kin, self._freeze, self._tools_in, clearance)
            self._clearance = clearance.to_numpy()
            self._partition = self._tool_spheres()
            self._partition_time = self.time
            self._slots_at_try = self._active_slots or self.n_act
        if nf < FREEZE_FEWEST:
            nf = 0
        self._repartition_due = False
        self._live_mask = self._mask
        if nf:  # the live part's table sized for the live particles, as the whole table is for all (_allocate)
            live_table = 64
            while live_table < min(MORTON_TABLE_PER_PARTICLE * (n - nf), self._mask + 1):
                live_table *= 2
            self._live_mask = live_table - 1
        self.n_frozen = nf
        args = self._sort_args(0, keep=keep)
        args.update(use_frozen=int(nf > 0), was_frozen=was_frozen)
        _rebuild_steps("sort_keep" if keep else "sort", self.per_particle).run(args)
        self._swap_particles()
        self._list_neighbors(0)
        if nf:
            self._mirror_frozen()

    def _rebuild_live(self, keep: bool) -> None:
        _rebuild_steps("sort_keep" if keep else "sort", self.per_particle).run(self._sort_args(self.n_frozen, keep))
        self._swap_particles()
        self._list_neighbors(self.n_frozen)

    def _mirror_frozen(self) -> None:
        """The frozen prefix into the spare particle and list buffers (a rebuild of the live part swaps them in),
        and its slots mapped to themselves (the live part's rebuilds look its particles up by old index)."""
        nf = self.n_frozen
        dem.identity_prefix(nf, self._order, self._order_inv)
        dem.gather_particles(0, nf, self._order, self._kin, self._kin2, self._prop, self._prop2, self._flags,
                             self._flags2, self._surf_id, self._surf_id2, self._surf_h, self._surf_h2, self._cell,
                             self._cell2)
        frozen_entries = int(self._nbr_off[nf])
        if self._nbr_j2.shape[0] < self._nbr_j.shape[0]:
            self._nbr_j2 = ti.ndarray(ti.i32, self._nbr_j.shape[0])
            self._nbr_h2 = ti.ndarray(dem.vec6f, self._nbr_j.shape[0])
        dem.copy_entries(nf, frozen_entries, self._nbr_off, self._nbr_j, self._nbr_h, self._nbr_off2, self._nbr_j2,
                         self._nbr_h2)

    def _freeze_margin(self) -> float:
        return max(FREEZE_MARGIN, 4.0 * (self.r_max + self.skin + self.micro.adhesion_range))

    def _tool_spheres(self) -> np.ndarray:
        """(MAX_TOOLS, 4): each tool's on flag and the world centre of its bounding sphere (host rows)."""
        rows = self._tools_host
        on = rows[:, dem.T_ON] > 0.0
        rot = rows[:, dem.T_ROT:dem.T_ROT + 9].reshape(-1, 3, 3)
        centres = rows[:, dem.T_POS:dem.T_POS + 3] + (rot @ rows[:, dem.T_BS:dem.T_BS + 3, None])[:, :, 0]
        return np.where(on[:, None], np.column_stack([np.ones(len(rows)), centres]), 0.0)

    def _partition_stale(self) -> bool:
        """Whether the next substeps need a new partition: the tools moved or switched, new parameters, or (nothing
        frozen in a big sleeping bed) FREEZE_RETRY has passed."""
        if not (self.freeze_far and self.sleep and self._n >= FREEZE_MIN and self._lists_built):
            return self.n_frozen > 0
        if self._repartition_due:
            return True
        if self.n_frozen == 0:
            waited = self.time - self._partition_time
            return waited >= FREEZE_RETRY or (waited >= FREEZE_SOON and 2 * self._active_slots < self._slots_at_try)
        # (plain floats: this runs before every rigid step of a frozen soil, where NumPy's small-array calls cost
        # ~50 us, 3% of the site's run)
        half_margin = 0.5 * self._freeze_margin()
        for row, then, clearance in zip(self._tools_host.tolist(), self._partition.tolist(), self._clearance.tolist()):
            if (row[dem.T_ON] > 0.0) != (then[0] != 0.0):
                return True
            if then[0] != 0.0:
                rot = row[dem.T_ROT:dem.T_ROT + 9]
                bx, by, bz = row[dem.T_BS:dem.T_BS + 3]
                dx = row[dem.T_POS] + rot[0] * bx + rot[1] * by + rot[2] * bz - then[1]
                dy = row[dem.T_POS + 1] + rot[3] * bx + rot[4] * by + rot[5] * bz - then[2]
                dz = row[dem.T_POS + 2] + rot[6] * bx + rot[7] * by + rot[8] * bz - then[3]
                if math.sqrt(dx * dx + dy * dy + dz * dz) > clearance - half_margin:
                    return True
        return False

    def _set_prm(self, prm: np.ndarray) -> None:
        """Upload the parameters. Who is asleep depends on them (P_SLEEP_STEPS): every block takes part in the next
        substep, so a particle the new values wake is integrated at once."""
        self._prm.from_numpy(prm)
        self._lists_keepable = False  # (a list's reach may have changed: the next rebuild searches them all)
        if self._blk_hot is not None:
            self._blk_hot.fill(1)
            self._tool_gap.fill(-dem.HUGE)  # (a sleeping particle's reach may have changed)
            self._repartition_due = True  # (the frozen prefix is found anew before the next substeps)

    def _blocks_changed(self) -> None:
        """After the particle order or the lists changed: the blocks that take part in the next substep are found
        anew from the particles (mark_awake_blocks)."""
        if self.n_act:
            dem.fill_rev_holder(self._rebuilt_from, self.n_act, self._nbr_off, self._rev_pos, self._rev_holder,
                                self._scratch)
            dem.mark_awake_blocks(self.n_frozen, self.n_act, self._block, self._kin, self._surf_id, self._prm,
                                  self._blk_hot, self._blk_box, self._rev_off, self._rev_holder, self._tool_gap)
        else:
            self._blk_hot.fill(1)

    # ------------------------------------------------------------------------------------------- beds
    def _cache_key(self, settle_time: float) -> str:
        # keyed by what the settling depends on: no tool touches a bed while it settles, so not the adhesion
        micro = {k: v for k, v in asdict(self.micro).items() if k not in ("adhesion_force", "adhesion_range")}
        spec = dict(version=SOLVER_VERSION, micro=micro, beds=[(a.tolist(), b.tolist()) for a, b in self.beds],
                    domain=(self.domain_min.tolist(), self.domain_max.tolist()), seed=self.seed, dt=self.dt,
                    gravity=self.gravity.tolist(), settle_time=settle_time, frictionless=POUR_FRICTIONLESS,
                    pour=dict(gap=POUR_GAP, scatter=POUR_SCATTER), compiled_for=compiled_for())
        if self.surface is not None:  # a bed filled to a scanned surface: keyed by that surface
            spec["surface"] = hashlib.sha256(b"".join(np.ascontiguousarray(a, np.float64).tobytes()
                                                      for a in self.surface)).hexdigest()
        return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:32]

    def _build_beds(self, settle_time: float) -> None:
        path = cache_dir() / "dem_beds" / f"{self._cache_key(settle_time)}.npz"
        if self.use_cache and path.is_file():
            try:
                self._load_state(path)
                self.bed_packing = self._measure_packing()
                self._check_settled(settle_time)
                self._check_stacking()
                self._start_asleep()
                return
            except (OSError, KeyError, ValueError):
                pass  # unreadable cache entry: settle again
        pos, rad, vel = self._pour_lattice()
        self.set_particles(pos, vel, radii=rad)
        self._settle(settle_time)
        state = self._state_arrays()
        if self.use_cache:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".tmp{np.random.randint(1 << 30)}.npz")
            np.savez(tmp, settle_speed=np.array(self.settle_speed), **state)
            tmp.replace(path)
        # go on from exactly what a run from the cache starts from (the settled particles alone, with their hash
        # table sized for them): the first run of a scene then gives the same numbers as every later one
        self._set_state(state)
        self.bed_packing = self._measure_packing()  # measured as a run from the cache measures it
        self._check_settled(settle_time)
        self._check_stacking()
        self._start_asleep()

    def _start_asleep(self) -> None:
        """With soil.sleep, a settled bed starts asleep: its grains are at rest (velocities zeroed at the end of the
        settling), so a big bed is not integrated whole for SLEEP_AFTER first and can be frozen at once. A bed that
        had not come to rest (the warning) starts asleep too, as it stands: a grain still falling hangs until a tool
        or moving soil wakes it."""
        if not self.sleep or self.n_act == 0:
            return
        surf = self._surf_id.to_numpy()
        word = surf[:self.n_act, dem.TOOL_BITS]
        surf[:self.n_act, dem.TOOL_BITS] = (word & dem.TOOL_MASK) | (dem.CALM_MAX << dem.CALM_SHIFT)
        self._surf_id.from_numpy(surf)
        self._blocks_changed()

    def _check_settled(self, settle_time: float) -> None:
        if self.settle_speed > 0.0:
            self.warnings.append(f"soil: the bed did not come to rest in soil.settle_time = {settle_time:g} s (a grain "
                                 f"still moved at {self.settle_speed:.3g} m/s); it goes on settling at the start of "
                                 f"the run, or with soil.sleep it starts asleep as it stands (grains still falling "
                                 f"hang until a tool or moving soil wakes them): raise soil.settle_time")

    def _check_stacking(self) -> None:
        """Measure how much of the settled beds stands as a cubic stack (stacked_fraction) and warn above
        STACKED_WARN: a bed a few grains deep or across keeps the poured lattice (docs/validation.md, calibration
        note 1)."""
        parts = self.particles(("positions", "radii"))
        pos, rad = parts["positions"], parts["radii"]
        floors = self._bed_floors(pos)
        inside = np.isfinite(floors)
        self.bed_stacked = stacked_fraction(pos[inside], rad[inside], floors[inside])
        if self.bed_stacked is not None and self.bed_stacked > STACKED_WARN:
            self.warnings.append(
                f"soil: {self.bed_stacked:.0%} of the settled bed's grains rest straight on the grain beneath, as the "
                f"pour's cubic lattice stacked them (beds a few grains deep or across keep it): such a stack stands "
                f"steeper and spreads less than loose soil (docs/validation.md, calibration note 1); finer grains "
                f"(soil.overrides.radius) settle into a random packing")

    def _pour_lattice(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Jittered cubic lattice over each pit, tall enough that the settled bed overfills it a little: positions,
        radii and velocities (at rest, or a random sideways start of POUR_SCATTER sqrt(g d))."""
        rng = np.random.default_rng(self.seed)
        r, r_max = self.micro.radius, self.r_max
        s = 2.0 * r_max * POUR_GAP
        v_mean = 4.0 / 3.0 * math.pi * r ** 3 * (1.0 + self.micro.polydispersity ** 2)  # E[r^3] ~ r^3 (1 + p^2)
        positions = []
        for i, (b_min, b_max) in enumerate(self.beds):
            inner_lo = b_min + r_max * 1.02
            inner_hi = b_max - r_max * 1.02
            nx, ny = (np.floor((inner_hi[:2] - inner_lo[:2]) / s).astype(int) + 1)
            # settles at ~0.6: fill ~10% over, trim later (to the bed's top, or its scanned surface: up to its highest)
            target = 0.66 * np.prod((b_max - b_min)[:2]) * (self._highest_top(b_min, b_max) - b_min[2]) / v_mean
            layers = int(math.ceil(target / (nx * ny)))
            top = inner_lo[2] + (layers - 1) * s
            if top > self.domain_max[2] - r_max:
                raise UserError(f"soil.domain.max: z = {self.domain_max[2]:g} leaves no room to pour soil.bed.{i} "
                                f"(its particles start up to z = {top + r_max:.3g})")
            xs = inner_lo[0] + s * np.arange(nx) + (inner_hi[0] - inner_lo[0] - s * (nx - 1)) / 2
            ys = inner_lo[1] + s * np.arange(ny) + (inner_hi[1] - inner_lo[1] - s * (ny - 1)) / 2
            zs = inner_lo[2] + s * np.arange(layers)
            grid = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)
            jitter = rng.uniform(-1.0, 1.0, grid.shape) * (0.5 * (s - 2.0 * r_max))
            positions.append(grid + jitter)
        pos = np.concatenate(positions)
        rad = r * (1.0 + self.micro.polydispersity * rng.uniform(-1.0, 1.0, len(pos)))
        vel = np.zeros_like(pos)
        if POUR_SCATTER:  # (its own random stream: the lattice is the same with and without it)
            heading = np.random.default_rng((self.seed, 1)).uniform(0.0, 2.0 * math.pi, len(pos))
            speed = POUR_SCATTER * math.sqrt(GRAVITY * 2.0 * r)
            vel[:, 0], vel[:, 1] = speed * np.cos(heading), speed * np.sin(heading)
        return pos, rad, vel

    def _settle(self, settle_time: float) -> None:
        """Let the poured lattice fall and come to rest, trim it level with the bed tops, rest again."""
        fall = max(float(np.max(self.particles()["positions"][:, 2])) - min(b[0][2] for b in self.beds), 0.0)
        t_fall = math.sqrt(2.0 * fall / GRAVITY) + 0.05
        self._settled_for = 0.0  # simulated settling so far, of at most _settle_budget (progress only)
        self._settle_budget = max(0.6 * settle_time, 2.0 * t_fall) + max(0.2 * settle_time, 1e-3) + \
            max(0.5 * settle_time, 1e-3) + max(0.3 * settle_time, 1e-3)
        quiet = 0.02 * math.sqrt(GRAVITY * self.micro.radius)  # max speed considered at rest
        # pour with the soil's friction and rolling resistance (POUR_FRICTIONLESS) but without cohesion and with
        # smooth pit walls (a rough tall column would hang on them); the pit walls reach up meanwhile, so the
        # column above the pit cannot spill over the rim. The lattice holds 0.66 x the pit volume of solid:
        # enough to overfill it at any packing below 0.66.
        loose = self._parameters()
        if POUR_FRICTIONLESS:
            loose[[dem.P_MU, dem.P_MU_R, dem.P_MU_WALL, dem.P_COH_F]] = 0.0
        else:
            loose[[dem.P_MU_WALL, dem.P_COH_F]] = 0.0
        loose[dem.P_WALL_TOP] = 1e30
        loose[dem.P_SLEEP_STEPS] = 0.0  # the bed settles awake: a cached bed does not depend on soil.sleep
        self._set_prm(loose)
        self._run_until_quiet(max(0.6 * settle_time, 2.0 * t_fall), t_fall, quiet, SETTLE_DAMPING)  # it must land
        # friction on (the slow creep of a frictionless packing stops), then level the beds and let them rest
        loose[[dem.P_MU, dem.P_MU_R, dem.P_MU_WALL, dem.P_COH_F]] = self._parameters()[
            [dem.P_MU, dem.P_MU_R, dem.P_MU_WALL, dem.P_COH_F]]
        self._set_prm(loose)
        self._run_until_quiet(max(0.2 * settle_time, 1e-3), 0.02, quiet, SETTLE_DAMPING)
        self._set_prm(self._settle_parameters())
        self._trim_to_beds()
        # on the grains kept (the levelled top packs looser), before the rest of the settling: the bed rests under
        # its final weight
        self._match_bulk_density()
        # a loose (friction-poured) bed keeps creeping for a while after levelling: rest it until quiet
        self._run_until_quiet(max(0.5 * settle_time, 1e-3), 0.02, quiet, SETTLE_DAMPING)
        speed = self._run_until_quiet(max(0.3 * settle_time, 1e-3), 0.0, quiet, 0.0)
        self.settle_speed = speed if speed >= quiet else 0.0
        kin = self._kin.to_numpy()
        kin[:, 1:] = 0.0
        self._kin.from_numpy(kin)
        self._reset_stat()
        self.time = 0.0
        self._rebuild()  # sorted for the final positions: a reload (which rebuilds) gets the same order
        self._set_prm(self._parameters())

    def _settle_parameters(self) -> np.ndarray:
        prm = self._parameters()
        prm[dem.P_SLEEP_STEPS] = 0.0
        return prm

    def _run_until_quiet(self, limit: float, at_least: float, quiet: float, damping: float) -> float:
        """Substeps until the fastest grain is slower than `quiet` (after at least `at_least`) or for `limit` s;
        returns the fastest grain's speed at the end."""
        chunk = max(1, int(round(0.01 / self.dt)))
        elapsed = 0.0
        while elapsed < limit:
            self._substeps(chunk, self.dt, damping)
            elapsed += chunk * self.dt
            if self._on_settle is not None:
                self._settled_for += chunk * self.dt
                self._on_settle(self._settled_for, self._settle_budget)
            if elapsed >= at_least and self._totals()[5] < quiet:
                break
        return float(self._totals()[5])

    def _measure_packing(self) -> float | None:
        """Solid volume of the active particles centred in the beds over the beds' volume."""
        flags = self._flags.to_numpy()[:self._n]
        pos = self._kin.to_numpy()[:self._n, 0]
        radii = self._prop.to_numpy()[:self._n, 0]
        inside = np.isfinite(self._bed_floors(pos))
        volume = sum(self._bed_volume(b_min, b_max) for b_min, b_max in self.beds)
        solid = float(np.sum(4.0 / 3.0 * math.pi * radii[inside & (flags == 1)] ** 3))
        return solid / volume if solid > 0.0 and volume > 0.0 else None

    def _bed_floors(self, pos: np.ndarray) -> np.ndarray:
        """The floor of the bed each position (N, 3) is centred in (between its floor and its fill height), NaN
        outside every bed."""
        floors = np.full(len(pos), np.nan)
        for b_min, b_max in self.beds:
            in_plan = np.all((pos[:, :2] >= b_min[:2]) & (pos[:, :2] <= b_max[:2]), axis=1)
            floors[in_plan & (pos[:, 2] >= b_min[2]) & (pos[:, 2] <= self._tops(pos[:, :2], b_max))] = b_min[2]
        return floors

    def _match_bulk_density(self) -> None:
        """Scale the particle masses so the settled beds have the user's bulk density.

        How densely spheres pack depends on their friction and rolling resistance (a poured bed of sand-like
        spheres packs at ~0.45-0.55 here, not the 0.6 that SoilMicro.solid_density assumes), so the solid
        density is fixed from the measured packing of the levelled beds: solid volume of the particles centred in
        the beds over the beds' volume (the grains' masses over that volume are then the bulk density)."""
        self.bed_packing = self._measure_packing()
        if not self.bed_packing:
            return
        prop = self._prop.to_numpy()
        scale = self.micro.bulk_density / (self.micro.solid_density * self.bed_packing)
        # lighter grains (a bed packed denser than SOLID_FRACTION) shorten the contact time: t_c ~ sqrt(m)
        limit = self.micro.dt_limit * math.sqrt(min(scale, 1.0))
        if self.dt > limit * (1.0 + 1e-9):
            raise UserError(f"sim.soil_dt: {self.dt:.3g} s is above the stability limit {limit:.3g} s of this bed: it "
                            f"settled at a solid fraction of {self.bed_packing:.3f}, so matching its bulk density makes "
                            f"the grains {1.0 / scale:.2f} x lighter than the limit of the soil mapping assumed")
        prop[:, 1] *= scale
        prop[:, 2] /= scale
        prop[:, 3] = prop[:, 1] ** 0.25
        self._prop.from_numpy(prop)

    def _tops(self, xy: np.ndarray, b_max: np.ndarray) -> np.ndarray:
        """Fill height of a bed at points (N, 2): its top, or the scanned surface (soil.terrain)."""
        if self.surface is None:
            return np.full(len(xy), b_max[2])
        from .terrain_bed import surface_at

        return surface_at(self.surface, xy)

    def _highest_top(self, b_min: np.ndarray, b_max: np.ndarray) -> float:
        if self.surface is None:
            return float(b_max[2])
        x, y, z = self.surface
        inside = ((x >= b_min[0]) & (x <= b_max[0]))[:, None] & ((y >= b_min[1]) & (y <= b_max[1]))[None, :]
        return float(max(b_max[2], np.nanmax(z[inside])))

    def _bed_volume(self, b_min: np.ndarray, b_max: np.ndarray) -> float:
        """Volume the bed's soil fills: the box, or from its floor up to the scanned surface."""
        if self.surface is None:
            return float(np.prod(b_max - b_min))
        x, y, z = self.surface
        # each node stands for its cell, as much of it as lies over the footprint (a node on the edge: half)
        dx, dy = abs(x[1] - x[0]), abs(y[1] - y[0])
        wx = np.clip(np.minimum(x + dx / 2, b_max[0]) - np.maximum(x - dx / 2, b_min[0]), 0.0, None)
        wy = np.clip(np.minimum(y + dy / 2, b_max[1]) - np.maximum(y - dy / 2, b_min[1]), 0.0, None)
        return float(np.nansum((z - b_min[2]) * wx[:, None] * wy[None, :]))

    def _trim_to_beds(self) -> None:
        """Remove particles centred above their bed's top less half a radius: each bed is full and level (or follows
        its scanned surface), its highest grains reaching at most r / 2 above the top."""
        flags = self._flags.to_numpy()
        kin = self._kin.to_numpy()
        top = np.full(len(flags), -np.inf)
        for b_min, b_max in self.beds:
            inside = np.all((kin[:, 0, :2] >= b_min[:2]) & (kin[:, 0, :2] <= b_max[:2]), axis=1)
            top[inside] = self._tops(kin[inside, 0, :2], b_max)
        rad = self._prop.to_numpy()[:, 0]
        flags[kin[:, 0, 2] + 0.5 * rad > top] = 0
        self._flags.from_numpy(flags)
        self._rebuild()

    _STATE = ("kin", "prop", "surf_id", "surf_h", "nbr_off", "nbr_j", "nbr_h")

    def _shift_particles(self, shift) -> None:
        """Move every particle by shift, keeping its mass (matched to the bulk density) and its contacts with other
        grains; the calm counters restart so that a moved block starts awake. Springs with faces it leaves are freed
        on its first step."""
        state = self._state_arrays()
        state["kin"][:, 0] += np.asarray(shift, float)
        state["surf_id"][:, dem.TOOL_BITS] = 0
        self._set_state(state)

    def _state_arrays(self) -> dict[str, np.ndarray]:
        """Active particles with their contact history (after a rebuild they are the first n_act)."""
        n, e = self.n_act, self._entries
        size = dict(nbr_off=n + 1, nbr_j=e, nbr_h=e)
        return {name: getattr(self, "_" + name).to_numpy()[:size.get(name, n)] for name in self._STATE}

    def _load_state(self, path) -> None:
        with np.load(path) as f:
            self._set_state({name: f[name] for name in self._STATE})
            self.settle_speed = float(f["settle_speed"]) if "settle_speed" in f.files else 0.0

    def _set_state(self, arrays: dict[str, np.ndarray]) -> None:
        n = len(arrays["kin"])
        self._allocate(n)
        if len(arrays["nbr_j"]) > self._nbr_j.shape[0]:
            self._allocate_neighbors(len(arrays["nbr_j"]))
        missing = dem.SURF_ID_WIDTH - arrays["surf_id"].shape[1]
        if missing > 0:  # saved before the tool-spring bits column: cached beds touch no tool, so the bits are 0
            arrays["surf_id"] = np.pad(arrays["surf_id"], ((0, 0), (0, missing)))
        for name, value in arrays.items():
            target = getattr(self, "_" + name)
            full = target.to_numpy()
            full[:len(value)] = value
            target.from_numpy(full)
        self._flags.fill(1)
        self._reset_stat()
        self._forget_partition()  # (a bed settled in this process digs as one loaded from the cache)
        self._rebuild()

    def _forget_partition(self) -> None:
        """The host's record of the substeps and the frozen partition, as in a new soil."""
        self._partition = np.zeros((dem.MAX_TOOLS, 4))  # each tool's on flag and sphere centre at the partition
        self._partition_time = -math.inf
        self._slots_at_try = 0
        self._clearance = np.full(dem.MAX_TOOLS, np.inf)  # each tool's clearance to the frozen soil at the partition
        self._repartition_due = False
        self._active_slots = 0  # particle slots the last run of substeps listed (_layout, _partition_stale)

    # ------------------------------------------------------------------------------------------- tools
    def add_tool(self, name: str, mesh, *, spacing: float | None = None) -> int:
        """Register a rigid tool by its mesh (link frame). Returns its index. It acts once its state is set."""
        if len(self._tool_names) >= dem.MAX_TOOLS:
            raise UserError(f"tools: at most {dem.MAX_TOOLS} soil-touching tools, cannot add {name!r}")
        h = 0.5 * self.micro.radius if spacing is None else float(spacing)
        margin = 2.0 * self.r_max + 2.0 * h
        grid = tool_sdf(mesh, h, margin, name=name, use_cache=self.use_cache)
        offset = sum(len(b) for b in self._sdf_blocks)
        self._sdf_blocks.append(grid.data.reshape(-1, 4))
        data = np.concatenate(self._sdf_blocks)
        self._sdf = ti.ndarray(dem.vec4f, len(data))
        self._sdf.from_numpy(data)
        i = len(self._tool_names)
        self._tool_names.append(name)
        self._tool_vertices.append(np.asarray(mesh.vertices, dtype=np.float64))
        row = self._tools_host[i]
        row[:] = 0.0
        row[dem.T_OFF] = offset
        row[dem.T_NX:dem.T_NX + 3] = grid.shape
        row[dem.T_ORG:dem.T_ORG + 3] = grid.origin
        row[dem.T_H] = grid.spacing
        row[dem.T_ROT:dem.T_ROT + 9] = np.eye(3).ravel()
        half = 0.5 * (np.asarray(grid.shape, dtype=np.float64) - 1.0) * grid.spacing
        row[dem.T_BS:dem.T_BS + 3] = np.asarray(grid.origin, dtype=np.float64) + half
        row[dem.T_BS + 3] = float(np.linalg.norm(half)) * (1.0 + 1e-9) + 1e-9
        self._tools_dirty = True
        return i

    def set_cutting_edge(self, i: int, centre, face_normal, face_up, width: float, where: str | None = None,
                         opening: bool = False) -> None:
        """Give tool i a cutting edge (link frame): its centre, the face's normal into the soil it cuts, the direction
        up the face away from the edge, and the edge's width. While the face moves into the soil, the grains between
        the face and the failure plane through the edge (at the earthmoving equation's angle) move with the tool as
        one wedge, and the tool feels that wedge's equilibrium with the bulk soil's strength (AGX Terrain's soil
        aggregate) instead of the grains' contacts: forces of the earthmoving equation at any grain size. opening: the
        face is a bucket's mouth, not a plate: the wedge is the soil the edge meets, which rises with it until it
        clears the edge, and the soil over the edge passes into the bucket."""
        if not 0 <= i < len(self._tool_names):
            raise IndexError(f"no tool {i}; {len(self._tool_names)} registered")
        name = self._tool_names[i]
        where = where or f"tools.{name}.cutting_edge"  # (as the user wrote it, for the errors)
        if self.bulk is None:
            raise UserError(f"{where}: this soil has no bulk properties to give the wedge")
        centre, normal, up = (np.asarray(v, dtype=np.float64).reshape(3) for v in (centre, face_normal, face_up))
        for key, v in (("centre", centre), ("face_normal", normal), ("face_up", up)):
            if not np.all(np.isfinite(v)):
                raise UserError(f"{where}.{key}: expected three finite numbers, got {v.tolist()}")
        for key, v in (("face_normal", normal), ("face_up", up)):
            if not np.any(v != 0.0):
                raise UserError(f"{where}.{key}: expected a direction, got the zero vector")
        normal = normal / np.max(np.abs(normal))  # (scaled first: any length)
        normal /= np.linalg.norm(normal)
        up = up / np.max(np.abs(up))
        up = up - up.dot(normal) * normal
        if not np.linalg.norm(up) > 1e-6:
            raise UserError(f"{where}.face_up: must not be parallel to face_normal")
        up /= np.linalg.norm(up)
        if not (math.isfinite(width) and width > 0.0):
            raise UserError(f"{where}.width: expected a width in m > 0, got {width!r}")
        # the edge lies on the tool: its ends within a grain radius of the tool's extent along it
        along = np.cross(normal, up)
        reach = (self._tool_vertices[i] - centre) @ along
        inside = (self._tool_vertices[i] - centre) @ normal
        slack = self.r_max
        if reach.min() > -0.5 * width + slack or reach.max() < 0.5 * width - slack:
            raise UserError(f"{where}.width: the edge ({width:g} m about its centre) runs past the "
                            f"tool, which spans {reach.min():.3g} to {reach.max():.3g} m from the centre along it")
        if inside.min() > slack or inside.max() < -slack:
            raise UserError(f"{where}.centre: {centre.tolist()} is off the tool (the face's plane "
                            f"misses the tool's mesh by more than a grain radius)")
        row = self._tools_host[i]
        row[dem.T_WG_ON] = dem.WG_OPENING if opening else dem.WG_PLATE
        row[dem.T_WG_E:dem.T_WG_E + 3] = centre
        row[dem.T_WG_N:dem.T_WG_N + 3] = normal
        row[dem.T_WG_U:dem.T_WG_U + 3] = up
        row[dem.T_WG_HW] = 0.5 * float(width)
        row[dem.T_WG_BETA] = 0.25 * math.pi - 0.5 * self.bulk.friction_angle  # (Rankine's; the kernels refine it)
        row[dem.T_WG_TOP] = -dem.HUGE
        row[dem.T_WG_GAP] = dem.NO_GAP
        row[dem.T_WG_ACC:dem.T_WG_ACC + 3] = 0.0
        self._tools_dirty = True

    def _reset_stat(self) -> None:
        """Zero the kernels' diagnostics; the wedges' front surfaces are unknown until a substep finds them."""
        stat = np.zeros(dem.N_STAT)
        stat[dem.S_WG_TOP:dem.S_WG_TOP + dem.MAX_TOOLS] = -dem.HUGE
        stat[dem.S_WG_GAP:dem.S_WG_GAP + dem.MAX_TOOLS] = dem.NO_GAP
        self._stat.from_numpy(stat)

    def clear_above(self, z: float) -> None:
        """From now on, remove every particle whose centre rises above height z and book its mass as out of the
        domain (a spoil-clearing plane: soil-bin tests of the surcharge-free cutting force). Lowers the domain top
        the kernels test; set after the beds have settled, which pour from above."""
        if not (math.isfinite(z) and 0.0 < z <= self.domain_max[2]):
            raise UserError(f"soil.clear_above: expected a height in m above the ground (> 0) and at most the "
                            f"domain top {self.domain_max[2]:g}, got {z!r}")
        prm = self._prm.to_numpy()
        prm[dem.P_DMAX + 2] = z
        self._set_prm(prm)

    @property
    def tool_names(self) -> list[str]:
        return list(self._tool_names)

    def set_tool_state(self, i: int, position, quat_xyzw, lin_vel, ang_vel) -> None:
        """Pose of tool i's link origin (world) and its linear and angular velocity, at the start of advance()."""
        if not 0 <= i < len(self._tool_names):
            raise IndexError(f"no tool {i}; {len(self._tool_names)} registered")
        row = self._tools_host[i]
        row[dem.T_ON] = 1.0
        row[dem.T_POS:dem.T_POS + 3] = np.asarray(position, dtype=np.float64)
        row[dem.T_ROT:dem.T_ROT + 9] = quat_to_matrix(_unit(quat_xyzw)).ravel()
        row[dem.T_VEL:dem.T_VEL + 3] = np.asarray(lin_vel, dtype=np.float64)
        row[dem.T_ANG:dem.T_ANG + 3] = np.asarray(ang_vel, dtype=np.float64)
        self._tools_dirty = True

    def tool_pose(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Current position and rotation matrix of tool i (moved kinematically by advance())."""
        row = self._tools_host[i]
        return row[dem.T_POS:dem.T_POS + 3].copy(), row[dem.T_ROT:dem.T_ROT + 9].reshape(3, 3).copy()

    # ------------------------------------------------------------------------------------------- stepping
    def _kernel_args(self, h: float, damping: float) -> dict:
        """The substep kernels' arguments by name (the arrays a rebuild swaps included)."""
        return dict(kin=self._kin, prop=self._prop, flags=self._flags, x_ref=self._x_ref, nbr_off=self._nbr_off,
                    nbr_j=self._nbr_j, nbr_h=self._nbr_h, pair_out=self._pair_out, own=self._own,
                    rev_off=self._rev_off, rev_pos=self._rev_pos, surf_id=self._surf_id, surf_h=self._surf_h,
                    tools=self._tools, tool_acc=self._tool_acc, sdf=self._sdf, prm=self._prm, stat=self._stat,
                    partial=self._partial, n_act=self.n_act, dt=h, bulk_damping=damping,
                    block=self._block, blk_hot=self._blk_hot, blk_active=self._blk_active,
                    blk_box=self._blk_box, rev_holder=self._rev_holder, blk_list=self._blk_list,
                    skip=int(self.skip_sleeping_blocks), tools_in=self._tools_in, report=self._report,
                    first=0, upload=0, todo=0, n_frozen=self.n_frozen, tool_gap=self._tool_gap)

    def _upload_tool_rows(self) -> None:
        """The host's tool rows into tools_in (begin_chunk copies them to the kernels' rows when asked to). A tool
        switched on or off, or a new one, voids the particles' tool clearances (tool_gap)."""
        on = self._tools_host[:, dem.T_ON] > 0.0
        if not np.array_equal(on, self._tools_on):
            self._tool_gap.fill(-dem.HUGE)
            self._tools_on = on
        if self._tools_in_view is not None:
            self._tools_in_view[:] = self._tools_host
        else:
            self._tools_in.from_numpy(self._tools_host)

    def _substeps(self, count: int, h: float, damping: float, first: bool = False) -> np.ndarray:
        """`count` substeps, run as compute graphs of up to CHUNK_MAX substeps; the neighbour lists are rebuilt
        after each substep that moved a particle more than half the skin since they were built (the graph halts
        there, the rest runs after the rebuild). first: the advance's first substeps (upload the tool rows if
        they changed, zero the tool sums). Returns the last report (end_chunk's layout)."""
        args = self._kernel_args(h, damping)
        args.update(first=int(first), upload=int(first and self._tools_dirty))
        if args["upload"]:
            self._upload_tool_rows()
            self._tools_dirty = False
        left = count
        while True:
            k = min(left, CHUNK_MAX)
            args["todo"] = k
            layout = self._layout()
            graph = _chunk_graph(k, layout)
            if graph is not None:
                graph.run(args)
            else:
                dem.begin_chunk(*(args[a] for a in _BEGIN_ARGS))
                for _ in range(k):
                    _substep_kernel(layout)(*(args[a] for a in _SUBSTEP_ARGS))
                dem.end_chunk(*(args[a] for a in _END_ARGS))
            args.update(first=0, upload=0)
            report = self._report.to_numpy() if self._report_view is None else self._report_view.copy()
            stat = report[dem.MAX_TOOLS * (dem.T_WIDTH + 6):]
            left -= int(stat[dem.S_DONE])
            self._active_slots = int(stat[dem.S_ACTIVE])
            if stat[dem.S_HALT] != 0.0:
                self._rebuild(keep_still=stat[dem.S_THAW] == 0.0)  # a frozen particle woke: repartition
                args = self._kernel_args(h, damping)
            if left <= 0:
                return report

    def warm_up(self, duration: float) -> None:
        """Compile the substeps that advance(duration) runs first (about 7 s the first time on a machine, 0.8 s from
        Taichi's disk cache), so that a run's clock does not count them: their compute graph is built and run with
        no substep to do (mark_blocks lists nothing and clears S_RUN), which moves nothing. The rebuild and observer
        kernels are compiled without a launch: those a run first launches after its setup (the frozen partition's,
        the observers') no longer compile on its clock. A big sleeping bed is partitioned here, as the first advance
        would do it (the tools are where the first step finds them: the same bits)."""
        names = WARM_KERNELS
        if self.per_particle:  # (the GPU layout's sort and reverse lists instead of the serial ones)
            names = tuple(f"{name}_parallel" if name in ("sort_by_bucket", "build_reverse") else name for name in names)
        kernels = [getattr(dem, name) for name in names]
        if self._serial_cpu:  # (a bed that wakes past SERIAL_BELOW switches to the threaded substep mid-run)
            kernels += [_substep_kernel("serial" + self._wedges()), _substep_kernel("block" + self._wedges())]
        precompile(*kernels)
        ti.ndarray(ti.f64, dem.MAX_TOOLS).to_numpy()  # (Taichi's read-back kernel for the partition's clearances)
        for which in ("sort", "sort_keep", "lists"):
            _rebuild_steps(which, self.per_particle)  # (the rebuilds' graphs: a live one's is first needed in the run)
        if self._partition_stale():
            self._rebuild()
        n_sub = max(1, math.ceil(duration / self.dt - 1e-9))
        k = min(n_sub, CHUNK_MAX)
        layout = self._layout()
        args = self._kernel_args(duration / n_sub, 0.0)  # (todo = 0, first = 0: the tool rows are not touched)
        graph = _chunk_graph(k, layout)
        if graph is not None:
            graph.run(args)
        else:
            dem.begin_chunk(*(args[a] for a in _BEGIN_ARGS))
            _substep_kernel(layout)(*(args[a] for a in _SUBSTEP_ARGS))
            dem.end_chunk(*(args[a] for a in _END_ARGS))

    def _wedges(self) -> str:
        """The substep variant's suffix: "+wedges" while a tool has a cutting edge (the others skip its tests)."""
        return "+wedges" if np.any(self._tools_host[:, dem.T_WG_ON] > 0.0) else ""

    def _layout(self) -> str:
        """The substep kernel for the next run of substeps: per particle on a GPU; on a CPU threaded, or serial
        while the last substep listed few particle slots (SERIAL_BELOW)."""
        wedges = self._wedges()
        if self.per_particle:
            return "particle" + wedges
        return ("serial" if self._serial_cpu and self._active_slots < SERIAL_BELOW else "block") + wedges

    def advance(self, duration: float) -> np.ndarray:
        """Advance by `duration` in n = ceil(duration / dt) equal substeps, tools moving kinematically.

        Returns (n_tools, 6): time-averaged force and torque (about each link origin) that the soil exerts on
        each tool over the call, world frame. Raises DivergenceError if a particle became non-finite or faster
        than max_speed.
        """
        if not duration > 0:
            raise ValueError(f"duration must be positive, got {duration!r}")
        n_sub = max(1, math.ceil(duration / self.dt - 1e-9))
        h = duration / n_sub
        if self._partition_stale():
            self._rebuild()
        report = self._substeps(n_sub, h, 0.0, first=True)
        self.time += duration
        tools_end = dem.MAX_TOOLS * dem.T_WIDTH
        self._tools_host[:] = report[:tools_end].reshape(dem.MAX_TOOLS, dem.T_WIDTH)
        n_tools = len(self._tool_names)
        acc = report[tools_end:tools_end + dem.MAX_TOOLS * 6].reshape(dem.MAX_TOOLS, 6)[:n_tools]
        self._last_impulse = acc * h
        self._check_divergence(report[tools_end + dem.MAX_TOOLS * 6:])
        return acc / n_sub

    @property
    def last_tool_impulse(self) -> np.ndarray:
        """(n_tools, 6) impulse and angular impulse (about the moving link origin) of the last advance()."""
        return self._last_impulse.copy()

    def _check_divergence(self, stat: np.ndarray) -> None:
        if stat[dem.S_NONFINITE] > 0:
            raise DivergenceError(f"soil diverged at t = {self.time:.3f} s: {int(stat[dem.S_NONFINITE])} particles "
                                  f"have a non-finite state (sim.soil_dt or the soil stiffness is unstable)"
                                  f"{self._crushing()}")
        speed = math.sqrt(stat[dem.S_SPEED2])
        if speed > self.max_speed:
            # a settled bed does not fly apart by itself in its first steps: something started inside it
            start = ("; this early, a tool or a machine's link that starts inside the soil (or in another body) is "
                     "the likely cause: check tools.*.start and the machines' poses") \
                if self.time < START_TIME and self._tool_names else ""
            raise DivergenceError(f"soil diverged at t = {self.time:.3f} s: particle speed {speed:.3g} m/s above "
                                  f"the limit {self.max_speed:g} m/s (soil.max_speed){start}{self._crushing()}")

    def _crushing(self) -> str:
        """The hint for a divergence with a tool closing on a pit's wall or floor within CRUSH_GAP grain diameters
        (grains squeezed between two stiff surfaces blow up; a tool sliding along a face does not squeeze them), or
        "". From the tools' poses and velocities now: computed only once the soil diverged."""
        try:
            return self._crushing_tool()
        except Exception:  # noqa: BLE001 - a hint must never cost the divergence its message
            return ""

    def _crushing_tool(self) -> str:
        gap, speed, tool, face = math.inf, 0.0, "", ""
        faces = _pit_faces(self.beds)
        for i, name in enumerate(self._tool_names):
            row = self._tools_host[i]
            if not faces or row[dem.T_ON] <= 0.0:
                continue
            points = self._tool_points(i)
            # (the nodes lie up to a cell's diagonal inside the surface: the gaps read up to that much too wide)
            reach = CRUSH_GAP * 2.0 * self.r_max + dem.SQRT_THREE * row[dem.T_H]
            velocity = row[dem.T_VEL:dem.T_VEL + 3] + np.cross(row[dem.T_ANG:dem.T_ANG + 3],
                                                               points - row[dem.T_POS:dem.T_POS + 3])
            for where, lo, hi, out in faces:
                gaps = np.linalg.norm(np.clip(points, lo, hi) - points, axis=1)
                closing = velocity @ out
                near = np.flatnonzero((gaps <= reach) & (closing > 0.0))
                j = near[np.argmin(gaps[near])] if len(near) else -1
                if j >= 0 and gaps[j] < gap:
                    gap, speed, tool, face = float(gaps[j]), float(closing[j]), name, where
        if not tool:
            return ""
        where = f"reaches {face}" if gap == 0.0 else f"is {gap:.2g} m from {face}"
        return (f"; the tool {tool!r} {where}, closing at {speed:.2g} m/s: grains squeezed between them are the "
                f"likely cause: slow the tool, keep it off the pit's walls and floor, or lower sim.soil_dt")

    def _tool_points(self, i: int) -> np.ndarray:
        """World positions of the nodes of tool i's SDF grid inside it (distance <= 0, which a thin plate's nodes
        within a grid spacing are too): the tool's surface to within a grid spacing."""
        row = self._tools_host[i]
        shape = row[dem.T_NX:dem.T_NZ + 1].astype(np.int64)
        inside = np.argwhere(self._sdf_blocks[i][:, 0].reshape(shape) <= 0.0)
        local = row[dem.T_ORG:dem.T_ORG + 3] + inside * row[dem.T_H]
        return row[dem.T_POS:dem.T_POS + 3] + local @ row[dem.T_ROT:dem.T_ROT + 9].reshape(3, 3).T

    # ------------------------------------------------------------------------------------------- outputs
    def _totals(self) -> np.ndarray:
        out = ti.ndarray(ti.f64, 8)
        if self.n_act == 0:
            return np.zeros(8)
        dem.totals(self.n_act, self._kin, self._prop, self._flags, self._partial, out)
        return out.to_numpy()

    @property
    def n_particles(self) -> int:
        return self.n_act

    @property
    def _block(self) -> int:
        """Particles per block of the substep kernels: blocks cover the live particles (after the frozen prefix)."""
        return dem.reduction_block(self.n_act - self.n_frozen)

    @property
    def n_sleeping(self) -> int:
        """Active particles asleep now (soil.sleep)."""
        steps = int(self._prm.to_numpy()[dem.P_SLEEP_STEPS])
        if steps <= 0 or self.n_act == 0:
            return 0
        calm = self._surf_id.to_numpy()[:self.n_act, dem.TOOL_BITS] >> dem.CALM_SHIFT
        return int(np.sum((calm >= steps) & (self._flags.to_numpy()[:self.n_act] == 1)))

    @property
    def neighbor_entries(self) -> int:
        """Entries in the neighbour lists (each pair counted from both sides)."""
        return self._entries

    @property
    def particle_mass(self) -> float | np.ndarray:
        """Mass of each active particle (a float when they are all equal)."""
        masses = self.particles()["masses"]
        if len(masses) and np.all(masses == masses[0]):
            return float(masses[0])
        return masses

    def mass_budget(self) -> dict[str, float]:
        """Soil mass in kg: in active particles, and booked out of the domain since the soil was built."""
        return {"particles": float(self._totals()[0]), "out_of_domain": float(self._stat[dem.S_LOST_MASS])}

    def momentum(self) -> np.ndarray:
        """Total linear momentum of the active particles, kg m/s."""
        return self._totals()[1:4].copy()

    def kinetic_energy(self) -> float:
        """Translational plus rotational kinetic energy of the active particles, J."""
        return float(self._totals()[4])

    def particles(self, fields=None) -> dict[str, np.ndarray]:
        """Copies of the active particles' state (for recorders and tests; not for every step): positions,
        velocities, angular_velocities, radii, masses, or only the names in `fields`."""
        columns = dict(positions=(0, 0), velocities=(0, 1), angular_velocities=(0, 2), radii=(1, 0), masses=(1, 1))
        names = list(columns) if fields is None else list(fields)
        unknown = [f for f in names if f not in columns]
        if unknown:
            raise ValueError(f"particles: no field {unknown[0]!r} (fields: {', '.join(columns)})")
        n = self.n_act
        views = [host_view(a) for a in (self._kin, self._prop, self._flags)]  # (a big soil: no full copies)
        kin, prop, flags = views if all(v is not None for v in views) else \
            (a.to_numpy() for a in (self._kin, self._prop, self._flags))
        arrays = (kin[:n], prop[:n])
        active = flags[:n] == 1
        # (all of them but for a substep after one left the domain: slices copy at twice the speed of a mask)
        pick = slice(None) if active.all() else active
        return {f: arrays[columns[f][0]][pick, columns[f][1]].copy() for f in names}

    def static_ground(self, x_axis: np.ndarray, y_axis: np.ndarray) -> np.ndarray:
        """Height of the static ground on a grid: 0, or the pit floor where the pit's footprint holds the node."""
        gx, gy = np.meshgrid(np.asarray(x_axis, float), np.asarray(y_axis, float), indexing="ij")
        ground = np.zeros(gx.shape)
        for b_min, b_max in reversed(self.beds):  # the first bed wins where footprints touch, as in the kernel
            inside = (gx >= b_min[0]) & (gx <= b_max[0]) & (gy >= b_min[1]) & (gy <= b_max[1])
            ground[inside] = b_min[2]
        return ground

    def heightmap(self, x_axis: np.ndarray, y_axis: np.ndarray, exclude: np.ndarray | None = None) -> np.ndarray:
        """Terrain height on the grid (x_axis, y_axis uniformly spaced nodes): the soil surface as a ball of the
        grain radius rolling over the grains traces it (each grain's own top z + r right above it, narrow gaps
        between grains bridged), or the static ground (the pit floor, the ground around a pit) where that is higher.
        exclude: a mask over particles() of grains to leave out (e.g. those a tool carries)."""
        x_axis = np.asarray(x_axis, dtype=np.float64).ravel()
        y_axis = np.asarray(y_axis, dtype=np.float64).ravel()
        spacing = []
        for name, axis in (("x_axis", x_axis), ("y_axis", y_axis)):
            if len(axis) == 0:
                raise ValueError(f"{name} is empty")
            step = axis[1] - axis[0] if len(axis) > 1 else 1.0
            if not step > 0 or (len(axis) > 2 and not np.allclose(np.diff(axis), step, rtol=1e-6, atol=0.0)):
                raise ValueError(f"{name} must be increasing and uniformly spaced")
            spacing.append(step)
        height = ti.ndarray(ti.f64, (len(x_axis), len(y_axis)))
        height.fill(-np.inf)
        if self.n_act:
            flags = self._flags
            if exclude is not None and np.any(exclude):
                host = flags.to_numpy()
                active = np.nonzero(host[:self.n_act] == 1)[0]
                host[active[np.asarray(exclude, bool)]] = 0
                flags = ti.ndarray(ti.i32, host.shape[0])
                flags.from_numpy(host)
            dem.surface_height(self.n_act, self._kin, self._prop, flags, height, x_axis[0], spacing[0],
                               y_axis[0], spacing[1])
        # the static ground bounds the surface from below: a grain against a pit wall bridges nodes just outside
        # the pit, where the ground is solid up to its rim
        return np.maximum(height.to_numpy(), self.static_ground(x_axis, y_axis))

    def mass_in_box(self, position, quat_xyzw, box_min, box_max) -> float:
        """Mass of the particles whose centre, in the frame (position, quat_xyzw), lies in the box [min, max].

        E.g. the soil carried in a bucket: the bucket link's pose and a box around its cavity.
        """
        if self.n_act == 0:
            return 0.0
        rot = quat_to_matrix(_unit(quat_xyzw))
        return float(dem.mass_in_box(self.n_act, self._kin, self._prop, self._flags, self._partial,
                                     ti.Vector(np.asarray(position, dtype=np.float64).tolist(), ti.f64),
                                     ti.Matrix(rot.tolist(), ti.f64),
                                     ti.Vector(np.asarray(box_min, dtype=np.float64).tolist(), ti.f64),
                                     ti.Vector(np.asarray(box_max, dtype=np.float64).tolist(), ti.f64)))
