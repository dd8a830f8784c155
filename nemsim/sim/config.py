"""Simulator configuration: the constants the paper leaves to the implementation ([supp_simulator]).

``SimConfig`` is a frozen dataclass; ``SimConfig.resolved(scene)`` fills the scene-dependent defaults
(voxel capacities) and ``to_meta()`` is what every generated file records as the simulator's constants.

Flux-to-particle conversion ([supp_simulator], "Particle Injection and Transport"): a control flux
Gamma_s [mol m^-2 s^-1] becomes a simulated particle rate

    R_s = Gamma_s * N_A * A_top * w,     w = flux_scale * capacity_si / (si_atoms_per_nm3 * V_voxel)

with A_top the top-plane area and V_voxel the voxel volume: one simulated particle stands for as many real
particles as one Si material unit holds Si atoms (divided by ``flux_scale``, kappa), so the etch rate per
unit flux does not depend on the voxel capacity or the resolution; the capacity only trades Monte Carlo
noise against run time. kappa, ``units_per_nm3`` and ``resist_density_ratio`` were set by short sweeps on
``small`` so that the design's depths and mask losses span a realistic range without removing the mask
(``nemsim data stats``; benchmarks/small/data_stats.json).

Mechanisms beyond the paper (``kernels`` module docstring): ``excess_probability_yield`` (on), the ion
reflection law, diffuse / lobed reflection, a broad-angle ion wing, the sputter re-calibrations
(``calibration``). All are off except the specular lobe ``ion_reflect_spread_deg`` = 10 deg: a mirror only
folds an ion's path, while a rough, eroding sidewall spreads it, and without the spread no recipe in the box
bows the hole by more than a voxel (benchmarks/small/bowing.md compares 5-20 deg; a modelling choice, not a
fit). ``to_meta`` leaves a mechanism out at the value a record made before it existed describes
(``_RECORD_DEFAULTS``), so older data files stay resumable and read back as they were made.

Particle budget b (``particle_budget``, ``nemsim bench speed-error``): b times the calibrated particle count,
each a super-particle of weight w = 1/b that moves stochastic_round(w Y) units per event (deposits
stochastic_round(w); emitted products carry w too), so the expected change per unit of real flux, the
voxel capacities and Psi stay as calibrated and only the Monte Carlo variance grows. A capped event's unused
weight flies on. b = 1 is the calibrated simulator exactly and is not written into ``to_meta``.

Simulated domain (``domain``): every shipped scene is a circular opening centred on a square, periodic
grid, so for even nx and ny the planes through the opening's axis (x = nx/2, y = ny/2 in the kernels'
voxel-corner coordinates) and, by periodicity, the outer faces x = 0 and y = 0 are mirror planes of the
mean evolution. "quarter" runs the Monte Carlo on the lower quadrant [0, nx/2) x [0, ny/2) with specular
walls on its four lateral faces (``kernels`` module docstring, "Walls"), launching over the quadrant's top
area (``simulated_scene``: a quarter of the particles), and mirrors each state into the full box before Psi
(``process``), so the recorded states have the scene's shape and are exactly symmetric under both mirrors.
Measured on ``small`` (``nemsim bench sim-quarter``: 16 recipes, two seeds per domain,
benchmarks/small/sim_quarter.md): no shift of the final depth, widths or mask loss beyond chance (mean
quarter - full within 1.6 standard errors; RMS difference / seed spread 0.8-1.3, chance bound 1.4), at
2.3x less CPU per trajectory (Psi still runs on the full box). The noise per voxel is the same, not that of
every derived quantity: the four mirror copies are one sample, so what averages over the field or the
floor (mask loss, bottom width) or is read on the axis (the depth: one voxel column mirrored instead of
four) has 1.8-2.8x the full domain's seed-to-seed standard deviation, and the seed-to-seed Avg RMSE of the
states is 12 % higher. Odd nx or ny is refused: a mirror plane through a voxel centre would split voxels.
"full" is the data sets' simulator and is not written into ``to_meta``.

Cross-section (``domain`` = "section", trenches only): a trench's mean evolution is invariant under the
mirror through its axis and every translation along the line (y), so its state is a cross-section in x and
z. "section" runs the Monte Carlo on a slab of the box, x in [0, nx/2) (the whole [0, nx) for an odd nx) by
``section_ny`` rows of y, between the same mirror walls (x: the trench's mirror and, by periodicity, the
outer faces; y: a mirror is a symmetry of a line's mean evolution, and a flight folded between y walls is a
flight along the line), launching over the slab's top area (``simulated_scene``). The particle physics per
unit area is unchanged; only the number of columns the state averages over shrinks (nx/2 x section_ny
instead of nx x ny), so its noise per voxel is larger. Each state is the slab's fractions averaged over its
rows, mirrored into the full x extent and through Psi as one row, then repeated along y: the states have the
scene's full shape (``process``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

from nemsim.scenes import Scene

AVOGADRO = 6.02214076e23  # 1/mol

# Atomic / molecular masses [amu] for the mass-ratio energy loss of specularly reflected ions.
# Resist has no single mass; we use a CH2 repeat unit (14 amu), a choice the paper does not make.
_PROJECTILE_MASS_AMU = (
    ("Cl", 35.45), ("Cl2", 70.90), ("Cl+", 35.45), ("Cl2+", 70.90), ("Ar+", 39.95),
    ("SiCl", 63.54), ("SiCl2", 98.99), ("SiCl3", 134.44),
)  # fmt: skip
_TARGET_MASS_AMU = (("Si", 28.09), ("SiCl", 63.54), ("SiCl2", 98.99), ("SiCl3", 134.44), ("Resist", 14.03))


# Optional surface and transport mechanisms (kernels module docstring, ``calibration``):
# the value a record that lacks the key describes (the simulator before the field existed): ``to_meta``
# leaves a field out at this value and ``from_meta`` reads a missing key as it
_RECORD_DEFAULTS: dict[str, Any] = {
    "particle_budget": 1.0, "sputter_calibration": "paper", "resist_sputter_scale": 1.0,
    "ion_reflect_diffuse": 0.0, "ion_reflect_spread_deg": 0.0, "ion_reflect_energy": 0.0,
    "ion_wing_fraction": 0.0, "ion_wing_m": 5.0, "rng_mode": "stream", "domain": "full", "section_ny": 2,
}  # fmt: skip
RNG_MODES = ("stream", "counter")  # kernels module docstring, "Random numbers"
DOMAINS = ("full", "quarter", "section")  # module docstring, "Simulated domain" and "Cross-section"
MIRROR_DOMAINS = ("quarter", "section")  # simulated between mirror walls


@dataclass(frozen=True)
class SimConfig:
    """Constants of the Monte Carlo feature-profile simulator (defaults = the calibrated data set).

    Capacities are material units per voxel; ``None`` means "derive from the per-volume density and the
    scene's voxel volume" so the physical behaviour is the same on every scene (see the module docstring).
    """

    capacity: int | None = None  # Si-class units per full voxel; None -> units_per_nm3 * V_voxel
    resist_capacity: int | None = None  # resist units per full voxel; None -> capacity * resist_density_ratio
    units_per_nm3: float = 0.25  # Si material units per nm^3 (small: 16 units per 4 nm voxel)
    min_capacity: int = 8  # floor on the derived Si capacity (paper: 8 units per 2 nm voxel)
    max_capacity: int = 16  # ceiling on the derived Si capacity (tiny's 8 nm voxels stay cheap)
    resist_density_ratio: float = 0.75  # resist units per voxel / Si units per voxel (calibrated)
    si_atoms_per_nm3: float = 50.0  # Si atomic density [nm^-3]: real atoms in one Si unit = n V / capacity
    flux_scale: float = 0.6  # kappa: simulated particles per (real particle / atoms per unit); calibrated
    particle_budget: float = 1.0  # b: fraction of the calibrated particle count; each weighs 1/b (docstring)
    max_steps: int = 10_000  # steps (voxel crossings + surface hits) per particle [supp_simulator]
    neutral_energy_ev: float = 0.2  # incident energy of neutral Cl [supp_simulator]
    product_energy_ev: float = 2.0  # energy of emitted SiCl_x products [supp_simulator]
    psi_sigma_vox: float = 0.7  # Gaussian smoothing of the material fraction before the SDF (voxels)
    # ion reflection law (kernels.reflection_probability; module docstring "Ion reflection"): a non-reacting
    # ion is absorbed (implanted and neutralized) below ion_absorb_below_deg incidence, always reflected
    # beyond ion_reflect_above_deg, linear in the angle between. 0, 0 (default) = every non-reacting ion
    # reflects, the calibrated behaviour; measured to *lower* lateral etch and bowing, so off by default.
    ion_absorb_below_deg: float = 0.0
    ion_reflect_above_deg: float = 0.0
    # excess-probability yield (kernels module docstring): when the competing channels' unsaturated
    # probabilities sum to P > 1, the chosen event's yield is multiplied by P (was: normalized away)
    excess_probability_yield: bool = True
    # ---- optional mechanisms (not written into ``to_meta`` at the value a record
    # without them describes, ``_RECORD_DEFAULTS``). Off by default except the specular lobe (module
    # docstring). Kernels module docstring.
    # Literature calibration of the rules' physical-sputtering laws (``calibration.SPUTTER_CALIBRATIONS``):
    # "paper" = the rule library as written; "laegreid_wehner" = Ar+ -> Si fitted to Laegreid & Wehner 1961.
    sputter_calibration: str = "paper"
    # mask faceting: multiplies p0 of the ion sputtering rules whose target is the resist
    resist_sputter_scale: float = 1.0
    # ion reflection: fraction of reflecting ions scattered diffusely (cosine about the normal) instead of
    # specularly; rms angular spread [deg] of the specular lobe (10: on, module docstring; 0: a mirror, the
    # simulator before the lobe); retained energy fraction (0 = mass law)
    ion_reflect_diffuse: float = 0.0
    ion_reflect_spread_deg: float = 10.0
    ion_reflect_energy: float = 0.0
    # broad-angle wing of the ion angular distribution: this fraction of the ions is launched from
    # cos^ion_wing_m instead of the control's cos^m (collisional-sheath tail)
    ion_wing_fraction: float = 0.0
    ion_wing_m: float = 5.0
    # random numbers (kernels module docstring): "stream" = one generator per kernel call (the data sets);
    # "counter" = common random numbers keyed by (seed, macro step, source, particle), for paired recipes
    rng_mode: str = "stream"
    # simulated domain (module docstring, "Simulated domain"): "full" = the scene's periodic box (the data
    # sets); "quarter" = its lower quadrant between mirror walls, unfolded into the full box at every state
    domain: str = "full"
    section_ny: int = 2  # rows of y the "section" domain simulates (module docstring, "Cross-section")
    queue_capacity: int = 1 << 15  # FIFO ring buffer for secondary products (drained after each primary)
    projectile_mass_amu: tuple[tuple[str, float], ...] = _PROJECTILE_MASS_AMU
    target_mass_amu: tuple[tuple[str, float], ...] = _TARGET_MASS_AMU

    def __post_init__(self) -> None:
        if self.flux_scale < 0 or not math.isfinite(self.flux_scale):
            raise ValueError(f"flux_scale must be a finite number >= 0, got {self.flux_scale}")
        for name in ("capacity", "resist_capacity"):
            value = getattr(self, name)
            if value is not None and not (1 <= value <= 30_000):
                raise ValueError(f"{name} must be in [1, 30000] units per voxel, got {value}")
        if not (self.particle_budget > 0 and math.isfinite(self.particle_budget)):
            raise ValueError(
                f"particle_budget must be a finite number > 0 (1 = full budget, 0.25 = a quarter), "
                f"got {self.particle_budget}"
            )
        if self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")
        lo, hi = self.ion_absorb_below_deg, self.ion_reflect_above_deg
        if not (0.0 <= lo <= hi <= 90.0):
            raise ValueError(
                f"ion reflection law needs 0 <= ion_absorb_below_deg <= ion_reflect_above_deg <= 90, "
                f"got {lo} and {hi}"
            )
        if self.psi_sigma_vox < 0:
            raise ValueError(f"psi_sigma_vox must be >= 0, got {self.psi_sigma_vox}")
        from .calibration import SPUTTER_CALIBRATIONS

        if self.sputter_calibration not in SPUTTER_CALIBRATIONS:
            choices = sorted(SPUTTER_CALIBRATIONS)
            raise ValueError(f"sputter_calibration is one of {choices}, got {self.sputter_calibration!r}")
        for name in ("ion_reflect_diffuse", "ion_wing_fraction", "ion_reflect_energy"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value}")
        scale = self.resist_sputter_scale
        if not (scale >= 0 and math.isfinite(scale)):
            raise ValueError(f"resist_sputter_scale must be a finite number >= 0, got {scale}")
        if not 0.0 <= self.ion_reflect_spread_deg <= 45.0:
            spread = self.ion_reflect_spread_deg
            raise ValueError(f"ion_reflect_spread_deg must be in [0, 45] degrees, got {spread}")
        if not self.ion_wing_m >= 0:
            raise ValueError(f"ion_wing_m must be >= 0, got {self.ion_wing_m}")
        if self.rng_mode not in RNG_MODES:
            raise ValueError(f"rng_mode is one of {RNG_MODES}, got {self.rng_mode!r}")
        if self.domain not in DOMAINS:
            raise ValueError(f"domain is one of {DOMAINS}, got {self.domain!r}")
        if not (isinstance(self.section_ny, int) and self.section_ny >= 1):
            raise ValueError(f"section_ny must be an int >= 1 (rows of y in the cross-section), "
                             f"got {self.section_ny!r}")

    def check_scene(self, scene: Scene) -> None:
        """Raise ValueError if this config cannot simulate ``scene`` (the quarter needs even nx and ny; the
        cross-section a trench)."""
        if self.domain == "section":
            if scene.kind != "trench" or scene.symmetry == "none":
                raise ValueError(f"domain 'section' simulates a trench's cross-section; scene "
                                 f"{scene.name!r} is a {scene.kind} with symmetry {scene.symmetry!r}: "
                                 "use 'full' or 'quarter'")
            if self.section_ny > scene.ny:
                raise ValueError(f"domain 'section' needs section_ny <= ny; scene {scene.name!r} has ny "
                                 f"{scene.ny}, section_ny {self.section_ny}")
            return
        if self.domain == "quarter" and getattr(scene, "symmetry", "d4") == "none":
            raise ValueError(f"domain 'quarter' needs a scene with the square's symmetry; scene "
                             f"{scene.name!r} declares none: use domain 'full'")
        if self.domain == "quarter" and (scene.nx % 2 or scene.ny % 2):
            raise ValueError(
                f"domain 'quarter' simulates the lower quadrant of the scene between mirror walls and needs "
                f"even nx and ny (the mirror planes through the opening's axis must be voxel faces); scene "
                f"{scene.name!r} is {scene.nx} x {scene.ny}: use domain 'full'"
            )

    def simulated_scene(self, scene: Scene) -> Scene:
        """The box the particles fly in: ``scene`` itself, or its lower quadrant (nx/2, ny/2, nz) for
        ``domain`` = "quarter" (its ``area_nm2`` is a quarter, and so is the particle rate)."""
        self.check_scene(scene)
        if self.domain == "full":
            return scene
        if self.domain == "section":  # half of an even x extent, the whole of an odd one
            nx = scene.nx // 2 if scene.nx % 2 == 0 else scene.nx
            return replace(scene, name=f"{scene.name}-section", nx=nx, ny=self.section_ny)
        return replace(scene, name=f"{scene.name}-quarter", nx=scene.nx // 2, ny=scene.ny // 2)

    def resolved(self, scene: Scene) -> SimConfig:
        """This config with ``capacity`` and ``resist_capacity`` filled in for ``scene``."""
        cap = self.capacity
        if cap is None:
            cap = int(round(self.units_per_nm3 * scene.voxel_nm**3))
            cap = min(max(cap, self.min_capacity), self.max_capacity)
        rcap = self.resist_capacity
        if rcap is None:
            rcap = max(1, int(round(cap * self.resist_density_ratio)))
        return replace(self, capacity=cap, resist_capacity=rcap)

    def particles_per_real(self, scene: Scene) -> float:
        """Simulated particles per real incident particle, w (module docstring), times the particle budget."""
        cap = self.resolved(scene).capacity
        assert cap is not None
        return self.flux_scale * cap / (self.si_atoms_per_nm3 * scene.voxel_nm**3) * self.particle_budget

    @property
    def reflection_cosines(self) -> tuple[float, float]:
        """(cos theta_full, cos theta_zero) for ``kernels.reflection_probability``; (1, 1): always reflect."""
        if self.ion_reflect_above_deg <= 0.0:
            return 1.0, 1.0
        return (
            math.cos(math.radians(self.ion_reflect_above_deg)),
            math.cos(math.radians(self.ion_absorb_below_deg)),
        )

    @property
    def particle_weight(self) -> float:
        """1 / particle_budget: full-budget particles one simulated particle stands for (module docstring)."""
        return 1.0 / self.particle_budget

    def particle_rate_per_flux(self, scene: Scene) -> float:
        """Simulated particles per second per unit flux (1 mol m^-2 s^-1) through the top plane."""
        return AVOGADRO * scene.area_nm2 * 1e-18 * self.particles_per_real(scene)

    def to_meta(self, scene: Scene | None = None) -> dict:
        """JSON-able record of every constant (resolved for ``scene`` when given)."""
        cfg = self.resolved(scene) if scene is not None else self
        out = asdict(cfg)
        # fields at the value files generated before the field existed describe: omitted, so those files
        # stay resumable (``from_meta`` reads a missing key as that value)
        for name, legacy in _RECORD_DEFAULTS.items():
            if out[name] == legacy:
                del out[name]
        out["projectile_mass_amu"] = dict(cfg.projectile_mass_amu)
        out["target_mass_amu"] = dict(cfg.target_mass_amu)
        if scene is not None:
            out["particle_rate_per_flux"] = self.particle_rate_per_flux(scene)
        return out

    @classmethod
    def from_record(cls, record: Any) -> SimConfig | None:
        """The configuration a checkpoint's ``sim_config`` records: a data file's ``generator`` record (its
        ``config`` entry is ``to_meta``) or a bare ``to_meta`` dict; None when nothing is recorded, i.e. also
        when the record names no simulator constant (it would otherwise read as today's defaults). The one
        reader of that record (the service, the simulator-judged benchmarks and inverse design use it)."""
        if not isinstance(record, dict) or not record:
            return None
        meta = record["config"] if isinstance(record.get("config"), dict) else record
        if not set(meta) & set(cls.__dataclass_fields__):
            return None
        return cls.from_meta(meta)

    @classmethod
    def from_meta(cls, meta: dict) -> SimConfig:
        """Inverse of ``to_meta`` (derived keys are ignored).

        A record written before ``excess_probability_yield`` existed describes a simulator without it, so
        the missing key reads as False (the reflection law's missing keys read as its default, off), and a
        missing optional mechanism reads as its ``_RECORD_DEFAULTS`` value (the specular lobe as 0 deg).
        """
        known = {f for f in cls.__dataclass_fields__}
        kwargs = {k: v for k, v in meta.items() if k in known}
        if kwargs and "excess_probability_yield" not in kwargs:
            kwargs["excess_probability_yield"] = False
        if kwargs:
            kwargs = {**_RECORD_DEFAULTS, **kwargs}
        for key in ("projectile_mass_amu", "target_mass_amu"):
            if isinstance(kwargs.get(key), dict):
                kwargs[key] = tuple(kwargs[key].items())
        return cls(**kwargs)
