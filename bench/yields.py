"""Flat-surface yields of the simulator, next to published values (``nemsim bench yields``).

Monoenergetic projectiles are fired one at a time (``kernels.fly``, the simulator's own transport and
surface-event code) at a flat, periodic slab whose top layer is in a chosen surface state; the slab is
restored before every projectile, so each number is a first-impact yield on a fresh surface (reflected
projectiles fly on and may hit again). One simulated particle stands for 1 / w real ones (``config`` module
docstring), so the yield per real ion is

    Y = flux_scale * (units removed per simulated projectile)

independently of the capacity. Cases:
  * ``cl+_on_clsat``: Cl+ on Cl-saturated Si (top layer SiCl2) vs energy and angle: ion-enhanced etching;
  * ``ar+_on_si``: Ar+ on bare Si vs energy (normal incidence): physical sputtering;
  * ``cl+_on_resist``: Cl+ on resist vs incidence angle: the mask's angular sputter yield (faceting);
  * ``cl_neutral``: thermal Cl on bare Si and on SiCl3: neutral-only etch probability.

Published values (``LITERATURE``; every row names its source) are compared as the ratio sim / literature
and whether it lies within a factor 2:
  * Laegreid & Wehner, J. Appl. Phys. 32, 365 (1961): Ar+ sputtering yield of Si at normal incidence,
    100-600 eV (the magnitudes of the Yamamura & Tawara 1996 fits);
  * Chang, Arnold, Sawin et al., J. Vac. Sci. Technol. A (1997), Chang & Sawin (1997-98): the ion-enhanced
    yield of Cl+ / Cl2+ on chlorinated Si scales as sqrt(E) - sqrt(E_th) and is flat in angle to ~45 deg,
    unlike sputtering; compared as shapes only (no verified absolute value);
  * Ogryzlo, Ibbotson, Flamm & Mucha, J. Appl. Phys. 67, 3115 (1990): thermal Cl etches undoped Si very
    slowly at room temperature (shape only).
The simulator's energy law p0 ((E - E_th)/(E_ref - E_th))^n with n = 0.5 has the published sqrt shape; the
absolute scale is set by p0 and flux_scale, which is what the table checks. ``--set
sputter_calibration=laegreid_wehner`` compares the refitted Ar+ -> Si rule (``nemsim.sim.calibration``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nemsim.rules.compile import RuleTensors
from nemsim.rules.vocab import PROJECTILES, TARGETS
from nemsim.sim import kernels as K
from nemsim.sim.config import SimConfig
from nemsim.sim.events import build_event_tables

ENERGIES_EV = (50.0, 100.0, 200.0, 300.0, 500.0)
AR_ENERGIES_EV = (50.0, 100.0, 200.0, 300.0, 600.0)  # the Laegreid & Wehner energies
ANGLES_DEG = (0.0, 30.0, 45.0, 60.0, 75.0)
ANGLE_ENERGY_EV = 300.0

# (case, x kind, x, reference value, source); ``None`` = the source is compared as a shape (its text).
_LW = "Laegreid & Wehner 1961 (Ar+ -> Si, normal incidence)"
LITERATURE: tuple[tuple[str, str, float, float | None, str], ...] = (
    ("ar+_on_si", "energy_ev", 100.0, 0.07, _LW),
    ("ar+_on_si", "energy_ev", 200.0, 0.18, _LW),
    ("ar+_on_si", "energy_ev", 300.0, 0.31, _LW),
    ("ar+_on_si", "energy_ev", 600.0, 0.53, _LW),
    ("cl+_on_clsat", "energy_ev", 100.0, None, "Chang, Arnold, Sawin et al. 1997: Y ~ sqrt(E) - sqrt(E_th)"),
    ("cl+_on_clsat", "angle_deg", 60.0, None, "Chang & Sawin: flat to ~45 deg, falling beyond"),
    ("cl_neutral", "state", 0.0, None, "Ogryzlo et al. 1990: very slow spontaneous etch of undoped Si"),
)


@dataclass(frozen=True)
class YieldPoint:
    """One measured point: case, the swept variable and its value, Si (or resist) removed per projectile."""

    case: str
    x_kind: str  # "energy_ev" | "angle_deg" | "state"
    x: float
    yield_per_ion: float
    stderr: float
    n: int


def _slab(surface: str, cap: int, rcap: int, n: int = 12, nz: int = 10, top: int = 6) -> np.ndarray:
    """(n, n, nz, 5) int32 flat slab: Si below ``top``, the top layer in state ``surface``."""
    if surface not in TARGETS:
        raise ValueError(f"unknown surface state {surface!r}; expected one of {TARGETS}")
    mat = np.zeros((n, n, nz, len(TARGETS)), dtype=np.int32)
    mat[:, :, : top - 1, TARGETS.index("Si")] = cap
    q = TARGETS.index(surface)
    mat[:, :, top - 1, q] = rcap if surface == "Resist" else cap
    return mat


def fire(
    rules: RuleTensors, config: SimConfig, projectile: str, surface: str, energy_ev: float,
    angle_deg: float, n: int, seed: int,
) -> tuple[float, float]:  # fmt: skip
    """Mean and standard error of units removed per projectile on a fresh flat ``surface`` (module doc).

    Counts every removed unit of any species (Si-class or resist), times ``flux_scale`` (Si-class units;
    resist units are scaled by the same factor, i.e. reported in Si-unit equivalents).
    """
    cfg = config
    cap = int(cfg.capacity or 16)  # small's capacity; the yield per real ion does not depend on it
    rcap = int(cfg.resist_capacity or max(1, round(cap * cfg.resist_density_ratio)))
    tables = build_event_tables(rules, cfg)
    s = PROJECTILES.index(projectile)
    mat0 = _slab(surface, cap, rcap)
    fill0 = (mat0[..., :4].sum(-1) / cap + mat0[..., 4] / rcap).astype(np.float64)
    nx, ny, nz = fill0.shape
    th = math.radians(angle_deg)
    d = (math.sin(th), 0.0, -math.cos(th))
    queue = np.zeros((4096, 8))
    pbuf = np.zeros(tables.max_channels)
    events = np.zeros(len(tables.action), dtype=np.int64)
    tab = tables.kernel_tables()
    prm = K.transport_params(cfg, cap, rcap)._replace(weight=1.0)  # one real projectile per flight
    rng = np.random.default_rng(seed)
    removed = np.empty(n)
    K.seed_rng(int(rng.integers(0, 2**31)))
    for i in range(n):
        mat = mat0.copy()
        fill = fill0.copy()
        counters = np.zeros(K.N_COUNTERS, dtype=np.int64)
        x0, y0 = rng.random() * nx, rng.random() * ny
        buf = K.WorkBuffers(queue, pbuf, counters, events)
        K.fly(s, energy_ev, x0, y0, nz - 1e-9, *d, mat, fill, tab, prm, buf, 0, 0)
        removed[i] = counters[K.C_REMOVED : K.C_REMOVED + 5].sum()
    y = cfg.flux_scale * removed
    return float(y.mean()), float(y.std(ddof=1) / math.sqrt(n)) if n > 1 else 0.0


def measure_yields(rules: RuleTensors, config: SimConfig, n: int = 2000, seed: int = 0) -> list[YieldPoint]:
    """All cases of the module docstring; n projectiles per point (neutrals: 50 n)."""
    out: list[YieldPoint] = []

    def add(case: str, kind: str, x: float, proj: str, surf: str, e: float, a: float, count: int) -> None:
        m, se = fire(rules, config, proj, surf, e, a, count, seed + len(out))
        out.append(YieldPoint(case, kind, x, m, se, count))

    for e in ENERGIES_EV:
        add("cl+_on_clsat", "energy_ev", e, "Cl+", "SiCl2", e, 0.0, n)
    for a in ANGLES_DEG:
        add("cl+_on_clsat", "angle_deg", a, "Cl+", "SiCl2", ANGLE_ENERGY_EV, a, n)
    for e in AR_ENERGIES_EV:
        add("ar+_on_si", "energy_ev", e, "Ar+", "Si", e, 0.0, n)
    for a in ANGLES_DEG:
        add("cl+_on_resist", "angle_deg", a, "Cl+", "Resist", ANGLE_ENERGY_EV, a, n)
    e_th = config.neutral_energy_ev
    add("cl_neutral", "state", 0.0, "Cl", "Si", e_th, 0.0, 50 * n)
    add("cl_neutral", "state", 3.0, "Cl", "SiCl3", e_th, 0.0, 50 * n)
    return out


def compare(points: list[YieldPoint]) -> list[dict]:
    """Rows of the comparison table: every LITERATURE row with the matching simulated point."""
    rows = []
    for case, kind, x, ref, source in LITERATURE:
        sim = [p for p in points if p.case == case and p.x_kind == kind and p.x == x]
        y = sim[0].yield_per_ion if sim else float("nan")
        ratio = y / ref if (ref and sim) else None
        rows.append(
            {
                "case": case, kind: x, "sim": y, "literature": ref, "ratio": ratio,
                "within_factor_2": None if ratio is None else bool(0.5 <= ratio <= 2.0), "source": source,
            }
        )  # fmt: skip
    return rows


def to_markdown(points: list[YieldPoint], rows: list[dict]) -> str:
    """The measured points and the comparison as markdown tables."""
    state_names = {0.0: "bare Si", 3.0: "SiCl3-saturated"}
    lines = ["| case | variable | value | yield per projectile | stderr | n |", "|---|---|---|---|---|---|"]
    for p in points:
        val = state_names.get(p.x, p.x) if p.x_kind == "state" else f"{p.x:g}"
        lines.append(f"| {p.case} | {p.x_kind} | {val} | {p.yield_per_ion:.4g} | {p.stderr:.2g} | {p.n} |")
    lines += ["", "| case | point | sim | literature | sim / lit | source |", "|---|---|---|---|---|---|"]
    for r in rows:
        key = next(k for k in r if k in ("energy_ev", "angle_deg", "state"))
        lit = "shape only" if r["literature"] is None else f"{r['literature']:.3g}"
        ratio = "" if r["ratio"] is None else f"{r['ratio']:.2f}"
        lines.append(f"| {r['case']} | {key}={r[key]:g} | {r['sim']:.4g} | {lit} | {ratio} | {r['source']} |")
    return "\n".join(lines) + "\n"
