"""What a client can rely on: booleans in request bodies are JSON booleans, a cancelled job reads
`cancelled` until it is forgotten (then 404), and schemathesis reads the request schema of POST /rollout
at the default ceiling of 100 steps."""

from __future__ import annotations

import threading

import pytest
from test_jobs import _blocking_work, wait_status  # tests/service is on sys.path (rootdir-relative)


@pytest.mark.parametrize("value", ["yes", "true", 1, 0, None])
def test_booleans_in_bodies_are_strict(make_client, default_controls, value):
    c = make_client()
    cases = [
        ("/design", {"targets": {"etch_depth": 50}, "verify": value}, "verify"),
        ("/design", {"targets": {"etch_depth": 50}, "refine": value}, "refine"),
        ("/rollout", {"controls": default_controls, "steps": 1, "intervals": value}, "intervals"),
    ]
    for path, body, field in cases:
        if value is None and field == "refine":  # null is refine's documented default
            continue
        r = c.post(path, json=body)
        assert r.status_code == 422, (path, field, r.text)
        assert field in r.json()["message"], r.json()


def test_a_cancelled_job_reads_cancelled_until_forgotten(make_client):
    c = make_client(jobs_keep_max=1)
    jobs = c.app.state.jobs
    started = threading.Event()
    running = jobs.submit("simulation", _blocking_work(started))
    assert started.wait(5)
    r = c.delete(f"/jobs/{running.id}")
    assert r.status_code == 200
    assert r.json()["status"] == "cancelled" and r.json()["result"] is None  # answered once it stopped
    for _ in range(2):  # as often as it is asked
        body = c.get(f"/jobs/{running.id}").json()
        assert body["status"] == "cancelled" and body["message"] == "cancelled while running"
    again = c.delete(f"/jobs/{running.id}")  # a finished job is left as it is
    assert again.status_code == 200 and again.json()["status"] == "cancelled"
    finished = jobs.submit("simulation", lambda job: {"ok": True})
    assert wait_status(c, f"/jobs/{finished.id}", {"done"}, timeout_s=10)["status"] == "done"
    r = c.get(f"/jobs/{running.id}")  # beyond jobs_keep_max (1) finished jobs: forgotten
    assert r.status_code == 404 and "unknown job id" in r.json()["message"]


def test_the_jobs_schema_documents_the_fate_of_a_cancelled_job(make_client):
    doc = make_client().get("/openapi.json").json()
    status = doc["components"]["schemas"]["JobStatus"]["properties"]["status"]["description"]
    assert "cancelled" in status and "404" in status
    assert "cancelled" in doc["paths"]["/jobs/{job_id}"]["delete"]["description"]


def test_schemathesis_reads_the_rollout_request_schema(make_client):
    """The default ceiling (100 steps): schemathesis builds its generator for the body and draws from it."""
    import schemathesis
    from hypothesis import HealthCheck, given, settings

    app = make_client().app
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    (operation,) = [r.ok() for r in schema.get_all_operations() if r.ok().path == "/rollout"]
    bodies = []

    @given(case=operation.as_strategy())
    @settings(max_examples=5, deadline=None, suppress_health_check=list(HealthCheck), database=None)
    def draw(case) -> None:
        bodies.append(case.body)

    draw()  # UnsupportedSchema here: the schema is beyond what schemathesis can expand
    assert bodies and all(isinstance(b, dict) for b in bodies)
