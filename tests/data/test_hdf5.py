"""nemsim.data.hdf5: writer (resume, completion flag), reader, integrity check and `nemsim data check`."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from nemsim.controls import CONTROL_NAMES, to_normalized, transform
from nemsim.data.hdf5 import TrajectoryWriter, check_dataset, open_trajectories


def _writer(path, scene, n=6, **kw):
    from nemsim.controls import lhs_design

    args = dict(scene=scene, case_ids=list(range(100, 100 + n)), controls_raw=lhs_design(n=n, seed=1),
                generator={"kind": "synthetic-test"}, rules_sha256="ab" * 32)
    args.update(kw)
    return TrajectoryWriter(path, **args)


def test_layout_and_reader(make_file, tiny_scene, decode):
    path = make_file()
    with h5py.File(path, "r") as f:
        st = f["states"]
        assert st.shape == (6, tiny_scene.n_states, *tiny_scene.state_shape) and st.dtype == np.float32
        assert st.chunks == (1, 1, *tiny_scene.state_shape) and st.compression == "gzip"
        assert list(f.attrs["control_names"]) == list(CONTROL_NAMES)
        assert list(f.attrs["channel_names"]) == ["mask", "si"]
        assert json.loads(f.attrs["scene"])["name"] == "tiny"
        assert json.loads(f.attrs["generator"]) == {"kind": "synthetic-test"}
        for k in ("format_version", "d_max", "rules_sha256"):
            assert k in f.attrs
        np.testing.assert_allclose(f["controls_transformed"][()], transform(f["controls_raw"][()]))
        assert f["seeds"][()].tolist() == [1000 + i for i in range(6)]
    with open_trajectories(path) as tf:
        assert tf.n_cases == 6 and tf.scene == tiny_scene and tf.rules_sha256 == "ab" * 32
        assert tf.case_ids.tolist() == list(range(100, 106))
        np.testing.assert_allclose(tf.times, np.arange(tiny_scene.n_states) * 0.1)
        np.testing.assert_allclose(tf.controls_normalized, to_normalized(tf.controls_raw))
        assert decode(tf.states[3, 17]) == (3, 17)
        assert tf.row_of(104) == 4 and tf.case_meta(2) == {"row": 2}
        assert tf.d_max == tiny_scene.d_max_nm
    rep = check_dataset(path)
    assert rep.ok, rep.text


def test_resume_redoes_unflagged_case(make_file, tiny_scene):
    path = make_file(write=[0, 1, 2])
    # simulate a kill between the states write and the flag: states present, flag unset
    with h5py.File(path, "r+") as f:
        f["states"][3] = f["states"][0]
    with _writer(path, tiny_scene) as w:
        assert w.finished == {0, 1, 2}
        rep = check_dataset(path)
        assert not rep.ok and "3/6" in rep.text and "unfinished case ids [103, 104, 105]" in rep.text
    with _writer(path, tiny_scene) as w:
        for row in sorted(set(range(6)) - w.finished):
            w.write(row, np.zeros((tiny_scene.n_states, *tiny_scene.state_shape), np.float32), seed=row)
        assert w.finished == set(range(6))
    assert check_dataset(path).ok


def test_resume_rejects_mismatch(make_file, tiny_scene):
    path = make_file(write=[0])
    with pytest.raises(ValueError, match="rules_sha256 mismatch"):
        _writer(path, tiny_scene, rules_sha256="cd" * 32)
    with pytest.raises(ValueError, match="controls_raw mismatch"):
        from nemsim.controls import lhs_design

        _writer(path, tiny_scene, controls_raw=lhs_design(6, seed=2))
    with pytest.raises(ValueError, match="generator mismatch"):
        _writer(path, tiny_scene, generator={"kind": "other"})
    from nemsim.scenes import SMALL

    with pytest.raises(ValueError, match="scene mismatch"):
        _writer(path, SMALL)


def test_write_rejects_invalid_states(tmp_path, tiny_scene):
    good = np.zeros((tiny_scene.n_states, *tiny_scene.state_shape), np.float32)
    with _writer(tmp_path / "x.h5", tiny_scene, n=2) as w:
        bad = good.copy()
        bad[5, 1, 2, 2, 2] = np.nan
        with pytest.raises(ValueError, match="case 100 .*non-finite"):
            w.write(0, bad, seed=0)
        with pytest.raises(ValueError, match="shape"):
            w.write(0, good[:-1], seed=0)
        with pytest.raises(ValueError, match="row 2 out of range"):
            w.write(2, good, seed=0)
        assert w.finished == set()
        w.write(0, good, seed=0)
        w.write(1, good, seed=1)


@pytest.mark.parametrize("corruption", ["nan", "range", "control", "times"])
def test_data_check_fails_on_corruption(make_file, corruption, capsys):
    from nemsim.cli import main

    path = make_file(n=3)
    assert main(["data", "check", str(path)]) == 0
    assert "result: OK" in capsys.readouterr().out
    with h5py.File(path, "r+") as f:
        if corruption == "nan":
            f["states"][1, 7, 0, 3, 3, 3] = np.nan
        elif corruption == "range":
            f["states"][2, 9, 1, 0, 0, 0] = 3.5
        elif corruption == "control":
            f["controls_raw"][0, 8] = 999.0  # mu(Cl+) above 500 eV
        else:
            t = f["times"][()]
            t[10] = t[9]
            f["times"][...] = t
    assert main(["data", "check", str(path)]) == 2
    out = capsys.readouterr().out
    expect = {"nan": "case 101: 1 non-finite", "range": "case 102: |SDF| up to 3.5",
              "control": "energy_mean_cl_plus", "times": "FAIL  timestamps"}[corruption]
    assert expect in out and "FAILED" in out


def test_data_check_not_hdf5(tmp_path, capsys):
    from nemsim.cli import main

    p = tmp_path / "junk.h5"
    p.write_bytes(b"not an hdf5 file")
    assert main(["data", "check", str(p)]) == 2
    assert "cannot open" in capsys.readouterr().out


def test_schedule_roundtrip(make_file, tiny_scene):
    path = make_file(n=2, schedule=True)
    with open_trajectories(path) as tf:
        assert tf.controls_raw_schedule.shape == (2, tiny_scene.n_transitions, 14)
        u = tf.controls_normalized_schedule(1)
        np.testing.assert_allclose(u[0], tf.controls_normalized[1])
        assert u[60, 0] < u[0, 0]
    assert check_dataset(path).ok



def _damage_chunk(path, row: int, step: int, garbage: bool) -> None:
    """Damage one stored state chunk of a case: overwrite half its bytes (``garbage``: it no longer
    decompresses), or replace it by a well-formed chunk of NaN values."""
    import zlib

    with h5py.File(path, "r+") as f:
        st = f["states"]
        offset = (row, step, 0, 0, 0, 0)
        info = st.id.get_chunk_info_by_coord(offset)
        if not garbage:
            nan = np.full(st.chunks, np.nan, dtype=st.dtype)
            st.id.write_direct_chunk(offset, zlib.compress(nan.tobytes(), 4))
    if garbage:
        with open(path, "r+b") as fh:
            fh.seek(info.byte_offset + info.size // 4)
            fh.write(b"\xff" * (info.size // 2))


@pytest.mark.parametrize("garbage", [True, False], ids=["undecodable-chunk", "nan-chunk"])
def test_resume_refuses_a_damaged_file(make_file, tiny_scene, garbage):
    """A complete case whose states are damaged is not resumed onto (the run would report it complete)."""
    path = make_file(write=[0, 1, 2])
    _damage_chunk(path, row=1, step=5, garbage=garbage)
    before = path.read_bytes()
    with pytest.raises(ValueError, match=r"cannot resume .*the file is damaged: case 101") as info:
        _writer(path, tiny_scene)
    assert "nemsim data check" in str(info.value)
    assert path.read_bytes() == before  # nothing written
    with _writer(make_file(write=[0], name="ok.h5"), tiny_scene) as w:
        assert w.finished == {0}  # an intact file resumes


def test_a_finished_file_opens_while_another_process_reads_it(make_file, tiny_scene):
    """A training reading the data does not stop a rerun of its recipe's generate step (nothing to write:
    the file is read back under a reader's lock); a file with cases left still needs the writer's lock."""
    import subprocess
    import sys

    from nemsim.data.hdf5 import DataFileError

    done, part = make_file(), make_file(write=[0], name="part.h5")
    holder = subprocess.Popen(
        [sys.executable, "-c", "import h5py, sys, time; fs = [h5py.File(p, 'r') for p in sys.argv[1:]]; "
         "print('ready', flush=True); time.sleep(60)", str(done), str(part)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "ready"
        before = done.read_bytes()
        with _writer(done, tiny_scene) as w:
            assert w.finished == set(range(6))
        assert done.read_bytes() == before
        with pytest.raises(DataFileError, match="in use by another process"):
            _writer(part, tiny_scene)
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.parametrize("compression, dtype", [(("gzip", 4, False), "float16"),
                                                (("gzip", 4, False), "float32"),
                                                (("lzf", None, False), "float32"),
                                                (("gzip", 4, True), "float16")])
def test_read_cases_gives_the_stored_states_in_order(tmp_path, tiny_scene, synthetic, compression, dtype):
    """The parallel reader (raw chunks inflated on threads; other layouts through h5py) yields exactly what
    h5py reads, row by row in the order asked, in the stored dtype."""
    from nemsim.data.hdf5 import _direct_chunks, read_cases

    path = tmp_path / "c.h5"
    with _writer(path, tiny_scene, n=4, compression=compression, state_dtype=dtype) as w:
        for row in range(4):
            w.write(row, synthetic(tiny_scene, row), seed=row, meta={})
    rows = [3, 0, 2]
    with h5py.File(path, "r") as f:
        expected = [f["states"][r] for r in rows]
        direct = _direct_chunks(f["states"])
    assert direct == (compression[0] == "gzip" and not compression[2])
    got = list(read_cases(path, rows, threads=3, ahead=1))
    assert [i for i, _ in got] == [0, 1, 2]
    for (_, states), ref in zip(got, expected, strict=True):
        assert states.dtype == np.dtype(dtype) and np.array_equal(states, ref)
