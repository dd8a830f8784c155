"""Bind the compiled Event Rules Library to the simulator's surface-event tables ([supp_simulator]).

The simulator has no reaction table of its own: every channel, probability law, yield law, product and
sticking coefficient below is read from ``RuleTensors``. This module only re-packs them into the flat
arrays the numba kernels index, and says what each rule *does* to a voxel:

  effect react   -> convert min(k, available) units of the target into the rule's product species
                    (E1 Si -> SiCl ...); no particle is emitted (the product names the new surface state)
  effect etch /
         sputter -> remove min(k, available) units of the target; emit the rule's SiCl_x products as
                    secondary particles (fixed coefficient, or coefficient x removed units if ``yield``)
  effect deposit -> (product-mediated events) add one unit of the projectile SiCl_x with p = p_stick

k is the rule's yield turned into an integer by stochastic rounding. The effect comes from the compiled
meta flags (``phi`` columns ``react/etch/sputter/deposit``); an event without an ``effect`` is treated as
removal when it is primary and as deposition otherwise. Dropped events (``event_mask = 0``) never fire.
The probability parameters are the rules' unless a ``SimConfig`` option re-parameterizes some of them
(``calibration``: literature-fitted sputtering, resist sputter scale; off by default).

Incident sources: the projectiles that drive primary events with a flux control (Cl, Cl+, Cl2+, Ar+);
their flux, angle, energy-mean and energy-std control indices are read from the rules' ``ctrl_idx``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from nemsim.rules.compile import META_FLAGS, RuleTensors
from nemsim.rules.vocab import ION_PROJECTILES, PROJECTILES, TARGETS

from .calibration import calibrated_prob_params
from .config import SimConfig

ACT_NONE, ACT_REACT, ACT_REMOVE, ACT_DEPOSIT = 0, 1, 2, 3
N_R_BAR = 18  # phi = [r_bar (18) | meta flags (17)]
PRODUCT_SPECIES = ("SiCl", "SiCl2", "SiCl3")  # emitted/deposited species that are also surface species


class KernelTables(NamedTuple):
    """The per-event arrays of ``EventTables`` as the numba kernels take them: one tuple argument."""

    pair_start: np.ndarray
    pair_count: np.ndarray
    pair_events: np.ndarray
    action: np.ndarray
    conv_to: np.ndarray
    prob_model: np.ndarray
    prob_params: np.ndarray
    angle_kind: np.ndarray
    yield_model: np.ndarray
    yield_params: np.ndarray
    s_dep: np.ndarray
    prod_coef: np.ndarray
    prod_is_yield: np.ndarray
    product_species: np.ndarray
    is_ion: np.ndarray
    proj_mass: np.ndarray
    target_mass: np.ndarray


@dataclass(frozen=True)
class EventTables:
    """Flat arrays for the numba kernels. E events, S = 8 projectile species, T = 5 target species."""

    pair_start: np.ndarray  # (S * T,) int64 start of the pair's channel list in pair_events
    pair_count: np.ndarray  # (S * T,) int64 number of channels for (projectile s, target t)
    pair_events: np.ndarray  # (n,) int64 event ids grouped by pair
    max_channels: int
    action: np.ndarray  # (E,) int64 ACT_*
    conv_to: np.ndarray  # (E,) int64 target index produced by react / added by deposit (-1 none)
    prob_model: np.ndarray  # (E,) int64
    prob_params: np.ndarray  # (E, 5) float64 physical eV
    angle_kind: np.ndarray  # (E,) int64
    yield_model: np.ndarray  # (E,) int64
    yield_params: np.ndarray  # (E, 4) float64
    s_dep: np.ndarray  # (E,) float64 sticking probability of deposition events
    prod_coef: np.ndarray  # (E, 3) float64 emitted SiCl, SiCl2, SiCl3 per event (or per removed unit)
    prod_is_yield: np.ndarray  # (E, 3) bool
    product_species: np.ndarray  # (3,) int64 projectile index of SiCl, SiCl2, SiCl3
    is_ion: np.ndarray  # (S,) bool
    proj_mass: np.ndarray  # (S,) float64 amu
    target_mass: np.ndarray  # (T,) float64 amu
    src_species: np.ndarray  # (K,) int64 projectile index of each incident source (K = 4)
    src_ctrl: np.ndarray  # (K, 4) int64 control indices (flux, angle, E_mean, E_std), -1 none

    def kernel_tables(self) -> KernelTables:
        """The arrays the kernels index, as one tuple (shapes as above)."""
        return KernelTables(*(getattr(self, name) for name in KernelTables._fields))


def build_event_tables(rules: RuleTensors, config: SimConfig) -> EventTables:
    """Re-pack ``rules`` for the kernels (module docstring). Raises ValueError on an unusable library."""
    n_ev = len(rules.names)
    n_s, n_t = len(PROJECTILES), len(TARGETS)
    meta = np.asarray(rules.phi)[:, N_R_BAR:]
    flag = {name: meta[:, i] > 0.5 for i, name in enumerate(META_FLAGS)}
    mask = np.asarray(rules.event_mask, dtype=float) > 0.5
    is_primary = np.asarray(rules.is_primary, dtype=bool)

    action = np.full(n_ev, ACT_NONE, dtype=np.int64)
    conv_to = np.full(n_ev, -1, dtype=np.int64)
    prod_sp = np.array([PROJECTILES.index(s) for s in PRODUCT_SPECIES], dtype=np.int64)
    w_src = np.asarray(rules.w_src, dtype=float)
    for e in range(n_ev):
        name = str(rules.names[e])
        if not is_primary[e]:
            action[e] = ACT_DEPOSIT
            proj = PROJECTILES[int(rules.projectile[e])]
            if proj not in PRODUCT_SPECIES:
                raise ValueError(
                    f"deposition event {name!r}: projectile {proj!r} is not a surface species; "
                    f"expected one of {PRODUCT_SPECIES}"
                )
            conv_to[e] = TARGETS.index(proj)
        elif flag["react"][e]:
            action[e] = ACT_REACT
            made = [PROJECTILES[q] for q in np.flatnonzero(w_src[e] > 0) if PROJECTILES[q] in TARGETS]
            if len(made) != 1:
                raise ValueError(
                    f"react event {name!r}: needs exactly one product that is a surface species "
                    f"{TARGETS} (the new chlorination state), got {made}"
                )
            conv_to[e] = TARGETS.index(made[0])
        else:  # etch, sputter, or no effect given
            action[e] = ACT_REMOVE
        if not mask[e]:
            action[e] = ACT_NONE

    # channels per (projectile, target) pair, CSR layout
    pair_lists: list[list[int]] = [[] for _ in range(n_s * n_t)]
    for e in range(n_ev):
        if action[e] != ACT_NONE:
            pair_lists[int(rules.projectile[e]) * n_t + int(rules.target[e])].append(e)
    pair_count = np.array([len(x) for x in pair_lists], dtype=np.int64)
    pair_start = np.concatenate([[0], np.cumsum(pair_count)[:-1]]).astype(np.int64)
    pair_events = np.array([e for x in pair_lists for e in x], dtype=np.int64)

    prod_coef = np.zeros((n_ev, 3))
    prod_is_yield = np.zeros((n_ev, 3), dtype=bool)
    for j, q in enumerate(prod_sp):
        prod_coef[:, j] = np.where(action == ACT_REMOVE, w_src[:, q], 0.0)
        prod_is_yield[:, j] = np.asarray(rules.src_is_yield)[:, q] & (action == ACT_REMOVE)

    # incident sources: projectiles of primary events with a flux control
    src_species, src_ctrl = [], []
    for s in range(n_s):
        sel = is_primary & (np.asarray(rules.projectile) == s) & (np.asarray(rules.ctrl_idx)[:, 0] >= 0)
        if not sel.any():
            continue
        rows = np.unique(np.asarray(rules.ctrl_idx)[sel], axis=0)
        # one flux per species; angle/energy keys may be missing on some rows (take the max = the bound one)
        if len(np.unique(rows[:, 0])) != 1:
            name = PROJECTILES[s]
            raise ValueError(f"projectile {name!r}: its events bind different flux controls {rows[:, 0]}")
        src_species.append(s)
        src_ctrl.append(rows.max(axis=0))
    if not src_species:
        raise ValueError("the rules library has no primary event with a flux control; nothing to simulate")

    pm = dict(config.projectile_mass_amu)
    tm = dict(config.target_mass_amu)
    missing = [p for p in PROJECTILES if p not in pm] + [t for t in TARGETS if t not in tm]
    if missing:
        raise ValueError(f"SimConfig masses missing for species {missing}")
    return EventTables(
        pair_start=pair_start,
        pair_count=pair_count,
        pair_events=pair_events if len(pair_events) else np.zeros(1, dtype=np.int64),
        max_channels=int(max(1, pair_count.max())),
        action=action,
        conv_to=conv_to,
        prob_model=np.asarray(rules.prob_model, dtype=np.int64),
        prob_params=np.ascontiguousarray(calibrated_prob_params(rules, config)),  # config's options applied
        angle_kind=np.asarray(rules.angle_kind, dtype=np.int64),
        yield_model=np.asarray(rules.yield_model, dtype=np.int64),
        yield_params=np.ascontiguousarray(rules.yield_params, dtype=np.float64),
        s_dep=np.asarray(rules.s_dep, dtype=np.float64),
        prod_coef=prod_coef,
        prod_is_yield=prod_is_yield,
        product_species=prod_sp,
        is_ion=np.array([p in ION_PROJECTILES for p in PROJECTILES]),
        proj_mass=np.array([pm[p] for p in PROJECTILES], dtype=np.float64),
        target_mass=np.array([tm[t] for t in TARGETS], dtype=np.float64),
        src_species=np.array(src_species, dtype=np.int64),
        src_ctrl=np.array(src_ctrl, dtype=np.int64),
    )
