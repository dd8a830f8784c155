"""One trajectory: controls -> 101 normalized two-channel SDF states [supp_simulator, supp_data_generation].

``simulate_trajectory(scene, rules, controls, rng, config)`` is the library entry point; ``run_trajectory``
returns the same states plus the bookkeeping (particle/event counters, final voxel state) used by the
tests and benchmarks.

Time stepping ([supp_simulator], "Flux-Triggered Morphology Evolution"): the horizon is cut into macro
steps of ``scene.macro_dt_s`` (0.02 s); a macro step processes ``floor(R_ion dt + carry)`` incident ions
(neutrals interleaved by species sampling, so their number varies); the fractional remainder is carried
to the next macro step so the long-run ion count is exact (the paper says "approximately
floor(R_ion dt)"). With zero ion flux a macro step processes floor(R dt + carry) neutrals instead. A state
is recorded every ``macro_steps_per_snapshot`` macro steps (0.1 s) through Psi (``sdf.psi``): 101 states
for the 10 s horizon. With ``config.particle_budget`` = b < 1 the rates (and so the ion counts) are b
times the calibrated ones and each particle carries weight 1/b (``config`` module docstring). Controls
are one vector (14,) for the whole trajectory or a recipe (T, 14) with one vector per transition. Every
macro step seeds the kernel from ``rng``, so a trajectory is a deterministic function of (scene, rules,
controls, config, rng state). With ``config.rng_mode`` = "counter" one key is drawn from ``rng`` instead,
macro step g (counted from 0 over the whole horizon) has the key ``counter_seed(key, g)``, and every source
k launches floor(R_k dt + carry_k) particles with its own carried remainder (every source's long-run count
stays exact; the number of neutrals per step no longer varies with the species sampling), keyed by
(step, projectile, index) and processed in the order of their arrival times: the j-th particle of a source
in step g draws the same numbers in every recipe simulated from the same seed (common random numbers,
``kernels`` module docstring).

Quarter domain (``config.domain`` = "quarter", ``config`` module docstring): the particles fly in the
scene's lower quadrant between mirror walls (``domain.lower_quadrant``), at the quadrant's particle rate
(``SimConfig.simulated_scene``); after every transition the quadrant's (mask, Si) fractions are mirrored
into the full box (``domain.unfold_quadrant``) and go through Psi as in "full" (the smoothing sees the
whole mirrored field), so the states have the scene's shape. Psi of an exactly symmetric field is symmetric
only up to the error of its closest-point sweeps, which run in one raster order (on ``small``, normalized
SDF units: RMS 7e-4 in the initial state and 1e-3 after 2 s, against 8e-3 between two seeds then; at most
0.04 at a few voxels); the quarter's state is therefore the mean of Psi's four images under the two mirrors
(``mirror_mean``), exactly symmetric, and so is its ``initial_state``.
The counters, the totals and ``TrajectoryResult.domain`` describe the simulated quadrant
(``TrajectoryResult.full_domain``: mirrored).

Cross-section (``config.domain`` = "section", a trench; ``config`` module docstring): the particles fly in a
slab of the box between mirror walls (``domain.section_slab``); each state is Psi of the slab's (mask, Si)
fractions averaged over its rows and mirrored across the trench's axis, computed on one row of y, symmetrized
under the x mirror like the quarter's, and repeated along y: the recorded states have the scene's full shape
and are exactly y-invariant and x-symmetric. ``initial_state`` goes through the same path, so it is every
trajectory's first state under the same config.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from nemsim.controls import N_CONTROLS
from nemsim.rules.compile import RuleTensors
from nemsim.scenes import Scene

from .config import SimConfig
from .domain import (
    Domain,
    initial_domain,
    lower_quadrant,
    section_slab,
    unfold_domain,
    unfold_quadrant,
    unfold_section,
)
from .events import EventTables, build_event_tables
from .kernels import (
    COUNTER_NAMES,
    Sources,
    WorkBuffers,
    counter_seed,
    run_particles,
    run_particles_crn,
    transport_params,
)
from .sdf import psi

log = logging.getLogger(__name__)


@dataclass
class TrajectoryResult:
    """Output of ``run_trajectory``.

    states: (n_states, 2, D, H, W) float32 normalized SDF (channel 0 mask, 1 Si).
    counters: name -> total over the trajectory (see ``kernels.COUNTER_NAMES``).
    event_counts: (E,) int64 realized events per rule.
    domain: final voxel state of the simulated box: the scene's, or with ``config.domain`` = "quarter" its
      lower quadrant (nx/2, ny/2, nz); ``full_domain()`` is always the scene's box.
    initial_totals / final_totals: (5,) species amounts in the simulated box.
    wall_s: wall-clock seconds. simulated: the ``SimConfig.domain`` simulated ("full", "quarter" or
      "section"). full_shape: the scene's (nx, ny) (the box ``full_domain`` unfolds a section slab into).
    """

    states: np.ndarray
    counters: dict[str, int]
    event_counts: np.ndarray
    domain: Domain
    initial_totals: np.ndarray
    final_totals: np.ndarray
    wall_s: float
    simulated: str = "full"
    full_shape: tuple[int, int] | None = None

    def full_domain(self) -> Domain:
        """The final voxel state on the scene's whole box (the quadrant mirrored in "quarter" mode, the slab
        unfolded in "section" mode)."""
        if self.simulated == "section":
            assert self.full_shape is not None
            d = self.domain
            return Domain(unfold_section(d.mat, *self.full_shape), unfold_section(d.fill, *self.full_shape),
                          d.capacity, d.resist_capacity)
        return unfold_domain(self.domain) if self.simulated == "quarter" else self.domain


def check_controls(controls_raw: np.ndarray, scene: Scene) -> np.ndarray:
    """Validate (14,) or (T, 14) raw controls; returns a (T, 14) float64 schedule (T = n_transitions)."""
    u = np.asarray(controls_raw, dtype=np.float64)
    if u.ndim == 1:
        if u.shape != (N_CONTROLS,):
            raise ValueError(f"controls must have shape (14,) or ({scene.n_transitions}, 14), got {u.shape}")
        u = np.broadcast_to(u, (scene.n_transitions, N_CONTROLS))
    elif u.shape != (scene.n_transitions, N_CONTROLS):
        raise ValueError(
            f"a control recipe must have one vector per transition: shape ({scene.n_transitions}, 14), "
            f"got {u.shape}"
        )
    if not np.all(np.isfinite(u)):
        raise ValueError("controls contain NaN or infinite values")
    if np.any(u < 0):
        bad = sorted({int(j) for j in np.argwhere(u < 0)[:, -1]})
        raise ValueError(f"controls must be >= 0 (fluxes, exponents, energies); negative at indices {bad}")
    return np.ascontiguousarray(u)


def _sources(tables: EventTables, u: np.ndarray, rate_per_flux: float) -> tuple[np.ndarray, ...]:
    """Per-source (rate [1/s], m, E_mean, E_std) from one raw control vector."""
    ctrl = tables.src_ctrl  # (K, 4)

    def pick(col: int, default: float) -> np.ndarray:
        idx = ctrl[:, col]
        return np.where(idx >= 0, u[np.maximum(idx, 0)], default).astype(np.float64)

    return pick(0, 0.0) * rate_per_flux, pick(1, 0.0), pick(2, 0.0), pick(3, 0.0)


def mirror_mean(state: np.ndarray) -> np.ndarray:
    """The mean of a state (..., D, H, W) and its images under the mirrors of the H and W axes (through the
    opening's axis), summed in pairs so the result is exactly symmetric (module docstring)."""
    a = state + state[..., ::-1]
    return (a + a[..., ::-1, :]) * np.float32(0.25)


def _simulated_box(scene: Scene, cfg: SimConfig) -> Domain:
    """The initial voxel state of the box the particles fly in (the scene's, its quadrant or a slab)."""
    assert cfg.capacity is not None and cfg.resist_capacity is not None
    dom = initial_domain(scene, cfg.capacity, cfg.resist_capacity)
    if cfg.domain == "quarter":
        return lower_quadrant(dom)
    if cfg.domain == "section":
        sim = cfg.simulated_scene(scene)
        return section_slab(dom, sim.nx, sim.ny)
    return dom


def _state(dom: Domain, scene: Scene, cfg: SimConfig) -> np.ndarray:
    """The recorded (2, D, H, W) state of the simulated box's voxels: Psi of the full box's fractions,
    symmetrized in "quarter" mode; of the cross-section's row in "section" mode (module docstring)."""
    mask, si = dom.fractions()
    if cfg.domain == "section":
        mask, si = (unfold_section(f.mean(axis=1, keepdims=True), scene.nx, 1) for f in (mask, si))
        x = psi(mask, si, replace(scene, ny=1), cfg.psi_sigma_vox)  # (2, D, 3, W): one row of y, padded
        x = (x[:, :, 1:2] + x[:, :, 1:2, ::-1]) * np.float32(0.5)  # exactly symmetric under the x mirror
        return np.ascontiguousarray(np.broadcast_to(x, scene.state_shape))
    if cfg.domain == "quarter":
        mask, si = unfold_quadrant(mask), unfold_quadrant(si)
    x = psi(mask, si, scene, cfg.psi_sigma_vox)
    return mirror_mean(x) if cfg.domain == "quarter" else x


def initial_state(scene: Scene, config: SimConfig | None = None) -> np.ndarray:
    """x_0: (2, D, H, W) float32 normalized SDF (Ψ) of the scene's initial geometry (its feature: a per-case
    scene, ``Feature.apply``), identical to every trajectory's first state under ``config``. The
    surrogate's rollouts (service, counterfactual) start from it."""
    cfg = (config or SimConfig()).resolved(scene)
    if cfg.domain == "quarter" and (scene.nx % 2 or scene.ny % 2):  # no quadrant to simulate, but x0's
        # fractions are symmetric: the full box's state, mirrored as a quarter's states are
        full = replace(cfg, domain="full")
        return mirror_mean(_state(_simulated_box(scene, full), scene, full))
    return _state(_simulated_box(scene, cfg), scene, cfg)


def run_trajectory(
    scene: Scene,
    rules: RuleTensors,
    controls_raw: np.ndarray,
    rng: np.random.Generator,
    config: SimConfig | None = None,
    *,
    tables: EventTables | None = None,
    n_transitions: int | None = None,
    on_transition: Callable[[int, int], None] | None = None,
) -> TrajectoryResult:
    """Simulate one trajectory (module docstring).

    Args:
      scene: geometry, grid and horizon. rules: compiled Event Rules Library (the only reaction table).
      controls_raw: (14,) raw controls (CONTROL_NAMES order, physical units) or a (T, 14) recipe.
      rng: generator the per-macro-step kernel seeds are drawn from. config: simulator constants.
      tables: prebuilt ``build_event_tables(rules, config)`` (saves a few ms per call).
      n_transitions: stop after this many transitions (default: the scene's horizon, 100).
      on_transition: called as ``on_transition(done, total)`` after each transition (progress reports).
    Returns: ``TrajectoryResult`` with states (n + 1, 2, D, H, W) float32.
    """
    t0 = time.perf_counter()
    cfg = (config or SimConfig()).resolved(scene)
    assert cfg.capacity is not None and cfg.resist_capacity is not None
    schedule = check_controls(controls_raw, scene)
    n_tr = scene.n_transitions if n_transitions is None else int(n_transitions)
    if not 0 <= n_tr <= scene.n_transitions:
        raise ValueError(f"n_transitions must be in [0, {scene.n_transitions}], got {n_transitions}")
    tables = tables if tables is not None else build_event_tables(rules, cfg)
    rate_per_flux = cfg.particle_rate_per_flux(cfg.simulated_scene(scene))  # checks the scene's sizes
    dom = _simulated_box(scene, cfg)

    def state() -> np.ndarray:
        return _state(dom, scene, cfg)

    initial_totals = dom.totals()
    states = np.empty((n_tr + 1, *scene.state_shape), dtype=np.float32)
    states[0] = state()

    buf = WorkBuffers.new(tables.max_channels, len(rules.names), cfg.queue_capacity)
    counters, event_counts = buf.counters, buf.event_counts
    tab = tables.kernel_tables()
    prm = transport_params(cfg, cfg.capacity, cfg.resist_capacity)
    carry = 0.0
    dt = scene.macro_dt_s
    counter = cfg.rng_mode == "counter"
    key = int(rng.integers(0, 2**63)) if counter else 0
    carries = np.zeros(len(tables.src_species))  # counter mode: each source's carried remainder
    e_neutral = cfg.neutral_energy_ev
    for t in range(n_tr):
        rate, m, e_mean, e_std = _sources(tables, schedule[t], rate_per_flux)
        total = float(rate.sum())
        ion_rate = float(rate[tables.is_ion[tables.src_species]].sum())
        src = Sources(tables.src_species, np.cumsum(rate) / total if total > 0.0 else rate, m, e_mean, e_std)
        for j in range(scene.macro_steps_per_snapshot):
            if counter:
                due = rate * dt + carries
                counts = np.floor(due).astype(np.int64)
                carries = due - counts
                if counts.any():
                    step_key = counter_seed(key, t * scene.macro_steps_per_snapshot + j)
                    run_particles_crn(dom.mat, dom.fill, counts, src, e_neutral, tab, prm, buf, step_key)
                continue
            seed = int(rng.integers(0, 2**32))
            if total <= 0.0:
                continue
            count_ions = ion_rate > 0.0
            expected = (ion_rate if count_ions else total) * dt + carry
            n_target = int(math.floor(expected))
            carry = expected - n_target
            if n_target == 0:
                continue
            run_particles(dom.mat, dom.fill, n_target, count_ions, src, e_neutral, tab, prm, buf, seed)
        states[t + 1] = state()
        if on_transition is not None:
            on_transition(t + 1, n_tr)
    wall = time.perf_counter() - t0
    result = TrajectoryResult(
        states=states,
        counters={name: int(v) for name, v in zip(COUNTER_NAMES, counters, strict=True)},
        event_counts=event_counts,
        domain=dom,
        initial_totals=initial_totals,
        final_totals=dom.totals(),
        wall_s=wall,
        simulated=cfg.domain,
        full_shape=(scene.nx, scene.ny),
    )
    log.debug("trajectory: %.2f s, %d primaries", wall, result.counters["primary"])
    return result


def simulate_trajectory(
    scene: Scene,
    rules: RuleTensors,
    controls_raw: np.ndarray,
    rng: np.random.Generator,
    config: SimConfig | None = None,
) -> np.ndarray:
    """Simulate one trajectory; returns (n_states, 2, D, H, W) float32 normalized, padded, transposed SDFs.

    Args: see ``run_trajectory``. ``controls_raw`` is (14,) (constant) or (n_transitions, 14) (recipe).
    """
    return run_trajectory(scene, rules, controls_raw, rng, config).states
