"""What a design result claims: intervals cut to each metric's physical range, and each recipe's verdict
(predicted by the surrogate or confirmed by the simulator) with whether its intervals fit the tolerances."""

from __future__ import annotations

import copy

import pytest

from nemsim.analysis.intervals import Calibration
from nemsim.analysis.inverse import label_recipes, misses, spec_from_dict, target_range
from nemsim.analysis.inverse.surrogate_search import _intervals_at
from nemsim.scenes import SMALL

SPEC = spec_from_dict(
    {"targets": {"etch_depth": {"value": 60, "tol": 5}, "mask_loss": {"value": 4, "tol": 2}}}
)


def _calibration(lower: float | None, upper: float | None) -> Calibration:
    per = {"lower": [lower] * 11, "upper": [upper] * 11}
    metrics = ("etch_depth", "top_width", "neck_width", "mask_loss")
    return Calibration(
        checkpoint_sha256="0" * 12,
        scene="small",
        levels=(0.9,),
        metrics=metrics,
        offsets={"0.9": {m: per for m in metrics}},
        calibration={"setting": "control-id", "split": "val", "cases": 3},
    )


@pytest.mark.parametrize("lower, upper", [(-40.0, 40.0), (None, None), (-500.0, -400.0)])
def test_intervals_never_leave_the_physical_range(lower, upper):
    """The issue's 161.7 nm depth bound on a 160 nm Si layer: cut to [0, Si thickness]; widths to the
    domain, mask loss to the mask; an unbounded side becomes the range's end."""
    at = {"etch_depth": 150.0, "top_width": 100.0, "neck_width": 2.0, "mask_loss": 1.0}
    iv = _intervals_at(_calibration(lower, upper), at, 10, SMALL)["0.9"]
    assert set(iv) == set(at)
    for m, (lo, hi) in iv.items():
        low, high, _ = target_range(m, SMALL)
        assert low <= lo <= hi <= high, (m, lo, hi)
    assert target_range("etch_depth", SMALL)[1] == 160.0 and target_range("mask_loss", SMALL)[1] == 80.0
    if upper is None or upper > 0:
        assert iv["etch_depth"][1] == 160.0 and iv["mask_loss"][0] == 0.0  # cut, not dropped
    if lower == -40.0:
        assert iv["etch_depth"][0] == 110.0  # a side inside the range is left alone


def _recipe(rank: int, depth: float, band: float) -> dict:
    predicted = {"etch_depth": depth, "mask_loss": 4.0}
    return {
        "rank": rank,
        "predicted": predicted,
        "targets": misses(predicted, SPEC),
        "intervals": {"0.9": {m: [v - band, v + band] for m, v in predicted.items()}},
    }


def test_a_prediction_is_never_called_confirmed():
    """Only the surrogate has spoken: met or missed as predicted, and whether the interval fits."""
    res = {"recipes": [_recipe(1, 61.0, 9.7), _recipe(2, 59.0, 1.0), _recipe(3, 80.0, 1.0)]}
    out = label_recipes(res, SPEC)["recipes"]
    assert [r["verdict"] for r in out] == ["predicted", "predicted", "predicted_miss"]
    # 51.3..70.7 against 55..65: met as predicted, but the interval is wider than the tolerance
    assert out[0]["intervals_within_tolerance"] == {"0.9": False}
    assert out[1]["intervals_within_tolerance"] == {"0.9": True}
    assert all("verified_by" not in r for r in out)  # nothing was simulated


def _run(rank: int, depth: float) -> dict:
    """A plain verification's entry (``verify_recipe``'s fields that labelling reads)."""
    achieved = {"etch_depth": depth, "mask_loss": 4.5}
    t = misses(achieved, SPEC)
    return {"rank": rank, "achieved": achieved, "targets": t, "met": all(v["met"] for v in t.values())}


def test_a_plain_verification_confirms_or_refutes_its_recipes():
    res = {"recipes": [_recipe(1, 61.0, 9.7), _recipe(2, 59.0, 1.0)]}
    res["verification"] = {"recipes": [_run(1, 71.0)]}
    again = label_recipes(copy.deepcopy(res), SPEC)
    out = label_recipes(res, SPEC)["recipes"]
    assert label_recipes(again, SPEC) == res  # idempotent
    assert out[0]["verdict"] == "simulator_miss" and out[0]["verified_by"] == "simulator"
    assert out[0]["simulated"]["etch_depth"] == 71.0 and not out[0]["simulated_targets"]["etch_depth"]["met"]
    assert out[1]["verdict"] == "predicted" and out[1]["verified_by"] == "surrogate"
    res["verification"]["recipes"] = [_run(1, 62.0)]
    assert label_recipes(res, SPEC)["recipes"][0]["verdict"] == "confirmed"


@pytest.mark.parametrize("met, confirmed, verdict", [
    (True, None, "confirmed"),  # no confirmation simulator: its one run decides
    (True, True, "confirmed"),
    (True, False, "simulator_miss"),  # met once, missed in the independent run
    (False, None, "simulator_miss"),
])
def test_a_refined_designs_recipe_is_confirmed_only_by_its_runs(met, confirmed, verdict):
    rec = {**_recipe(1, 61.0, 1.0), "verified_by": "simulator", "simulator_met": met}
    if confirmed is not None:
        rec["confirmed"] = confirmed
    res = {"recipes": [rec], "verification": {"recipes": [{"rank": 1, "round": 0, "met": met}]}}
    assert label_recipes(res, SPEC)["recipes"][0]["verdict"] == verdict
