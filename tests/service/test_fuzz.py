"""Property-based fuzz of the OpenAPI schema (schemathesis): whatever the input, never a 5xx."""

from __future__ import annotations

import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error


def test_no_server_errors(served):
    """Every operation of the schema, a bounded number of generated requests each (< 30 s in all)."""
    from service.config import Settings
    from service.main import create_app

    # sim_queue: a fuzzed simulator job must not meet a full queue (its 503 is tested in test_jobs.py)
    app = create_app(
        Settings(warmup_steps=0, max_steps=3, rate_limit_per_minute=0, sim_queue=1000), served=served
    )
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    operations = [result.ok() for result in schema.get_all_operations()]
    assert {op.path for op in operations} >= {
        "/rollout",
        "/rollouts/{rollout_id}/mesh",
        "/mechanisms",
        "/model",
    }
    seen: list[int] = []
    for op in operations:

        @given(case=op.as_strategy())
        @settings(max_examples=10, deadline=None, suppress_health_check=list(HealthCheck), database=None)
        def fuzz(case) -> None:
            response = case.call()
            seen.append(response.status_code)
            case.validate_response(response, checks=[not_a_server_error])

        fuzz()
    app.state.jobs.close()  # cancel the simulator jobs the fuzzing started
    assert seen and max(seen) < 500
    assert 200 in seen  # the generator also produced valid requests, not only rejections
