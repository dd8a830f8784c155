"""Scheduling (defects 8, 9): cheap requests never wait behind rollouts, fair queueing between clients,
and queued work is dropped when its client disconnects."""

from __future__ import annotations

import asyncio
import os
import sys
import threading

import numpy as np
import pytest

from service.scheduler import ClientGone, FairGate, ServiceBusy, run_gated


@pytest.fixture
def blocked_rollouts(served, monkeypatch):
    """block(): from then on uncached rollouts wait until `release` is set; `started` is set when one is
    computing."""
    started, release = threading.Event(), threading.Event()
    compute = type(served)._compute

    def slow(self, *args):
        started.set()
        release.wait(20)
        return compute(self, *args)

    def block():
        monkeypatch.setattr(type(served), "_compute", slow)
        return started, release

    yield block
    release.set()


def test_cheap_requests_do_not_wait_behind_rollouts(
    make_client, default_controls, served, blocked_rollouts
):
    c = make_client(max_queue=0)
    done = c.post(
        "/rollout", json={"controls": default_controls, "steps": 2}
    ).json()  # cached before blocking
    _ = c.get("/mechanisms")  # cached analysis
    started, release = blocked_rollouts()
    busy = threading.Thread(
        target=c.post,
        args=("/rollout",),
        kwargs={"json": {"controls": {**default_controls, "flux_cl": 0.0111}, "steps": 1}},
    )
    busy.start()
    try:
        assert started.wait(10)
        other = {**default_controls, "flux_cl": 0.0112}
        assert c.post("/rollout", json={"controls": other, "steps": 1}).status_code == 503  # rollouts full
        # ... while a cached rollout, a new mesh of a finished rollout and a cached analysis are served
        assert c.post("/rollout", json={"controls": default_controls, "steps": 2}).json()["cached"]
        mesh = c.get(f"/rollouts/{done['id']}/mesh", params={"step": 1, "format": "ply"})
        assert mesh.status_code == 200, mesh.text
        assert c.get("/mechanisms").status_code == 200
        assert c.get("/health").status_code == 200 and c.get("/ready").status_code == 200
    finally:
        release.set()
        busy.join()


def test_gate_round_robin_between_clients():
    async def scenario() -> list[str]:
        gate = FairGate("test", limit=1, queue=10, per_client=10, timeout_s=5)
        order: list[str] = []
        hold = asyncio.Event()

        async def job(client: str, tag: str) -> None:
            async with gate.slot(client):
                order.append(tag)
                if tag == "first":
                    await hold.wait()

        tasks = [asyncio.create_task(job("a", "first"))]
        await asyncio.sleep(0)
        for tag in ("a1", "a2", "a3"):
            tasks.append(asyncio.create_task(job("a", tag)))
            await asyncio.sleep(0)
        tasks.append(asyncio.create_task(job("b", "b1")))
        await asyncio.sleep(0)
        hold.set()
        await asyncio.gather(*tasks)
        return order

    # b's one request goes second, not behind a's whole backlog
    assert asyncio.run(scenario()) == ["first", "a1", "b1", "a2", "a3"]


def test_gate_limits_queue_per_client_and_in_all():
    async def scenario() -> None:
        gate = FairGate("test", limit=1, queue=3, per_client=2, timeout_s=5)
        hold = asyncio.Event()

        async def job(client: str) -> None:
            async with gate.slot(client):
                await hold.wait()

        tasks = [asyncio.create_task(job("a")) for _ in range(3)]  # 1 running + 2 queued
        await asyncio.sleep(0.01)
        with pytest.raises(ServiceBusy, match="per-client"):
            await job("a")
        tasks.append(asyncio.create_task(job("b")))
        await asyncio.sleep(0.01)
        with pytest.raises(ServiceBusy, match="queued"):
            await job("c")
        hold.set()
        await asyncio.gather(*tasks)
        assert gate.active == 0 and gate.waiting == 0

    asyncio.run(scenario())


def test_gate_timeout_leaves_queue_clean():
    async def scenario() -> None:
        gate = FairGate("test", limit=1, queue=4, per_client=4, timeout_s=0.05)
        async with gate.slot("a"):
            with pytest.raises(ServiceBusy, match="no slot became free"):
                async with gate.slot("b"):
                    pass
            assert gate.waiting == 0
        async with gate.slot("b"):
            assert gate.active == 1

    asyncio.run(scenario())


class _Gone:
    """A request whose client disconnects after `after_s`."""

    def __init__(self, after_s: float) -> None:
        self.after_s = after_s
        self.url = type("U", (), {"path": "/rollout"})()

    async def receive(self):
        await asyncio.sleep(self.after_s)
        return {"type": "http.disconnect"}


def test_disconnected_client_leaves_the_queue_and_its_work_never_runs():
    ran: list[str] = []

    async def scenario() -> None:
        gate = FairGate("test", limit=1, queue=20, per_client=20, timeout_s=30)
        hold = asyncio.Event()

        async def occupant() -> None:
            async with gate.slot("x"):
                await hold.wait()

        running = asyncio.create_task(occupant())
        await asyncio.sleep(0)
        waiters = [
            asyncio.create_task(run_gated(_Gone(0.3), gate, f"c{i}", ran.append, f"job{i}"))
            for i in range(17)
        ]
        await asyncio.sleep(0.01)
        assert gate.waiting == 17
        for w in waiters:
            with pytest.raises(ClientGone):
                await w
        assert gate.waiting == 0  # all 17 left the queue at once, not after their turn
        hold.set()
        await running
        assert gate.active == 0

    asyncio.run(scenario())
    assert ran == []


def test_rollout_cache_is_bounded_in_bytes(served, default_controls):
    """The cache keeps at most `cache_bytes` of states, evicting the least recently used."""
    from service.served_model import ServedModel

    s = ServedModel(served.predictor, cache_size=100, cache_bytes=1)
    raw = np.array([list(default_controls.values())] * 2)
    result, cached = s.rollout(raw)
    assert not cached and result.states.nbytes > 1
    assert s.rollout(raw)[1] is False  # larger than the whole budget: never kept
    rows = [raw * f for f in (1.0, 1.01, 1.02)]
    sizes = [s.rollout(r)[0].states.nbytes for r in rows]  # compact: each its own size
    budget = sizes[1] + sizes[2]
    s = ServedModel(served.predictor, cache_size=100, cache_bytes=budget)
    for r in rows:
        s.rollout(r)[0].encoded.result()  # stored: cached (or not) by now
    assert s._rollouts.bytes <= budget and len(s._rollouts) == 2
    assert s.rollout(rows[2])[1] is True and s.rollout(rows[0])[1] is False


def test_mesh_warm_up_exports_every_format(served, monkeypatch):
    import nemsim.geometry.mesh as mesh_lib

    seen: list[str] = []
    export = mesh_lib.export_mesh
    monkeypatch.setattr(mesh_lib, "export_mesh", lambda mesh, fmt: seen.append(fmt) or export(mesh, fmt))
    served.warm_up_meshes()
    assert sorted(seen) == ["glb", "obj", "ply", "stl"]


@pytest.mark.skipif(not hasattr(os, "getpriority"), reason="thread priorities are a POSIX facility")
def test_rollouts_compute_on_lower_priority_threads(make_client, default_controls, served, monkeypatch):
    """Uncached rollouts run on the gate's own threads, `rollout_nice` nicer than the server's, so cheap
    answers get the CPU first when rollouts saturate it."""
    seen: list[tuple[str, int]] = []
    compute = type(served)._compute

    def spy(self, *args):
        tid = threading.get_native_id()
        seen.append((threading.current_thread().name, os.getpriority(os.PRIO_PROCESS, tid)))
        return compute(self, *args)

    monkeypatch.setattr(type(served), "_compute", spy)
    c = make_client(rollout_nice=3)
    controls = {**default_controls, "flux_cl": default_controls["flux_cl"] * 1.0123}
    assert c.post("/rollout", json={"controls": controls, "steps": 2}).status_code == 200
    (name, nice), base = seen[0], os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    assert name.startswith("nemsim-rollout")
    assert nice == min(19, base + 3) if sys.platform.startswith("linux") else nice == base


def test_cancelled_work_holds_its_slot_until_the_thread_finishes():
    """in_thread on an executor: cancelling the awaiting task does not return before the thread is done
    (a gate's slot must not be freed while its work still runs)."""
    from concurrent.futures import ThreadPoolExecutor

    from service.scheduler import in_thread

    finished = threading.Event()

    def work():
        threading.Event().wait(0.3)
        finished.set()

    async def main():
        with ThreadPoolExecutor(1) as pool:
            task = asyncio.ensure_future(in_thread(pool, work))
            await asyncio.sleep(0.05)
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            return finished.is_set()

    assert asyncio.run(main())


def test_cache_keeps_entries_in_use_under_a_flood_of_new_ones():
    """A stream of one-off entries evicts other one-off entries, not those that were hit again; the
    `size` most recent entries always stay, the reused ones on top (at most `KEPT_SHARE` more), and the
    byte bound holds throughout."""
    from service.served_model import _LRU

    cache = _LRU(6, max_bytes=900, weigh=lambda v: v)
    for key in ("hot1", "hot2"):
        cache.put(key, 100)
        assert cache.get(key) == 100  # used again: kept when it falls out of the recent ones
    for k in range(50):
        cache.put(f"once{k}", 100)
        assert len(cache) <= 6 + 3 and cache.bytes <= 900
    assert cache.get("once43") is None and all(cache.get(f"once{k}") == 100 for k in range(44, 50))
    assert cache.get("hot1") == 100 and cache.get("hot2") == 100
    plain = _LRU(6, max_bytes=600, weigh=lambda v: v)  # nothing reused: plain LRU order
    for k in range(8):
        plain.put(k, 100)
    assert [plain.get(k) for k in range(8)] == [None, None, *[100] * 6]
    tight = _LRU(6, max_bytes=600, weigh=lambda v: v)  # the budget binds: the kept ones go first
    tight.put("hot", 100)
    tight.get("hot")
    for k in range(6):
        tight.put(k, 100)
    assert tight.get("hot") is None and all(tight.get(k) == 100 for k in range(6))
