"""Where the simulator bows: a map over ion angular exponent x ion energy x neutral-to-ion flux ratio
(``nemsim bench bowing``).

Every grid point is one trajectory of the median recipe (unit-cube centre of the design, ``controls
.from_unit``) with three controls overridden for all three ions (Ar+, Cl+, Cl2+): the angular exponent m,
the mean energy, and the ion fluxes (unit coordinate ``ion_q``; the neutral Cl flux stays at the median),
so the flux ratio Gamma(Cl) / sum Gamma(ions) is reported per point. Metrics at the final time
(``geometry.profile``), in nm:
  * ``bowing``: the profile metric on the simulator's state (Psi with the configured smoothing);
  * ``bowing_unsmoothed``: the same metric on Psi of the final voxel fractions without the Gaussian
    smoothing (sigma = 0). Reason: Psi smooths each channel separately and the Si channel sees the resist
    above the top Si row as vacuum, so the smoothed top row reads wider than the voxels are, which would
    hide a bulge of that size just below it (benchmarks/small/bowing.md).
  * ``bowing_area``: the same "widest row minus the narrowest row above it" on the equivalent diameter
    d(z) = 2 sqrt(A(z) / pi) of every Si row, A(z) the open (non-Si) area of the row from the final voxel
    fractions, from the top Si row down. It averages over the whole perimeter instead of the four points
    of the x and y lines, so it sees a bulge of a fraction of a voxel that the line metrics lose in the
    sidewall roughness; ``bow_depth``: depth below the initial Si top of the row where it peaks (0 when
    there is no bulge). The profile d(z) (nm, top Si row first) is kept in the JSON rows.
Every point is run for each of a list of named simulator configurations (variants: e.g. ``before_variants``
= with and without the excess-probability yield, or the optional mechanisms of ``SimConfig``) and seeds.
``design_points`` runs the same measurement on rows of the 500-case design (m and energy columns: the Cl+
values).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from nemsim.controls import CONTROL_INDEX, from_unit
from nemsim.geometry.profile import profile_metrics
from nemsim.rules.compile import RuleTensors
from nemsim.scenes import Scene
from nemsim.sim.config import SimConfig
from nemsim.sim.process import run_trajectory
from nemsim.sim.sdf import psi

ION_FLUX = ("flux_ar_plus", "flux_cl_plus", "flux_cl2_plus")
ION_ANGLE = ("angle_ar_plus", "angle_cl_plus", "angle_cl2_plus")
ION_ENERGY = ("energy_mean_ar_plus", "energy_mean_cl_plus", "energy_mean_cl2_plus")


def grid_controls(m: float, energy_ev: float, ion_q: float) -> np.ndarray:
    """(14,) raw controls: the median recipe with ion angle exponent m, ion energy and ion-flux coordinate."""
    xi = np.full(14, 0.5)
    for name in ION_FLUX:
        xi[CONTROL_INDEX[name]] = ion_q
    raw = from_unit(xi[None])[0]
    for name in ION_ANGLE:
        raw[CONTROL_INDEX[name]] = m
    for name in ION_ENERGY:
        raw[CONTROL_INDEX[name]] = energy_ev
    return raw


def equivalent_diameters(si: np.ndarray, scene: Scene) -> np.ndarray:
    """(si_top,) equivalent diameter [nm] of the open area of every Si row, top Si row first.

    si: (nx, ny, nz) Si-class volume fractions of the voxels (``Domain.fractions``)."""
    rows = si[:, :, : scene.si_top][:, :, ::-1]  # top Si row first
    area = (1.0 - rows.astype(np.float64)).sum(axis=(0, 1)) * scene.voxel_nm**2  # (si_top,) nm^2
    return 2.0 * np.sqrt(area / np.pi)


def bulge(diam: np.ndarray, voxel_nm: float) -> tuple[float, float]:
    """(largest excess of a row's diameter over the narrowest row above it [nm], its depth below the
    initial Si top [nm], 0 when there is no bulge) for a profile that starts at the top Si row."""
    neck = np.minimum.accumulate(diam)  # narrowest row at or above each row
    excess = diam - neck
    i = int(np.argmax(excess))
    if excess[i] <= 0.0:
        return 0.0, 0.0
    return float(excess[i]), (i + 0.5) * voxel_nm


def run_point(scene: Scene, rules: RuleTensors, raw: np.ndarray, config: SimConfig, seed: int) -> dict:
    """Final-time metrics (module docstring), flux ratio and CPU seconds of one trajectory."""
    t0 = time.process_time()
    res = run_trajectory(scene, rules, raw, np.random.default_rng(seed), config)
    cpu = time.process_time() - t0
    m = profile_metrics(res.states[-1], scene)
    m0 = profile_metrics(psi(*res.domain.fractions(), scene, 0.0), scene)
    ions = sum(raw[CONTROL_INDEX[n]] for n in ION_FLUX)
    diam = equivalent_diameters(res.domain.fractions()[1], scene)
    bow, depth = bulge(diam, scene.voxel_nm)
    return {
        **{k: round(float(v), 3) for k, v in m.items()},
        "bowing_unsmoothed": round(float(m0["bowing"]), 3),
        "top_width_unsmoothed": round(float(m0["top_width"]), 3),
        "bowing_area": round(bow, 3),
        "bow_depth": round(depth, 1),
        "diameter_profile": [round(float(d), 2) for d in diam],
        "flux_ratio": round(float(raw[CONTROL_INDEX["flux_cl"]] / ions), 3),
        "cpu_s": round(cpu, 2),
        "wall_s": round(res.wall_s, 2),
    }


Variant = tuple[str, SimConfig]  # (name, simulator configuration) compared at every point


def before_variants(config: SimConfig) -> list[Variant]:
    """``after`` = ``config``, ``before`` = ``config`` without the excess-probability yield."""
    return [("after", config), ("before", replace(config, excess_probability_yield=False))]


def bowing_map(
    scene: Scene, rules: RuleTensors, variants: list[Variant], ms: tuple[float, ...],
    energies: tuple[float, ...], ion_qs: tuple[float, ...], seeds: tuple[int, ...] = (0,), log=None,
) -> list[dict]:  # fmt: skip
    """One row per grid point, variant and seed (module docstring)."""
    rows = []
    for m in ms:
        for e in energies:
            for q in ion_qs:
                raw = grid_controls(m, e, q)
                for name, cfg in variants:
                    for seed in seeds:
                        row = {"variant": name, "seed": seed, "m": m, "energy_ev": e, "ion_q": q,
                               **run_point(scene, rules, raw, cfg, seed)}  # fmt: skip
                        rows.append(row)
                        if log is not None:
                            log(row)
    return rows


def design_points(
    scene: Scene, rules: RuleTensors, variants: list[Variant], design_rows: tuple[int, ...],
    seeds: tuple[int, ...] = (0,), log=None,
) -> list[dict]:  # fmt: skip
    """The same metrics on rows of the 500-case design (calibration figures: depth range, mask loss)."""
    from nemsim.controls import lhs_design

    design = lhs_design()
    rows = []
    for i in design_rows:
        raw = design[i]
        for name, cfg in variants:
            for seed in seeds:
                row = {
                    "variant": name, "seed": seed, "design_row": i,
                    "m": float(raw[CONTROL_INDEX["angle_cl_plus"]]),
                    "energy_ev": round(float(raw[CONTROL_INDEX["energy_mean_cl_plus"]]), 1), "ion_q": None,
                    **run_point(scene, rules, raw, cfg, seed),
                }  # fmt: skip
                rows.append(row)
                if log is not None:
                    log(row)
    return rows


def to_markdown(rows: list[dict]) -> str:
    """The map as a markdown table."""
    lead = ("design_row",) if rows and "design_row" in rows[0] else ()
    cols = lead + (
        "variant", "seed", "m", "energy_ev", "ion_q", "flux_ratio", "bowing", "bowing_unsmoothed",
        "bowing_area", "bow_depth", "etch_depth", "top_width", "top_width_unsmoothed", "mask_loss", "cpu_s",
    )  # fmt: skip
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = ("-" if r[c] is None else r[c] if isinstance(r[c], str) else f"{r[c]:g}" for c in cols)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
