"""Which recording goes to which dataset split, with which instruction (pure logic, no files).

One LeRobot dataset per split, under ``<out>/<split>/`` with repo id ``<repo_id>_<split>``:

=========================  ====================  ==========================================
split                      episodes of           instruction (the frame's ``task``)
=========================  ====================  ==========================================
train                      train variations      synthetic (as recorded)
val                        train variations      synthetic; held-out *episodes* (--val-ratio)
test_unseen_synthetic      test variations       synthetic (as recorded)
test_unseen_corrupted      test variations       synthetic with colour words → unseen synonyms
test_unseen_paraphrased    test variations       a held-out phrasing (``Task.held_out_phrasings``)
test_unseen_human          test variations       human-written, from a file (see instructions.human)
=========================  ====================  ==========================================

The test splits hold the same test-variation recordings (the human split repeats or leaves out
episodes as the assignment rule says; the paraphrased one holds those of tasks with held-out
phrasings). A split with no episodes is not written.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

from demo_factory.instructions import HumanInstruction, assign_human_instructions, corrupt_instruction
from demo_factory.instructions.human import HumanAssignment
from demo_factory.tasks import Variation, get_task

DATASET_SPLITS: dict[str, str] = {  # split → instruction source
    "train": "synthetic",
    "val": "synthetic",
    "test_unseen_synthetic": "synthetic",
    "test_unseen_corrupted": "corrupted",
    "test_unseen_paraphrased": "paraphrased",
    "test_unseen_human": "human",
}


@dataclass(frozen=True)
class SourceEpisode:
    """What the split plan needs to know about one valid recording (read once, frames dropped)."""

    path: Path
    task: str
    split: str  # the recorded variation split: "train" or "test"
    variation_id: int
    words: tuple[str, ...]
    episode_seed: int
    instruction: str
    frames: int  # dataset frames it yields at the chosen granularity
    keyframes: int = 0
    planner_attempts: tuple[int, ...] = ()  # attempts used per planned transition
    exact_attempts: int = 0  # attempts that found an exact path
    success: bool = True
    versions: tuple[tuple[str, str], ...] = ()  # library versions that recorded it
    # Train recordings: (words, n) of other variations, none of the test split, whose expert starts with
    # this episode's first n keyframes (``Task.instruction_relabels``).
    relabels: tuple[tuple[tuple[str, ...], int], ...] = ()
    perturbations: tuple[str, ...] = ()  # the factors applied to its scene (`generate --perturb`)


@dataclass(frozen=True)
class PlannedEpisode:
    """One episode of one split: a recording and the instruction it gets there."""

    source: SourceEpisode
    instruction: str
    human: HumanInstruction | None = None


@dataclass
class SplitPlan:
    name: str
    instruction_source: str
    episodes: list[PlannedEpisode] = field(default_factory=list)

    @property
    def frames(self) -> int:
        return sum(e.source.frames for e in self.episodes)


def split_repo_id(repo_id: str, split: str) -> str:
    """The repo id of one split's dataset: ``me/push_buttons`` → ``me/push_buttons_train``."""
    return f"{repo_id}_{split}"


def held_out_for_val(episodes: list[SourceEpisode], val_ratio: float) -> set[Path]:
    """The recordings that go to val: a fixed pseudo-random choice by episode identity.

    ``round(ratio * n)`` episodes, at least one when the ratio is positive and at least one stays
    in train. The choice depends only on each episode's (variation, seed), not on file names or
    on which other files are present, so adding recordings moves few episodes between splits.
    """
    n = len(episodes)
    if n < 2 or val_ratio <= 0:
        return set()
    count = min(max(1, round(val_ratio * n)), n - 1)
    ranked = sorted(episodes, key=lambda e: hashlib.sha256(f"{e.variation_id}:{e.episode_seed}".encode()).hexdigest())
    return {e.path for e in ranked[:count]}


def plan_splits(
    sources: list[SourceEpisode], val_ratio: float, human_rows: list[HumanInstruction] | None
) -> tuple[dict[str, SplitPlan], HumanAssignment | None]:
    """Every split's episodes and instructions (empty splits included; the writer skips them)."""
    ordered = sorted(sources, key=lambda e: (e.variation_id, e.episode_seed, e.path.name))
    train = [e for e in ordered if e.split == "train"]
    test = [e for e in ordered if e.split == "test"]
    val_paths = held_out_for_val(train, val_ratio)
    plans = {name: SplitPlan(name, source) for name, source in DATASET_SPLITS.items()}
    for e in train:
        plans["val" if e.path in val_paths else "train"].episodes.append(PlannedEpisode(e, e.instruction))
    for e in test:
        plans["test_unseen_synthetic"].episodes.append(PlannedEpisode(e, e.instruction))
        plans["test_unseen_corrupted"].episodes.append(PlannedEpisode(e, corrupt_instruction(e.instruction)))
        held_out = get_task(e.task).held_out_instruction(Variation(e.variation_id, e.words), e.episode_seed)
        if held_out is not None:
            plans["test_unseen_paraphrased"].episodes.append(PlannedEpisode(e, held_out))
    assignment = None
    if human_rows is not None:
        by_variation: dict[int, list[SourceEpisode]] = {}
        for e in test:
            by_variation.setdefault(e.variation_id, []).append(e)
        assignment = assign_human_instructions(by_variation, human_rows)
        plans["test_unseen_human"].episodes = [PlannedEpisode(e, row.instruction, row) for e, row in assignment.pairs]
    return plans, assignment
