"""Operations: API keys, loopback-only without keys, rate limits, request ids, security headers,
/docs switch and Prometheus metrics."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

KEY = "k" * 20
OTHER = "o" * 24


@pytest.fixture
def app_with(served):
    from service.config import Settings
    from service.main import create_app

    def make(**overrides):
        return create_app(Settings(**{"warmup_steps": 0, **overrides}), served=served)

    return make


def test_api_keys_required_when_configured(app_with, default_controls):
    with TestClient(app_with(api_keys=f"{KEY}, {OTHER}")) as c:
        assert c.get("/health").status_code == 200 and c.get("/ready").status_code == 200  # probes open
        r = c.get("/model")
        assert r.status_code == 401 and "X-API-Key" in r.json()["message"]
        assert c.get("/model", headers={"X-API-Key": "wrong" * 5}).status_code == 401
        assert c.get("/model", headers={"X-API-Key": KEY}).status_code == 200
        assert c.get("/model", headers={"X-API-Key": OTHER}).status_code == 200
        assert c.get("/metrics").status_code == 401


def test_api_keys_from_file(app_with, tmp_path):
    f = tmp_path / "keys"
    f.write_text(f"# service keys\n{KEY}  # lab\n\n")
    with TestClient(app_with(api_keys_file=f)) as c:
        assert c.get("/model", headers={"X-API-Key": KEY}).status_code == 200
        assert c.get("/model").status_code == 401


def test_short_key_refused():
    from service.config import Settings

    with pytest.raises(ValueError, match="at least 16"):
        Settings(api_keys="short").api_key_set()


def test_without_keys_only_loopback(app_with):
    app = app_with()
    with TestClient(app, client=("203.0.113.5", 5000)) as remote:
        r = remote.get("/model")
        assert r.status_code == 403 and "API keys" in r.json()["message"]
        assert remote.get("/health").status_code == 200  # probes stay open
    with TestClient(app, client=("127.0.0.1", 5000)) as local:
        assert local.get("/model").status_code == 200
    with TestClient(app_with(allow_remote_without_key=True), client=("203.0.113.5", 5000)) as remote:
        assert remote.get("/model").status_code == 200


def test_rate_limit_per_key(app_with):
    with TestClient(app_with(api_keys=f"{KEY},{OTHER}", rate_limit_per_minute=60, rate_limit_burst=3)) as c:
        codes = [c.get("/model", headers={"X-API-Key": KEY}).status_code for _ in range(5)]
        assert codes[:3] == [200] * 3 and codes[3:] == [429, 429]
        r = c.get("/model", headers={"X-API-Key": KEY})
        assert int(r.headers["retry-after"]) >= 1 and "rate limit" in r.json()["message"]
        assert c.get("/model", headers={"X-API-Key": OTHER}).status_code == 200  # another key: own bucket
        assert all(c.get("/health").status_code == 200 for _ in range(5))  # probes exempt


def test_token_bucket_refills():
    from service.access import TokenBuckets

    b = TokenBuckets(per_minute=60, burst=2)
    assert [b.take("a", 0.0), b.take("a", 0.0)] == [0.0, 0.0]
    assert b.take("a", 0.0) == pytest.approx(1.0)
    assert b.take("a", 1.0) == 0.0  # one token per second


def test_request_id_and_security_headers(client):
    r = client.get("/model", headers={"X-Request-ID": "abc-123"})
    assert r.headers["x-request-id"] == "abc-123"
    assert r.headers["x-content-type-options"] == "nosniff" and r.headers["x-frame-options"] == "DENY"
    assert "default-src 'none'" in r.headers["content-security-policy"]
    generated = client.get("/model", headers={"X-Request-ID": "bad id\twith spaces"}).headers["x-request-id"]
    assert generated != "bad id\twith spaces" and len(generated) == 16
    assert "content-security-policy" not in client.get("/docs").headers  # the UI loads its script
    assert client.get("/nope").headers["x-request-id"]  # errors too


def test_access_log_is_json(client, caplog):
    import json
    import logging

    with caplog.at_level(logging.INFO, logger="service.access"):
        client.get("/model", headers={"X-Request-ID": "log-me"})
    line = next(
        json.loads(r.message) for r in caplog.records if r.name == "service.access" and "log-me" in r.message
    )
    assert line["route"] == "/model" and line["status"] == 200 and line["ms"] >= 0


def test_docs_can_be_turned_off(app_with):
    with TestClient(app_with(docs=False)) as c:
        assert c.get("/docs").status_code == 404 and c.get("/openapi.json").status_code == 404
        assert c.get("/model").status_code == 200


def test_metrics(app_with, default_controls):
    with TestClient(app_with()) as c:
        controls = {**default_controls, "flux_cl": 0.0071}
        first = c.post("/rollout", json={"controls": controls, "steps": 1})
        c.post("/rollout", json={"controls": controls, "steps": 1})
        c.get(f"/rollouts/{first.json()['id']}/mesh", params={"format": "ply"})
        text = c.get("/metrics").text
    assert 'nemsim_http_requests_total{method="POST",route="/rollout",status="200"} 2.0' in text
    assert 'nemsim_http_request_duration_seconds_count{route="/rollouts/{rollout_id}/mesh"} 1.0' in text
    assert 'nemsim_cache_requests_total{kind="rollout",result="hit"} 1.0' in text
    assert 'nemsim_cache_requests_total{kind="rollout",result="miss"} 1.0' in text
    assert "nemsim_rollouts_total 1.0" in text
    assert 'nemsim_queue_depth{work="rollouts"} 0.0' in text and "nemsim_model_ready 1.0" in text


def test_bind_warning():
    from service.access import bind_warning

    assert bind_warning("127.0.0.1", frozenset(), False) is None
    assert bind_warning("0.0.0.0", frozenset({KEY}), False) is None
    assert "403" in bind_warning("0.0.0.0", frozenset(), False)
    assert "anyone" in bind_warning("0.0.0.0", frozenset(), True)
