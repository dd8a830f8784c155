"""``nemsim.model.transport``: the line-of-sight direct flux equals a straightforward ray march, is 1 in an
empty box and 0 under a solid slab, responds to the angular controls and to depth the way transport does,
is exact on a top slab (what a depth-windowed call sees), and enters NEMSim as a zero-initialized input
(a warm start predicts exactly what the model without it predicts)."""

from __future__ import annotations

import math

import torch

from nemsim.controls import ANGLE_CONTROLS, control_index
from nemsim.model.transport import (
    TransportConfig,
    directions,
    material_cells,
    species_weights,
    transport_field,
)

torch.set_num_threads(1)
CFG = TransportConfig(polar_deg=(0.0, 5.0, 30.0, 60.0), azimuths=4)


def _march(o: torch.Tensor, w: torch.Tensor, cfg: TransportConfig) -> torch.Tensor:
    """Φ (4, d, h, w) by marching every ray level by level (o: (d, h, w) cells, bottom level first; the
    lateral position i levels below the top is rounded from the top, as the module documents)."""
    _, step, _ = directions(cfg)
    d, h, wd = o.shape
    out = torch.zeros(4, d, h, wd, dtype=torch.float64)

    def at(i: int, s: float) -> int:  # lateral offset of a ray i levels below the top
        return -round(i * s)

    for k, (dy, dx) in enumerate(step.tolist()):
        for z in range(d):
            i = d - 1 - z
            for y in range(h):
                for x in range(wd):
                    s = sum(float(o[z2, (y - at(i, dy) + at(d - 1 - z2, dy)) % h,
                                    (x - at(i, dx) + at(d - 1 - z2, dx)) % wd]) for z2 in range(z + 1, d))
                    out[:, z, y, x] += w[:, k].double() * max(0.0, 1.0 - cfg.kappa * s)
    return out


def test_matches_ray_march():
    g = torch.Generator().manual_seed(0)
    x = (0.3 * torch.randn(2, 2, 16, 6, 8, generator=g)).clamp(-1, 1)  # (B, 2, D, H, W)
    w = species_weights(torch.rand(2, 14, generator=g) * 2 - 1, CFG)  # (2, 4, K)
    phi = transport_field(x, w, CFG)  # (2, 4, 8, 3, 4)
    for b in range(2):
        ref = _march(material_cells(x, CFG)[b], w[b], CFG)
        assert torch.allclose(phi[b].double(), ref, atol=1e-5)


def test_weights_are_normalized_and_follow_the_exponent():
    u = torch.zeros(3, 14)
    u[0, [control_index(n) for n in ANGLE_CONTROLS]] = -1.0  # design minimum: m = 0 (Cl), 50 (ions)
    u[2, [control_index(n) for n in ANGLE_CONTROLS]] = 1.0  # maximum: m = 20, 3000
    w = species_weights(u, CFG)  # (3, 4, K)
    assert torch.allclose(w.sum(-1), torch.ones(3, 4))
    assert (w[:, :, 0].diff(dim=0) > 0).all()  # more collimated: more weight straight down
    theta, _, omega = directions(CFG)
    iso = omega / omega.sum()  # m = 0: weight by solid angle alone
    assert torch.allclose(w[0, 0].double(), iso, atol=1e-6)
    assert math.isclose(float(omega.sum()), 2 * math.pi, rel_tol=1e-12)  # the bins tile the hemisphere


def test_empty_box_and_solid_slab():
    w = species_weights(torch.zeros(1, 14), CFG)
    empty = torch.ones(1, 2, 16, 8, 8)
    assert torch.allclose(transport_field(empty, w, CFG), torch.ones(1, 4, 8, 4, 4), atol=1e-6)
    slab = empty.clone()
    slab[:, 1, 10:12] = -1.0  # one solid cell layer (2 voxels) at cell level 5
    phi = transport_field(slab, w, CFG)
    assert torch.allclose(phi[:, :, :5], torch.zeros(1, 4, 5, 4, 4))  # shadowed
    assert torch.allclose(phi[:, :, 6:], torch.ones(1, 4, 2, 4, 4), atol=1e-6)  # above it: open sky


def _hole(depth_cells: int = 10, size: int = 16, radius: float = 2.5) -> torch.Tensor:
    """(1, 2, D, H, W) state: solid below the top 4 voxels with a cylindrical hole of the given depth."""
    D = 2 * (depth_cells + 6)
    x = torch.ones(1, 2, D, size, size)
    yy, xx = torch.meshgrid(torch.arange(size) + 0.5 - size / 2, torch.arange(size) + 0.5 - size / 2,
                            indexing="ij")
    inside = (yy ** 2 + xx ** 2).sqrt() < radius * 2
    x[:, 1, : D - 4] = torch.where(inside, 1.0, -1.0)  # Si with a hole through the top D - 4 - 8 voxels
    x[:, 1, :8] = -1.0  # the hole's bottom
    return x


def test_transport_physics_in_a_hole():
    x = _hole()
    cfg = TransportConfig()
    lo, hi = torch.full((1, 14), 0.0), torch.full((1, 14), 0.0)
    for n in ANGLE_CONTROLS:
        lo[0, control_index(n)], hi[0, control_index(n)] = -1.0, 1.0
    broad = transport_field(x, species_weights(lo, cfg), cfg)[0]  # (4, d, h, w)
    narrow = transport_field(x, species_weights(hi, cfg), cfg)[0]
    c = x.shape[-1] // 4  # the hole's axis on the cell grid
    bottom = 4  # the first open cell level above the hole's bottom
    # neutrals (channel 0) reach the bottom less than collimated ions (channel 1) do
    assert broad[0, bottom, c, c] < broad[1, bottom, c, c]
    # a more collimated distribution reaches the bottom better, for neutrals and ions alike
    assert narrow[0, bottom, c, c] > broad[0, bottom, c, c]
    assert narrow[1, bottom, c, c] >= broad[1, bottom, c, c]
    # down the hole the neutral flux falls
    column = broad[0, bottom:-3, c, c]
    assert (column.diff() >= -1e-6).all() and column[-1] > column[0]


def test_exact_on_a_top_slab():
    """Only material above a cell shadows it: the field of the top slab is the full field's top part."""
    x = _hole()
    w = species_weights(torch.rand(1, 14) * 2 - 1, CFG)
    full = transport_field(x, w, CFG)
    a = 8  # voxels below the slab (a multiple of 2)
    assert torch.allclose(transport_field(x[:, :, a:], w, CFG), full[:, :, a // 2:], atol=1e-6)


def test_warm_start_is_exact_and_input_trains(tiny_scene):
    from bench.stress import initial_state
    from nemsim.registry import build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    rules = compile_rules(load_rules())
    torch.manual_seed(0)
    base = build_model("nemsim", tiny_scene, rules, {"steps_per_call": 2}).eval()
    model = build_model("nemsim", tiny_scene, rules, {"steps_per_call": 2, "transport_input": True}).eval()
    missing, unexpected = model.load_state_dict(base.state_dict(), strict=False)
    assert sorted(missing) == ["transport_in.bias", "transport_in.weight"] and not unexpected
    x = torch.as_tensor(initial_state(tiny_scene))[None].repeat(2, 1, 1, 1, 1)
    u = torch.rand(2, 14) * 2 - 1
    with torch.no_grad():
        assert torch.equal(model(x, u, all_steps=True), base(x, u, all_steps=True))
    model.train()
    model(x, u, all_steps=True).square().mean().backward()
    assert model.transport_in.weight.grad.abs().sum() > 0  # the input reaches the loss


def test_config_from_a_stored_dict(tiny_scene):
    """A checkpoint's config (lists where the dataclass has tuples) builds a model whose rays are cached."""
    from bench.stress import initial_state
    from nemsim.registry import build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    model = build_model("nemsim", tiny_scene, compile_rules(load_rules()),
                        {"transport_input": True, "transport": {"polar_deg": [0, 10, 40], "azimuths": 3}})
    assert model.config.transport == TransportConfig(polar_deg=(0.0, 10.0, 40.0), azimuths=3)
    x = torch.as_tensor(initial_state(tiny_scene))[None]
    with torch.no_grad():
        assert model(x, torch.zeros(1, 14)).shape == x.shape
