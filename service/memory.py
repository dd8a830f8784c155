"""Hand the heap's free pages back to the kernel after large, short-lived allocations (model warm-up, jobs,
every rollout, mesh and mechanisms analysis): glibc keeps freed blocks resident, so a server's resident size
would otherwise only ever grow.

Choices: after every gated computation (`service.scheduler.run_gated`) `trim_heap` alone, about a
millisecond of CPU (the page faults of the next computation included, measured on `small`: within the
noise of an uncached rollout, about a millisecond per mesh), which kept a loaded `small` server's peak
resident size through the service probes' load some 35 MB lower (concurrent rollouts, meshes and
responses leave their temporaries scattered over the heap); a garbage collection only after the warm-up
and after jobs (`release_free_memory`), where its cost does not matter.
"""

from __future__ import annotations

import ctypes
import gc
import sys
import threading
from typing import Any

_LIBC: list[Any] = []  # glibc, once loaded; [None] where there is none (not Linux, musl)


def _libc() -> Any:
    if not _LIBC:
        libc = None
        if sys.platform.startswith("linux"):
            try:
                libc = ctypes.CDLL("libc.so.6")
                libc.malloc_trim  # noqa: B018 -- glibc's, absent elsewhere (e.g. musl)
            except (OSError, AttributeError):
                libc = None
        _LIBC.append(libc)
    return _LIBC[0]


def trim_heap() -> None:
    """Hand the heap's free pages back to the kernel (glibc `malloc_trim`; elsewhere nothing)."""
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)


class ResponseBudget:
    """Bytes of large response bodies (every field, meshes) being sent at once, at most `max_bytes`.

    A body is streamed piece by piece from the compact cache, yet each one in flight keeps a thread, its
    decode buffers and its socket's buffers busy: many at once grew the server past its memory budget, and
    glibc kept the peak. `reserve` refuses a body that would pass the budget (the route answers 503 +
    Retry-After); `release` hands it back once sent or abandoned, and the heap is trimmed whenever the last
    one is done (`trim_heap`), so the resident size comes back down after a burst."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes, self.used = max_bytes, 0
        self._lock = threading.Lock()

    def reserve(self, n: int) -> bool:
        """Take `n` bytes if they fit (one body always fits an idle budget); whether they were taken."""
        with self._lock:
            if self.used and self.used + n > self.max_bytes:
                return False
            self.used += n
            return True

    def release(self, n: int) -> None:
        with self._lock:
            self.used -= n
            idle = self.used == 0
        if idle:
            trim_heap()


def release_free_memory() -> None:
    """Collect garbage, then `trim_heap`. After the warm-up and after every job (module docstring)."""
    if _libc() is None:
        return
    gc.collect()
    trim_heap()
