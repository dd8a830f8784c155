"""Operations: Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import Response

router = APIRouter(tags=["operations"])


@router.get("/metrics", response_class=Response, responses={200: {"content": {"text/plain": {}}}})
async def get_metrics(request: Request) -> Response:
    """Prometheus text format: requests and latency per route, queue depth, cache hits, rollouts."""
    state = request.app.state
    return Response(
        state.metrics.render(state.gates, state.service.ready), media_type=state.metrics.content_type
    )
