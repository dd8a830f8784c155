"""`bench responses`: least-squares slopes of the final profile metrics on the controls, simulator's data
against the surrogate's rollouts."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.responses import fit_linear, response_rows, summarize
from nemsim.controls import CONTROL_INDEX, N_CONTROLS

CL = CONTROL_INDEX["flux_cl"]


def test_fit_linear_recovers_a_plane_and_its_noise():
    rng = np.random.default_rng(0)
    u = rng.uniform(-1, 1, size=(400, N_CONTROLS))
    y = 2.0 + 3.0 * u[:, 0] - 1.0 * u[:, 5]
    coef, se = fit_linear(u, y)
    np.testing.assert_allclose(coef[[0, 1, 6]], [2.0, 3.0, -1.0], atol=1e-10)
    assert np.all(se < 1e-10)
    # noise of sd 0.5: the standard error of a slope is about sd / sqrt(N var(u)) = 0.5 / sqrt(400 / 3)
    coef, se = fit_linear(u, y + rng.normal(0, 0.5, size=400))
    assert se[1] == pytest.approx(0.5 / np.sqrt(400 / 3), rel=0.15)
    assert abs(coef[1] - 3.0) < 4 * se[1]
    with pytest.raises(ValueError, match="more than 15 cases"):
        fit_linear(u[:15], y[:15])


def test_response_rows_ratio_sign_and_resolution():
    """A model with half the simulator's depth response is resolved but off; the right response is within
    ±25 %; an opposite one has the wrong sign; a control the data do not move is not resolved."""
    rng = np.random.default_rng(1)
    u = rng.uniform(-1, 1, size=(200, N_CONTROLS))
    noise = rng.normal(0, 0.1, size=200)
    sim = {m: noise.copy() for m in ("etch_depth", "top_width", "bottom_width", "mask_loss", "bowing")}
    sim["etch_depth"] = 10 * u[:, CL] + noise
    sim["bottom_width"] = -4 * u[:, CL] + noise
    sim["top_width"] = 2 * u[:, 0] + noise
    model = {**sim, "etch_depth": 5 * u[:, CL], "bottom_width": 4 * u[:, CL], "top_width": 2.1 * u[:, 0]}
    rows = {(r["metric"], r["control"]): r for r in response_rows(u, sim, model)}
    depth = rows[("etch_depth", "flux_cl")]
    assert depth["resolved"] and depth["ratio"] == pytest.approx(0.5, abs=0.02) and not depth["within"]
    bottom = rows[("bottom_width", "flux_cl")]
    assert bottom["resolved"] and not bottom["same_sign"] and not bottom["within"]
    top = rows[("top_width", "flux_ar_plus")]
    assert top["resolved"] and top["within"]
    assert not rows[("mask_loss", "flux_cl")]["resolved"]
    s = summarize(list(rows.values()))
    assert s["resolved"] >= 3 and s["wrong_sign"] >= 1 and s["within_25pct"] >= 1


def test_cli_bench_responses_on_a_data_file(tiny_checkpoint, tiny_scene, tmp_path, make_hole, capsys):
    """A data file whose final hole depth rises with the neutral Cl flux: the report resolves that slope
    (2 voxels of 8 nm per normalized unit), rolls the surrogate out on every case, and refuses bad input."""
    from nemsim.cli import main
    from nemsim.controls import from_unit, lhs_unit, to_normalized
    from nemsim.data.hdf5 import TrajectoryWriter
    from nemsim.rules import compile_rules, load_rules
    from nemsim.sim import SimConfig, initial_state
    from nemsim.sim.generate import generator_meta

    n = 20
    raw = from_unit(lhs_unit(n, seed=3))
    u = to_normalized(raw)
    data = tmp_path / "tiny.h5"
    x0 = initial_state(tiny_scene)
    with TrajectoryWriter(data, scene=tiny_scene, case_ids=list(range(n)), controls_raw=raw,
                          generator=generator_meta(tiny_scene, SimConfig(), 0),
                          rules_sha256=compile_rules(load_rules()).sha256) as writer:
        for row in range(n):
            states = np.repeat(x0[None], tiny_scene.n_states, axis=0)
            states[-1] = make_hole(tiny_scene, 2.5, 6.0 + 2.0 * u[row, CL])
            writer.write(row, states, seed=row)
    out = tmp_path / "resp"
    assert main(["bench", "responses", "--checkpoint", str(tiny_checkpoint), "--data", str(data),
                 "--no-progress", "--out", str(out)]) == 0
    rep = json.loads((out / "responses.json").read_text())
    assert rep["n_cases"] == n and (out / "responses.png").is_file() and (out / "responses.md").is_file()
    depth = next(r for r in rep["rows"] if r["metric"] == "etch_depth" and r["control"] == "flux_cl")
    assert depth["resolved"] and depth["slope_sim"] == pytest.approx(16.0, rel=0.15)
    assert "resolved slopes within" in capsys.readouterr().out
    # --one-call: one call (k = 1 here) from the simulator's own state at T - 1 (the initial state in this
    # file) to T (the hole): the increment's slope is the final depth's, from one network call
    T = tiny_scene.n_states - 1
    one = tmp_path / "resp-one"
    assert main(["bench", "responses", "--checkpoint", str(tiny_checkpoint), "--data", str(data),
                 "--one-call", str(T - 1), "--no-progress", "--out", str(one)]) == 0
    rep1 = json.loads((one / "responses.json").read_text())
    assert rep1["one_call"] == {"t0": T - 1, "k": 1} and rep1["n_cases"] == n
    depth1 = next(r for r in rep1["rows"] if r["metric"] == "etch_depth" and r["control"] == "flux_cl")
    assert depth1["slope_sim"] == pytest.approx(depth["slope_sim"], rel=1e-6)
    assert "increments over one call (1 step) from the simulator's state at step" in capsys.readouterr().out
    assert main(["bench", "responses", "--checkpoint", str(tiny_checkpoint), "--data", str(data),
                 "--one-call", str(T), "--no-progress", "--out", str(one)]) == 2  # the call leaves the data
    assert main(["bench", "responses", "--checkpoint", str(tiny_checkpoint), "--data", str(data),
                 "--max-cases", "10", "--no-progress", "--out", str(out)]) == 2  # 10 cases: too few
    assert main(["bench", "responses", "--checkpoint", str(tiny_checkpoint), "--data",
                 str(tmp_path / "no.h5")]) == 2
