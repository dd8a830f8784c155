"""`CompactStates`: a float16 trajectory kept losslessly in a fraction of its size, for the rollout cache.

Why: a 100-step `small` trajectory is 20.6 MB as float16, so the cache's memory budget held a third of
the rollouts its entry count promised and response ids died early. Consecutive states differ in few
voxels (the normalized SDF is clipped to +-1 away from the surfaces, and the surfaces move little per
step), and most of those differences are small, so the trajectory is stored as what changes:

* the first and the last state, as they are;
* per transition, one bit per voxel: did its value change (zlib-compressed: the changes lie along the
  surfaces, so the bits come in long runs);
* the changes in order, as differences of the float16 bit patterns (uint16, wrapping): int8 where they
  fit, else the int8 `ESCAPE` plus the int16 difference in a second array.

Decoding adds the differences back in the same wrapping arithmetic, so every state is bit-identical to
the float16 it was made from (what the API returned before). The states of a quarter-domain model are exactly
symmetric under the square's mirrors (``nemsim.symmetry``): of them only the quadrant is stored and every
decoded state is unfolded, the same states for a quarter of the work and memory; a trench's (a cross-section
model's) likewise as its cross-section. One state is decoded from
the nearer of the two stored ends (at most half the transitions); the whole trajectory, or blocks of
consecutive states (`blocks`) for a response streamed without holding it all. Encoding works through
`CHUNK` transitions at a time, so its temporaries stay a fraction of the trajectory's size. Both directions
are single passes compiled by numba (numpy's boolean indexing took most of an uncached rollout's extra
time).
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numba
import numpy as np
import torch

ESCAPE = np.int8(-128)  # in `small`: the difference is the next entry of `wide`
CHUNK = 16  # transitions encoded at a time


@numba.njit(cache=True, nogil=True)
def _encode_chunk(
    v: np.ndarray, words: np.ndarray, bits: np.ndarray, small: np.ndarray, wide: np.ndarray,
    counts: np.ndarray, wide_counts: np.ndarray,
) -> tuple[int, int]:
    """Transitions of v (n+1, N) uint16 (bit patterns of n+1 states): transition j sets bit i % 8 of
    bits[j, i // 8] (zeroed) where voxel i changes, and appends its differences to small (ESCAPE and wide
    beyond int8); counts[j], wide_counts[j]: how many. words: v viewed as (n+1, N / 4) uint64 (N a multiple
    of 8; else (n+1, 0)), to skip 8 unchanged voxels at once. Returns (entries in small, in wide)."""
    n_voxels = v.shape[1]
    ps = 0
    pw = 0
    for j in range(v.shape[0] - 1):
        start, start_wide = ps, pw
        now, after, now_w, after_w, row = v[j], v[j + 1], words[j], words[j + 1], bits[j]
        for b in range(row.shape[0]):
            q = 2 * b
            if q + 1 < now_w.shape[0] and now_w[q] == after_w[q] and now_w[q + 1] == after_w[q + 1]:
                continue  # 8 unchanged voxels
            byte = 0
            for k in range(min(8, n_voxels - 8 * b)):
                i = 8 * b + k
                # branch-free: the entries are written unconditionally and kept by advancing ps / pw
                d = (np.int64(after[i]) - np.int64(now[i])) & 0xFFFF
                d -= (d >> 15) << 16  # as int16
                changed = int(d != 0)
                escape = int((d < -127) | (d > 127))
                byte |= changed << k
                small[ps] = np.int8(-128 if escape else d)  # ESCAPE
                wide[pw] = np.int16(d)
                ps += changed
                pw += escape
            row[b] = byte
        counts[j] = ps - start
        wide_counts[j] = pw - start_wide
    return ps, pw


@numba.njit(cache=True, nogil=True)
def _apply(
    acc: np.ndarray, bits: np.ndarray, small: np.ndarray, wide: np.ndarray, offsets: np.ndarray,
    wide_offsets: np.ndarray, t0: int, t1: int, sign: int, out: np.ndarray,
) -> None:
    """acc (N,) uint16 += sign · the differences of transitions t0..t1-1 (wrapping); out (t1 - t0, N) or
    (0, N): with rows, out[j] = acc after transition t0 + j."""
    for t in range(t0, t1):
        ps = offsets[t]
        pw = wide_offsets[t]
        row = bits[t]
        for b in range(row.shape[0]):
            byte = row[b]
            if byte == 0:
                continue
            for k in range(8):
                if byte & (1 << k):
                    i = b * 8 + k
                    d = np.int64(small[ps])
                    ps += 1
                    if d == -128:  # ESCAPE
                        d = np.int64(wide[pw])
                        pw += 1
                    acc[i] = (np.int64(acc[i]) + sign * d) & 0xFFFF
        if out.shape[0] > 0:
            out[t - t0, :] = acc


@dataclass(frozen=True, eq=False)
class CompactStates:
    """A trajectory (T+1, 2, D, H, W) of float16 states (module docstring). Build with `encode`."""

    shape: tuple[int, ...]  # (T+1, 2, D, H, W) of the trajectory (what every method returns)
    first: np.ndarray  # (N,) uint16: bit patterns of state 0, N = 2·D·H·W
    last: np.ndarray  # (N,) uint16: bit patterns of state T
    changed: bytes  # zlib of (T, ceil(N / 8)) uint8: bit i % 8 of byte i // 8 of row t: voxel i changes at t
    small: np.ndarray  # (M,) int8: the M differences in (t, i) order, ESCAPE where wide holds it
    wide: np.ndarray  # (E,) int16: the differences outside [-127, 127], in order
    offsets: np.ndarray  # (T+1,) int64: transition t's differences are small[offsets[t]:offsets[t+1]]
    wide_offsets: np.ndarray  # (T+1,) int64: and its wide ones wide[wide_offsets[t]:wide_offsets[t+1]]
    # the states are exactly symmetric under the square's mirrors (or a trench's) and only their folded part
    # is stored (``nemsim.symmetry.FieldFold``): the lateral size they are unfolded to; None: the whole
    # states are stored
    full_size: int | None = None
    fold_kind: str = "quarter"  # what is stored with full_size: "quarter" (a quadrant) or "section"

    @classmethod
    def encode(cls, states: np.ndarray | torch.Tensor, full_size: int | None = None,
               fold_kind: str = "quarter") -> CompactStates:
        """From states (T+1, 2, D, H, W): a float16 array, or a float32 tensor rounded to float16 here chunk
        by chunk (torch's conversion is vectorized; no float16 copy of the whole trajectory is made).
        ``full_size``: the states are exactly symmetric under the square's mirrors (a quarter-domain
        model's): only their quadrant is stored, a quarter of the work and of the memory; the states may
        then be given as that quadrant (T+1, 2, D, c, c) already. ``fold_kind`` "section": a trench's
        states, constant along y and mirrored in x, stored as their cross-section (T+1, 2, D, 4, c)."""
        from nemsim.symmetry import FieldFold

        shape = tuple(int(d) for d in states.shape)
        f = FieldFold(fold_kind, full_size) if full_size is not None else None  # type: ignore[arg-type]
        if f is not None and shape[-1] != full_size:  # given as their folded part already?
            if tuple(shape[-2:]) != f.plane:
                raise ValueError(f"full_size {full_size} does not match states of shape {list(shape)}")
            shape = (*shape[:-2], f.n, f.n)  # the trajectory's shape (what decoding returns)
        elif f is not None:
            folded = f.fold(torch.as_tensor(states))
            states = folded.contiguous() if isinstance(states, torch.Tensor) else folded.numpy().copy()
        if isinstance(states, torch.Tensor):
            if states.dtype != torch.float32 or states.dim() < 2:
                raise ValueError(f"need a float32 tensor (T+1, ...), got {states.dtype} {list(states.shape)}")
            src = states.detach()

            def bits(t0: int, t1: int) -> np.ndarray:  # (t1 - t0, N) uint16 patterns of the float16 states
                return src[t0:t1].half().numpy().view(np.uint16).reshape(t1 - t0, -1)
        else:
            if states.dtype != np.float16 or states.ndim < 2:
                raise ValueError(f"need float16 states (T+1, ...), got {states.dtype} {states.shape}")
            v = np.ascontiguousarray(states).view(np.uint16).reshape(states.shape[0], -1)  # (T+1, N)

            def bits(t0: int, t1: int) -> np.ndarray:
                return v[t0:t1]

        steps = int(states.shape[0]) - 1
        n = int(np.prod(states.shape[1:]))
        packer = zlib.compressobj(1, zlib.DEFLATED, 15, 9, zlib.Z_RLE)  # the bits come in runs
        packed, smalls, wides = [], [], []
        counts = np.zeros((2, steps + 1), dtype=np.int64)  # per transition: entries in small, in wide
        for t0 in range(0, steps, CHUNK):
            t1 = min(t0 + CHUNK, steps)
            mask = np.zeros((t1 - t0, (n + 7) // 8), dtype=np.uint8)
            small = np.empty((t1 - t0) * n, dtype=np.int8)
            wide = np.empty((t1 - t0) * n, dtype=np.int16)
            chunk = np.ascontiguousarray(bits(t0, t1 + 1))  # states t0..t1
            words = chunk.view(np.uint64) if n % 8 == 0 else np.zeros((chunk.shape[0], 0), dtype=np.uint64)
            n_small, n_wide = _encode_chunk(chunk, words, mask, small, wide, *counts[:, t0 + 1 :])
            packed.append(packer.compress(mask.tobytes()))
            smalls.append(small[:n_small].copy())
            wides.append(wide[:n_wide].copy())
        packed.append(packer.flush())
        return cls(
            shape=shape,
            first=bits(0, 1)[0].copy(),
            last=bits(steps, steps + 1)[0].copy(),
            changed=b"".join(packed),
            small=np.concatenate(smalls) if smalls else np.zeros(0, dtype=np.int8),
            wide=np.concatenate(wides) if wides else np.zeros(0, dtype=np.int16),
            offsets=np.cumsum(counts[0]),
            wide_offsets=np.cumsum(counts[1]),
            full_size=full_size,
            fold_kind=fold_kind,
        )

    @property
    def _stored(self) -> tuple[int, ...]:
        """The shape of one stored state: (2, D, H, W), or its folded part's."""
        if self.full_size is None:
            return self.shape[1:]
        return (*self.shape[1:-2], *self._fold().plane)

    def _fold(self):  # the FieldFold of the stored states (full_size set)
        from nemsim.symmetry import FieldFold

        return FieldFold(self.fold_kind, int(self.full_size or 0))  # type: ignore[arg-type]

    def _out(self, stored: np.ndarray) -> np.ndarray:
        """Stored states (..., h, w) float16 as the trajectory's (unfolded when a folded part is kept)."""
        if self.full_size is None:
            return stored
        return self._fold().unfold(torch.from_numpy(stored)).numpy()

    @property
    def steps(self) -> int:
        """T: transitions (the trajectory has T+1 states)."""
        return self.shape[0] - 1

    @property
    def nbytes(self) -> int:
        arrays = (self.first, self.last, self.small, self.wide, self.offsets, self.wide_offsets)
        return len(self.changed) + sum(int(a.nbytes) for a in arrays)

    def _bits(self) -> np.ndarray:
        """The change bits (T, ceil(N / 8)) uint8."""
        n = self.first.size
        return np.frombuffer(zlib.decompress(self.changed), dtype=np.uint8).reshape(self.steps, (n + 7) // 8)

    def _run(
        self, acc: np.ndarray, t0: int, t1: int, sign: int, out: np.ndarray | None = None,
        bits: np.ndarray | None = None,
    ) -> None:
        """`_apply` over transitions t0..t1-1."""
        rows = np.empty((0, acc.size), dtype=np.uint16) if out is None else out
        bits = self._bits() if bits is None else bits
        _apply(acc, bits, self.small, self.wide, self.offsets, self.wide_offsets, t0, t1, sign, rows)

    def state(self, k: int) -> np.ndarray:
        """State k (2, D, H, W) float16, from the nearer stored end."""
        if not 0 <= k <= self.steps:
            raise IndexError(f"state {k} of a trajectory with states 0..{self.steps}")
        forward = k <= self.steps - k
        acc = (self.first if forward else self.last).copy()
        if forward:
            self._run(acc, 0, k, 1)
        else:
            self._run(acc, k, self.steps, -1)
        return self._out(acc.view(np.float16).reshape(self._stored))

    def decode(self) -> np.ndarray:
        """All states (T+1, 2, D, H, W) float16."""
        out = np.empty((self.shape[0], self.first.size), dtype=np.uint16)  # (T+1, N)
        out[0] = self.first
        if self.steps:
            self._run(self.first.copy(), 0, self.steps, 1, out[1:])
        return self._out(out.view(np.float16).reshape(self.shape[0], *self._stored))

    def blocks(self, size: int = 4) -> Iterator[np.ndarray]:
        """All states in order, at most `size` at a time ((n, 2, D, H, W) float16 each): `decode` in
        pieces."""
        acc = self.first.copy()
        yield self._out(acc.copy().view(np.float16).reshape(1, *self._stored))
        bits = self._bits() if self.steps else None
        for t0 in range(0, self.steps, size):
            t1 = min(t0 + size, self.steps)
            block = np.empty((t1 - t0, acc.size), dtype=np.uint16)
            self._run(acc, t0, t1, 1, block, bits)
            yield self._out(block.view(np.float16).reshape(t1 - t0, *self._stored))

    def take(self, steps: Sequence[int]) -> np.ndarray:
        """States at `steps` (n, 2, D, H, W) float16, C-contiguous: decoded one by one, or all at once
        when that is less work."""
        steps = [int(k) for k in steps]
        if steps == list(range(self.shape[0])):
            return self.decode()
        if len(steps) > 2:
            return self.decode()[steps]
        if not steps:
            return np.empty((0, *self.shape[1:]), dtype=np.float16)
        return np.stack([self.state(k) for k in steps])
