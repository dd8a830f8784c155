"""`nemsim bench sim` and `nemsim bench noise` on `tiny` (smoke tests of the report)."""

from __future__ import annotations

import json


def test_bench_sim_and_noise_cli(tmp_path, capsys):
    from nemsim.cli import main

    out = tmp_path / "speed.json"
    assert main(["bench", "sim", "--scenes", "tiny", "--cases", "1", "--json", str(out)]) == 0
    rep = json.loads(out.read_text())["tiny"]
    assert rep["n_cases"] == 1 and rep["median"]["primaries"] > 0 and rep["median"]["wall_s"] > 0
    out = tmp_path / "noise.json"
    assert main(["bench", "noise", "--scene", "tiny", "--cases", "1", "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert 0 < rep["avg_rmse"] < 0.05 and len(rep["per_case_avg_rmse"]) == 1
    text = capsys.readouterr().out
    assert "primaries/s" in text and "Avg RMSE" in text
    assert main(["bench", "noise", "--scene", "tiny", "--seeds", "3,3"]) == 2
