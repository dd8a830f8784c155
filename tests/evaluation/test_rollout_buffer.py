"""The rollout's in-place trajectory buffer returns exactly what the plain protocol does: every predicted
state kept as its own tensor, projected out of place (``MonotoneProjection.__call__``) and stacked at the
end, on `tiny`, for the model itself and every runtime backend (chunks of k = 3 split by a recipe change,
monotone projection on)."""

from __future__ import annotations

import pytest
import torch

from bench.stress import initial_state
from nemsim.evaluation.rollout import rollout
from nemsim.inference.runtime import compile_model, openvino_available
from nemsim.model import NEMSim, NEMSimConfig
from nemsim.model.monotone import MonotoneProjection, axis_eps_of
from nemsim.scenes import TINY

T = 8  # with k = 3 and the change at 5: calls at t = 0 (3 states), 3 (2), 5 (3)
CHUNKS = [(0, 3), (3, 2), (5, 3)]


@pytest.fixture(scope="module")
def setup(rules):
    """(model, x0 (2, 2, D, H, W), u (2, T, 14)): perturbed weights, so states move up and down and the
    projection is active; flux gate on as in the served model."""
    torch.manual_seed(0)
    model = NEMSim(rules, NEMSimConfig(steps_per_call=3, flux_gate=True)).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    x0 = torch.as_tensor(initial_state(TINY))[None].repeat(2, 1, 1, 1, 1).float()
    g = torch.Generator().manual_seed(3)
    u = torch.rand(2, 1, 14, generator=g).repeat(1, T, 1) * 2 - 1
    u[:, 5:] = torch.rand(2, 1, 14, generator=g) * 2 - 1
    return model, x0, u


def _plain(model, x0: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """The protocol without buffers: (B, T+1, 2, D, H, W). The controls' cache is computed where they change
    (t = 0, 5), as the rollout does (``precompute`` of equal controls at another address can differ in the
    last bit)."""
    project = MonotoneProjection(x0, model.config.monotone_eps, axis_eps_of(model))
    states, x, cache = [x0], x0, None
    with torch.no_grad():
        for t, n in CHUNKS:
            if t in (0, 5):
                cache = model.precompute(u[:, t])
            for y in model.predict(x, cache)[:, :n].unbind(1):
                x = project(y.clone())
                states.append(x)
    return torch.stack(states, dim=1)


def _backends() -> list[tuple[str, str]]:
    return [("torch", "f32")] + ([("openvino", "f32"), ("openvino", "bf16")] if openvino_available() else [])


@pytest.mark.parametrize(("backend", "precision"), [("model", "-"), *_backends()])
def test_buffer_path_equals_the_plain_protocol(setup, backend, precision):
    model, x0, u = setup
    pred = model if backend == "model" else compile_model(model, backend, precision)  # type: ignore[arg-type]
    if backend != "model":
        assert pred.backend == backend
    ref = _plain(pred, x0, u)
    assert (ref[:, 1:] != ref[:, :-1]).any() and ref.shape == (2, T + 1, *TINY.state_shape)
    unprojected = rollout(pred, x0, u, monotone=False)
    assert not torch.equal(unprojected, ref)  # the projection is active on these states
    seen: dict[int, torch.Tensor] = {}
    traj = rollout(pred, x0, u, on_step=lambda t, x: seen.__setitem__(t, x.clone()))
    assert torch.equal(traj, ref)
    assert sorted(seen) == list(range(1, T + 1)) and all(torch.equal(seen[t], ref[:, t]) for t in seen)
    # a caller's buffer (longer than needed, as the service's reused one): filled in place and returned
    buf = torch.full((2, T + 4, *TINY.state_shape), float("nan"))
    with torch.inference_mode():  # as the service calls it
        out = rollout(pred, x0, u, out=buf)
    assert out.data_ptr() == buf.data_ptr() and torch.equal(out, ref) and buf[:, T + 1 :].isnan().all()
    # keep=False: the last state; each state handed to on_step stays valid until the next one is handed
    prev: list[torch.Tensor] = []
    first_seen: list[torch.Tensor] = []

    def check(t: int, x: torch.Tensor) -> None:
        if prev:
            assert torch.equal(prev[0], ref[:, t - 1])
        prev[:] = [x]
        first_seen.append(x.clone())

    last = rollout(pred, x0, u, keep=False, on_step=check)
    assert torch.equal(last, ref[:, -1]) and torch.equal(torch.stack(first_seen, 1), ref[:, 1:])


def test_bad_out_buffers_are_refused(setup):
    model, x0, u = setup
    with pytest.raises(ValueError, match="out must be"):
        rollout(model, x0, u, out=torch.empty(2, T, *TINY.state_shape))  # one state short
    with pytest.raises(ValueError, match="out must be"):
        rollout(model, x0, u, out=torch.empty(2, T + 1, *TINY.state_shape, dtype=torch.float64))
    with pytest.raises(ValueError, match="keep=True"):
        rollout(model, x0, u, keep=False, out=torch.empty(2, T + 1, *TINY.state_shape))
