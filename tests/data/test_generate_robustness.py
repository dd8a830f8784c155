"""`nemsim generate` robustness: stopping, a file in use, growing a file, failures, torch-free workers."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from nemsim.sim.generate import generate_dataset

REPO = Path(__file__).resolve().parents[2]



@pytest.fixture(scope="module")
def cheap_controls():
    """(4, 14) admissible rows of the design with low fluxes (a fraction of a second per `tiny` case)."""
    from nemsim.controls import lhs_design

    raw = lhs_design(n=4, seed=3)
    raw[:, :4] = [2e-4, 2e-4, 2e-6, 1e-3]
    return raw


def _env() -> dict:
    """Environment of the subprocesses, which run with cwd=REPO so that they import this source tree."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    env.pop("HDF5_USE_FILE_LOCKING", None)
    return env


@pytest.mark.slow  # two spawned workers must start and finish a case first (~10-30 s)
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["TERM", "KILL"])
def test_a_stopped_generate_leaves_no_workers_and_keeps_finished_cases(tmp_path, sig, stops):
    """TERM: the parent cleans up (exit 130, file closed). KILL: the workers' watchdog ends them."""
    out = tmp_path / "g.h5"
    cmd = [sys.executable, "-m", "nemsim.cli", "generate", "--scene", "tiny", "--n", "40", "--workers", "2",
           "--no-progress", "--out", str(out)]  # fmt: skip
    pipe = subprocess.PIPE
    proc = subprocess.Popen(cmd, env=_env(), cwd=REPO, stdout=pipe, stderr=pipe, text=True)
    try:
        deadline = time.time() + 120
        workers: set[int] = set()
        while time.time() < deadline and proc.poll() is None:  # wait for a written case: workers busy
            workers |= stops.children(proc.pid)
            if len(workers) >= 2 and stops.cases_written(out) >= 1:
                break
            time.sleep(0.2)
        assert proc.poll() is None, "generate finished before it could be stopped"
        workers |= stops.children(proc.pid)
        assert len(workers) >= 2
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            for pid in workers:  # do not leave a failing run's workers behind
                if stops.alive(pid):
                    os.kill(pid, signal.SIGKILL)
    time.sleep(1.5)  # the workers' watchdog polls once a second
    assert not [p for p in workers if stops.alive(p)], "workers outlived the generate process"
    if sig == signal.SIGKILL:
        assert proc.returncode == -signal.SIGKILL
        return
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "interrupted" in err
    from nemsim.data.hdf5 import check_dataset

    rep = check_dataset(out, require_complete=False)
    assert rep.ok, rep.text
    with h5py.File(out, "r") as f:
        done = int(f["complete"][()].sum())
    assert 1 <= done < 40


def test_a_second_generate_on_a_file_in_use_is_one_line(tmp_path, capsys):
    from nemsim.cli import main

    out = tmp_path / "busy.h5"
    with h5py.File(out, "w"):
        pass
    holder = subprocess.Popen(
        [sys.executable, "-c", "import h5py, sys, time; f = h5py.File(sys.argv[1], 'r+'); print('ready', "
         "flush=True); time.sleep(60)", str(out)],
        env=_env(), stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "ready"
        code = main(["generate", "--scene", "tiny", "--n", "2", "--no-progress", "--out", str(out)])
        err = capsys.readouterr().err
        assert code == 2
        assert "in use by another process" in err and len(err.strip().splitlines()) == 1, err
        code = main(["data", "check", str(out)])
        assert code == 2 and "in use by another process" in capsys.readouterr().out
    finally:
        holder.kill()
        holder.wait()


def test_a_damaged_file_is_one_line(tmp_path, capsys):
    from nemsim.cli import main

    out = tmp_path / "junk.h5"
    out.write_bytes(b"not an hdf5 file" * 100)
    assert main(["generate", "--scene", "tiny", "--n", "2", "--no-progress", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "cannot open" in err and "damaged" in err and len(err.strip().splitlines()) == 1, err


def test_growing_a_file_appends_the_new_cases(tmp_path, tiny_scene, rules, cheap_controls):
    from nemsim.data.hdf5 import check_dataset, open_trajectories

    out = tmp_path / "grow.h5"
    rep = generate_dataset(out, tiny_scene, rules, cheap_controls[:2], [0, 1], seed=4, progress=False)
    assert rep["written"] == 2
    with open_trajectories(out) as tf:
        first = np.asarray(tf.states[()])
    rep = generate_dataset(out, tiny_scene, rules, cheap_controls[:3], [0, 1, 2], seed=4, progress=False)
    assert rep["written"] == 1 and rep["skipped"] == 2
    assert check_dataset(out).ok
    with open_trajectories(out) as tf:
        np.testing.assert_array_equal(tf.case_ids, [0, 1, 2])
        np.testing.assert_array_equal(tf.controls_raw, cheap_controls[:3])
        np.testing.assert_array_equal(tf.states[:2], first)  # untouched
        assert tf.complete.all()
    # a grow interrupted before the case ids were extended is redone by the next run
    with h5py.File(out, "r+") as f:
        for name in ("complete", "seeds", "controls_raw", "controls_transformed", "case_meta", "states"):
            f[name].resize(4, axis=0)
    rep = generate_dataset(out, tiny_scene, rules, cheap_controls[:4], [0, 1, 2, 3], seed=4, progress=False)
    assert rep["written"] == 1 and rep["skipped"] == 3
    with open_trajectories(out) as tf:
        assert tf.complete.all() and tf.n_cases == 4
    # a smaller or different request is refused with the file's contents and what to do
    with pytest.raises(ValueError, match=r"case_ids mismatch: the file holds 4 cases, ids 0\.\.3.*--n 16"):
        generate_dataset(out, tiny_scene, rules, cheap_controls[:2], [0, 1], seed=4, progress=False)


def test_a_fixed_size_file_explains_how_to_grow(tmp_path, tiny_scene, rules, cheap_controls):
    out = tmp_path / "old.h5"
    generate_dataset(out, tiny_scene, rules, cheap_controls[:1], [0], seed=4, progress=False)
    with h5py.File(out, "r+") as f:  # rewrite as the fixed-size layout of earlier files
        for name in ("case_ids", "controls_raw", "controls_transformed", "seeds", "complete"):
            data = f[name][()]
            del f[name]
            f.create_dataset(name, data=data)
    with pytest.raises(ValueError, match=r"without room to grow.*--cases 1-1 --out OTHER\.h5"):
        generate_dataset(out, tiny_scene, rules, cheap_controls[:2], [0, 1], seed=4, progress=False)


def test_a_failing_generate_keeps_finished_cases_and_resumes(tmp_path, tiny_scene, rules, cheap_controls,
                                                             monkeypatch):  # fmt: skip
    import nemsim.sim.generate as gen
    from nemsim.data.hdf5 import open_trajectories

    real = gen.simulate_case

    def flaky(scene, rules_, config, task):
        if task.case_id == 2:
            raise RuntimeError("simulated failure")
        return real(scene, rules_, config, task)

    out = tmp_path / "fail.h5"
    monkeypatch.setattr(gen, "simulate_case", flaky)
    with pytest.raises(RuntimeError, match="simulated failure"):
        generate_dataset(out, tiny_scene, rules, cheap_controls[:4], [0, 1, 2, 3], seed=4, progress=False)
    with open_trajectories(out) as tf:
        assert tf.complete.tolist() == [True, True, False, False]
    monkeypatch.setattr(gen, "simulate_case", real)
    rep = generate_dataset(out, tiny_scene, rules, cheap_controls[:4], [0, 1, 2, 3], seed=4, progress=False)
    assert rep["written"] == 2 and rep["skipped"] == 2


_PROBE = """
import importlib.abc, json, sys, traceback
importers = []
class Probe(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            importers.append([f.filename for f in traceback.extract_stack() if "nemsim" in f.filename][-1:])
        return None
sys.meta_path.insert(0, Probe())
import numpy as np
from nemsim.controls import lhs_design
from nemsim.rules import compile_rules, load_rules
from nemsim.scenes import TINY
from nemsim.sim import SimConfig
from nemsim.sim.generate import CaseTask, simulate_case
u = lhs_design(n=1, seed=3)[0]
u[:4] = [2e-4, 2e-4, 2e-6, 1e-3]
simulate_case(TINY, compile_rules(load_rules()), SimConfig().resolved(TINY), CaseTask(0, 0, 1, u))
print(json.dumps({"torch": "torch" in sys.modules, "importers": importers}))
"""


def test_generation_workers_do_not_import_torch():
    """What a generation worker runs (unpickle the task, simulate one case) must not load torch: the
    simulator takes its kinetic laws from the torch-free ``nemsim.rules.laws``."""
    cmd = [sys.executable, "-c", _PROBE]
    res = subprocess.run(cmd, env=_env(), cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    found = json.loads(res.stdout.strip().splitlines()[-1])
    assert not found["torch"], f"torch imported by {found['importers']}"
