"""Optional re-parameterizations of the rule library's laws for the simulator (``SimConfig``; off by default).

The simulator reads every probability and yield law from the compiled Event Rules Library (``events``).
Two ``SimConfig`` options change the probability parameters it reads, and nothing else (the model's rule
tensors, the rule text and its SHA-256 are untouched):

``sputter_calibration`` (``SPUTTER_CALIBRATIONS``)
  * ``"paper"`` (default): the paper's ion catalog as written (tab:supp_ion_catalog).
  * ``"laegreid_wehner"``: Ar+ -> Si physical sputtering (E18, ``Arp_on_Si_phys``) fitted to the normal
    incidence yields of Laegreid & Wehner, J. Appl. Phys. 32, 365 (1961): 0.07 / 0.18 / 0.31 / 0.53 Si
    atoms per Ar+ at 100 / 200 / 300 / 600 eV. Why the paper's rule misses them: its Yamamura-style
    yield is normalized to one unit at normal incidence (the paper says it is "an event-yield multiplier
    rather than an independently calibrated absolute sputter yield"), so the flat-surface yield per real
    ion is flux_scale * p0 * ((E - E_th)/(E_ref - E_th))^n = 0.6 * 0.05 * sqrt((E - 25)/75): 0.03 at
    100 eV, and it grows as sqrt(E) while the data grow almost linearly (7.6x from 100 to 600 eV against
    2.8x). The fit keeps the rule's E_th = 25 eV and E_ref = 100 eV and sets n = 1.0 and the yield at
    E_ref to 0.075 atoms per ion (least squares in log yield over the four points, n and the yield free:
    n = 1.01, so n = 1); p0 = 0.075 / flux_scale, so the yield per real ion does not depend on the
    flux calibration. The angular law (P) is the rule's. Cl+ and Cl2+ on bare Si (E7, E13) keep the
    paper's values: the cited data are for Ar+ only.

``resist_sputter_scale``
  Multiplies p0 of the ion sputtering rules whose target is the resist (E12, E17, E22): the mask erodes
  faster at every angle, so the opening's top corner facets sooner (the rules' P law already makes
  oblique incidence erode the resist several times faster than normal incidence). A study knob for the
  facet-deflected-ion bowing mechanism (benchmarks/small/bowing.md); no literature value is claimed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple, Protocol

import numpy as np

if TYPE_CHECKING:
    from nemsim.rules.compile import RuleTensors


class SputterOptions(Protocol):
    """The ``SimConfig`` fields this module reads (``SimConfig`` imports this module, not the reverse)."""

    @property
    def sputter_calibration(self) -> str: ...
    @property
    def flux_scale(self) -> float: ...
    @property
    def resist_sputter_scale(self) -> float: ...


class SputterFit(NamedTuple):
    """A probModel rule re-fitted to a flat-surface yield: p = p0 ((E - E_th)/(E_ref - E_th))^n with
    p0 = yield_at_ref / flux_scale (one unit removed per event at normal incidence, ``yields`` module)."""

    event: str  # rule name
    e_th: float  # eV
    e_ref: float  # eV
    yield_at_ref: float  # atoms per real ion at E_ref, normal incidence
    n: float  # energy exponent


SPUTTER_CALIBRATIONS: dict[str, tuple[SputterFit, ...]] = {
    "paper": (),
    "laegreid_wehner": (SputterFit("Arp_on_Si_phys", e_th=25.0, e_ref=100.0, yield_at_ref=0.075, n=1.0),),
}

_P_E_TH, _P_E_REF, _P_P0, _P_N = 0, 1, 2, 3  # probModel columns of prob_params (E_th, E_ref, p0, n, angle)


def calibrated_prob_params(rules: RuleTensors, config: SputterOptions) -> np.ndarray:
    """(E, 5) float64 probability parameters the simulator uses: the rules' with ``config``'s options applied.

    Raises ValueError if a calibration names an event the library does not have or that is not probModel.
    """
    out = np.array(rules.prob_params, dtype=np.float64, copy=True)
    names = [str(n) for n in rules.names]
    for fit in SPUTTER_CALIBRATIONS[config.sputter_calibration]:
        if fit.event not in names:
            name = config.sputter_calibration
            raise ValueError(f"sputter_calibration {name!r}: the rules have no event named {fit.event!r}")
        e = names.index(fit.event)
        if int(rules.prob_model[e]) != 1:
            raise ValueError(f"sputter_calibration: rule {fit.event!r} does not use the probModel law")
        if config.flux_scale <= 0:
            raise ValueError("sputter_calibration needs flux_scale > 0 (p0 = yield / flux_scale)")
        out[e, _P_E_TH], out[e, _P_E_REF], out[e, _P_N] = fit.e_th, fit.e_ref, fit.n
        out[e, _P_P0] = fit.yield_at_ref / config.flux_scale
    if config.resist_sputter_scale != 1.0:
        from nemsim.rules.vocab import ION_PROJECTILES, PROJECTILES, TARGETS

        resist = TARGETS.index("Resist")
        for e in range(len(names)):
            ion = PROJECTILES[int(rules.projectile[e])] in ION_PROJECTILES
            if ion and int(rules.target[e]) == resist and int(rules.prob_model[e]) == 1:
                out[e, _P_P0] *= config.resist_sputter_scale
    return out
