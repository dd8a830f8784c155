"""Hand the heap's free pages back to the kernel after large, short-lived allocations (model warm-up, jobs):
glibc keeps freed blocks resident, so a server's resident size would otherwise only ever grow."""

from __future__ import annotations

import ctypes
import gc
import sys


def release_free_memory() -> None:
    """Hand the heap's free pages back to the kernel (glibc `malloc_trim`; elsewhere nothing). After the
    warm-up and after every job (module docstring)."""
    if not sys.platform.startswith("linux"):
        return
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc (e.g. musl)
        return
