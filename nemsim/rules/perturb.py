"""Perturbed Event Rules Libraries for the robustness study ([supp_rule_robustness]).

Pure seeded functions (``rng = np.random.default_rng(seed)``; same seed -> same library):
  * ``rate_yield_noise(spec, seed)`` -> RulesSpec: every positive continuous rate/yield parameter
    (p_const, E_th, E_ref, p0, n, Y_const, yield E_th, theta_max, Y_max, Y0, p_stick) is multiplied by
    U(0.7, 1.3), drawn in event order then in the parameter order of ``schema``; then clipped to its valid
    range (probabilities to [0, 1], theta_max to [0.1, 89.9] deg, E_ref to > E_th). Product coefficients,
    models, bindings and groups are unchanged. The result is recompiled, so it has its own sha256.
  * ``mechanism_shuffle(tensors, seed, k=12)``: k events drawn without replacement get their dominant prior
    entry moved to a different family (drawn uniformly from the other two); rows stay 0.90/0.05/0.05.
  * ``event_drop(tensors, seed, k=12)``: k events drawn without replacement get ``event_mask = 0``; the
    kinetics zero their intensities before the Product Pool, so they feed no deposition event.
  * ``structure_only(tensors, seed)``: the paper replaces descriptors and event parameters by fixed random
    embeddings, the prior by a uniform one, and removes product/dependency metadata. Our choice for the
    parts the paper leaves open: phi ~ U(0,1)^(E x 35), psi ~ U(0,1)^(E x 7), alpha0 = 1/3,
    r_mech ~ Bernoulli(0.5) (keeps the MAC rule-correction path active but meaningless); every event becomes
    a primary constant-probability, unit-yield event with p ~ U(0,1) bound to one flux control drawn
    uniformly from the four flux channels (no angle/energy binding); no products, sinks or sticking; group,
    projectile and target ids are drawn uniformly.
Tensor-level perturbations keep ``source_text`` (the unperturbed library) and set
``perturbation = "<kind>(seed=<seed>)"`` and ``sha256 = SHA-256("<base sha>:<kind>:seed=<seed>")``.
"""

from __future__ import annotations

import hashlib
from typing import Any, Literal

import numpy as np

from nemsim.rules.compile import EPS_ALPHA, RuleTensors, build_R, compile_rules
from nemsim.rules.schema import RulesSpec, canonical_text, parse_rules
from nemsim.rules.vocab import N_FAMILIES, N_SPECIES, TARGETS

__all__ = [
    "PERTURBATION_KINDS",
    "event_drop",
    "mechanism_shuffle",
    "perturb",
    "rate_yield_noise",
    "structure_only",
]

PerturbationKind = Literal["none", "structure-only", "mechanism-shuffle", "event-drop", "rate-noise"]
PERTURBATION_KINDS: tuple[str, ...] = (
    "none", "structure-only", "mechanism-shuffle", "event-drop", "rate-noise"
)

_PROB_KEYS = ("p_const", "E_th", "E_ref", "p0", "n")
_YIELD_KEYS = ("Y_const", "E_th", "theta_max", "Y_max", "Y0")
_UNIT_INTERVAL = {"p_const", "p0", "p_stick"}


def _tag(tensors: RuleTensors, kind: str, seed: int) -> dict:
    sha = hashlib.sha256(f"{tensors.sha256}:{kind}:seed={seed}".encode()).hexdigest()
    return {"sha256": sha, "perturbation": f"{kind}(seed={seed})"}


def rate_yield_noise(spec: RulesSpec, seed: int, low: float = 0.7, high: float = 1.3) -> RulesSpec:
    """Multiply the continuous rate/yield parameters by U(low, high), clipped to valid ranges."""
    rng = np.random.default_rng(seed)

    def noisy(key: str, value: Any) -> float:
        v = float(value) * float(rng.uniform(low, high))
        if key in _UNIT_INTERVAL:
            v = min(max(v, 0.0), 1.0)
        elif key == "theta_max":
            v = min(max(v, 0.1), 89.9)
        return max(v, 0.0)

    events = []
    for ev in spec.events:
        upd: dict = {}
        if ev.prob_params is not None:
            pp: dict[str, Any] = dict(ev.prob_params)
            for key in _PROB_KEYS:
                if key in pp:
                    pp[key] = noisy(key, pp[key])
            if "E_ref" in pp and pp["E_ref"] <= pp["E_th"]:
                pp["E_ref"] = pp["E_th"] * 1.01 + 1e-3
            upd["prob_params"] = pp
        if ev.yield_params is not None:
            yp = dict(ev.yield_params)
            for key in _YIELD_KEYS:
                if key in yp:
                    yp[key] = noisy(key, yp[key])
            upd["yield_params"] = yp
        if ev.dep_params is not None:
            dp = dict(ev.dep_params)
            dp["p_stick"] = noisy("p_stick", dp["p_stick"])
            upd["dep_params"] = dp
        events.append(ev.model_copy(update=upd))
    out = spec.model_copy(update={"events": events})
    # round trip through the validator so a perturbed library is a valid library
    return parse_rules(canonical_text(out))


def mechanism_shuffle(tensors: RuleTensors, seed: int, k: int = 12) -> RuleTensors:
    """Move the dominant prior family of k random events to a different family."""
    rng = np.random.default_rng(seed)
    n_ev = tensors.n_events
    chosen = np.sort(rng.choice(n_ev, size=min(k, n_ev), replace=False))
    alpha0 = tensors.alpha0.copy()
    for e in chosen:
        dom = int(np.argmax(alpha0[e]))
        others = [m for m in range(N_FAMILIES) if m != dom]
        new = others[int(rng.integers(len(others)))]
        alpha0[e] = EPS_ALPHA
        alpha0[e, new] = 1.0 - (N_FAMILIES - 1) * EPS_ALPHA
    return tensors.replace(alpha0=alpha0, **_tag(tensors, "mechanism-shuffle", seed))


def event_drop(tensors: RuleTensors, seed: int, k: int = 12) -> RuleTensors:
    """Deactivate k random events (event_mask = 0)."""
    rng = np.random.default_rng(seed)
    n_ev = tensors.n_events
    chosen = rng.choice(n_ev, size=min(k, n_ev), replace=False)
    mask = tensors.event_mask.copy()
    mask[chosen] = 0.0
    return tensors.replace(event_mask=mask, **_tag(tensors, "event-drop", seed))


def structure_only(tensors: RuleTensors, seed: int) -> RuleTensors:
    """Same shapes and topology, no physical/chemical semantics (see the module docstring)."""
    from nemsim.controls import CONTROL_NAMES

    rng = np.random.default_rng(seed)
    n_ev = tensors.n_events
    flux_channels = np.array([i for i, n in enumerate(CONTROL_NAMES) if n.startswith("flux_")])
    phi = rng.uniform(0.0, 1.0, size=tensors.phi.shape)
    psi = rng.uniform(0.0, 1.0, size=tensors.psi.shape)
    r_mech = (rng.uniform(size=tensors.r_mech.shape) < 0.5).astype(float)
    p_rand = rng.uniform(0.0, 1.0, size=n_ev)
    flux = flux_channels[rng.integers(len(flux_channels), size=n_ev)]
    group = rng.integers(N_FAMILIES, size=n_ev)
    projectile = rng.integers(N_SPECIES, size=n_ev)
    target = rng.integers(len(TARGETS), size=n_ev)

    is_primary = np.ones(n_ev, dtype=bool)
    ctrl_idx = np.full((n_ev, 4), -1, dtype=np.int64)
    ctrl_idx[:, 0] = flux
    prob_model = np.zeros(n_ev, dtype=np.int64)
    prob_params = np.zeros((n_ev, 5))
    prob_params[:, 0] = p_rand
    yield_model = np.zeros(n_ev, dtype=np.int64)
    yield_params = np.zeros((n_ev, 4))
    yield_params[:, 0] = 1.0
    s_dep = np.zeros(n_ev)
    R = build_R(group, projectile, target, is_primary, ctrl_idx, prob_model, prob_params, yield_model,
                yield_params, np.full(n_ev, -1), s_dep)  # fmt: skip
    return tensors.replace(
        R=R, phi=phi, psi=psi, alpha0=np.full((n_ev, N_FAMILIES), 1.0 / N_FAMILIES), r_mech=r_mech,
        w_src=np.zeros_like(tensors.w_src), w_sink=np.zeros_like(tensors.w_sink), s_dep=s_dep,
        src_is_yield=np.zeros_like(tensors.src_is_yield), is_primary=is_primary, ctrl_idx=ctrl_idx,
        projectile=projectile, target=target, group=group, prob_model=prob_model, prob_params=prob_params,
        angle_kind=np.zeros(n_ev, dtype=np.int64), yield_model=yield_model, yield_params=yield_params,
        prob_params_norm=prob_params.copy(), yield_params_norm=yield_params.copy(),
        **_tag(tensors, "structure-only", seed),
    )  # fmt: skip


def perturb(rules: RulesSpec | RuleTensors, kind: str, seed: int) -> RuleTensors:
    """Compile ``rules`` with perturbation ``kind`` (one of PERTURBATION_KINDS) and ``seed``."""
    if kind not in PERTURBATION_KINDS:
        raise ValueError(f"unknown perturbation kind {kind!r}; expected one of {PERTURBATION_KINDS}")
    if isinstance(rules, RuleTensors):
        if rules.perturbation != "none":
            raise ValueError(f"rules are already perturbed ({rules.perturbation}); pass the base library")
        spec, tensors = None, rules
    else:
        spec, tensors = rules, compile_rules(rules)
    if kind == "none":
        return tensors
    if kind == "rate-noise":
        spec = spec if spec is not None else parse_rules(tensors.source_text)
        out = compile_rules(rate_yield_noise(spec, seed))
        return out.replace(perturbation=f"rate-noise(seed={seed})")
    if kind == "structure-only":
        return structure_only(tensors, seed)
    if kind == "mechanism-shuffle":
        return mechanism_shuffle(tensors, seed)
    return event_drop(tensors, seed)
