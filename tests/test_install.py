"""How `make venv` (under `make serve` and `make test`) installs torch: the CPU build from the PyTorch CPU
index unless TORCH=cuda, and the default index's build after a one-line message when the CPU index cannot
serve it. The Makefile's own recipe runs against a stand-in venv whose `pip` records its arguments (and
fails on the CPU index when told to), so no package is installed and no network is used."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CPU_INDEX = "https://download.pytorch.org/whl/cpu"
STAND_IN_PIP = """#!/bin/sh
echo "$*" >> "$PIP_LOG"
case "$*" in *--index-url*) exit "${CPU_INDEX_RC:-0}" ;; esac
"""

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="no make")


def make_venv(
    tmp_path: Path, *args: str, cpu_index_rc: int = 0
) -> tuple[subprocess.CompletedProcess, list[str]]:
    """The Makefile's venv recipe for a stand-in venv in tmp_path: (the make run, pip's argument lines)."""
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True, exist_ok=True)
    for name, text in (("python", "#!/bin/sh\n"), ("pip", STAND_IN_PIP)):
        (venv / "bin" / name).write_text(text)
        (venv / "bin" / name).chmod(0o755)
    log = tmp_path / "pip.log"
    log.unlink(missing_ok=True)
    env = {**os.environ, "PIP_LOG": str(log), "CPU_INDEX_RC": str(cpu_index_rc)}
    env.pop("MAKEFLAGS", None)
    run = subprocess.run(
        ["make", "-B", "-C", str(ROOT), f"VENV={venv}", *args, "venv"],
        capture_output=True, text=True, env=env, timeout=60,
    )  # fmt: skip
    return run, log.read_text().splitlines() if log.exists() else []


def torch_installs(calls: list[str]) -> list[str]:
    return [c for c in calls if re.search(r"\btorch==", c)]


def test_cpu_build_by_default(tmp_path):
    run, calls = make_venv(tmp_path)
    assert run.returncode == 0, run.stderr
    assert torch_installs(calls) == [f"install -q --retries 1 --index-url {CPU_INDEX} torch==2.13.0"]
    assert calls[-1] == "install -q -e .[service,test]"  # after torch: the package install keeps it
    assert "CPU index" not in run.stderr


def test_unreachable_cpu_index_falls_back_with_one_line(tmp_path):
    run, calls = make_venv(tmp_path, cpu_index_rc=1)
    assert run.returncode == 0, run.stderr
    assert torch_installs(calls) == [
        f"install -q --retries 1 --index-url {CPU_INDEX} torch==2.13.0",
        "install -q torch==2.13.0",
    ]
    said = [line for line in run.stderr.splitlines() if "CPU index" in line]
    assert len(said) == 1 and CPU_INDEX in said[0] and "CUDA" in said[0], run.stderr


def test_cuda_switch(tmp_path):
    run, calls = make_venv(tmp_path, "TORCH=cuda")
    assert run.returncode == 0, run.stderr
    assert torch_installs(calls) == ["install -q torch==2.13.0"]
    assert not any("--index-url" in c for c in calls)


def test_unknown_torch_build_is_refused(tmp_path):
    run, calls = make_venv(tmp_path, "TORCH=gpu")
    assert run.returncode != 0 and calls == []
    assert "TORCH=gpu" in run.stderr and "cpu" in run.stderr and "cuda" in run.stderr


def test_container_follows_the_same_rule():
    """The Dockerfile's default build is the CPU one, from the Makefile's CPU index; `make container`
    passes the switch on."""
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert "ARG TORCH=cpu" in dockerfile and f"ARG TORCH_INDEX_URL={CPU_INDEX}" in dockerfile
    makefile = (ROOT / "Makefile").read_text()
    assert f"TORCH_CPU_INDEX ?= {CPU_INDEX}" in makefile
    dry = subprocess.run(
        ["make", "-n", "-C", str(ROOT), "container", "TORCH=cuda"], capture_output=True, text=True, timeout=60
    )
    assert "--build-arg TORCH=cuda" in dry.stdout, dry.stdout + dry.stderr
