"""`nemsim.client.Client` against a real `nemsim serve` (the tiny checkpoint, the server's default settings)
and, for what a healthy server never does on demand (429 then 200, a non-JSON error), against a scripted
HTTP server of the standard library."""

from __future__ import annotations

import csv
import http.server
import json
import threading
from collections.abc import Iterator

import numpy as np
import pytest

from bench.live_server import LiveServer
from nemsim.client import Client, JobTimeout, ServiceError, ServiceUnreachable
from nemsim.controls import CONTROL_NAMES
from service.protocol import free_port


@pytest.fixture(scope="module")
def live(tiny_checkpoint, tmp_path_factory) -> Iterator[LiveServer]:
    folder = tmp_path_factory.mktemp("client_server")
    (folder / "jobs").mkdir()
    server = LiveServer(tiny_checkpoint, folder / "jobs", folder / "serve.log")
    try:
        server.wait_ready()
        yield server
    finally:
        server.stop()


@pytest.fixture(scope="module")
def nemsim(live) -> Client:
    return Client(live.base, timeout=60)


def test_ready_and_model(nemsim):
    assert nemsim.ready()
    model = nemsim.model()
    assert model["scene"]["name"] == "tiny"
    assert [c["name"] for c in model["controls"]] == list(CONTROL_NAMES)


def test_partial_rollout_and_its_exports(nemsim, tmp_path):
    from nemsim.data.hdf5 import open_trajectories

    run = nemsim.rollout({"flux_cl": 0.01}, steps=3)
    defaults = {c["name"]: c["default"] for c in nemsim.model()["controls"]}
    assert run["controls"] == pytest.approx({**defaults, "flux_cl": 0.01})
    assert run["defaulted"] == [n for n in CONTROL_NAMES if n != "flux_cl"]
    assert run["steps"] == 3 and len(run["metrics"]["etch_depth"]) == 4
    assert nemsim.rollout({**defaults, "flux_cl": 0.01}, steps=3)["id"] == run["id"]  # the same rollout

    rows = list(csv.reader(line for line in nemsim.metrics_csv(run["id"]).splitlines() if line[0] != "#"))
    depth = rows[0].index("etch_depth [nm]")
    assert [float(r[depth]) for r in rows[1:]] == pytest.approx(run["metrics"]["etch_depth"], abs=1e-5)

    path = nemsim.trajectory(run["id"], tmp_path / "run.h5")
    with open_trajectories(path) as traj:
        assert traj.states.shape[:2] == (1, 4) and traj.controls_raw[0][3] == pytest.approx(0.01)

    vtp = nemsim.mesh(run["id"], step=3, channel="si", format="vtp")
    assert vtp.startswith(b'<?xml version="1.0"?>') and f'rollout_id: "{run["id"]}"'.encode() in vtp
    assert nemsim.mesh(run["id"], format="glb")[:4] == b"glTF"  # default: the final state's Si surface


def test_mechanisms(nemsim):
    answer = nemsim.mechanisms({"flux_cl": 0.01}, factors=[0.5, 2])
    assert answer["controls"]["flux_cl"] == pytest.approx(0.01)
    interventions = answer["result"]["interventions"]
    assert len(interventions) == 8  # (s_Cl+, s_Cl) in {0.5, 1, 2}^2 except (1, 1)


def test_errors_carry_the_servers_message(nemsim, live):
    with pytest.raises(ServiceError) as err:
        nemsim.rollout({"flux_cll": 0.01}, steps=1)
    assert err.value.status == 422 and "did you mean 'flux_cl'?" in err.value.message
    assert err.value.detail[0]["loc"] == ["body", "controls"]
    with pytest.raises(ServiceError) as err:
        nemsim.metrics_csv("deadbeef")
    assert err.value.status == 404 and "unknown rollout id 'deadbeef'" in err.value.message
    with pytest.raises(ServiceError) as err:
        nemsim.job("nosuchjob")
    assert err.value.status == 404 and str(err.value).startswith("HTTP 404: unknown job id")
    with pytest.raises(ServiceError) as err:
        Client(live.base).rollout(steps=10**6)
    assert err.value.status == 422 and "steps" in err.value.message

    nowhere = Client(f"http://127.0.0.1:{free_port()}", timeout=5)
    assert not nowhere.ready()
    with pytest.raises(ServiceUnreachable, match="no answer"):
        nowhere.model()


def test_a_job_past_its_time_is_cancelled(nemsim):
    """The simulator is far slower than the zero-second budget: the client cancels the job on the server."""
    with pytest.raises(JobTimeout) as err:
        nemsim.simulate({"flux_cl": 0.01}, steps=2, timeout_s=0.0)
    job_id = err.value.job["id"]
    assert err.value.job["kind"] == "simulation"
    status = nemsim.job(job_id)["status"]
    assert status in ("running", "cancelled")  # cancelled once the simulator child stopped
    assert nemsim.cancel(job_id)["id"] == job_id


@pytest.mark.slow
def test_design_waits_for_the_result(nemsim):
    result = nemsim.design({"etch_depth": {"value": 5.0, "tol": 5.0}}, step=2, k=1, timeout_s=300)
    assert result["status"] in ("met", "unreachable") and len(result["recipes"]) == 1
    assert result["step"] == 2 and result["model_id"] == nemsim.model()["model_id"]


# --- a scripted server: what a healthy server does not do on demand ---------------------------------------


class _Scripted(http.server.BaseHTTPRequestHandler):
    """Answers each request with the next (status, headers, body) of `script`; records the requests
    (method, path, headers with lower-case names)."""

    script: list[tuple[int, dict[str, str], bytes]] = []
    seen: list[tuple[str, str, dict[str, str]]] = []

    def _answer(self) -> None:
        length = int(self.headers.get("Content-Length") or 0)
        self.rfile.read(length)
        self.seen.append((self.command, self.path, {k.lower(): v for k, v in self.headers.items()}))
        status, headers, body = self.script.pop(0)
        self.send_response(status)
        for k, v in {"Content-Length": str(len(body)), **headers}.items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(body)

    do_GET = do_POST = do_DELETE = _answer

    def log_message(self, *args) -> None:  # quiet
        pass


@pytest.fixture
def scripted() -> Iterator[tuple[str, type[_Scripted]]]:
    handler = type("Handler", (_Scripted,), {"script": [], "seen": []})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", handler
    finally:
        server.shutdown()
        server.server_close()


def _json_body(obj) -> bytes:
    return json.dumps(obj).encode()


def test_busy_answers_are_waited_out(scripted):
    base, handler = scripted
    busy = (
        429,
        {"Retry-After": "0", "Content-Type": "application/json"},
        _json_body({"message": "slow down"}),
    )
    ok = (200, {"Content-Type": "application/json"}, _json_body({"model_id": "m"}))
    handler.script += [busy, busy, ok]
    assert Client(base, api_key="secret", retries=2).model() == {"model_id": "m"}
    assert [s[:2] for s in handler.seen] == [("GET", "/model")] * 3
    assert all(s[2]["x-api-key"] == "secret" for s in handler.seen)

    handler.script += [busy, busy]
    with pytest.raises(ServiceError) as err:  # retries spent: the last answer is raised
        Client(base, retries=1).model()
    assert err.value.status == 429 and err.value.message == "slow down" and err.value.retry_after == 0.0
    assert not handler.script


def test_errors_without_retry_after_or_json(scripted):
    base, handler = scripted
    handler.script += [
        (503, {"Content-Type": "application/json"}, _json_body({"detail": "loading", "message": "not yet"})),
        (502, {"Content-Type": "text/html"}, b"<html>\n  Bad   gateway\n</html>"),
    ]
    with pytest.raises(ServiceError) as err:  # 503 without Retry-After: not retried
        Client(base, retries=3).model()
    assert (err.value.status, err.value.message, err.value.detail) == (503, "not yet", "loading")
    with pytest.raises(ServiceError) as err:
        Client(base).metrics_csv("a/b")
    assert err.value.status == 502 and err.value.message == "<html> Bad gateway </html>"
    assert handler.seen[-1][1] == "/rollouts/a%2Fb/metrics.csv"  # ids are one path segment


def test_requests_are_json_with_the_given_fields(scripted):
    base, handler = scripted
    handler.script += [
        (200, {"Content-Type": "application/json"}, _json_body({"result": {}, "controls": {}}))
    ]
    Client(base).mechanisms({"angle_cl": 4, "flux_cl": 0.01}, factors=[0.5, 2])
    path = handler.seen[-1][1]
    assert path.startswith("/mechanisms?") and "angle_cl=4.0" in path and "factors=0.5&factors=2.0" in path
    assert np.isclose(float(path.split("flux_cl=")[1].split("&")[0]), 0.01)
