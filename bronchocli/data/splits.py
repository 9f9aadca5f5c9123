"""The two population schemes: which trajectories train, validate and test (leak-free, reproducible).

``POPULATIONS`` maps each name to its builder; ``make_split`` picks one.

* ``personalized`` (intra-patient): for every patient and lobe, disjoint
  train / val / test trajectories (``splits.train/val/test``, paper 15/3/3),
  drawn without replacement. Trajectories beyond that total are left out.
  With fewer than the total but at least 3, the counts shrink in proportion:
  test = max(1, floor(n*test/total)), val likewise, train = the rest (at least
  1); with fewer than 3 it is an error naming the patient, lobe and count.
* ``cross-subject`` (leave one patient out): the fold is the held-out patient,
  whose trajectories are all test and nothing else; for every other patient
  and lobe ``splits.cross_subject_val`` trajectories validate (at most all but
  one, so every lobe keeps a training trajectory) and the rest train.

Draws use ``numpy.random.default_rng([splits.seed, sha256(patient/lobe)])``
over the trajectories in natural id order, so a split depends only on the
config and the dataset, never on the process, platform or Python's ``hash``.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ..config import Splits
from ..errors import ConfigError, DataError
from ..io import atomic_path
from .reader import Dataset, Trajectory, natural_key

PARTS: tuple[str, ...] = ("train", "val", "test")
MANIFEST_COLUMNS: tuple[str, ...] = ("patient", "lobe", "trajectory", "split")


@dataclass(frozen=True)
class Split:
    """Train / val / test trajectories of one population (and fold), each list in dataset order."""

    population: str
    fold: str | None
    train: list[Trajectory]
    val: list[Trajectory]
    test: list[Trajectory]
    notes: tuple[str, ...] = ()  # where the configured counts could not be met, and what was done

    def parts(self) -> dict[str, list[Trajectory]]:
        return {"train": self.train, "val": self.val, "test": self.test}

    def frame_indices(self, part: str) -> np.ndarray:
        """Global frame indices of every trajectory in ``part`` (e.g. for channel_stats on 'train')."""
        trajs = self.parts()[part]
        return np.concatenate([t.frame_index for t in trajs]) if trajs else np.zeros(0, dtype=np.int64)

    def manifest(self) -> pd.DataFrame:
        """One row per used trajectory: patient, lobe, trajectory, split (train, val, test)."""
        rows = [(t.patient, t.lobe, t.traj_id, part) for part, trajs in self.parts().items() for t in trajs]
        return pd.DataFrame(rows, columns=list(MANIFEST_COLUMNS))

    def write_manifest(self, path: str | os.PathLike) -> Path:
        """Write :meth:`manifest` as CSV, atomically."""
        with atomic_path(path) as tmp:
            self.manifest().to_csv(tmp, index=False)
        return Path(path)

    def counts(self) -> pd.DataFrame:
        """Trajectories, frames and pairs per split."""
        rows = [(part, len(trajs), sum(t.n_frames for t in trajs), sum(t.n_pairs for t in trajs))
                for part, trajs in self.parts().items()]
        return pd.DataFrame(rows, columns=["split", "trajectories", "frames", "pairs"])


def stable_hash(*parts: str) -> int:
    """A 64-bit integer from strings, identical in every process (unlike ``hash()``)."""
    digest = hashlib.sha256("\0".join(parts).encode("utf-8")).digest()
    return int.from_bytes(digest[:8], "little")


def shuffled(trajs: Sequence[Trajectory], seed: int, patient: str, lobe: str) -> list[Trajectory]:
    """The trajectories of one patient and lobe in a random order fixed by (seed, patient, lobe)."""
    ordered = sorted(trajs, key=lambda t: natural_key(t.traj_id))
    rng = np.random.default_rng([seed, stable_hash(patient, lobe)])
    return [ordered[i] for i in rng.permutation(len(ordered))]


def groups(dataset: Dataset) -> dict[tuple[str, str], list[Trajectory]]:
    """Trajectories by (patient, lobe), in dataset order."""
    out: dict[tuple[str, str], list[Trajectory]] = {}
    for t in dataset.trajectories:
        out.setdefault((t.patient, t.lobe), []).append(t)
    return out


def personalized_counts(n: int, train: int, val: int, test: int, where: str) -> tuple[int, int, int]:
    """(train, val, test) counts for ``n`` trajectories; the fallback rule is in the module docstring."""
    total = train + val + test
    if n >= total:
        return train, val, test
    if n < 3:
        raise DataError(f"personalized split: {where} has {n} trajector{'y' if n == 1 else 'ies'}; "
                        f"at least 3 are needed (one each for train, val and test; configured {train}/{val}/{test})")
    te, va = max(1, n * test // total), max(1, n * val // total)
    while n - te - va < 1:  # keep a training trajectory: take from the larger of val/test
        if va >= te:
            va -= 1
        else:
            te -= 1
    return n - te - va, va, te


def _notes(by_message: dict[str, list[str]]) -> tuple[str, ...]:
    """One note per distinct outcome, naming the patient/lobe groups it applies to."""
    out = []
    for message, where in by_message.items():
        shown = ", ".join(where[:4]) + (f" and {len(where) - 4} more" if len(where) > 4 else "")
        out.append(f"{shown}: {message}")
    return tuple(out)


def _order(dataset: Dataset, chosen: set[int]) -> list[Trajectory]:
    return [t for t in dataset.trajectories if id(t) in chosen]


def personalized(dataset: Dataset, fold: str | None, splits: Splits) -> Split:
    """Per patient and lobe: disjoint train / val / test trajectories."""
    if fold is not None:
        raise ConfigError(f"population personalized takes no fold (got {fold!r}); folds are for cross-subject")
    chosen: dict[str, set[int]] = {p: set() for p in PARTS}
    notes: dict[str, list[str]] = {}
    configured = f"{splits.train}/{splits.val}/{splits.test}"
    for (patient, lobe), trajs in groups(dataset).items():
        where = f"{patient}/{lobe}"
        counts = personalized_counts(len(trajs), splits.train, splits.val, splits.test, where)
        if len(trajs) != splits.train + splits.val + splits.test:
            unused = len(trajs) - sum(counts)
            notes.setdefault(f"{len(trajs)} trajectories -> train/val/test {'/'.join(map(str, counts))} "
                             + (f"({unused} unused)" if unused else f"(fewer than the configured {configured})"),
                             []).append(where)
        order = shuffled(trajs, splits.seed, patient, lobe)
        n_tr, n_va, n_te = counts
        chosen["test"].update(id(t) for t in order[:n_te])
        chosen["val"].update(id(t) for t in order[n_te: n_te + n_va])
        chosen["train"].update(id(t) for t in order[n_te + n_va: n_te + n_va + n_tr])
    return Split("personalized", None, *(_order(dataset, chosen[p]) for p in PARTS), notes=_notes(notes))


def cross_subject(dataset: Dataset, fold: str | None, splits: Splits) -> Split:
    """Leave one patient out: ``fold`` is the test patient; validation comes from the others."""
    if fold is None or fold not in dataset.patients:
        what = "needs a fold" if fold is None else f"fold {fold!r} is not a patient of {dataset.root}"
        raise ConfigError(f"cross-subject {what}: the held-out patient, one of {', '.join(dataset.patients)}")
    if len(dataset.patients) < 2:
        raise DataError(f"cross-subject needs at least 2 patients; {dataset.root} has {len(dataset.patients)}")
    chosen: dict[str, set[int]] = {p: set() for p in PARTS}
    notes: dict[str, list[str]] = {}
    for (patient, lobe), trajs in groups(dataset).items():
        if patient == fold:
            chosen["test"].update(id(t) for t in trajs)
            continue
        n_val = min(splits.cross_subject_val, len(trajs) - 1)
        if n_val < splits.cross_subject_val:
            notes.setdefault(f"{len(trajs)} trajector{'y' if len(trajs) == 1 else 'ies'} -> {n_val} val "
                             f"(configured {splits.cross_subject_val}), {len(trajs) - n_val} train",
                             []).append(f"{patient}/{lobe}")
        order = shuffled(trajs, splits.seed, patient, lobe)
        chosen["val"].update(id(t) for t in order[:n_val])
        chosen["train"].update(id(t) for t in order[n_val:])
    return Split("cross-subject", fold, *(_order(dataset, chosen[p]) for p in PARTS), notes=_notes(notes))


POPULATIONS: dict[str, Callable[[Dataset, str | None, Splits], Split]] = {
    "personalized": personalized,
    "cross-subject": cross_subject,
}


def make_split(dataset: Dataset, population: str, fold: str | None, splits: Splits) -> Split:
    """The split of ``dataset`` for ``population`` (and ``fold``, the held-out patient for cross-subject)."""
    try:
        builder = POPULATIONS[population]
    except KeyError:
        raise ConfigError(f"population {population!r}: must be one of {', '.join(POPULATIONS)}") from None
    return builder(dataset, fold, splits)


def limit_train(split: Split, per_group: int | None, seed: int) -> Split:
    """The split with at most ``per_group`` training trajectories per (patient, lobe); val and test unchanged.

    The kept ones are the first of a fixed random order per group, so smaller
    limits are subsets of larger ones (nested training sets for a learning curve).
    """
    if per_group is None:
        return split
    by_group: dict[tuple[str, str], list[Trajectory]] = {}
    for t in split.train:
        by_group.setdefault((t.patient, t.lobe), []).append(t)
    keep: set[int] = set()
    short = []
    for (patient, lobe), trajs in by_group.items():
        order = shuffled(trajs, seed, patient, f"{lobe}/train-limit")
        keep.update(id(t) for t in order[:per_group])
        if len(trajs) < per_group:
            short.append(f"{patient}/{lobe}")
    notes = split.notes
    if short:
        notes += _notes({f"fewer than train_trajectories={per_group} training trajectories: all used": short})
    train = [t for t in split.train if id(t) in keep]
    return Split(split.population, split.fold, train, split.val, split.test, notes=notes)


def read_manifest(path: str | os.PathLike) -> pd.DataFrame:
    """A manifest written by :meth:`Split.write_manifest` (ids kept as text)."""
    return pd.read_csv(path, dtype=str)
