"""Streaming torch datasets over a trajectory file (``nemsim.data.hdf5``).

``TransitionDataset`` yields one-step samples (x_t, u_t, x_{t+1}) (eq:supp_transition_sample) of the cases of
one split, restricted to the first ``visible_transitions`` transitions of each case
(eq:supp_temporal_training_set). ``TrajectoryDataset`` yields whole trajectories for autoregressive rollouts.

Nothing but the (tiny) controls and ids is held in memory: each item reads its states from disk. The h5py
handle is opened lazily on first access in each process, so a dataset built in the parent can be handed to
DataLoader workers (fork or spawn); the handle is never pickled. A ``paper`` file (~70 GB raw) therefore
streams with O(1) memory.

Recipes: if the file has ``controls_raw_schedule`` (N, T-1, 14), u_t is that transition's control;
otherwise u_t is the case's constant control (the benchmark). Controls are normalized with the fixed bounds
(eq:supp_control_normalization).

Choices where the paper is silent: items are ordered case-major (case, t) in manifest order; cases without
their completion flag are refused (ValueError naming them) rather than silently skipped.

Scene symmetry ("model only what a scene needs", ``nemsim.symmetry``): a ``TransitionDataset`` can average
every state it yields over the scene's symmetries (``symmetrize``: the mean of a Monte Carlo state's 8
images, a quieter target of the same mean evolution) and yield the fundamental domain's quadrant
(``quarter``: what a quarter-domain model trains on), or a trench's cross-section (``section``: the mean
over y and the x mirror, 2 rows of the low half of x; what a section-domain model trains on).

``MemoryTransitions`` holds the training items of one or more such datasets in memory instead (the input
pipeline that keeps up with a GPU): each trajectory is read and inflated once on every core
(``nemsim.data.hdf5.read_cases``), symmetrized and folded as asked on the device that holds it, and kept
as float16 (on the training device when it fits); a batch is a gather of whole windows by index, no
per-sample Python work (``__getitems__``). The decoded states are kept for the next set of the same cases
and shape in this process (the stages of a recipe share one decode; ``decoded_states``).
``MemoryTrajectories`` does the same for whole trajectories (the validation rollouts of a training run).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import ConcatDataset, Dataset

from nemsim.data.hdf5 import open_trajectories
from nemsim.symmetry import FieldFold, section_mean, symmetrize

SPLITS = ("train", "val", "test", "unused")


def _select_rows(tf, manifest: dict | None, split: str) -> np.ndarray:
    """Row indices (in manifest order) of the split's case ids; all complete rows if manifest is None."""
    if manifest is None:
        return np.flatnonzero(tf.complete)
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
    ids = [int(c) for c in manifest.get(split, [])]
    missing = [c for c in ids if c not in tf._row_of]
    if missing:
        raise ValueError(f"{len(missing)} case ids of split {split!r} are not in {tf.path}: {missing[:10]}")
    rows = np.array([tf._row_of[c] for c in ids], dtype=np.int64)
    unfinished = [int(tf.case_ids[r]) for r in rows if not tf.complete[r]]
    if unfinished:
        raise ValueError(f"{len(unfinished)} cases of split {split!r} are unfinished in {tf.path}: "
                         f"{unfinished[:10]}; finish generation (rerun to resume) first")
    return rows


class _H5Backed(Dataset):
    """Shared lazy-handle logic: ``self._states`` is (re)opened per process."""

    def __init__(self, path: str | Path, manifest: dict | None, split: str) -> None:
        self.path = Path(path)
        self.split = split
        with open_trajectories(self.path) as tf:
            self.scene = tf.scene
            self.feature_kind = tf.feature_kind  # "hole" or "trench" (the file's features)
            self.rows = _select_rows(tf, manifest, split)  # (n,) file rows
            self.case_ids = tf.case_ids[self.rows].astype(np.int64)  # (n,)
            self.n_states = tf.n_states
            # (n, T-1, 14) float32 normalized per-transition controls (constant ones broadcast, no copy)
            if tf.controls_raw_schedule is not None:
                from nemsim.controls import to_normalized

                self.u = to_normalized(tf.controls_raw_schedule[self.rows]).astype(np.float32)
            else:
                const = tf.controls_normalized[self.rows].astype(np.float32)  # (n, 14)
                shape = (len(self.rows), self.n_states - 1, const.shape[1])  # (n, T-1, 14)
                self.u = np.broadcast_to(const[:, None, :], shape)
        self._file = None
        self._states = None
        self._pid = None

    def _dataset(self):
        if self._states is None or self._pid != os.getpid():
            import h5py

            self._file = h5py.File(self.path, "r")
            self._states = self._file["states"]  # (N, T, 2, D, H, W), lazy
            self._pid = os.getpid()
        return self._states

    def transform(self, states: torch.Tensor) -> torch.Tensor:
        """States (..., C, D, H, W) as the items carry them (here unchanged; ``TransitionDataset`` may
        symmetrize and fold them)."""
        return states

    def close(self) -> None:
        if self._file is not None and self._pid == os.getpid():
            self._file.close()
        self._file = self._states = self._pid = None

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_file"] = state["_states"] = state["_pid"] = None
        return state

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown; nothing to report
            pass


class TransitionDataset(_H5Backed):
    """One-step samples of a split, streamed from disk.

    Args:
        path: trajectory ``.h5``.
        manifest: split manifest dict (``nemsim.data.splits``) or None for every complete case.
        split: "train" | "val" | "test" | "unused".
        visible_transitions: only t = 0..V-1 of each case (Vis-p%); None = all T-1 transitions.
        unroll: transitions per item (n). 1 = the paper's one-step samples; n > 1 gives n consecutive
            transitions, t = 0..V-n: the k-step targets of a model with ``steps_per_call`` k, over
            ``TrainConfig.unroll_steps`` U calls (n = U·k; k = 1, U > 1: the pushforward loss).
    Items:
        unroll 1: (x_t (2, D, H, W) float32, u_t (14,) float32 normalized, x_{t+1} (2, D, H, W) float32);
        unroll n: (x_t (2, D, H, W), u_{t..t+n-1} (n, 14), x_{t+1..t+n} (n, 2, D, H, W)).
    """

    def __init__(
        self,
        path: str | Path,
        manifest: dict | None = None,
        split: str = "train",
        visible_transitions: int | None = None,
        unroll: int = 1,
        symmetrize: bool = False,
        quarter: bool = False,
        section: bool = False,
    ) -> None:
        super().__init__(path, manifest, split)
        if quarter and section:
            raise ValueError("a training set is folded to a quarter or to a cross-section, not both")
        if (symmetrize or quarter) and not section and self.scene.symmetry == "none":
            raise ValueError(f"{self.path}: scene {self.scene.name!r} declares no symmetry, so its states "
                             "cannot be symmetrized or folded to a quarter domain")
        if section and self.feature_kind != "trench":
            raise ValueError(f"{self.path}: a cross-section is a trench's; the file holds "
                             f"{self.feature_kind!r} features")
        self.symmetrize, self.quarter, self.section = bool(symmetrize), bool(quarter), bool(section)
        n = int(self.scene.field_shape[-1])
        self._fold = FieldFold("section", n) if section else FieldFold("quarter", n) if quarter else None
        n_trans = self.n_states - 1
        v = n_trans if visible_transitions is None else int(visible_transitions)
        if not 1 <= v <= n_trans:
            raise ValueError(f"visible_transitions={visible_transitions} must be in [1, {n_trans}]")
        if not 1 <= unroll <= v:
            raise ValueError(f"unroll={unroll} must be in [1, visible transitions {v}]")
        self.visible_transitions = v
        self.unroll = int(unroll)
        self._starts = v - self.unroll + 1  # start times per case

    def __len__(self) -> int:
        return len(self.rows) * self._starts

    def index(self, i: int) -> tuple[int, int]:
        """(case id, t) of item i."""
        k, t = divmod(int(i), self._starts)
        return int(self.case_ids[k]), t

    def __getitem__(self, i: int):
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} transitions")
        i = int(i) % len(self)
        k, t = divmod(i, self._starts)
        n = self.unroll
        run = self._dataset()[int(self.rows[k]), t : t + n + 1]  # (n+1, C, D, H, W): x_t .. x_{t+n}
        run = self.transform(torch.from_numpy(np.ascontiguousarray(run, dtype=np.float32)))
        if n == 1:
            return run[0], torch.from_numpy(np.array(self.u[k, t])), run[1]
        return run[0], torch.from_numpy(np.array(self.u[k, t : t + n])), run[1:]


    def transform(self, states: torch.Tensor) -> torch.Tensor:
        """States (..., C, D, H, W) as the items carry them: symmetrized and/or folded (module docstring; a
        cross-section always averaged over the trench's symmetries first)."""
        if self.section:
            states = section_mean(states)
        elif self.symmetrize:
            states = symmetrize(states)
        return self._fold.fold(states).contiguous() if self._fold is not None else states


class TransitionSets(ConcatDataset):
    """Several ``TransitionDataset`` s trained on as one (``nemsim train --extra-data``): items of the first,
    then of the next, ...; all must have the same ``unroll``."""

    def __init__(self, sets: list[TransitionDataset]) -> None:
        unrolls = {s.unroll for s in sets}
        if len(unrolls) != 1:
            raise ValueError(f"transition sets with different unroll {sorted(unrolls)}")
        super().__init__(sets)
        self.unroll = unrolls.pop()


class TrajectoryDataset(_H5Backed):
    """Whole trajectories of a split for rollouts.

    Items: (case_id int, states (T, 2, D, H, W) float32 tensor with T = n_states = transitions + 1,
    u (T-1, 14) float32 normalized tensor).
    """

    def __init__(self, path: str | Path, manifest: dict | None = None, split: str = "test") -> None:
        super().__init__(path, manifest, split)

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, i: int):
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} trajectories")
        k = int(i) % len(self)
        states = np.asarray(self._dataset()[int(self.rows[k])], dtype=np.float32)  # (T, 2, D, H, W)
        return int(self.case_ids[k]), torch.from_numpy(states), torch.from_numpy(np.array(self.u[k]))


class PairDataset(Dataset):
    """Sweep pairs of a trajectory file (``nemsim design --kind pairs``) as paired k-step samples.

    The pairs are the cases that share a stored simulator seed, two by two (``nemsim.sim.generate``: the
    ``seed_id`` column); cases with a seed of their own are not used, and a seed held by more than two
    cases is refused. Item (pair p, start t) is the two cases' items at the same t of a
    ``TransitionDataset`` over the whole file (its ``unroll`` and ``visible_transitions``), stacked on a new
    leading axis: x (2, 2, D, H, W), u (2, n, 14), y (2, n, 2, D, H, W) with n = ``unroll`` (n = 1:
    u (2, 14), y (2, 2, D, H, W)); ``symmetrize`` and ``quarter`` shape the states as the training items'
    (``TransitionDataset``), so the pairs join a quarter-domain model's batches.
    Ordering: pair-major (p, t), pairs in the order of their first case's row.
    """

    def __init__(self, path: str | Path, unroll: int = 1, visible_transitions: int | None = None,
                 symmetrize: bool = False, quarter: bool = False, section: bool = False) -> None:
        self.base = TransitionDataset(path, None, "train", visible_transitions=visible_transitions,
                                      unroll=unroll, symmetrize=symmetrize, quarter=quarter, section=section)
        self.scene, self.unroll = self.base.scene, self.base.unroll
        with open_trajectories(self.base.path) as tf:
            file_pairs = tf.seed_pairs()  # (P, 2) file rows
        k_of = {int(r): k for k, r in enumerate(self.base.rows)}
        self.pairs = np.array([[k_of[a], k_of[b]] for a, b in file_pairs], dtype=np.int64).reshape(-1, 2)
        if not len(self.pairs):
            raise ValueError(f"{path}: no two complete cases share a simulator seed, so it holds no sweep "
                             "pair; make one with `nemsim design --kind pairs` and `nemsim generate "
                             "--controls`")
        self._starts = self.base._starts

    def __len__(self) -> int:
        return len(self.pairs) * self._starts

    def case_ids(self, p: int) -> tuple[int, int]:
        """The two case ids of pair p."""
        a, b = self.pairs[p]
        return int(self.base.case_ids[a]), int(self.base.case_ids[b])

    def __getitem__(self, i: int):
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} pair samples")
        p, t = divmod(int(i) % len(self), self._starts)
        a, b = (self.base[int(k) * self._starts + t] for k in self.pairs[p])
        return tuple(torch.stack([ta, tb]) for ta, tb in zip(a, b, strict=True))

    def close(self) -> None:
        self.base.close()


class MemoryTransitions(Dataset):
    """The items of ``TransitionDataset`` s (in order, as ``TransitionSets`` has them) held in memory
    (module docstring): states (N, T, C, D, H', W') float16 and controls (N, T-1, 14) float32 on ``device``.

    ``dataset[i]`` is one item as the streamed sets give it; ``dataset.__getitems__(indices)`` the batch
    (x (B, C, D, H', W'), u (B, n, 14) or (B, 14), y (B, n, C, D, H', W') or (B, C, D, H', W')), float32,
    which a ``DataLoader`` hands on unchanged with ``collate_fn=as_batch``.
    """

    batched = True  # __getitems__ returns a whole batch (the training loader's collate is ``as_batch``)

    def __init__(self, sets: list[TransitionDataset], device: torch.device | str = "cpu",
                 progress: bool = False) -> None:
        if not sets:
            raise ValueError("no transition datasets to hold in memory")
        first = sets[0]
        if any(s.unroll != first.unroll or s._starts != first._starts for s in sets):
            raise ValueError("the sets held in memory must have the same unroll and visible transitions")
        self.unroll, self._starts = first.unroll, first._starts
        self.n_states = first.n_states
        self.device = torch.device(device)
        self.states, self.u = decoded_states(sets, self.device, progress, "decode training set")
        self._offsets = torch.arange(self.unroll + 1, device=self.device)  # (n+1,)

    @staticmethod
    def state_shape(sets: list[_H5Backed]) -> tuple[int, ...]:
        """(C, D, H', W') of one state as ``sets`` yield it (after their transform)."""
        return tuple(sets[0].transform(torch.zeros(1, *sets[0].scene.state_shape)).shape[1:])

    @classmethod
    def nbytes_of(cls, sets: list[_H5Backed]) -> int:
        """Bytes the states of ``sets`` take in memory (float16, after their transform)."""
        return sum(len(s.rows) for s in sets) * sets[0].n_states * int(np.prod(cls.state_shape(sets))) * 2

    def __len__(self) -> int:
        return int(self.states.shape[0]) * self._starts

    def __getitem__(self, i: int):
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} transitions")
        x, u, y = self.__getitems__([int(i) % len(self)])
        return x[0], u[0], y[0]

    def __getitems__(self, indices) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        idx = torch.as_tensor(indices, dtype=torch.long, device=self.device)  # (B,)
        case, t = idx // self._starts, idx % self._starts
        times = t[:, None] + self._offsets  # (B, n+1)
        run = self.states[case[:, None], times].float()  # (B, n+1, C, D, H', W')
        u = self.u[case[:, None], times[:, :-1]]  # (B, n, 14)
        if self.unroll == 1:
            return run[:, 0], u[:, 0], run[:, 1]
        return run[:, 0], u, run[:, 1:]


class MemoryTrajectories(Dataset):
    """The trajectories of a ``TrajectoryDataset`` held in memory as float16 (on ``device``), items as it
    gives them: (case_id, states (T, 2, D, H, W) float32, u (T-1, 14) float32), on ``device``."""

    def __init__(self, base: TrajectoryDataset, device: torch.device | str = "cpu",
                 progress: bool = False) -> None:
        self.case_ids = base.case_ids
        self.device = torch.device(device)
        self.states, self.u = decoded_states([base], self.device, progress, f"decode {base.split} set")

    def __len__(self) -> int:
        return int(self.states.shape[0])

    def __getitem__(self, i: int):
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} trajectories")
        k = int(i) % len(self)
        return int(self.case_ids[k]), self.states[k].float(), self.u[k]


_DECODED: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}  # recent decodes (``decoded_states``)
KEEP_DECODED = 2  # decodes kept: a run's training set and its validation set


def decoded_states(sets: list, device: torch.device, progress: bool = False,
                   desc: str = "decode") -> tuple[torch.Tensor, torch.Tensor]:
    """(states (N, T, C, D, H', W') float16, u (N, T-1, 14) float32) on ``device`` of the cases of ``sets``
    (``_H5Backed`` datasets; states shaped by each set's ``transform``), in order.

    The trajectories are inflated on every core (``read_cases``) and shaped on ``device`` (float32 there,
    stored float16). The last ``KEEP_DECODED`` results are kept for the same files (path, size,
    modification time), rows, shaping and device, so the next stage of a recipe reuses them rather than
    decoding again.
    """
    from nemsim.data.hdf5 import read_cases

    def key_of(s) -> tuple:
        st = s.path.stat()
        return (str(s.path.resolve()), st.st_size, st.st_mtime_ns, s.rows.tobytes(),
                getattr(s, "symmetrize", False), getattr(s, "quarter", False), getattr(s, "section", False))

    key = (tuple(key_of(s) for s in sets), str(device))
    if key in _DECODED:
        _DECODED[key] = _DECODED.pop(key)  # the most recently used last
        return _DECODED[key]
    while len(_DECODED) >= KEEP_DECODED:  # the least recently used goes before this one is made
        del _DECODED[next(iter(_DECODED))]
    first = sets[0]
    n_cases = sum(len(s.rows) for s in sets)
    shape = MemoryTransitions.state_shape(sets)
    states = torch.empty((n_cases, first.n_states, *shape), dtype=torch.float16, device=device)
    u = torch.empty((n_cases, first.n_states - 1, first.u.shape[-1]), dtype=torch.float32, device=device)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_cases, desc=desc, unit="case", leave=False)
    g = 0
    for s in sets:
        for k, traj in read_cases(s.path, s.rows):
            x = torch.from_numpy(traj).to(device, non_blocking=False)  # (T, C, D, H, W), stored dtype
            states[g].copy_(s.transform(x.float()))
            u[g].copy_(torch.from_numpy(np.array(s.u[k], dtype=np.float32)))
            g += 1
            if bar is not None:
                bar.update()
        s.close()
    if bar is not None:
        bar.close()
    _DECODED[key] = (states, u)
    return states, u


def as_batch(batch):
    """The collate of a ``MemoryTransitions`` loader: its ``__getitems__`` already made the batch."""
    return batch
