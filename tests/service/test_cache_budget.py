"""The rollout cache holds what the settings say: the ids (and mesh links) of the last `cache_size` rollouts
resolve within the default memory budget, follow-ups of old ids never push recent ones out, meshes of the
stored float16 states match those of the float32 rollout, and every state streams back whole."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
MESH_TOLERANCE_NM = 0.01  # largest vertex displacement from the float16 rounding (a 4 nm voxel: 1/400)


@pytest.mark.slow
def test_the_last_cache_size_rollouts_keep_their_mesh_links(served, make_client, default_controls):
    """33 uncached rollouts with distinct controls under the default cache settings: the mesh link of the
    2nd still resolves, the 1st's is gone (capacity 32). 200 steps, so that 32 trajectories as plain
    float16 (6.3 MB each on `tiny`) would exceed the default budget."""
    from service.config import Settings
    from service.deps import get_served_model
    from service.served_model import ServedModel

    defaults = Settings.model_fields
    size, budget_mb = defaults["cache_size"].default, defaults["cache_max_mb"].default
    assert size == 32
    fresh = ServedModel(served.predictor, cache_size=size, cache_bytes=budget_mb << 20)
    c = make_client(max_steps=200)
    c.app.dependency_overrides[get_served_model] = lambda: fresh
    links = []
    for i in range(size + 1):
        controls = {**default_controls, "flux_cl": default_controls["flux_cl"] * (1 + 0.01 * i)}
        body = {"controls": controls, "steps": 200, "meshes": [{"step": 200, "channel": "si"}]}
        r = c.post("/rollout", json=body)
        assert r.status_code == 200 and r.json()["cached"] is False, r.text
        links.append(r.json()["meshes"][0]["url"])
    assert c.get(links[1]).status_code == 200
    assert c.get(links[-1]).status_code == 200
    assert c.get(links[0]).status_code == 404
    assert all(fresh.get_rollout(url.split("/")[2]) for url in links[1:])


def test_follow_ups_of_old_ids_never_evict_recent_ones():
    """Mesh and slice requests look rollouts up with touch=False: an old rollout clients come back to is
    kept, but it does not become one of the `size` most recent, so the ids of the latest POST /rollout
    answers all stay."""
    from service.served_model import _LRU

    cache = _LRU(4, max_bytes=800, weigh=lambda v: v)
    for key in ("old1", "old2"):
        cache.put(key, 100)
        assert cache.get(key, touch=False) == 100  # followed up: kept when it leaves the recent ones
    for key in "CDEF":
        cache.put(key, 100)
    for _ in range(3):
        assert cache.get("old1", touch=False) == 100 and cache.get("old2", touch=False) == 100
    assert all(cache.get(key, touch=False) == 100 for key in "CDEF")
    assert len(cache) == 6 and cache.bytes == 600


def test_meshes_of_float16_states_match_the_float32_ones():
    """The cache keeps float16 states (what the API returns); a mesh made from them lies within
    MESH_TOLERANCE_NM of the mesh of the float32 rollout (every vertex, both ways), for the served model."""
    from scipy.spatial import cKDTree

    from nemsim.geometry.mesh import surface_mesh
    from nemsim.inference import ControlSchedule, Predictor

    predictor = Predictor.from_checkpoint(REPO / "checkpoints" / "nemsim-small.pt", backend="torch")
    rng = np.random.default_rng(0)
    for _ in range(2):
        u = rng.uniform(-1, 1, 14).astype(np.float32)
        pred = predictor.rollout(ControlSchedule.from_normalized(u, steps=20))
        for k in (10, 20):
            for ch in (0, 1):
                exact = pred.states[k, ch]  # (D, H, W) float32
                stored = exact.astype(np.float16).astype(np.float32)
                a = np.asarray(surface_mesh(exact, predictor.scene).vertices)  # (V, 3) nm
                b = np.asarray(surface_mesh(stored, predictor.scene).vertices)
                gap = max(cKDTree(a).query(b)[0].max(), cKDTree(b).query(a)[0].max())
                assert gap <= MESH_TOLERANCE_NM, (k, ch, gap)


def test_all_states_stream_back_whole(make_client, served, default_controls, decode_fields):
    """fields="all" is streamed state block by state block: the JSON is complete (Content-Length exact)
    and the states are the cached trajectory's, bit for bit."""
    c = make_client()
    controls = {**default_controls, "flux_cl": default_controls["flux_cl"] * 1.037}
    for _ in range(2):  # computed, then from the cache
        r = c.post("/rollout", json={"controls": controls, "steps": 7, "fields": "all"})
        assert r.status_code == 200 and int(r.headers["content-length"]) == len(r.content)
        body = r.json()
        got = decode_fields(body["fields"])
        want = served.get_rollout(body["id"]).states.decode()
        assert body["fields"]["steps"] == list(range(8))
        assert np.array_equal(got.view(np.uint16), want.view(np.uint16))
    assert body["cached"] is True
