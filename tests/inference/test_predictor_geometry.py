"""The trained geometry of a checkpoint (``checkpoint_geometry``) and the predictor's rollouts of a feature:
x0 and metrics from the per-case scene, a kind the checkpoint never saw refused naming the kinds it knows,
a known kind outside the trained ranges rolled out and said to be outside."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from nemsim.controls import CONTROL_SPECS
from nemsim.geometry.feature import Feature
from nemsim.inference import Predictor
from nemsim.inference.checkpoint import checkpoint_geometry, read_checkpoint, save_checkpoint
from nemsim.inference.range_check import UnknownGeometry

torch.set_num_threads(1)
RANGES = {"hole": {"cd_nm": [30.0, 50.0], "mask_nm": [64.0, 96.0]}}


@pytest.fixture(scope="module")
def predictor(tiny_checkpoint):
    return Predictor.from_checkpoint(tiny_checkpoint, backend="torch")


def _save(path, tiny_scene, rules, **kwargs):
    from nemsim.registry import build_model, model_config

    torch.manual_seed(0)
    model = build_model("nemsim", tiny_scene, rules)
    cfg = dataclasses.asdict(model_config("nemsim", tiny_scene))
    return save_checkpoint(path, model, model_name="nemsim", model_config=cfg, scene=tiny_scene, rules=rules,
                           **kwargs)  # fmt: skip


def _mid() -> dict[str, float]:
    return {s.name: (s.low + s.high) / 2 for s in CONTROL_SPECS}


def test_without_a_record_the_scene_feature_is_the_only_trained_point(tiny_checkpoint):
    trained = checkpoint_geometry(read_checkpoint(tiny_checkpoint))
    assert trained.kinds == ("hole",)
    assert trained.as_dict()["kinds"] == {"hole": {"cd_nm": [40.0, 40.0], "mask_nm": [80.0, 80.0]}}
    assert "scene" in trained.source
    assert trained.contains(Feature("hole", 40.0, 80.0))
    assert not trained.contains(Feature("hole", 60.0, 80.0))
    assert not trained.contains(Feature("trench", 40.0, 80.0))


@pytest.mark.parametrize("where", ["top", "summary", "list"])
def test_a_recorded_range_is_read(tmp_path, tiny_scene, rules, where):
    if where == "top":
        path = _save(tmp_path / "g.pt", tiny_scene, rules, geometry=RANGES)
    elif where == "summary":
        path = _save(tmp_path / "g.pt", tiny_scene, rules, summary={"geometry": RANGES})
    else:
        path = _save(tmp_path / "g.pt", tiny_scene, rules,
                     geometry=[{"kind": "hole", "cd_nm": [30, 50], "mask_nm": [64, 96]}])  # fmt: skip
    trained = checkpoint_geometry(read_checkpoint(path))
    assert trained.as_dict()["kinds"] == RANGES
    assert trained.contains(Feature("hole", 45.0, 72.0))
    assert not trained.contains(Feature("hole", 56.0, 80.0))


def test_an_unreadable_record_is_refused_at_write(tmp_path, tiny_scene, rules):
    with pytest.raises(ValueError, match="unknown kind"):
        _save(tmp_path / "bad.pt", tiny_scene, rules, geometry={"slot": {"cd_nm": 40, "mask_nm": 80}})
    with pytest.raises(ValueError, match="low <= high"):
        _save(tmp_path / "bad.pt", tiny_scene, rules, geometry={"hole": {"cd_nm": [50, 30], "mask_nm": 80}})


def test_a_feature_rolls_out_from_its_own_scene(predictor):
    """x0 is the simulator's initial state of the per-case scene (symmetric mean for a quarter model) and
    the metrics read that scene."""
    from nemsim.geometry.profile import measured_profile_metrics
    from nemsim.sim import initial_state
    from nemsim.symmetry import quarter_model_size, symmetrize

    feature = Feature("hole", 60.0, 80.0)
    case = predictor.case(feature)
    assert not case.default and case.scene == feature.apply(predictor.scene)
    x0 = initial_state(case.scene, predictor.sim_config)
    if quarter_model_size(predictor.model) is not None:
        x0 = symmetrize(torch.as_tensor(x0)).numpy()
    np.testing.assert_array_equal(case.x0, x0)
    assert not np.array_equal(case.x0, predictor.x0)
    pred = predictor.rollout(_mid(), 2, feature=feature)
    np.testing.assert_array_equal(pred.states[0], case.x0)
    for name, values in measured_profile_metrics(pred.states, case.scene).items():
        np.testing.assert_array_equal(pred.metrics[name], values)
    assert predictor.case(Feature("hole", 60.0, 80.0)) is case  # kept


def test_the_default_feature_is_the_scene_own(predictor):
    assert predictor.case(None).default and predictor.case(None).x0 is predictor.x0
    # a mask built in whole voxels: 82 nm on 8 nm voxels is the default 80 nm
    assert predictor.case(Feature("hole", 40.0, 82.0)).default


def test_a_trench_on_the_hole_model_is_refused_naming_the_kinds(predictor):
    with pytest.raises(UnknownGeometry, match=r"trained on hole features only.*trench.*\['hole'\]"):
        predictor.rollout(_mid(), 1, feature=Feature("trench", 40.0, 80.0))


def test_a_feature_that_does_not_fit_the_grid_is_a_value_error(predictor):
    with pytest.raises(ValueError, match="does not fit scene 'tiny'"):
        predictor.case(Feature("hole", 100.0, 80.0))


def test_outside_the_trained_range_is_said_with_both(predictor):
    assert predictor.geometry_outside(Feature("hole", 40.0, 80.0)) is None
    reason = predictor.geometry_outside(Feature("hole", 60.0, 80.0))
    assert reason is not None and "cd 60 nm" in reason and "hole, cd 40 nm, mask 80 nm" in reason
