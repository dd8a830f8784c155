"""Controls outside the training box in the service (NEMSIM_EXTRAPOLATION = allow | clip | refuse), and
what /model says of the initial state (the predictor's own: tests/inference/test_predictor.py)."""

from __future__ import annotations

import numpy as np
import pytest


def _outside(default_controls):
    # flux_cl 10x the box maximum (log scale: log10(10) / half-width), energy 100 eV above 500
    return {**default_controls, "flux_cl": 0.2, "energy_mean_ar_plus": 600.0}


def test_allow_quantifies_the_distance(client, default_controls):
    r = client.post("/rollout", json={"controls": _outside(default_controls), "steps": 1})
    assert r.status_code == 200 and not r.json()["clipped"]
    ex = {e["control"]: e for e in r.json()["extrapolation"]}
    assert set(ex) == {"flux_cl", "energy_mean_ar_plus"}
    half = (np.log10(2e-2) - np.log10(1e-3)) / 2
    assert ex["flux_cl"]["half_widths_outside"] == pytest.approx(1.0 / half, rel=1e-6)
    assert ex["energy_mean_ar_plus"]["half_widths_outside"] == pytest.approx(100 / 170)
    assert ex["energy_mean_ar_plus"]["side"] == "above" and ex["energy_mean_ar_plus"]["train_max"] == 500
    assert any("flux_cl" in w and "half-widths" in w for w in r.json()["warnings"])
    assert r.json()["controls"]["flux_cl"] == 0.2


def test_in_box_has_no_excursions(client, default_controls):
    r = client.post("/rollout", json={"controls": default_controls, "steps": 1})
    assert r.json()["extrapolation"] == [] and r.json()["warnings"] == []


def test_zero_flux_is_below_the_box(client, default_controls):
    r = client.post("/rollout", json={"controls": {**default_controls, "flux_cl": 0.0}, "steps": 1})
    (ex,) = r.json()["extrapolation"]
    assert ex["control"] == "flux_cl" and ex["side"] == "below" and ex["half_widths_outside"] > 10


def test_allow_says_where_the_network_reads_a_saturated_control(client, default_controls):
    """The served model saturates its controls (``control_saturation``): each excursion says at what
    distance its network reads the control, and the warning says so when that is nearer than given."""
    from nemsim.model.saturation import CONTROL_SATURATION, saturation_point

    knee, limit = CONTROL_SATURATION
    r = client.post("/rollout", json={"controls": {**default_controls, "flux_cl": 0.0}, "steps": 1})
    (ex,) = r.json()["extrapolation"]
    assert ex["network_half_widths_outside"] == pytest.approx(limit, abs=1e-6)  # zero flux: at the limit
    assert any("saturated" in w and "ion-flux gate" in w for w in r.json()["warnings"])
    r = client.post("/rollout", json={"controls": _outside(default_controls), "steps": 1})
    for e in r.json()["extrapolation"]:
        seen = saturation_point(e["half_widths_outside"], knee, limit)
        assert e["network_half_widths_outside"] == pytest.approx(seen)
        assert e["network_half_widths_outside"] <= e["half_widths_outside"]


def test_clip(make_client, default_controls):
    c = make_client(extrapolation="clip")
    r = c.post("/rollout", json={"controls": _outside(default_controls), "steps": 1})
    assert r.status_code == 200 and r.json()["clipped"]
    assert r.json()["controls"]["flux_cl"] == pytest.approx(2e-2)
    assert r.json()["controls"]["energy_mean_ar_plus"] == 500.0
    notes = " ".join(r.json()["warnings"])
    assert (
        "flux_cl clipped from 0.2 to 0.02" in notes and "energy_mean_ar_plus clipped from 600 to 500" in notes
    )
    # the same as asking for the clipped controls directly (same rollout id)
    inside = {**default_controls, "flux_cl": 2e-2, "energy_mean_ar_plus": 500.0}
    assert c.post("/rollout", json={"controls": inside, "steps": 1}).json()["id"] == r.json()["id"]
    m = c.get("/mechanisms", params={"energy_mean_ar_plus": 600.0})
    assert (
        m.status_code == 200 and m.json()["clipped"] and m.json()["controls"]["energy_mean_ar_plus"] == 500.0
    )


def test_refuse(make_client, default_controls):
    c = make_client(extrapolation="refuse")
    r = c.post("/rollout", json={"controls": _outside(default_controls), "steps": 1})
    assert r.status_code == 422
    msg = r.json()["message"]
    assert "flux_cl" in msg and "energy_mean_ar_plus" in msg and "160..500" in msg and "refuse" in msg
    assert c.post("/rollout", json={"controls": default_controls, "steps": 1}).status_code == 200
    assert c.get("/mechanisms", params={"flux_cl": 0.2}).status_code == 422
    assert c.get("/model").json()["extrapolation"] == "refuse"


def test_bad_policy_setting():
    from pydantic import ValidationError

    from service.config import Settings

    with pytest.raises(ValidationError, match="allow"):
        Settings(extrapolation="sometimes")


# --- initial state from the checkpoint's simulator configuration ------------------------------------


def test_old_checkpoint_uses_simulator_defaults(client, served, tiny_scene):
    from nemsim.sim import initial_state

    assert "defaults" in client.get("/model").json()["initial_state"]
    want = np.asarray(initial_state(tiny_scene), dtype=np.float32)
    np.testing.assert_array_equal(served.predictor.x0, want)
