"""bench.pair_noise: the seed noise of a sweep pair's difference in both random-number modes."""

from __future__ import annotations

from bench.pair_noise import PAIR_METRICS, format_markdown, simulate_pair_noise


def test_pair_noise_reports_both_modes_for_every_pair(tiny_scene, rules):
    pairs = {"flux": ({}, {"flux_cl_plus": 1e-3}),  # from the design centre (8.4e-4)
             "angle": ({"angle_cl_plus": 50.0}, {"angle_cl_plus": 3000.0})}
    rep = simulate_pair_noise(tiny_scene, rules, pairs, seeds=(1, 2, 3), n_transitions=8)
    assert rep["steps"] == 8 and set(rep["speed"]) == {"stream", "counter"}
    for row in rep["pairs"].values():
        for mode in ("stream", "counter"):
            for part in ("paired", "independent"):
                assert set(row[mode][part]) == {"field", "field_final", *PAIR_METRICS}
                assert row[mode][part]["field"] > 0.0
    # the shared counter streams take most of the early noise out of the pair's difference
    for row in rep["pairs"].values():
        assert row["counter"]["paired"]["field"] < 0.7 * row["counter"]["independent"]["field"]
    text = format_markdown(rep)
    assert "| flux | counter |" in text and "Speed" in text
