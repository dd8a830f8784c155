"""Exit codes and messages of the command line on out-of-range options and damaged input files: exit 2 and
one line on stderr that names the option or the file (never "a bug")."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from test_cli import _fails_cleanly as _fails  # tests/ is on sys.path (rootdir-relative)

from nemsim.cli import main


def test_design_size_has_a_clear_limit(tmp_path, capsys):
    from nemsim.controls import MAX_DESIGN_N

    line = _fails(capsys, ["design", "--n", "1000000000", "--out", tmp_path / "d.csv"])
    assert "--n must be in 1..100000" in line and "1000000000" in line
    assert not (tmp_path / "d.csv").exists()
    with pytest.raises(ValueError, match="design size"):
        from nemsim.controls import lhs_unit

        lhs_unit(MAX_DESIGN_N + 1)


@pytest.mark.parametrize(
    "argv",
    [
        ["design", "--seed", "-1", "--out", "{tmp}/d.csv"],
        ["design", "--kind", "pairs", "--n", "4", "--seed", "-1", "--out", "{tmp}/d.csv"],
        ["splits", "--design", "{tmp}/d.csv", "--seed", "-1", "--out", "{tmp}/s"],
        ["generate", "--scene", "tiny", "--n", "1", "--seed", "-1", "--out", "{tmp}/g.h5"],
        ["train", "--model", "nemsim", "--data", "{tmp}/x.h5", "--setting", "control-id", "--out", "{tmp}/r",
         "--seed", "-1"],
        ["train", "--model", "nemsim", "--data", "{tmp}/x.h5", "--setting", "control-id", "--out", "{tmp}/r",
         "--perturb-seed", "-2"],
    ],
    ids=["design", "design-pairs", "splits", "generate", "train", "train-perturb"],
)
def test_a_negative_seed_names_the_option(tmp_path, capsys, argv):
    argv = [a.format(tmp=tmp_path) for a in argv]
    option = next(a for a in argv if a.endswith("seed"))
    line = _fails(capsys, argv)
    assert f"argument {option}: must be an integer in 0.." in line and "'-" in line


def test_a_controls_csv_that_is_not_text_is_named(tmp_path, capsys):
    bad = tmp_path / "design.csv"
    bad.write_bytes(b"\xfb\x00\xff" * 100)
    for argv in (["splits", "--design", bad, "--out", tmp_path / "s"],
                 ["generate", "--scene", "tiny", "--controls", bad, "--out", tmp_path / "g.h5"]):
        line = _fails(capsys, argv)
        assert str(bad) in line and "not a CSV text file" in line


def test_a_damaged_split_manifest_is_named(tmp_path, capsys):
    from nemsim.data.splits import load_manifest

    for content in (b"\xff\xfe{", b"{not json", b"[1, 2]"):
        path = tmp_path / "control-id.json"
        path.write_bytes(content)
        with pytest.raises(ValueError, match=str(path)):
            load_manifest(tmp_path, "control-id")


def test_a_damaged_calibration_file_is_named(tmp_path):
    from nemsim.analysis.intervals import load_calibration

    path = tmp_path / "x.calibration.json"
    path.write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(ValueError, match=f"{path}: not JSON"):
        load_calibration(path)


def test_a_train_config_that_is_not_text_is_named(tmp_path):
    from nemsim.training.config import read_config_file

    path = tmp_path / "cfg.yaml"
    path.write_bytes(b"lr: 1\n\xff\xfe")
    with pytest.raises(ValueError, match=f"{path}: not a YAML or JSON text file"):
        read_config_file(path)


def test_generate_refuses_to_resume_onto_a_damaged_file(tmp_path, capsys):
    out = tmp_path / "g.h5"
    argv = ["generate", "--scene", "tiny", "--n", "2", "--out", out, "--no-progress"]
    assert main([str(a) for a in argv]) == 0
    with h5py.File(out, "r") as f:  # damage one stored state chunk of case 1
        info = f["states"].id.get_chunk_info_by_coord((1, 4, 0, 0, 0, 0))
    with open(out, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 4)
        fh.write(b"\xff" * (info.size // 2))
    before = out.read_bytes()
    line = _fails(capsys, argv)
    assert f"cannot resume {out}: the file is damaged: case 1" in line and "nemsim data check" in line
    assert out.read_bytes() == before
    assert main(["data", "check", str(out)]) == 2  # and the check says so too


def test_inverse_budget_is_checked_without_verify(tiny_checkpoint, tmp_path, capsys):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"targets": {"etch_depth": 10}}))
    line = _fails(capsys, ["inverse", "--checkpoint", tiny_checkpoint, "--spec", spec, "--budget", "-1"])
    assert "--budget must be a number of seconds >= 0, got -1" in line


def test_seed_type_accepts_the_full_range():
    from nemsim.cli.common import MAX_SEED, seed_arg

    assert seed_arg("0") == 0 and seed_arg(str(MAX_SEED)) == MAX_SEED
    for text in ("-1", str(MAX_SEED + 1), "1.5", "x"):
        with pytest.raises(Exception, match="must be an integer in 0.."):
            seed_arg(text)
    assert np.random.default_rng(seed_arg(str(MAX_SEED))) is not None

