"""Cohesive DEM of spheres: contact forces, integration, neighbour lists on a hashed cell grid, tools.

Taichi code only. Every array is a Taichi ndarray owned by the caller (opera_taichi.dem_soil), so one
compiled kernel serves every soil instance in a process (fields would recompile per instance).

Precision: particle state, forces and every reduction are f64. The momentum and Newton's-third-law checks
need 1e-6 relative over thousands of steps and tool wrenches are summed over many particles; in f32 the
rounding of v += F/m dt alone drifts past that. Contact history (spring elongations) is f32: it only has to be
accurate to the contact law, and pair forces stay exactly antisymmetric because both sides store the exact
negation of the same rounded value.

Particle order: a frozen prefix (particles 0..n_frozen: asleep, far from tools and from anything awake; see
DemSoil), the live particles, then the inactive ones; the substep kernels' blocks start at n_frozen.

Data layout (n = particle capacity, E = neighbour-entry capacity):
  kin[n, 3]     vec3 f64   position, velocity, angular velocity
  prop[n]       vec4 f64   radius, mass, 1/mass, mass^(1/4) (pair damping without a per-pair division)
  flags[n]      i32        1 active, 0 inactive (left the domain)
  x_ref[n]      vec4 f64   position at the last neighbour build (Verlet skin criterion) and its clearance to the
                static faces: a particle moves at most skin/2 before the next build, so one whose clearance then
                exceeded r + skin/2 cannot touch a face and skips the face search
  surf_id[n, 5] i32        columns 0-3: static face held by each wall-contact slot (-1 free); column 4 (TOOL_BITS):
                bits 0-3: bit t set while tool t's slot may hold a spring, so a particle away from every tool does
                not read its tool slots each substep (a cache line per particle); bit 4 (WAKE_BIT): a moving
                neighbour asked a sleeping particle to wake; bits 8-30: how many substeps in a row the particle
                has been quiet (CALM_SHIFT; asleep from P_SLEEP_STEPS on)
  surf_h[n, 8]  vec6 f32   history: slots 0-3 static faces, 4-7 tools; (tangential spring, rolling spring)
  nbr_off[n+1], nbr_j[E], nbr_h[E] vec6 f32  half neighbour list in CSR form (each pair once, held by one of
                the two, i: entries nbr_off[i]..nbr_off[i+1]) and each pair's springs (seen from i)
  rev_off[n+1], rev_pos[E] reverse segments: a slot for each pair in which a particle is the partner, and
                the slot of each entry
  pair_out[E, 2] vec3 f32  force and torque each pair puts on its partner (this substep), by slot; the holder
                adds the same f32-rounded force with the opposite sign, so the pair stays exactly antisymmetric
                (f32 halves the scattered stores, the pair kernel's main memory traffic)
  own[n, 4]     vec3 f64   force and torque from the pairs a particle lists itself (2: a wedge grain's separation;
                           3: its wedge role, _role)
  prm[N_PRM]    f64        model parameters and static geometry (P_* indices)
  stat[N_STAT]  f64        diagnostics written by the kernels (S_* indices)
  tools[MAX_TOOLS, T_WIDTH] f64   SDF grid placement and the current kinematic pose of each tool
  tool_acc[MAX_TOOLS, 6]    f64   force and torque (about the link origin) the soil puts on each tool
  sdf[total]    vec4 f32   all tool SDF grids back to back: distance, unit gradient (link frame)
  tool_gap[n]   f64        the tools' summed T_TRAVEL up to which no tool can reach the particle (asleep: where it
                is; awake: within skin/2 of x_ref, the lists' bound), so it skips the SDF test until then (-HUGE:
                test at the next substep; reset by each rebuild and whenever it falls asleep or wakes)
  partial[rows, PART_WIDTH] f64   per-block sums, added up in block order (deterministic): the step kernel's
                blocks (reduction_block) and the diagnostics' (BLOCK)

The neighbour list is a half list (each pair evaluated once, by the particle that holds it) without atomics:
a pair adds the force on its holder to the holder's sum and writes the opposite force into a per-pair slot,
which the partner reads from its reverse segment. Every sum has a fixed order, so results
do not depend on thread scheduling (deterministic for a seed, backend and thread count), and the two sides of a
pair get exactly opposite forces: linear momentum is conserved to round-off.

A GPU's layout (substep_per_particle, sort_by_bucket_parallel, build_reverse_parallel; DemSoil.per_particle) gives
the step loop one particle per iteration and the rebuilds parallel scans: the same particles, lists and slots, but
the tool wrenches and the lost mass summed by atomics in thread order. Each particle's term is first rounded to a
multiple of a power of two (WRENCH_QUANTUM, MASS_QUANTUM), so every partial sum is exact and the order does not
matter: the same bits from run to run and for any thread count (not the bits of the CPU's block sums).
"""
import types

import taichi as ti

# The substep kernel's particle loops run on Taichi's thread pool, or serially in the calling thread (substep_serial,
# CPU only): a parallel loop costs a thread-pool round trip (15-40 us on a 2-core host) even when it has
# nothing to do, more than a few hundred awake particles cost to compute; DemSoil picks one per run of substeps.
SERIAL_LOOPS = False
PER_PARTICLE = False  # the step loop's layout: a block of particles per iteration (CPU) or one (GPU); see substep
WEDGES = False  # the substep tests each particle's part in the tools' soil wedges (a variant: free where no tool has one)
MAX_TOOLS = 4
MAX_PITS = 16
WALL_SLOTS = 4
SURF_SLOTS = WALL_SLOTS + MAX_TOOLS
TOOL_BITS = WALL_SLOTS        # surf_id column of the tool-spring bits, the wake request and the calm counter
TOOL_MASK = (1 << MAX_TOOLS) - 1
WAKE_BIT = 1 << MAX_TOOLS
CALM_SHIFT = 8
CALM_MAX = (1 << 22) - 1
SURF_ID_WIDTH = WALL_SLOTS + 1
BLOCK = 64  # particles per reduction block: sums per block, then added in block order
# the GPU layout's atomic sums: f64 sums of multiples of 2^-k are exact (so independent of the order) while they stay
# under 2^53 quanta: 8.6e9 N (N m) summed over one advance's substeps, 8.4e6 kg lost over a run
WRENCH_QUANTUM = 2.0 ** -20   # N, N m: 1e-5 of a 1 cm grain's weight (0.1 N)
MASS_QUANTUM = 2.0 ** -30     # kg
# A lost mass restored off this grid (a CPU layout's checkpoint) stays order-independent: its terms are positive
# multiples of MASS_QUANTUM, at least 4 ulp of a total under 2^21 kg, so the sum is exact within a binade and the one
# rounding where it crosses into the next does not depend on which terms came first (checked by enumeration).
# The step kernel's blocks. Taichi 1.7's CPU thread pool hands out a parallel loop in tasks of 512 iterations
# whatever the loop's block_dim (measured: with 560 iterations one thread ran 0-511, the other 512-559), so the step
# loop gives each block STEP_SPREAD iterations, all but one empty: a task is then 32 blocks. Blocks are sized for
# about STEP_BLOCKS of them, whatever the thread count, so results do not depend on the machine; at least
# MIN_STEP_BLOCK particles each (smaller blocks list fewer sleeping particles but cost more to sum).
STEP_BLOCKS = 2048
STEP_SPREAD = 16
MIN_STEP_BLOCK = 16


def reduction_block(n_act: int) -> int:
    """Particles per block of the step kernel's sums for n_act particles (MIN_STEP_BLOCK..BLOCK)."""
    return max(MIN_STEP_BLOCK, min(BLOCK, -(-n_act // STEP_BLOCKS)))
MORTON_BITS = 21
CELL_LIMIT = (1 << MORTON_BITS) - 2

# prm indices
P_KN = 0          # particle-particle normal stiffness, N/m
P_DAMP = 1        # damping factor: gamma_n = P_DAMP * sqrt(m_eff k)
P_MU = 2          # particle-particle friction coefficient
P_MU_R = 3        # rolling resistance coefficient
P_COH_F = 4       # cohesive force at contact, N
P_COH_D = 5       # cohesion range beyond contact, m
P_K_WALL = 6      # ground / wall normal stiffness
P_MU_WALL = 7
P_K_TOOL = 8
P_MU_TOOL = 9
P_G = 10          # gravity, 3 entries
P_DMIN = 13       # domain min corner, 3 entries
P_DMAX = 16       # domain max corner, 3 entries
P_CELL = 19       # neighbour cell edge, m
P_SKIN = 20       # Verlet skin, m
P_NPITS = 21
P_ETA_R = 22      # rolling damping ratio (EPSD)
P_KT_RATIO = 23   # k_t / k_n (2/7)
P_SQRT_KN = 24    # sqrt of P_KN, P_K_WALL, P_K_TOOL
P_SQRT_KWALL = 25
P_SQRT_KTOOL = 26
P_WALL_TOP = 27   # top of the pit walls: 0 (the ground), raised while a bed is poured so nothing spills
P_ADH_F = 28      # soil-tool adhesion: attraction at contact and added tangential capacity, N
P_ADH_D = 29      # adhesion range beyond contact, m
# Sleeping: a particle quiet (speed and r x spin below sqrt(P_SLEEP_V2), the quiet speed; no tool contact; and not
# in the bounding sphere of a slow tool, one moving slower than SLOW_FACTOR x the wake speed: a load a tool creeps
# with would press into sleepers that never wake) for P_SLEEP_STEPS substeps in a row sleeps: it is neither
# integrated nor are its pairs with other sleepers evaluated (their springs keep their values: neither side moves).
# It wakes when a tool comes within r + skin of it, or when a touching neighbour moves faster than the wake speed
# (WAKE_FACTOR x the quiet speed). Soil a slow tool shoves moves slower than that, and sleepers ahead of it held as a
# wall (35 x the awake bed's force at 2 cm/s), so while a tool moves at CREEP_FRACTION to SLOW_FACTOR x the wake
# speed, a sleeper also wakes in that tool's SDF grid or when a neighbour closes in on it faster than WAKE_APPROACH x
# the quiet speed (only then: always on, that wakes twice the soil of a fast dig). P_SLEEP_STEPS 0: nothing sleeps
# (the default).
P_SLEEP_STEPS = 30
P_SLEEP_V2 = 31
WAKE_FACTOR2 = 4.0
WAKE_APPROACH = 0.1
SLOW_FACTOR = 4.0
CREEP_FRACTION = 0.01  # slower than this fraction of the wake speed a tool is parked (a bucket the hydraulics hold)
P_PITS = 32       # pits: 6 entries each (min xyz, max xyz), MAX_PITS of them
# The soil wedge at a tool's cutting edge (see _wedge_role): the bulk soil's strength, which the wedge's equilibrium
# takes instead of the grains'
P_WG_PHI = P_PITS + 6 * MAX_PITS  # internal friction angle, rad
P_WG_DELTA = P_WG_PHI + 1         # soil-tool friction angle, rad
P_WG_C = P_WG_PHI + 2             # cohesion, Pa
P_WG_CA = P_WG_PHI + 3            # adhesion, Pa
P_WG_GAMMA = P_WG_PHI + 4         # bulk unit weight, N/m^3 (the failure angle's depth terms)
N_PRM = P_WG_PHI + 5

# stat indices
S_DISP2 = 0       # max squared displacement since the last neighbour build (this substep)
S_SPEED2 = 1      # max squared particle speed since the last reset
S_NONFINITE = 2   # particles with a non-finite state since the last reset
S_LOST_MASS = 3   # cumulative mass deactivated (left the domain), kg
S_LOST_COUNT = 4  # cumulative count deactivated
# Several substeps run as one compute graph (DemSoil._substeps): a substep after which a particle moved more than
# half the skin since the lists were built halts the ones after it (they do nothing), and the host rebuilds the
# lists and runs the rest: the same substeps, the same rebuilds as launching them one by one.
S_RUN = 5         # 1 while this substep runs (set by mark_blocks), 0 once halted or done
S_HALT = 6        # 1: the lists need a rebuild before the next substep
S_DONE = 7        # substeps done since begin_chunk
S_ACTIVE = 8      # most particle slots in the listed blocks of one substep since begin_chunk
S_THAW = 9        # 1: a frozen particle (DemSoil's frozen prefix) was asked to wake: the host repartitions
# the wedges' sums over one substep on a GPU (quantised atomics; the CPU sums them per block in partial), reset after
# each substep's equilibrium, and each wedge's front surface (atomic max, order-free on both)
S_WG_SUM = 10
S_WG_TOP = S_WG_SUM + 8 * MAX_TOOLS
S_WG_GAP = S_WG_TOP + MAX_TOOLS  # each wedge's narrowest face gap this substep (atomic min)
N_STAT = S_WG_GAP + MAX_TOOLS
# a rebuild's sizes (DemSoil._sizes), passed from kernel to kernel in its compute graph
SZ_ACTIVE = 0     # active particles (sort_by_bucket)
SZ_ENTRIES = 1    # neighbour-list entries (count_neighbors)
N_SIZES = 2

# per-block partial sums (step): tool wrenches 0..6*MAX_TOOLS-1, then these
PART_LOST_MASS = 6 * MAX_TOOLS
PART_LOST_COUNT = PART_LOST_MASS + 1
PART_NONFINITE = PART_LOST_MASS + 2
# then per tool the wedge's sums: what free grains put on its grains (3), what the layer beyond its failure plane puts
# on them (3), their mass, the layer's mass
PART_WG = PART_LOST_MASS + 3
WG_SUMS = 8
PART_WIDTH = PART_WG + WG_SUMS * MAX_TOOLS
PART_BASE = PART_WG  # the columns summed for every substep (the wedges' only for a tool that has one)

# tools row layout
T_ON, T_OFF, T_NX, T_NY, T_NZ, T_ORG, T_H, T_POS, T_ROT, T_VEL, T_ANG = 0, 1, 2, 3, 4, 5, 8, 9, 12, 21, 24
T_BS = 27         # bounding sphere of the SDF grid (link-frame centre, radius): no contact outside it
T_TRAVEL = 31     # how far, at most, a point near the tool has moved in the tool's frame since the start (m; tool_gap)
# A cutting edge (link frame; host-set): its centre, the face's normal (into the soil it cuts) and the direction up
# the face away from the edge, unit vectors, and the edge's half width; T_WG_ON 1 where the tool has one whose face
# is a plate (a blade), WG_OPENING where its face is an opening (a bucket's mouth: _into_the_opening). The kernels
# keep the rest: the failure angle, the front surface's height and the layer's acceleration (last substep's).
T_WG_ON = 32
WG_PLATE, WG_OPENING = 1.0, 2.0
T_WG_E = 33
T_WG_N = 36
T_WG_U = 39
T_WG_HW = 42
T_WG_BETA = 43
T_WG_TOP = 44
T_WG_ACC = 45
# and, refreshed whenever the tool moves (_wedge_refresh), the wedge in the world for the particles' tests: 1 while it
# cuts, the edge's centre, the face normal, the edge's direction, the failure plane's normal into the ground, the
# wedge's velocity
T_WG_LIVE = 48
T_WG_EW = 49
T_WG_NW = 52
T_WG_YW = 55
T_WG_MG = 58
T_WG_VW = 61
T_WG_PUSH = 64     # the force the wedge put on the tool in the last substep (world; part of tool_acc)
T_WG_GAP = 67      # the last substep's narrowest gap between the face and a grain of the wedge's region, in radii
T_WG_ENGAGED = 68  # 1 while the wedge acts: it cuts (T_WG_LIVE), its face rises from the edge over the ground ahead,
# and the soil has touched the face since the cut began (T_WG_GAP): a face still short of the soil pushes nothing
T_WIDTH = 69
# wedge roles of a particle (_wedge_role): kind in the low two bits, the tool above them
WG_FREE, WG_IN, WG_LAYER, WG_SIDE = 0, 1, 2, 3
WG_LOW = 1.0       # the failure plane starts this many grain radii under the edge: the grains the edge meets rise
WG_LAYER_R = 2.5   # radii: the layer beyond the plane that carries its reaction
UNKNOWN_TOP = 1e6  # m: a front surface below -UNKNOWN_TOP is not known yet (-HUGE)
NO_GAP = 1e30      # T_WG_GAP while no grain lies in the wedge's region
WG_TOUCH = 0.1     # radii: a grain this near the face (or nearer) touches it
WG_MIN_RAKE = 0.05  # rad: a face that rises from the edge at less than this (or falls) cuts no wedge
WG_FREEZE_REACH = 3.0  # bounding-sphere radii beyond a tool's sphere that its wedge may reach (_freeze_radius)
WG_FRONT_R = 8.0   # radii: the band beyond the failure plane where the ground ahead is read (_wedge_front)
WG_REST = 0.1      # x the wedge's speed: a grain slower than this is at rest there
# A particle's tool clearance (tool_gap) is trusted while the tools have travelled less than it: within
# CLEAR_MARGIN x the bounding radius of the sphere, the motion is bounded by the translation and the rotation at
# that lever; the trilinear SDF of a distance field changes by at most sqrt(3) per metre (each partial derivative
# is an average of grid differences of at most 1), less two grid spacings for the distance transform inside bodies.
CLEAR_MARGIN = 0.25

FACE_GROUND = 4   # face ids: 0-3 domain walls (x-, x+, y-, y+), 4 ground top, 5 + 5k + f pit k faces
FACES_PER_PIT = 5
HUGE = 1e300
SQRT_HALF = 0.7071067811865476
SQRT_FIFTH = 0.4472135954999579
SQRT_TWO_FIFTHS = 0.6324555320336759
SQRT_THREE = 1.7320508075688772

vec3 = ti.types.vector(3, ti.f64)
vec4 = ti.types.vector(4, ti.f64)
vec6f = ti.types.vector(6, ti.f32)
vec4f = ti.types.vector(4, ti.f32)
vec3f = ti.types.vector(3, ti.f32)
mat3 = ti.types.matrix(3, 3, ti.f64)

KIN = ti.types.ndarray(dtype=vec3, ndim=2)
REF = ti.types.ndarray(dtype=vec4, ndim=1)
PROP = ti.types.ndarray(dtype=vec4, ndim=1)
I32_1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
I32_2 = ti.types.ndarray(dtype=ti.i32, ndim=2)
HIST_1 = ti.types.ndarray(dtype=vec6f, ndim=1)
I64_1 = ti.types.ndarray(dtype=ti.i64, ndim=1)
F64_1 = ti.types.ndarray(dtype=ti.f64, ndim=1)
F64_2 = ti.types.ndarray(dtype=ti.f64, ndim=2)
HIST = ti.types.ndarray(dtype=vec6f, ndim=2)
PAIR_OUT = ti.types.ndarray(dtype=vec3f, ndim=2)
SDF = ti.types.ndarray(dtype=vec4f, ndim=1)


# ----------------------------------------------------------------------------------------------- contact law
@ti.func
def contact_law(n, overlap, v_c, w_rel, sqrt_mk, sqrt_ik, r_roll, hist, k, mu, mu_r, prm: ti.template(), dt,
                cap_extra=0.0):
    """Force and torque on body A of one contact (n points from B to A, overlap > 0).

    v_c: velocity of A's contact point relative to B's; w_rel: angular velocity of A relative to B;
    sqrt_mk, sqrt_ik: sqrt(m_eff k) and sqrt(I_eff k) (effective mass and moment of inertia of the pair);
    hist: (tangential spring, rolling spring); cap_extra: tangential capacity added to mu F_n (adhesion). Returns
    the force on A, its tangential part, the rolling torque on A, and the new history; the torque on A is
    lever x f_t + m_r (B gets the opposite of each).
    Normal: linear spring-dashpot (Cundall & Strack). The dashpot may pull briefly while the bodies separate;
    that is what makes the restitution exactly e (clipping it would raise e for strong damping). Tangential: spring k_t = P_KT_RATIO k with history,
    capped at mu F_n (Coulomb); the stored spring is projected onto the current tangent plane each step (the
    contact frame turns a little per step; the length lost is of second order in that turn). Rolling and
    twisting: EPSD type C (Ai et al. 2011) spring k_r = 2.25 mu_r^2 k r_roll^2 on the relative rotation with
    viscous damping while elastic, torque capped at mu_r r_roll F_n.
    """
    gamma = prm[P_DAMP] * sqrt_mk
    v_n = v_c.dot(n)
    f_n = k * overlap - gamma * v_n
    f_press = ti.max(f_n, 0.0)  # friction and rolling resistance need compression
    v_t = v_c - v_n * n
    kt = prm[P_KT_RATIO] * k
    gt = prm[P_KT_RATIO] * gamma
    xi = vec3(hist[0], hist[1], hist[2])
    xi += v_t * dt - xi.dot(n) * n
    f_t = -kt * xi - gt * v_t
    cap = mu * f_press + cap_extra
    ft2 = f_t.dot(f_t)
    if ft2 > cap * cap:
        # sliding: force at the Coulomb limit, spring set to what that force implies (Luding 2008)
        f_t *= cap / ti.sqrt(ft2)
        xi = -(f_t + gt * v_t) / kt
    theta = vec3(0.0)
    m_r = vec3(0.0)
    if mu_r > 0.0:
        # the whole relative rotation, rolling and twisting (spin about n): a sphere spinning on its contact
        # would otherwise never stop
        kr = ti.f64(2.25) * mu_r * mu_r * k * r_roll * r_roll
        cr = prm[P_ETA_R] * 3.0 * mu_r * r_roll * sqrt_ik  # eta 2 sqrt(I_eff k_r)
        theta = vec3(hist[3], hist[4], hist[5]) + w_rel * dt
        m_r = -kr * theta - cr * w_rel
        cap_r = mu_r * r_roll * f_press
        mr2 = m_r.dot(m_r)
        if mr2 > cap_r * cap_r:
            m_r *= cap_r / ti.sqrt(mr2)
            theta = -m_r / ti.max(kr, 1e-300)  # kr > 0 here; the guard only silences constant folding
    new_hist = vec6f(xi[0], xi[1], xi[2], theta[0], theta[1], theta[2])
    return f_n * n + f_t, f_t, m_r, new_hist


@ti.func
def band_attraction(gap, big_f, dist):
    """Attraction magnitude at surface gap `gap` (negative = overlapping) of a Holz-style bond: big_f at and inside
    contact, falling linearly to 0 at gap = dist, so the force is continuous."""
    f = ti.f64(0.0)
    if gap <= 0.0:
        f = big_f
    elif gap < dist:
        f = big_f * (1.0 - gap / dist)
    return f


@ti.func
def cohesion_force(gap, prm: ti.template()):
    """Attraction between two particles with surface gap `gap`: band_attraction(F, D) of the soil's cohesion."""
    return band_attraction(gap, prm[P_COH_F], prm[P_COH_D])


# ----------------------------------------------------------------------------------------------- pair forces
def _pair_forces(n_act: ti.i32, kin: ti.template(), prop: ti.template(), nbr_off: ti.template(),
                 nbr_j: ti.template(), nbr_h: ti.template(), rev_pos: ti.template(), pair_out: ti.template(),
                 own: ti.template(), surf_id: ti.template(), prm: ti.template(), dt: ti.f64,
                 blk_list: ti.template(), blk_active: ti.template(), block: ti.i32, n_frozen: ti.i32,
                 stat: ti.template(), tools: ti.template()):
    """Contact and cohesion forces of every listed pair, each evaluated once, by its holder i.

    The force and torque on i are summed into own[i]; what j receives is written to pair_out[rev_pos[e]]
    (e: the entry), i.e. into j's reverse segment, which step() reads sequentially (scattered stores are
    cheaper than scattered loads). No atomics: deterministic for a given thread count, and j gets exactly
    minus i's force (momentum is conserved to round-off).
    A soil wedge's grains (_wedge_role) move together: no force between two of them, but two that overlap are
    pushed apart, each by half the overlap (own[i, 2] for i, pair_out[q, 1] for j instead of a torque: they do not
    spin; step() moves them by at most the wedge's own travel per substep), so a grain eased off the face does not
    sink into its neighbours; across its failure plane a pair keeps only its normal push (the plane's strength is
    the wedge's equilibrium), which a wedge grain holding the pair sums in own[i, 1] instead of a torque.
    """
    sleep_steps = ti.cast(prm[P_SLEEP_STEPS], ti.i32)
    wake_v2 = WAKE_FACTOR2 * prm[P_SLEEP_V2]
    # while a slow tool shoves soil, a neighbour closing in on a sleeper faster than WAKE_APPROACH x the quiet speed
    # wakes it (see P_SLEEP_STEPS)
    shoving = _shoving(tools, prm)
    approach_v = WAKE_APPROACH * ti.sqrt(prm[P_SLEEP_V2])
    # only the blocks mark_blocks listed: in the others all are asleep and hold pairs with sleepers only, all skipped
    ti.loop_config(serialize=SERIAL_LOOPS)
    for slot in range(blk_list[0] * block):
        i = n_frozen + blk_list[slot // block + 1] * block + slot % block
        if i >= n_act:
            continue
        x_i = kin[i, 0]
        v_i = kin[i, 1]
        w_i = kin[i, 2]
        p_i = prop[i]
        r_i = p_i[0]
        asleep_i = False
        fast_i = False
        if sleep_steps > 0:
            asleep_i = (surf_id[i, TOOL_BITS] >> CALM_SHIFT) >= sleep_steps
            fast_i = v_i.dot(v_i) > wake_v2
        reach_extra = prm[P_COH_D]
        k = prm[P_KN]
        sqrt_k = prm[P_SQRT_KN]
        mu = prm[P_MU]
        mu_r = prm[P_MU_R]
        f = vec3(0.0)
        t = vec3(0.0)
        f_plane = vec3(0.0)
        apart = vec3(0.0)  # a wedge grain's way out of the wedge grains it overlaps
        role_i = WG_FREE
        if ti.static(WEDGES):
            role_i = _wedge_role(x_i, r_i, tools)
            own[i, 3] = vec3(ti.cast(role_i, ti.f64), 0.0, 0.0)  # (step() reads it: positions move there)
        for e in range(nbr_off[i], nbr_off[i + 1]):
            j = nbr_j[e]
            together = False  # both in a wedge: no force
            plane = False     # a wedge's grain and one beyond its failure plane or beside it: the normal push only
            across = False    # beyond the failure plane: its reaction
            if ti.static(WEDGES) and role_i != WG_FREE:
                role_j = _wedge_role(kin[j, 0], prop[j][0], tools)
                if role_j != WG_FREE:
                    together = (role_i & 3) == WG_IN and (role_j & 3) == WG_IN
                    one_in = ((role_i & 3) == WG_IN) != ((role_j & 3) == WG_IN)
                    plane = one_in and (role_i >> 2) == (role_j >> 2)
                    across = plane and ((role_i & 3) == WG_LAYER or (role_j & 3) == WG_LAYER)
            if sleep_steps > 0:
                asleep_j = (surf_id[j, TOOL_BITS] >> CALM_SHIFT) >= sleep_steps
                if asleep_i and asleep_j:
                    continue  # neither moves: the pair's force is not needed and its springs keep their values
                if asleep_i != asleep_j:
                    v_j = kin[j, 1]
                    d_ij = x_i - kin[j, 0]
                    reach_ij = r_i + prop[j][0] + prm[P_COH_D]
                    if d_ij.dot(d_ij) < reach_ij * reach_ij:
                        closing_i = False
                        closing_j = False
                        if shoving:  # (not a frozen sleeper: frozen soil lies beyond every tool's reach, and a
                            # thaw costs a repartition of the whole bed)
                            closing_i = j >= n_frozen and -v_i.dot(d_ij) > approach_v * d_ij.norm()
                            closing_j = v_j.dot(d_ij) > approach_v * d_ij.norm()
                        if asleep_j and (fast_i or closing_i):
                            ti.atomic_or(surf_id[j, TOOL_BITS], WAKE_BIT)
                            if j < n_frozen:  # frozen: not integrated until the host repartitions
                                stat[S_THAW] = 1.0
                                stat[S_HALT] = 1.0
                            else:  # its step() this substep takes the request, as if its block had been listed
                                # (nested: Taichi's `and` evaluates both sides, in an order of its choosing)
                                b_j = (j - n_frozen) // block
                                if blk_active[b_j] == 0:
                                    if ti.atomic_max(blk_active[b_j], 1) == 0:
                                        blk_list[ti.atomic_add(blk_list[0], 1) + 1] = b_j
                        if asleep_i and (v_j.dot(v_j) > wake_v2 or closing_j):
                            ti.atomic_or(surf_id[i, TOOL_BITS], WAKE_BIT)
            dx = x_i - kin[j, 0]
            d2 = dx.dot(dx)
            p_j = prop[j]
            r_j = p_j[0]
            r_sum = r_i + r_j
            reach = r_sum + reach_extra
            f_pair = vec3(0.0)  # on i
            t_j = vec3(0.0)
            touching = False
            if d2 < reach * reach and d2 > 0.0 and not together:
                d = ti.sqrt(d2)
                n = dx * (1.0 / d)
                gap = d - r_sum
                if gap < 0.0:
                    touching = True
                    # pair means by products, not divisions (the hot loop is bound by sqrt/div latency): with
                    # radii within +-10% the geometric mean is within 1% of the harmonic one.
                    # m_eff = m_i m_j/(m_i + m_j) ~ sqrt(m_i m_j)/2, I_eff likewise, r_i r_j/r_sum ~ r_sum/4
                    qq = p_i[3] * p_j[3]
                    sqrt_mk = ti.f64(SQRT_HALF) * qq * sqrt_k
                    sqrt_ik = ti.f64(SQRT_FIFTH) * qq * 0.5 * r_sum * sqrt_k
                    # contact points at -r_i n (on i) and +r_j n (on j): one cross product each for the relative
                    # contact velocity and for both torques
                    w_j = kin[j, 2]
                    v_c = (v_i - kin[j, 1]) - (r_i * w_i + r_j * w_j).cross(n)
                    mu_pair = mu
                    mu_r_pair = mu_r
                    if plane:
                        mu_pair = 0.0
                        mu_r_pair = 0.0
                    force, f_t, m_r, h = contact_law(n, -gap, v_c, w_i - w_j, sqrt_mk, sqrt_ik, 0.25 * r_sum,
                                                     nbr_h[e], k, mu_pair, mu_r_pair, prm, dt)
                    f_pair = force
                    c = n.cross(f_t)
                    t += m_r - r_i * c
                    t_j = -r_j * c - m_r
                    nbr_h[e] = h
                if not plane:
                    f_pair -= cohesion_force(gap, prm) * n
            elif ti.static(WEDGES) and together and d2 < r_sum * r_sum and d2 > 0.0:
                d = ti.sqrt(d2)
                half = (0.5 * (r_sum - d) / d) * dx
                apart += half
                t_j = -half
            if not touching:
                h_old = nbr_h[e]
                if h_old[0] != 0.0 or h_old[1] != 0.0 or h_old[3] != 0.0 or h_old[4] != 0.0:
                    nbr_h[e] = vec6f(0.0)
            f_out = ti.cast(-f_pair, ti.f32)
            f -= ti.cast(f_out, ti.f64)  # exactly minus what j gets
            if across:
                f_plane -= ti.cast(f_out, ti.f64)
            q = rev_pos[e]
            pair_out[q, 0] = f_out
            pair_out[q, 1] = ti.cast(t_j, ti.f32)
        if ti.static(WEDGES) and (role_i & 3) == WG_IN:
            own[i, 0] = f - f_plane
            own[i, 1] = f_plane
            own[i, 2] = apart
        else:
            own[i, 0] = f
            own[i, 1] = t


# ----------------------------------------------------------------------------------------------- static geometry
@ti.func
def _pit_of(x, prm: ti.template()):
    """Index of the pit whose footprint holds x (its centre), or -1."""
    found = -1
    for k in range(ti.cast(prm[P_NPITS], ti.i32)):
        b = P_PITS + 6 * k
        if found < 0 and prm[b] <= x[0] <= prm[b + 3] and prm[b + 1] <= x[1] <= prm[b + 4]:
            found = k
    return found


@ti.func
def _clearance(x, pit, prm: ti.template()):
    """Lower bound of the distance from x to every static face that can touch it (plane distances)."""
    c = ti.min(ti.min(x[0] - prm[P_DMIN], prm[P_DMAX] - x[0]), ti.min(x[1] - prm[P_DMIN + 1], prm[P_DMAX + 1] - x[1]))
    if pit < 0:
        c = ti.min(c, x[2])
    else:
        b = P_PITS + 6 * pit
        c = ti.min(c, ti.min(x[2] - prm[b + 2], ti.min(ti.min(x[0] - prm[b], prm[b + 3] - x[0]),
                                                       ti.min(x[1] - prm[b + 1], prm[b + 4] - x[1]))))
    return c


@ti.func
def _face(fid, pit, x, r, prm: ti.template()):
    """Geometry of static face `fid` seen from a particle at x: (overlap, outward normal, buried).

    overlap <= 0: no contact. buried: the centre is inside the solid (the particle tunnelled) or outside the
    domain, and the particle must be taken out of the simulation.
    """
    overlap = ti.f64(-1.0)
    n = vec3(0.0)
    buried = False
    if fid < 4:  # domain side walls, full height
        axis = fid // 2
        side = fid % 2
        dist = x[axis] - prm[P_DMIN + axis]
        n[axis] = 1.0
        if side == 1:
            dist = prm[P_DMAX + axis] - x[axis]
            n[axis] = -1.0
        if dist <= 0.0:
            buried = True
        overlap = r - dist
    elif fid == FACE_GROUND:
        if pit < 0:
            n[2] = 1.0
            if x[2] <= 0.0:
                buried = True
            overlap = r - x[2]
    else:
        k = (fid - 5) // FACES_PER_PIT
        f = (fid - 5) % FACES_PER_PIT
        if k == pit:
            b = P_PITS + 6 * k
            z_floor = prm[b + 2]
            if f == 0:
                n[2] = 1.0
                if x[2] <= z_floor:
                    buried = True
                overlap = r - (x[2] - z_floor)
            else:
                # wall rectangle spans floor..0; above ground its top edge is the (rounded) pit rim
                axis = (f - 1) // 2
                side = (f - 1) % 2
                # a pit wall on (or beyond) the domain boundary is left to the smooth domain wall there
                on_boundary = prm[b + axis] <= prm[P_DMIN + axis]
                if side == 1:
                    on_boundary = prm[b + 3 + axis] >= prm[P_DMAX + axis]
                d = vec3(0.0)
                d[axis] = x[axis] - prm[b + axis]
                if side == 1:
                    d[axis] = x[axis] - prm[b + 3 + axis]
                d[2] = x[2] - ti.min(ti.max(x[2], z_floor), prm[P_WALL_TOP])
                dist = d.norm()
                if dist > 0.0 and not on_boundary:
                    n = d / dist
                    overlap = r - dist
    return overlap, n, buried


@ti.func
def _face_plane_distance(fid, pit, x, prm: ti.template()):
    """Distance from x to the plane of static face `fid`: a lower bound of the distance to the face itself, so a
    particle farther than its radius cannot touch it, nor be buried in it (HUGE for a ground face under a pit)."""
    dist = ti.f64(HUGE)
    if fid < 4:
        axis = fid // 2
        dist = x[axis] - prm[P_DMIN + axis]
        if fid % 2 == 1:
            dist = prm[P_DMAX + axis] - x[axis]
    elif fid == FACE_GROUND:
        if pit < 0:
            dist = x[2]
    else:
        f = (fid - 5) % FACES_PER_PIT
        b = P_PITS + 6 * pit
        if f == 0:
            dist = x[2] - prm[b + 2]
        else:
            axis = (f - 1) // 2
            dist = ti.abs(x[axis] - prm[b + axis])
            if (f - 1) % 2 == 1:
                dist = ti.abs(x[axis] - prm[b + 3 + axis])
    return dist


@ti.func
def _find_slot(ids, fid):
    """Slot already holding face fid, else the first free slot, else -1 (contact without history)."""
    slot = -1
    free = -1
    for s in ti.static(range(WALL_SLOTS)):
        if ids[s] == fid and slot < 0:
            slot = s
        if ids[s] < 0 and free < 0:
            free = s
    if slot < 0:
        slot = free
    return slot


@ti.func
def _tool_rotation(tools: ti.template(), t):
    return mat3(tools[t, T_ROT + 0], tools[t, T_ROT + 1], tools[t, T_ROT + 2],
                tools[t, T_ROT + 3], tools[t, T_ROT + 4], tools[t, T_ROT + 5],
                tools[t, T_ROT + 6], tools[t, T_ROT + 7], tools[t, T_ROT + 8])


@ti.func
def sample_sdf(sdf: ti.template(), tools: ti.template(), t, p_local):
    """Trilinear (distance, gradient) of tool t's SDF at a link-frame point; distance HUGE outside the grid."""
    out = vec4(HUGE, 0.0, 0.0, 0.0)
    h = tools[t, T_H]
    u = (p_local - vec3(tools[t, T_ORG], tools[t, T_ORG + 1], tools[t, T_ORG + 2])) / h
    nx = ti.cast(tools[t, T_NX], ti.i32)
    ny = ti.cast(tools[t, T_NY], ti.i32)
    nz = ti.cast(tools[t, T_NZ], ti.i32)
    if 0.0 <= u[0] < nx - 1 and 0.0 <= u[1] < ny - 1 and 0.0 <= u[2] < nz - 1:
        i0 = ti.cast(ti.floor(u[0]), ti.i32)
        j0 = ti.cast(ti.floor(u[1]), ti.i32)
        k0 = ti.cast(ti.floor(u[2]), ti.i32)
        fx = u[0] - i0
        fy = u[1] - j0
        fz = u[2] - k0
        base = ti.cast(tools[t, T_OFF], ti.i32) + (i0 * ny + j0) * nz + k0
        acc = vec4(0.0)
        for c in ti.static(range(8)):
            di, dj, dk = c // 4, (c // 2) % 2, c % 2
            wgt = (fx if di else 1.0 - fx) * (fy if dj else 1.0 - fy) * (fz if dk else 1.0 - fz)
            acc += wgt * ti.cast(sdf[base + (di * ny + dj) * nz + dk], ti.f64)
        out = acc
    return out


@ti.func
def _on_grid(x, quantum):
    """x rounded to a multiple of quantum (a power of two: both steps are exact)."""
    return ti.floor(x / quantum + 0.5) * quantum


@ti.func
def _rotation_from_vector(phi):
    """Rotation matrix of the rotation vector phi (Rodrigues)."""
    angle = phi.norm()
    rot = ti.Matrix.identity(ti.f64, 3)
    if angle > 1e-300:
        a = phi / angle
        kx = mat3(0.0, -a[2], a[1], a[2], 0.0, -a[0], -a[1], a[0], 0.0)
        rot += ti.sin(angle) * kx + (1.0 - ti.cos(angle)) * (kx @ kx)
    return rot


# ----------------------------------------------------------------------------------------------- integration
@ti.func
def _wedge_frame(tools: ti.template(), t):
    """Tool t's cutting edge in the world: its centre e, the face normal n and up-face direction u, the edge's
    direction y, the horizontal h the face pushes along, the failure plane's direction f (up from the edge at the
    failure angle, in the vertical plane of h) and its normal m_g into the ground beyond it, and the edge's velocity;
    hn: the face normal's horizontal length (a face looking down or up cuts nothing)."""
    rot = _tool_rotation(tools, t)
    origin = vec3(tools[t, T_POS], tools[t, T_POS + 1], tools[t, T_POS + 2])
    e = origin + rot @ vec3(tools[t, T_WG_E], tools[t, T_WG_E + 1], tools[t, T_WG_E + 2])
    n = rot @ vec3(tools[t, T_WG_N], tools[t, T_WG_N + 1], tools[t, T_WG_N + 2])
    u = rot @ vec3(tools[t, T_WG_U], tools[t, T_WG_U + 1], tools[t, T_WG_U + 2])
    y = n.cross(u)
    h = vec3(n[0], n[1], 0.0)
    hn = h.norm()
    h = h / ti.max(hn, 1e-12)
    beta = tools[t, T_WG_BETA]
    f = ti.cos(beta) * h + vec3(0.0, 0.0, ti.sin(beta))
    m_g = y.cross(f)
    m_g = m_g / ti.max(m_g.norm(), 1e-12)
    if m_g[2] > 0.0:
        m_g = -m_g
    vel = vec3(tools[t, T_VEL], tools[t, T_VEL + 1], tools[t, T_VEL + 2])
    ang = vec3(tools[t, T_ANG], tools[t, T_ANG + 1], tools[t, T_ANG + 2])
    v_e = vel + ang.cross(e - origin)
    return e, n, u, y, h, f, m_g, v_e, hn


@ti.func
def _wedge_cutting(tools: ti.template(), t, n, v_e, hn):
    """Tool t's wedge acts while the tool is on, has an edge, and its face moves into the soil."""
    return tools[t, T_ON] > 0.0 and tools[t, T_WG_ON] > 0.0 and hn > 0.1 and v_e.dot(n) > 1e-6


@ti.func
def _wedge_role(x, r, tools: ti.template()):
    """A particle's part in the soil wedges (AGX Terrain's aggregate at a cutting edge): WG_IN + 4 t, a grain of tool
    t's wedge (ahead of its face, behind the failure plane through the edge, under the ground ahead: it moves with
    the wedge); WG_LAYER + 4 t, a grain of the layer beyond the plane (it takes the plane's reaction; at an opening,
    whose wedge is only the soil the edge meets, the soil beyond takes its push through the contacts alone: the whole
    plane's reaction on that short a layer would shove the ground ahead); WG_SIDE + 4 t, a grain beside the wedge,
    past the edge's ends (it slides along the wedge without friction, as the plane-strain wedge of the equation has no
    sides); WG_FREE. At an opening a grain over the edge is free (_into_the_opening)."""
    code = WG_FREE
    for t in ti.static(range(MAX_TOOLS)):
        if code == WG_FREE and tools[t, T_WG_ENGAGED] > 0.0:
            rel = x - vec3(tools[t, T_WG_EW], tools[t, T_WG_EW + 1], tools[t, T_WG_EW + 2])
            s_f = rel.dot(vec3(tools[t, T_WG_NW], tools[t, T_WG_NW + 1], tools[t, T_WG_NW + 2]))
            side = ti.abs(rel.dot(vec3(tools[t, T_WG_YW], tools[t, T_WG_YW + 1], tools[t, T_WG_YW + 2]))) - \
                tools[t, T_WG_HW]
            # (nested: Taichi's `and` evaluates both sides, and most grains are far from the slab)
            if s_f > -r and side < WG_LAYER_R * r:
                if not _into_the_opening(rel, r, tools, t):
                    low = tools[t, T_WG_EW + 2] - WG_LOW * r
                    s_g = (rel + vec3(0.0, 0.0, WG_LOW * r)).dot(vec3(tools[t, T_WG_MG], tools[t, T_WG_MG + 1],
                                                                      tools[t, T_WG_MG + 2]))
                    if side >= 0.0:
                        if s_g < WG_LAYER_R * r and x[2] > low - 2.0 * r:
                            code = WG_SIDE + 4 * t
                    elif s_g < 0.0:
                        if x[2] > low and x[2] < tools[t, T_WG_TOP]:
                            code = WG_IN + 4 * t
                    elif s_g < WG_LAYER_R * r and x[2] > low - 2.0 * r and tools[t, T_WG_ON] != WG_OPENING:
                        code = WG_LAYER + 4 * t
    return code


@ti.func
def _into_the_opening(rel, r, tools: ti.template(), t):
    """Whether a grain at rel from tool t's edge is free to pass into its opening (a bucket's mouth, T_WG_ON
    WG_OPENING): it lies over the edge, up the opening's plane by more than its radius. At an opening the wedge is the
    soil the edge meets, which rises with it until it clears the edge; the soil over the edge meets the tool only
    through that wedge and the tool's plates, and the advancing bucket takes it in (over a blade's face it moves with
    the wedge)."""
    n = vec3(tools[t, T_WG_NW], tools[t, T_WG_NW + 1], tools[t, T_WG_NW + 2])
    u = vec3(tools[t, T_WG_YW], tools[t, T_WG_YW + 1], tools[t, T_WG_YW + 2]).cross(n)  # (y = n x u)
    return tools[t, T_WG_ON] == WG_OPENING and rel.dot(u) > r


@ti.func
def _role(own: ti.template(), i):
    """Particle i's part in the soil wedges this substep (_wedge_role), as pair_forces found it before any particle
    moved: step() moves them in parallel, so a role found there from a neighbour's position would depend on the
    threads' order (a grain of a listed block: its block, and those holding its pairs, were listed)."""
    return ti.cast(own[i, 3][0], ti.i32)


@ti.func
def _wedge_watch(x, v, r, tools: ti.template(), stat: ti.template()):
    """What a cutting tool's wedge needs to know of a grain that is not in it. The ground ahead, as it was: the highest
    top among the grains at rest (slower than WG_REST x the wedge) in a band WG_FRONT_R radii deep beyond the failure
    plane (the grains the wedge pushes, heave, and the spoil move: they are the earthmoving equation's surcharge, not
    its wedge). And whether the soil touches the face: the narrowest gap to it of a grain in the wedge's region."""
    for t in ti.static(range(MAX_TOOLS)):
        if tools[t, T_WG_LIVE] > 0.0:
            rel = x - vec3(tools[t, T_WG_EW], tools[t, T_WG_EW + 1], tools[t, T_WG_EW + 2])
            s_f = rel.dot(vec3(tools[t, T_WG_NW], tools[t, T_WG_NW + 1], tools[t, T_WG_NW + 2]))
            if s_f > -r and ti.abs(rel.dot(vec3(tools[t, T_WG_YW], tools[t, T_WG_YW + 1],
                                                tools[t, T_WG_YW + 2]))) < tools[t, T_WG_HW]:
                s_g = (rel + vec3(0.0, 0.0, WG_LOW * r)).dot(vec3(tools[t, T_WG_MG], tools[t, T_WG_MG + 1],
                                                                  tools[t, T_WG_MG + 2]))
                v_w = vec3(tools[t, T_WG_VW], tools[t, T_WG_VW + 1], tools[t, T_WG_VW + 2])
                if s_g >= 0.0 and s_g < WG_FRONT_R * r and v.dot(v) < WG_REST * WG_REST * v_w.dot(v_w):
                    ti.atomic_max(stat[S_WG_TOP + t], x[2] + r)
                if s_g < 0.0 and x[2] > tools[t, T_WG_EW + 2] - WG_LOW * r and x[2] < tools[t, T_WG_TOP]:
                    ti.atomic_min(stat[S_WG_GAP + t], (s_f - r) / r)


@ti.func
def _wedge_refresh(tools: ti.template(), t):
    """Tool t's wedge in the world, for the particles' tests (T_WG_LIVE..): after the tool moved or was set."""
    live = 0.0
    engaged = 0.0
    if tools[t, T_WG_ON] > 0.0:
        e, n, u, y, h, f, m_g, v_e, hn = _wedge_frame(tools, t)
        if _wedge_cutting(tools, t, n, v_e, hn):
            live = 1.0
            # (once the soil has touched the face the wedge moves with it, at the gap it had: it stays engaged
            # until the tool stops cutting)
            if ti.atan2(u[2], -u.dot(h)) > WG_MIN_RAKE and tools[t, T_WG_TOP] > e[2] and \
                    (tools[t, T_WG_ENGAGED] > 0.0 or tools[t, T_WG_GAP] <= WG_TOUCH):
                engaged = 1.0
        # a plate's wedge slides along the failure plane, as fast into the soil as the face; at an opening the soil
        # the edge meets moves with the edge and up the mouth at that speed, into the bucket (sliding along the
        # plane, it shoved the soil ahead of the mouth: docs/dig_path.md)
        v_w = f * (v_e.dot(n) / f.dot(n))
        if tools[t, T_WG_ON] == WG_OPENING:
            v_w = v_e + v_e.dot(n) * u
        for c in ti.static(range(3)):
            tools[t, T_WG_EW + c] = e[c]
            tools[t, T_WG_NW + c] = n[c]
            tools[t, T_WG_YW + c] = y[c]
            tools[t, T_WG_MG + c] = m_g[c]
            tools[t, T_WG_VW + c] = v_w[c]
    tools[t, T_WG_LIVE] = live
    tools[t, T_WG_ENGAGED] = engaged


@ti.func
def _fee_p(beta, alpha, prm: ti.template(), depth):
    """The earthmoving equation's push per metre of edge at failure angle beta (HUGE where no wedge is admissible)."""
    phi = prm[P_WG_PHI]
    delta = prm[P_WG_DELTA]
    cot_a = ti.cos(alpha) / ti.sin(alpha)
    cot_b = ti.cos(beta) / ti.sin(beta)
    cot_bp = ti.cos(beta + phi) / ti.sin(beta + phi)
    dd = ti.cos(alpha + delta) + ti.sin(alpha + delta) * cot_bp
    p = ti.f64(HUGE)
    if dd > 0.0:
        p = (prm[P_WG_GAMMA] * depth * depth * (cot_a + cot_b) / 2.0 + prm[P_WG_C] * depth * (1.0 + cot_b * cot_bp)
             + prm[P_WG_CA] * depth * (1.0 - cot_a * cot_bp)) / dd
    return p


@ti.func
def _wedge_equilibrium(t, sums, tools: ti.template(), tool_acc: ti.template(), prm: ti.template(),
                       on_grid: ti.template()):
    """Tool t's wedge after a substep. sums: what the free grains put on its grains (0-2), what the layer beyond the
    plane puts on them across it (3-5), their mass (6), the layer's mass (7). The wedge is in equilibrium under its
    weight, those forces, the face's push (at delta to its normal, with adhesion up the face) and the plane's
    reaction (at phi to its normal, with cohesion along it): the push goes on the tool, the plane's reaction less
    what the contacts across it carried on the layer (spread by mass, from the next substep). Then the failure angle
    that minimises the equation's push at this depth, and the front surface, are kept for the next substep."""
    e, n, u, y, h, f, m_g, v_e, hn = _wedge_frame(tools, t)
    acc = vec3(0.0)
    depth = tools[t, T_WG_TOP] - e[2]
    alpha = ti.atan2(u[2], -u.dot(h))
    if tools[t, T_WG_ENGAGED] > 0.0 and depth > 0.0 and sums[6] > 0.0 and alpha > WG_MIN_RAKE:
        phi = prm[P_WG_PHI]
        delta = prm[P_WG_DELTA]
        beta = tools[t, T_WG_BETA]
        width = 2.0 * tools[t, T_WG_HW]
        adhesion = prm[P_WG_CA] * depth / ti.sin(alpha) * width * u
        cohesion = prm[P_WG_C] * depth / ti.sin(beta) * width * f
        a = n * ti.cos(delta) - u * ti.sin(delta)
        b = -m_g * ti.cos(phi) - f * ti.sin(phi)
        weight = sums[6] * vec3(prm[P_G], prm[P_G + 1], prm[P_G + 2])
        rhs = adhesion + cohesion - weight - vec3(sums[0], sums[1], sums[2])
        z = vec3(0.0, 0.0, 1.0)
        det = a.dot(h) * b[2] - a[2] * b.dot(h)
        p = ti.max((rhs.dot(h) * b[2] - rhs[2] * b.dot(h)) / det, 0.0)
        r_plane = ti.max((a.dot(h) * rhs[2] - a[2] * rhs.dot(h)) / det, 0.0)
        side = rhs - rhs.dot(h) * h - rhs[2] * z  # along the edge: the face holds it
        push = p * a - adhesion + side
        plane = r_plane * b - cohesion
        origin = vec3(tools[t, T_POS], tools[t, T_POS + 1], tools[t, T_POS + 2])
        on_tool = -push
        moment = (e + u * (depth / (3.0 * ti.sin(alpha))) - origin).cross(on_tool)
        if ti.static(on_grid):  # (the GPU layout's: the grains' terms come by atomics on WRENCH_QUANTUM's grid, so a
            # total kept on it is exact in any order; one off it would round each term by where the order put it)
            on_tool = _on_grid(on_tool, WRENCH_QUANTUM)
            moment = _on_grid(moment, WRENCH_QUANTUM)
        for c in ti.static(range(3)):
            tool_acc[t, c] += on_tool[c]
            tool_acc[t, 3 + c] += moment[c]
            tools[t, T_WG_PUSH + c] = on_tool[c]
        if sums[7] > 0.0:  # (at most the plane's whole reaction: a layer the wedge lost touch with is not flung)
            rest = plane - vec3(sums[3], sums[4], sums[5])
            acc = -rest * ti.min(1.0, plane.norm() / ti.max(rest.norm(), 1e-300)) / sums[7]
        # the failure angle of the equation at this depth and rake: golden section on (0, pi/2)
        lo = ti.f64(1e-3)
        hi = ti.f64(0.5 * 3.141592653589793 - 1e-3)
        for _ in range(48):
            m1 = hi - 0.6180339887498949 * (hi - lo)
            m2 = lo + 0.6180339887498949 * (hi - lo)
            if _fee_p(m1, alpha, prm, depth) < _fee_p(m2, alpha, prm, depth):
                hi = m2
            else:
                lo = m1
        tools[t, T_WG_BETA] = 0.5 * (lo + hi)
    for c in ti.static(range(3)):
        tools[t, T_WG_ACC + c] = acc[c]


@ti.func
def _mark_hot(i, base, block, blk_hot: ti.template(), rev_off: ti.template(), rev_holder: ti.template()):
    """Particle i is awake for the next substep: its block and the blocks holding its other pairs take part in it.
    The pairs i holds are evaluated in its own block, so its partners' blocks are not needed unless i asks one of
    them to wake (pair_forces lists that block then). Blocks start at `base` (the first particle after the frozen
    prefix, which is in none)."""
    blk_hot[(i - base) // block] = 1
    for q in range(rev_off[i], rev_off[i + 1]):
        blk_hot[(rev_holder[q] - base) // block] = 1


@ti.func
def _sphere_centre(tools: ti.template(), t, rot):
    """World centre of tool t's bounding sphere (rot: the tool's rotation)."""
    return vec3(tools[t, T_POS], tools[t, T_POS + 1], tools[t, T_POS + 2]) + \
        rot @ vec3(tools[t, T_BS], tools[t, T_BS + 1], tools[t, T_BS + 2])


@ti.func
def _near_a_slow_tool(x, tools: ti.template(), v_wake, v_min):
    """Whether x lies in the bounding sphere of an active tool's SDF grid whose points move slower than v_wake (and
    at v_min or faster): a tool that carries or presses soil that slowly would never wake the sleepers it pushes
    against (the soil it pushes moves slower than the wake speed too)."""
    near = False
    for t in range(MAX_TOOLS):
        if tools[t, T_ON] > 0.0:
            r_bs = tools[t, T_BS + 3]
            d = x - _sphere_centre(tools, t, _tool_rotation(tools, t))
            speed = _tool_speed(tools, t)
            near = near or (d.dot(d) < r_bs * r_bs and v_min <= speed < v_wake)
    return near


@ti.func
def _tool_speed(tools: ti.template(), t):
    """An upper bound of the speed of tool t's points in its bounding sphere."""
    return vec3(tools[t, T_VEL], tools[t, T_VEL + 1], tools[t, T_VEL + 2]).norm() + \
        vec3(tools[t, T_ANG], tools[t, T_ANG + 1], tools[t, T_ANG + 2]).norm() * tools[t, T_BS + 3]


@ti.func
def _slow(tools: ti.template(), t, prm: ti.template()):
    """Whether tool t shoves soil too slowly to wake it by speed: between CREEP_FRACTION and SLOW_FACTOR x the wake
    speed (slower: parked; faster: the soil it moves wakes its neighbours)."""
    v_wake = ti.sqrt(WAKE_FACTOR2 * prm[P_SLEEP_V2])
    v_t = _tool_speed(tools, t)
    return tools[t, T_ON] > 0.0 and CREEP_FRACTION * v_wake <= v_t and v_t < SLOW_FACTOR * v_wake


@ti.func
def _shoving(tools: ti.template(), prm: ti.template()):
    """Whether any tool is slow (_slow): the sleepers' extra wake tests run only then."""
    any_slow = False
    for t in ti.static(range(MAX_TOOLS)):
        if _slow(tools, t, prm):
            any_slow = True
    return any_slow


@ti.func
def _in_a_slow_tools_grid(x, tools: ti.template(), prm: ti.template()):
    """Whether x may lie in the SDF grid of a slow tool (the test _box_meets_tool_grid makes for a block's box: a
    sleeper this wakes is in a block mark_blocks lists, so skipping the other blocks changes nothing)."""
    inside = False
    for t in range(MAX_TOOLS):
        if _slow(tools, t, prm):
            inside = inside or _box_meets_tool_grid(x, x, tools, t)
    return inside


@ti.func
def _box_meets_tool_grid(lo, hi, tools: ti.template(), t):
    """Whether a world box may meet tool t's SDF grid (sample_sdf is HUGE outside it, so no grain outside can touch
    or wake): the box against the grid's bounding sphere, then against the grid box along the tool's three axes
    (conservative: a box that passes may still miss the grid, never the other way round)."""
    rot = _tool_rotation(tools, t)
    centre = _sphere_centre(tools, t, rot)
    d = ti.max(lo, ti.min(centre, hi)) - centre
    meets = d.dot(d) <= tools[t, T_BS + 3] * tools[t, T_BS + 3]
    if meets:
        local = rot.transpose() @ (0.5 * (lo + hi) - centre)
        box_half = 0.5 * (hi - lo)
        for a in ti.static(range(3)):
            grid_half = 0.5 * (tools[t, T_NX + a] - 1.0) * tools[t, T_H]
            reach = grid_half + ti.abs(rot[0, a]) * box_half[0] + ti.abs(rot[1, a]) * box_half[1] + \
                ti.abs(rot[2, a]) * box_half[2]
            if ti.abs(local[a]) > reach * (1.0 + 1e-9) + 1e-9:
                meets = False
    return meets


@ti.func
def _box_meets_wedge(lo, hi, tools: ti.template(), t, r):
    """Whether a world box of particle centres may hold a grain that tool t's live wedge moves, loads or watches
    (_wedge_role, _wedge_watch; r: at least the largest grain radius): the box against the slab beside the edge and the
    half-spaces ahead of the face, over the floor of the wedge, and short of the front band's far side
    (conservative, as _box_meets_tool_grid)."""
    centre = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    e = vec3(tools[t, T_WG_EW], tools[t, T_WG_EW + 1], tools[t, T_WG_EW + 2])
    n = vec3(tools[t, T_WG_NW], tools[t, T_WG_NW + 1], tools[t, T_WG_NW + 2])
    y = vec3(tools[t, T_WG_YW], tools[t, T_WG_YW + 1], tools[t, T_WG_YW + 2])
    m_g = vec3(tools[t, T_WG_MG], tools[t, T_WG_MG + 1], tools[t, T_WG_MG + 2])
    rel = centre - e
    meets = rel.dot(n) + ti.abs(n).dot(half) > -r                                             # ahead of the face
    meets = meets and ti.abs(rel.dot(y)) - ti.abs(y).dot(half) < tools[t, T_WG_HW] + WG_LAYER_R * r  # beside
    meets = meets and rel[2] + half[2] > -(WG_LOW + 2.0) * r                                   # over its floor
    meets = meets and (rel + vec3(0.0, 0.0, WG_LOW * r)).dot(m_g) - ti.abs(m_g).dot(half) < WG_FRONT_R * r
    return meets


@ti.func
def _tool_sample(sdf: ti.template(), tools: ti.template(), t, x, reach):
    """Tool t's SDF sample at world point x (as sample_sdf: distance HUGE where no contact can be) and a bound of how
    far the tool may travel (T_TRAVEL) before the distance could fall below `reach`: the distance to the bounding
    sphere from outside it, else to the SDF grid's box, else the margin over sqrt(3) less two grid spacings; capped
    at CLEAR_MARGIN x the sphere's radius (beyond which T_TRAVEL's lever no longer bounds the motion)."""
    rot = _tool_rotation(tools, t)
    r_bs = tools[t, T_BS + 3]
    rho = (x - _sphere_centre(tools, t, rot)).norm()
    clear = rho - r_bs
    sample = vec4(HUGE, 0.0, 0.0, 0.0)
    if rho <= r_bs * (1.0 + CLEAR_MARGIN):
        origin = vec3(tools[t, T_POS], tools[t, T_POS + 1], tools[t, T_POS + 2])
        p_local = rot.transpose() @ (x - origin)
        h = tools[t, T_H]
        lo = vec3(tools[t, T_ORG], tools[t, T_ORG + 1], tools[t, T_ORG + 2])
        hi = lo + h * (vec3(tools[t, T_NX], tools[t, T_NY], tools[t, T_NZ]) - 1.0)
        clear = ti.max(ti.max(lo - p_local, p_local - hi), 0.0).norm()
        if clear <= 0.0:
            sample = sample_sdf(sdf, tools, t, p_local)
            clear = 0.0  # (on the box's upper faces sample_sdf's half-open test may say outside: test again)
            if sample[0] < HUGE:
                clear = ti.max((sample[0] - reach - 2.0 * h) / SQRT_THREE, 0.0)
        clear = ti.min(clear, CLEAR_MARGIN * r_bs)
    return sample, clear


def _mark_blocks(n_act: ti.i32, block: ti.i32, skip: ti.i32, tools: ti.template(), blk_hot: ti.template(),
                 blk_active: ti.template(), blk_box: ti.template(), blk_list: ti.template(), stat: ti.template(),
                 todo: ti.i32, n_frozen: ti.i32, prm: ti.template()):
    """Which blocks of particles take part in this substep: hot ones (marked by the last step, or by
    mark_awake_blocks after a rebuild: an awake particle in them or a pair they hold with one) and those whose
    bounding box may meet a tool's SDF grid; pair_forces adds the block of a sleeper it asks to wake.
    The others are asleep, hold pairs with sleepers only and are out of every tool's reach, so computing them would
    change nothing (an awake grain's pair with a sleeper of theirs is its own block's work): a sleeping bed costs
    what its blocks cost to skip, whatever its size. skip = 0: all active.
    blk_list[0] = the number of active blocks, blk_list[1:] their indices (in no fixed order: each block's work
    is the same whichever thread does it, and the sums are taken in block order).

    A halted chunk (S_HALT) or one that has done its `todo` substeps lists no block and clears S_RUN: this
    substep and its step() do nothing. Blocks cover the particles after the frozen prefix (n_frozen on)."""
    n_blocks = (n_act - n_frozen + block - 1) // block
    blk_list[0] = 0
    stat[S_RUN] = 1.0
    if stat[S_HALT] != 0.0 or stat[S_DONE] >= todo:
        stat[S_RUN] = 0.0
        n_blocks = 0
    ti.loop_config(serialize=SERIAL_LOOPS)
    for b in range(n_blocks):
        active = 1
        if skip != 0 and blk_hot[b] == 0:
            active = 0
            lo = blk_box[b, 0]
            hi = blk_box[b, 1]
            for t in range(MAX_TOOLS):
                if tools[t, T_ON] > 0.0 and _box_meets_tool_grid(lo, hi, tools, t):
                    active = 1
                if ti.static(WEDGES):  # the grains a wedge moves and the ground ahead it reads, asleep or not
                    if tools[t, T_WG_LIVE] > 0.0 and _box_meets_wedge(lo, hi, tools, t, 0.5 * prm[P_CELL]):
                        active = 1
        blk_active[b] = active
        blk_hot[b] = 0
        if active != 0:
            blk_list[ti.atomic_add(blk_list[0], 1) + 1] = b
            if ti.static(PER_PARTICLE):  # (step() grows it particle by particle)
                blk_box[b, 0] = vec3(HUGE)
                blk_box[b, 1] = vec3(-HUGE)


@ti.kernel
def mark_awake_blocks(n_frozen: ti.i32, n_act: ti.i32, block: ti.i32, kin: KIN, surf_id: I32_2, prm: F64_1,
                      blk_hot: I32_1, blk_box: KIN, rev_off: I32_1, rev_holder: I32_1, tool_gap: F64_1):
    """After the particle order or the lists changed (a rebuild): each block's box anew, and hot the blocks that
    hold an awake particle (or one asked to wake) or a pair with one, as step() would have marked them. The
    others are asleep and hold pairs with sleepers only: computing them would change nothing, so a rebuild does not
    make the next substep walk the whole bed. Blocks cover the particles after the frozen prefix (n_frozen on)."""
    n_blocks = (n_act - n_frozen + block - 1) // block
    sleep_steps = ti.cast(prm[P_SLEEP_STEPS], ti.i32)
    for b in range(n_blocks):
        lo = vec3(HUGE)
        hi = vec3(-HUGE)
        for i in range(n_frozen + b * block, ti.min(n_act, n_frozen + (b + 1) * block)):
            lo = ti.min(lo, kin[i, 0])
            hi = ti.max(hi, kin[i, 0])
        blk_box[b, 0] = lo
        blk_box[b, 1] = hi
        blk_hot[b] = 0
    for i in range(n_frozen, n_act):
        tool_gap[i] = -HUGE  # (another particle may sit in this slot now)
        word = surf_id[i, TOOL_BITS]
        if sleep_steps <= 0 or (word >> CALM_SHIFT) < sleep_steps or (word & WAKE_BIT) != 0:
            _mark_hot(i, n_frozen, block, blk_hot, rev_off, rev_holder)


@ti.kernel
def fill_rev_holder(lo: ti.i32, n_act: ti.i32, nbr_off: I32_1, rev_pos: I32_1, rev_holder: I32_1, scratch: ti.i32):
    """rev_holder[slot] = the particle that holds the pair of each reverse slot (of the holders lo..n_act)."""
    for i in range(lo, n_act):
        for e in range(nbr_off[i], nbr_off[i + 1]):
            q = rev_pos[e]
            if q != scratch:
                rev_holder[q] = i


def _step(n_act: ti.i32, kin: ti.template(), prop: ti.template(), flags: ti.template(), x_ref: ti.template(),
          own: ti.template(), rev_off: ti.template(), pair_out: ti.template(), surf_id: ti.template(),
          surf_h: ti.template(), tools: ti.template(), tool_acc: ti.template(), sdf: ti.template(),
          prm: ti.template(), stat: ti.template(), partial: ti.template(), dt: ti.f64, bulk_damping: ti.f64,
          block: ti.i32, blk_active: ti.template(), blk_list: ti.template(), blk_hot: ti.template(),
          blk_box: ti.template(), nbr_off: ti.template(), nbr_j: ti.template(), rev_holder: ti.template(),
          n_frozen: ti.i32, tool_gap: ti.template(), skip: ti.i32):
    """After pair_forces: sum each particle's forces (own pairs, the pairs listed by its neighbours, gravity,
    ground and walls, tools), advance it (symplectic Euler), then move the tools.

    block: particles per reduction block (reduction_block(n_act)). Returns the largest squared displacement since
    the last neighbour build (HUGE when a particle left the domain, so the caller rebuilds and drops it from the
    lists). Blocks that mark_blocks left inactive are skipped (all asleep, no pair of theirs with an awake grain, no
    tool near: nothing would change); each particle awake after its step marks its block and the blocks holding its
    pairs hot, and the block's bounding box is kept for mark_blocks' tool test.
    """
    running = stat[S_RUN] != 0.0
    if running:
        stat[S_DISP2] = 0.0
    sleep_steps = ti.cast(prm[P_SLEEP_STEPS], ti.i32)
    n_blocks = (n_act - n_frozen + block - 1) // block
    # Taichi's CPU thread pool hands out a parallel loop in tasks of 512 iterations (whatever its block_dim): over
    # the listed blocks alone, a few hundred of them would make one task for one thread. Each block takes
    # STEP_SPREAD iterations (all but the first skip), so a task is 512 / STEP_SPREAD blocks.
    # The GPU layout (PER_PARTICLE) gives each particle of a listed block its own iteration instead.
    spread = ti.static(1 if SERIAL_LOOPS else STEP_SPREAD)
    per_block = spread
    if ti.static(PER_PARTICLE):
        per_block = block
    ti.loop_config(serialize=SERIAL_LOOPS)
    for item in range(blk_list[0] * per_block):
        if ti.static(not PER_PARTICLE):
            if item % spread != 0:
                continue
        kb = item // per_block
        blk = blk_list[kb + 1]
        first = n_frozen + blk * block
        last = ti.min(n_act, first + block)
        if ti.static(PER_PARTICLE):
            first += item % block
            last = ti.min(last, first + 1)
        shoving = _shoving(tools, prm)
        travel = ti.f64(0.0)  # summed over the tools, which a particle's tool_gap is compared with
        for t in range(MAX_TOOLS):
            if tools[t, T_ON] > 0.0:
                travel += tools[t, T_TRAVEL]
        box_lo = vec3(HUGE)
        box_hi = vec3(-HUGE)
        disp2_max = ti.f64(0.0)
        speed2_max = ti.f64(0.0)
        nonfinite = ti.f64(0.0)
        lost_mass = ti.f64(0.0)
        lost_count = ti.f64(0.0)
        tool_sum = ti.Matrix.zero(ti.f64, MAX_TOOLS, 6)
        wedge_sum = ti.Matrix.zero(ti.f64, MAX_TOOLS, WG_SUMS)
        for i in range(first, last):
            if flags[i] == 1:  # (all of 0..n_act are active: a deactivation triggers a rebuild at once)
                word = surf_id[i, TOOL_BITS]
                in_wedge = False
                if ti.static(WEDGES):
                    in_wedge = (_role(own, i) & 3) == WG_IN
                if sleep_steps > 0 and (word >> CALM_SHIFT) >= sleep_steps:
                    # asleep: no forces, no integration; wake on a neighbour's request or a tool within r + skin,
                    # integrated again from the next substep (its pairs are evaluated again from then on)
                    woken = (word & WAKE_BIT) != 0
                    if shoving and not woken:  # a slow tool near: the soil it pushes would meet sleepers
                        woken = _in_a_slow_tools_grid(kin[i, 0], tools, prm)
                    if not woken and (skip == 0 or not travel < tool_gap[i]):  # (the test is due; NaN: test)
                        x_s = kin[i, 0]
                        reach = prop[i][0] + prm[P_SKIN] + prm[P_ADH_D]
                        clear = ti.f64(HUGE)
                        for t in range(MAX_TOOLS):
                            if tools[t, T_ON] > 0.0:
                                sample, gap_t = _tool_sample(sdf, tools, t, x_s, reach)
                                woken = woken or sample[0] < reach
                                clear = ti.min(clear, gap_t)
                        tool_gap[i] = travel + clear
                    if ti.static(WEDGES):  # a wedge's grains move with it, and the layer beyond it takes its reaction
                        if not woken:  # (found here: a block added late has no role)
                            woken = _wedge_role(kin[i, 0], prop[i][0], tools) != WG_FREE
                        if not woken:  # (a sleeper is the ground ahead at rest)
                            _wedge_watch(kin[i, 0], vec3(0.0), prop[i][0], tools, stat)
                    if woken:
                        surf_id[i, TOOL_BITS] = word & TOOL_MASK
                        tool_gap[i] = -HUGE  # (the sleeping particle's gap assumed it would not move)
                        _mark_hot(i, n_frozen, block, blk_hot, rev_off, rev_holder)
                    x_b = kin[i, 0]
                    box_lo = ti.min(box_lo, x_b)
                    box_hi = ti.max(box_hi, x_b)
                elif in_wedge:
                    # a wedge's grain moves with the wedge: along the failure plane, at the speed that keeps it on
                    # the face; what the free grains and, across the plane, the layer put on it go to the wedge's sums
                    # (the tool's push comes from its equilibrium after the substep: _wedge_equilibrium)
                    tw = _role(own, i) >> 2
                    x = kin[i, 0]
                    m = prop[i][1]
                    from_free = own[i, 0]
                    across = own[i, 1]
                    apart = own[i, 2]
                    for q in range(rev_off[i], rev_off[i + 1]):
                        holder = rev_holder[q]
                        role_h = _role(own, holder)
                        if role_h == WG_LAYER + 4 * tw:
                            across += ti.cast(pair_out[q, 0], ti.f64)
                        else:
                            from_free += ti.cast(pair_out[q, 0], ti.f64)
                        if (role_h & 3) == WG_IN:
                            apart += ti.cast(pair_out[q, 1], ti.f64)
                    for c in ti.static(range(3)):
                        wedge_sum[tw, c] += from_free[c]
                        wedge_sum[tw, 3 + c] += across[c]
                    wedge_sum[tw, 6] += m
                    # (and turning with the tool about its edge: a curling bucket's face keeps its distance from
                    # every grain of the wedge, and the grains theirs from one another)
                    e_w = vec3(tools[tw, T_WG_EW], tools[tw, T_WG_EW + 1], tools[tw, T_WG_EW + 2])
                    omega = vec3(tools[tw, T_ANG], tools[tw, T_ANG + 1], tools[tw, T_ANG + 2])
                    v = vec3(tools[tw, T_WG_VW], tools[tw, T_WG_VW + 1], tools[tw, T_WG_VW + 2]) + omega.cross(x - e_w)
                    x += v * dt
                    step_max = v.norm() * dt  # (the overlaps a wedge grain takes in come undone as it travels)
                    apart_len = apart.norm()
                    if apart_len > step_max:
                        apart *= step_max / apart_len
                    x += apart
                    # off the face, which it does not touch (one the edge met under it would rise into the tool), at
                    # most as fast as the wedge moves (no jump into its neighbours)
                    n_w = vec3(tools[tw, T_WG_NW], tools[tw, T_WG_NW + 1], tools[tw, T_WG_NW + 2])
                    s_f = (x - e_w).dot(n_w)
                    if s_f < prop[i][0]:
                        x += ti.min(prop[i][0] - s_f, v.norm() * dt) * n_w
                    ti.atomic_min(stat[S_WG_GAP + tw], ti.max(s_f - prop[i][0], -prop[i][0]) / prop[i][0])
                    kin[i, 0] = x
                    kin[i, 1] = v
                    kin[i, 2] = vec3(0.0)
                    box_lo = ti.min(box_lo, x)
                    box_hi = ti.max(box_hi, x)
                    ref = x_ref[i]
                    dx = x - vec3(ref[0], ref[1], ref[2])
                    disp2_max = ti.max(disp2_max, dx.dot(dx))
                    speed2_max = ti.max(speed2_max, v.dot(v))
                    tool_gap[i] = -HUGE
                    if sleep_steps > 0:
                        surf_id[i, TOOL_BITS] = surf_id[i, TOOL_BITS] & TOOL_MASK  # (awake: calm count 0)
                        _mark_hot(i, n_frozen, block, blk_hot, rev_off, rev_holder)
                    else:
                        blk_hot[blk] = 1
                else:
                    x = kin[i, 0]
                    v = kin[i, 1]
                    w = kin[i, 2]
                    p = prop[i]
                    r = p[0]
                    m = p[1]
                    q2 = p[3] * p[3]  # sqrt(m): the effective mass against ground, walls and tools is m
                    force = own[i, 0]
                    torque = own[i, 1]
                    for q in range(rev_off[i], rev_off[i + 1]):  # what the pairs held by others put on i
                        force += ti.cast(pair_out[q, 0], ti.f64)
                        torque += ti.cast(pair_out[q, 1], ti.f64)
                    force += m * vec3(prm[P_G], prm[P_G + 1], prm[P_G + 2])
                    if ti.static(WEDGES):
                        role = _role(own, i)
                        if (role & 3) == WG_LAYER:  # the wedge's failure plane: its reaction, by mass
                            tw = role >> 2
                            push = vec3(tools[tw, T_WG_ACC], tools[tw, T_WG_ACC + 1], tools[tw, T_WG_ACC + 2])
                            v_w = vec3(tools[tw, T_WG_VW], tools[tw, T_WG_VW + 1], tools[tw, T_WG_VW + 2])
                            # (the soil beyond the plane moves no faster than the wedge that drives it: a grain that
                            # does is left to its contacts, or a layer of fine grains, light and at the verge of
                            # sliding, runs away along the plane: the blade diverged at 20 grains across)
                            if v.dot(push) < v_w.norm() * push.norm():
                                force += m * push
                            wedge_sum[tw, 7] += m
                        if (role & 3) != WG_IN:
                            _wedge_watch(x, v, r, tools, stat)
                    buried = False
                    # ground, pit faces and domain walls; each contact keeps its spring in a face-keyed slot
                    ids = ti.Vector([surf_id[i, 0], surf_id[i, 1], surf_id[i, 2], surf_id[i, 3]])
                    ref = x_ref[i]
                    pit = -1
                    near = ids.max() >= 0
                    if not near and ref[3] < r + prm[P_SKIN]:  # most particles are far from every face
                        pit = _pit_of(x, prm)
                        near = _clearance(x, pit, prm) < r
                    elif near:
                        pit = _pit_of(x, prm)
                    if near:
                        touched = ti.Vector([0, 0, 0, 0])
                        n_faces = 5
                        if pit >= 0:
                            n_faces += FACES_PER_PIT
                        for q in range(n_faces):  # domain walls, ground, then the faces of this particle's pit
                            fid = q if q < 5 else q + FACES_PER_PIT * pit
                            overlap = ti.f64(-1.0)
                            n = vec3(0.0)
                            out = False
                            if _face_plane_distance(fid, pit, x, prm) < r:  # cheap test first: most faces are far
                                overlap, n, out = _face(fid, pit, x, r, prm)
                            if out:
                                buried = True
                            if overlap > 0.0 and not out:
                                slot = _find_slot(ids, fid)
                                hist = vec6f(0.0)
                                if slot >= 0:
                                    hist = surf_h[i, slot]
                                lever = -r * n
                                sqrt_k = prm[P_SQRT_KWALL]
                                # domain walls are symmetry planes (the soil beyond them would shear with it):
                                # smooth, so a narrow slice or a bed cut by the domain is not held up by them;
                                # the ground and pit faces are rough
                                mu_face = prm[P_MU_WALL]
                                mu_r_face = prm[P_MU_R]
                                if fid < 4:
                                    mu_face = 0.0
                                    mu_r_face = 0.0
                                f_c, f_t, m_r, h_new = contact_law(n, overlap, v + w.cross(lever), w, q2 * sqrt_k,
                                                                   ti.f64(SQRT_TWO_FIFTHS) * q2 * r * sqrt_k, r, hist,
                                                                   prm[P_K_WALL], mu_face, mu_r_face, prm, dt)
                                force += f_c
                                torque += lever.cross(f_t) + m_r
                                if slot >= 0:
                                    ids[slot] = fid
                                    touched[slot] = 1
                                    surf_h[i, slot] = h_new
                        for s in ti.static(range(WALL_SLOTS)):
                            if touched[s] == 0 and ids[s] >= 0:
                                surf_h[i, s] = vec6f(0.0)
                                ids[s] = -1
                            surf_id[i, s] = ids[s]
                    # kinematic tools: SDF in the link frame, the reaction summed per tool
                    # (tool_gap: no tool can reach a particle that stays within skin / 2 of x_ref, the lists' bound,
                    # before the tools have travelled that far: no sample, as if it were far)
                    bits_in = surf_id[i, TOOL_BITS]
                    tool_bits = bits_in
                    due = skip == 0 or not travel < tool_gap[i]
                    clear = ti.f64(HUGE)
                    for t in range(MAX_TOOLS):
                        if tools[t, T_ON] > 0.0:
                            hit = False
                            sample = vec4(HUGE, 0.0, 0.0, 0.0)
                            if due:
                                sample, gap_t = _tool_sample(sdf, tools, t, x, r + prm[P_ADH_D])
                                clear = ti.min(clear, gap_t)
                            # contact (gap < 0), or within the adhesion band beyond it (P_ADH_D: 0 without adhesion)
                            if sample[0] < r + prm[P_ADH_D]:
                                rot = _tool_rotation(tools, t)
                                origin = vec3(tools[t, T_POS], tools[t, T_POS + 1], tools[t, T_POS + 2])
                                g_world = rot @ vec3(sample[1], sample[2], sample[3])
                                g_norm = g_world.norm()
                                if g_norm > 1e-12:
                                    n = g_world / g_norm
                                    lever = -r * n
                                    x_c = x + lever
                                    f_c = vec3(0.0)
                                    m_r_tool = vec3(0.0)
                                    if sample[0] < r:
                                        hit = True
                                        w_tool = vec3(tools[t, T_ANG], tools[t, T_ANG + 1], tools[t, T_ANG + 2])
                                        v_tool = vec3(tools[t, T_VEL], tools[t, T_VEL + 1], tools[t, T_VEL + 2]) + \
                                            w_tool.cross(x_c - origin)
                                        # adhesion: the tool holds the particle by attraction (below) and resists
                                        # its sliding by P_ADH_F more than friction does (soil.bulk_to_micro)
                                        sqrt_k = prm[P_SQRT_KTOOL]
                                        f_c, f_t, m_r, h_new = contact_law(n, r - sample[0], v + w.cross(lever) - v_tool,
                                                                           w - w_tool, q2 * sqrt_k,
                                                                           ti.f64(SQRT_TWO_FIFTHS) * q2 * r * sqrt_k, r,
                                                                           surf_h[i, WALL_SLOTS + t], prm[P_K_TOOL],
                                                                           prm[P_MU_TOOL], prm[P_MU_R], prm, dt,
                                                                           prm[P_ADH_F])
                                        torque += lever.cross(f_t) + m_r
                                        m_r_tool = m_r
                                        surf_h[i, WALL_SLOTS + t] = h_new
                                        tool_bits |= 1 << t
                                    if prm[P_ADH_F] > 0.0:
                                        f_c -= band_attraction(sample[0] - r, prm[P_ADH_F], prm[P_ADH_D]) * n
                                    force += f_c
                                    arm = x_c - origin
                                    on_tool = -f_c
                                    moment = arm.cross(on_tool) - m_r_tool  # the rolling resistance's reaction too
                                    for c in ti.static(range(3)):
                                        tool_sum[t, c] += on_tool[c]
                                        tool_sum[t, 3 + c] += moment[c]
                            if not hit and ((tool_bits >> t) & 1) == 1:
                                surf_h[i, WALL_SLOTS + t] = vec6f(0.0)
                                tool_bits &= ~(1 << t)
                    if due:
                        tool_gap[i] = travel + clear - (0.5 * prm[P_SKIN] + (x - vec3(ref[0], ref[1], ref[2])).norm())
                    if x[2] > prm[P_DMAX + 2]:
                        buried = True
                    if buried:
                        # left the domain (or tunnelled into the ground): book the mass, drop the particle
                        flags[i] = 0
                        kin[i, 1] = vec3(0.0)
                        kin[i, 2] = vec3(0.0)
                        lost_mass += m
                        lost_count += 1.0
                        disp2_max = HUGE
                    else:
                        damp = 1.0 / (1.0 + bulk_damping * dt)
                        v = (v + force * (p[2] * dt)) * damp
                        w = (w + torque * (2.5 * p[2] / (r * r) * dt)) * damp  # I = 2/5 m r^2
                        x += v * dt
                        kin[i, 0] = x
                        kin[i, 1] = v
                        kin[i, 2] = w
                        box_lo = ti.min(box_lo, x)
                        box_hi = ti.max(box_hi, x)
                        dx = x - vec3(ref[0], ref[1], ref[2])
                        speed2 = v.dot(v)
                        if not (speed2 < HUGE and dx.dot(dx) < HUGE):  # NaN fails every comparison
                            nonfinite += 1.0
                        else:
                            disp2_max = ti.max(disp2_max, dx.dot(dx))
                            speed2_max = ti.max(speed2_max, speed2)
                        if sleep_steps > 0:
                            calm = 0
                            if (tool_bits & TOOL_MASK) == 0 and speed2 < prm[P_SLEEP_V2] and \
                                    w.dot(w) * r * r < prm[P_SLEEP_V2]:
                                calm = ti.min((tool_bits >> CALM_SHIFT) + 1, CALM_MAX)
                                if calm >= sleep_steps and _near_a_slow_tool(
                                        x, tools, SLOW_FACTOR * ti.sqrt(WAKE_FACTOR2 * prm[P_SLEEP_V2]), 0.0):
                                    calm = sleep_steps - 1  # a slow tool's load or ground: it would press sleepers
                                if calm >= sleep_steps:  # falls asleep at rest
                                    kin[i, 1] = vec3(0.0)
                                    kin[i, 2] = vec3(0.0)
                                    tool_gap[i] = -HUGE
                            tool_bits = (tool_bits & TOOL_MASK) | (calm << CALM_SHIFT)
                            if calm < sleep_steps:
                                _mark_hot(i, n_frozen, block, blk_hot, rev_off, rev_holder)
                        else:
                            blk_hot[blk] = 1
                    if tool_bits != bits_in:
                        surf_id[i, TOOL_BITS] = tool_bits
            else:  # (inactive: left the domain; a rebuild follows)
                blk_hot[blk] = 1
        if ti.static(PER_PARTICLE):
            # atomics in thread order (a GPU's threads are many and a serial sum over the blocks would cost it more
            # than the substep's work), of terms on a grid of WRENCH_QUANTUM / MASS_QUANTUM so that the sums are
            # exact whatever the order; the box was reset by mark_blocks, and only the rare non-zero terms are added
            if box_lo[0] < HUGE:
                for c in ti.static(range(3)):
                    ti.atomic_min(blk_box[blk, 0][c], box_lo[c])
                    ti.atomic_max(blk_box[blk, 1][c], box_hi[c])
            if disp2_max > stat[S_DISP2]:
                ti.atomic_max(stat[S_DISP2], disp2_max)
            if speed2_max > stat[S_SPEED2]:
                ti.atomic_max(stat[S_SPEED2], speed2_max)
            for t, c in ti.static(ti.ndrange(MAX_TOOLS, 6)):
                if tool_sum[t, c] != 0.0:
                    ti.atomic_add(tool_acc[t, c], _on_grid(tool_sum[t, c], WRENCH_QUANTUM))
            for t, c in ti.static(ti.ndrange(MAX_TOOLS if WEDGES else 0, WG_SUMS)):
                if wedge_sum[t, c] != 0.0:
                    quantum = WRENCH_QUANTUM if c < 6 else MASS_QUANTUM
                    ti.atomic_add(stat[S_WG_SUM + WG_SUMS * t + c], _on_grid(wedge_sum[t, c], quantum))
            if lost_count != 0.0:
                ti.atomic_add(stat[S_LOST_MASS], _on_grid(lost_mass, MASS_QUANTUM))
                ti.atomic_add(stat[S_LOST_COUNT], lost_count)
            if nonfinite != 0.0:
                ti.atomic_add(stat[S_NONFINITE], nonfinite)
        else:
            blk_box[blk, 0] = box_lo
            blk_box[blk, 1] = box_hi
            ti.atomic_max(stat[S_DISP2], disp2_max)
            ti.atomic_max(stat[S_SPEED2], speed2_max)
            for t, c in ti.static(ti.ndrange(MAX_TOOLS, 6)):
                partial[blk, 6 * t + c] = tool_sum[t, c]
            for t, c in ti.static(ti.ndrange(MAX_TOOLS if WEDGES else 0, WG_SUMS)):
                partial[blk, PART_WG + WG_SUMS * t + c] = wedge_sum[t, c]
            partial[blk, PART_LOST_MASS] = lost_mass
            partial[blk, PART_LOST_COUNT] = lost_count
            partial[blk, PART_NONFINITE] = nonfinite
    # sums in block order (not atomics in thread order): the tool wrench fed back to the machine is
    # bit-for-bit reproducible. One serial task, so the sums stay in registers.
    if not running or ti.static(PER_PARTICLE):
        n_blocks = 0
    ti.loop_config(serialize=True)
    for _ in range(1):
        stat[S_ACTIVE] = ti.max(stat[S_ACTIVE], ti.cast(blk_list[0] * block, ti.f64))
        acc = ti.Vector.zero(ti.f64, PART_BASE)
        for blk in range(n_blocks):
            if blk_active[blk] != 0:  # (a skipped block's row is stale; it would have added zeros)
                for c in ti.static(range(PART_BASE)):
                    acc[c] += partial[blk, c]
        for t, c in ti.static(ti.ndrange(MAX_TOOLS, 6)):
            tool_acc[t, c] += acc[6 * t + c]
        stat[S_LOST_MASS] += acc[PART_LOST_MASS]
        stat[S_LOST_COUNT] += acc[PART_LOST_COUNT]
        stat[S_NONFINITE] += acc[PART_NONFINITE]
        if ti.static(WEDGES) and running:
            for t in ti.static(range(MAX_TOOLS)):
                if tools[t, T_WG_ON] > 0.0:
                    sums = ti.Vector.zero(ti.f64, WG_SUMS)
                    if ti.static(PER_PARTICLE):
                        for c in ti.static(range(WG_SUMS)):
                            sums[c] = stat[S_WG_SUM + WG_SUMS * t + c]
                            stat[S_WG_SUM + WG_SUMS * t + c] = 0.0
                    else:
                        for blk in range(n_blocks):
                            if blk_active[blk] != 0:
                                for c in ti.static(range(WG_SUMS)):
                                    sums[c] += partial[blk, PART_WG + WG_SUMS * t + c]
                    _wedge_equilibrium(t, sums, tools, tool_acc, prm, PER_PARTICLE)
                    # the front surface (_wedge_front); kept while no grain at rest shows it
                    top = stat[S_WG_TOP + t]
                    if tools[t, T_WG_LIVE] == 0.0:
                        tools[t, T_WG_TOP] = -HUGE
                    elif top > -UNKNOWN_TOP:
                        # the ground ahead falls at most as fast as the wedge moves (a 45 degree slope): grains
                        # the wedge stirs up leave the band at rest for a while, the ground does not drop
                        fall = vec3(tools[t, T_WG_VW], tools[t, T_WG_VW + 1], tools[t, T_WG_VW + 2]).norm() * dt
                        last = tools[t, T_WG_TOP]
                        if last > -UNKNOWN_TOP:
                            top = ti.max(top, last - fall)
                        tools[t, T_WG_TOP] = top
                    stat[S_WG_TOP + t] = -HUGE
                    tools[t, T_WG_GAP] = stat[S_WG_GAP + t]
                    stat[S_WG_GAP + t] = NO_GAP
    # tools move kinematically: p += v dt, R <- Rot(w dt) R (serial: a parallel loop over four rows would cost a
    # thread-pool round trip per substep, which small soils feel)
    n_tools = MAX_TOOLS
    if not running:
        n_tools = 0
    ti.loop_config(serialize=True)
    for t in range(n_tools):
        if tools[t, T_ON] > 0.0:
            vel = vec3(tools[t, T_VEL], tools[t, T_VEL + 1], tools[t, T_VEL + 2])
            ang = vec3(tools[t, T_ANG], tools[t, T_ANG + 1], tools[t, T_ANG + 2])
            for c in ti.static(range(3)):
                tools[t, T_POS + c] += vel[c] * dt
            rot_old = _tool_rotation(tools, t)
            # a point within (1 + 2 CLEAR_MARGIN) r_bs of the sphere's centre moves in the tool's frame by at most the
            # translation plus the rotation angle times its lever about the link origin
            lever = (rot_old @ vec3(tools[t, T_BS], tools[t, T_BS + 1], tools[t, T_BS + 2])).norm() + \
                (1.0 + 2.0 * CLEAR_MARGIN) * tools[t, T_BS + 3]
            tools[t, T_TRAVEL] += (vel.norm() + ang.norm() * lever) * dt
            rot = _rotation_from_vector(ang * dt) @ rot_old
            for a in ti.static(range(3)):
                for b in ti.static(range(3)):
                    tools[t, T_ROT + 3 * a + b] = rot[a, b]
            if ti.static(WEDGES):
                _wedge_refresh(tools, t)
    if running:
        stat[S_DONE] += 1.0
        if stat[S_DISP2] > 0.25 * prm[P_SKIN] * prm[P_SKIN]:
            stat[S_HALT] = 1.0


def _substep(n_act: ti.i32, block: ti.i32, skip: ti.i32, todo: ti.i32, dt: ti.f64, bulk_damping: ti.f64, kin: KIN,
             prop: PROP, flags: I32_1, x_ref: REF, own: KIN, rev_off: I32_1, pair_out: PAIR_OUT, surf_id: I32_2,
             surf_h: HIST, tools: F64_2, tool_acc: F64_2, sdf: SDF, prm: F64_1, stat: F64_1, partial: F64_2,
             blk_active: I32_1, blk_list: I32_1, blk_hot: I32_1, blk_box: KIN, nbr_off: I32_1, nbr_j: I32_1,
             nbr_h: HIST_1, rev_pos: I32_1, rev_holder: I32_1, n_frozen: ti.i32, tool_gap: F64_1):
    """One substep, one launch: the blocks that take part, their pair forces, then everything else and the
    integration (the loops run one after the other; a launch costs ~20 us of argument setup on the CPU even in a
    compute graph, more than an idle substep's work)."""
    _mark_blocks(n_act, block, skip, tools, blk_hot, blk_active, blk_box, blk_list, stat, todo, n_frozen, prm)
    _pair_forces(n_act, kin, prop, nbr_off, nbr_j, nbr_h, rev_pos, pair_out, own, surf_id, prm, dt, blk_list,
                 blk_active, block, n_frozen, stat, tools)
    _step(n_act, kin, prop, flags, x_ref, own, rev_off, pair_out, surf_id, surf_h, tools, tool_acc, sdf, prm, stat,
          partial, dt, bulk_damping, block, blk_active, blk_list, blk_hot, blk_box, nbr_off, nbr_j, rev_holder,
          n_frozen, tool_gap, skip)


def _variant(fn, decorator, **names):
    """fn under `decorator` (ti.func or ti.kernel) with some of this module's names replaced: Taichi reads the
    module's globals when it compiles, so one source gives both the threaded and the serial loops."""
    scope = dict(fn.__globals__)
    scope.update(names)
    copy = types.FunctionType(fn.__code__, scope, fn.__name__, fn.__defaults__, fn.__closure__)
    copy.__annotations__ = fn.__annotations__
    return decorator(copy)


def _substep_kernel(serial: bool, per_particle: bool = False, wedges: bool = False):
    flags = dict(SERIAL_LOOPS=serial, PER_PARTICLE=per_particle, WEDGES=wedges)
    funcs = {name: _variant(globals()[name], ti.func, **flags) for name in ("_mark_blocks", "_pair_forces", "_step")}
    return _variant(_substep, ti.kernel, **flags, **funcs)


substep = _substep_kernel(False)
substep_serial = _substep_kernel(True)  # every particle loop in the calling thread (CPU)
# a GPU's layout: one iteration per particle of the listed blocks in step() too, its sums by atomics of terms on a
# grid (the same bits in any order, not the block sums' bits)
substep_per_particle = _substep_kernel(False, per_particle=True)
# the same with the soil wedges (a tool has a cutting edge)
substep_wedges = _substep_kernel(False, wedges=True)
substep_serial_wedges = _substep_kernel(True, wedges=True)
substep_per_particle_wedges = _substep_kernel(False, per_particle=True, wedges=True)


# ----------------------------------------------------------------------------------------------- neighbour build
@ti.func
def _spread_bits(v):
    x = ti.cast(v, ti.i64) & ti.i64(0x1fffff)
    x = (x | (x << 32)) & ti.i64(0x1f00000000ffff)
    x = (x | (x << 16)) & ti.i64(0x1f0000ff0000ff)
    x = (x | (x << 8)) & ti.i64(0x100f00f00f00f00f)
    x = (x | (x << 4)) & ti.i64(0x10c30c30c30c30c3)
    x = (x | (x << 2)) & ti.i64(0x1249249249249249)
    return x


@ti.func
def _morton(c):
    return _spread_bits(c[0]) | (_spread_bits(c[1]) << 1) | (_spread_bits(c[2]) << 2)


# Half stencil: the own cell (pairs with a higher index) and the 13 neighbour cells "ahead" of it; every pair
# of particles in adjacent cells is found exactly once, from the cell that sees the other ahead.
HALF_STENCIL = tuple(d for d in ((dx, dy, dz) for dz in (-1, 0, 1) for dy in (-1, 0, 1) for dx in (-1, 0, 1))
                     if (d[2], d[1], d[0]) >= (0, 0, 0))


@ti.func
def _neighbor_bits(c):
    """Interleaved bits of the cell coordinates c - 1, c, c + 1 per axis: the Morton code of each of the 27
    neighbour cells is then three ORs (9 bit spreads per particle instead of 81)."""
    sx = ti.Vector([_spread_bits(c[0] - 1), _spread_bits(c[0]), _spread_bits(c[0] + 1)])
    sy = ti.Vector([_spread_bits(c[1] - 1), _spread_bits(c[1]), _spread_bits(c[1] + 1)]) << 1
    sz = ti.Vector([_spread_bits(c[2] - 1), _spread_bits(c[2]), _spread_bits(c[2] + 1)]) << 2
    return sx, sy, sz


@ti.func
def _cell_of(x, prm: ti.template()):
    """Integer cell of a position, offset by one so that every neighbour cell index stays >= 0."""
    c = ti.Vector([1, 1, 1])
    for a in ti.static(range(3)):
        u = (x[a] - prm[P_DMIN + a]) / prm[P_CELL]
        if u > -1.0 and u < CELL_LIMIT - 1:  # also false for NaN: such particles go to cell 1
            c[a] = ti.cast(ti.floor(u), ti.i32) + 1
    return c


# The particle arrays hold a frozen prefix (DemSoil: particles asleep and far from every tool and from everything
# awake), then the live particles, then the inactive ones. The hash table has two parts: buckets 0..T-1 (T =
# mask + 1) for the frozen prefix's cells, T..T+L-1 (L = live_mask + 1 <= T, sized for the live particles) for the
# live particles', T+L for the inactive. A rebuild of the live part (lo = n_frozen) bins, sorts, gathers and lists
# only particles lo..n and leaves the prefix, its lists and its part of the table as they are: frozen particles
# neither move nor change their springs.
@ti.kernel
def bin_particles(lo: ti.i32, n: ti.i32, kin: KIN, flags: I32_1, frozen: I32_1, use_frozen: ti.i32, cell: I64_1,
                  bucket: I32_1, counts: I32_1, prm: F64_1, mask: ti.i32, live_mask: ti.i32):
    """Hash each active particle lo..n's cell (Morton code, masked: spatially coherent buckets) into the frozen or
    the live half of the table (use_frozen: by frozen[i]; else all live) and count per bucket.

    Inactive particles go to the extra bucket T + L, i.e. after every active one.
    """
    half = mask + 1
    k0 = 0
    if lo > 0:
        k0 = half
    for b in range(k0, half + live_mask + 2):
        counts[b] = 0
    for i in range(lo, n):
        key = half + live_mask + 1
        code = ti.i64(-1)
        if flags[i] == 1:
            code = _morton(_cell_of(kin[i, 0], prm))
            if use_frozen != 0 and frozen[i] != 0:
                key = ti.cast(code & ti.cast(mask, ti.i64), ti.i32)
            else:
                key = half + ti.cast(code & ti.cast(live_mask, ti.i64), ti.i32)
        cell[i] = code
        bucket[i] = key
        ti.atomic_add(counts[key], 1)


@ti.kernel
def sort_by_bucket(lo: ti.i32, n: ti.i32, bucket: I32_1, counts: I32_1, starts: I32_1, order: I32_1,
                   mask: ti.i32, live_mask: ti.i32, sizes: I32_1):
    """Counting sort of particles lo..n (serial, so the order inside a bucket is the old order: deterministic).

    starts[b]..starts[b+1] are the sorted slots of bucket b; order[sorted slot] = old index. With lo > 0 only the
    live part of the table is sorted (the frozen prefix keeps its slots). sizes[SZ_ACTIVE] = the number of active
    particles (an array, not a return value, so that a compute graph can pass it on to count_neighbors).
    """
    half = mask + 1
    k0 = 0
    if lo > 0:
        k0 = half
    ti.loop_config(serialize=True)
    for _ in range(1):
        starts[k0] = lo
        for b in range(k0, half + live_mask + 2):
            starts[b + 1] = starts[b] + counts[b]
            counts[b] = starts[b]
    ti.loop_config(serialize=True)
    for i in range(lo, n):
        key = bucket[i]
        order[counts[key]] = i
        counts[key] += 1
    sizes[SZ_ACTIVE] = starts[half + live_mask + 1]


# A GPU runs a serial loop on one thread: the rebuilds' serial scans and scatters cost it 10-40 ms each at 16,000
# particles. These variants give the same arrays (the same bits) from parallel loops: sums by chunks, and a scatter
# by atomics whose order within each segment is then sorted back into the serial loop's.
SCAN_CHUNK = 256


@ti.func
def _scan(a: ti.template(), lo, n, base):
    """a[lo..n) <- base + its inclusive prefix sums: each chunk (about sqrt(n) entries, at least SCAN_CHUNK) summed
    by a thread, the chunks' totals carried serially, then each chunk's offset added."""
    size = ti.max(SCAN_CHUNK, ti.cast(ti.sqrt(ti.cast(ti.max(n - lo, 0), ti.f64)), ti.i32) + 1)
    n_chunks = (n - lo + size - 1) // size
    for c in range(n_chunks):
        s = 0
        for k in range(lo + c * size, ti.min(n, lo + (c + 1) * size)):
            s += a[k]
            a[k] = s
    ti.loop_config(serialize=True)
    for _ in range(1):
        carry = base
        for c in range(n_chunks):
            last = ti.min(n, lo + (c + 1) * size) - 1
            a[last] += carry
            carry = a[last]
    for c in range(n_chunks):
        off = base
        if c > 0:
            off = a[lo + c * size - 1]
        for k in range(lo + c * size, ti.min(n, lo + (c + 1) * size) - 1):
            a[k] += off


@ti.func
def _sort_segment(keys: ti.template(), first, last):
    """keys[first..last) in ascending order (insertion sort: a segment holds a few entries)."""
    for k in range(first + 1, last):
        v = keys[k]
        m = k
        while m > first and keys[m - 1] > v:
            keys[m] = keys[m - 1]
            m -= 1
        keys[m] = v


@ti.kernel
def sort_by_bucket_parallel(lo: ti.i32, n: ti.i32, bucket: I32_1, counts: I32_1, starts: I32_1, order: I32_1,
                            mask: ti.i32, live_mask: ti.i32, sizes: I32_1):
    """sort_by_bucket from parallel loops (a GPU's): the same starts and order."""
    half = mask + 1
    k0 = 0
    if lo > 0:
        k0 = half
    end = half + live_mask + 2
    for b in range(k0, end):
        starts[b + 1] = counts[b]
    _scan(starts, k0 + 1, end + 1, lo)
    starts[k0] = lo
    for b in range(k0, end):
        counts[b] = starts[b]
    gone = half + live_mask + 1  # the inactive particles' bucket: it may hold many, so not sorted by a thread
    for i in range(lo, n):
        if bucket[i] != gone:
            order[ti.atomic_add(counts[bucket[i]], 1)] = i
    for b in range(k0, gone):
        _sort_segment(order, starts[b], starts[b + 1])
    # the inactive ones in index order, from a scan of a 0/1 mark (bucket is free once the scatter read it)
    for i in range(lo, n):
        bucket[i] = ti.cast(bucket[i] == gone, ti.i32)
    _scan(bucket, lo, n, 0)
    for i in range(lo, n):
        before = 0
        if i > lo:
            before = bucket[i - 1]
        if bucket[i] != before:
            order[starts[gone] + before] = i
    counts[gone] = starts[gone]  # (where the serial scatter leaves its cursor: the bucket's end)
    if n > lo:
        counts[gone] += bucket[n - 1]
    sizes[SZ_ACTIVE] = starts[half + live_mask + 1]


@ti.kernel
def gather_particles(lo: ti.i32, n: ti.i32, order: I32_1, kin: KIN, kin_out: KIN, prop: PROP, prop_out: PROP,
                     flags: I32_1, flags_out: I32_1, surf_id: I32_2, surf_id_out: I32_2, surf_h: HIST,
                     surf_h_out: HIST, cell: I64_1, cell_out: I64_1):
    """Reorder the per-particle state of slots lo..n into cell order (memory locality for the pair loop)."""
    for k in range(lo, n):
        o = order[k]
        for c in ti.static(range(3)):
            kin_out[k, c] = kin[o, c]
        prop_out[k] = prop[o]
        flags_out[k] = flags[o]
        cell_out[k] = cell[o]
        for s in ti.static(range(SURF_ID_WIDTH)):
            surf_id_out[k, s] = surf_id[o, s]
        for s in ti.static(range(SURF_SLOTS)):
            surf_h_out[k, s] = surf_h[o, s]


@ti.func
def _freeze_radius(tools: ti.template(), t):
    """The sphere about tool t beyond which its soil may freeze: its bounding sphere's, and with a cutting edge
    WG_FREEZE_REACH of those radii more, for the wedge and the ground ahead it reads (a wedge that reaches farther
    wakes the frozen grains it meets, and they thaw)."""
    r_bs = tools[t, T_BS + 3]
    if tools[t, T_WG_ON] > 0.0:
        r_bs *= 1.0 + WG_FREEZE_REACH
    return r_bs


@ti.kernel
def mark_frozen(n: ti.i32, n_act: ti.i32, kin: KIN, flags: I32_1, surf_id: I32_2, prm: F64_1, tools: F64_2,
                margin: ti.f64, frozen: I32_1) -> ti.i32:
    """Before a full rebuild: frozen[i] = 1 for each particle asleep (no wake request) and farther than `margin`
    beyond every tool's bounding sphere. Returns how many (thaw_layer then keeps layers around the others)."""
    sleep_steps = ti.cast(prm[P_SLEEP_STEPS], ti.i32)
    for i in range(n):
        f = 0
        word = surf_id[i, TOOL_BITS]
        if i < n_act and flags[i] == 1 and sleep_steps > 0 and (word >> CALM_SHIFT) >= sleep_steps and \
                (word & WAKE_BIT) == 0:
            f = 1
            x = kin[i, 0]
            for t in range(MAX_TOOLS):
                if tools[t, T_ON] > 0.0:
                    reach = _freeze_radius(tools, t) + margin
                    d = x - _sphere_centre(tools, t, _tool_rotation(tools, t))
                    if d.dot(d) <= reach * reach:
                        f = 0
        frozen[i] = f
    count = 0
    for i in range(n):
        count += frozen[i]
    return count


@ti.kernel
def thaw_layer(n_act: ti.i32, frozen: I32_1, frozen_out: I32_1, nbr_off: I32_1, nbr_j: I32_1, rev_off: I32_1,
               rev_holder: I32_1) -> ti.i32:
    """One layer of particles around the unfrozen ones unfrozen too (from frozen into frozen_out, so the result does
    not depend on the threads' order). Returns how many stay frozen."""
    for i in range(n_act):
        f = frozen[i]
        if f != 0:
            for e in range(nbr_off[i], nbr_off[i + 1]):
                if frozen[nbr_j[e]] == 0:
                    f = 0
            for q in range(rev_off[i], rev_off[i + 1]):
                if frozen[rev_holder[q]] == 0:
                    f = 0
        frozen_out[i] = f
    for i in range(n_act):  # (a frozen particle's reverse list lacks the live holders: they thaw it from their side)
        if frozen[i] == 0:
            for e in range(nbr_off[i], nbr_off[i + 1]):
                frozen_out[nbr_j[e]] = 0
    count = 0
    for i in range(n_act):
        count += frozen_out[i]
    return count


@ti.kernel
def frozen_clearance(n: ti.i32, kin: KIN, frozen: I32_1, tools: F64_2, out: F64_1):
    """out[t] = how far the nearest frozen particle's centre lies beyond tool t's bounding sphere (HUGE for a tool
    that is off or when nothing is frozen): how far the tool may move before it could reach one."""
    for t in range(MAX_TOOLS):
        out[t] = HUGE
    for i in range(n):
        if frozen[i] != 0:
            x = kin[i, 0]
            for t in range(MAX_TOOLS):
                if tools[t, T_ON] > 0.0:
                    centre = _sphere_centre(tools, t, _tool_rotation(tools, t))
                    ti.atomic_min(out[t], (x - centre).norm() - _freeze_radius(tools, t))


@ti.kernel
def identity_prefix(n_frozen: ti.i32, order: I32_1, order_inv: I32_1):
    """The frozen prefix keeps its slots in the rebuilds of the live part: old index = new index there."""
    for k in range(n_frozen):
        order[k] = k
        order_inv[k] = k


@ti.kernel
def copy_entries(n_frozen: ti.i32, entries: ti.i32, nbr_off: I32_1, nbr_j: I32_1, nbr_h: HIST_1, off_out: I32_1,
                 j_out: I32_1, h_out: HIST_1):
    """The frozen prefix's lists (offsets 0..n_frozen, entries 0..entries) into the other list buffers."""
    for k in range(n_frozen + 1):
        off_out[k] = nbr_off[k]
    for e in range(entries):
        j_out[e] = nbr_j[e]
        h_out[e] = nbr_h[e]


@ti.kernel
def copy_i32(count: ti.i32, src: I32_1, dst: I32_1):
    for k in range(count):
        dst[k] = src[k]


FULL_STENCIL = tuple((dx, dy, dz) for dz in (-1, 0, 1) for dy in (-1, 0, 1) for dx in (-1, 0, 1))


@ti.kernel
def mark_moved_cells(lo: ti.i32, n: ti.i32, n_listed: ti.i32, kin: KIN, flags: I32_1, x_ref: REF, order: I32_1,
                     order_inv: I32_1, moved: I32_1, prm: F64_1, mask: ti.i32, live_mask: ti.i32, was_frozen: ti.i32,
                     freeze: I32_1, use_frozen: ti.i32):
    """Between bin/sort and the gather of lo..n, for a rebuild that keeps the lists of still neighbourhoods:
    moved[half + b] = 1 for each live-half bucket b that holds a cell a listed particle left, entered or moved in
    since the last build (or left the domain from), or where a particle joins or leaves the frozen prefix (a
    repartition: it was frozen when its index was below was_frozen, it is when use_frozen and freeze say so);
    order_inv[old index] = new index."""
    half = mask + 1
    for b in range(half, half + live_mask + 2):
        moved[b] = 0
    for k in range(lo, n):
        order_inv[order[k]] = k
    for o in range(lo, n):
        ref = x_ref[o]
        x = kin[o, 0]
        if o >= n_listed:
            if flags[o] == 1:
                moved[_live_bucket(x, prm, half, live_mask)] = 1
        elif flags[o] == 0 or x[0] != ref[0] or x[1] != ref[1] or x[2] != ref[2]:
            moved[_live_bucket(vec3(ref[0], ref[1], ref[2]), prm, half, live_mask)] = 1
            if flags[o] == 1:
                moved[_live_bucket(x, prm, half, live_mask)] = 1
        elif (o < was_frozen) != (use_frozen != 0 and freeze[o] == 1):  # (freeze is set below n_listed only)
            moved[_live_bucket(x, prm, half, live_mask)] = 1


@ti.func
def _live_bucket(x, prm: ti.template(), half, live_mask):
    """The slot of moved (mark_moved_cells, _still_around) for the cell of x: its live-half bucket."""
    return half + ti.cast(_morton(_cell_of(x, prm)) & ti.cast(live_mask, ti.i64), ti.i32)


@ti.func
def _still_around(x_i, moved: ti.template(), prm: ti.template(), mask, live_mask):
    """Whether no cell of the 27 around x_i's shares a live bucket with a cell where anything moved (nothing in
    the frozen prefix moves)."""
    sx, sy, sz = _neighbor_bits(_cell_of(x_i, prm))
    still = True
    for d in ti.static(FULL_STENCIL):
        code = sx[d[0] + 1] | sy[d[1] + 1] | sz[d[2] + 1]
        if moved[mask + 1 + ti.cast(code & ti.cast(live_mask, ti.i64), ti.i32)] != 0:
            still = False
    return still


@ti.kernel
def count_neighbors(lo: ti.i32, n_frozen: ti.i32, sizes: I32_1, kin: KIN, prop: PROP, cell: I64_1, starts: I32_1,
                    nbr_off: I32_1, prm: F64_1, mask: ti.i32, live_mask: ti.i32, keep_still: ti.i32, moved: I32_1,
                    order: I32_1, old_off: I32_1, kept: I32_1):
    """nbr_off[i + 1] = number of particles within r_i + r_j + cohesion range + skin of i (i in lo..n_act,
    n_act = sizes[SZ_ACTIVE], as sort_by_bucket left it) found through the half stencil (a half list: each pair
    once, held by one of the two); then the prefix sum (nbr_off[i] is where i's list starts; nbr_off[lo] is kept).
    sizes[SZ_ENTRIES] = the entry count.

    A frozen particle lists frozen partners only; a live one lists the live partners of its half stencil and every
    frozen partner around it (the pairs between the two are held by the live side, so the frozen lists never
    change while they stay frozen).

    keep_still = 1 (mark_moved_cells ran): a particle none of whose 27 cells saw anything move, join or leave the
    frozen prefix since the last build keeps its old list (kept[i] = 1): the same particles at the same places, found
    in the same order (the sort keeps the order within a cell), so the search would give exactly that list. A
    sleeping bed is then not searched again whenever the soil at the tool needs new lists, nor the frozen soil when
    the prefix is partitioned anew."""
    n_act = sizes[SZ_ACTIVE]
    if lo == 0:
        nbr_off[0] = 0
    for i in range(lo, n_act):
        x_i = kin[i, 0]
        r_i = prop[i][0]
        extra = prm[P_COH_D] + prm[P_SKIN]
        count = 0
        kept[i] = 0
        if keep_still != 0:
            if _still_around(x_i, moved, prm, mask, live_mask):
                kept[i] = 1
                o_i = order[i]
                count = old_off[o_i + 1] - old_off[o_i]
        if kept[i] == 0:
            if i < n_frozen:
                count = _count_found(i, x_i, r_i, extra, kin, prop, cell, starts, prm, mask, 0, True)
            else:
                count = _count_found(i, x_i, r_i, extra, kin, prop, cell, starts, prm, live_mask, mask + 1, True)
                if n_frozen > 0:
                    count += _count_found(i, x_i, r_i, extra, kin, prop, cell, starts, prm, mask, 0, False)
        nbr_off[i + 1] = count
    ti.loop_config(serialize=True)
    for i in range(lo, n_act):
        nbr_off[i + 1] += nbr_off[i]
    sizes[SZ_ENTRIES] = nbr_off[n_act]


@ti.func
def _count_found(i, x_i, r_i, extra, kin: ti.template(), prop: ti.template(), cell: ti.template(),
                 starts: ti.template(), prm: ti.template(), mask, key0, half: ti.template()):
    """How many particles of one half of the table (buckets key0..) i's stencil finds within reach: the half
    stencil in its own half (half=True), all 27 cells in the other."""
    count = 0
    sx, sy, sz = _neighbor_bits(_cell_of(x_i, prm))
    for d in ti.static(HALF_STENCIL if half else FULL_STENCIL):
        code = sx[d[0] + 1] | sy[d[1] + 1] | sz[d[2] + 1]
        b = key0 + ti.cast(code & ti.cast(mask, ti.i64), ti.i32)
        first = starts[b]
        if ti.static(half and d == (0, 0, 0)):
            first = ti.max(first, i + 1)  # own cell: each pair once, by its lower index
        for j in range(first, starts[b + 1]):
            if cell[j] == code:  # buckets mix cells: keep only this cell's particles
                dx = x_i - kin[j, 0]
                reach = r_i + prop[j][0] + extra
                if dx.dot(dx) < reach * reach:
                    count += 1
    return count


@ti.func
def _old_history(o_i, o_j, old_off: ti.template(), old_j: ti.template(), old_h: ti.template()):
    """Springs of the pair (o_i, o_j) in the old lists (held by either particle), seen from o_i."""
    h = vec6f(0.0)
    for s in range(old_off[o_i], old_off[o_i + 1]):
        if old_j[s] == o_j:
            h = old_h[s]
    for s in range(old_off[o_j], old_off[o_j + 1]):
        if old_j[s] == o_i:
            h = -old_h[s]  # held by the other side: every spring of a pair is antisymmetric
    return h


@ti.kernel
def fill_neighbors(lo: ti.i32, n_frozen: ti.i32, n_act: ti.i32, kin: KIN, prop: PROP, cell: I64_1, starts: I32_1,
                   order: I32_1, old_off: I32_1, old_j: I32_1, old_h: HIST_1, nbr_off: I32_1, nbr_j: I32_1,
                   nbr_h: HIST_1, x_ref: REF, prm: F64_1, mask: ti.i32, live_mask: ti.i32, kept: I32_1,
                   order_inv: I32_1):
    """Write the lists of lo..n_act counted by count_neighbors, carrying each pair's springs over from the old lists.

    Particles are already sorted (new index = slot; order[new] = old). Also records the positions the skin
    criterion is measured from. A list kept (count_neighbors) is copied with its partners renumbered
    (order_inv: old -> new index) and the springs the search would have carried over.
    """
    for i in range(lo, n_act):
        x_i = kin[i, 0]
        r_i = prop[i][0]
        extra = prm[P_COH_D] + prm[P_SKIN]
        e = nbr_off[i]
        o_i = order[i]
        if kept[i] != 0:
            for s in range(old_off[o_i], old_off[o_i + 1]):
                j = order_inv[old_j[s]]
                nbr_j[e] = j
                h = vec6f(0.0)
                if _touching(x_i, r_i, kin, prop, j):
                    h = old_h[s]
                nbr_h[e] = h
                e += 1
        elif i < n_frozen:
            _fill_found(i, o_i, x_i, r_i, extra, e, kin, prop, cell, starts, order, old_off, old_j, old_h, nbr_j,
                        nbr_h, prm, mask, 0, True)
        else:
            e = _fill_found(i, o_i, x_i, r_i, extra, e, kin, prop, cell, starts, order, old_off, old_j, old_h,
                            nbr_j, nbr_h, prm, live_mask, mask + 1, True)
            if n_frozen > 0:
                _fill_found(i, o_i, x_i, r_i, extra, e, kin, prop, cell, starts, order, old_off, old_j, old_h, nbr_j,
                            nbr_h, prm, mask, 0, False)
        x_ref[i] = vec4(x_i[0], x_i[1], x_i[2], _clearance(x_i, _pit_of(x_i, prm), prm))


@ti.func
def _touching(x_i, r_i, kin: ti.template(), prop: ti.template(), j):
    """Whether i and j overlap: one function for a searched list and a kept one, so both compile the same test."""
    dx = x_i - kin[j, 0]
    r_sum = r_i + prop[j][0]
    return dx.dot(dx) < r_sum * r_sum


@ti.func
def _fill_found(i, o_i, x_i, r_i, extra, e0, kin: ti.template(), prop: ti.template(), cell: ti.template(),
                starts: ti.template(), order: ti.template(), old_off: ti.template(), old_j: ti.template(),
                old_h: ti.template(), nbr_j: ti.template(), nbr_h: ti.template(), prm: ti.template(), mask, key0,
                half: ti.template()):
    """Write what _count_found counts into i's list from entry e0 on; returns the next entry."""
    e = e0
    sx, sy, sz = _neighbor_bits(_cell_of(x_i, prm))
    for d in ti.static(HALF_STENCIL if half else FULL_STENCIL):
        code = sx[d[0] + 1] | sy[d[1] + 1] | sz[d[2] + 1]
        b = key0 + ti.cast(code & ti.cast(mask, ti.i64), ti.i32)
        first = starts[b]
        if ti.static(half and d == (0, 0, 0)):
            first = ti.max(first, i + 1)
        for j in range(first, starts[b + 1]):
            if cell[j] == code:
                dx = x_i - kin[j, 0]
                d2 = dx.dot(dx)
                r_sum = r_i + prop[j][0]
                reach = r_sum + extra
                if d2 < reach * reach:
                    nbr_j[e] = j
                    h = vec6f(0.0)
                    if _touching(x_i, r_i, kin, prop, j):  # only touching pairs have springs that matter
                        h = _old_history(o_i, order[j], old_off, old_j, old_h)
                    nbr_h[e] = h
                    e += 1
    return e


@ti.kernel
def build_reverse(lo: ti.i32, n_frozen: ti.i32, n_act: ti.i32, nbr_off: I32_1, nbr_j: I32_1, rev_off: I32_1,
                  rev_pos: I32_1, scratch: ti.i32, rev_holder: I32_1):
    """Reverse lists of the holders lo..n_act: each particle j gets a segment rev_off[j]..rev_off[j+1] with one slot
    per pair held by another particle; rev_pos[e] is the slot of entry e (slots in entry order; serial:
    deterministic, and cheap next to the neighbour search). A frozen particle is not integrated, so what a live
    holder puts on it goes to the `scratch` slot, and its segment (frozen holders only) never changes."""
    if lo == 0:
        rev_off[0] = 0
    for i in range(lo + 1, n_act + 1):
        rev_off[i] = 0
    ti.loop_config(serialize=True)
    for i in range(lo, n_act):
        for e in range(nbr_off[i], nbr_off[i + 1]):
            j = nbr_j[e]
            if i < n_frozen or j >= n_frozen:
                rev_off[j + 1] += 1
    base = rev_off[lo]
    ti.loop_config(serialize=True)
    for i in range(lo, n_act):
        rev_off[i + 1] += rev_off[i]
    ti.loop_config(serialize=True)
    for i in range(lo, n_act):
        for e in range(nbr_off[i], nbr_off[i + 1]):
            j = nbr_j[e]
            if i < n_frozen or j >= n_frozen:
                rev_pos[e] = rev_off[j]
                rev_off[j] += 1
            else:
                rev_pos[e] = scratch
    ti.loop_config(serialize=True)
    for k in range(n_act - lo):  # the fill advanced each start to the next one's: shift back
        rev_off[n_act - k] = rev_off[n_act - k - 1]
    rev_off[lo] = base


@ti.kernel
def build_reverse_parallel(lo: ti.i32, n_frozen: ti.i32, n_act: ti.i32, nbr_off: I32_1, nbr_j: I32_1,
                           rev_off: I32_1, rev_pos: I32_1, scratch: ti.i32, rev_holder: I32_1):
    """build_reverse from parallel loops (a GPU's): the same rev_off and rev_pos. Each particle's count goes to its
    own rev_off entry, summed to its segment's end; the fill takes slots from the end down in any order, which
    leaves each entry at its segment's start; each segment's entries are then sorted back into entry order
    (rev_holder serves as the slot -> entry map: fill_rev_holder rewrites every live slot after this)."""
    if lo == 0:
        rev_off[0] = 0
    base = rev_off[lo]
    for j in range(lo, n_act + 1):
        rev_off[j] = 0
    for i in range(lo, n_act):
        for e in range(nbr_off[i], nbr_off[i + 1]):
            j = nbr_j[e]
            if i < n_frozen or j >= n_frozen:
                ti.atomic_add(rev_off[j], 1)
    _scan(rev_off, lo, n_act, base)
    rev_off[n_act] = base
    if n_act > lo:
        rev_off[n_act] = rev_off[n_act - 1]
    for i in range(lo, n_act):
        for e in range(nbr_off[i], nbr_off[i + 1]):
            j = nbr_j[e]
            if i < n_frozen or j >= n_frozen:
                q = ti.atomic_sub(rev_off[j], 1) - 1
                rev_holder[q] = e
            else:
                rev_pos[e] = scratch
    for j in range(lo, n_act):
        _sort_segment(rev_holder, rev_off[j], rev_off[j + 1])
        for q in range(rev_off[j], rev_off[j + 1]):
            rev_pos[rev_holder[q]] = q


# ----------------------------------------------------------------------------------------------- diagnostics
@ti.kernel
def totals(n_act: ti.i32, kin: KIN, prop: PROP, flags: I32_1, partial: F64_2, out: F64_1):
    """out = [mass, momentum x y z, kinetic energy (translation + rotation), max speed, count, 0]; block sums
    added in block order, so the result does not depend on thread scheduling."""
    n_blocks = (n_act + BLOCK - 1) // BLOCK
    for blk in range(n_blocks):
        acc = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], ti.f64)
        for i in range(blk * BLOCK, ti.min(n_act, (blk + 1) * BLOCK)):
            if flags[i] == 1:
                m = prop[i][1]
                v = kin[i, 1]
                w = kin[i, 2]
                acc[0] += m
                acc[1] += m * v[0]
                acc[2] += m * v[1]
                acc[3] += m * v[2]
                acc[4] += 0.5 * m * v.dot(v) + ti.f64(0.2) * m * prop[i][0] ** 2 * w.dot(w)
                acc[5] = ti.max(acc[5], v.norm())
                acc[6] += 1.0
        for c in ti.static(range(7)):
            partial[blk, c] = acc[c]
    for c in range(8):
        out[c] = 0.0
    ti.loop_config(serialize=True)
    for blk in range(n_blocks):
        for c in ti.static(range(7)):
            if c == 5:
                out[c] = ti.max(out[c], partial[blk, c])
            else:
                out[c] += partial[blk, c]


@ti.kernel
def surface_height(n_act: ti.i32, kin: KIN, prop: PROP, flags: I32_1, height: F64_2, x0: ti.f64, dx: ti.f64,
                   y0: ti.f64, dy: ti.f64):
    """height[ix, iy] = the soil surface above each node as a ball of the grain's radius rolling over it would
    trace it: every sphere raises the nodes within 2r of its centre to z - r + sqrt((2r)^2 - d^2) (its own top
    z + r right above it). Nodes finer than a grain are not left empty, and the narrow gaps between grains
    (down which a bare envelope of sphere caps would read the pit floor) are bridged."""
    for i in range(n_act):
        if flags[i] == 1:
            x = kin[i, 0]
            r = prop[i][0]
            reach = 2.0 * r
            ix0 = ti.max(ti.cast(ti.ceil((x[0] - reach - x0) / dx), ti.i32), 0)
            ix1 = ti.min(ti.cast(ti.floor((x[0] + reach - x0) / dx), ti.i32), height.shape[0] - 1)
            iy0 = ti.max(ti.cast(ti.ceil((x[1] - reach - y0) / dy), ti.i32), 0)
            iy1 = ti.min(ti.cast(ti.floor((x[1] + reach - y0) / dy), ti.i32), height.shape[1] - 1)
            for ix in range(ix0, ix1 + 1):
                for iy in range(iy0, iy1 + 1):
                    ddx = x0 + ix * dx - x[0]
                    ddy = y0 + iy * dy - x[1]
                    d2 = ddx * ddx + ddy * ddy
                    if d2 <= reach * reach:
                        ti.atomic_max(height[ix, iy], x[2] - r + ti.sqrt(reach * reach - d2))


@ti.kernel
def mass_in_box(n_act: ti.i32, kin: KIN, prop: PROP, flags: I32_1, partial: F64_2, origin: vec3, rot: mat3,
                lo: vec3, hi: vec3) -> ti.f64:
    """Mass of active particles whose centre, in the frame (origin, rot: frame -> world), lies in [lo, hi]."""
    n_blocks = (n_act + BLOCK - 1) // BLOCK
    for blk in range(n_blocks):
        total = ti.f64(0.0)
        for i in range(blk * BLOCK, ti.min(n_act, (blk + 1) * BLOCK)):
            if flags[i] == 1:
                q = rot.transpose() @ (kin[i, 0] - origin)
                if lo[0] <= q[0] <= hi[0] and lo[1] <= q[1] <= hi[1] and lo[2] <= q[2] <= hi[2]:
                    total += prop[i][1]
        partial[blk, 0] = total
    mass = ti.f64(0.0)
    ti.loop_config(serialize=True)
    for blk in range(n_blocks):
        mass += partial[blk, 0]
    return mass


@ti.kernel
def begin_chunk(first: ti.i32, upload: ti.i32, tools_in: F64_2, tools: F64_2, tool_acc: F64_2, stat: F64_1):
    """Start a run of substeps: nothing done, not halted. first (the advance's first run): copy the tool rows set
    on the host (if upload), zero the tool accumulators and the per-call divergence diagnostics."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        if first != 0:
            if upload != 0:
                for t in range(MAX_TOOLS):
                    # the jump from the pose the substeps reached to the one set is travel too (T_TRAVEL's bound:
                    # the sphere centre's move plus the rotation's, at most its Frobenius norm, times the lever)
                    travel = tools_in[t, T_TRAVEL]
                    if tools[t, T_ON] > 0.0 and tools_in[t, T_ON] > 0.0:
                        rot_old = _tool_rotation(tools, t)
                        rot_new = _tool_rotation(tools_in, t)
                        shift = _sphere_centre(tools_in, t, rot_new) - _sphere_centre(tools, t, rot_old)
                        turn = (rot_new - rot_old).norm()
                        travel = tools[t, T_TRAVEL] + shift.norm() + turn * (1.0 + 2.0 * CLEAR_MARGIN) * \
                            tools_in[t, T_BS + 3]
                    for c in range(T_WIDTH):
                        tools[t, c] = tools_in[t, c]
                    tools[t, T_TRAVEL] = travel
                    _wedge_refresh(tools, t)
            for t, c in ti.ndrange(MAX_TOOLS, 6):
                tool_acc[t, c] = 0.0
            stat[S_SPEED2] = 0.0
            stat[S_NONFINITE] = 0.0
        stat[S_HALT] = 0.0
        stat[S_THAW] = 0.0
        stat[S_DONE] = 0.0
        stat[S_ACTIVE] = 0.0


@ti.kernel
def end_chunk(tools: F64_2, tool_acc: F64_2, stat: F64_1, report: F64_1):
    """Everything the caller reads after a run of substeps in one array (one copy to the host): tool rows,
    accumulators, stat. One serial task."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        for t, c in ti.ndrange(MAX_TOOLS, T_WIDTH):
            report[t * T_WIDTH + c] = tools[t, c]
        for t, c in ti.ndrange(MAX_TOOLS, 6):
            report[MAX_TOOLS * T_WIDTH + t * 6 + c] = tool_acc[t, c]
        for c in range(N_STAT):
            report[MAX_TOOLS * (T_WIDTH + 6) + c] = stat[c]


REPORT_SIZE = MAX_TOOLS * (T_WIDTH + 6) + N_STAT


@ti.kernel
def reset_contacts(n: ti.i32, nbr_off: I32_1, surf_id: I32_2, surf_h: HIST):
    """Empty neighbour lists and free every wall and tool contact slot."""
    for i in range(n + 1):
        nbr_off[i] = 0
    for i in range(n):
        for s in ti.static(range(WALL_SLOTS)):
            surf_id[i, s] = -1
        surf_id[i, TOOL_BITS] = 0
        for s in ti.static(range(SURF_SLOTS)):
            surf_h[i, s] = vec6f(0.0)
