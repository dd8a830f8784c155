"""`bench.learning_curve`: the points of `nemsim learn run` directories (cases counted from each round's
batch, an unfinished round ends the arm), hand-computed summaries, a shared start, and the files."""

from __future__ import annotations

import json

import pytest

from bench import learning_curve as lc
from nemsim.cli import main


def _round(run, r: int, status: str, n: int, start: str = "start.pt") -> None:
    d = run / f"round-{r:02d}"
    d.mkdir(parents=True)
    (d / "batch.csv").write_text("flux_cl,angle_cl\n" + "".join(f"0.{i},1\n" for i in range(n)))
    (d / "round.json").write_text(json.dumps({"round": r, "checkpoint_in": start, "status": status,
                                              "checkpoint": str(d / "train" / "best.pt")}))


def _arm(tmp_path, name: str, statuses, n: int = 4, start: str = "start.pt"):
    run = tmp_path / name
    run.mkdir()
    (run / "learn.json").write_text("{}")
    for r, status in enumerate(statuses, start=1):
        _round(run, r, status, n, start)
    return run


def _reports(depth_err: float):
    """A physics and an extrapolation report of one model: two corners, one interior recipe."""
    held = [{"name": "corner-0", "avg_rmse": 0.04, "error": {"etch_depth": depth_err}},
            {"name": "corner-1", "avg_rmse": 0.02, "error": {"etch_depth": -3.0}},
            {"name": "lhs-0", "avg_rmse": 0.01, "error": {"etch_depth": 1.5}}]
    phys = {"heldout": held, "summary": {"slopes_within_25pct": 17, "slopes_resolved": 24,
                                         "slopes_wrong_sign": 1, "heldout_worse_than_no_change": 2}}
    ex = {"summary": {"groups": {"axis 1.5": {"avg_rmse": 0.019, "ratio_to_in_box": 2.0},
                                 "corner": {"mae_nm": {"etch_depth": 12.3}}}}}
    return phys, ex


def test_points_count_each_rounds_batch_and_stop_at_an_unfinished_round(tmp_path):
    run = _arm(tmp_path, "active", ["trained", "trained", "simulated"], n=4)
    start, points = lc.arm_points(run)
    assert start == "start.pt"
    assert [c for c, _ in points] == [4, 8]  # round 3 is not trained: not a point
    assert points[1][1] == run / "round-02" / "train" / "best.pt"
    with pytest.raises(FileNotFoundError, match="learn.json"):
        lc.arm_points(tmp_path / "active" / "round-01")


def test_summary_by_hand():
    s = lc.summarize(*_reports(depth_err=5.0))
    assert s["corner_depth_mae_nm"] == pytest.approx(4.0)  # (|5| + |-3|) / 2
    assert s["corner_avg_rmse"] == pytest.approx(0.03)
    assert s["lhs_depth_mae_nm"] == pytest.approx(1.5) and s["lhs_avg_rmse"] == pytest.approx(0.01)
    assert (s["slopes_within_25pct"], s["slopes_resolved"], s["slopes_wrong_sign"]) == (17, 24, 1)
    assert s["band_avg_rmse"] == 0.019 and s["band_ratio"] == 2.0
    assert s["outer_corner_depth_mae_nm"] == 12.3 and s["worse_than_no_change"] == 2


def test_arms_share_their_start_and_the_files_are_written(tmp_path):
    arms = {"active": _arm(tmp_path, "a", ["trained", "trained"]), "lhs": _arm(tmp_path, "b", ["trained"])}
    judged = []

    def judge(ckpt):
        judged.append(str(ckpt))
        return _reports(depth_err=float(len(judged)))

    rep = lc.run_learning_curve(arms, judge)
    assert judged[0] == "start.pt" and judged.count("start.pt") == 1  # the start judged once, shared
    assert [p["cases"] for p in rep["arms"]["active"]["points"]] == [0, 4, 8]
    assert [p["cases"] for p in rep["arms"]["lhs"]["points"]] == [0, 4]
    assert rep["arms"]["lhs"]["points"][0] == rep["arms"]["active"]["points"][0]
    paths = lc.write_outputs(rep, tmp_path / "out")
    md = (tmp_path / "out" / "learning_curve.md").read_text()
    assert "| active | 8 |" in md and "| lhs | 4 |" in md
    assert open(paths["png"], "rb").read(8) == b"\x89PNG\r\n\x1a\n"
    other = _arm(tmp_path, "c", ["trained"], start="other.pt")
    with pytest.raises(ValueError, match="different checkpoints"):
        lc.run_learning_curve({"active": arms["active"], "other": other}, judge)


def test_cli_refuses_a_run_that_is_not_label_equals_dir(tmp_path, capsys):
    assert main(["bench", "learning-curve", "--run", str(tmp_path)]) == 2
    assert "LABEL=DIR" in capsys.readouterr().err
