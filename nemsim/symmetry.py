"""Scene symmetry: the group a scene's mean evolution is invariant under, its fundamental domain, and the maps
between full fields and that domain ("model only what a scene needs").

Every shipped scene is a circular opening centred on a square grid with periodic lateral boundaries, so the
mean etch evolution is invariant under the 8 symmetries of the square about the hole axis (the dihedral group
D4: the mirrors x -> -x and y -> -y about the axis, the diagonal mirror x <-> y, and their products). On a
state (..., D, H, W) (padded and transposed, ``nemsim.scenes``) the axis sits at index (n - 1) / 2 of each
lateral axis, so the two axis mirrors are flips of the whole H or W axis and the diagonal mirror is the
transpose of H and W.

  * ``symmetrize(x)``: the mean of the 8 images of x (a Monte Carlo state's noise averaged over the group;
    the mean evolution is unchanged).
  * ``fold(x)``: the lower quadrant x[..., :c, :c], c = ceil(n / 2), a fundamental domain of the two axis
    mirrors; the hole axis lies on its high H and W faces (between indices c - 1 and c for an even n,
    through index c - 1 for an odd n).
  * ``unfold(q, n)``: the full field rebuilt by reflection, exactly symmetric under both axis mirrors;
    ``unfold(fold(x)) == x`` for every x symmetric under them.
  * ``mirror_pad(q, p)``: q extended by p voxels across the axis faces with the voxels the full field has
    there (the network's halo on a quarter domain).

Choice: the quadrant, not the eighth. The eighth (a triangle) is not a box a 3-D convolution can run on;
the diagonal mirror is kept by averaging the quadrant with its transpose (``symmetrize`` on a quadrant).
A scene with ``symmetry = "none"`` (an off-centre or asymmetric layout) keeps the full domain everywhere.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from nemsim.scenes import quadrant_size

N_D4 = 8  # order of the square's symmetry group


def _square(x: torch.Tensor) -> tuple[int, int]:
    h, w = int(x.shape[-2]), int(x.shape[-1])
    if h != w:
        raise ValueError(f"the square's symmetry needs H == W, got a field of H={h}, W={w}")
    return h, w


def symmetrize(x: torch.Tensor, group: str = "d4") -> torch.Tensor:
    """The mean of x (..., H, W) over the 8 symmetries of the square about the field's centre (``d4``) or over
    the diagonal mirror only (``diagonal``: a quadrant from ``fold``, whose axis mirrors are already
    folded away). Returns a new tensor of x's shape and dtype (computed in float32 for float16 input)."""
    _square(x)
    xf = x.float() if x.dtype in (torch.float16, torch.bfloat16) else x
    if group == "diagonal":
        out = 0.5 * (xf + xf.transpose(-1, -2))
    elif group == "d4":
        s = xf + xf.flip(-1)
        s = s + s.flip(-2)  # the 4 axis-mirror images
        out = (s + s.transpose(-1, -2)) / N_D4
    else:
        raise ValueError(f"group is 'd4' or 'diagonal', got {group!r}")
    return out.to(x.dtype)


def symmetrize_diagonal_(x: torch.Tensor) -> torch.Tensor:
    """``x.copy_(symmetrize(x, "diagonal"))`` in place, without a temporary: each off-diagonal pair (i, j),
    (j, i) of every (..., c, c) plane is replaced by its mean (the same float32 operation, 0.5 * (a + b)).
    Used on every call of a quarter-domain rollout. Returns x."""
    _square(x)
    if (x.device.type == "cpu" and x.dtype == torch.float32 and not x.requires_grad
            and x[(0,) * (x.dim() - 2)].is_contiguous() and x.numel()):
        planes = x.detach().reshape(-1, *x.shape[-2:]) if x.is_contiguous() else None
        if planes is not None:
            _symmetrize_planes(planes.numpy())
            return x
        if x.dim() > 2:  # e.g. a chunk of a batched trajectory buffer: contiguous per leading index
            for sub in x.unbind(0):
                symmetrize_diagonal_(sub)
            return x
    return x.copy_(symmetrize(x, "diagonal"))


def fold(x: torch.Tensor) -> torch.Tensor:
    """The lower quadrant (..., c, c) of a square field (..., n, n) (a view)."""
    _, n = _square(x)
    c = quadrant_size(n)
    return x[..., :c, :c]


def unfold(q: torch.Tensor, n: int, out: torch.Tensor | None = None) -> torch.Tensor:
    """The full field (..., n, n) rebuilt by reflection from its lower quadrant q (..., c, c), written into
    ``out`` (q's leading shape, (..., n, n)) when given."""
    c = quadrant_size(n)
    if tuple(q.shape[-2:]) != (c, c):
        raise ValueError(f"a quadrant of a field of size {n} is {c} x {c}, got {tuple(q.shape[-2:])}")
    skip = n % 2  # an odd axis shares its centre voxel between the two halves
    if out is None and q.device.type == "cpu" and q.dtype == torch.float32 and not q.requires_grad:
        out = q.new_empty((*q.shape[:-2], n, n))
    if out is None:
        q = torch.cat([q, q.flip(-1)[..., skip:]], dim=-1)
        return torch.cat([q, q.flip(-2)[..., skip:, :]], dim=-2)
    if tuple(out.shape) != (*q.shape[:-2], n, n):
        raise ValueError(f"out must be {(*q.shape[:-2], n, n)}, got {tuple(out.shape)}")
    if (q.device.type == out.device.type == "cpu" and q.dtype == out.dtype == torch.float32
            and out.is_contiguous() and not q.requires_grad):  # one pass over out (the rollout's unfold)
        _unfold_planes(q.contiguous().reshape(-1, c, c).numpy(), out.view(-1, n, n).numpy())
        return out
    out[..., :c, :c] = q
    out[..., :c, c:] = q.flip(-1)[..., skip:]
    out[..., c:, :] = out[..., : c - skip, :].flip(-2)
    return out


def mirror_pad(q: torch.Tensor, pad: int, n: int) -> torch.Tensor:
    """q (..., c, c) extended by ``pad`` voxels on its high H and W faces (across the hole axis) with the full
    field's voxels there: ``unfold(q, n)[..., :c + pad, :c + pad]`` without building the full field."""
    if pad <= 0:
        return q
    c = quadrant_size(n)
    skip = n % 2
    if pad > c - skip:
        raise ValueError(f"a mirror halo of {pad} voxels needs a quadrant of more than {pad + skip}, got {c}")
    q = torch.cat([q, q[..., c - skip - pad: c - skip].flip(-1)], dim=-1)
    return torch.cat([q, q[..., c - skip - pad: c - skip, :].flip(-2)], dim=-2)


def quarter_model_size(model: object) -> int | None:
    """The full lateral size n of the fields a quarter-domain model (``config.domain == "quarter"``, a NEMSim
    or a runtime exposing its config) rebuilds; None for a full-domain model."""
    cfg = getattr(model, "config", None)
    n = int(getattr(cfg, "full_size", 0) or 0)
    return n if getattr(cfg, "domain", "full") == "quarter" and n else None


@numba.njit(cache=True, nogil=True)
def _unfold_planes(q: np.ndarray, out: np.ndarray) -> None:
    """out[p, i, j] = q[p, m(i), m(j)], m(i) = i below c else n - 1 - i: ``unfold`` of (P, c, c) planes into
    (P, n, n) in one pass."""
    c, n = q.shape[1], out.shape[1]
    for p in range(q.shape[0]):
        for i in range(n):
            a = i if i < c else n - 1 - i
            for j in range(c):
                out[p, i, j] = q[p, a, j]
            for j in range(c, n):
                out[p, i, j] = q[p, a, n - 1 - j]


@numba.njit(cache=True, nogil=True)
def _symmetrize_planes(a: np.ndarray) -> None:
    """a[p, i, j] = a[p, j, i] = 0.5 * (a[p, i, j] + a[p, j, i]) for every plane p, in place."""
    for p in range(a.shape[0]):
        symmetrize_plane_(a[p])


@numba.njit(inline="always")
def symmetrize_plane_(a: np.ndarray) -> None:
    """One (c, c) plane replaced by its mean with its transpose, in place (shared with the fused writer
    ``nemsim.model.unpack``)."""
    c = a.shape[0]
    half = np.float32(0.5)
    for i in range(c):
        for j in range(i + 1, c):
            v = half * (a[i, j] + a[j, i])
            a[i, j] = v
            a[j, i] = v
