"""The feature etched into a scene, as data: its kind, opening (CD) and mask thickness.

A scene fixes the grid, the voxel and the pitch (the periodic box); a ``Feature`` says what is drawn in it:

  * ``hole``: a cylindrical opening of diameter ``cd_nm`` centred on the box's axis, symmetry "d4" (the
    square's 8 symmetries about the axis; quarter domain);
  * ``trench``: a slot |x - cx| < cd_nm / 2 along the whole y axis (a line with the box's x pitch), symmetry
    "mirror_x_translate_y" (the mirror x -> -x about the line's axis plus every translation along y: its
    mean evolution is a cross-section in x and z).

``Feature.apply(scene)`` (also ``scene.with_feature(feature)``) returns the per-case ``Scene`` the simulator,
the profile metrics and the frame read: same grid and pitch, ``opening_radius_vox`` = cd / 2 (the hole's
radius or the trench's half-width, sub-voxel: the initial state's partial voxels carry it), ``si_top`` and
``resist_top`` from the mask, ``kind`` and ``symmetry`` from the feature.

Choice: how a mask thicker than the scene's fits the fixed grid. The mask top stays at the scene's
``resist_top`` and the Si top moves: si_top = resist_top - round(mask_nm / voxel_nm). Above the mask the grid
holds only the launch gap (3 voxels on ``small``), so a thicker mask cannot grow upward, while the Si below
is deep (160 nm on ``small``): a 120 nm mask leaves 120 nm of Si, a 40 nm one 200 nm. The frame's origin
(the initial Si top, ``nemsim.geometry.frame``) moves with it, so depths stay depths below the case's own Si
top. The mask thickness is whole voxels (``on_grid`` gives the thickness built; data sets store that), since
``mask_loss`` and the CD crops read the mask's top and bottom as voxel layers.

Fit (``check``): at least ``MIN_OPENING_VOX`` voxels of opening, at least ``MIN_WALL_VOX`` voxels of mask
between periodic neighbours (pitch - cd), at least one voxel of mask, and at least half the scene's own Si
thickness left below the mask for the etch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from nemsim.scenes import KINDS, TRENCH_SYMMETRY, Scene

FeatureKind = Literal["hole", "trench"]
MIN_OPENING_VOX = 2.0  # narrowest opening the grid resolves, voxels across
MIN_WALL_VOX = 2.0  # narrowest mask between periodic neighbours, voxels
MIN_SI_FRACTION = 0.5  # Si left below the mask, as a fraction of the scene's own Si thickness


@dataclass(frozen=True)
class Feature:
    """One feature: ``kind`` ("hole" or "trench"), opening ``cd_nm`` (hole diameter, trench width) and
    ``mask_nm`` (resist thickness), both nm."""

    kind: FeatureKind
    cd_nm: float
    mask_nm: float

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown feature kind {self.kind!r}; expected one of {KINDS}")
        for name in ("cd_nm", "mask_nm"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"feature {name} must be a finite number > 0 nm, got {value!r}")

    # --- construction ----------------------------------------------------------------------------
    @classmethod
    def default(cls, scene: Scene) -> Feature:
        """The scene's own feature (for the named scenes the 40 nm hole under 80 nm of mask)."""
        return cls.of(scene)

    @classmethod
    def of(cls, scene: Scene) -> Feature:
        """The feature a (per-case) scene draws: kind, cd = 2 opening_radius_vox voxel_nm, mask =
        (resist_top - si_top) voxel_nm."""
        return cls(
            kind=scene.kind,  # type: ignore[arg-type]
            cd_nm=2.0 * scene.opening_radius_vox * scene.voxel_nm,
            mask_nm=float(scene.resist_top - scene.si_top) * scene.voxel_nm,
        )

    def to_dict(self) -> dict[str, Any]:
        """``{"kind", "cd_nm", "mask_nm"}`` (the API's and the checkpoints' geometry block)."""
        return {"kind": self.kind, "cd_nm": float(self.cd_nm), "mask_nm": float(self.mask_nm)}

    @classmethod
    def from_dict(cls, record: dict[str, Any]) -> Feature:
        """Inverse of ``to_dict``; raises ValueError naming a missing or unknown key."""
        keys = {"kind", "cd_nm", "mask_nm"}
        if not isinstance(record, dict):
            raise ValueError(f"a feature is a dict with keys {sorted(keys)}, got {type(record).__name__}")
        missing, extra = keys - set(record), set(record) - keys
        if missing or extra:
            raise ValueError(f"a feature has exactly the keys {sorted(keys)}; missing {sorted(missing)}, "
                             f"unknown {sorted(extra)}")
        return cls(kind=record["kind"], cd_nm=float(record["cd_nm"]), mask_nm=float(record["mask_nm"]))

    # --- symmetry ----------------------------------------------------------------------------------
    @property
    def symmetry(self) -> str:
        """The group its mean evolution is invariant under: "d4" (hole) or "mirror_x_translate_y" (trench)."""
        return "d4" if self.kind == "hole" else TRENCH_SYMMETRY

    # --- on a scene's grid ---------------------------------------------------------------------------
    def mask_vox(self, scene: Scene) -> int:
        """Mask thickness in whole voxels of ``scene`` (module docstring)."""
        return int(round(self.mask_nm / scene.voxel_nm))

    def check(self, scene: Scene) -> None:
        """Raise ValueError (one line) when this feature does not fit ``scene``'s grid (module docstring)."""
        vox = scene.voxel_nm
        pitch_nm = (scene.nx if self.kind == "trench" else min(scene.nx, scene.ny)) * vox
        lo_cd, hi_cd = MIN_OPENING_VOX * vox, pitch_nm - MIN_WALL_VOX * vox
        if not lo_cd <= self.cd_nm <= hi_cd:
            raise ValueError(
                f"{self.kind} cd_nm={self.cd_nm:g} does not fit scene {scene.name!r}: the opening needs "
                f"{lo_cd:g}..{hi_cd:g} nm ({MIN_OPENING_VOX:g} voxels across, {MIN_WALL_VOX:g} voxels of "
                f"mask to the next feature on the {pitch_nm:g} nm pitch)"
            )
        mask_vox = self.mask_vox(scene)
        si_vox = scene.resist_top - mask_vox
        min_si_vox = math.ceil(MIN_SI_FRACTION * scene.si_top)
        hi_mask = (scene.resist_top - min_si_vox) * vox
        if mask_vox < 1 or si_vox < min_si_vox:
            raise ValueError(
                f"mask_nm={self.mask_nm:g} does not fit scene {scene.name!r}: the mask needs "
                f"{0.5 * vox:g}..{hi_mask + 0.5 * vox:g} nm (at least one {vox:g} nm voxel, and "
                f"{min_si_vox * vox:g} nm of Si left below it)"
            )

    def on_grid(self, scene: Scene) -> Feature:
        """This feature as ``apply`` builds it on ``scene``: the mask thickness rounded to whole voxels."""
        return replace(self, mask_nm=float(self.mask_vox(scene)) * scene.voxel_nm)

    def apply(self, scene: Scene) -> Scene:
        """The per-case scene: ``scene``'s grid, pitch and horizon with this feature drawn (module docstring).

        Raises ValueError when the feature does not fit (``check``).
        """
        self.check(scene)
        if self.kind == "trench":
            symmetry = "none" if scene.symmetry == "none" else TRENCH_SYMMETRY
        else:
            symmetry = "none" if scene.symmetry == "none" else "d4"
        return replace(
            scene,
            si_top=scene.resist_top - self.mask_vox(scene),
            opening_radius_vox=0.5 * self.cd_nm / scene.voxel_nm,
            kind=self.kind,
            symmetry=symmetry,
        )


# --- data sets: geometry ranges sampled with the controls ---------------------------------------------

GEOMETRY_COLUMNS = ("cd_nm", "mask_nm")  # the HDF5 ``geometry`` dataset's columns and the CSV's


def parse_range(text: str, name: str) -> tuple[float, float]:
    """"24:64" -> (24.0, 64.0); "40" -> (40.0, 40.0). ValueError naming ``name`` otherwise."""
    lo, sep, hi = str(text).partition(":")
    try:
        a = float(lo)
        b = float(hi) if sep else a
    except ValueError:
        raise ValueError(f"{name} {text!r}: expected a value or a range LO:HI in nm, e.g. 24:64") from None
    if not (math.isfinite(a) and math.isfinite(b) and 0 < a <= b):
        raise ValueError(f"{name} {text!r}: need 0 < LO <= HI (nm)")
    return a, b


def geometry_design(n: int, seed: int, cd_nm: tuple[float, float],
                    mask_nm: tuple[float, float]) -> np.ndarray:
    """(n, 2) [cd_nm, mask_nm]: two Latin-hypercube columns over the ranges (uniform in nm), drawn from
    ``default_rng([seed, 1])``. A Latin hypercube's columns are independent stratified permutations, so
    appended to the control design's 14 columns (``nemsim.controls.lhs_unit(n, seed)``) they make a joint
    16-column Latin hypercube and leave the control design as it was."""
    rng = np.random.default_rng([int(seed), 1])
    jitter = rng.uniform(size=(n, 2))  # (n, 2)
    perms = np.stack([rng.permutation(n) for _ in range(2)], axis=1)  # (n, 2) strata 0..n-1
    unit = (perms + jitter) / n  # (n, 2) in [0, 1)
    lo = np.array([cd_nm[0], mask_nm[0]])
    hi = np.array([cd_nm[1], mask_nm[1]])
    return lo + unit * (hi - lo)


def case_features(kind: str, geometry: np.ndarray, scene: Scene) -> list[Feature]:
    """The features of rows (N, 2) [cd_nm, mask_nm] as built on ``scene`` (``on_grid``); ValueError naming
    the first row that does not fit."""
    out = []
    for r, (cd, mask) in enumerate(np.asarray(geometry, dtype=np.float64).reshape(-1, 2)):
        feature = Feature(kind, float(cd), float(mask))  # type: ignore[arg-type]
        try:
            feature.check(scene)
        except ValueError as exc:
            raise ValueError(f"geometry row {r}: {exc}") from None
        out.append(feature.on_grid(scene))
    return out
