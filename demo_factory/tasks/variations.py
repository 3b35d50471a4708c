"""Deterministic enumeration of variations (word sequences) and their disjoint train/test split.

Two schemes:

- ``hiveformer_sequences``: the HiveFormer authors' numbering (their RLBench fork's
  ``PushButtons3.sequences`` / ``Tower3.sequences``), so that variation *i* here is variation *i*
  in the paper; there, variations 0-99 are trained on and 100-199 are the unseen test variations.
- ``enumerate_sequences`` + ``split_variations``: every sequence, shortest first, dealt at random
  to train and test with a per-task seed (the tasks the paper has no numbering for).
"""

from __future__ import annotations

import itertools
import random
from dataclasses import dataclass

import numpy as np

SPLITS = ("train", "test")


@dataclass(frozen=True)
class Variation:
    """An ordered sequence of palette words; ``id`` is its index in the task's full enumeration.

    The words are colours for colour tasks, or another kind of goal (a slot, a shelf, a tap): the
    task's ``variation_kind`` says which. Files keep their own keys (``colours`` in instruction files).
    """

    id: int
    words: tuple[str, ...]

    @property
    def name(self) -> str:
        return ",".join(self.words)


def enumerate_sequences(palette: tuple[str, ...], max_length: int) -> list[Variation]:
    """All ordered sequences of 1..max_length distinct palette colours, shortest first."""
    sequences = [
        seq for n in range(1, max_length + 1) for seq in itertools.permutations(palette, n)
    ]
    return [Variation(i, seq) for i, seq in enumerate(sequences)]


@dataclass(frozen=True)
class PaperNumbering:
    """How the HiveFormer authors' RLBench fork numbers one task's variations.

    ``per_length`` cuts each length's shuffled list, ``total`` the shuffled concatenation; the
    fork's train variations are ids ``0 .. n_train - 1`` and its test variations the next ``n_test``.
    """

    fork_task: str  # the task's name in the fork and in the authors' annotations.json
    per_length: int
    total: int
    seed: int = 3


def hiveformer_sequences(palette: tuple[str, ...], max_length: int, numbering: PaperNumbering) -> list[tuple[str, ...]]:
    """The fork's variation list: element *i* is the colour sequence of its variation *i*.

    The rule (read from the fork's code, reproduced here): take every ordered prefix of length
    1..max_length of every permutation of ``max_length`` palette colours, de-duplicated per length;
    sort each length's sequences, shuffle them with one ``random.Random(seed)`` generator (lengths
    in increasing order) and cut each to ``per_length``; concatenate, shuffle once more with the same
    generator and cut to ``total``. The fork sorts (name, rgb) pairs, which orders exactly as the
    names do, so only the palette's set of names matters, not its order.
    """
    by_length: list[set[tuple[str, ...]]] = [set() for _ in range(max_length)]
    for permutation in itertools.permutations(palette, max_length):
        for length in range(1, max_length + 1):
            by_length[length - 1].add(permutation[:length])
    generator = random.Random(numbering.seed)  # Python's Mersenne Twister, as in the fork
    sequences: list[tuple[str, ...]] = []
    for same_length in by_length:
        ordered = sorted(same_length)
        generator.shuffle(ordered)
        sequences += ordered[: numbering.per_length]
    generator.shuffle(sequences)
    return sequences[: numbering.total]


def paper_variations(palette: tuple[str, ...], max_length: int, numbering: PaperNumbering) -> list[Variation]:
    """Every sequence of 1..max_length distinct colours: the fork's variations first, with the
    fork's ids, then (ids from ``numbering.total`` on) the sequences the fork never uses, in
    ``enumerate_sequences`` order, so that any sequence can still be named as an unseen variation."""
    paper = hiveformer_sequences(palette, max_length, numbering)
    taken = set(paper)
    rest = [v.words for v in enumerate_sequences(palette, max_length) if v.words not in taken]
    return [Variation(i, seq) for i, seq in enumerate(paper + rest)]


def split_variations(
    variations: list[Variation], n_train: int, n_test: int, split_seed: int
) -> dict[str, list[Variation]]:
    """Deal variations to train and test, disjoint by construction.

    Sequences of each length are shuffled with ``split_seed``; then, cycling through the lengths
    (1, 2, 3, ...), one variation goes to train and the next to test until both are full. Every
    length is represented in both splits while it lasts.
    """
    rng = np.random.default_rng(split_seed)
    by_length: dict[int, list[Variation]] = {}
    for v in variations:
        by_length.setdefault(len(v.words), []).append(v)
    pools = []
    for length in sorted(by_length):
        pool = list(by_length[length])
        order = rng.permutation(len(pool))
        pools.append([pool[i] for i in order])
    out: dict[str, list[Variation]] = {"train": [], "test": []}
    want = {"train": n_train, "test": n_test}
    while any(pools) and (len(out["train"]) < n_train or len(out["test"]) < n_test):
        for pool in pools:
            for split in SPLITS:
                if pool and len(out[split]) < want[split]:
                    out[split].append(pool.pop())
    if len(out["train"]) < n_train or len(out["test"]) < n_test:
        raise ValueError(f"only {len(variations)} variations; cannot split {n_train}+{n_test}")
    return out
