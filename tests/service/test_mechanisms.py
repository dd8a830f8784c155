"""GET /mechanisms: the same library function as `nemsim counterfactual`."""

from __future__ import annotations

import pytest


def test_default_base(client):
    r = client.get("/mechanisms")
    assert r.status_code == 200, r.text
    body = r.json()
    from service.schemas import default_controls_raw

    assert list(body["controls"].values()) == pytest.approx(list(default_controls_raw()))
    res = body["result"]
    assert res["families"] == ["physical", "chemical", "coupled"]
    assert len(res["interventions"]) == 8
    pairs = {(i["s_cl_plus"], i["s_cl"]) for i in res["interventions"]}
    assert (1.0, 1.0) not in pairs and (1.5, 0.5) in pairs
    assert set(res["interventions"][0]["delta_M_pct"]) == set(res["families"])
    assert "delta_R_pct" in res["interventions"][0]
    assert len(res["base"]["lambda"]) == 37 and len(res["base"]["alpha"]) == 37


def test_matches_library(client, served):
    """Same numbers as calling mechanism_response directly (what `nemsim counterfactual` does)."""
    import numpy as np

    from nemsim.analysis.counterfactual import mechanism_response
    from service.schemas import default_controls_raw

    raw = default_controls_raw()
    raw[3] *= 2.0  # flux_cl
    body = client.get("/mechanisms", params={"flux_cl": float(raw[3])}).json()
    direct = mechanism_response(served.predictor.loaded, raw, x0=served.predictor.x0)
    assert body["result"]["base"]["lambda"] == pytest.approx(direct["base"]["lambda"], rel=1e-5)
    got = [i["delta_R_pct"] for i in body["result"]["interventions"]]
    want = [i["delta_R_pct"] for i in direct["interventions"]]
    assert np.allclose(np.array(got, dtype=float), np.array(want, dtype=float), equal_nan=True)


def test_custom_factors(client):
    r = client.get("/mechanisms", params=[("factors", "0.25"), ("factors", "2")])
    assert r.status_code == 200, r.text
    assert len(r.json()["result"]["interventions"]) == 8
    r = client.get("/mechanisms", params=[("factors", "0.5")])
    assert len(r.json()["result"]["interventions"]) == 3


def test_out_of_range_warns(client):
    r = client.get("/mechanisms", params={"energy_mean_ar_plus": 5000.0})
    assert r.status_code == 200 and "energy_mean_ar_plus" in r.json()["warnings"][0]


@pytest.mark.parametrize(
    "params",
    [
        {"flux_cl": -1.0},
        {"energy_mean_cl_plus": -2},
        {"flux_cl": "nan"},
        {"flux_cl": "inf"},
        {"flux_cl": "lots"},
        {"temperature": 300},
        {"factors": 0},
        {"factors": -1},
    ],
)
def test_bad_query_422(client, params):
    r = client.get("/mechanisms", params=params)
    assert r.status_code == 422, (params, r.text)
    assert r.json()["message"]
