"""Deterministic enumeration of variations (word sequences) and their disjoint train/test split."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

SPLITS = ("train", "test")


@dataclass(frozen=True)
class Variation:
    """An ordered sequence of palette words; ``id`` is its index in the task's full enumeration.

    The words are colours for colour tasks (``colours`` keeps that name because recordings, the
    converter and the instruction tools read it), or another kind of goal: a slot, a shelf.
    """

    id: int
    colours: tuple[str, ...]

    @property
    def name(self) -> str:
        return ",".join(self.colours)


def enumerate_sequences(palette: tuple[str, ...], max_length: int) -> list[Variation]:
    """All ordered sequences of 1..max_length distinct palette colours, shortest first."""
    sequences = [
        seq for n in range(1, max_length + 1) for seq in itertools.permutations(palette, n)
    ]
    return [Variation(i, seq) for i, seq in enumerate(sequences)]


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
        by_length.setdefault(len(v.colours), []).append(v)
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
