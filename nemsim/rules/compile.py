"""Compile a validated ``RulesSpec`` into the fixed tensors of NEMSim ([eq:supp_event_library_compilation]).

``compile_rules(spec) -> RuleTensors`` is pure (no I/O). E = number of events (37), S = 8 species
(``vocab.PROJECTILES``), M = 3 families (physical, chemical, coupled); ``RuleTensors`` lists every field.

Event-parameter matrix R (E, 22) [eq:supp_event_matrix_blocks], blocks 4 + 4 + 6 + 6 + 2:
  identity  0 family id g_e - 1 (0 physical, 1 chemical, 2 coupled), 1 projectile idx, 2 target idx,
            3 dep_model id (0 none, 1 from_products_pool)
  controls  4..7 control indices (flux, angle, E_mean, E_std) into CONTROL_NAMES; -1 = none
  prob      8 prob_model id (-1 none, 0 const, 1 probModel), 9..13 prob_params
  yield     14 yield_model id (-1 none, 0 const, 1 yamamura), 15 Y_const, 16..19 (E_th, theta_max [deg],
            Y_max, Y0) of the Yamamura model (a const-yield event has 16..19 = 0, a Yamamura event 15 = 0)
  dep       20 required pool species idx (-1 none), 21 p_stick
Energies in R are physical eV (the kinetic code maps them to normalized coordinates itself).

Event descriptor phi (E, 35) = [r_bar (18) | m (17)] [eq:supp_event_descriptor]. The paper names the
contents but not the normalizations or the order; our choice:
  r_bar: 0 (g_e - 1)/2, 1 projectile/7, 2 target/4, 3 d_e (product-mediated), 4 mu_p/2 (0 none, 1 const,
         2 probModel), 5 p_const, 6 N(E_th), 7 N(E_ref), 8 p0, 9 n, 10 angle_kind/2, 11 mu_Y/2 (0 none,
         1 const, 2 yamamura), 12 Y_const, 13 N(E_Y_th), 14 cos(theta_max), 15 log(Y_max/Y0),
         16 (dep species idx + 1)/8 (0 = none), 17 p_stick; N(.) = energy normalization of the event's
         energy channel; entries of a model the event does not use are 0.
  m (META_FLAGS order): dep, ion, neutral, angle_P, angle_C, energy (probModel), yamamura, react, etch,
         sputter, deposit, src, sink, target_resist, target_chlor, group_physical, group_both.
Rate descriptor psi (E, 7) [eq:supp_eic_rate_descriptor] = [g_e/3 with g_e in {1,2,3}, projectile/7,
  target/4, d_e, mu_p/2, mu_Y/2, a_e/2] with the same 0-based ids as phi (mu: 0 = none for deposition).
Static prior alpha0 (E, 3) [eq:supp_smoothed_mechanism_prior], eps_alpha = 0.05: 0.90 / 0.05 / 0.05.
Role signals r_mech (E, 3) [eq:supp_physical_role_signal .. eq:supp_coupled_role_signal]:
  phys = max(m_P, m_yamamura, m_sputter, m_ion * m_group_physical)
  chem = max(m_C, m_react, m_neutral, m_dep)
  coup = max(m_group_both, m_src, m_sink, m_ion * m_target_chlor)
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from dataclasses import dataclass, field

import numpy as np

from nemsim.rules.schema import RulesSpec, canonical_text
from nemsim.rules.vocab import (
    ANGLE_KINDS,
    CHLORINATED_TARGETS,
    GROUP_TO_FAMILY,
    ION_PROJECTILES,
    N_FAMILIES,
    N_SPECIES,
    NEUTRAL_PROJECTILES,
    PROB_MODELS,
    PROJECTILES,
    TARGETS,
    YIELD_MODELS,
)

__all__ = [
    "EPS_ALPHA",
    "META_FLAGS",
    "PARAM_NAMES",
    "R_COLUMNS",
    "RuleTensors",
    "build_R",
    "compile_rules",
    "normalize_energy",
]

EPS_ALPHA = 0.05  # smoothing of the static mechanism prior [eq:supp_smoothed_mechanism_prior]

R_COLUMNS: tuple[str, ...] = (
    "family", "projectile", "target", "dep_model",
    "ctrl_flux", "ctrl_angle", "ctrl_E_mean", "ctrl_E_std",
    "prob_model", "prob_p1", "prob_p2", "prob_p3", "prob_p4", "prob_p5",
    "yield_model", "Y_const", "Y_E_th", "Y_theta_max", "Y_max", "Y0",
    "dep_species", "p_stick",
)  # fmt: skip
PARAM_NAMES: tuple[str, ...] = (
    "family", "projectile", "target", "is_dep", "prob_model", "p_const", "E_th", "E_ref", "p0", "n",
    "angle_kind", "yield_model", "Y_const", "Y_E_th", "cos_theta_max", "log_Y_ratio", "dep_species",
    "p_stick",
)  # fmt: skip
META_FLAGS: tuple[str, ...] = (
    "dep", "ion", "neutral", "angle_P", "angle_C", "energy", "yamamura", "react", "etch", "sputter",
    "deposit", "src", "sink", "target_resist", "target_chlor", "group_physical", "group_both",
)  # fmt: skip
assert len(R_COLUMNS) == 22 and len(PARAM_NAMES) == 18 and len(META_FLAGS) == 17


@dataclass(frozen=True, eq=False)
class RuleTensors:
    """Compiled Event Rules Library (fixed buffers). E events, S = 8 species, M = 3 families.

    Structured kinetic fields (what the simulator and ``kinetics`` read): prob_params (E, 5): const ->
    (p_const, 0, 0, 0, 0), probModel -> (E_th, E_ref, p0, n, angle_kind); yield_params (E, 4): const ->
    (Y_const, 0, 0, 0), yamamura -> (E_th, theta_max_deg, Y_max, Y0); the ``_norm`` versions map E_th and
    E_ref by [eq:supp_energy_normalization] with the bounds of the event's own E_mean control. Deposition
    events have prob_model = yield_model = -1 and zero parameters. Product graph: w_src (E, S) the fixed
    coefficient, or 1.0 where it is ``yield`` (``src_is_yield``: the kinetic code multiplies by Y_e);
    w_sink (E, S) one-hot of the deposition species; s_dep (E,) = p_stick (0 for primary events).
    sha256 = SHA-256 of ``source_text`` = ``schema.canonical_text(spec)`` (UTF-8). ``event_mask`` (1 =
    active) and ``perturbation`` serve [supp_rule_robustness] (event drop).
    """

    names: np.ndarray  # (E,) str
    R: np.ndarray  # (E, 22) event-parameter matrix
    phi: np.ndarray  # (E, 35) event descriptor [r_bar (18) | meta flags (17)]
    psi: np.ndarray  # (E, 7) EIC rate descriptor
    alpha0: np.ndarray  # (E, 3) static mechanism prior
    r_mech: np.ndarray  # (E, 3) deterministic mechanism-role signals in {0, 1}
    w_src: np.ndarray  # (E, S) product-source coefficients (1.0 where yield-scaled)
    w_sink: np.ndarray  # (E, S) required pool species, one-hot for deposition events
    s_dep: np.ndarray  # (E,) sticking coefficients (0 for primary events)
    src_is_yield: np.ndarray  # (E, S) bool, source coefficient is the event yield
    is_primary: np.ndarray  # (E,) bool
    ctrl_idx: np.ndarray  # (E, 4) int (flux, angle, E_mean, E_std); -1 = none
    projectile: np.ndarray  # (E,) int index into PROJECTILES
    target: np.ndarray  # (E,) int index into TARGETS
    group: np.ndarray  # (E,) int family index (0 physical, 1 chemical, 2 coupled)
    prob_model: np.ndarray  # (E,) int (-1 none, 0 const, 1 probModel)
    prob_params: np.ndarray  # (E, 5) physical eV
    angle_kind: np.ndarray  # (E,) int (0 none, 1 P, 2 C)
    yield_model: np.ndarray  # (E,) int (-1 none, 0 const, 1 yamamura)
    yield_params: np.ndarray  # (E, 4) physical eV, degrees
    prob_params_norm: np.ndarray  # (E, 5) E_th, E_ref in normalized energy coordinates
    yield_params_norm: np.ndarray  # (E, 4) E_th in normalized energy coordinates
    sha256: str
    source_text: str
    event_mask: np.ndarray = field(default=None)  # type: ignore[arg-type]  # (E,) 1 active / 0 dropped
    perturbation: str = "none"

    def __post_init__(self) -> None:
        if self.event_mask is None:
            object.__setattr__(self, "event_mask", np.ones(len(self.names)))

    @property
    def n_events(self) -> int:
        return len(self.names)

    @property
    def is_dep(self) -> np.ndarray:
        return ~self.is_primary

    def replace(self, **changes) -> RuleTensors:
        return dataclasses.replace(self, **changes)

    def torch_buffers(self, dtype=None) -> dict:
        """All array fields as torch tensors (floats as ``dtype``, default float32; int64; bool), for
        ``register_buffer``."""
        import torch

        dtype = torch.float32 if dtype is None else dtype

        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, np.ndarray) or value.dtype.kind in "UO":
                continue
            if value.dtype == bool:
                out[f.name] = torch.from_numpy(value.copy())
            elif value.dtype.kind in "iu":
                out[f.name] = torch.from_numpy(value.astype(np.int64))
            else:
                out[f.name] = torch.from_numpy(value.astype(np.float64)).to(dtype)
        return out

    def to_npz_dict(self) -> dict[str, np.ndarray]:
        """The arrays written by ``nemsim rules compile`` (paper names)."""
        return {
            "R": self.R, "phi": self.phi, "psi": self.psi, "alpha0": self.alpha0, "r_mech": self.r_mech,
            "w_src": self.w_src, "w_sink": self.w_sink, "s_dep": self.s_dep,
        }  # fmt: skip


def normalize_energy(values_ev: np.ndarray, channel: np.ndarray) -> np.ndarray:
    """[eq:supp_energy_normalization]: map physical energies to the normalized coordinate of a control
    channel, N_j(v) = 2 (v - l_j) / d_j - 1, using the fixed bounds of ``nemsim.controls``.

    Args:
      values_ev: (...) energies in eV.
      channel: (...) int control index of the energy channel (same shape), -1 -> value returned as 0.
    """
    from nemsim.controls import CONTROL_SPECS  # lazy: owned by the data module

    values_ev = np.asarray(values_ev, dtype=np.float64)
    channel = np.broadcast_to(np.asarray(channel), values_ev.shape)
    out = np.zeros_like(values_ev)
    for idx in np.unique(channel):
        if idx < 0:
            continue
        spec = CONTROL_SPECS[int(idx)]
        if spec.kind != "linear":
            raise ValueError(f"control {spec.name!r} is not a linear (energy) channel; "
                             f"got kind {spec.kind!r}")
        sel = channel == idx
        out[sel] = 2.0 * (values_ev[sel] - spec.t_low) / (spec.t_high - spec.t_low) - 1.0
    return out


def build_R(
    group, projectile, target, is_primary, ctrl_idx, prob_model, prob_params, yield_model, yield_params,
    dep_species, s_dep,
) -> np.ndarray:  # fmt: skip
    """Assemble the event-parameter matrix R (E, 22) from the structured fields (layout: module doc)."""
    n_ev = len(group)
    R = np.zeros((n_ev, 22))
    R[:, 0], R[:, 1], R[:, 2] = group, projectile, target
    R[:, 3] = (~np.asarray(is_primary, dtype=bool)).astype(float)
    R[:, 4:8] = ctrl_idx
    R[:, 8] = prob_model
    R[:, 9:14] = prob_params
    R[:, 14] = yield_model
    R[:, 15] = np.where(yield_model == 0, yield_params[:, 0], 0.0)
    R[:, 16:20] = np.where((yield_model == 1)[:, None], yield_params, 0.0)
    R[:, 20] = dep_species
    R[:, 21] = s_dep
    return R


@dataclass
class _EventColumns:
    """Per-event arrays read from the spec (E events), before any normalization."""

    names: np.ndarray  # (E,) str
    is_primary: np.ndarray  # (E,) bool
    group: np.ndarray  # (E,) int64 mechanism family
    projectile: np.ndarray  # (E,) int64
    target: np.ndarray  # (E,) int64
    ctrl_idx: np.ndarray  # (E, 4) int64 control indices (flux, angle, E_mean, E_std), -1 none
    prob_model: np.ndarray  # (E,) int64, -1 none
    yield_model: np.ndarray  # (E,) int64, -1 none
    prob_params: np.ndarray  # (E, 5) float64 physical
    yield_params: np.ndarray  # (E, 4) float64 physical
    angle_kind: np.ndarray  # (E,) int64
    w_src: np.ndarray  # (E, S) products emitted
    src_is_yield: np.ndarray  # (E, S) bool
    w_sink: np.ndarray  # (E, S) species consumed by deposition
    s_dep: np.ndarray  # (E,) sticking probability
    dep_species: np.ndarray  # (E,) int64, -1 none


def _event_columns(spec: RulesSpec) -> _EventColumns:
    """Read every event's identity, laws, parameters, products and deposition into arrays."""
    from nemsim.controls import CONTROL_NAMES  # lazy: owned by the data module

    ctrl_pos = {name: i for i, name in enumerate(CONTROL_NAMES)}
    n_ev = len(spec.events)
    names = np.array([ev.name for ev in spec.events])
    is_primary = np.array([ev.is_primary for ev in spec.events], dtype=bool)
    group = np.array([GROUP_TO_FAMILY[ev.group] for ev in spec.events], dtype=np.int64)
    projectile = np.array([PROJECTILES.index(ev.projectile) for ev in spec.events], dtype=np.int64)
    target = np.array([TARGETS.index(ev.target) for ev in spec.events], dtype=np.int64)
    ctrl_idx = np.full((n_ev, 4), -1, dtype=np.int64)
    prob_model = np.full(n_ev, -1, dtype=np.int64)
    yield_model = np.full(n_ev, -1, dtype=np.int64)
    prob_params = np.zeros((n_ev, 5))
    yield_params = np.zeros((n_ev, 4))
    angle_kind = np.zeros(n_ev, dtype=np.int64)
    w_src = np.zeros((n_ev, N_SPECIES))
    src_is_yield = np.zeros((n_ev, N_SPECIES), dtype=bool)
    w_sink = np.zeros((n_ev, N_SPECIES))
    s_dep = np.zeros(n_ev)
    dep_species = np.full(n_ev, -1, dtype=np.int64)

    for e, ev in enumerate(spec.events):
        for k, key in enumerate((ev.flux_key, ev.angle_key, ev.E_mean_key, ev.E_std_key)):
            if key is not None:
                ctrl_idx[e, k] = ctrl_pos[key]
        if ev.is_primary:
            prob_model[e] = PROB_MODELS.index(ev.prob_model)
            pp = ev.prob_params or {}
            if ev.prob_model == "const":
                prob_params[e, 0] = float(pp["p_const"])
            else:
                angle_kind[e] = ANGLE_KINDS.index(str(pp.get("angle", "None")))
                prob_params[e] = (
                    float(pp["E_th"]), float(pp["E_ref"]), float(pp["p0"]), float(pp["n"]), angle_kind[e]
                )
            yield_model[e] = YIELD_MODELS.index(ev.yield_model)
            yp = ev.yield_params or {}
            if ev.yield_model == "const":
                yield_params[e, 0] = float(yp["Y_const"])
            else:
                yield_params[e] = (yp["E_th"], yp["theta_max"], yp["Y_max"], yp["Y0"])
            for prod in ev.products:
                q = PROJECTILES.index(prod.species)
                if prod.coeff == "yield":
                    w_src[e, q] = 1.0
                    src_is_yield[e, q] = True
                else:
                    w_src[e, q] = float(prod.coeff)
        else:
            dp = ev.dep_params or {}
            q = PROJECTILES.index(str(dp["species"]))
            dep_species[e] = q
            w_sink[e, q] = 1.0
            s_dep[e] = float(dp["p_stick"])
    return _EventColumns(names, is_primary, group, projectile, target, ctrl_idx, prob_model, yield_model,
                         prob_params, yield_params, angle_kind, w_src, src_is_yield, w_sink, s_dep,
                         dep_species)  # fmt: skip


def _normalized_energies(c: _EventColumns) -> tuple[np.ndarray, np.ndarray]:
    """(prob_params_norm, yield_params_norm): energies in the coordinates of the event's E_mean control."""
    e_chan = c.ctrl_idx[:, 2]
    prob_params_norm = c.prob_params.copy()
    is_pm = c.prob_model == 1
    for col in (0, 1):
        prob_params_norm[is_pm, col] = normalize_energy(c.prob_params[is_pm, col], e_chan[is_pm])
    yield_params_norm = c.yield_params.copy()
    is_ya = c.yield_model == 1
    yield_params_norm[is_ya, 0] = normalize_energy(c.yield_params[is_ya, 0], e_chan[is_ya])
    return prob_params_norm, yield_params_norm


def _meta_flags(spec: RulesSpec, c: _EventColumns) -> np.ndarray:
    """The meta flags m (E, 17), columns in META_FLAGS order."""
    effects = [ev.effect for ev in spec.events]
    proj_names = [ev.projectile for ev in spec.events]
    flags = {
        "dep": ~c.is_primary,
        "ion": np.array([p in ION_PROJECTILES for p in proj_names]) & c.is_primary,
        "neutral": np.array([p in NEUTRAL_PROJECTILES for p in proj_names]) & c.is_primary,
        "angle_P": c.angle_kind == 1,
        "angle_C": c.angle_kind == 2,
        "energy": c.prob_model == 1,
        "yamamura": c.yield_model == 1,
        "react": np.array([x == "react" for x in effects]),
        "etch": np.array([x == "etch" for x in effects]),
        "sputter": np.array([x == "sputter" for x in effects]),
        "deposit": np.array([x == "deposit" for x in effects]),
        "src": c.w_src.sum(1) > 0,
        "sink": c.w_sink.sum(1) > 0,
        "target_resist": np.array([ev.target == "Resist" for ev in spec.events]),
        "target_chlor": np.array([ev.target in CHLORINATED_TARGETS for ev in spec.events]),
        "group_physical": c.group == 0,
        "group_both": c.group == 2,
    }
    return np.stack([np.asarray(flags[k], dtype=float) for k in META_FLAGS], axis=1)  # (E, 17)


def _r_bar(c: _EventColumns, prob_params_norm: np.ndarray, yield_params_norm: np.ndarray, mu_p: np.ndarray,
           mu_y: np.ndarray) -> np.ndarray:
    """The normalized parameters r_bar (E, 18); mu_p, mu_y (E,): the law codes (0 none, 1 const, 2 law)."""
    n_ev = len(c.names)
    is_pm, is_ya = c.prob_model == 1, c.yield_model == 1
    r_bar = np.zeros((n_ev, 18))
    r_bar[:, 0] = c.group / 2.0
    r_bar[:, 1] = c.projectile / (N_SPECIES - 1)
    r_bar[:, 2] = c.target / (len(TARGETS) - 1)
    r_bar[:, 3] = (~c.is_primary).astype(float)
    r_bar[:, 4] = mu_p / 2.0
    r_bar[:, 5] = np.where(c.prob_model == 0, c.prob_params[:, 0], 0.0)
    r_bar[:, 6] = np.where(is_pm, prob_params_norm[:, 0], 0.0)
    r_bar[:, 7] = np.where(is_pm, prob_params_norm[:, 1], 0.0)
    r_bar[:, 8] = np.where(is_pm, c.prob_params[:, 2], 0.0)
    r_bar[:, 9] = np.where(is_pm, c.prob_params[:, 3], 0.0)
    r_bar[:, 10] = c.angle_kind / 2.0
    r_bar[:, 11] = mu_y / 2.0
    r_bar[:, 12] = np.where(c.yield_model == 0, c.yield_params[:, 0], 0.0)
    r_bar[:, 13] = np.where(is_ya, yield_params_norm[:, 0], 0.0)
    r_bar[:, 14] = np.where(is_ya, np.cos(np.deg2rad(c.yield_params[:, 1])), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_ratio = np.log(c.yield_params[:, 2] / np.maximum(c.yield_params[:, 3], 1e-12))
    r_bar[:, 15] = np.where(is_ya, log_ratio, 0.0)
    r_bar[:, 16] = (c.dep_species + 1) / N_SPECIES
    r_bar[:, 17] = c.s_dep
    return r_bar


def _mechanisms(c: _EventColumns, meta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(alpha0 (E, 3) family prior, r_mech (E, 3) mechanism evidence) from the family and the meta flags."""
    n_ev = len(c.names)
    alpha0 = np.full((n_ev, N_FAMILIES), EPS_ALPHA)
    alpha0[np.arange(n_ev), c.group] = 1.0 - (N_FAMILIES - 1) * EPS_ALPHA
    m = {k: meta[:, i] for i, k in enumerate(META_FLAGS)}
    r_phys = np.maximum.reduce([m["angle_P"], m["yamamura"], m["sputter"], m["ion"] * m["group_physical"]])
    r_chem = np.maximum.reduce([m["angle_C"], m["react"], m["neutral"], m["dep"]])
    r_coup = np.maximum.reduce([m["group_both"], m["src"], m["sink"], m["ion"] * m["target_chlor"]])
    r_mech = np.stack([r_phys, r_chem, r_coup], axis=1)
    return alpha0, r_mech


def compile_rules(spec: RulesSpec) -> RuleTensors:
    """Compile a validated spec into ``RuleTensors`` (pure; see the module docstring for the layout)."""
    c = _event_columns(spec)
    n_ev = len(c.names)
    prob_params_norm, yield_params_norm = _normalized_energies(c)
    R = build_R(c.group, c.projectile, c.target, c.is_primary, c.ctrl_idx, c.prob_model, c.prob_params,
                c.yield_model, c.yield_params, c.dep_species, c.s_dep)  # (E, 22)
    meta = _meta_flags(spec, c)  # (E, 17)
    mu_p = np.where(c.is_primary, c.prob_model + 1, 0)  # 0 none, 1 const, 2 probModel
    mu_y = np.where(c.is_primary, c.yield_model + 1, 0)  # 0 none, 1 const, 2 yamamura
    r_bar = _r_bar(c, prob_params_norm, yield_params_norm, mu_p, mu_y)  # (E, 18)
    phi = np.concatenate([r_bar, meta], axis=1)  # (E, 35)
    psi = np.stack(  # (E, 7)
        [(c.group + 1) / 3.0, c.projectile / 7.0, c.target / 4.0, (~c.is_primary).astype(float),
         mu_p / 2.0, mu_y / 2.0, c.angle_kind / 2.0],
        axis=1,
    )  # fmt: skip
    alpha0, r_mech = _mechanisms(c, meta)
    text = canonical_text(spec)
    assert all(math.isfinite(x) for x in phi.ravel()), "non-finite descriptor"
    return RuleTensors(
        names=c.names, R=R, phi=phi, psi=psi, alpha0=alpha0, r_mech=r_mech, w_src=c.w_src, w_sink=c.w_sink,
        s_dep=c.s_dep, src_is_yield=c.src_is_yield, is_primary=c.is_primary, ctrl_idx=c.ctrl_idx,
        projectile=c.projectile, target=c.target, group=c.group, prob_model=c.prob_model,
        prob_params=c.prob_params, angle_kind=c.angle_kind, yield_model=c.yield_model,
        yield_params=c.yield_params, prob_params_norm=prob_params_norm, yield_params_norm=yield_params_norm,
        sha256=hashlib.sha256(text.encode("utf-8")).hexdigest(), source_text=text,
        event_mask=np.ones(n_ev),
    )  # fmt: skip
