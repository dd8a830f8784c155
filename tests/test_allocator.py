"""The console script's allocator settings (nemsim.cli.allocator): when it re-executes, and that it does."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from nemsim.cli.allocator import OPT_OUT, TUNED, tuned_environ

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc settings apply on Linux")


@linux_only
def test_tuned_environ_fills_missing_and_keeps_user_values():
    env = tuned_environ({"PATH": "/bin", "MALLOC_TOP_PAD_": "123"})
    assert env is not None
    assert env["MALLOC_TOP_PAD_"] == "123"  # the user's value is kept
    assert env["MALLOC_MMAP_THRESHOLD_"] == TUNED["MALLOC_MMAP_THRESHOLD_"]
    assert env[OPT_OUT] == "tuned" and env["PATH"] == "/bin"


def test_tuned_environ_nothing_to_do():
    assert tuned_environ({**TUNED}) is None  # already tuned
    assert tuned_environ({OPT_OUT: "default"}) is None  # opted out
    assert tuned_environ({OPT_OUT: "tuned"}) is None  # the re-executed process never loops


def _probe(env: dict[str, str]) -> subprocess.CompletedProcess:
    code = "from nemsim.cli.allocator import reexec_tuned; reexec_tuned(['--help']); print('not re-executed')"
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)


@linux_only
def test_reexec_runs_the_cli_with_the_settings():
    base = {k: v for k, v in os.environ.items() if k not in TUNED and k != OPT_OUT}
    out = _probe(base)
    assert out.returncode == 0 and "usage: nemsim" in out.stdout and "not re-executed" not in out.stdout
    out = _probe({**base, OPT_OUT: "default"})
    assert out.returncode == 0 and out.stdout.strip() == "not re-executed"


@linux_only
def test_serve_keeps_the_default_allocator():
    base = {k: v for k, v in os.environ.items() if k not in TUNED and k != OPT_OUT}
    code = ("from nemsim.cli.allocator import reexec_tuned; reexec_tuned(['--debug', 'serve', '--help']); "
            "print('not re-executed')")
    out = subprocess.run([sys.executable, "-c", code], env=base, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "not re-executed"
