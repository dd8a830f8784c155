"""Physical invariants against the simulator (bench.invariants) on `tiny`, with stub surrogates
whose behaviour is known: a plausible one passes, each deliberately broken one is flagged by its check."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from bench.invariants import (
    InvariantConfig,
    format_invariants,
    ions_off_recipes,
    monotone_grid,
    read_noise,
    run_invariants,
    write_noise,
    zero_flux_recipes,
)
from nemsim.controls import CONTROL_INDEX, FLUX_INDICES, to_normalized

torch.set_num_threads(1)
STEPS = 5  # simulated transitions: enough for the ion fluxes to move the depth beyond the seed noise


CFG = InvariantConfig(pair_bases=0, levels=3)


def _rows(rep):
    return {r["name"]: r for r in rep["invariants"]}


ION = [CONTROL_INDEX[n] for n in ("flux_ar_plus", "flux_cl_plus", "flux_cl2_plus")]
ENERGY = [CONTROL_INDEX[n] for n in ("energy_mean_cl_plus", "energy_mean_cl2_plus", "energy_mean_ar_plus")]


def run(model, truth, x0, noise=None):
    return run_invariants(model, truth, x0, CFG, long_steps=8, noise=noise)


def test_recipes():
    for raw in zero_flux_recipes().values():
        assert np.all(raw[list(FLUX_INDICES)] == 0)
    for raw in ions_off_recipes().values():
        assert np.all(raw[ION] == 0) and raw[CONTROL_INDEX["flux_cl"]] > 0
    grid = monotone_grid(InvariantConfig(pair_bases=1, levels=3))
    assert len(grid) == 2 * 4  # (centre + 1 base) x 4 axes
    line = next(g for g in grid if g["axis"] == "ion_energy")
    u = to_normalized(line["raw"])
    np.testing.assert_allclose(u[:, ENERGY], np.repeat([[-1.0], [0.0], [1.0]], 3, axis=1), atol=1e-9)
    others = [j for j in range(14) if j not in ENERGY]
    assert np.allclose(line["raw"][:, others], line["raw"][0, others])


def test_plausible_model_passes(truth, x0, stubs):
    rep = run(stubs.Plausible(), truth, x0)
    rows = _rows(rep)
    assert rep["passed"], format_invariants(rep)
    # the grid exercised the response check: the simulator clearly deepens with the Ar+ and Cl+ fluxes
    assert rows["responds where the simulator does"]["checked"] >= 2
    assert rows["depth non-decreasing in flux_ar_plus"]["simulator_violations"] == 0
    tol = rep["tolerances"]
    assert tol["rmse"] > 0 and tol["depth_nm"] > 0 and tol["depth_decrease_nm"] >= CFG.depth_decrease_floor_nm
    json.dumps(rep)


def test_no_change_model_is_caught_only_by_the_response_check(truth, x0, stubs):
    rep = run(stubs.NoChange(), truth, x0)
    failed = {r["name"] for r in rep["invariants"] if r["violations"]}
    assert failed == {"responds where the simulator does"}
    assert not rep["passed"]


def test_etching_without_flux_is_flagged(truth, x0, stubs):
    rows = _rows(run(stubs.EtchesWithoutFlux(), truth, x0))
    for name in ("zero flux: state", "zero flux: depth", "zero flux: mask loss", "ions off: state",
                 "ions off: depth", "mask loss >= -tol"):
        assert rows[name]["violations"] == rows[name]["checked"] > 0, name
    assert rows["depth never decreases"]["violations"] == 0


def test_unetching_and_reversed_flux_response_are_flagged(truth, x0, stubs):
    rows = _rows(run(stubs.Unetches(), truth, x0))
    assert rows["depth never decreases"]["violations"] == rows["depth never decreases"]["checked"]
    rows = _rows(run(stubs.Plausible(sign=-1.0), truth, x0))
    assert rows["depth non-decreasing in flux_ar_plus"]["violations"] == 2  # both pairs of the 3-level line
    assert rows["depth non-decreasing in flux_cl_plus"]["violations"] == 0


def test_noise_file_round_trip(truth, x0, tmp_path, tiny_scene, stubs):
    rep = run(stubs.Plausible(), truth, x0)
    path = tmp_path / "noise.json"
    write_noise(path, rep["noise"])
    noise = read_noise(path, tiny_scene.name)
    again = run(stubs.Plausible(), truth, x0, noise=noise)
    assert again["tolerances"] == rep["tolerances"]
    with pytest.raises(ValueError, match="scene"):
        read_noise(path, "small")
    path.write_text("{}")
    with pytest.raises(ValueError, match="lacks"):
        read_noise(path, tiny_scene.name)


def test_cli_stress_invariants_exit_codes(tmp_path, tiny_scene, monkeypatch, stubs):
    """The suite's exit code: 0 for a plausible model, 1 for one that etches without flux; bad flags 2."""
    import nemsim.cli as cli
    from nemsim.inference.checkpoint import LoadedModel

    def fake_loader(model):
        from nemsim.rules import compile_rules, load_rules

        return lambda path: LoadedModel(model=model, name="stub", config={}, scene=tiny_scene,
                                        rules=compile_rules(load_rules()))

    args = ["stress", "--checkpoint", "stub.pt", "--steps", "6", "--max-corners", "2", "--noise-cases", "0",
            "--sim-steps", str(STEPS), "--pair-bases", "0", "--no-progress",
            "--cache-dir", str(tmp_path / "c")]
    import nemsim.inference.checkpoint as ck

    monkeypatch.setattr(ck, "load_checkpoint", fake_loader(stubs.Plausible()))
    out = tmp_path / "ok.json"
    assert cli.main(args + ["--json", str(out), "--noise-out", str(tmp_path / "noise.json")]) == 0
    rep = json.loads(out.read_text())
    assert rep["passed"] and rep["invariants"]["passed"]
    monkeypatch.setattr(ck, "load_checkpoint", fake_loader(stubs.EtchesWithoutFlux()))
    assert cli.main(args + ["--noise", str(tmp_path / "noise.json")]) == 1
    assert cli.main(args + ["--seeds", "1,1"]) == 2
    assert cli.main(args + ["--levels", "1"]) == 2


def test_monotone_pair_is_held_to_the_truth_where_the_simulator_itself_falls():
    from bench.invariants import pair_ok

    tol = 2.23  # nm, seed-to-seed depth difference
    assert pair_ok(-2.0, +5.0, tol) and not pair_ok(-2.5, +5.0, tol)  # the law holds in the truth: -tol
    assert pair_ok(-2.48, -2.5, tol)  # the simulator's own pair falls as much: not the model's violation
    assert not pair_ok(-6.0, -2.5, tol)  # falls by more than the truth plus the tolerance
