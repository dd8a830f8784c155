"""``nemsim.inference.Predictor``: physical controls normalized once at its boundary, the rollout and metrics
of the library functions it wraps, the initial state from the checkpoint's simulator configuration, the
range check, the stability guard, and OpenVINO against PyTorch."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from nemsim.controls import CONTROL_NAMES, CONTROL_SPECS, to_normalized
from nemsim.inference import ControlSchedule, Predictor, control_schedule, stability_warnings
from nemsim.inference.runtime import openvino_available

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def predictor(tiny_checkpoint):
    return Predictor.from_checkpoint(tiny_checkpoint, backend="torch")


def _mid() -> dict[str, float]:
    return {s.name: (s.low + s.high) / 2 for s in CONTROL_SPECS}


def test_physical_mapping_gives_the_rollout_of_the_library(predictor):
    """A mapping of physical controls gives exactly the trajectory and metrics of `rollout` on the
    normalized vector (the path callers wrote by hand before) and of `measured_profile_metrics`."""
    from nemsim.evaluation.rollout import rollout
    from nemsim.geometry.profile import measured_profile_metrics

    controls, steps = _mid(), 3
    pred = predictor.rollout(controls, steps)
    raw = np.array([controls[n] for n in CONTROL_NAMES])
    u = torch.from_numpy(np.asarray(to_normalized(np.tile(raw, (steps, 1))), dtype=np.float32))[None]
    with torch.inference_mode():
        ref = rollout(predictor.runtime, torch.from_numpy(predictor.x0)[None], u, steps)[0].numpy()
    np.testing.assert_array_equal(pred.states, ref)
    for name, values in measured_profile_metrics(ref, predictor.scene).items():
        np.testing.assert_array_equal(pred.metrics[name], values)
    assert pred.steps == steps and len(pred.times_s) == steps + 1
    np.testing.assert_array_equal(pred.schedule.raw, np.tile(raw, (steps, 1)))


def test_controls_are_normalized_once(predictor, monkeypatch):
    """One normalization per schedule of physical controls, none for normalized input (read as given);
    a schedule passed on is never converted again."""
    import nemsim.inference.predictor as module

    calls: list[tuple[int, ...]] = []
    original = module.to_normalized

    def counting(raw):
        calls.append(np.shape(raw))
        return original(raw)

    monkeypatch.setattr(module, "to_normalized", counting)
    schedule = predictor.schedule(_mid(), 2)
    predictor.rollout(schedule)
    assert calls == [(2, 14)]
    u = np.full((2, 14), 0.25, dtype=np.float32)
    given = ControlSchedule.from_normalized(u)
    pred = predictor.rollout(given)
    assert calls == [(2, 14)] and pred.schedule.normalized is given.normalized
    np.testing.assert_array_equal(given.normalized, u)
    np.testing.assert_allclose(to_normalized(given.raw), u, atol=1e-6)  # the derived physical values


def test_time_varying_schedule(predictor):
    a, b = _mid(), {**_mid(), "flux_cl": 2e-3}
    pred = predictor.rollout([a, b, a])
    assert pred.steps == 3 and pred.schedule.raw[1, CONTROL_NAMES.index("flux_cl")] == 2e-3
    same = predictor.rollout(np.stack([[c[n] for n in CONTROL_NAMES] for c in (a, b, a)]))
    np.testing.assert_array_equal(pred.states, same.states)


@pytest.mark.parametrize(
    ("controls", "steps", "match"),
    [
        ({**_mid(), "flux_xx": 1.0}, 2, "unknown"),
        ({k: v for k, v in _mid().items() if k != "flux_cl"}, 2, "missing"),
        (_mid(), None, "steps"),
        ([_mid(), _mid()], 3, "one per transition"),
        (np.zeros((2, 13)), None, "shape"),
    ],
)
def test_bad_controls_are_value_errors(controls, steps, match):
    with pytest.raises(ValueError, match=match):
        control_schedule(controls, steps)


def test_range_check_clips_in_physical_units(predictor):
    outside = {**_mid(), "flux_cl": 0.2, "energy_mean_ar_plus": 600.0}
    schedule = predictor.schedule(outside, 1)
    same, warnings, found, clipped = predictor.check_range(schedule, "allow")
    assert same is schedule and not clipped and {e.name for e in found} == {"flux_cl", "energy_mean_ar_plus"}
    assert len(warnings) == 2
    inside, _, _, clipped = predictor.check_range(schedule, "clip")
    assert clipped and inside.raw[0, CONTROL_NAMES.index("energy_mean_ar_plus")] == 500.0
    np.testing.assert_array_equal(inside.normalized, predictor.schedule(inside.raw).normalized)
    from nemsim.inference import Refused

    with pytest.raises(Refused, match="flux_cl"):
        predictor.check_range(schedule, "refuse")


def test_model_id_and_facts(predictor, tiny_checkpoint):
    assert predictor.model_id.startswith("tiny_nemsim@") and len(predictor.model_id.split("@")[1]) == 12
    assert predictor.horizon_steps == predictor.scene.n_transitions and predictor.n_params > 0
    assert predictor.supports_mechanisms and predictor.runtime.backend == "torch"
    spec = CONTROL_SPECS[CONTROL_NAMES.index("flux_cl")]
    assert predictor.train_range["flux_cl"] == (spec.low, spec.high)


# --- initial state from the checkpoint's simulator configuration ---------------------------------------


@pytest.mark.parametrize("nested", [True, False])
def test_recorded_sim_config_builds_the_initial_state(predictor, tiny_scene, nested):
    from nemsim.sim import initial_state
    from nemsim.sim.config import SimConfig

    config = SimConfig(psi_sigma_vox=1.5)
    meta = config.to_meta(tiny_scene)
    raw = {**predictor.loaded.raw, "sim_config": {"config": meta} if nested else meta}
    p = Predictor(dataclasses.replace(predictor.loaded, raw=raw), backend="torch")
    assert "sim_config" in p.initial_state_source and p.sim_config is not None
    want = np.asarray(initial_state(tiny_scene, config), dtype=np.float32)
    np.testing.assert_array_equal(p.x0, want)
    assert not np.array_equal(want, predictor.x0)  # the configuration matters


def test_unreadable_sim_config_falls_back(predictor):
    raw = {**predictor.loaded.raw, "sim_config": {"capacity": -5}}
    p = Predictor(dataclasses.replace(predictor.loaded, raw=raw), backend="torch")
    assert "could not be read" in p.initial_state_source and p.sim_config is None
    np.testing.assert_array_equal(p.x0, predictor.x0)


def test_stability_guard():
    traj = np.zeros((4, 2, 3, 3, 3), dtype=np.float32)
    assert stability_warnings(traj) == []
    traj[2, 1, 0, 0, 0] = 7.0
    traj[3, 0, 1, 1, 1] = np.nan
    msgs = stability_warnings(traj)
    assert len(msgs) == 2
    assert "step 3" in msgs[0] and "NaN" in msgs[0]
    assert "step 2" in msgs[1] and "7" in msgs[1]


@pytest.mark.slow
@pytest.mark.skipif(not openvino_available(), reason="openvino not installed (nemsim[fast])")
def test_openvino_matches_torch(predictor, tiny_checkpoint):
    fast = Predictor.from_checkpoint(tiny_checkpoint, backend="openvino", precision="f32")
    auto = Predictor(predictor.loaded, backend="auto")
    assert fast.runtime.backend == "openvino" and auto.runtime.backend == "openvino"
    a = fast.rollout(_mid(), 4)
    b = predictor.rollout(_mid(), 4)
    assert fast.runtime.backend == "openvino"  # no silent fallback
    assert np.abs(a.states - b.states).max() <= 1e-4


def test_a_quarter_domain_model_rolls_out_exactly_symmetric_states(tmp_path, tiny_scene, rules):
    """A quarter-domain checkpoint: the predictor starts from the symmetric mean of the scene's initial state,
    so every state it returns has the square's 8 symmetries exactly (``symmetric_size``); the service stores
    such trajectories as their quadrant."""
    import dataclasses

    from nemsim.inference.checkpoint import save_checkpoint
    from nemsim.registry import build_model, model_config
    from nemsim.symmetry import fold, symmetrize
    from service.compact_states import CompactStates

    torch.manual_seed(0)
    overrides = {"domain": "quarter", "steps_per_call": 2, "decoder_out_scale": 1.0}
    model = build_model("nemsim", tiny_scene, rules, overrides)
    path = tmp_path / "quarter.pt"
    save_checkpoint(path, model, model_name="nemsim",
                    model_config=dataclasses.asdict(model_config("nemsim", tiny_scene, overrides)),
                    scene=tiny_scene, rules=rules, summary={}, metrics={})
    pred = Predictor.from_checkpoint(path, backend="torch")
    assert pred.symmetric_size == tiny_scene.field_shape[-1]
    assert "averaged over the scene's symmetries" in pred.initial_state_source
    states = torch.from_numpy(pred.rollout(_mid(), 4).states.copy())
    assert torch.equal(states, symmetrize(states)) and (states[-1] - states[0]).abs().max() > 1e-3
    stored = CompactStates.encode(states, full_size=pred.symmetric_size)
    assert np.array_equal(stored.decode(), states.half().numpy())
    # on the quadrant (the service's path): the same states' quadrant, the same metrics, no full field built
    whole = pred.rollout(_mid(), 4)
    quad = pred.rollout(_mid(), 4, quadrant=True)
    assert quad.full_size == pred.symmetric_size and whole.full_size is None
    assert quad.states.shape[1:] == pred.state_shape(quadrant=True) == tiny_scene.quarter_state_shape
    assert np.array_equal(quad.states, fold(torch.from_numpy(whole.states)).numpy())
    for name, values in whole.metrics.items():
        np.testing.assert_allclose(quad.metrics[name], values, rtol=0, atol=1e-9, err_msg=name)
    from_quadrant = CompactStates.encode(torch.from_numpy(quad.states.copy()), full_size=quad.full_size)
    assert np.array_equal(from_quadrant.decode(), stored.decode())
