"""One validation layer for controls, targets and tolerances: the library's rules (``nemsim.controls``,
``nemsim.analysis.inverse.spec``) refuse out-of-range input with the name, the value and the accepted range,
and `nemsim inverse` turns that into one line naming the option (exit 2)."""

from __future__ import annotations

import json
import math

import pytest

from nemsim.analysis.inverse import (
    MIN_TOL_NM,
    check_target,
    check_targets,
    check_tolerance,
    run_inverse,
    spec_from_dict,
    target_range,
)
from nemsim.cli import main
from nemsim.controls import admissible_range, check_control, guard_max
from nemsim.scenes import SMALL, TINY

# each: (spec, words the message carries)
BAD_SPECS = [
    ({"targets": {"etch_depth": 50}, "fixed": {"flux_cl": 1e308}}, ["fixed.flux_cl", "1e+308", "0..20"]),
    ({"targets": {"etch_depth": -1e308}}, ["targets.etch_depth", "-1e+308", ">= 0"]),
    ({"targets": {"etch_depth": {"value": 50, "tol": 1e-300}}},
     ["targets.etch_depth.tol", "1e-300", "0.1 nm"]),
    ({"targets": {"top_width": {"value": 30, "tol": -3}}}, ["targets.top_width.tol", "-3"]),
    ({"targets": {"etch_depth": 50}, "bounds": {"flux_cl": [1e-3, 1e308]}}, ["bounds.flux_cl[1]", "1e+308"]),
    ({"targets": {"etch_depth": 50}, "fixed": {"energy_mean_ar_plus": -5}}, ["physically impossible"]),
    ({"targets": {"etch_depth": 50}, "search": {"screen": 10**12}}, ["search.screen", "100000"]),
    ({"targets": {"etch_depth": 50}, "search": {"lr": "fast"}}, ["search.lr", "finite number"]),
]


def test_control_rules_are_rollouts_guard():
    """The scale guard `/rollout` enforces (flux_cl accepted up to 20) lives in the library."""
    assert guard_max("flux_cl") == pytest.approx(20.0) and admissible_range("flux_cl") == (0.0, 20.0)
    assert check_control("flux_cl", 20.0) == 20.0
    for value, word in ((20.5, "far outside"), (1e308, "far outside"), (-1e-9, "physically impossible"),
                        (math.nan, "not a finite number"), (math.inf, "not a finite number")):
        with pytest.raises(ValueError, match=word) as info:
            check_control("flux_cl", value, where="fixed.")
        assert str(info.value).startswith("fixed.flux_cl = ")
    with pytest.raises(ValueError, match="not an integer"):
        check_control("angle_cl", 2.5)
    assert check_control("angle_cl", 2.5, whole=False) == 2.5


def test_target_ranges_follow_the_scene():
    assert target_range("etch_depth", SMALL)[:2] == (0.0, 160.0)  # the Si thickness
    assert target_range("mask_loss", SMALL)[:2] == (0.0, 80.0)  # the mask thickness
    assert target_range("top_width", SMALL)[:2] == target_range("bowing", TINY)[:2] == (0.0, 104.0)
    assert check_target("etch_depth", 160.0, SMALL) == 160.0
    with pytest.raises(ValueError, match=r"targets.etch_depth = 160.5 nm .* 0..160 nm .*Si thickness"):
        check_target("etch_depth", 160.5, SMALL)
    assert check_tolerance("mask_loss", MIN_TOL_NM, SMALL) == MIN_TOL_NM
    with pytest.raises(ValueError, match=r"at most 80 nm"):
        check_tolerance("mask_loss", 81.0, SMALL)
    check_target("etch_depth", 1e308)  # no scene: only finite and >= 0
    with pytest.raises(ValueError, match="outside the physical range"):
        check_targets(spec_from_dict({"targets": {"etch_depth": 1e308}}).targets, SMALL)


@pytest.mark.parametrize("spec, words", BAD_SPECS)
def test_bad_specs_name_the_field_the_value_and_the_range(spec, words):
    with pytest.raises(ValueError) as info:
        spec_from_dict(spec)
    assert all(w in str(info.value) for w in words), str(info.value)


def test_run_inverse_refuses_targets_outside_the_scene(tiny_checkpoint):
    from nemsim.analysis.inverse import load_inverse_context

    ctx = load_inverse_context(tiny_checkpoint)
    with pytest.raises(ValueError, match=r"targets.etch_depth.value = 1e\+308 nm is outside"):
        run_inverse(ctx, spec_from_dict({"targets": {"etch_depth": {"value": 1e308, "tol": 5}}}))


def _inverse_fails(capsys, checkpoint, spec_path, *extra: str) -> str:
    capsys.readouterr()
    code = main(["inverse", "--checkpoint", str(checkpoint), "--spec", str(spec_path), *extra])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("nemsim inverse: "), err
    return err


@pytest.mark.parametrize(
    "spec, words",
    [*BAD_SPECS[:3], ({"targets": {"etch_depth": 1e308}}, ["targets.etch_depth.value", "Si thickness"])],
)
def test_cli_refuses_bad_specs_naming_the_option(tiny_checkpoint, tmp_path, capsys, spec, words):
    path = tmp_path / "spec.json"
    path.write_text(json.dumps(spec))
    err = _inverse_fails(capsys, tiny_checkpoint, path)
    assert f"--spec {path}: " in err and all(w in err for w in words), err


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--budget", "-1"], "--budget must be"),  # refused even without --verify / --refine
        (["--budget", "nan"], "--budget must be"),
        (["--rounds", "11"], "--rounds must be"),
        (["--verify-top", "0"], "--verify-top must be"),
        (["--seed", "-1"], "argument --seed: must be an integer"),
        (["--sim-seed", "-1"], "argument --sim-seed: must be an integer"),
    ],
)
def test_cli_refuses_bad_options_naming_them(tiny_checkpoint, tmp_path, capsys, extra, words):
    path = tmp_path / "spec.json"
    path.write_text(json.dumps({"targets": {"etch_depth": 10}}))
    try:
        err = _inverse_fails(capsys, tiny_checkpoint, path, *extra)
    except SystemExit as exc:  # argparse's usage errors exit from parse_args
        assert exc.code == 2
        err = capsys.readouterr().err
    assert words in err, err


def test_cli_names_a_spec_file_that_is_not_text(tiny_checkpoint, tmp_path, capsys):
    path = tmp_path / "spec.json"
    path.write_bytes(b"\xff\xfe\x00garbage")
    err = _inverse_fails(capsys, tiny_checkpoint, path)
    assert f"--spec {path}" in err and "not UTF-8 text" in err
