"""bench.pair_noise: the seed noise of a sweep pair's difference in both random-number modes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bench.pair_noise import (
    PAIR_METRICS,
    field_times,
    format_markdown,
    main,
    pair_statistics,
    pooled_ratios,
    simulate_pair_noise,
)


def test_pair_statistics_by_hand():
    # three seeds; member a is a[s] everywhere, member b is b[s]: D = (2, 1, 3), std 1; var a = 1, var b = 3
    a, b = np.array([0.0, 1.0, 2.0]), np.array([2.0, 2.0, 5.0])
    shape = (3, 2, 2, 1, 1, 2)  # (seeds, kept transitions, channels, D, H, W)
    xa = np.broadcast_to(a[:, None, None, None, None, None], shape)
    xb = np.broadcast_to(b[:, None, None, None, None, None], shape)
    metrics_a = {k: a + i for i, k in enumerate(PAIR_METRICS)}  # a shift leaves every spread alone
    metrics_b = {k: b + i for i, k in enumerate(PAIR_METRICS)}
    r = pair_statistics(xa, xb, metrics_a, metrics_b, [1, 5])
    for k in ("field", "field_final", *PAIR_METRICS):
        assert r["paired"][k] == pytest.approx(1.0)
        assert r["independent"][k] == pytest.approx(2.0)  # sqrt(1 + 3)
        assert r["ratio"][k] == pytest.approx(0.5)
    assert r["field_ratio_by_time"] == {"1": pytest.approx(0.5), "5": pytest.approx(0.5)}
    assert r["response"]["etch_depth"] == pytest.approx(2.0)
    assert r["response_se"]["top_width"] == pytest.approx(1 / math.sqrt(3))
    lo, hi = r["ratio_ci90"]["bottom_width"]
    assert 0.0 <= lo <= 0.5 <= hi
    # pooled over two pairs: sqrt((1 + 3^2) / (2^2 + 4^2))
    other = {"paired": {"field": 3.0}, "independent": {"field": 4.0}}
    pooled = pooled_ratios({"q": {"counter": other}, "p": {"counter": r}}, ["counter"])  # q names the keys
    assert pooled == {"counter": {"field": pytest.approx(math.sqrt(0.5))}}
    assert field_times(100, 5)[:4] == [1, 2, 5, 10] and field_times(100, 5)[-1] == 100
    assert field_times(3, 5) == [1, 2, 3]


def test_pair_noise_reports_both_modes_for_every_pair(tiny_scene, rules):
    pairs = {"flux": ({}, {"flux_cl_plus": 1e-3}),  # from the design centre (8.4e-4)
             "angle": ({"angle_cl_plus": 50.0}, {"angle_cl_plus": 3000.0})}  # fmt: skip
    rep = simulate_pair_noise(tiny_scene, rules, pairs, seeds=(1, 2, 3), n_transitions=8)
    assert rep["steps"] == 8 and rep["field_times"] == [1, 2, 5, 8] and rep["domain"] == "full"
    assert set(rep["speed"]) == set(rep["summary"]) == {"stream", "counter"}
    for row in rep["pairs"].values():
        for mode in ("stream", "counter"):
            for part in ("paired", "independent", "ratio"):
                assert set(row[mode][part]) == {"field", "field_final", *PAIR_METRICS}
            assert row[mode]["independent"]["field"] > 0.0
    # a shared seed of the counter streams takes most of the early noise out of the pair's difference
    flux = rep["pairs"]["flux"]
    assert flux["counter"]["ratio"]["field"] < 0.7 < flux["stream"]["ratio"]["field"]
    assert flux["counter"]["field_ratio_by_time"]["1"] < 0.5
    text = format_markdown(rep, "cmd", "cpu")
    assert "| flux | counter |" in text and "Speed" in text and "Command: `cmd`" in text


def test_main_writes_results_for_one_mode(tmp_path, capsys):
    main(["--scene", "tiny", "--seeds", "2", "--steps", "2", "--rng", "counter", "--out", str(tmp_path)])
    rep = json.loads((tmp_path / "results.json").read_text())
    assert rep["modes"] == ["counter"] and rep["seeds"] == [1, 2] and rep["steps"] == 2
    assert rep["command"].endswith("--rng counter --out " + str(tmp_path)) and rep["cpu"]
    assert len(rep["pairs"]) == 4 and "stream" not in rep["pairs"]["flux_cl +10 %"]
    text = (tmp_path / "results.md").read_text()
    assert text.startswith("# Seed noise of sweep-pair differences on `tiny`")
    capsys.readouterr()
