"""glibc allocator settings for the `nemsim` process: the console script re-executes itself once with them.

Why: PyTorch on CPU allocates and frees the same large activation and gradient buffers every step. With
glibc's defaults, blocks above the (dynamic) mmap threshold are mapped and unmapped on every allocation and
the heap top is trimmed back to the kernel, so every training step pays page faults and the zeroing of fresh
pages. Keeping large blocks on the heap and never trimming it reuses the memory instead (`nemsim bench
allocator` measures it); the resident size then stays at the process's high-water mark.

How: glibc reads the settings from the environment once, at process start, so ``entry()`` calls
``reexec_tuned`` before any work. Values the user has set are kept; ``NEMSIM_ALLOCATOR=default`` turns the
re-execution off; other C libraries ignore the variables. `nemsim serve` keeps glibc's defaults: a server
runs indefinitely and its resident size is bounded by its settings, which a never-shrinking heap would undo.
"""

from __future__ import annotations

import os
import sys

# glibc tunables (malloc(3), mallopt(3)): large blocks from the heap, never trimmed, the heap grown in 1 GiB
TUNED = {
    "MALLOC_MMAP_THRESHOLD_": str(16 << 30),
    "MALLOC_TRIM_THRESHOLD_": str(16 << 30),
    "MALLOC_TOP_PAD_": str(1 << 30),
}
OPT_OUT = "NEMSIM_ALLOCATOR"  # "default": keep glibc's defaults
EXEMPT_COMMANDS = ("serve",)  # long-running: resident size matters more than speed (module docstring)


def tuned_environ(environ: dict[str, str]) -> dict[str, str] | None:
    """The environment to re-execute with, or None when nothing needs to change (already tuned, opted out,
    or not Linux)."""
    if not sys.platform.startswith("linux") or environ.get(OPT_OUT, "") in ("default", "tuned"):
        return None
    missing = {k: v for k, v in TUNED.items() if k not in environ}
    if not missing:
        return None
    return {**environ, **missing, OPT_OUT: environ.get(OPT_OUT, "tuned")}


def reexec_tuned(argv: list[str] | None = None) -> None:
    """Replace this process by ``python -m nemsim.cli ARGS`` with the tuned allocator (no return), unless
    ``tuned_environ`` says nothing needs to change or the command is exempt (then return at once)."""
    args = sys.argv[1:] if argv is None else argv
    command = next((a for a in args if not a.startswith("-")), None)
    env = tuned_environ(dict(os.environ))
    if env is None or command in EXEMPT_COMMANDS:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, "-m", "nemsim.cli", *args], env)
