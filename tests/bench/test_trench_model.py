"""bench.trench_model on the tiny scene: a cross-section checkpoint's field and profile errors against two
cross-section simulator seeds, its served speed beside the 3-D simulator of its trench, and the stamp."""

from __future__ import annotations

import json

import pytest


@pytest.fixture(scope="module")
def trench_files(tmp_path_factory, two_seed_files):
    """Two tiny trench files of one design on the cross-section (simulator seeds 1 and 2)."""
    root = tmp_path_factory.mktemp("trench")
    return two_seed_files(root, "trench", "32:48", "48:80", "--sim-domain", "section")


def test_trench_report_on_tiny(tmp_path, trench_files, tiny_section_checkpoint):
    from bench import trench_model

    out = tmp_path / "trench_model"
    assert trench_model.main(["--checkpoint", str(tiny_section_checkpoint), "--test", str(trench_files["a"]),
                              "--test-seed", str(trench_files["b"]), "--speed", "2", "--sim-cases", "1",
                              "--out", str(out)]) == 0
    rep = json.loads(out.with_suffix(".json").read_text())
    field = rep["field"]
    assert len(field["cases"]) == 2 and field["floor"]["avg_rmse"] > 0
    model = field["model"]
    assert model["ratio_to_floor"] == pytest.approx(model["avg_rmse"] / field["floor"]["avg_rmse"])
    depth = rep["profile"]["etch_depth"]
    lo, hi = depth["ratio_interval_90"]
    assert lo <= hi
    assert depth["cases"] == 2 and depth["floor_nm"] > 0
    assert depth["model_nm"] == pytest.approx(0.5 * (depth["vs_seed_a_nm"] + depth["vs_seed_b_nm"]))
    speed = rep["speed"]
    assert speed["simulator"]["feature"].startswith("trench, cd 40 nm")  # the served trench, in 3-D
    assert speed["simulator"]["domain"] == "full" and speed["simulator"]["n_cases"] == 1
    assert speed["simulator_speedup"] == pytest.approx(
        speed["simulator"]["median"]["wall_s"] / (speed["uncached"]["p50_ms"] / 1e3))
    assert rep["geometry"] == {"trench": {"cd_nm": [32.0, 48.0], "mask_nm": [48.0, 80.0]}}
    text = out.with_suffix(".md").read_text()
    assert "_Made with checkpoint" in text and "seed-to-seed floor" in text and "3-D simulator" in text


def test_a_hole_model_is_refused(tmp_path, trench_files, tiny_checkpoint, capsys):
    from bench import trench_model

    with pytest.raises(SystemExit):
        trench_model.main(["--checkpoint", str(tiny_checkpoint), "--test", str(trench_files["a"]),
                           "--test-seed", str(trench_files["b"])])
    assert "not a cross-section (trench) model" in capsys.readouterr().err



def test_ratio_interval_brackets_the_ratio():
    import numpy as np

    from bench.geometry import ratio_interval

    rng = np.random.default_rng(1)
    sa, sb = rng.normal(size=50), rng.normal(size=50)

    def ratio_of(m):
        def rms(d):
            return np.sqrt(np.mean(d**2))
        return lambda i: 0.5 * (rms(m[i] - sa[i]) + rms(m[i] - sb[i])) / rms(sa[i] - sb[i])

    # a model equal to seed A: its error is half the floor on every resample
    assert ratio_interval(ratio_of(sa.copy()), 50) == pytest.approx((0.5, 0.5))
    m = 0.5 * (sa + sb) + rng.normal(scale=0.8, size=50)
    lo, hi = ratio_interval(ratio_of(m), 50)
    assert lo < ratio_of(m)(np.arange(50)) < hi and hi - lo > 0.05
