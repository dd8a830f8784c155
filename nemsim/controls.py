"""Process-control vocabulary, transforms, normalization, OOD coordinate and the LHS design.

The 14 controls in the order of the paper's control-space table (tab:supp_control_space):
fluxes of Ar+, Cl+, Cl2+, Cl (mol m^-2 s^-1, log-sampled), cosine-power exponents of Cl, Cl+, Cl2+, Ar+
(bounded integers) and the mean / standard deviation of the Cl+, Cl2+, Ar+ energy distributions (eV, linear).
The paper's equation eq:supp_angle_controls lists the angles in another order; the table (with indices) is
authoritative.

Representation ([supp_representation]):
  * transform  eq:supp_control_transformation  u~ = log10(u + eps_u) for fluxes (eps_u = 1e-12), else u;
  * normalize  eq:supp_control_normalization   u = 2 (u~ - u~min) / (u~max - u~min) - 1 with the fixed
    bounds of the table (eq:supp_flux_control_bounds), no clipping;
  * OOD unit coordinate eq:supp_ood_unit_coordinate  q = (u~ - u~min) / (u~max - u~min) = (u + 1) / 2.

Design ([supp_data_generation], eq:supp_lhs_design, eq:supp_control_mapping): Xi = LHS(500, 14), seed 42,
mapped column-wise to physical units.

Choices where the paper is silent:
  * Sampler: the classic scrambled LHS of ``scipy.stats.qmc.LatinHypercube(d=14, seed=42).random(500)``,
    re-implemented in numpy (``default_rng(42)``) so it does not depend on scipy's seed keyword; of the
    samplers tried it is the one that reproduces the paper's OOD-Joint test composition (14, 15, 13, 11)
    (tests/data/test_splits.py).
  * Log mapping is the exact inverse of the normalization, u = 10^(u~min + xi (u~max - u~min)) - eps_u, so
    the OOD coordinate of a design row equals its LHS coordinate (q = xi).
  * Bounded integers: u = min(low + floor(xi (high - low + 1)), high), every integer equally likely.
  * Physically admissible limits (``phys_min`` / ``phys_max``, used to reject impossible inputs): every
    control >= 0, no upper limit. Values admissible but outside the design range [low, high] are
    extrapolation.
"""

from __future__ import annotations

import csv
import difflib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np

EPS_U = 1e-12  # epsilon of the flux log transform, eq:supp_control_transformation
DESIGN_N = 500  # N_control, eq:supp_lhs_design
# the largest design drawn: about 60 MB of working arrays, and far more cases than any data set simulates
MAX_DESIGN_N = 100_000
DESIGN_SEED = 42
LHS_SAMPLER = "scipy.stats.qmc.LatinHypercube(d=14, seed=42).random(500)  (numpy re-implementation)"

ControlKind = Literal["log", "int", "linear"]


@dataclass(frozen=True)
class ControlSpec:
    """One process control. ``low``/``high``: configured design range (tab:supp_control_space)."""

    name: str
    unit: str
    kind: ControlKind  # sampling transformation: "log" | "int" | "linear"
    low: float
    high: float
    phys_min: float = 0.0  # physically admissible minimum
    phys_max: float = math.inf  # physically admissible maximum
    label: str = ""  # human-readable symbol
    description: str = ""  # what the control means, for help texts and the service schema

    @property
    def t_low(self) -> float:
        """Transformed lower bound u~min (eq:supp_flux_control_bounds)."""
        return math.log10(self.low + EPS_U) if self.kind == "log" else float(self.low)

    @property
    def t_high(self) -> float:
        """Transformed upper bound u~max."""
        return math.log10(self.high + EPS_U) if self.kind == "log" else float(self.high)


_FLUX = "mol m^-2 s^-1"


def _flux(species: str) -> str:
    return f"flux of {species} arriving at the wafer"


def _angle(species: str) -> str:
    return (f"angular spread of {species}: the dimensionless exponent m of the cos^m(theta) distribution of "
            "the polar angle from the vertical at launch (larger m = more collimated, closer to vertical)")


CONTROL_SPECS: tuple[ControlSpec, ...] = (
    ControlSpec("flux_ar_plus", _FLUX, "log", 1e-4, 7e-3, label="Gamma(Ar+)", description=_flux("Ar+ ions")),
    ControlSpec("flux_cl_plus", _FLUX, "log", 1e-4, 7e-3, label="Gamma(Cl+)", description=_flux("Cl+ ions")),
    ControlSpec("flux_cl2_plus", _FLUX, "log", 1e-6, 2e-4, label="Gamma(Cl2+)",
                description=_flux("Cl2+ ions")),
    ControlSpec("flux_cl", _FLUX, "log", 1e-3, 2e-2, label="Gamma(Cl)", description=_flux("neutral Cl")),
    ControlSpec("angle_cl", "1", "int", 0, 20, label="m(Cl)", description=_angle("neutral Cl")),
    ControlSpec("angle_cl_plus", "1", "int", 50, 3000, label="m(Cl+)", description=_angle("Cl+ ions")),
    ControlSpec("angle_cl2_plus", "1", "int", 50, 3000, label="m(Cl2+)", description=_angle("Cl2+ ions")),
    ControlSpec("angle_ar_plus", "1", "int", 50, 3000, label="m(Ar+)", description=_angle("Ar+ ions")),
    ControlSpec("energy_mean_cl_plus", "eV", "linear", 160.0, 500.0, label="mu(Cl+)",
                description="mean energy of the Cl+ ions"),
    ControlSpec("energy_std_cl_plus", "eV", "linear", 5.0, 10.0, label="sigma(Cl+)",
                description="standard deviation of the Cl+ ion energy"),
    ControlSpec("energy_mean_cl2_plus", "eV", "linear", 160.0, 500.0, label="mu(Cl2+)",
                description="mean energy of the Cl2+ ions"),
    ControlSpec("energy_std_cl2_plus", "eV", "linear", 5.0, 15.0, label="sigma(Cl2+)",
                description="standard deviation of the Cl2+ ion energy"),
    ControlSpec("energy_mean_ar_plus", "eV", "linear", 160.0, 500.0, label="mu(Ar+)",
                description="mean energy of the Ar+ ions"),
    ControlSpec("energy_std_ar_plus", "eV", "linear", 5.0, 15.0, label="sigma(Ar+)",
                description="standard deviation of the Ar+ ion energy"),
)
CONTROL_NAMES: tuple[str, ...] = tuple(s.name for s in CONTROL_SPECS)
N_CONTROLS = len(CONTROL_SPECS)  # 14
CONTROL_INDEX: dict[str, int] = {n: i for i, n in enumerate(CONTROL_NAMES)}
# F = {1, 2, 3, 4} in the paper's 1-based numbering
FLUX_INDICES: tuple[int, ...] = tuple(i for i, s in enumerate(CONTROL_SPECS) if s.kind == "log")
INT_INDICES: tuple[int, ...] = tuple(i for i, s in enumerate(CONTROL_SPECS) if s.kind == "int")

ION_ENERGIES = ("energy_mean_cl_plus", "energy_mean_cl2_plus", "energy_mean_ar_plus")
# the four cosine-power exponents: neutral Cl, then the ions
ANGLE_CONTROLS = ("angle_cl", "angle_cl_plus", "angle_cl2_plus", "angle_ar_plus")
# The controls an engineer moves together: each flux alone, the three ion energies, the three ion angular
# exponents, the neutral angular exponent. The physics benchmark sweeps each group from the median recipe;
# ``pair_design`` moves one group per pair.
CONTROL_GROUPS: dict[str, tuple[str, ...]] = {
    "flux_cl_plus": ("flux_cl_plus",),
    "flux_ar_plus": ("flux_ar_plus",),
    "flux_cl2_plus": ("flux_cl2_plus",),
    "flux_cl": ("flux_cl",),
    "ion_energy": ION_ENERGIES,
    "ion_angle": ("angle_cl_plus", "angle_cl2_plus", "angle_ar_plus"),
    "neutral_angle": ("angle_cl",),
}

# Fixed bounds as arrays (14,)
LOW = np.array([s.low for s in CONTROL_SPECS], dtype=np.float64)
HIGH = np.array([s.high for s in CONTROL_SPECS], dtype=np.float64)
T_LOW = np.array([s.t_low for s in CONTROL_SPECS], dtype=np.float64)
T_HIGH = np.array([s.t_high for s in CONTROL_SPECS], dtype=np.float64)
PHYS_MIN = np.array([s.phys_min for s in CONTROL_SPECS], dtype=np.float64)
PHYS_MAX = np.array([s.phys_max for s in CONTROL_SPECS], dtype=np.float64)
IS_LOG = np.array([s.kind == "log" for s in CONTROL_SPECS])

A = TypeVar("A")  # np.ndarray or torch.Tensor


def closest_name(name: str, choices: tuple[str, ...] = CONTROL_NAMES) -> str | None:
    """The name among ``choices`` closest to a misspelt one (``difflib`` similarity >= 0.6, compared in
    lower case with '-' and ' ' read as '_'), or None when none is close."""
    key = str(name).strip().lower().replace("-", "_").replace(" ", "_")
    found = difflib.get_close_matches(key, [c.lower() for c in choices], n=1, cutoff=0.6)
    return next(c for c in choices if c.lower() == found[0]) if found else None


def unknown_control(name: str, extra: tuple[str, ...] = ()) -> str:
    """The message for an unknown control name: the closest valid name ("did you mean ...") when one is
    close, else the list of the controls; ``extra``: other names valid where the name was given."""
    close = closest_name(name, CONTROL_NAMES + extra)
    if close is not None:
        return f"unknown control {name!r}; did you mean {close!r}?"
    return f"unknown control {name!r}; expected one of {list(CONTROL_NAMES + extra)}"


def control_index(name: str) -> int:
    """Column index of a control; ValueError naming the closest valid name (``unknown_control``)."""
    try:
        return CONTROL_INDEX[name]
    except KeyError:
        raise ValueError(unknown_control(name)) from None


def _is_torch(x: object) -> bool:
    return type(x).__module__.startswith("torch")


def _check_last_dim(x: object) -> None:
    shape = tuple(x.shape)  # type: ignore[attr-defined]
    if not shape or shape[-1] != N_CONTROLS:
        raise ValueError(f"controls must have shape (..., {N_CONTROLS}); got {shape}")


def _consts(x: object, *arrays: np.ndarray) -> list:
    """The given (14,) constant arrays as numpy float64 or as torch tensors matching x."""
    if _is_torch(x):
        import torch

        return [torch.as_tensor(a, dtype=x.dtype, device=x.device) for a in arrays]  # type: ignore[attr-defined]
    return list(arrays)


def transform(raw: A) -> A:
    """eq:supp_control_transformation: log10(u + eps_u) for the fluxes, identity otherwise. (..., 14)."""
    _check_last_dim(raw)
    x: Any = raw  # numpy array or torch tensor; A keeps the caller's type in the signature
    if _is_torch(x):
        import torch

        x = x if x.is_floating_point() else x.double()
        is_log = torch.as_tensor(IS_LOG, device=x.device)
        return torch.where(is_log, torch.log10(x + EPS_U), x)  # type: ignore[return-value]
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        logged = np.log10(np.where(IS_LOG, x, 0.0) + EPS_U)
    return np.where(IS_LOG, logged, x)  # type: ignore[return-value]


def inverse_transform(transformed: A) -> A:
    """Inverse of ``transform``: 10**u~ - eps_u for the fluxes. (..., 14)."""
    _check_last_dim(transformed)
    x: Any = transformed
    if _is_torch(x):
        import torch

        is_log = torch.as_tensor(IS_LOG, device=x.device)
        return torch.where(is_log, torch.pow(10.0, x) - EPS_U, x)  # type: ignore[return-value]
    t = np.asarray(x, dtype=np.float64)
    return np.where(IS_LOG, np.power(10.0, np.where(IS_LOG, t, 0.0)) - EPS_U, t)  # type: ignore[return-value]


def normalize(transformed: A) -> A:
    """eq:supp_control_normalization: 2 (u~ - u~min) / (u~max - u~min) - 1, fixed bounds, no clipping."""
    _check_last_dim(transformed)
    lo, hi = _consts(transformed, T_LOW, T_HIGH)
    x: Any = transformed if _is_torch(transformed) else np.asarray(transformed, dtype=np.float64)
    return 2.0 * (x - lo) / (hi - lo) - 1.0


def denormalize(normalized: A) -> A:
    """Inverse of ``normalize``: transformed controls from [-1, 1] coordinates. (..., 14)."""
    _check_last_dim(normalized)
    lo, hi = _consts(normalized, T_LOW, T_HIGH)
    x: Any = normalized if _is_torch(normalized) else np.asarray(normalized, dtype=np.float64)
    return lo + (x + 1.0) * 0.5 * (hi - lo)


def to_normalized(raw: A) -> A:
    """Raw physical controls (..., 14) -> normalized model input (..., 14) (numpy float64 or torch)."""
    return normalize(transform(raw))


def from_normalized(normalized: A) -> A:
    """Normalized controls (..., 14) -> raw physical units. Integer controls are not rounded."""
    return inverse_transform(denormalize(normalized))


def ood_coordinate(raw: np.ndarray, name: str) -> np.ndarray:
    """eq:supp_ood_unit_coordinate: q_j = (u~_j - u~min_j) / (u~max_j - u~min_j) of control ``name``.

    Args:
        raw: (..., 14) raw controls.
    Returns:
        (...,) q (in [0, 1] inside the design range; not clipped).
    """
    j = control_index(name)
    return (np.asarray(to_normalized(raw))[..., j] + 1.0) * 0.5


def from_unit(xi: np.ndarray) -> np.ndarray:
    """eq:supp_control_mapping: unit-hypercube coordinates (N, 14) -> raw controls (N, 14).

    Log and linear controls: inverse of the normalization, so q(u) = xi. Integer controls:
    low + floor(xi (high - low + 1)), capped at high.
    """
    xi = np.asarray(xi, dtype=np.float64)
    _check_last_dim(xi)
    raw = from_normalized(2.0 * xi - 1.0)
    ints = np.minimum(LOW + np.floor(xi * (HIGH - LOW + 1.0)), HIGH)
    is_int = np.array([s.kind == "int" for s in CONTROL_SPECS])
    return np.where(is_int, ints, raw)


def lhs_unit(n: int = DESIGN_N, seed: int = DESIGN_SEED) -> np.ndarray:
    """eq:supp_lhs_design: Xi = LHS(n, 14) in (0, 1)^(n x 14), bit-identical to LHS_SAMPLER.

    Column j holds (pi_j(i) - U_ij) / n with pi_j a random permutation of 1..n and U_ij ~ U[0, 1).
    """
    if not 1 <= n <= MAX_DESIGN_N:
        raise ValueError(f"n must be in 1..{MAX_DESIGN_N} (design size); got {n}")
    rng = np.random.default_rng(seed)
    jitter = rng.uniform(size=(n, N_CONTROLS))  # (n, 14), drawn first, as scipy does
    perms = np.tile(np.arange(1, n + 1), (N_CONTROLS, 1))  # (14, n)
    for j in range(N_CONTROLS):
        rng.shuffle(perms[j, :])
    return (perms.T - jitter) / n


def lhs_design(n: int = DESIGN_N, seed: int = DESIGN_SEED, log_angles: bool = False) -> np.ndarray:
    """The control design in raw physical units, (n, 14) float64; row i is control id i.

    ``log_angles``: the ion angular exponents are uniform in log m over their range instead of uniform in m
    (the same unit coordinates otherwise; rounded to integers). The profile follows the angular spread of a
    species, which goes as 1 / sqrt(m) (``sweep_coordinate``, ``nemsim.model.angle_features``): uniform in
    m, 3.8 % of the recipes have m < 162 for a given ion, where half of the spread's range lies; uniform in
    log m, 28.7 %. Not the paper's design: extra training data for the angular responses."""
    xi = lhs_unit(n, seed)  # (n, 14)
    raw = from_unit(xi)
    if log_angles:
        for j in range(N_CONTROLS):
            if _log_level(j):
                lo, hi = _log_range(j)
                raw[:, j] = np.clip(np.round(np.exp(lo + xi[:, j] * (hi - lo))), LOW[j], HIGH[j])
    return raw


def round_int_controls(raw: np.ndarray) -> np.ndarray:
    """raw (..., 14) with the integer controls (angular exponents) rounded to the nearest integer."""
    out = np.array(raw, dtype=np.float64)
    out[..., list(INT_INDICES)] = np.round(out[..., list(INT_INDICES)])
    return out


def set_group(raw: np.ndarray, names: tuple[str, ...], u: float) -> np.ndarray:
    """raw (14,) with the controls ``names`` set to the normalized value ``u`` (integers not rounded)."""
    at = from_normalized(np.full(N_CONTROLS, float(u)))
    out = np.array(raw, dtype=np.float64)
    for n in names:
        out[CONTROL_INDEX[n]] = at[CONTROL_INDEX[n]]
    return out


def _log_level(j: int) -> bool:
    """Whether control j's sweep level is linear in log m: the ion angular exponents (m from 50 to 3,000)."""
    return CONTROL_SPECS[j].kind == "int" and LOW[j] > 0


def _log_range(j: int) -> tuple[float, float]:
    """(log m_low, log m_high) of a control whose level is linear in log m (``_log_level``)."""
    return math.log(LOW[j]), math.log(HIGH[j])


def sweep_coordinate(raw: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """The level of the controls ``names`` of raw (..., 14) in [-1, 1], one column per name: the normalized
    control, except for the ion angular exponents, whose level is linear in log m (-1 and +1 at the design
    bounds). Why: the angular width of a cos^m distribution goes as 1 / sqrt(m), so the profile responds
    mostly at small m (docs/experiments.md). The neutral exponent (0 to 20) stays
    linear: its depth response spreads over the whole range."""
    cols = [CONTROL_INDEX[n] for n in names]
    x = np.asarray(raw, dtype=np.float64)
    out = np.asarray(to_normalized(x))[..., cols]
    for k, j in enumerate(cols):
        if _log_level(j):
            lo, hi = _log_range(j)
            out[..., k] = 2.0 * (np.log(x[..., j]) - lo) / (hi - lo) - 1.0
    return out


def set_sweep_level(raw: np.ndarray, names: tuple[str, ...], v: float) -> np.ndarray:
    """raw (14,) with the controls ``names`` at level ``v`` of ``sweep_coordinate`` (integers not rounded)."""
    out = set_group(raw, names, v)
    for n in names:
        j = CONTROL_INDEX[n]
        if _log_level(j):
            lo, hi = _log_range(j)
            out[j] = math.exp(lo + (v + 1.0) / 2.0 * (hi - lo))
    return out


def pair_design(n_pairs: int, seed: int, min_move: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Sweep pairs: (2 n_pairs, 14) raw controls and (2 n_pairs,) seed ids, rows (base_i, partner_i).

    Base i is point i of a Latin hypercube of ``n_pairs`` points (seed ``seed``). Its partner moves one
    control group (``CONTROL_GROUPS``, in turn: pair i moves group i mod 7) to one level v of
    ``sweep_coordinate``, drawn uniformly in [-1, 1] at least ``min_move`` away from the mean level of the
    base's group, as a one-at-a-time sweep does; every other control is the base's. For the ion angular
    exponents the level is uniform in log m, not in m: a Latin hypercube, uniform in m, puts few recipes
    where the profile responds (of the 1,500 cases of the seed-43 design, 7 have all three ion exponents
    below 500), and the pairs are to carry the responses.
    Both rows get the seed id of the base (row 2i): simulated with that one seed (``nemsim generate``
    reads the ``seed_id`` column), the pair shares its random numbers, so the simulated difference of the
    pair carries the response to the group with less of the Monte Carlo noise of two independent runs
    (common random numbers; ``nemsim bench pair-noise`` measures how much less).
    Why: a Latin hypercube moves every control at once, and the responses to the angular exponents and the
    neutral flux were missed by every model trained on one (docs/experiments.md); the pairs
    give a training loss on the predicted difference (``TrainConfig.pair_loss_weight``).
    """
    if n_pairs < 1:
        raise ValueError(f"n_pairs must be >= 1, got {n_pairs}")
    if not 0.0 <= min_move <= 1.0:
        raise ValueError(f"min_move must be in [0, 1], got {min_move}")
    bases = lhs_design(n_pairs, seed)  # (P, 14)
    rng = np.random.default_rng([seed, 1])  # the levels: independent of the hypercube's stream
    groups = list(CONTROL_GROUPS.values())
    rows, seed_ids = [], []
    for i, base in enumerate(bases):
        names = groups[i % len(groups)]
        mean = float(np.mean(sweep_coordinate(base, names)))
        v = float(rng.uniform(-1.0, 1.0))
        while abs(v - mean) < min_move:
            v = float(rng.uniform(-1.0, 1.0))
        rows += [base, round_int_controls(set_sweep_level(base, names, v))]
        seed_ids += [2 * i, 2 * i]
    return np.stack(rows), np.array(seed_ids, dtype=np.int64)


def box_corner(signs: np.ndarray) -> np.ndarray:
    """(..., 14) signs (> 0: maximum, else minimum) -> raw controls exactly at the design box's bounds."""
    return np.where(np.asarray(signs) > 0, HIGH, LOW)


HELDOUT_SEED = 2026  # seed of the physics benchmark's fresh held-out recipes (the training design's: 42)
HELDOUT_CORNERS = 16  # box corners among them; `corner_design` for training never draws these


def box_corners(n: int, seed: int) -> np.ndarray:
    """(n, 14) raw corners of the design box: all-min, all-max, then random sign patterns."""
    if n == 0:
        return np.zeros((0, N_CONTROLS))
    rng = np.random.default_rng(seed)
    signs = [np.full(N_CONTROLS, -1.0), np.full(N_CONTROLS, 1.0)]
    while len(signs) < n:
        signs.append(rng.choice([-1.0, 1.0], size=N_CONTROLS))
    return box_corner(np.stack(signs[:n]))


def heldout_corners() -> np.ndarray:
    """(HELDOUT_CORNERS, 14) raw corners the physics benchmark holds out (``corner_design``'s exclusions)."""
    return box_corners(HELDOUT_CORNERS, HELDOUT_SEED)


def corner_design(n: int, seed: int, exclude: np.ndarray | None = None) -> np.ndarray:
    """(n, 14) raw controls at n distinct random corners of the design box, none of them in ``exclude``.

    Each control sits at its design minimum or maximum with probability 1/2. Why: a Latin hypercube
    leaves the box's corners empty. In the 2,000 points of the seed-42 and seed-43 designs, a point has
    on average 2.8 of its 14 controls in the outer tenth of their ranges (at most 8), and every point has
    some control at least a quarter of its range away from both bounds. A surrogate trained on them
    extrapolates at the corners, which are real recipes (all fluxes high, energies low, ...).
    ``exclude`` (m, 14) raw corners are never drawn, e.g. the physics benchmark's held-out corners.
    """
    n_all = 2**N_CONTROLS
    banned = set()
    if exclude is not None and len(exclude):
        ex = np.asarray(exclude, dtype=np.float64)
        _check_last_dim(ex)
        banned = {tuple(row) for row in (ex >= HIGH).astype(int)}
    if not 1 <= n <= n_all - len(banned):
        raise ValueError(f"n must be in 1..{n_all - len(banned)} (distinct corners of the box), got {n}")
    rng = np.random.default_rng(seed)
    seen: set[tuple[int, ...]] = set()
    picked: list[np.ndarray] = []
    while len(picked) < n:
        bits = rng.integers(0, 2, size=N_CONTROLS)  # (14,) 1 = maximum
        key = tuple(int(b) for b in bits)
        if key in seen or key in banned:
            continue
        seen.add(key)
        picked.append(bits)
    return box_corner(np.stack(picked))  # (n, 14)


# --- admissible values: one set of rules for the service, the inverse design and the CLI --------------

MAX_ABS_NORMALIZED = 1e3  # linear/int controls: |normalized| beyond this is no process at all
MAX_FLUX_DECADES = 3.0  # fluxes: more than 10^3 x the design maximum is no process at all


def guard_max(name: str) -> float:
    """The largest accepted value of control ``name`` (physical units): the scale guard.

    Linear and integer controls: MAX_ABS_NORMALIZED half-widths of the design box past its centre.
    Log-sampled fluxes: MAX_FLUX_DECADES decades above the design maximum (a normalized bound would be
    meaningless for fluxes: 1e300 mol m^-2 s^-1 normalizes to about 465). Zero is always admissible.
    """
    spec = CONTROL_SPECS[control_index(name)]
    if spec.kind == "log":
        return float(spec.high * 10.0**MAX_FLUX_DECADES)
    return float(spec.low + (MAX_ABS_NORMALIZED + 1.0) * 0.5 * (spec.high - spec.low))


GUARD_MAX = np.array([guard_max(n) for n in CONTROL_NAMES], dtype=np.float64)  # (14,)
ACCEPT_MAX = np.minimum(PHYS_MAX, GUARD_MAX)  # (14,) the highest accepted value per control


def admissible_range(name: str) -> tuple[float, float]:
    """(lowest, highest) accepted value of control ``name``: the physical minimum and the smaller of the
    physical maximum and the scale guard (``guard_max``), physical units."""
    j = control_index(name)
    return float(PHYS_MIN[j]), float(ACCEPT_MAX[j])


def control_problem(name: str, value: float, *, whole: bool = True) -> str | None:
    """Why ``value`` is no admissible value of control ``name`` (None if it is one).

    Refused: non-finite values, values below the physical minimum or above the physical maximum
    ("physically impossible"), values past the scale guard ("far outside any meaningful range") and, with
    ``whole``, fractional values of the integer controls (cosine-power exponents).
    """
    spec = CONTROL_SPECS[control_index(name)]
    lo, hi = admissible_range(name)
    v = float(value)
    accepted = f"accepted {lo:g}..{hi:g} {spec.unit}"
    if not math.isfinite(v):
        return f"{name} = {v!r} is not a finite number ({accepted})"
    if v < spec.phys_min or v > spec.phys_max:
        bound = f">= {spec.phys_min:g}" if v < spec.phys_min else f"<= {spec.phys_max:g}"
        return f"{name} = {v:g} {spec.unit} is physically impossible: it must be {bound} {spec.unit}"
    if v > hi:
        return (f"{name} = {v:g} {spec.unit} is far outside any meaningful range (training range "
                f"{spec.low:g}..{spec.high:g}, {accepted})")
    if whole and spec.kind == "int" and v != math.floor(v):
        return (f"{name} = {v:g} is not an integer: cosine-power exponents are whole numbers "
                f"(e.g. {math.floor(v):g} or {math.ceil(v):g})")
    return None


def check_control(name: str, value: float, *, where: str = "", whole: bool = True) -> float:
    """``value`` as a float, or ValueError (``where`` + ``control_problem``'s reason: the name, the value
    and the accepted range). ``where``: a prefix such as ``"fixed."`` that locates the value."""
    problem = control_problem(name, value, whole=whole)
    if problem is not None:
        raise ValueError(where + problem)
    return float(value)


def check_admissible(raw: np.ndarray) -> list[str]:
    """One message per inadmissible value of raw controls, (14,) or (..., 14); empty if admissible.

    Inadmissible: non-finite, physically impossible or past the scale guard (``control_problem``;
    fractional exponents are allowed here). Every row is checked; with more than one row each message
    starts with ``row i:`` (i indexes the flattened rows).
    """
    raw = np.asarray(raw, dtype=np.float64)
    _check_last_dim(raw)
    rows = raw.reshape(-1, N_CONTROLS)  # (N, 14)
    bad = ~np.isfinite(rows) | (rows < PHYS_MIN) | (rows > ACCEPT_MAX)  # (N, 14)
    out = []
    for i, j in zip(*np.nonzero(bad), strict=True):
        where = f"row {i}: " if rows.shape[0] > 1 else ""
        out.append(f"{where}{control_problem(CONTROL_NAMES[j], float(rows[i, j]), whole=False)}")
    return out


def check_controls(raw: np.ndarray, where: str = "") -> None:
    """ValueError naming the first inadmissible value of raw controls (14,) or (..., 14)
    (``check_admissible``); ``where`` prefixes the message."""
    bad = check_admissible(raw)
    if bad:
        raise ValueError(where + bad[0])


def outside_design_range(raw: np.ndarray) -> list[str]:
    """Names of the controls outside the design (training) range in any row of raw (14,) or (..., 14)."""
    rows = np.asarray(raw, dtype=np.float64).reshape(-1, N_CONTROLS)  # (N, 14)
    outside = np.asarray(((rows < LOW) | (rows > HIGH) | np.isnan(rows)).any(axis=0))  # (14,)
    return [s.name for s, o in zip(CONTROL_SPECS, outside, strict=True) if o]


# --- CSV -----------------------------------------------------------------------------------------------


CSV_GEOMETRY = ("feature", "cd_nm", "mask_nm")  # a design's geometry columns (``nemsim.geometry.feature``)


def write_controls_csv(path: str | Path, raw: np.ndarray, seed_ids: np.ndarray | None = None,
                       geometry: tuple[str, np.ndarray] | None = None) -> None:
    """Write raw controls (N, 14): header = CONTROL_NAMES, one row per case, full float precision; with
    ``seed_ids`` (N,) a column ``seed_id``: the case id whose simulator seed the case uses; with
    ``geometry`` = (kind, (N, 2) [cd_nm, mask_nm]) the last columns ``feature``, ``cd_nm``, ``mask_nm``."""
    raw = np.asarray(raw, dtype=np.float64)
    if raw.ndim != 2 or raw.shape[1] != N_CONTROLS:
        raise ValueError(f"controls must have shape (N, {N_CONTROLS}); got {raw.shape}")
    if seed_ids is not None and len(seed_ids) != len(raw):
        raise ValueError(f"{len(seed_ids)} seed ids for {len(raw)} cases")
    is_int = [s.kind == "int" for s in CONTROL_SPECS]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(CONTROL_NAMES + (() if seed_ids is None else ("seed_id",))
                   + (() if geometry is None else CSV_GEOMETRY))
        for i, row in enumerate(raw):
            cells = [str(int(v)) if k and float(v).is_integer() else repr(float(v))
                     for v, k in zip(row, is_int, strict=True)]
            cells += [] if seed_ids is None else [str(int(seed_ids[i]))]
            if geometry is not None:
                cells += [geometry[0], *(repr(float(v)) for v in geometry[1][i])]
            w.writerow(cells)


def _csv_table(path: str | Path) -> tuple[list[str], list[list[str]]]:
    """(header with names stripped, data rows) of a controls CSV; ValueError on an empty file."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except (UnicodeDecodeError, csv.Error) as exc:
        raise ValueError(f"{path}: not a CSV text file ({exc})") from None
    if not rows:
        raise ValueError(f"{path}: empty file; expected a header with {list(CONTROL_NAMES)}")
    return [h.strip() for h in rows[0]], rows[1:]


def read_seed_ids(path: str | Path) -> np.ndarray | None:
    """The ``seed_id`` column of a controls CSV as (N,) int64 (written by ``pair_design``'s ``nemsim design
    --kind pairs``), or None if it has none."""
    header, body = _csv_table(path)
    if "seed_id" not in header:
        return None
    j = header.index("seed_id")
    out = np.empty(len(body), dtype=np.int64)
    for r, row in enumerate(body):
        try:
            out[r] = int(row[j])
        except (ValueError, IndexError):
            raise ValueError(f"{path}: row {r + 2}, column 'seed_id': not an integer: "
                             f"{row[j] if j < len(row) else ''!r}") from None
        if out[r] < 0:
            raise ValueError(f"{path}: row {r + 2}, column 'seed_id': must be >= 0, got {out[r]}")
    return out


def read_geometry_csv(path: str | Path) -> tuple[str, np.ndarray] | None:
    """The geometry columns of a controls CSV (``write_controls_csv``): (kind, (N, 2) float64 [cd_nm,
    mask_nm]), or None if it has none. One kind per file; ValueError naming the row of a bad value."""
    header, body = _csv_table(path)
    present = [c for c in CSV_GEOMETRY if c in header]
    if not present:
        return None
    if len(present) != len(CSV_GEOMETRY):
        raise ValueError(f"{path}: geometry needs all of the columns {list(CSV_GEOMETRY)}, got {present}")
    jk, jc, jm = (header.index(c) for c in CSV_GEOMETRY)
    kinds = sorted({row[jk].strip() for row in body if len(row) > jk})
    if len(kinds) > 1:
        raise ValueError(f"{path}: one feature kind per file, got {kinds}")
    out = np.empty((len(body), 2), dtype=np.float64)
    for r, row in enumerate(body):
        for k, j in enumerate((jc, jm)):
            try:
                out[r, k] = float(row[j])
            except (ValueError, IndexError):
                col = CSV_GEOMETRY[k + 1]
                raise ValueError(f"{path}: row {r + 2}, column {col!r}: not a number") from None
    return (kinds[0] if kinds else "hole"), out


def read_controls_csv(path: str | Path) -> np.ndarray:
    """Read a controls CSV -> (N, 14) float64 in CONTROL_NAMES order.

    The header must name each of the 14 controls exactly once (any order); optional ``case_id``, ``seed_id``
    and geometry columns are ignored (``read_seed_ids`` and ``read_geometry_csv`` read them). Raises
    ValueError naming missing, unknown or duplicate columns, or the row/column of a bad value.
    """
    header, body = _csv_table(path)
    dup = sorted({h for h in header if header.count(h) > 1})
    unknown = [h for h in header if h not in CONTROL_INDEX and h not in ("case_id", "seed_id", *CSV_GEOMETRY)]
    missing = [n for n in CONTROL_NAMES if n not in header]
    problems = []
    if missing:
        problems.append(f"missing columns {missing}")
    if unknown:
        problems.append(f"unknown columns {unknown}")
    if dup:
        problems.append(f"duplicate columns {dup}")
    if problems:
        raise ValueError(f"{path}: bad header: {'; '.join(problems)}; expected {list(CONTROL_NAMES)}")
    cols = [header.index(n) for n in CONTROL_NAMES]
    out = np.empty((len(body), N_CONTROLS), dtype=np.float64)
    for r, row in enumerate(body):
        if len(row) != len(header):
            raise ValueError(f"{path}: row {r + 2} has {len(row)} fields; header has {len(header)}")
        for j, c in enumerate(cols):
            try:
                out[r, j] = float(row[c])
            except ValueError:
                raise ValueError(
                    f"{path}: row {r + 2}, column {CONTROL_NAMES[j]!r}: not a number: {row[c]!r}"
                ) from None
    return out
