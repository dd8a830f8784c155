"""Wrong API keys are rate-limited per client address: 401 up to a burst, then 429 + Retry-After for every
request of that address that needs a key, the right key included; missing keys and probes do not count."""

from __future__ import annotations

KEY = "k" * 24
WRONG = "w" * 24


def test_wrong_keys_meet_429_after_the_burst(make_client):
    c = make_client(api_keys=KEY, key_failure_burst=5, key_failures_per_minute=1)
    assert c.get("/model", headers={"X-API-Key": KEY}).status_code == 200
    codes = [c.get("/model", headers={"X-API-Key": f"{WRONG}{i}"}).status_code for i in range(150)]
    assert codes[:5] == [401] * 5 and set(codes[5:]) == {429}
    r = c.get("/model", headers={"X-API-Key": KEY})  # no answer tells a right key from a wrong one now
    assert r.status_code == 429 and "wrong API keys" in r.json()["message"]
    assert 1 <= int(r.headers["retry-after"]) <= 60
    assert c.get("/ready").status_code == 200  # probes need no key


def test_the_default_bounds_wrong_keys(make_client):
    c = make_client(api_keys=KEY)
    codes = [c.get("/model", headers={"X-API-Key": f"{WRONG}{i}"}).status_code for i in range(150)]
    assert codes.count(401) <= 25 and codes[-1] == 429


def test_missing_keys_do_not_count(make_client):
    c = make_client(api_keys=KEY, key_failure_burst=2, key_failures_per_minute=1)
    assert {c.get("/model").status_code for _ in range(10)} == {401}
    assert c.get("/model", headers={"X-API-Key": KEY}).status_code == 200


def test_token_buckets_wait_without_taking():
    from service.access import TokenBuckets

    b = TokenBuckets(per_minute=60, burst=1)
    assert b.wait("a", 0.0) == 0.0 and b.wait("a", 0.0) == 0.0
    assert b.take("a", 0.0) == 0.0
    assert b.wait("a", 0.0) == 1.0 and b.wait("a", 0.5) == 0.5 and b.wait("a", 1.0) == 0.0
