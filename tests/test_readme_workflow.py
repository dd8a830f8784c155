"""The README's toy workflow, run line by line exactly as written (parsed from the README: they cannot drift).

The block between ``<!-- toy-workflow:begin -->`` and ``<!-- toy-workflow:end -->`` may hold only
``. .venv/bin/activate``, ``nemsim`` commands (one ending in ``&`` runs in the background), ``curl`` requests
and ``kill %1``. As in a fresh shell, ``nemsim`` is found only on the PATH that the activation line sets (the
``bin`` folder of the interpreter running the tests, the ``.venv`` that ``make test`` builds), so a block that
calls it first fails; ``curl`` lines are interpreted here with urllib (options -s -f -w -X -H -d --retry
--retry-connrefused --retry-delay), so the test does not depend on a curl binary; the server's port is swapped
for a free one. Everything runs in a temporary directory, in the block's order.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from service.protocol import free_port

ROOT = Path(__file__).parents[1]
BEGIN, END = "<!-- toy-workflow:begin -->", "<!-- toy-workflow:end -->"
ACTIVATE = [".", ".venv/bin/activate"]


def readme_commands(text: str) -> list[list[str]]:
    """The toy block's commands as argument lists (continuation lines joined, comments dropped)."""
    assert text.count(BEGIN) == 1 and text.count(END) == 1, "README lacks the toy-workflow markers"
    block = text[text.index(BEGIN) : text.index(END)]
    body = block.split("```bash\n", 1)[1].split("```", 1)[0]
    joined = body.replace("\\\n", " ")
    return [words for line in joined.splitlines() if (words := shlex.split(line, comments=True))]



def _curl(words: list[str]) -> bytes:
    """Perform a curl command line with urllib; raise on a final non-2xx answer (like curl -f)."""
    method, headers, data, url = None, {}, None, None
    retries, delay, it = 0, 1.0, iter(words[1:])
    for w in it:
        if w == "-X":
            method = next(it)
        elif w == "-H":
            k, _, v = next(it).partition(":")
            headers[k.strip()] = v.strip()
        elif w == "-d":
            data = next(it).encode()
        elif w == "-w":
            next(it)
        elif w == "--retry":
            retries = int(next(it))
        elif w == "--retry-delay":
            delay = float(next(it))
        elif w in ("-s", "-f", "-sf", "--retry-connrefused"):
            pass
        elif w.startswith("-"):
            pytest.fail(f"README curl option {w!r} is not interpreted by this test")
        else:
            url = w if "://" in w else f"http://{w}"
    assert url, f"no URL in {words}"
    for attempt in range(retries + 1):
        try:
            req = urllib.request.Request(url, data=data, headers=headers, method=method)
            with urllib.request.urlopen(req, timeout=60) as resp:
                return resp.read()
        except (urllib.error.URLError, ConnectionError) as exc:
            transient = not isinstance(exc, urllib.error.HTTPError) or exc.code >= 500
            if attempt == retries or not transient:
                raise
            time.sleep(delay)
    raise AssertionError("unreachable")


def _without_venv(path: str) -> str:
    """``path`` (a PATH) without the folder of the tests' own interpreter: a shell before activation."""
    venv_bin = str(Path(sys.executable).parent)
    return os.pathsep.join(p for p in path.split(os.pathsep) if p and p != venv_bin)


def test_readme_activates_the_venv_before_any_nemsim_command():
    """Read top to bottom, the README's shell blocks say how to put `nemsim` on the PATH before using it."""
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, re.S)
    lines = [ln.strip() for block in blocks for ln in block.splitlines()]
    first = next(i for i, ln in enumerate(lines) if ln.startswith("nemsim "))
    assert any(shlex.split(ln, comments=True) == ACTIVATE for ln in lines[:first]), lines[first]


@pytest.mark.slow
def test_readme_toy_workflow(tmp_path):
    commands = readme_commands((ROOT / "README.md").read_text())
    assert [c[1] for c in commands if c[0] == "nemsim"][:4] == ["design", "generate", "data", "splits"]
    port = free_port()
    env = {**os.environ, "PATH": _without_venv(os.environ.get("PATH", "")), "PYTHONPATH": str(ROOT),
           "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    background: list[subprocess.Popen] = []
    server_log = tmp_path / "server.log"
    try:
        for words in commands:
            words = [w.replace("localhost:8001", f"localhost:{port}") for w in words]
            if words == ACTIVATE:
                env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env["PATH"]])
            elif words[0] == "nemsim":
                bg = words[-1] == "&"
                args = [a if a != "8001" else str(port) for a in (words[1:-1] if bg else words[1:])]
                nemsim = shutil.which("nemsim", path=env["PATH"])
                assert nemsim, f"`{' '.join(words)}` comes before `. .venv/bin/activate` puts it on the PATH"
                argv = [nemsim, *args]
                if bg:
                    log = server_log.open("w")
                    background.append(subprocess.Popen(argv, cwd=tmp_path, env=env, stdout=log,
                                                       stderr=subprocess.STDOUT))  # fmt: skip
                    continue
                res = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=170)
                assert res.returncode == 0, f"{' '.join(words)}\n{res.stdout[-2000:]}\n{res.stderr[-3000:]}"
            elif words[0] == "curl":
                try:
                    answer = _curl(words)
                except Exception as exc:
                    log = server_log.read_text()[-3000:] if server_log.exists() else ""
                    pytest.fail(f"{' '.join(words)}: {exc}\nserver log:\n{log}")
                assert json.loads(answer)  # every request in the block answers JSON
            elif words == ["kill", "%1"]:
                proc = background.pop(0)
                proc.terminate()
                proc.wait(timeout=30)
            else:
                pytest.fail(f"README toy workflow line not understood by this test: {' '.join(words)}")
        assert not background, "a background command was never stopped with kill"
    finally:
        for proc in background:
            proc.kill()
            proc.wait()
    for path in (
        "data/toy/design.csv",
        "data/toy/tiny.h5",
        "data/toy/splits/control-id.json",
        "runs/toy/best.pt",
        "runs/toy/test.json",
    ):
        assert (tmp_path / path).is_file(), path


def test_readme_controls_table_matches_the_controls():
    """Every control appears in the README's controls table with its unit and design range."""
    from nemsim.controls import CONTROL_SPECS

    text = (ROOT / "README.md").read_text()
    section = text[text.index("## The 14 process controls") :].split("\n## ", 1)[0]
    rows = [r for r in section.splitlines() if r.startswith("| `")]
    for spec in CONTROL_SPECS:
        (row,) = [r for r in rows if f"`{spec.name}`" in r]
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[1] == spec.unit or cells[1].startswith(spec.unit + " ("), (spec.name, cells[1])
        lo, hi = (float(v) for v in cells[2].split("–"))
        assert (lo, hi) == (spec.low, spec.high), spec.name
