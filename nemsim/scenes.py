"""Scenes: geometry, grid and horizon, read by every part of NEMSim from one config.

A scene fixes the native voxel box (x, y, z), the voxel size, the initial geometry (Si slab below a
resist layer with a centred cylindrical opening), the SDF clipping distance d_max and the time horizon.
Native fields are padded by one voxel on each side and transposed (x, y, z) -> (z, y, x), so the
state tensor is (C=2, D=nz+2, H=ny+2, W=nx+2) and depth index = z + 1 ([supp_representation]).

Choices where the paper is silent:
  * ``small`` halves the paper's resolution (4 nm voxels) so a trajectory simulates in seconds on a CPU;
    all physical extents (substrate 160 nm, resist 80 nm, opening radius 20 nm, d_max 30 nm) are kept.
  * ``tiny`` (tests only) uses 8 nm voxels with the same physical extents: 13 x 13 x 33 = 5,577 voxels.
  * ``symmetry``: every shipped scene is a centred circular opening on a square grid and declares the
    square's 8-fold symmetry about the hole axis ("d4"; ``nemsim.symmetry`` has its mirror planes and
    fundamental domain); a layout without it declares "none" and keeps the full domain.
  * ``kind``: the feature's shape, "hole" (a cylinder, ``opening_radius_vox`` its radius) or "trench" (a
    slot |x - cx| < ``opening_radius_vox`` along the whole y axis, symmetry "mirror_x_translate_y": the
    mirror x -> -x about the line's axis plus every translation along y). The named scenes are the default
    hole; a case's own geometry is a ``nemsim.geometry.feature.Feature`` applied to its scene
    (``Scene.with_feature``), which keeps the grid and pitch and derives si_top and the opening.
  * CD crops scale with the scene: the paper's mask crop is depth 80..121 and the Si crop depth 0..80
    (both inclusive) for Si below z=80 and resist up to z=120, i.e. mask = [si_top, resist_top + 1] and
    Si = [0, si_top] in depth index.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from typing import Protocol

SYMMETRIES = ("d4", "mirror_x_translate_y", "none")  # what a scene may declare (nemsim.symmetry)
KINDS = ("hole", "trench")  # feature shapes (module docstring)
TRENCH_SYMMETRY = "mirror_x_translate_y"  # a line along y: the mirror x -> -x and translations along y


def check_symmetry(name: str) -> str:
    if name not in SYMMETRIES:
        raise ValueError(f"unknown scene symmetry {name!r}; expected one of {SYMMETRIES}")
    return name


def quadrant_size(n: int) -> int:
    """Size c = ceil(n / 2) of the fundamental domain (``nemsim.symmetry.fold``) along a lateral axis of
    padded size n."""
    return (int(n) + 1) // 2


class FeatureLike(Protocol):
    """What ``Scene.with_feature`` takes: a ``nemsim.geometry.feature.Feature`` (not imported here: geometry
    imports scenes)."""

    def apply(self, scene: Scene) -> Scene: ...


@dataclass(frozen=True)
class Scene:
    name: str
    nx: int  # native voxels along x
    ny: int  # native voxels along y
    nz: int  # native voxels along z (growth direction; particles enter at the top, z = nz)
    voxel_nm: float  # isotropic voxel edge, nm
    si_top: int  # Si occupies 0 <= z < si_top
    resist_top: int  # resist occupies si_top <= z < resist_top, except the opening
    opening_radius_vox: float  # radius of the centred hole (half-width of a trench) in the resist, voxels
    d_max_nm: float = 30.0  # SDF clipping distance, nm (normalized SDF = clip(phi / d_max, -1, 1))
    horizon_s: float = 10.0  # macro time simulated, s
    snapshot_dt_s: float = 0.1  # one saved state every snapshot_dt_s
    macro_dt_s: float = 0.02  # simulator morphology/level-set step, s
    # the group the mean evolution is invariant under (``nemsim.symmetry``): "d4", the square's 8 symmetries
    # about the hole axis (a centred opening on a square grid), or "none" (the full domain everywhere)
    symmetry: str = "d4"
    kind: str = "hole"  # "hole" or "trench" (module docstring); a per-case scene's comes from its Feature

    def __post_init__(self) -> None:
        if not (0 < self.si_top < self.resist_top < self.nz):
            raise ValueError(
                f"scene {self.name!r}: need 0 < si_top ({self.si_top}) < resist_top ({self.resist_top}) "
                f"< nz ({self.nz})"
            )
        check_symmetry(self.symmetry)
        if self.kind not in KINDS:
            raise ValueError(f"scene {self.name!r}: unknown feature kind {self.kind!r}; "
                             f"expected one of {KINDS}")
        if self.kind == "trench" and self.symmetry == "d4":
            raise ValueError(f"scene {self.name!r}: a trench has symmetry {TRENCH_SYMMETRY!r} (or 'none'), "
                             "not the square's 'd4'")
        if self.kind == "hole" and self.symmetry == TRENCH_SYMMETRY:
            raise ValueError(f"scene {self.name!r}: symmetry {TRENCH_SYMMETRY!r} is a trench's; a hole "
                             "declares 'd4' or 'none'")
        if self.symmetry == "d4" and self.nx != self.ny:
            raise ValueError(f"scene {self.name!r}: the square's symmetry needs nx == ny, "
                             f"got {self.nx}, {self.ny}")
        ratio = self.snapshot_dt_s / self.macro_dt_s
        if abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(f"scene {self.name!r}: snapshot_dt_s must be a multiple of macro_dt_s")

    # --- derived quantities -------------------------------------------------------------------
    @property
    def d_max_vox(self) -> float:
        """SDF clipping distance in voxels."""
        return self.d_max_nm / self.voxel_nm

    @property
    def n_transitions(self) -> int:
        """Transitions per trajectory (100 for a 10 s horizon at 0.1 s)."""
        return int(round(self.horizon_s / self.snapshot_dt_s))

    @property
    def n_states(self) -> int:
        """States per trajectory including the initial one (101)."""
        return self.n_transitions + 1

    @property
    def macro_steps_per_snapshot(self) -> int:
        return int(round(self.snapshot_dt_s / self.macro_dt_s))

    @property
    def field_shape(self) -> tuple[int, int, int]:
        """(D, H, W) of one padded, transposed SDF channel."""
        return (self.nz + 2, self.ny + 2, self.nx + 2)

    @property
    def state_shape(self) -> tuple[int, int, int, int]:
        """(C, D, H, W) of one state: channel 0 = mask, channel 1 = Si."""
        return (2, *self.field_shape)

    @property
    def mask_crop(self) -> tuple[int, int]:
        """Inclusive depth-index range used for the mask channel's Chamfer distance."""
        return (self.si_top, self.resist_top + 1)

    @property
    def si_crop(self) -> tuple[int, int]:
        """Inclusive depth-index range used for the Si channel's Chamfer distance."""
        return (0, self.si_top)

    @property
    def area_nm2(self) -> float:
        """Top-plane area through which particles are launched, nm^2."""
        return self.nx * self.ny * self.voxel_nm**2

    @property
    def opening_centre(self) -> tuple[float, float]:
        """(x, y) of the opening axis in voxel-centre coordinates."""
        return ((self.nx - 1) / 2.0, (self.ny - 1) / 2.0)

    @property
    def quarter_state_shape(self) -> tuple[int, int, int, int]:
        """(C, D, c, c) of a state on the fundamental domain (``nemsim.symmetry.fold``); needs symmetry d4."""
        if self.symmetry != "d4":
            raise ValueError(f"scene {self.name!r} declares no symmetry: it has no quarter domain")
        c = quadrant_size(self.field_shape[-1])
        return (2, self.field_shape[0], c, c)

    def with_feature(self, feature: FeatureLike) -> Scene:
        """The per-case scene of ``feature`` on this scene's grid (``Feature.apply``)."""
        return feature.apply(self)

    def to_json(self) -> str:
        """JSON of every field; ``kind`` is left out for a hole, so a hole scene's record is what it was
        before features existed (files and checkpoints compare it)."""
        record = asdict(self)
        if record["kind"] == "hole":
            del record["kind"]
        return json.dumps(record, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "Scene":
        return cls(**json.loads(text))


PAPER = Scene("paper", nx=52, ny=52, nz=125, voxel_nm=2.0, si_top=80, resist_top=120, opening_radius_vox=10.0)
SMALL = Scene("small", nx=26, ny=26, nz=63, voxel_nm=4.0, si_top=40, resist_top=60, opening_radius_vox=5.0)
TINY = Scene("tiny", nx=13, ny=13, nz=33, voxel_nm=8.0, si_top=20, resist_top=30, opening_radius_vox=2.5)

SCENES: dict[str, Scene] = {s.name: s for s in (PAPER, SMALL, TINY)}
DEFAULT_SCENE = "small"


def get_scene(name: str) -> Scene:
    """Return the named scene; raises ValueError listing the choices."""
    try:
        return SCENES[name]
    except KeyError:
        raise ValueError(f"unknown scene {name!r}; expected one of {sorted(SCENES)}") from None
