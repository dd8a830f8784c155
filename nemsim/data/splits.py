"""Trajectory-level split manifests ([supp_protocols], tab:supp_split_summary) and nested data-efficiency
subsets ([supp_data_efficiency]).

Settings:
  control-id  random 60/20/20 partition of all cases.
  ood-ar      q(Ar+ flux) in I_in = [0.15, 0.85] -> train/val pool, q in I_out -> test
              (eq:supp_ood_intervals).
  ood-cl      the same on q(Cl+ flux) (the ionic flux, not neutral Cl).
  ood-joint   A and C (both in) -> pool, (not A) and (not C) -> test, A xor C -> unused
              (eq:supp_joint_ood_indicators).
  vis-50/60   the control-id partition with visible_transitions = 50 / 60 (eq:supp_temporal_training_set).

Manifest (JSON, DESIGN.md): {"setting", "train", "val", "test", "unused", "visible_transitions"} plus
informational keys: "seed", "n_transitions", for OOD settings "ood_controls", "interval_in" and
"test_groups" (case ids per boundary region: "L"/"H", or "LL", "LH", "HL", "HH" for (Ar+, Cl+)), and
"data_efficiency" ({"0.1": [...], "0.2": [...], "0.5": [...], "1.0": [...]}, nested training subsets).

Choices where the paper is silent:
  * Partitions are drawn with ``numpy.random.default_rng(seed)``, seed 0: control-id permutes all case ids
    (train = round(0.6 N), val = round(0.2 N), test = rest); each OOD pool is permuted and
    val = round(0.2 pool) (gives 280/70, 279-280/70, 202/50-51 as in the paper's table). vis-50/vis-60 reuse
    the control-id partition.
  * Data-efficiency strata: a 3 x 3 grid of equal-width bins over [min, max] of the training cases' log10
    Ar+ and Cl+ fluxes. Each stratum's members are shuffled once (seed 0); a fraction f keeps
    n_f = floor(f n + 1/2) cases, allocated to strata proportionally to their size by growing the previous
    fraction's allocation one case at a time (largest deficit f n_s - k_s first, ties by stratum index), and
    takes the first k_s of each stratum's order. So D_10% subset D_20% subset D_50% subset D_100% by
    construction.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from nemsim.controls import CONTROL_INDEX, N_CONTROLS, ood_coordinate, transform

SETTINGS = ("control-id", "ood-ar", "ood-cl", "ood-joint", "vis-50", "vis-60")
INTERVAL_IN = (0.15, 0.85)  # I_in, eq:supp_ood_intervals
VAL_FRACTION = 0.2
CONTROL_ID_FRACTIONS = (0.6, 0.2, 0.2)
DATA_EFFICIENCY_FRACTIONS = (0.1, 0.2, 0.5, 1.0)
OOD_CONTROLS = {"ood-ar": ("flux_ar_plus",), "ood-cl": ("flux_cl_plus",),
                "ood-joint": ("flux_ar_plus", "flux_cl_plus")}


def _region(q: np.ndarray) -> np.ndarray:
    """'L' (q < 0.15), 'I' (inside [0.15, 0.85]) or 'H' (q > 0.85) per case."""
    lo, hi = INTERVAL_IN
    return np.where(q < lo, "L", np.where(q > hi, "H", "I"))


def _split_pool(pool: np.ndarray, rng: np.random.Generator) -> tuple[list[int], list[int]]:
    perm = rng.permutation(pool)
    n_val = int(round(VAL_FRACTION * len(perm)))
    return sorted(int(c) for c in perm[n_val:]), sorted(int(c) for c in perm[:n_val])


def _manifest(setting, train, val, test, unused, visible, n_transitions, seed, **extra) -> dict:
    return {
        "setting": setting,
        "train": sorted(int(c) for c in train),
        "val": sorted(int(c) for c in val),
        "test": sorted(int(c) for c in test),
        "unused": sorted(int(c) for c in unused),
        "visible_transitions": int(visible),
        "n_transitions": int(n_transitions),
        "seed": int(seed),
        **extra,
    }


def make_manifests(design_raw, case_ids=None, *, seed: int = 0, n_transitions: int = 100) -> dict[str, dict]:
    """All six split manifests of a control design.

    Args:
        design_raw: (N, 14) raw controls, row i = case ``case_ids[i]``.
        case_ids: (N,) ids (default 0..N-1).
        seed: partition seed.
        n_transitions: transitions per trajectory (vis-p keeps round(p/100 * n_transitions)).
    Returns:
        {setting: manifest}; each manifest also carries its nested "data_efficiency" training subsets.
    """
    raw = np.asarray(design_raw, dtype=np.float64)
    if raw.ndim != 2 or raw.shape[1] != N_CONTROLS:
        raise ValueError(f"design must have shape (N, {N_CONTROLS}); got {raw.shape}")
    if int(n_transitions) < 1:
        raise ValueError(f"n_transitions must be >= 1 (transitions per trajectory), got {n_transitions}")
    n = raw.shape[0]
    ids = (np.arange(n, dtype=np.int64) if case_ids is None
           else np.asarray(case_ids, dtype=np.int64).reshape(-1))
    if ids.shape != (n,) or len(np.unique(ids)) != n:
        raise ValueError(f"case_ids must be {n} unique integers; got shape {ids.shape}")
    out: dict[str, dict] = {}

    perm = np.random.default_rng(seed).permutation(ids)
    n_tr = int(round(CONTROL_ID_FRACTIONS[0] * n))
    n_va = int(round(CONTROL_ID_FRACTIONS[1] * n))
    tr, va, te = perm[:n_tr], perm[n_tr : n_tr + n_va], perm[n_tr + n_va :]
    out["control-id"] = _manifest("control-id", tr, va, te, [], n_transitions, n_transitions, seed)
    for p in (50, 60):
        out[f"vis-{p}"] = _manifest(f"vis-{p}", tr, va, te, [], round(p / 100 * n_transitions), n_transitions,
                                    seed)

    regions = {name: _region(ood_coordinate(raw, name)) for name in ("flux_ar_plus", "flux_cl_plus")}
    for setting in ("ood-ar", "ood-cl"):
        (name,) = OOD_CONTROLS[setting]
        reg = regions[name]
        train, val = _split_pool(ids[reg == "I"], np.random.default_rng(seed))
        groups = {g: sorted(int(c) for c in ids[reg == g]) for g in ("L", "H")}
        out[setting] = _manifest(setting, train, val, ids[reg != "I"], [], n_transitions, n_transitions, seed,
                                 ood_controls=[name], interval_in=list(INTERVAL_IN), test_groups=groups)
    ra, rc = regions["flux_ar_plus"], regions["flux_cl_plus"]
    a_in, c_in = ra == "I", rc == "I"
    train, val = _split_pool(ids[a_in & c_in], np.random.default_rng(seed))
    groups = {g1 + g2: sorted(int(c) for c in ids[(ra == g1) & (rc == g2)]) for g1 in "LH" for g2 in "LH"}
    out["ood-joint"] = _manifest("ood-joint", train, val, ids[~a_in & ~c_in], ids[a_in ^ c_in], n_transitions,
                                 n_transitions, seed, ood_controls=list(OOD_CONTROLS["ood-joint"]),
                                 interval_in=list(INTERVAL_IN), test_groups=groups)

    row_of = {int(c): r for r, c in enumerate(ids)}
    for m in out.values():
        rows = [row_of[c] for c in m["train"]]
        subsets = data_efficiency_subsets(m, raw[rows], m["train"])
        m["data_efficiency"] = {k: v for k, v in subsets.items()}
    return out


def data_efficiency_subsets(
    manifest: dict,
    train_raw=None,
    train_ids=None,
    *,
    fractions=DATA_EFFICIENCY_FRACTIONS,
    seed: int = 0,
) -> dict[str, list[int]]:
    """Nested training subsets {"0.1": ids, "0.2": ids, "0.5": ids, "1.0": ids} ([supp_data_efficiency]).

    Args:
        manifest: a split manifest; if ``train_raw`` is None its stored "data_efficiency" key is returned.
        train_raw: (n, 14) raw controls of the training cases (row k = ``train_ids[k]``).
        train_ids: (n,) their ids (default: ``manifest["train"]`` in order).
        fractions: increasing fractions in (0, 1].
        seed: sampling seed (paper: 0).
    """
    if train_raw is None:
        if "data_efficiency" not in manifest:
            raise ValueError(f"manifest {manifest.get('setting')!r} has no stored 'data_efficiency' subsets; "
                             "pass train_raw (the training cases' raw controls) to compute them")
        return {str(k): [int(c) for c in v] for k, v in manifest["data_efficiency"].items()}
    ids = np.asarray(manifest["train"] if train_ids is None else train_ids, dtype=np.int64)
    raw = np.asarray(train_raw, dtype=np.float64).reshape(-1, N_CONTROLS)
    if raw.shape[0] != ids.shape[0]:
        raise ValueError(f"{raw.shape[0]} control rows for {ids.shape[0]} training ids")
    fr = [float(f) for f in fractions]
    if any(not 0 < f <= 1 for f in fr) or fr != sorted(fr):
        raise ValueError(f"fractions must be increasing in (0, 1]; got {fractions}")
    n = len(ids)
    if n == 0:
        return {_key(f): [] for f in fr}
    t = transform(raw)
    cols = [CONTROL_INDEX["flux_ar_plus"], CONTROL_INDEX["flux_cl_plus"]]
    bins = []
    for j in cols:
        lo, hi = t[:, j].min(), t[:, j].max()
        b = np.floor((t[:, j] - lo) / max(hi - lo, 1e-300) * 3).astype(int) if hi > lo else np.zeros(n, int)
        bins.append(np.clip(b, 0, 2))
    stratum = bins[0] * 3 + bins[1]  # (n,) in 0..8
    rng = np.random.default_rng(seed)
    members = [rng.permutation(ids[stratum == s]) for s in range(9)]
    sizes = np.array([len(m) for m in members], dtype=float)
    k = np.zeros(9, dtype=int)
    out = {}
    for f in fr:
        target = min(n, max(1, int(math.floor(f * n + 0.5))))
        while k.sum() < target:
            deficit = np.where(k < sizes, f * sizes - k, -np.inf)
            k[int(np.argmax(deficit))] += 1
        out[_key(f)] = sorted(int(c) for s in range(9) for c in members[s][: k[s]])
    return out


def _key(f: float) -> str:
    return f"{f:.1f}" if round(f, 1) == f else f"{f:g}"


def write_manifests(manifests: dict[str, dict], out_dir: str | Path) -> list[Path]:
    """Write ``<out_dir>/<setting>.json`` for each manifest; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for setting, m in manifests.items():
        p = out / f"{setting}.json"
        p.write_text(json.dumps(m, indent=1))
        paths.append(p)
    return paths


def load_manifest(path_or_dir: str | Path, setting: str | None = None) -> dict:
    """Load a manifest from a JSON file, or ``<dir>/<setting>.json``. ValueError if absent or malformed."""
    p = Path(path_or_dir)
    if p.is_dir() or (setting is not None and p.suffix != ".json"):
        if setting not in SETTINGS:
            raise ValueError(f"unknown setting {setting!r}; expected one of {SETTINGS}")
        p = p / f"{setting}.json"
    if not p.is_file():
        raise ValueError(f"no split manifest {p}; make the manifests with `nemsim splits --data FILE.h5 "
                         f"--out {p.parent}` (or --design FILE.csv)")
    try:
        m = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"{p}: not a JSON split manifest ({exc}); remake it with `nemsim splits`") from None
    if not isinstance(m, dict):
        raise ValueError(f"{p}: not a split manifest (a JSON {type(m).__name__}, not an object)")
    missing = [k for k in ("setting", "train", "val", "test", "unused", "visible_transitions") if k not in m]
    if missing:
        raise ValueError(f"{p}: manifest lacks {missing}")
    if setting is not None and m["setting"] != setting:
        raise ValueError(f"{p}: manifest is for setting {m['setting']!r}, not {setting!r}")
    return m


def resolve_manifest(
    setting: str, data_path: str | Path, case_ids, controls_raw, n_transitions: int,
    splits: str | Path | None = None,
) -> tuple[dict, str]:
    """The manifest of ``setting`` for a trajectory file, and where it came from (for the log).

    Order: ``<splits>/<setting>.json`` if ``splits`` is given; else ``<data dir>/splits/<setting>.json`` if
    present; else computed from the file's own controls and case ids with ``make_manifests`` (seed 0).
    A manifest read from disk must fit the file: ValueError if any train/val/test id is not one of
    ``case_ids``, saying how to make manifests that fit.

    Args:
        setting: one of SETTINGS.
        data_path: the trajectory file (names it in messages; its folder holds the default ``splits/``).
        case_ids: (N,) the file's case ids; controls_raw: (N, 14) its raw controls.
        n_transitions: transitions per trajectory of the file's scene.
        splits: a directory of ``<setting>.json`` manifests (from ``nemsim splits``), or None.
    """
    if setting not in SETTINGS:
        raise ValueError(f"unknown setting {setting!r}; expected one of {SETTINGS}")
    data_path = Path(data_path)
    directory = Path(splits) if splits is not None else data_path.parent / "splits"
    if splits is None and not (directory / f"{setting}.json").is_file():
        manifests = make_manifests(controls_raw, case_ids, n_transitions=n_transitions)
        return manifests[setting], f"computed from the controls of {data_path}"
    manifest = load_manifest(directory, setting)
    known = {int(c) for c in np.asarray(case_ids).reshape(-1)}
    foreign = [int(c) for part in ("train", "val", "test") for c in manifest[part] if int(c) not in known]
    if foreign:
        default = " (the default for --splits)" if splits is None else ""
        raise ValueError(
            f"{directory / (setting + '.json')}{default} does not fit {data_path}: {len(foreign)} of its "
            "train/val/test "
            f"case ids (e.g. {foreign[:3]}) are not in the file; make manifests for this file with "
            f"`nemsim splits --data {data_path} --out DIR` and pass --splits DIR"
        )
    return manifest, str(directory / f"{setting}.json")


def complete_cases(manifest: dict, case_ids, complete) -> tuple[dict, dict[str, list[int]]]:
    """The manifest restricted to the cases a trajectory file holds complete, and what was dropped.

    For a file still being generated (a prefix of a design, e.g. the first 120 of 500 ``paper`` cases): its
    train/val/test lists keep their order and lose the cases that are absent or unfinished. The caller
    says so (``nemsim train --complete-only`` logs the counts): nothing is dropped silently.

    Args:
        manifest: split manifest (``load_manifest``).
        case_ids: (N,) the file's case ids; complete: (N,) its completion flags.
    Returns:
        (manifest copy with train/val/test filtered, {split: dropped case ids} for train, val and test).
    """
    done = {int(c) for c, ok in zip(np.asarray(case_ids).reshape(-1), np.asarray(complete).reshape(-1),
                                    strict=True) if ok}
    out, dropped = dict(manifest), {}
    for split in ("train", "val", "test"):
        ids = [int(c) for c in manifest.get(split, [])]
        out[split] = [c for c in ids if c in done]
        dropped[split] = [c for c in ids if c not in done]
    return out, dropped


def split_table(manifests: dict[str, dict]) -> str:
    """The set sizes as a text table (columns of tab:supp_split_summary)."""
    head = (f"{'Setting':<11} {'Train':>5} {'Val':>5} {'Test':>5} {'Unused':>6} {'Trans/traj':>10} "
            f"{'Train samples':>13}")
    lines = [head, "-" * len(head)]
    for s in SETTINGS:
        if s not in manifests:
            continue
        m = manifests[s]
        v = m["visible_transitions"]
        lines.append(f"{s:<11} {len(m['train']):>5} {len(m['val']):>5} {len(m['test']):>5} "
                     f"{len(m['unused']):>6} {v:>10} {len(m['train']) * v:>13,}")
    j = manifests.get("ood-joint", {}).get("test_groups")
    if j:
        groups = ", ".join(f"({g[0]},{g[1]}) {len(v)}" for g, v in j.items())
        lines.append(f"ood-joint test (Ar+, Cl+): {groups}")
    return "\n".join(lines)
