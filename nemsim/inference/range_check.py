"""Controls outside the training box: how far outside, and what a caller's policy does with them.

The distance of a control from the box is measured where the model sees it: in the transformed
coordinate (log10 for the fluxes, the value itself otherwise), in units of the box half-width, i.e.
how far past the nearest edge of [-1, 1] the normalized input lies. 0.5 means half a half-width past
the edge; a zero flux is many half-widths below its box (log scale).

Policies (the service's `NEMSIM_EXTRAPOLATION`):
  allow   answer, and say per control how far outside the box it is;
  clip    move every control to the nearest point of the box, answer for that, and say which
          controls were moved from what to what;
  refuse  `Refused`, naming the controls outside the box and the box.

The box is the one recorded in the checkpoint (`control_ranges`), else the current design range.

Geometry (the feature drawn, `nemsim.geometry.feature.Feature`) is checked against the features the
checkpoint was trained on (`nemsim.inference.checkpoint.checkpoint_geometry`): a kind it never saw is
`UnknownGeometry` (never rolled out: the model has no notion of it), a known kind outside its trained cd or
mask range is answered, but `geometry_outside` says so and the trust verdict is `reject`, whatever the
policy (clipping a geometry would answer for another feature than the one asked).
A NEMSim model with `control_saturation` (knee, limit) has its network read every control saturated
beyond `knee` half-widths past the edge, towards at most `limit` (`nemsim.model.saturation`; the
ion-flux gate reads the value given); each excursion then also says where the network reads it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from nemsim.controls import CONTROL_SPECS, EPS_U
from nemsim.geometry.feature import Feature
from nemsim.inference.checkpoint import TrainedGeometry
from nemsim.model.saturation import saturation_point

Policy = Literal["allow", "clip", "refuse"]
POLICIES: tuple[str, ...] = ("allow", "clip", "refuse")


@dataclass(frozen=True)
class Excursion:
    """The worst value of one control outside the box (over all transitions)."""

    name: str
    unit: str
    value: float
    low: float
    high: float
    side: Literal["below", "above"]
    half_widths: float  # distance past the nearest edge, in box half-widths (transformed coordinate)
    network_half_widths: float | None = None  # where the network reads it (saturated controls), else None

    def describe(self) -> str:
        scale = ", on the log scale the model uses" if _is_log(self.name) else ""
        text = (
            f"{self.name} = {self.value:g} {self.unit} is outside the training range "
            f"{self.low:g}..{self.high:g} by {self.half_widths:.3g} box half-widths ({self.side}{scale}): "
            "the prediction is an extrapolation"
        )
        if self.network_half_widths is not None and self.network_half_widths < self.half_widths:
            text += (f"; the network reads it saturated, at {self.network_half_widths:.3g} box half-widths "
                     "(the ion-flux gate uses the value given)")
        return text

    def as_dict(self) -> dict[str, float | str | None]:
        return {
            "control": self.name,
            "value": self.value,
            "unit": self.unit,
            "train_min": self.low,
            "train_max": self.high,
            "side": self.side,
            "half_widths_outside": self.half_widths,
            "network_half_widths_outside": self.network_half_widths,
        }


def _is_log(name: str) -> bool:
    return next(s.kind for s in CONTROL_SPECS if s.name == name) == "log"


def _t(x: np.ndarray | float, log: bool) -> np.ndarray:
    return np.log10(np.asarray(x, dtype=np.float64) + EPS_U) if log else np.asarray(x, dtype=np.float64)


def excursions(raw: np.ndarray, box: dict[str, tuple[float, float]],
               saturation: tuple[float, float] | None = None) -> list[Excursion]:
    """Controls of `raw` (T, 14) or (14,) physical units outside `box` {name: (low, high)}, the worst
    value of each; `saturation`: the model's (knee, limit), if it saturates its controls."""
    rows = np.atleast_2d(np.asarray(raw, dtype=np.float64))  # (T, 14)
    out: list[Excursion] = []
    for i, spec in enumerate(CONTROL_SPECS):
        lo, hi = box[spec.name]
        log = spec.kind == "log"
        t, t_lo, t_hi = _t(rows[:, i], log), float(_t(lo, log)), float(_t(hi, log))
        half = (t_hi - t_lo) / 2.0
        below, above = t_lo - t, t - t_hi  # (T,) > 0 when outside
        k_lo, k_hi = int(np.argmax(below)), int(np.argmax(above))
        if below[k_lo] <= 0 and above[k_hi] <= 0:
            continue
        side, k, d = (
            ("below", k_lo, below[k_lo]) if below[k_lo] >= above[k_hi] else ("above", k_hi, above[k_hi])
        )
        dist = float(d / half) if half > 0 else math.inf
        seen = None if saturation is None else saturation_point(dist, *saturation)
        out.append(Excursion(spec.name, spec.unit, float(rows[k, i]), lo, hi, side, dist, seen))  # type: ignore[arg-type]
    return out


def clip(raw: np.ndarray, box: dict[str, tuple[float, float]]) -> np.ndarray:
    """`raw` (..., 14) with every control moved into its box (a copy)."""
    lo = np.array([box[s.name][0] for s in CONTROL_SPECS])
    hi = np.array([box[s.name][1] for s in CONTROL_SPECS])
    return np.clip(np.asarray(raw, dtype=np.float64), lo, hi)


def clip_notes(found: list[Excursion]) -> list[str]:
    return [
        f"{e.name} clipped from {e.value:g} to {e.low if e.side == 'below' else e.high:g} {e.unit} "
        f"(training range {e.low:g}..{e.high:g}; {e.half_widths:.3g} box half-widths {e.side} it)"
        for e in found
    ]


def refusal(found: list[Excursion]) -> str:
    return (
        "controls outside the training box are refused by this server (extrapolation policy 'refuse'): "
        + "; ".join(
            f"{e.name} = {e.value:g} {e.unit} "
            f"({e.half_widths:.3g} box half-widths {e.side} {e.low:g}..{e.high:g})"
            for e in found
        )
    )


class Refused(ValueError):
    """The policy is `refuse` and some control is outside the box (the message names them)."""


def apply(
    raw: np.ndarray, box: dict[str, tuple[float, float]], policy: str,
    saturation: tuple[float, float] | None = None,
) -> tuple[np.ndarray, list[str], list[Excursion], bool]:
    """(controls to use, warnings, excursions of the given controls, clipped?) under `policy`;
    `saturation`: the model's control saturation (knee, limit), if any (module docstring)."""
    if policy not in POLICIES:
        raise ValueError(f"extrapolation policy {policy!r}; expected one of {list(POLICIES)}")
    found = excursions(raw, box, saturation)
    if not found:
        return raw, [], [], False
    if policy == "refuse":
        raise Refused(refusal(found))
    if policy == "clip":
        return clip(raw, box), clip_notes(found), found, True
    return raw, [e.describe() for e in found], found, False


class UnknownGeometry(ValueError):
    """The feature's kind is not one the checkpoint was trained on (the message names the kinds it knows)."""


def check_kind(feature: Feature, trained: TrainedGeometry) -> None:
    """`UnknownGeometry` unless the checkpoint was trained on `feature`'s kind."""
    if trained.range_of(feature.kind) is None:
        known = " and ".join(trained.kinds)
        raise UnknownGeometry(
            f"this model was trained on {known} features only; a {feature.kind} is not answered "
            f"(kinds it knows: {list(trained.kinds)})"
        )


def geometry_outside(feature: Feature, trained: TrainedGeometry) -> str | None:
    """A one-line reason when `feature` (a kind the checkpoint knows, as built on the grid) lies outside
    the trained range of its kind, naming both; None inside."""
    found = trained.range_of(feature.kind)
    if found is None or found.contains(feature):
        return None
    return (
        f"geometry {feature.kind} cd {feature.cd_nm:g} nm, mask {feature.mask_nm:g} nm is outside the "
        f"features this model was trained on ({found.describe()}): the prediction is an extrapolation "
        "in geometry"
    )
