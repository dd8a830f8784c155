"""Numba kernels of the Monte Carlo feature-profile simulator ([supp_simulator]).

Pure functions over explicit arrays: the voxel state (``mat``, ``fill``), the event tables of
``events.EventTables`` and a seed, so a call is a deterministic function of its inputs. Nothing is
allocated per particle; secondary products go through a preallocated FIFO ring buffer that is drained
after every primary particle.

Random numbers (``SimConfig.rng_mode``):
  * "stream" (default, the data sets' simulator): numba's generator, re-seeded at every ``run_particles``
    call; the particles of a call consume one shared stream, so a particle that draws one number more (or
    becomes another species) shifts every later one.
  * "counter": common random numbers (``run_particles_crn``). Every uniform is a counter-based hash
    (SplitMix64's finalizer of key + counter x golden gamma, ``mix64``) of a key, and keys are derived by
    the same hash (``stream_key``): the macro step's key from (trajectory key, macro step) (``counter_seed``),
    a source's from (step, projectile), the j-th particle of that source from (source, j). A macro step
    launches a fixed number of particles per source (its rate x dt, with its own carried remainder) and
    processes them in the order of their arrival times, slot 0 of each particle's launch draws: the
    particles of two recipes are then the same particles in the same relative order, and a recipe with
    more flux of one source has the other's particles plus its extra ones inserted at their own times.
    A primary draws its launch from 8 fixed slots (arrival time, two for the Box-Muller energy, wing,
    polar angle, azimuth, x, y; drawn whether used or not); its h-th surface hit draws from sub-stream h:
    the target, channel, absorption and diffuse-reflection choices from fixed slots, then in order the
    yield rounding, reflection and product directions; its n-th emitted product has its own key. Every
    draw goes through an inverse CDF, so the same uniform gives the nearest outcome under either recipe
    (same launch point, angle quantile, energy quantile, channel quantile).
    What still decorrelates a pair: different particle counts (a flux change: only the extra particles),
    different outcomes of one draw (a probability, yield, angle or energy control moves the decision
    boundaries), and every later event that differs because an earlier one changed the surface: a changed
    voxel changes the target, the channel and the normal of the later hits on and around it, and a
    changed path hits other voxels. The cascade is fast: on ``small`` (quarter domain, 10 % changes of an
    ion energy or flux, ``bench.pair_noise``, benchmarks/small/pair_noise) the paired / independent noise
    ratio of the field is 0.06-0.17 at the first state, 0.36-0.42 after 5 transitions and 0.65-0.74 at
    the end (the default stream: 0.45-0.87 at once, 0.82-1.01 at the end); a change of 0.1 % reaches
    0.3 within 40 transitions.
  Helpers take the state ``rs`` (``RS_SIZE`` uint64: mode, particle key, draw key, counter) as an
  optional last argument; without it (or in mode 0) they draw from numba's generator as before.

Coordinates are voxel units: voxel (i, j, k) covers [i, i+1) x [j, j+1) x [k, k+1); z grows upward.

Walls (``TransportParams.mirror_walls``, ``SimConfig.domain`` = "quarter"): the lateral faces x = 0, nx and
y = 0, ny are periodic (default) or specular mirrors. A mirror box is traversed unfolded: the straight
flight crosses the mirror images of the box (period 2n along each axis), and a voxel is looked up at its
reflection into the box (``wall_index``: column -1 is column 0, column n is column n - 1). At a surface hit
the restart point is folded back (``wall_fold``): in an odd image its coordinate, the direction component
and the entry face are reflected, which is a specular reflection at every wall crossed (|v| unchanged).
The surface normal's 26-neighbourhood and a product's deposition voxel use the same reflection instead of
the periodic wrap. The surface events themselves are those of the periodic box. Default (periodic): the
code path of the data sets, bit for bit.

Per primary particle ([supp_simulator], "Particle Injection and Transport"):
  * species k with probability R_k / sum R (``src_cum``); launched at (U nx, U ny, nz - eps);
    polar angle with p(Omega) ~ cos^m theta [eq:supp_particle_angular_distribution], i.e.
    cos theta = U^(1/(m+1)), uniform azimuth; energy max(N(mu, sigma^2), 0) for ions
    [eq:supp_particle_energy_sampling], ``neutral_energy_ev`` (0.2 eV) for neutrals.
  * transport: exact voxel traversal (Amanatides-Woo) in continuous coordinates, periodic in x and y
    (or between mirror walls, below), terminated when leaving through z < 0 or z >= nz or after
    ``max_steps`` steps (voxel crossings plus surface hits) [supp_simulator].
  * at the first solid voxel (fill > 0; it is surface-exposed by construction since the particle arrives
    through a vacuum face neighbour): surface normal from the local material configuration (the
    fill-weighted unit offsets of the 26 neighbours, n = -sum f(o) o/|o|, normalized; the entry face normal
    when that estimate is degenerate or faces away); incidence cosine = -d.n; target species sampled from
    the voxel's contents; all rule channels of the (projectile, target) pair compete: total probability
    < 1 leaves a non-reactive remainder, otherwise the channels are normalized.
  * probability: ``laws.prob_physical`` (hard thresholds, real incidence angle). Choice: the paper
    lists "saturation at the reference energy" among the safeguards its *differentiable* form adds to the
    source Monte Carlo expression ([supp_kinetic_models]), so the simulator uses the unsaturated law
    p0 ((E - E_th)/(E_ref - E_th))^n F(theta): ``prob_physical`` times ((E - E_th)/(E_ref - E_th))^n for
    E > E_ref. Without it every design energy (160-500 eV > E_ref = 100-150 eV) would give the same
    probabilities.
  * yield: ``laws.yield_physical``; integer removal count k by stochastic rounding.
  * outcome: react / remove (+ SiCl_x products) / deposit, see ``events``; a reacting particle is consumed.
    Non-reactive ions reflect specularly about the normal and keep the fraction
    sin^2 theta + cos^2 theta ((M1 - M2)/(M1 + M2))^2 of their energy (elastic transfer of the normal
    momentum to a target atom at rest -- our choice of "energy reduction determined by the
    projectile-target mass relation"); non-reactive neutrals and products reflect diffusely (cosine about
    the normal) at unchanged energy.
  * excess-probability yield (``SimConfig.excess_probability_yield``, on by default): with the
    unsaturated law the competing channels' probabilities can sum to P > 1 (Cl+ / Ar+ on SiCl2 or SiCl3
    above ~330 eV). The channels are then chosen with probabilities p_c / P and, so that each channel's
    expected effect stays p_c Y_c as the unsaturated law says, the chosen event's yield is multiplied by P.
    Before this, the normalization silently re-saturated the law: one unit per ion at most, so Cl+ on a
    Cl-saturated surface gave the same flat-surface yield at 330 and 500 eV (``nemsim bench yields``:
    0.60 Si per ion at 500 eV, now 0.69), against the sqrt(E) growth of the ion-enhanced yield in the
    beam studies (Chang, Arnold, Sawin et al., J. Vac. Sci. Technol. A, 1997). Below P = 1 nothing
    changes (no extra random draw, identical states).
  * ion reflection law (``SimConfig.ion_absorb_below_deg`` / ``ion_reflect_above_deg``, off by default):
    a non-reacting ion reflects with probability R(theta) = 0 below theta_zero, 1 beyond theta_full,
    linear in theta between (``reflection_probability``), and is otherwise absorbed (implanted and
    neutralized; counter ``absorbed``). Molecular-dynamics studies of Cl+/Ar+ on Si find reflection
    rare near normal incidence and dominant at grazing incidence. Off by default because, measured on
    ``small`` (median recipe with m = 50, 500 eV, high ion flux), absorbing the near-normal and
    intermediate-angle ions (45-75 deg) removes the mask-facet-reflected ions that drive the sidewall
    bulge: lateral width -10 nm and the unsmoothed bow 4.6 -> 2.1 nm; kept as an option for studies.
  * optional mechanisms (``SimConfig``, off by default except the specular lobe, ``config`` module
    docstring; no extra random draws when off; measured in benchmarks/small/bowing.md):
      - diffuse ion reflection (``ion_reflect_diffuse`` = f): a reflecting ion scatters with probability
        f cosine-distributed about the local normal instead of specularly (rough or amorphized
        surfaces);
      - specular lobe (``ion_reflect_spread_deg`` = sigma): the reflected direction is drawn from a
        cos^k lobe about the specular one, k = 1 / sigma^2 (sigma in radians = the rms deviation per
        transverse direction), redrawn until it leaves the surface;
      - retained energy (``ion_reflect_energy`` = e): a reflected ion keeps the fraction e of its energy
        instead of the mass-ratio law above (inelastic losses the binary-collision law leaves out);
      - broad-angle wing (``ion_wing_fraction`` = w, ``ion_wing_m``): a fraction w of the ions is
        launched from cos^ion_wing_m instead of the control's cos^m (the wide tail of a collisional
        sheath's ion angular distribution);
      - ``sputter_calibration`` and ``resist_sputter_scale`` change rule parameters, not the kernels
        (``calibration`` module).
  * products: ``product_energy_ev`` (2 eV), cosine-distributed about the local normal, launched from the
    vacuum voxel in front of the hit face; on a solid voxel they stick with the rule's p_stick (adding one
    unit of their species to the hit voxel, or to the vacuum voxel in front of it when the hit voxel is
    full), otherwise reflect diffusely.
  * particle budget: every particle carries ``weight`` = 1/budget (1 by default); a surface event moves
    stochastic_round(weight x units) and emitted products carry the same weight (``config`` module
    docstring, "Particle budget"). When such an event is capped by the target present in the voxel
    (k > available), the unused fraction (k - removed)/k of the weight flies on along the same path
    (budget < 1 only; at weight 1 the calibrated simulator is unchanged and draws no extra numbers).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from nemsim.rules.laws import EPS, prob_physical, yield_physical

from .config import SimConfig
from .events import ACT_DEPOSIT, ACT_REACT, ACT_REMOVE, KernelTables

# counters (int64 array) layout
C_PRIMARY, C_IONS, C_NEUTRALS, C_PRODUCTS, C_STUCK = 0, 1, 2, 3, 4
C_ESC_TOP, C_ESC_BOTTOM, C_STEP_LIMIT, C_HITS, C_REACTIONS = 5, 6, 7, 8, 9
C_STEPS, C_DROPPED = 10, 11
C_REMOVED = 12  # + target index (5)
C_DEPOSITED = 17  # + target index (5)
C_CONV_FROM = 22  # + target index (5)
C_CONV_TO = 27  # + target index (5)
C_ABSORBED = 32  # non-reacting ions absorbed instead of reflected (angle-dependent reflection)
N_COUNTERS = 33
COUNTER_NAMES = (
    "primary", "ions", "neutrals", "products", "stuck", "escaped_top", "escaped_bottom", "step_limit",
    "hits", "reactions", "steps", "dropped",
) + tuple(f"removed_{i}" for i in range(5)) + tuple(f"deposited_{i}" for i in range(5)) + tuple(
    f"converted_from_{i}" for i in range(5)
) + tuple(f"converted_to_{i}" for i in range(5)) + ("absorbed",)  # fmt: skip
assert len(COUNTER_NAMES) == N_COUNTERS



class TransportParams(NamedTuple):
    """Scalar settings of the particle transport (one numba tuple argument of ``fly``/``run_particles``)."""

    cap: float  # Si-class units per full voxel
    rcap: float  # resist units per full voxel
    product_energy: float  # energy of emitted SiCl_x products [eV]
    max_steps: int  # voxel crossings + surface hits per particle
    # 1 / particle budget: the material one surface event moves, relative to budget 1 (module docstring)
    weight: float = 1.0
    # cosines of the incidence angles above which a non-reacting ion always reflects / below which it never
    # does (``reflection_probability``; 1, 1 = every non-reacting ion reflects)
    refl_cos_full: float = 1.0
    refl_cos_zero: float = 1.0
    excess_yield: bool = False  # the excess-probability yield (module docstring)
    # optional ion mechanisms (module docstring, "Optional mechanisms"; all off at these values)
    refl_diffuse: float = 0.0  # fraction of reflecting ions scattered diffusely instead of specularly
    refl_lobe_k: float = 0.0  # cos^k lobe about the specular direction (0: exactly specular)
    refl_energy: float = 0.0  # retained energy fraction of a reflected ion (0: the mass-ratio law)
    wing_fraction: float = 0.0  # fraction of ions launched from cos^wing_m instead of the control's cos^m
    wing_m: float = 5.0
    mirror_walls: bool = False  # lateral walls: mirrors instead of periodic wrap (module docstring, "Walls")


def transport_params(config: SimConfig, cap: float, rcap: float) -> TransportParams:
    """The transport settings of ``config``; ``cap``/``rcap``: the resolved voxel capacities."""
    cos_full, cos_zero = config.reflection_cosines
    spread = math.radians(config.ion_reflect_spread_deg)
    lobe_k = 1.0 / (spread * spread) if spread > 0.0 else 0.0  # rms transverse deviation = spread
    return TransportParams(float(cap), float(rcap), float(config.product_energy_ev), int(config.max_steps),
                           float(config.particle_weight), float(cos_full), float(cos_zero),
                           bool(config.excess_probability_yield), float(config.ion_reflect_diffuse),
                           float(lobe_k), float(config.ion_reflect_energy), float(config.ion_wing_fraction),
                           float(config.ion_wing_m), config.domain in ("quarter", "section"))  # fmt: skip


class WorkBuffers(NamedTuple):
    """Arrays the kernels write: the product queue, channel scratch and the accumulated counters."""

    queue: np.ndarray  # (Q, 8) float64 ring buffer of emitted products (_Q_* columns)
    pbuf: np.ndarray  # (max_channels,) float64 scratch
    counters: np.ndarray  # (N_COUNTERS,) int64, accumulated
    event_counts: np.ndarray  # (E,) int64 realized events per rule, accumulated

    @classmethod
    def new(cls, max_channels: int, n_events: int, queue_capacity: int) -> WorkBuffers:
        """Zeroed buffers for a rule library with ``n_events`` events."""
        return cls(np.zeros((queue_capacity, 8)), np.zeros(max_channels),
                   np.zeros(N_COUNTERS, dtype=np.int64), np.zeros(n_events, dtype=np.int64))  # fmt: skip


class Sources(NamedTuple):
    """The K incident sources of one macro step (K = 4: Cl, Cl+, Cl2+, Ar+)."""

    species: np.ndarray  # (K,) int64 projectile index
    cum: np.ndarray  # (K,) float64 cumulative normalized rate
    m: np.ndarray  # (K,) float64 cos-power exponent of the angular distribution
    e_mean: np.ndarray  # (K,) float64 ion energy mean [eV] (ignored for neutrals)
    e_std: np.ndarray  # (K,) float64 ion energy std [eV]


_Q_X, _Q_Y, _Q_Z, _Q_DX, _Q_DY, _Q_DZ, _Q_SPECIES, _Q_ENERGY = 0, 1, 2, 3, 4, 5, 6, 7
_FACE_EPS = 1e-9  # how far inside the vacuum voxel a particle restarts after a surface hit


# counter-based random numbers (module docstring): SplitMix64 constants and the state layout
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_S11, _S27, _S30, _S31 = np.uint64(11), np.uint64(27), np.uint64(30), np.uint64(31)
_ONE = np.uint64(1)
_TO_UNIT = 1.0 / 9007199254740992.0  # 2^-53
_PRODUCT_STREAMS = np.uint64(1 << 32)  # product n of a particle: sub-stream 2^32 + n (hits: 0, 1, ...)
N_LAUNCH_DRAWS = 8  # fixed launch slots of a primary in counter mode
# fixed slots of a surface hit in counter mode (the hit's other draws follow them in order)
_SLOT_TARGET, _SLOT_CHANNEL, _SLOT_ABSORB, _SLOT_DIFFUSE = 0, 1, 2, 3
N_HIT_SLOTS = 4
RS_MODE, RS_PARTICLE, RS_KEY, RS_COUNT = 0, 1, 2, 3  # the rng state ``rs``: uint64 (RS_SIZE,)
RS_SIZE = 4


@numba.njit(cache=True)
def seed_rng(seed: int) -> None:
    """Seed numba's internal generator (the "stream" random numbers of this module)."""
    np.random.seed(seed)


@numba.njit(cache=True)
def mix64(z: np.uint64) -> np.uint64:
    """SplitMix64's output function (Stafford's variant 13): a bijective 64-bit hash."""
    z = (z ^ (z >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    return z ^ (z >> _S31)


@numba.njit(cache=True)
def stream_key(key: np.uint64, index: np.uint64) -> np.uint64:
    """Key of sub-stream ``index`` of the stream ``key`` (both uint64)."""
    return mix64(mix64(key) + (index + _ONE) * _GOLDEN)


def counter_seed(trajectory_key: int, macro_step: int) -> int:
    """The ``run_particles`` seed of a macro step in counter mode: a non-negative int64 from the
    trajectory's key and the macro step's index (primary i of the call is keyed by (this seed, i))."""
    return int(stream_key(np.uint64(trajectory_key), np.uint64(macro_step))) >> 1


@numba.njit(cache=True)
def new_rng_state(counter: bool) -> np.ndarray:
    """A zeroed rng state ``rs``; mode 1 (counter) or 0 (numba's generator)."""
    rs = np.zeros(RS_SIZE, dtype=np.uint64)
    if counter:
        rs[RS_MODE] = _ONE
    return rs


@numba.njit(cache=True)
def seat_particle(rs: np.ndarray, key: np.uint64) -> None:
    """Counter mode: start the draws of the particle keyed ``key`` (its launch slots)."""
    rs[RS_PARTICLE] = key
    rs[RS_KEY] = key
    rs[RS_COUNT] = 0


@numba.njit(cache=True)
def _seat_hit(rs: np.ndarray | None, hit: int) -> None:
    """Counter mode: draw the particle's ``hit``-th surface event from its own sub-stream."""
    if rs is None:
        return
    if rs[RS_MODE] == 0:
        return
    rs[RS_KEY] = stream_key(rs[RS_PARTICLE], np.uint64(hit))
    rs[RS_COUNT] = N_HIT_SLOTS


@numba.njit(cache=True)
def uniform_at(rs: np.ndarray | None, slot: int) -> float:
    """U[0, 1) from the fixed ``slot`` (< N_HIT_SLOTS) of the current hit in counter mode, so that whether
    an earlier decision drew does not move it; else the next number of numba's generator."""
    if rs is None:
        return np.random.random()
    if rs[RS_MODE] == 0:
        return np.random.random()
    return float(mix64(rs[RS_KEY] + np.uint64(slot + 1) * _GOLDEN) >> _S11) * _TO_UNIT


@numba.njit(cache=True)
def uniform(rs: np.ndarray | None = None) -> float:
    """U[0, 1): the next counter-based draw of ``rs`` (mode 1), else numba's generator."""
    if rs is None:
        return np.random.random()
    if rs[RS_MODE] == 0:
        return np.random.random()
    c = rs[RS_COUNT] + _ONE
    rs[RS_COUNT] = c
    return float(mix64(rs[RS_KEY] + c * _GOLDEN) >> _S11) * _TO_UNIT


@numba.njit(cache=True)
def unsaturated_factor(prob_model: int, prob_params: np.ndarray, energy_ev: float) -> float:
    """((E - E_th)/(E_ref - E_th))^n above E_ref for probModel events, else 1 (module docstring)."""
    if prob_model != 1:
        return 1.0
    e_th = prob_params[0]
    x = (energy_ev - e_th) / (prob_params[1] - e_th + EPS)
    if x <= 1.0:
        return 1.0
    return x ** prob_params[3]


@numba.njit(cache=True)
def stochastic_round(value: float, rs: np.ndarray | None = None) -> int:
    """floor(value) + Bernoulli(frac(value)): an integer with expectation ``value`` (value >= 0)."""
    if value <= 0.0:
        return 0
    k = int(math.floor(value))
    if uniform(rs) < value - k:
        k += 1
    return k


@numba.njit(cache=True)
def cos_power_polar(m: float, rs: np.ndarray | None = None) -> float:
    """cos theta for p(Omega) ~ cos^m theta on the hemisphere [eq:supp_particle_angular_distribution]."""
    return uniform(rs) ** (1.0 / (m + 1.0))


@numba.njit(cache=True)
def cosine_about(
    nx_: float, ny_: float, nz_: float, rs: np.ndarray | None = None
) -> tuple[float, float, float]:
    """Direction drawn from the cosine-weighted hemisphere about the unit vector n."""
    u1 = uniform(rs)
    return _polar_about(math.sqrt(u1), math.sqrt(max(0.0, 1.0 - u1)), nx_, ny_, nz_, rs)


@numba.njit(cache=True)
def lobe_about(
    k: float, nx_: float, ny_: float, nz_: float, rs: np.ndarray | None = None
) -> tuple[float, float, float]:
    """Direction drawn from p(Omega) ~ cos^k (angle to the unit vector n): a lobe about n (rms transverse
    deviation 1/sqrt(k) rad for large k)."""
    ct = cos_power_polar(k, rs)
    return _polar_about(ct, math.sqrt(max(0.0, 1.0 - ct * ct)), nx_, ny_, nz_, rs)


@numba.njit(cache=True)
def _polar_about(
    ct: float, st: float, nx_: float, ny_: float, nz_: float, rs: np.ndarray | None = None
) -> tuple[float, float, float]:
    """Unit direction at polar cosine ``ct`` (sine ``st``) from the unit vector n, uniform azimuth (one
    random draw)."""
    u2 = uniform(rs)
    ph = 2.0 * math.pi * u2
    a = st * math.cos(ph)
    b = st * math.sin(ph)
    # orthonormal basis around n (Duff et al. 2017)
    sign = 1.0 if nz_ >= 0.0 else -1.0
    e = -1.0 / (sign + nz_)
    f = nx_ * ny_ * e
    t1x = 1.0 + sign * nx_ * nx_ * e
    t1y = sign * f
    t1z = -sign * nx_
    t2x = f
    t2y = sign + ny_ * ny_ * e
    t2z = -ny_
    return (a * t1x + b * t2x + ct * nx_, a * t1y + b * t2y + ct * ny_, a * t1z + b * t2z + ct * nz_)


@numba.njit(cache=True)
def diffuse_direction(
    nnx: float, nny: float, nnz: float, fnx: float, fny: float, fnz: float, rs: np.ndarray | None = None
) -> tuple[float, float, float]:
    """Cosine-distributed direction about the surface normal n that leaves through the entry face f
    (8 redraws, then cosine about f)."""
    ex, ey, ez = cosine_about(nnx, nny, nnz, rs)
    for _try in range(8):
        if ex * fnx + ey * fny + ez * fnz > 0.0:
            break
        ex, ey, ez = cosine_about(nnx, nny, nnz, rs)
    if ex * fnx + ey * fny + ez * fnz <= 0.0:
        ex, ey, ez = cosine_about(fnx, fny, fnz, rs)
    return ex, ey, ez


@numba.njit(cache=True)
def wall_index(i: int, n: int, mirror: bool) -> int:
    """The box column (0 <= . < n) that holds unfolded column ``i``: i mod n (periodic), or between mirror
    walls at 0 and n the reflection of i (column -1 is column 0, column n is column n - 1; period 2n)."""
    if not mirror:
        return i % n
    m = i % (2 * n)
    if m >= n:
        m = 2 * n - 1 - m
    return m


@numba.njit(cache=True)
def wall_fold(x: float, d: float, f: float, n: int) -> tuple[float, float, float]:
    """Fold an unfolded coordinate ``x`` into the box [0, n] between mirror walls at 0 and n: a position in
    an odd image is reflected, and so are the velocity component ``d`` and the face-normal component ``f``
    along that axis (a specular wall: |velocity| and the other components unchanged)."""
    p = 2.0 * n
    x -= p * math.floor(x / p)
    if x > n:
        return p - x, -d, -f
    return x, d, f


@numba.njit(cache=True)
def _fill_at(fill: np.ndarray, i: int, j: int, k: int, mirror: bool = False) -> float:
    nx, ny, nz = fill.shape
    if k >= nz:
        return 0.0
    if k < 0:
        k = 0
    if mirror:
        return fill[wall_index(i, nx, True), wall_index(j, ny, True), k]
    return fill[i % nx, j % ny, k]


@numba.njit(cache=True)
def surface_normal(
    fill: np.ndarray, i: int, j: int, k: int, mirror: bool = False
) -> tuple[float, float, float]:
    """Outward normal at voxel (i, j, k) from its 26 neighbours' fill (module docstring); may be 0. Neighbours
    beyond the lateral faces: periodic images, or with ``mirror`` the mirror images (module docstring,
    "Walls")."""
    gx = 0.0
    gy = 0.0
    gz = 0.0
    for a in range(-1, 2):
        for b in range(-1, 2):
            for c in range(-1, 2):
                r2 = a * a + b * b + c * c
                if r2 == 0:
                    continue
                f = _fill_at(fill, i + a, j + b, k + c, mirror)
                if f == 0.0:
                    continue
                w = f / math.sqrt(r2)
                gx -= w * a
                gy -= w * b
                gz -= w * c
    norm = math.sqrt(gx * gx + gy * gy + gz * gz)
    if norm < 1e-9:
        return 0.0, 0.0, 0.0
    return gx / norm, gy / norm, gz / norm


@numba.njit(cache=True)
def reflection_probability(cos_inc: float, cos_full: float, cos_zero: float) -> float:
    """Probability that a non-reacting ion reflects at incidence cosine ``cos_inc`` (module docstring).

    0 at or below the incidence angle theta_zero (cos_inc >= cos_zero), 1 at or beyond theta_full
    (cos_inc <= cos_full), linear in the incidence angle between them.
    """
    if cos_inc <= cos_full:
        return 1.0
    if cos_inc >= cos_zero:
        return 0.0
    th = math.acos(min(cos_inc, 1.0))
    th_full = math.acos(cos_full)
    th_zero = math.acos(cos_zero)
    return (th - th_zero) / (th_full - th_zero)


@numba.njit(cache=True)
def _specular(
    dx: float, dy: float, dz: float, ddotn: float, nnx: float, nny: float, nnz: float, fnx: float, fny: float,
    fnz: float, lobe_k: float, rs: np.ndarray | None = None,
) -> tuple[float, float, float]:  # fmt: skip
    """Specular reflection of d about the normal n (about the entry face f if that would not leave through
    it); with ``lobe_k`` > 0 a direction from the cos^k lobe about it that leaves through f (8 draws, else
    the exact specular direction)."""
    rx = dx - 2.0 * ddotn * nnx
    ry = dy - 2.0 * ddotn * nny
    rz = dz - 2.0 * ddotn * nnz
    if rx * fnx + ry * fny + rz * fnz <= 1e-9:
        dotf = dx * fnx + dy * fny + dz * fnz
        rx = dx - 2.0 * dotf * fnx
        ry = dy - 2.0 * dotf * fny
        rz = dz - 2.0 * dotf * fnz
    norm = math.sqrt(rx * rx + ry * ry + rz * rz)
    rx /= norm
    ry /= norm
    rz /= norm
    if lobe_k > 0.0:
        for _try in range(8):
            ex, ey, ez = lobe_about(lobe_k, rx, ry, rz, rs)
            if ex * fnx + ey * fny + ez * fnz > 1e-9:
                return ex, ey, ez
    return rx, ry, rz


@numba.njit(cache=True)
def _refill(mat: np.ndarray, fill: np.ndarray, i: int, j: int, k: int, cap: float, rcap: float) -> None:
    s = mat[i, j, k, 0] + mat[i, j, k, 1] + mat[i, j, k, 2] + mat[i, j, k, 3]
    fill[i, j, k] = s / cap + mat[i, j, k, 4] / rcap


@numba.njit(cache=True)
def _push(queue: np.ndarray, tail: int, head: int, x: float, y: float, z: float,
          dx: float, dy: float, dz: float, species: int, energy: float) -> int:  # fmt: skip
    """Append to the ring buffer; returns the new tail (unchanged when full)."""
    cap = queue.shape[0]
    nxt = (tail + 1) % cap
    if nxt == head:
        return tail
    queue[tail, _Q_X] = x
    queue[tail, _Q_Y] = y
    queue[tail, _Q_Z] = z
    queue[tail, _Q_DX] = dx
    queue[tail, _Q_DY] = dy
    queue[tail, _Q_DZ] = dz
    queue[tail, _Q_SPECIES] = species
    queue[tail, _Q_ENERGY] = energy
    return nxt


@numba.njit(cache=True)
def fly(
    species: int, energy: float, x: float, y: float, z: float, dx: float, dy: float, dz: float,
    mat: np.ndarray, fill: np.ndarray, tab: KernelTables, prm: TransportParams, buf: WorkBuffers,
    head: int, tail: int, rs: np.ndarray | None = None,
) -> int:  # fmt: skip
    """Transport one particle until it reacts, escapes or runs out of steps; returns the queue tail.

    Args: the particle (projectile index, energy eV, position in voxels, unit direction); ``mat`` (nx, ny,
    nz, 5) and ``fill`` (nx, ny, nz), mutated by surface events; ``tab`` the rule tables; ``prm`` the
    transport settings (``TransportParams``); ``buf`` the queue of emitted products and the counters
    (``WorkBuffers``, mutated); ``head``, ``tail``: the product queue's ring pointers; ``rs``: the rng
    state (module docstring, "Random numbers"; omitted: numba's generator).
    """
    cap, rcap, weight = prm.cap, prm.rcap, prm.weight
    max_steps = prm.max_steps
    queue, pbuf, counters, event_counts = buf.queue, buf.pbuf, buf.counters, buf.event_counts
    nx, ny, nz = fill.shape
    mirror = prm.mirror_walls
    n_t = mat.shape[3]
    steps = 0
    hits = 0  # surface hits so far (counter mode: hit h draws from sub-stream h)
    w_event = weight  # weight still to be spent by this particle (< weight after a capped event)
    inf = 1e300
    while True:
        # ---------------- voxel traversal from (x, y, z) along (dx, dy, dz) ----------------
        ix = int(math.floor(x))
        iy = int(math.floor(y))
        iz = int(math.floor(z))
        if iz < 0:
            counters[C_ESC_BOTTOM] += 1
            return tail
        if iz >= nz:
            counters[C_ESC_TOP] += 1
            return tail
        sx = 1 if dx > 0.0 else -1
        sy = 1 if dy > 0.0 else -1
        sz = 1 if dz > 0.0 else -1
        if dx != 0.0:
            tdx = 1.0 / abs(dx)
            tmx = ((ix + 1.0 - x) if dx > 0.0 else (x - ix)) * tdx
        else:
            tdx = inf
            tmx = inf
        if dy != 0.0:
            tdy = 1.0 / abs(dy)
            tmy = ((iy + 1.0 - y) if dy > 0.0 else (y - iy)) * tdy
        else:
            tdy = inf
            tmy = inf
        if dz != 0.0:
            tdz = 1.0 / abs(dz)
            tmz = ((iz + 1.0 - z) if dz > 0.0 else (z - iz)) * tdz
        else:
            tdz = inf
            tmz = inf
        axis = -1
        t = 0.0
        hit = False
        wx = wall_index(ix, nx, mirror)
        wy = wall_index(iy, ny, mirror)
        if fill[wx, wy, iz] > 0.0:
            # started inside material (e.g. a product deposited where this particle waits): hit it at once
            hit = True
            axis = 2
            sz = -1 if dz < 0.0 else 1
        while not hit and steps < max_steps:
            if tmx < tmy:
                if tmx < tmz:
                    axis = 0
                    t = tmx
                    ix += sx
                    tmx += tdx
                else:
                    axis = 2
                    t = tmz
                    iz += sz
                    tmz += tdz
            else:
                if tmy < tmz:
                    axis = 1
                    t = tmy
                    iy += sy
                    tmy += tdy
                else:
                    axis = 2
                    t = tmz
                    iz += sz
                    tmz += tdz
            steps += 1
            if iz < 0:
                counters[C_STEPS] += steps
                counters[C_ESC_BOTTOM] += 1
                return tail
            if iz >= nz:
                counters[C_STEPS] += steps
                counters[C_ESC_TOP] += 1
                return tail
            wx = wall_index(ix, nx, mirror)
            wy = wall_index(iy, ny, mirror)
            if fill[wx, wy, iz] > 0.0:
                hit = True
        if not hit:
            counters[C_STEPS] += steps
            counters[C_STEP_LIMIT] += 1
            return tail
        steps += 1  # a surface hit counts as a step (guarantees termination)
        counters[C_HITS] += 1
        _seat_hit(rs, hits)
        hits += 1
        # restart point: on the entry face, just inside the vacuum voxel in front of it
        x = x + t * dx
        y = y + t * dy
        z = z + t * dz
        fnx = 0.0
        fny = 0.0
        fnz = 0.0
        if axis == 0:
            fnx = -float(sx)
            x = (ix if sx > 0 else ix + 1) - sx * _FACE_EPS
        elif axis == 1:
            fny = -float(sy)
            y = (iy if sy > 0 else iy + 1) - sy * _FACE_EPS
        else:
            fnz = -float(sz)
            z = (iz if sz > 0 else iz + 1) - sz * _FACE_EPS
        if mirror:
            # back from the unfolded traversal into the box: in an odd mirror image the position, the
            # direction and the entry face are reflected (module docstring, "Walls")
            x, dx, fnx = wall_fold(x, dx, fnx, nx)
            y, dy, fny = wall_fold(y, dy, fny, ny)
        else:
            x -= nx * math.floor(x / nx)
            y -= ny * math.floor(y / ny)
        # ---------------- surface normal and incidence ----------------
        nnx, nny, nnz = surface_normal(fill, wx, wy, iz, mirror)
        ddotn = dx * nnx + dy * nny + dz * nnz
        if ddotn > -1e-3 or nnx * fnx + nny * fny + nnz * fnz <= 0.0:
            nnx = fnx
            nny = fny
            nnz = fnz
            ddotn = dx * nnx + dy * nny + dz * nnz
        cos_inc = min(1.0, -ddotn)
        # ---------------- target species from the voxel contents ----------------
        total = 0
        for q in range(n_t):
            total += mat[wx, wy, iz, q]
        r = uniform_at(rs, _SLOT_TARGET) * total
        tgt = n_t - 1
        acc = 0.0
        for q in range(n_t):
            acc += mat[wx, wy, iz, q]
            if r < acc:
                tgt = q
                break
        # ---------------- competing rule channels ----------------
        pi = species * n_t + tgt
        start = tab.pair_start[pi]
        cnt = tab.pair_count[pi]
        ptot = 0.0
        for c in range(cnt):
            e = tab.pair_events[start + c]
            if tab.action[e] == ACT_DEPOSIT:
                p = tab.s_dep[e]
            else:
                p = prob_physical(tab.prob_model[e], tab.prob_params[e], tab.angle_kind[e], energy, cos_inc)
                p *= unsaturated_factor(tab.prob_model[e], tab.prob_params[e], energy)
            pbuf[c] = p
            ptot += p
        chosen = -1
        if ptot > 0.0:
            u = uniform_at(rs, _SLOT_CHANNEL) * max(ptot, 1.0)
            acc = 0.0
            for c in range(cnt):
                acc += pbuf[c]
                if u < acc:
                    chosen = tab.pair_events[start + c]
                    break
        if chosen >= 0:
            counters[C_STEPS] += steps
            counters[C_REACTIONS] += 1
            event_counts[chosen] += 1
            act = tab.action[chosen]
            if act == ACT_DEPOSIT:
                add = tab.conv_to[chosen]
                # units stuck: 1 at full budget (no random draw there, so budget 1 keeps its stream)
                n_add = 1 if w_event == 1.0 else stochastic_round(w_event, rs)
                if n_add == 0:
                    return tail
                if n_add > 1:
                    # what fits stays in the hit voxel, the rest goes to the vacuum voxel in front of it
                    room = int(math.floor((1.0 + 1e-9 - fill[wx, wy, iz]) * cap))
                    here = min(max(room, 0), n_add)
                    if here > 0:
                        mat[wx, wy, iz, add] += here
                        _refill(mat, fill, wx, wy, iz, cap, rcap)
                        counters[C_STUCK] += here
                        counters[C_DEPOSITED + add] += here
                    n_add -= here
                    if n_add == 0:
                        return tail
                elif fill[wx, wy, iz] + 1.0 / cap <= 1.0 + 1e-9:
                    mat[wx, wy, iz, add] += 1
                    _refill(mat, fill, wx, wy, iz, cap, rcap)
                    counters[C_STUCK] += 1
                    counters[C_DEPOSITED + add] += 1
                    return tail
                px = wall_index(int(math.floor(x)), nx, mirror)
                py = wall_index(int(math.floor(y)), ny, mirror)
                pz = int(math.floor(z))
                if 0 <= pz < nz:
                    mat[px, py, pz, add] += n_add
                    _refill(mat, fill, px, py, pz, cap, rcap)
                    counters[C_STUCK] += n_add
                    counters[C_DEPOSITED + add] += n_add
                else:
                    counters[C_DROPPED] += 1
                return tail
            y_val = yield_physical(tab.yield_model[chosen], tab.yield_params[chosen], energy, cos_inc)
            if prm.excess_yield and ptot > 1.0:
                # excess-probability yield: the channels were normalized by ptot; scaling the yield by
                # ptot keeps each channel's expected effect at p_c Y_c (module docstring)
                y_val *= ptot
            k = stochastic_round(y_val * w_event, rs)  # units this (weighted) event moves
            have = mat[wx, wy, iz, tgt]
            nrem = k if k < have else have
            if act == ACT_REACT:
                dst = tab.conv_to[chosen]
                mat[wx, wy, iz, tgt] -= nrem
                mat[wx, wy, iz, dst] += nrem
                counters[C_CONV_FROM + tgt] += nrem
                counters[C_CONV_TO + dst] += nrem
                if tgt == 4 or dst == 4:
                    _refill(mat, fill, wx, wy, iz, cap, rcap)
                if weight == 1.0 or nrem >= k:
                    return tail
                # capped super-particle: the unused part flies on (budget < 1 only)
                w_event *= (k - nrem) / k
                counters[C_STEPS] -= steps  # counted again where the particle ends
                continue
            if act == ACT_REMOVE:
                mat[wx, wy, iz, tgt] -= nrem
                counters[C_REMOVED + tgt] += nrem
                _refill(mat, fill, wx, wy, iz, cap, rcap)
                for j in range(tab.product_species.shape[0]):
                    coef = tab.prod_coef[chosen, j]
                    if coef <= 0.0:
                        continue
                    if tab.prod_is_yield[chosen, j]:
                        amount = coef * nrem / weight  # emitted products carry the same weight
                    elif weight == 1.0:
                        amount = coef if nrem > 0 else 0.0
                    elif nrem > 0:
                        # per real event: coef with P(k >= 1) = min(y, 1); nrem / (y w) corrects for the
                        # rounding and the cap of this weighted event (expectation 1 when uncapped)
                        amount = coef * min(y_val, 1.0) * nrem / (y_val * weight)
                    else:
                        amount = 0.0
                    n_emit = stochastic_round(amount, rs)
                    for _ in range(n_emit):
                        ex, ey, ez = diffuse_direction(nnx, nny, nnz, fnx, fny, fnz, rs)
                        new_tail = _push(
                            queue, tail, head, x, y, z, ex, ey, ez, tab.product_species[j], prm.product_energy
                        )
                        if new_tail == tail:
                            counters[C_DROPPED] += 1
                        else:
                            counters[C_PRODUCTS] += 1
                        tail = new_tail
            if weight == 1.0 or nrem >= k:
                return tail
            # capped super-particle (budget < 1): the real particles it still stands for did not find
            # material here; they fly on along the same path with the unused weight
            w_event *= (k - nrem) / k
            counters[C_STEPS] -= steps  # counted again where the particle ends
            continue
        # ---------------- no reaction: reflect (ions: or be absorbed) ----------------
        if tab.is_ion[species]:
            if prm.refl_cos_full < 1.0:
                r_prob = reflection_probability(cos_inc, prm.refl_cos_full, prm.refl_cos_zero)
                if r_prob < 1.0 and uniform_at(rs, _SLOT_ABSORB) >= r_prob:
                    counters[C_STEPS] += steps
                    counters[C_ABSORBED] += 1
                    return tail
            if prm.refl_energy > 0.0:
                energy *= prm.refl_energy
            else:
                m1 = tab.proj_mass[species]
                m2 = tab.target_mass[tgt]
                ratio = (m1 - m2) / (m1 + m2)
                c2 = cos_inc * cos_inc
                energy *= (1.0 - c2) + c2 * ratio * ratio
            if prm.refl_diffuse > 0.0 and uniform_at(rs, _SLOT_DIFFUSE) < prm.refl_diffuse:
                dx, dy, dz = diffuse_direction(nnx, nny, nnz, fnx, fny, fnz, rs)
            else:
                dx, dy, dz = _specular(dx, dy, dz, ddotn, nnx, nny, nnz, fnx, fny, fnz, prm.refl_lobe_k, rs)
        else:
            dx, dy, dz = diffuse_direction(nnx, nny, nnz, fnx, fny, fnz, rs)
        if steps >= max_steps:
            counters[C_STEPS] += steps
            counters[C_STEP_LIMIT] += 1
            return tail


@numba.njit(cache=True)
def _launch_uniform(launch: np.ndarray, slot: int, counter: bool) -> float:
    """A launch draw: the primary's fixed slot in counter mode, else the next number of numba's generator."""
    if counter:
        return launch[slot]
    return np.random.random()


@numba.njit(cache=True)
def _launch_all(
    mat: np.ndarray, fill: np.ndarray, n_target: int, count_ions: bool, owner: np.ndarray, index: np.ndarray,
    src: Sources, neutral_energy: float, tab: KernelTables, prm: TransportParams, buf: WorkBuffers, key: int,
    counter: bool,
) -> None:  # fmt: skip
    """The launch loop of both modes (one loop, so that no call per primary is added to ``fly``'s).

    Counter mode: the primaries ``(owner[p], index[p])`` (source, index) in this order, keyed from ``key``;
    else primaries of sources drawn from ``src.cum`` with numba's generator seeded with ``key`` until
    ``n_target`` ions (``count_ions``) or primaries; the launch draws then come in the order source,
    energy, wing, polar, azimuth, x, y.
    """
    if counter:
        np.random.seed(key & 0xFFFFFFFF)  # nothing draws from it in this mode; a call stays deterministic
    else:
        np.random.seed(key)
    rs = new_rng_state(counter)
    launch = np.zeros(N_LAUNCH_DRAWS)
    call_key = np.uint64(key)
    particle_key = np.uint64(0)
    queue, counters = buf.queue, buf.counters
    nx, ny, nz = fill.shape
    n_src = src.species.shape[0]
    done = 0
    p = 0
    while (p < owner.shape[0]) if counter else (done < n_target):
        if counter:
            ks = owner[p]
            particle_key = stream_key(stream_key(call_key, np.uint64(src.species[ks])), np.uint64(index[p]))
            seat_particle(rs, particle_key)
            for q in range(N_LAUNCH_DRAWS):
                launch[q] = uniform(rs)
            p += 1
        else:
            u = np.random.random()
            ks = n_src - 1
            for q in range(n_src):
                if u < src.cum[q]:
                    ks = q
                    break
        s = src.species[ks]
        counters[C_PRIMARY] += 1
        if tab.is_ion[s]:
            counters[C_IONS] += 1
            if counter:  # Box-Muller from two fixed slots
                gauss = math.sqrt(-2.0 * math.log(1.0 - launch[1])) * math.cos(2.0 * math.pi * launch[2])
            else:
                gauss = np.random.standard_normal()
            energy = max(src.e_mean[ks] + src.e_std[ks] * gauss, 0.0)
            if count_ions:
                done += 1
        else:
            counters[C_NEUTRALS] += 1
            energy = neutral_energy
        if not count_ions:
            done += 1
        m_launch = src.m[ks]
        wing = prm.wing_fraction > 0.0 and tab.is_ion[s]
        if wing and _launch_uniform(launch, 3, counter) < prm.wing_fraction:
            m_launch = prm.wing_m  # broad-angle wing (module docstring, "Optional mechanisms")
        ct = _launch_uniform(launch, 4, counter) ** (1.0 / (m_launch + 1.0))  # cos_power_polar
        st = math.sqrt(max(0.0, 1.0 - ct * ct))
        ph = 2.0 * math.pi * _launch_uniform(launch, 5, counter)
        x0 = _launch_uniform(launch, 6, counter) * nx
        y0 = _launch_uniform(launch, 7, counter) * ny
        dx0, dy0 = st * math.cos(ph), st * math.sin(ph)
        head = 0
        tail = fly(s, energy, x0, y0, nz - _FACE_EPS, dx0, dy0, -ct, mat, fill, tab, prm, buf, head, 0, rs)
        # drain the FIFO of secondary products (they may not emit further products, but could)
        n_products = 0
        while head != tail:
            qx = queue[head, _Q_X]
            qy = queue[head, _Q_Y]
            qz = queue[head, _Q_Z]
            qdx = queue[head, _Q_DX]
            qdy = queue[head, _Q_DY]
            qdz = queue[head, _Q_DZ]
            qs = int(queue[head, _Q_SPECIES])
            qe = queue[head, _Q_ENERGY]
            head = (head + 1) % queue.shape[0]
            if counter:
                seat_particle(rs, stream_key(particle_key, _PRODUCT_STREAMS + np.uint64(n_products)))
            n_products += 1
            tail = fly(qs, qe, qx, qy, qz, qdx, qdy, qdz, mat, fill, tab, prm, buf, head, tail, rs)


@numba.njit(cache=True)
def run_particles(
    mat: np.ndarray, fill: np.ndarray, n_target: int, count_ions: bool, src: Sources, neutral_energy: float,
    tab: KernelTables, prm: TransportParams, buf: WorkBuffers, seed: int,
) -> None:  # fmt: skip
    """Stream random numbers ("stream" mode, module docstring): launch primaries until ``n_target`` ions
    (``count_ions``) or primaries have been processed, each of the source drawn from ``src.cum``.

    Args:
      mat: (nx, ny, nz, 5) int32 species amounts; fill: (nx, ny, nz) float64 (both mutated).
      src: the incident sources (``Sources``); neutral_energy: energy of incident neutrals [eV].
      tab: the rule tables (``events.KernelTables``); prm: transport settings (``TransportParams``).
      buf: product queue, scratch and counters (``WorkBuffers``; counters accumulated).
      seed: seeds numba's generator for this call.
    """
    none = np.zeros(0, dtype=np.int64)
    _launch_all(mat, fill, n_target, count_ions, none, none, src, neutral_energy, tab, prm, buf, seed, False)


@numba.njit(cache=True)
def launch_order(step_key: int, counts: np.ndarray, species: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Counter mode: the primaries of one macro step as (source, index) pairs in the order of their arrival
    times (``counts[k]`` particles of source k, keyed by its projectile ``species[k]``; module docstring).
    Ties (probability 2^-53 per pair) keep source order, then index order."""
    n = 0
    for k in range(counts.shape[0]):
        n += counts[k]
    times = np.empty(n)
    owner = np.empty(n, dtype=np.int64)
    index = np.empty(n, dtype=np.int64)
    rs = new_rng_state(True)
    key = np.uint64(step_key)
    p = 0
    for k in range(counts.shape[0]):
        source_key = stream_key(key, np.uint64(species[k]))
        for j in range(counts[k]):
            seat_particle(rs, stream_key(source_key, np.uint64(j)))
            times[p] = uniform(rs)  # launch slot 0
            owner[p] = k
            index[p] = j
            p += 1
    order = np.argsort(times, kind="mergesort")
    return owner[order], index[order]


@numba.njit(cache=True)
def run_particles_crn(
    mat: np.ndarray, fill: np.ndarray, counts: np.ndarray, src: Sources, neutral_energy: float,
    tab: KernelTables, prm: TransportParams, buf: WorkBuffers, step_key: int,
) -> None:  # fmt: skip
    """Counter-based random numbers ("counter" mode, module docstring): launch ``counts[k]`` primaries of
    every source k, keyed by (``step_key``, projectile, index), in the order of their arrival times
    (``launch_order``).

    Args: as ``run_particles``; counts: (K,) int64 primaries per source; step_key: the macro step's key
    (``counter_seed``, a non-negative int64). ``src.cum`` is not used.
    """
    owner, index = launch_order(step_key, counts, src.species)
    _launch_all(mat, fill, 0, False, owner, index, src, neutral_energy, tab, prm, buf, step_key, True)
