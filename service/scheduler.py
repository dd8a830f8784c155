"""Admission and fair queueing for the expensive work, and cancellation when the client goes away.

Why: one compute slot served rollouts, meshes and mechanisms alike, so a burst of uncached rollouts
turned cheap mesh requests into 503s, and requests whose client had already disconnected still ran.

* `FairGate`: at most `limit` holders, at most `queue` waiting (more: `ServiceBusy`, the route answers
  503 + Retry-After) and at most `per_client` waiting per client key, so one client cannot fill the
  queue. A freed slot goes to the clients in round-robin order (each client's own requests in FIFO
  order), so one client with many queued requests does not starve another with one. A waiter gives up
  after `timeout_s`. Runs on the event loop: waiting costs no thread.
* The app keeps one gate per kind of work (`Gates`): uncached rollouts, meshes, mechanisms. Cache hits
  never touch a gate, and meshes of finished rollouts never wait behind rollouts.
* Rollouts run on their own worker threads (`low_priority_executor`), `rollout_nice` nicer than the
  server (Linux only; default 0: the server's priority). Jobs run at the server's priority too
  (`service.sim_child.JOB_NICE`), one at a time on one core (`service.jobs`). A positive
  `rollout_nice` lets the event loop (cheap answers, new requests) take the CPU first when rollouts
  saturate it, at the price of rollouts yielding to anything else on the machine. The model runtime
  computes in the calling thread, so the priority covers the forward passes; other work uses the
  default thread pool.
* No micro-batching of concurrent uncached rollouts (one forward pass over several waiting requests):
  measured through the served runtime (OpenVINO bf16, one thread), it saved only a small share of the
  model's CPU per rollout (the post-processing per rollout does not batch), while every batch shape
  compiles its own model (resident memory against the server's 1 GB budget) and each member of a batch
  waits for the whole batch. The figures are in benchmarks/service/README.md.
* `run_gated`: wait for a slot, run the blocking function in a worker thread, and give up as soon as
  the client disconnects. A request still waiting is dropped at once (its slot goes to the next one);
  one already computing finishes (a thread cannot be interrupted mid forward pass) and its result is
  cached, so a retry is free. The worker thread then hands the heap's free pages back to the kernel
  (`service.memory.trim_heap`): the computation's temporaries do not stay resident.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import sys
import threading
from collections import deque
from collections.abc import AsyncIterator, Callable
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

import anyio.to_thread
from starlette.requests import Request

from service.memory import trim_heap

T = TypeVar("T")
log = logging.getLogger(__name__)


class ServiceBusy(RuntimeError):
    """Too many requests are computing or waiting; retry later."""


class ClientGone(Exception):
    """The client disconnected before the answer was ready."""


def lower_thread_priority(increment: int) -> None:
    """Raise the calling thread's nice value by `increment` (at most to 19). Linux only: there
    `setpriority(PRIO_PROCESS, tid)` applies to one thread; elsewhere it would renice the whole server."""
    if increment <= 0 or not sys.platform.startswith("linux"):
        return
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + increment))
    except OSError as exc:  # e.g. a sandbox that forbids it: run at the normal priority
        log.warning("could not lower the priority of a compute thread: %s", exc)


def low_priority_executor(workers: int, increment: int, name: str) -> ThreadPoolExecutor:
    """`workers` threads whose nice value is `increment` above the server's (`lower_thread_priority`)."""
    return ThreadPoolExecutor(
        workers, thread_name_prefix=name, initializer=lower_thread_priority, initargs=(increment,)
    )


class FairGate:
    def __init__(
        self,
        name: str,
        limit: int,
        queue: int,
        per_client: int,
        timeout_s: float,
        executor: Executor | None = None,
    ) -> None:
        if limit < 1 or queue < 0 or per_client < 1 or timeout_s <= 0:
            raise ValueError(
                f"gate {name!r}: limit >= 1, queue >= 0, per_client >= 1 and timeout_s > 0 required, got "
                f"{limit}, {queue}, {per_client}, {timeout_s}"
            )
        self.name, self.limit, self.queue, self.per_client, self.timeout_s = (
            name,
            limit,
            queue,
            per_client,
            timeout_s,
        )
        self.executor = executor  # where the gated work runs (None: anyio's default thread pool)
        self.active = 0
        self._waiting: dict[str, deque[asyncio.Future[None]]] = {}
        self._turn: deque[str] = deque()  # client keys with waiters, in round-robin order

    @property
    def waiting(self) -> int:
        return sum(len(q) for q in self._waiting.values())

    @contextlib.asynccontextmanager
    async def slot(self, client: str = "-") -> AsyncIterator[None]:
        await self._acquire(client)
        try:
            yield
        finally:
            self._release()

    async def _acquire(self, client: str) -> None:
        if self.active < self.limit and not self._waiting:
            self.active += 1
            return
        if self.waiting >= self.queue:
            raise ServiceBusy(
                f"{self.name}: {self.active} running and {self.waiting} queued (the limit); retry shortly"
            )
        mine = self._waiting.setdefault(client, deque())
        if len(mine) >= self.per_client:
            raise ServiceBusy(
                f"{self.name}: this client already has {len(mine)} requests queued (the per-client limit); "
                "retry when one has finished"
            )
        if client not in self._turn:
            self._turn.append(client)
        granted: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        mine.append(granted)
        try:
            await asyncio.wait_for(asyncio.shield(granted), self.timeout_s)
        except BaseException as exc:  # timeout or cancellation (client gone): leave the queue cleanly
            if granted.done() and not granted.cancelled():
                self._release()  # the slot arrived just now: pass it on
            else:
                granted.cancel()
                self._forget(client, granted)
            if isinstance(exc, TimeoutError):
                raise ServiceBusy(
                    f"{self.name}: no slot became free within {self.timeout_s:g} s; retry shortly"
                ) from None
            raise

    def _forget(self, client: str, granted: asyncio.Future[None]) -> None:
        mine = self._waiting.get(client)
        if mine is not None and granted in mine:
            mine.remove(granted)
            if not mine:
                del self._waiting[client]
                self._turn.remove(client)

    def _release(self) -> None:
        self.active -= 1
        while self.active < self.limit and self._turn:
            client = self._turn.popleft()
            mine = self._waiting[client]
            granted = mine.popleft()
            if mine:
                self._turn.append(client)  # back of the line: the next client goes first
            else:
                del self._waiting[client]
            if not granted.done():
                self.active += 1
                granted.set_result(None)


@dataclass
class Gates:
    """One gate per kind of expensive work (module docstring)."""

    rollout: FairGate
    mesh: FairGate
    mechanisms: FairGate

    @classmethod
    def from_settings(cls, settings: Any) -> Gates:
        def gate(name: str, limit: int, executor: Executor | None = None) -> FairGate:
            return FairGate(
                name,
                limit,
                settings.max_queue,
                settings.max_queue_per_client,
                settings.queue_timeout_s,
                executor,
            )

        rollout_threads = low_priority_executor(
            settings.max_concurrency, settings.rollout_nice, "nemsim-rollout"
        )
        return cls(
            rollout=gate("rollouts", settings.max_concurrency, rollout_threads),
            mesh=gate("meshes", settings.mesh_concurrency),
            mechanisms=gate("mechanisms", settings.mechanisms_concurrency),
        )

    def all(self) -> list[FairGate]:
        return [self.rollout, self.mesh, self.mechanisms]

    def close(self) -> None:
        """Stop the gates' own worker threads once their running work is done (app shutdown)."""
        for gate in self.all():
            if gate.executor is not None:
                gate.executor.shutdown(wait=False, cancel_futures=True)


async def until_disconnect(request: Request, work: Any) -> Any:
    """Await `work` (a coroutine) unless the client disconnects first: then cancel it, wait for the
    cancellation to finish (a running thread completes; its slot is released) and raise ClientGone."""
    task = asyncio.ensure_future(work)

    async def disconnected() -> None:
        while (await request.receive())["type"] != "http.disconnect":
            pass

    watcher = asyncio.ensure_future(disconnected())
    try:
        await asyncio.wait({task, watcher}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        if not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            watcher.cancel()
            raise ClientGone(request.url.path)
        watcher.cancel()
    return task.result()


async def run_gated(request: Request, gate: FairGate, client: str, fn: Callable[..., T], *args: Any) -> T:
    """`fn(*args)` in a worker thread once `gate` has a slot for `client`; ClientGone on disconnect."""

    async def work() -> T:
        async with gate.slot(client):
            return await in_thread(gate.executor, _then_trim, fn, *args)

    return await until_disconnect(request, work())


def _then_trim(fn: Callable[..., T], *args: Any) -> T:
    try:
        return fn(*args)
    finally:
        trim_heap()


async def in_thread(executor: Executor | None, fn: Callable[..., T], *args: Any) -> T:
    """`fn(*args)` on `executor` (None: anyio's thread pool). Cancellation waits for the thread to
    finish (it cannot be interrupted), so a gate's slot is only freed once its work is really done."""
    if executor is None:
        return await anyio.to_thread.run_sync(fn, *args)
    future = asyncio.get_running_loop().run_in_executor(executor, fn, *args)
    try:
        return await asyncio.shield(future)
    except asyncio.CancelledError:
        await asyncio.wait({future})
        raise
