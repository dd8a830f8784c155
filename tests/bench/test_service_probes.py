"""`nemsim bench service --probes` end to end on a tiny checkpoint: every probe runs against a real
`nemsim serve`, with counts scaled down and the connection timeouts shortened (no timing is asserted)."""

from __future__ import annotations

import json

import pytest

from bench.service_fuzz import CaseMaker
from bench.service_probes import ProbeConfig, run_probes
from bench.service_report import probes_markdown

TINY = ProbeConfig(
    steps=5, quiet_uncached=3, quiet_cached=3, load_clients=2, load_requests=6, burst_clients=8,
    burst_waves=1, slow_sockets=40, slow_cap_s=20.0, silent_sockets=40, silent_seconds=3.0, fuzz_calls=300,
    fuzz_cap_s=120.0, job_rollouts=3, job_cap_s=60.0,
)


def test_cases_are_seeded_and_labelled():
    make_a, make_b = CaseMaker(3, 100, 100, None), CaseMaker(3, 100, 100, None)
    a = [make_a.next() for _ in range(200)]
    b = [make_b.next() for _ in range(200)]
    assert [(c.route, c.kind, c.body) for c in a] == [(c.route, c.kind, c.body) for c in b]
    assert {c.cls for c in a} >= {"guard", "malformed"}
    assert {c.route for c in a} == {"/rollout", "/design", "/simulations"}


@pytest.mark.slow
def test_probes_against_a_live_server(tiny_checkpoint):
    report = run_probes(tiny_checkpoint, TINY, server_env={"NEMSIM_HEAD_TIMEOUT_S": "2"})
    json.dumps(report)  # JSON-ready
    p = report["probes"]
    assert not [k for k, v in p.items() if "error" in v], p
    assert p["fuzz"]["calls"] == 300 and p["fuzz"]["guard_cases"] > 0
    assert p["fuzz"]["server_errors_5xx"] == 0
    assert p["fuzz"]["out_of_guard_accepted"] == 0, p["fuzz"]["accepted_examples"]
    assert p["fuzz"]["error_bodies_leaking"] == 0, p["fuzz"]["leak_examples"]
    assert p["load"]["server_errors_5xx"] == 0 and p["load"]["mesh_404_last_32"] == 0
    assert p["slowloris"]["dropped_at_once"] > 0 and p["slowloris"]["server_alive"]
    assert p["silent_sockets"]["other_client"]["failures"] == 0, p["silent_sockets"]["other_client"]
    assert p["job_beside_rollouts"]["rollouts_during_job"]["n"] > 0
    assert p["sigterm"]["children_before"] == 1
    assert p["sigterm"]["children_left"] == 0 and p["sigterm"]["job_folders_left"] == 0
    k9 = p["kill9_restart"]
    assert k9["children_before_kill"] == 1 and k9["children_left_after_kill"] == 0
    assert k9["job_folders_left_by_the_killed_server"] == 1 and k9["job_folders_after_restart"] == 0
    assert 0 < p["memory"]["peak_rss_mib"]
    page = probes_markdown(report)
    assert "| fuzz: out-of-guard requests accepted | 0 |" in page
