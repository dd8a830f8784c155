"""`nemsim inverse` and `nemsim calibrate` on the tiny checkpoint: the happy path (table and JSON) and bad
input (one line on stderr, exit 2)."""

from __future__ import annotations

import json

from nemsim.cli import main

SPEC = {
    "targets": {"etch_depth": {"value": 10, "tol": 5}},
    "step": 2,
    "k": 2,
    "search": {"screen": 4, "starts": 1, "iterations": 1, "batch": 4, "method": "adam"},
}


def test_inverse_prints_a_table_and_writes_json(tiny_checkpoint, tmp_path, capsys):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(SPEC))
    out = tmp_path / "out" / "design.json"
    assert (
        main(["inverse", "--checkpoint", str(tiny_checkpoint), "--spec", str(spec), "--json", str(out)]) == 0
    )
    text = capsys.readouterr().out
    assert "| rank |" in text and "cost:" in text and "recipe 1:" in text
    res = json.loads(out.read_text())
    assert res["status"] in ("met", "unreachable") and len(res["recipes"]) == 2
    assert res["spec"]["targets"]["etch_depth"] == {"value": 10.0, "tol": 5.0}
    # nothing was simulated: every recipe is a prediction, and the table says so
    assert {r["verdict"] for r in res["recipes"]} <= {"predicted", "predicted_miss"}
    assert "| verdict |" in text and "confirmed" not in text and "predicted to" in text


def test_inverse_json_to_stdout(tiny_checkpoint, tmp_path, capsys):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(SPEC))
    assert main(["inverse", "--checkpoint", str(tiny_checkpoint), "--spec", str(spec), "--json", "-"]) == 0
    assert json.loads(capsys.readouterr().out)["recipes"][0]["rank"] == 1


def test_inverse_bad_input_is_one_line_exit_2(tiny_checkpoint, tmp_path, capsys):
    cases = [
        ('{"targets": {"depth": 3}}', "unknown metric"),
        ("{not json", "not JSON"),
        ('{"targets": {"etch_depth": 3}, "fixed": {"angle_cl": 1.5}}', "not an integer"),
    ]
    for text, word in cases:
        spec = tmp_path / "bad.json"
        spec.write_text(text)
        code = main(["inverse", "--checkpoint", str(tiny_checkpoint), "--spec", str(spec)])
        err = capsys.readouterr().err
        assert code == 2, err
        assert err.count("\n") == 1 and word in err and err.startswith("nemsim inverse:")
    spec.write_text(json.dumps(SPEC))
    code = main(["inverse", "--checkpoint", str(tmp_path / "missing.pt"), "--spec", str(spec)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1


def test_inverse_refine_reports_simulated_rounds(tiny_checkpoint, tmp_path, capsys):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(SPEC))
    args = ["inverse", "--checkpoint", str(tiny_checkpoint), "--spec", str(spec), "--refine", "--rounds", "0",
            "--verify-top", "1", "--sim-seed", "4", "--json", "-"]
    assert main(args) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["refinement"]["config"]["rounds"] == 0 and res["refinement"]["config"]["verify_top"] == 1
    assert res["verification"]["seed"] == 4 and len(res["verification"]["recipes"]) == 1
    assert res["recipes"][0]["verified_by"] == "simulator"
    expected = "unverified" if res["refinement"]["surrogate_status"] == "met" else "unreachable"
    assert res["status"] == ("verified" if res["verification"]["recipes"][0]["met"] else expected)
    code = main(args[:-2] + ["--rounds", "-1"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "rounds" in err


def test_verify_refines_by_default_and_no_refine_only_simulates(tiny_checkpoint, tmp_path, capsys):
    from nemsim.analysis.inverse import REFINE_WITH_VERIFY

    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(SPEC))
    base = ["inverse", "--checkpoint", str(tiny_checkpoint), "--spec", str(spec), "--verify", "--rounds", "0",
            "--verify-top", "1", "--json", "-"]
    assert main(base) == 0
    assert ("refinement" in json.loads(capsys.readouterr().out)) == REFINE_WITH_VERIFY
    assert main(base + ["--no-refine"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert "refinement" not in res and len(res["verification"]["recipes"]) == 1
    assert res["status"] in ("met", "unreachable")
