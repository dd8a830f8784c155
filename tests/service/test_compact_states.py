"""`service.compact_states.CompactStates`: lossless (bit for bit), compact, every way of reading it agrees."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from service.compact_states import CHUNK, CompactStates


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and np.array_equal(a.view(np.uint16), b.view(np.uint16))


@pytest.mark.parametrize("steps", [0, 1, CHUNK - 1, CHUNK, CHUNK + 1, 2 * CHUNK + 3])
def test_any_float16_trajectory_comes_back_bit_for_bit(steps):
    """Every bit pattern (NaN, Inf, subnormals, -0, jumps across the sign) and unchanged voxels, across
    the encoder's chunk boundaries: `decode`, `state`, `blocks` and `take` all give the states back."""
    rng = np.random.default_rng(steps)
    bits = rng.integers(0, 1 << 16, size=(steps + 1, 2, 3, 4, 5), dtype=np.uint16)
    bits[:, 0, 0] = bits[0, 0, 0]  # some voxels never change
    bits[1::2, 1, 1] = bits[::2, 1, 1][: bits[1::2].shape[0]] + 1  # small steps too
    states = bits.view(np.float16)
    compact = CompactStates.encode(states)
    assert _same_bits(compact.decode(), states)
    assert all(_same_bits(compact.state(k), states[k]) for k in range(steps + 1))
    assert _same_bits(np.concatenate(list(compact.blocks(3))), states)
    assert _same_bits(compact.take(range(steps + 1)), states)
    assert _same_bits(compact.take([steps]), states[[steps]])
    assert _same_bits(compact.take([0, steps, 0]), states[[0, steps, 0]])
    with pytest.raises(IndexError):
        compact.state(steps + 1)


def test_a_float32_tensor_is_stored_as_its_float16_rounding():
    x = torch.randn(2 * CHUNK + 2, 2, 3, 4, 5)
    assert _same_bits(CompactStates.encode(x).decode(), x.half().numpy())
    with pytest.raises(ValueError, match="float16"):
        CompactStates.encode(x.numpy())  # a float32 array: say so rather than store other values


def test_a_rollout_takes_a_fraction_of_its_float16_size(served, default_controls):
    """What the cache weighs (`nbytes`) for a real trajectory: well under its float16 size."""
    from service.served_model import ServedModel

    s = ServedModel(served.predictor, cache_size=0)
    result, _ = s.rollout(np.array([list(default_controls.values())] * 20))
    float16_bytes = 2 * int(np.prod(result.states.shape))
    assert result.states.nbytes < float16_bytes / 2, (result.states.nbytes, float16_bytes)


def test_a_symmetric_trajectory_keeps_its_quadrant_only():
    """States with the square's symmetry (a quarter-domain model's) are stored as their quadrant: every
    decoded state, block and pick equals the original, and the entry is a fraction of the full one."""
    from nemsim.symmetry import symmetrize

    g = torch.Generator().manual_seed(3)
    states = symmetrize((torch.rand(9, 2, 6, 10, 10, generator=g) * 2 - 1).clamp(-0.9, 0.9))
    states[3:] = states[3]  # some transitions without change
    full = CompactStates.encode(states)
    quarter = CompactStates.encode(states, full_size=10)
    want = states.half().numpy()
    assert quarter.shape == full.shape == tuple(states.shape)
    assert np.array_equal(quarter.decode(), want) and np.array_equal(quarter.state(7), want[7])
    assert np.array_equal(np.concatenate(list(quarter.blocks(3))), want)
    assert np.array_equal(quarter.take([2, 5]), want[[2, 5]])
    assert quarter.nbytes < 0.4 * full.nbytes
    with pytest.raises(ValueError, match="full_size"):
        CompactStates.encode(states, full_size=12)
