"""Trajectory files: the HDF5 contract of DESIGN.md "Data contracts", writer (resumable), reader, integrity
check.

Layout (one file per dataset, N cases, T = scene.n_states states, state (2, D, H, W)):
  datasets
    states                 (N, T, 2, D, H, W) float32 (or float16, ``state_dtype``), one state per chunk
    controls_raw           (N, 14) float64, physical units, columns = CONTROL_NAMES
    controls_transformed   (N, 14) float64, eq:supp_control_transformation
    times                  (T,) float64, seconds (0, 0.1, ..., 10.0)
    case_ids, seeds        (N,) int64: control-configuration ids, per-case simulator seed (-1 until written)
    complete               (N,) uint8, set only after the case's states are flushed
    case_meta              (N,) JSON strings, per-case metadata given to ``write``
    controls_raw_schedule  (N, T-1, 14) float64, optional: recipe controls, one vector per transition
    geometry               (N, 2) float64, optional: each case's feature [cd_nm, mask_nm] as built on the
                           scene's grid (``nemsim.geometry.feature``), with the root attribute feature_kind
                           ("hole" | "trench"); a file without them holds the scene's default feature
  root attributes
    format_version, scene (JSON: the named scene, the default feature), control_names, channel_names
    ["mask", "si"], d_max (nm), d_max_vox, rules_sha256, generator (JSON: simulator version, constants,
    seeds), feature_kind (with geometry)

``check_dataset`` runs the "Trajectory Integrity Checks" of [supp_dataset_statistics]: complete cases with
T frames of both channels on one evenly spaced time axis, finite values, |SDF| <= 1 + 1e-5 (states are
SDF / d_max clipped to [-1, 1]), one spatial shape, all 14 controls inside their global ranges, unique case
ids and control vectors. ``close(validate=True)`` runs the metadata-level ones only (no state reads).

Choices where the paper is silent:
  * gzip level 4, no shuffle (``DEFAULT_COMPRESSION``): readable by every HDF5 tool, smaller than lzf, and
    its read cost is small next to a model step.
  * Crash safety: a case's states are validated, written and flushed before its completion flag; a case
    whose flag is unset is redone on resume, so the file only holds valid complete cases.
  * ``state_dtype`` float16 rounds a clipped SDF by at most 2^-12 (far below the seed-to-seed noise) and
    roughly halves the file; readers get float32 either way. Recommended for ``paper``; float32 is default.
  * Per-case datasets are resizable along the case axis, so ``nemsim generate --n 16`` after ``--n 12``
    appends; a file open for writing elsewhere, or one HDF5 cannot open, is refused with one line.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from nemsim.controls import CONTROL_NAMES, CONTROL_SPECS, HIGH, LOW, N_CONTROLS, to_normalized, transform
from nemsim.geometry.feature import GEOMETRY_COLUMNS, Feature
from nemsim.scenes import Scene

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
CHANNEL_NAMES = ("mask", "si")
SDF_BOUND = 1.0 + 1e-5  # sanity bound on |normalized SDF|
CONTROL_RANGE_RTOL = 1e-9  # tolerance on the configured global control ranges (float round-off)
DEFAULT_COMPRESSION: tuple[str, int | None, bool] = ("gzip", 4, False)  # (filter, level, shuffle)
STATE_DTYPES = ("float32", "float16")  # storage of the states; both read back as float32
# datasets with one row per case (resizable along axis 0); case_ids last: a grow interrupted before it
# leaves the file's case list unchanged, and the next run redoes the grow
_PER_CASE = ("complete", "seeds", "controls_raw", "controls_transformed", "case_meta",
             "controls_raw_schedule", "geometry", "states", "case_ids")

_REQUIRED_DATASETS = ("states", "controls_raw", "controls_transformed", "times", "case_ids", "seeds",
                      "complete")
_REQUIRED_ATTRS = ("format_version", "scene", "control_names", "channel_names", "d_max", "rules_sha256",
                   "generator")


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def _dumps(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, default=_json_default)


class DataFileError(ValueError, OSError):
    """A trajectory file cannot be opened (in use, damaged, not HDF5): a one-line message. Both a
    ValueError (bad input) and an OSError (what h5py raised before), so either handler catches it."""


def open_h5(path: str | Path, mode: str) -> h5py.File:
    """h5py.File with one-line errors: DataFileError if another process holds the file (HDF5 file locking:
    a running writer) or if HDF5 cannot open it (damaged, truncated or not HDF5)."""
    try:
        return h5py.File(path, mode)
    except BlockingIOError:
        raise DataFileError(
            f"{path} is in use by another process (a running `nemsim generate`?); wait for it to finish "
            "or stop it, or choose another file"
        ) from None
    except OSError as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DataFileError(f"cannot open {path} as HDF5 ({first}); the file may be damaged or truncated: "
                         "move it away and regenerate") from None  # fmt: skip


def _ids_text(ids: np.ndarray) -> str:
    """Short description of a case-id list: '12 cases, ids 0..11' (contiguous) or the first few ids."""
    ids = np.asarray(ids).reshape(-1)
    if ids.size == 0:
        return "no cases"
    if ids.size > 1 and np.array_equal(ids, np.arange(ids[0], ids[0] + ids.size)):
        return f"{ids.size} cases, ids {ids[0]}..{ids[-1]}"
    head = ", ".join(str(int(i)) for i in ids[:6])
    return f"{ids.size} cases, ids {head}{', ...' if ids.size > 6 else ''}"


def validate_states(states: np.ndarray, scene: Scene) -> list[str]:
    """Problems of one case's states (T, 2, D, H, W) (empty list if valid)."""
    expect = (scene.n_states, *scene.state_shape)
    if tuple(states.shape) != expect:
        return [f"states shape {tuple(states.shape)} != expected {expect} (T, 2, D, H, W) "
                f"for scene {scene.name!r}"]
    out = []
    finite = np.isfinite(states)
    if not finite.all():
        bad = np.argwhere(~finite)[0]
        out.append(f"{int((~finite).sum())} non-finite values (first at step {bad[0]}, channel "
                   f"{CHANNEL_NAMES[bad[1]]})")
    amax = float(np.nanmax(np.abs(np.where(finite, states, 0.0)))) if states.size else 0.0
    if amax > SDF_BOUND:
        step = int(np.argmax(np.abs(np.where(finite, states, 0.0)).reshape(states.shape[0], -1).max(axis=1)))
        out.append(f"|SDF| up to {amax:.4g} exceeds the sanity bound {SDF_BOUND} (first such step {step})")
    return out


def _damaged_cases(f: h5py.File, scene: Scene) -> list[str]:
    """One line per complete case of an open trajectory file whose states cannot be read (a damaged chunk)
    or are not valid states (``validate_states``): what a resume must not build on. Reads every complete
    case's states."""
    ids, complete = f["case_ids"][()], f["complete"][()] > 0
    out = []
    for r in np.flatnonzero(complete):
        try:
            states = f["states"][r].astype(np.float32, copy=False)  # (T, 2, D, H, W)
        except OSError as exc:  # h5py: a chunk that does not decompress
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            out.append(f"case {int(ids[r])}: its states cannot be read ({first})")
            continue
        problems = validate_states(states, scene)
        if problems:
            out.append(f"case {int(ids[r])}: {'; '.join(problems)}")
    return out


class TrajectoryWriter:
    """Create (or resume) a trajectory file and write cases one at a time.

    Args:
        path: output ``.h5``.
        scene: the scene of every state.
        case_ids: (N,) control-configuration identifiers, one per row.
        controls_raw: (N, 14) physical controls (the constant control of each case).
        generator: JSON-able provenance (simulator version, constants, base seed, ...).
        rules_sha256: SHA-256 of the rules library used.
        controls_schedule: optional (N, T-1, 14) per-transition raw controls (recipes).
        compression: (filter, level, shuffle), default ``DEFAULT_COMPRESSION``.
        state_dtype: "float32" (default) or "float16" storage of the states (module docstring).
        geometry: optional (kind, (N, 2) [cd_nm, mask_nm]): each case's feature on ``scene``'s grid.

    An existing file is reopened to resume if scene, rules, generator and state dtype match and its case
    ids and controls (and schedule) equal the requested ones; if the requested list extends the file's
    (same ids and controls first, more after), the file grows by the new rows. Otherwise ValueError names
    the mismatch and what to do. A file with a complete case whose states cannot be read or are invalid
    (damaged) is refused with ValueError too: resuming would report it complete. ``finished`` lists
    complete rows.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        scene: Scene,
        case_ids,
        controls_raw,
        generator: dict,
        rules_sha256: str,
        controls_schedule=None,
        compression: tuple[str, int | None, bool] = DEFAULT_COMPRESSION,
        state_dtype: str = "float32",
        geometry: tuple[str, np.ndarray] | None = None,
    ) -> None:
        if state_dtype not in STATE_DTYPES:
            raise ValueError(f"state_dtype {state_dtype!r} is not one of {STATE_DTYPES}")
        self.state_dtype = state_dtype
        self.path = Path(path)
        self.scene = scene
        case_ids = np.asarray(case_ids, dtype=np.int64).reshape(-1)
        controls_raw = np.asarray(controls_raw, dtype=np.float64)
        n = case_ids.shape[0]
        if controls_raw.shape != (n, N_CONTROLS):
            raise ValueError(f"controls_raw shape {controls_raw.shape} != ({n}, {N_CONTROLS}) "
                             f"for {n} case ids")
        if len(np.unique(case_ids)) != n:
            raise ValueError("case_ids are not unique")
        schedule = None
        if controls_schedule is not None:
            schedule = np.asarray(controls_schedule, dtype=np.float64)
            expect = (n, scene.n_transitions, N_CONTROLS)
            if schedule.shape != expect:
                raise ValueError(f"controls_schedule shape {schedule.shape} != expected {expect}")
        self.n_cases = n
        self.geometry = None
        if geometry is not None:
            kind, rows = geometry[0], np.asarray(geometry[1], dtype=np.float64)
            if rows.shape != (n, 2):
                raise ValueError(f"geometry shape {rows.shape} != ({n}, 2) [cd_nm, mask_nm]")
            self.geometry = (str(kind), rows)
        gen_json = _dumps(generator)
        if self.path.exists():
            # read-only first: a file holding every requested case finished is not written to, so it opens
            # while other processes read it (a training on the same data)
            self._f = open_h5(self.path, "r")
            try:
                if not self._check_compatible(case_ids, controls_raw, schedule, gen_json, rules_sha256):
                    self._f.close()
                    self._f = open_h5(self.path, "r+")
                self._resume(case_ids, controls_raw, schedule)
            except Exception:
                self._f.close()
                raise
            log.info("resuming %s: %d/%d cases complete", self.path, len(self.finished), n)
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = open_h5(self.path, "w")
            self._create(case_ids, controls_raw, schedule, gen_json, rules_sha256, compression)

    # --- creation / resume -----------------------------------------------------------------------
    def _create(self, case_ids, controls_raw, schedule, gen_json, rules_sha256, compression) -> None:
        f, s = self._f, self.scene
        T = s.n_states
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["scene"] = s.to_json()
        f.attrs["control_names"] = list(CONTROL_NAMES)
        f.attrs["channel_names"] = list(CHANNEL_NAMES)
        f.attrs["d_max"] = float(s.d_max_nm)
        f.attrs["d_max_unit"] = "nm"
        f.attrs["d_max_vox"] = float(s.d_max_vox)
        f.attrs["rules_sha256"] = str(rules_sha256)
        f.attrs["generator"] = gen_json
        filt, level, shuffle = compression
        dtype = np.dtype(self.state_dtype)
        f.create_dataset(
            "states",
            shape=(self.n_cases, T, *s.state_shape),
            maxshape=(None, T, *s.state_shape),
            dtype=dtype,
            chunks=(1, 1, *s.state_shape),
            compression=filt,
            compression_opts=level,
            shuffle=shuffle,
            fillvalue=dtype.type(np.nan),
        )

        def per_case(name: str, data: np.ndarray) -> None:  # resizable along the case axis
            f.create_dataset(name, data=data, maxshape=(None, *data.shape[1:]), chunks=True)

        per_case("controls_raw", controls_raw)
        per_case("controls_transformed", transform(controls_raw))
        f.create_dataset("times", data=np.arange(T, dtype=np.float64) * s.snapshot_dt_s)
        per_case("case_ids", case_ids)
        per_case("seeds", np.full(self.n_cases, -1, dtype=np.int64))
        per_case("complete", np.zeros(self.n_cases, dtype=np.uint8))
        f.create_dataset("case_meta", shape=(self.n_cases,), maxshape=(None,), chunks=True,
                         dtype=h5py.string_dtype())  # fmt: skip
        if schedule is not None:
            per_case("controls_raw_schedule", schedule)
        if self.geometry is not None:
            per_case("geometry", self.geometry[1])
            f.attrs["feature_kind"] = self.geometry[0]
            f.attrs["geometry_columns"] = list(GEOMETRY_COLUMNS)
        f.flush()

    def _check_compatible(self, case_ids, controls_raw, schedule, gen_json, rules_sha256) -> bool:
        """Refuse (ValueError) a file this run cannot resume; True when it holds every requested case
        finished (nothing to write)."""
        f = self._f
        where = f"cannot resume {self.path}"
        missing = [k for k in _REQUIRED_DATASETS if k not in f]
        missing += [a for a in _REQUIRED_ATTRS if a not in f.attrs]
        if missing:
            raise ValueError(f"{where}: not a NEMSim trajectory file (missing {missing}); "
                             "remove it or choose another --out")
        if int(f.attrs["format_version"]) != FORMAT_VERSION:
            raise ValueError(f"{where}: format_version {f.attrs['format_version']} != {FORMAT_VERSION}")
        if Scene.from_json(str(f.attrs["scene"])) != self.scene:
            stored = Scene.from_json(str(f.attrs["scene"])).name
            raise ValueError(f"{where}: scene mismatch (file {stored!r}, requested {self.scene.name!r})")
        stored = str(f["states"].dtype)
        if stored != self.state_dtype:
            raise ValueError(f"{where}: the file stores {stored} states, {self.state_dtype} were requested "
                             f"(resume with state dtype {stored}, e.g. --state-dtype {stored})")  # fmt: skip
        file_ids = f["case_ids"][()]
        m = len(file_ids)
        has = "controls_raw_schedule" in f
        if has != (schedule is not None):
            raise ValueError(f"{where}: controls_schedule mismatch (the file {'has' if has else 'has no'} "
                             "per-transition recipes); choose another --out")  # fmt: skip
        if len(case_ids) < m or not np.array_equal(file_ids, case_ids[:m]):
            raise ValueError(
                f"{where}: case_ids mismatch: the file holds {_ids_text(file_ids)}, this run asks for "
                f"{_ids_text(case_ids)}; a file resumes with its own cases and grows only by cases appended "
                "after them (e.g. --n 16 after --n 12): rerun with its cases or more, or choose another --out"
            )
        if not np.array_equal(f["controls_raw"][:m], controls_raw[:m]):  # [:m]: after an interrupted grow
            raise ValueError(f"{where}: controls_raw mismatch: the file's cases were simulated with other "
                             "controls (another design or --controls file); "
                             "choose another --out")  # fmt: skip
        if has and not np.array_equal(f["controls_raw_schedule"][:m], schedule[:m]):
            raise ValueError(f"{where}: controls_schedule mismatch: the file's cases have other recipes; "
                             "choose another --out")  # fmt: skip
        stored_geo = ((str(f.attrs.get("feature_kind", "")), f["geometry"][:m]) if "geometry" in f else None)
        want = None if self.geometry is None else (self.geometry[0], self.geometry[1][:m])
        if (stored_geo is None) != (want is None) or (
                stored_geo is not None and want is not None
                and (stored_geo[0] != want[0] or not np.array_equal(stored_geo[1], want[1]))):
            raise ValueError(f"{where}: geometry mismatch: the file's cases have other features (kind, CD, "
                             "mask); choose another --out")
        if str(f.attrs["rules_sha256"]) != str(rules_sha256):
            raise ValueError(f"{where}: rules_sha256 mismatch (file {str(f.attrs['rules_sha256'])[:12]}..., "
                             f"requested {str(rules_sha256)[:12]}...)")
        if str(f.attrs["generator"]) != gen_json:
            raise ValueError(f"{where}: generator mismatch (file {f.attrs['generator']}, "
                             f"requested {gen_json})")
        return len(case_ids) == m and bool(np.all(f["complete"][()]))  # nothing to write

    def _resume(self, case_ids, controls_raw, schedule) -> None:
        """The finished cases read back (a damaged file is refused, even with nothing left to write: it is
        never reported complete), then rows appended for requested cases the file lacks."""
        m = len(self._f["case_ids"])
        log.info("%s: reading back its finished cases before resuming", self.path)
        damaged = _damaged_cases(self._f, self.scene)
        if damaged:
            more = f" (and {len(damaged) - 1} more)" if len(damaged) > 1 else ""
            raise ValueError(
                f"cannot resume {self.path}: the file is damaged: {damaged[0]}{more}; `nemsim data check "
                f"{self.path}` reports it; move the file away and regenerate, or write the other cases to "
                "another --out"
            )
        if len(case_ids) > m:
            self._grow(m, case_ids, controls_raw, schedule)

    def _grow(self, m: int, case_ids, controls_raw, schedule) -> None:
        """Append rows m..n-1 (not yet simulated) to a file holding the first m of the requested cases."""
        f, n = self._f, len(case_ids)
        fixed = [k for k in _PER_CASE if k in f and f[k].maxshape[0] is not None]
        if fixed:
            raise ValueError(
                f"cannot grow {self.path} from {m} to {n} cases: it was written without room to grow "
                f"(fixed-size {fixed[0]}); write cases {int(case_ids[m])}.. to another file (e.g. --cases "
                f"{m}-{n - 1} --out OTHER.h5) or regenerate it"
            )
        new = {
            "complete": np.zeros(n - m, dtype=np.uint8),
            "seeds": np.full(n - m, -1, dtype=np.int64),
            "controls_raw": controls_raw[m:],
            "controls_transformed": transform(controls_raw[m:]),
            "controls_raw_schedule": None if schedule is None else schedule[m:],
            "geometry": None if self.geometry is None else self.geometry[1][m:],
            "case_ids": case_ids[m:],
        }
        for k in _PER_CASE:
            if k in f:
                f[k].resize(n, axis=0)
                if new.get(k) is not None:
                    f[k][m:] = new[k]
        f.flush()
        log.info("growing %s from %d to %d cases", self.path, m, n)

    # --- writing -------------------------------------------------------------------------------
    @property
    def finished(self) -> set[int]:
        """Row indices whose completion flag is set."""
        return {int(i) for i in np.flatnonzero(self._f["complete"][()])}

    def write(self, row: int, states, seed: int, meta: dict | None = None) -> None:
        """Validate and write one case (T, 2, D, H, W), then flag it complete.

        Raises ValueError (and writes nothing) if the row is out of range or the states are invalid.
        """
        if not 0 <= int(row) < self.n_cases:
            raise ValueError(f"row {row} out of range [0, {self.n_cases})")
        states = np.asarray(states, dtype=np.float32)
        problems = validate_states(states, self.scene)
        if problems:
            cid = int(self._f["case_ids"][row])
            raise ValueError(f"case {cid} (row {row}) rejected: {'; '.join(problems)}")
        f = self._f
        f["complete"][row] = 0  # rewriting a finished case: unflag first
        f.flush()
        f["states"][row] = states.astype(self.state_dtype, copy=False)
        f["seeds"][row] = int(seed)
        f["case_meta"][row] = _dumps(meta or {})
        f.flush()  # states on disk before the flag
        f["complete"][row] = 1
        f.flush()

    def close(self, validate: bool = True) -> None:
        """Close the file; with ``validate`` run the metadata-level checks and raise ValueError on failure."""
        if self._f is None:
            return
        self._f.flush()
        self._f.close()
        self._f = None
        if validate:
            report = check_dataset(self.path, read_states=False, require_complete=False)
            if not report.ok:
                raise ValueError(f"{self.path} failed validation:\n{report.text}")

    def __enter__(self) -> TrajectoryWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(validate=exc_type is None)


class TrajectoryFile:
    """Read-only view of a trajectory file; ``states`` is the lazy h5py dataset (N, T, 2, D, H, W)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._f = open_h5(self.path, "r")
        f = self._f
        missing = [k for k in ("states", "controls_raw", "case_ids", "times") if k not in f]
        missing += [a for a in ("scene", "format_version") if a not in f.attrs]
        if missing:
            f.close()
            raise ValueError(f"{self.path}: not a NEMSim trajectory file (missing {missing})")
        self.format_version = int(f.attrs["format_version"])
        self.scene = Scene.from_json(str(f.attrs["scene"]))
        self.case_ids = f["case_ids"][()].astype(np.int64)  # (N,)
        self.controls_raw = f["controls_raw"][()]  # (N, 14)
        self.times = f["times"][()]  # (T,)
        self.control_names = tuple(str(s) for s in f.attrs.get("control_names", CONTROL_NAMES))
        self.channel_names = tuple(str(s) for s in f.attrs.get("channel_names", CHANNEL_NAMES))
        self.d_max = float(f.attrs.get("d_max", self.scene.d_max_nm))
        self.rules_sha256 = str(f.attrs.get("rules_sha256", ""))
        self.generator = json.loads(str(f.attrs.get("generator", "{}")))
        raw = f["states"]
        self.state_dtype = str(raw.dtype)  # storage dtype; reads are float32 either way
        # lazy (N, T, 2, D, H, W) float32: the dataset itself, or a converting view of float16 storage
        self.states = raw if raw.dtype == np.float32 else raw.astype(np.float32)
        self.seeds = f["seeds"][()] if "seeds" in f else np.full(len(self.case_ids), -1, dtype=np.int64)
        n_cases = len(self.case_ids)
        self.complete = (f["complete"][()] > 0) if "complete" in f else np.ones(n_cases, dtype=bool)
        self.controls_raw_schedule = f["controls_raw_schedule"][()] if "controls_raw_schedule" in f else None
        # each case's feature (module docstring); a file without geometry holds the scene's default feature
        self.feature_kind = str(f.attrs.get("feature_kind", self.scene.kind))
        default = Feature.default(self.scene)
        self.has_geometry = "geometry" in f
        self.geometry = (f["geometry"][()] if self.has_geometry
                         else np.tile([default.cd_nm, default.mask_nm], (n_cases, 1)))  # (N, 2)
        self._row_of = {int(c): r for r, c in enumerate(self.case_ids)}

    @property
    def n_cases(self) -> int:
        return int(self.case_ids.shape[0])

    def case_feature(self, row: int) -> Feature:
        """The feature of one row (the scene's default for a file without geometry)."""
        cd, mask = self.geometry[row]
        return Feature(self.feature_kind, float(cd), float(mask))  # type: ignore[arg-type]

    def case_scene(self, row: int) -> Scene:
        """The per-case scene of one row (``Feature.apply``): what its states and profile metrics read."""
        return self.case_feature(row).apply(self.scene)

    def seed_pairs(self) -> np.ndarray:
        """(P, 2) rows of the complete cases that share a simulator seed, two by two, in the order of their
        first row: the sweep pairs of ``nemsim design --kind pairs``. A seed of more than two complete cases
        is a ValueError naming their ids."""
        members: dict[int, list[int]] = {}
        for r in np.flatnonzero(self.complete):
            members.setdefault(int(self.seeds[r]), []).append(int(r))
        for s, rows in members.items():
            if len(rows) > 2:
                raise ValueError(f"{self.path}: seed {s} is shared by {len(rows)} cases (case ids "
                                 f"{self.case_ids[rows].tolist()}); a pair file pairs two cases")
        return np.array(sorted(r for r in members.values() if len(r) == 2), dtype=np.int64).reshape(-1, 2)

    @property
    def n_states(self) -> int:
        return int(self.states.shape[1])

    @property
    def controls_transformed(self) -> np.ndarray:
        return transform(self.controls_raw)

    @property
    def controls_normalized(self) -> np.ndarray:
        """(N, 14) float64 normalized controls, eq:supp_control_normalization."""
        return to_normalized(self.controls_raw)

    def controls_normalized_schedule(self, row: int) -> np.ndarray:
        """(T-1, 14) normalized per-transition controls of one row (constant rows repeat their vector)."""
        if self.controls_raw_schedule is not None:
            return to_normalized(self.controls_raw_schedule[row])
        return np.repeat(to_normalized(self.controls_raw[row])[None], self.n_states - 1, axis=0)

    def row_of(self, case_id: int) -> int:
        """Row index of a case id; KeyError naming the id."""
        try:
            return self._row_of[int(case_id)]
        except KeyError:
            raise KeyError(f"case id {case_id} not in {self.path}") from None

    def warn_if_other_rules(self, sha256: str, whose: str = "the library") -> bool:
        """Log a warning (and return True) if the file was generated with another rules library than the
        one of SHA-256 ``sha256`` (``whose`` names it in the message); files without a hash pass."""
        if not self.rules_sha256 or self.rules_sha256 == str(sha256):
            return False
        log.warning("%s was generated with rules %s..., %s is %s...", self.path, self.rules_sha256[:12],
                    whose, str(sha256)[:12])
        return True

    def case_meta(self, row: int) -> dict:
        if "case_meta" not in self._f:
            return {}
        raw = self._f["case_meta"][row]
        raw = raw.decode() if isinstance(raw, bytes) else raw
        return json.loads(raw) if raw else {}

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None

    def __enter__(self) -> TrajectoryFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_trajectories(path: str | Path) -> TrajectoryFile:
    """Open a trajectory file read-only (states stay on disk)."""
    return TrajectoryFile(path)


# --- integrity check ---------------------------------------------------------------------------------


def _direct_chunks(states: h5py.Dataset) -> bool:
    """Whether ``states`` can be read a raw chunk at a time and inflated outside HDF5 (``read_cases``): one
    state per chunk, gzip (zlib) or no filter at all, no other filter."""
    plain = states.compression in (None, "gzip") and not states.shuffle and not states.fletcher32 \
        and states.scaleoffset is None
    return plain and states.chunks == (1, 1, *states.shape[2:])


def read_cases(path: str | Path, rows: Any, threads: int | None = None, ahead: int | None = None):
    """Yield (i, states (T, 2, D, H, W) in the stored dtype) for each file row ``rows[i]``, in order.

    The whole-file decode of a training set (``nemsim.data.dataset.MemoryTransitions``): HDF5 inflates a
    chunk holding its one global lock, so a plain read decodes on one core. Here each state's compressed
    chunk is read as it is stored and inflated by ``zlib`` (which releases the GIL) on ``threads`` threads
    (default: the cores this process may use), at most ``ahead`` cases (default 2 x threads) read ahead of
    the consumer. A layout this cannot read (``_direct_chunks``) is read row by row through h5py.
    """
    import os
    import zlib
    from concurrent.futures import ThreadPoolExecutor

    rows = [int(r) for r in np.asarray(rows).reshape(-1)]
    if threads is None:
        threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    threads = max(1, int(threads))
    with h5py.File(path, "r") as f:
        states = f["states"]
        if not _direct_chunks(states):
            for i, row in enumerate(rows):
                yield i, states[row]
            return
        shape, dtype, n_t = states.shape[2:], states.dtype, states.shape[1]
        zero = (0,) * len(shape)

        def case(row: int) -> np.ndarray:
            out = np.empty((n_t, *shape), dtype=dtype)
            for t in range(n_t):
                mask, raw = states.id.read_direct_chunk((row, t, *zero))
                inflated = raw if mask & 1 or states.compression is None else zlib.decompress(raw)
                out[t] = np.frombuffer(inflated, dtype=dtype).reshape(shape)
            return out

        with ThreadPoolExecutor(max_workers=threads) as pool:
            window = max(1, ahead or 2 * threads)
            futures = {i: pool.submit(case, r) for i, r in enumerate(rows[:window])}
            for i in range(len(rows)):
                if i + window < len(rows):
                    futures[i + window] = pool.submit(case, rows[i + window])
                yield i, futures.pop(i).result()


@dataclass
class CheckReport:
    """Result of ``check_dataset``: ``ok`` is False if any check failed; ``text`` is the readable report."""

    path: str
    checks: list[tuple[str, bool, str]] = field(default_factory=list)  # (name, passed, detail)
    warnings: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return all(p for _, p, _ in self.checks)

    @property
    def errors(self) -> list[str]:
        return [f"{n}: {d}" for n, p, d in self.checks if not p]

    def add(self, name: str, passed: bool, detail: str = "") -> None:
        self.checks.append((name, bool(passed), detail))

    @property
    def text(self) -> str:
        lines = [f"data check {self.path}"]
        for name, passed, detail in self.checks:
            lines.append(f"  {'PASS' if passed else 'FAIL'}  {name:<22} {detail}")
        for w in self.warnings:
            lines.append(f"  WARN  {w}")
        n_fail = sum(not p for _, p, _ in self.checks)
        lines.append(f"result: {'OK' if self.ok else f'FAILED ({n_fail} of {len(self.checks)} checks)'}")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.text


def check_dataset(path: str | Path, *, read_states: bool = True,
                  require_complete: bool = True) -> CheckReport:
    """Run the integrity checks of [supp_dataset_statistics] on a trajectory file.

    Args:
        path: the ``.h5`` file.
        read_states: stream through every state (finite values, sanity bound); False = metadata only.
        require_complete: fail if any case lacks its completion flag (False: only warn).
    Returns:
        CheckReport (never raises for a bad file; an unreadable file is a failed check).
    """
    rep = CheckReport(str(path))
    try:
        f = open_h5(path, "r")
    except ValueError as exc:
        rep.add("open", False, str(exc))
        return rep
    with f:
        missing = [k for k in _REQUIRED_DATASETS if k not in f]
        missing += [f"@{a}" for a in _REQUIRED_ATTRS if a not in f.attrs]
        rep.add("layout", not missing,
                f"missing {missing}" if missing else "all datasets and attributes present")
        if missing:
            return rep
        ok = int(f.attrs["format_version"]) == FORMAT_VERSION
        rep.add("format_version", ok,
                f"{f.attrs['format_version']}" + ("" if ok else f" != {FORMAT_VERSION}"))
        try:
            scene = Scene.from_json(str(f.attrs["scene"]))
        except (TypeError, ValueError) as exc:
            rep.add("scene", False, f"bad scene JSON: {exc}")
            return rep
        names = [str(s) for s in f.attrs["control_names"]]
        miss = [n for n in CONTROL_NAMES if n not in names]
        ok = names == list(CONTROL_NAMES)
        rep.add("control_names", ok, "14 controls in table order" if ok else f"missing {miss}, got {names}")
        chans = [str(s) for s in f.attrs["channel_names"]]
        rep.add("channel_names", chans == list(CHANNEL_NAMES), f"{chans}")

        st = f["states"]
        n = int(f["case_ids"].shape[0])
        T = scene.n_states
        expect = (n, T, *scene.state_shape)
        ok = tuple(st.shape) == expect and str(st.dtype) in STATE_DTYPES
        rep.add("state shape", ok, f"{tuple(st.shape)} {st.dtype}"
                + ("" if ok else f"; expected {expect} in one of {STATE_DTYPES}"))  # fmt: skip
        if not ok:
            return rep

        times = f["times"][()]
        dt = np.diff(times)
        ok = times.shape == (T,) and abs(times[0]) < 1e-9 and bool(np.all(dt > 0))
        ok = ok and bool(np.allclose(dt, scene.snapshot_dt_s, rtol=1e-6, atol=1e-9))
        rep.add("timestamps", ok, f"{T} frames, t = {times[0]:g}..{times[-1]:g} s"
                + ("" if ok else f"; expected increasing steps of {scene.snapshot_dt_s} s from 0"))

        complete = f["complete"][()] > 0
        n_inc = int((~complete).sum())
        detail = f"{n - n_inc}/{n} cases complete"
        if n_inc:
            detail += f"; unfinished case ids {f['case_ids'][()][~complete][:10].tolist()}" + (
                "..." if n_inc > 10 else "")
        if require_complete:
            rep.add("completeness", n_inc == 0, detail)
        elif n_inc:
            rep.warnings.append(detail)
        seeds = f["seeds"][()]
        bad_seeds = int(((seeds < 0) & complete).sum())
        rep.add("seeds", bad_seeds == 0, "recorded for every complete case" if not bad_seeds
                else f"{bad_seeds} complete cases without a seed")

        ids = f["case_ids"][()]
        raw = f["controls_raw"][()]
        geo = _check_geometry(f, scene, n, rep)  # (N, 2) or None
        ok_ids = len(np.unique(ids)) == n
        keys = raw if geo is None else np.concatenate([raw, geo], axis=1)  # a case = its controls and feature
        uniq_rows = len(np.unique(keys, axis=0)) if n else 0
        what = "control vectors" if geo is None else "(controls, geometry) rows"
        rep.add("unique ids/controls", ok_ids and uniq_rows == n,
                f"{len(np.unique(ids))} unique ids, {uniq_rows} unique {what} of {n}")
        ok, detail, note = _check_ranges(raw, "controls_raw")
        rep.add("control ranges", ok, detail)
        if note:
            rep.warnings.append(note)
        tr = f["controls_transformed"][()]
        ok = tr.shape == raw.shape and bool(np.allclose(tr, transform(raw), rtol=1e-12, atol=1e-12))
        rep.add("controls_transformed", ok,
                "= transform(controls_raw)" if ok else "inconsistent with controls_raw")
        if "controls_raw_schedule" in f:
            sch = f["controls_raw_schedule"][()]
            shp_ok = sch.shape == (n, T - 1, N_CONTROLS)
            ok, detail, note = _check_ranges(sch.reshape(-1, N_CONTROLS), "schedule")
            rep.add("schedule", shp_ok and ok, f"{sch.shape}; {detail}")
            if note:
                rep.warnings.append(note)
        ints = [j for j, s in enumerate(CONTROL_SPECS) if s.kind == "int"]
        if not np.all(raw[:, ints] == np.round(raw[:, ints])):
            rep.warnings.append("non-integer cosine-power exponents in controls_raw")

        if read_states:
            bad_cases: list[str] = []
            for r in np.flatnonzero(complete):
                problems = validate_states(st[r].astype(np.float32, copy=False), scene)
                if problems:
                    bad_cases.append(f"case {int(ids[r])}: {'; '.join(problems)}")
            detail = (f"{int(complete.sum())} complete cases finite and within |SDF| <= {SDF_BOUND}"
                      if not bad_cases else f"{len(bad_cases)} bad cases: " + " | ".join(bad_cases[:5]))
            rep.add("state values", not bad_cases, detail)
    return rep


def _check_geometry(f: h5py.File, scene: Scene, n: int, rep: CheckReport) -> np.ndarray | None:
    """Add the "geometry" check: each case's feature fits the scene's grid and is on it (whole-voxel
    mask); a file without geometry holds the default feature. Returns the (N, 2) rows or None."""
    if "geometry" not in f:
        d = Feature.default(scene)
        rep.add("geometry", True, f"default feature ({d.kind}, CD {d.cd_nm:g} nm, mask {d.mask_nm:g} nm)")
        return None
    geo, kind = f["geometry"][()], str(f.attrs.get("feature_kind", ""))
    if geo.shape != (n, 2) or not np.all(np.isfinite(geo)):
        rep.add("geometry", False, f"shape {geo.shape} (expected ({n}, 2) [cd_nm, mask_nm]), finite values")
        return None
    problems = []
    for r, (cd, mask) in enumerate(geo):
        try:
            feature = Feature(kind, float(cd), float(mask))  # type: ignore[arg-type]
            feature.check(scene)
            if feature.on_grid(scene) != feature:
                raise ValueError(f"mask_nm={mask:g} is not whole {scene.voxel_nm:g} nm voxels")
        except ValueError as exc:
            problems.append(f"case {int(f['case_ids'][r])}: {exc}")
    detail = (f"{kind}, CD {geo[:, 0].min():g}..{geo[:, 0].max():g} nm, mask {geo[:, 1].min():g}.."
              f"{geo[:, 1].max():g} nm" if n else f"{kind}, no cases")
    rep.add("geometry", not problems, detail if not problems else f"{len(problems)} bad: {problems[0]}")
    return geo


def _check_ranges(raw: np.ndarray, what: str) -> tuple[bool, str, str]:
    """(ok, detail, warning) of raw controls (rows, 14): inadmissible values (``check_admissible``: not
    finite, physically impossible) fail; admissible values outside the design box (a recipe simulated past
    its edges, e.g. by active learning) only warn: the file is sound, its cases lie beyond the box."""
    from nemsim.controls import check_admissible

    bad = check_admissible(raw)
    if bad:
        return False, f"{len(bad)} inadmissible values in {what}, e.g. {bad[0]}", ""
    span = HIGH - LOW
    lo, hi = LOW - CONTROL_RANGE_RTOL * span, HIGH + CONTROL_RANGE_RTOL * span
    out = (raw < lo) | (raw > hi)
    if not out.any():
        return True, f"all {raw.shape[0]} rows inside the configured ranges", ""
    cols = sorted({CONTROL_NAMES[j] for j in np.nonzero(out)[1]})
    rows = int(out.any(axis=1).sum())
    return True, f"admissible; {rows} rows beyond the design box", \
        f"{rows} rows of {what} outside the configured ranges in {cols} (admissible: beyond the design box)"
