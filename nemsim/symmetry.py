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

A trench (symmetry "mirror_x_translate_y": the mirror x -> -x about its axis, every translation along y)
has a cross-section as its fundamental domain: ``FieldFold("section", n)`` keeps ``SECTION_ROWS`` equal rows
of y and the low half of x (the axis on the high W face), ``unfold`` mirrors x and repeats the row along y.

Choice: the quadrant, not the eighth. The eighth (a triangle) is not a box a 3-D convolution can run on;
the diagonal mirror is kept by averaging the quadrant with its transpose (``symmetrize`` on a quadrant).
Choice: a cross-section keeps 2 equal rows of y, not one, so the same 3-D network runs on it with its
parameters unchanged: y is periodic and every feature constant along it, so each 3x3x3 kernel acts as its
sum over y on one row ("line mode", ``nemsim.model.layers``). The stem's stride takes the two rows to one,
the decoder's voxel shuffle gives them back as its two y sub-voxels, and ``FieldFold.finish`` averages them,
exactly. Every grid below the full one has a single row: the network costs what a 2-D one would.
A scene with ``symmetry = "none"`` (an off-centre or asymmetric layout) keeps the full domain everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np
import torch

from nemsim.scenes import quadrant_size

N_D4 = 8  # order of the square's symmetry group
SECTION_ROWS = 2  # rows of y a cross-section keeps (the stem's stride takes them to one; docstring)
FOLDS = ("quarter", "section")  # the model domains a FieldFold maps to


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


def section_mean(x: torch.Tensor) -> torch.Tensor:
    """The mean of x (..., H, W) over a trench's symmetries: the mirror of W about the field's centre and
    every translation along H (the mean over H, repeated). A new tensor of x's shape and dtype. The mean is
    taken in float64, so a field that already has the symmetries comes back exactly."""
    xf = x.double()
    m = (0.5 * (xf + xf.flip(-1))).mean(dim=-2, keepdim=True)
    return m.to(x.dtype).expand_as(x).contiguous()


def section_line(q: torch.Tensor, n: int) -> torch.Tensor:
    """The line profile (..., 1, n) of a cross-section q (..., r, c): its first row mirrored across the high W
    face (the trench axis)."""
    row = q[..., :1, :]  # (..., 1, c)
    return torch.cat([row, row.flip(-1)[..., n % 2:]], dim=-1)


def unfold_section(q: torch.Tensor, n: int, out: torch.Tensor | None = None) -> torch.Tensor:
    """The full field (..., n, n) of a cross-section q (..., r, c) (rows equal): its first row mirrored across
    the high W face (x) and repeated along H (y); written into ``out`` when given."""
    c = quadrant_size(n)
    if q.shape[-1] != c:
        raise ValueError(f"a cross-section of a field of size {n} is {c} wide, got {tuple(q.shape[-2:])}")
    full = section_line(q, n).expand(*q.shape[:-2], n, n)
    if out is None:
        return full.contiguous()
    if tuple(out.shape) != tuple(full.shape):
        raise ValueError(f"out must be {tuple(full.shape)}, got {tuple(out.shape)}")
    return out.copy_(full)


def mirror_pad_x(q: torch.Tensor, pad: int, n: int) -> torch.Tensor:
    """A cross-section q (..., r, c) extended by ``pad`` voxels on its high W face (across the trench axis)
    with the full field's voxels there (``mirror_pad`` on one axis)."""
    if pad <= 0:
        return q
    c = quadrant_size(n)
    skip = n % 2
    if pad > c - skip:
        raise ValueError(f"a mirror halo of {pad} voxels needs a half-width of more than {pad + skip}, "
                         f"got {c}")
    return torch.cat([q, q[..., c - skip - pad: c - skip].flip(-1)], dim=-1)


def rows_mean_(x: torch.Tensor) -> torch.Tensor:
    """Every row of x (..., H, W) replaced by the mean of the H rows, in place (a cross-section's rows are
    equal; this makes them so exactly). Returns x."""
    return x.copy_(x.mean(dim=-2, keepdim=True).expand_as(x))


@dataclass(frozen=True)
class FieldFold:
    """The maps between full fields (..., n, n) and a model's fundamental domain (module docstring):
    ``kind`` "quarter" (a hole's quadrant, (c, c)) or "section" (a trench's cross-section,
    (``SECTION_ROWS``, c)); n the full field's lateral size."""

    kind: Literal["quarter", "section"]
    n: int

    def __post_init__(self) -> None:
        if self.kind not in FOLDS:
            raise ValueError(f"a fold is one of {FOLDS}, got {self.kind!r}")

    @property
    def plane(self) -> tuple[int, int]:
        """(H, W) of a folded field."""
        c = quadrant_size(self.n)
        return (c, c) if self.kind == "quarter" else (SECTION_ROWS, c)

    def is_full(self, x: torch.Tensor) -> bool:
        """True when x (..., H, W) is a full field rather than a folded one."""
        return tuple(x.shape[-2:]) == (self.n, self.n)

    def symmetrize(self, x: torch.Tensor) -> torch.Tensor:
        """The mean of a full field over the fold's group (the square's 8 symmetries; a trench's mirror and
        translations)."""
        return symmetrize(x, "d4") if self.kind == "quarter" else section_mean(x)

    def fold(self, x: torch.Tensor) -> torch.Tensor:
        """The folded part (..., H, W) = ``plane`` of a symmetric full field (a view)."""
        h, w = self.plane
        return x[..., :h, :w]

    def unfold(self, q: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
        """The full field (..., n, n) of a folded one (into ``out`` when given)."""
        return unfold(q, self.n, out) if self.kind == "quarter" else unfold_section(q, self.n, out)

    def pad(self, q: torch.Tensor, pad: int) -> torch.Tensor:
        """The folded field with a mirror halo of ``pad`` voxels across the feature's axis (or axes)."""
        return mirror_pad(q, pad, self.n) if self.kind == "quarter" else mirror_pad_x(q, pad, self.n)

    def finish(self, x: torch.Tensor) -> torch.Tensor:
        """A predicted folded field made exactly symmetric (differentiable, a new tensor): the quadrant's
        diagonal mean, the section's row mean (in place on a rollout's buffer: ``symmetrize_diagonal_``,
        ``rows_mean_``)."""
        if self.kind == "quarter":
            return symmetrize(x, "diagonal")
        return x.mean(dim=-2, keepdim=True).expand_as(x).contiguous()


def model_fold(model: object) -> FieldFold | None:
    """The fold of a model that runs on a fundamental domain (``config.domain`` "quarter" or "section", a
    NEMSim or a runtime exposing its config); None for a full-domain model."""
    cfg = getattr(model, "config", None)
    n = int(getattr(cfg, "full_size", 0) or 0)
    kind = getattr(cfg, "domain", "full")
    return FieldFold(kind, n) if kind in FOLDS and n else None  # type: ignore[arg-type]


def quarter_model_size(model: object) -> int | None:
    """The full lateral size n of the fields a quarter-domain model (``config.domain == "quarter"``, a NEMSim
    or a runtime exposing its config) rebuilds; None for a full-domain model."""
    f = model_fold(model)
    return f.n if f is not None and f.kind == "quarter" else None


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
