"""`nemsim data stats`: final-state profile metrics over a design, and the paired change between two files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nemsim.data.stats import final_profiles, paired_change, stats
from nemsim.geometry.profile import profile_metrics_batch


def test_final_profiles_read_only_complete_cases_last_state(make_file, synthetic, tiny_scene):
    path = make_file(n=6, write=[0, 2, 5])
    prof = final_profiles(path, chunk=2)  # chunks of 2 cross the case boundary
    assert prof.case_ids.tolist() == [100, 102, 105]
    finals = np.stack([synthetic(tiny_scene, r)[-1] for r in (0, 2, 5)])
    expect = profile_metrics_batch(finals, tiny_scene)
    for k, v in expect.items():
        np.testing.assert_allclose(prof.metrics[k], v)
    report = stats(prof)
    assert report["cases"] == 3
    assert report["metrics"]["etch_depth"][0] == pytest.approx(expect["etch_depth"].min())
    assert report["metrics"]["etch_depth"][-1] == pytest.approx(expect["etch_depth"].max())


def test_paired_change_on_common_ids(make_file, tiny_scene):
    a = final_profiles(make_file(n=4, name="a.h5"))
    b = final_profiles(make_file(n=4, name="b.h5", case_ids=[102, 103, 104, 105]))
    change = paired_change(a, b)
    assert change["cases"] == 2  # ids 102, 103: rows 2, 3 of a against rows 0, 1 of b
    d = a.metrics["etch_depth"][2:] - b.metrics["etch_depth"][:2]
    assert change["etch_depth"]["mean"] == pytest.approx(d.mean())
    assert change["etch_depth"]["mean_abs"] == pytest.approx(np.abs(d).mean())
    assert paired_change(a, a)["etch_depth"]["mean_abs"] == 0.0
    c = final_profiles(make_file(n=2, name="c.h5", case_ids=[7, 8]))
    with pytest.raises(ValueError, match="share no case id"):
        paired_change(a, c)


def test_cli_prints_writes_json_and_refuses_missing_files(make_file, tmp_path, capsys):
    from nemsim.cli import main

    path = make_file(n=3)
    out = tmp_path / "s.json"
    assert main(["data", "stats", str(path), "--against", str(path), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "etch_depth" in text and "paired change" in text
    payload = json.loads(out.read_text())
    assert payload["cases"] == 3 and payload["change"]["cases"] == 3
    assert main(["data", "stats", str(tmp_path / "none.h5")]) == 2
    assert "no such file" in capsys.readouterr().err
