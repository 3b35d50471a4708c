"""The task interface: variations, instructions, scene, expert keyframes and success check."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from functools import cache

import numpy as np

from demo_factory.tasks.palette import canonical_colour
from demo_factory.tasks.variations import (
    SPLITS,
    PaperNumbering,
    Variation,
    enumerate_sequences,
    paper_variations,
    split_variations,
)


@dataclass(frozen=True)
class KeyframeTarget:
    """One expert macro-step: reach ``pose`` then set the gripper to ``gripper_open``.

    ``motion`` says how the pose is reached: "planned" (OMPL, collision-free joint path),
    "cartesian" (straight line of the grasp frame, for approach / press / lift / retreat moves that
    touch things on purpose) or "gripper" (pose unchanged, only the gripper command changes).
    """

    pose: tuple[float, ...]  # x, y, z, qx, qy, qz, qw
    gripper_open: float
    motion: str


@dataclass(frozen=True)
class Failure:
    """What went wrong in a failed episode, in the task's own words (``Task.failure``).

    ``reason`` is a short fixed phrase from the task's small vocabulary ("wrong button pressed", "press too
    shallow", "grasp missed", "cube dropped", ...), counted as is in the evaluation's results; ``subgoal`` the
    1-based index of the instructed sub-goal (the k-th button, the k-th cube of the instruction) where it went
    wrong, None when the task has no sub-goals; ``detail`` one human sentence ("pressed navy where teal was
    next").
    """

    reason: str
    subgoal: int | None = None
    detail: str = ""


class Task(ABC):
    """A tabletop task with enumerated variations. Subclasses register themselves in ``registry``.

    A variation is a sequence of words from ``palette``: colours by default (``variation_kind``
    "colour"), or the names of another kind of goal ("slot", "shelf", ...). A task whose goal does
    not vary has one variation, named by its single palette word, and differs between episodes by
    the placement drawn from the episode seed only.

    Splits: a task with ``paper_numbering`` (HiveFormer's multi-variation tasks) numbers its
    variations as the HiveFormer authors' RLBench fork does, with train = ids 0..n_train-1 and
    test = the next n_test ids, as in the paper. Other colour tasks deal their variations to
    disjoint train and test sets (``n_train`` / ``n_test``) at random with ``split_seed``. With
    ``shared_split`` both splits hold every variation (tasks with a handful of goals, where the
    paper has no unseen-variation split); their test episodes differ from the training ones only by
    the scene seed, and ``check_split_membership`` accepts either split.
    """

    name: str
    description: str
    categories: tuple[str, ...]  # the paper's categories of the task (``categories.PAPER_CATEGORIES``)
    paper_name: str | None = None  # the task's name in the paper's lists, where it differs from ``name``
    palette: tuple[str, ...]
    variation_kind: str = "colour"
    max_sequence: int = 3
    n_train: int = 100
    n_test: int = 100
    shared_split: bool = False
    split_seed: int = 0
    paper_numbering: PaperNumbering | None = None
    gripper_starts_open: bool = True
    # Colosseum's object size (the `object_size` perturbation): a task that is ``resizable`` builds its objects
    # ``object_scale`` times their size, and its expert follows.
    resizable: bool = False
    object_scale: float = 1.0

    # -- variations (pure functions of the class, computed once per process) ----------------
    @property
    def variations(self) -> list[Variation]:
        """Every variation of the task, in its fixed enumeration order (``id`` = index)."""
        return _enumeration(type(self))[0]

    @property
    def splits(self) -> dict[str, list[Variation]]:
        """The disjoint train and test variation sets."""
        return _enumeration(type(self))[1]

    @property
    def variation_scheme(self) -> str:
        """How the variation ids and the splits are chosen, in one line (for `demo-factory tasks` and cards)."""
        if self.paper_numbering is not None:
            n = self.paper_numbering
            scheme = (f"HiveFormer paper ids (the authors' RLBench fork, {n.fork_task}): train 0-{self.n_train - 1}, "
                      f"test {self.n_train}-{self.n_train + self.n_test - 1}")
            if n.total < len(self.variations):
                scheme += f"; {n.total}-{len(self.variations) - 1}: sequences the fork does not use"
            return scheme
        if self.shared_split:
            return "every variation in both splits"
        return f"dealt at random (seed {self.split_seed})"

    def split_variations(self, split: str) -> list[Variation]:
        if split not in SPLITS:
            raise ValueError(f"unknown split {split!r}; accepted: {', '.join(SPLITS)}")
        return self.splits[split]

    def variation(self, variation_id: int) -> Variation:
        return self.variations[variation_id]

    def variation_of(self, words) -> Variation:
        """The variation of a colour sequence (a list or "maroon,navy"; any case, grey = gray), or of
        another kind's words for tasks whose variations are not colours (e.g. "top" for a shelf).

        Raises ``ValueError`` naming an unknown or repeated word, or a sequence that is too long.
        """
        kind = self.variation_kind
        words = words.split(",") if isinstance(words, str) else list(words)
        sequence = []
        for word in words:
            value = canonical_colour(word) if kind == "colour" else word.strip().lower()
            if value is None or value not in self.palette:
                raise ValueError(f"unknown {kind} {word.strip()!r} for {self.name}; accepted: {', '.join(self.palette)}")
            if value in sequence:
                raise ValueError(f"{kind} {value!r} is repeated in {','.join(w.strip() for w in words)!r}; "
                                 f"each {kind} may appear once")
            sequence.append(value)
        if not 1 <= len(sequence) <= self.max_sequence:
            raise ValueError(f"{','.join(sequence)!r} has {len(sequence)} {kind}s; {self.name} takes 1 to {self.max_sequence}")
        return _enumeration(type(self))[2][tuple(sequence)]

    def parse_variation(self, text: str) -> Variation:
        """A variation named by its id (``"123"``) or its colour sequence (``"maroon,navy"``)."""
        text = text.strip()
        if text.isdigit():
            if int(text) >= len(self.variations):
                raise ValueError(f"variation id {text} does not exist; {self.name} has ids 0 to {len(self.variations) - 1}")
            return self.variation(int(text))
        return self.variation_of(text)

    def check_split_membership(self, variation: Variation, split: str) -> None:
        """Refuse a variation that belongs to the other split (it would leak data across splits).

        Variations of neither split (ids past the paper's 0-199) may be named for either: as extra
        training variations or as further unseen ones.
        """
        if self.shared_split:
            return
        other = "train" if split == "test" else "test"
        if variation in self.splits[other]:
            raise ValueError(
                f"variation {variation.id} ({variation.name}) is a {other} variation of {self.name}; generating it "
                f"for the {split} split would leak {other} data into a {split} split"
            )

    # -- instructions ---------------------------------------------------------------------
    @abstractmethod
    def synthetic_instructions(self, variation: Variation) -> list[str]:
        """Every synthetic rendering of the variation's instruction (one per template)."""

    def instruction(self, variation: Variation, episode_seed: int) -> str:
        """The synthetic instruction of one episode: a template chosen from the episode seed."""
        return _drawn(self.synthetic_instructions(variation), episode_seed, 7)

    def paraphrases(self, variation: Variation) -> list[str]:
        """Every phrasing of the variation's instruction that training may draw (the templates first): what a
        dataset lists in ``meta/task_paraphrases.json``. By default the templates; a task with a grammar
        (``demo_factory.tasks.grammar``) gives tens."""
        return self.synthetic_instructions(variation)

    def held_out_phrasings(self, variation: Variation) -> list[str]:
        """Phrasings of the variation's instruction unlike any template or paraphrase and kept out of every
        training source: the ``test_unseen_paraphrased`` split's. By default none (no such split)."""
        return []

    def held_out_instruction(self, variation: Variation, episode_seed: int) -> str | None:
        """The held-out phrasing of one test episode, chosen from the episode seed; None without any."""
        options = self.held_out_phrasings(variation)
        return _drawn(options, episode_seed, 11) if options else None

    def instruction_relabels(self, variation: Variation, scene: dict) -> list[tuple[Variation, int]]:
        """Other variations whose expert, in the same scene, would start exactly as this episode's did:
        (variation, n) where the episode's first n expert keyframes are that variation's first n. Read
        from the recorded ``scene_facts``; a training may relabel the episode's first n keyframe actions
        with that variation's instruction. By default none."""
        return []

    # -- simulation -----------------------------------------------------------------------
    @abstractmethod
    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        """Add the task's objects to ``world`` (a ``demo_factory.sim.World``)."""

    @abstractmethod
    def expert(self, world) -> list[KeyframeTarget]:
        """The scripted expert: keyframes from the scene's state (no rendering, no planning)."""

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """A deliberately wrong action for the scene (the wrong object, the wrong place, stopping short): the
        tests check that `success` stays False after it. By default no action at all (stopping before the
        first keyframe); tasks write a closer miss."""
        return []

    def expert_with(self, world, **attributes) -> list[KeyframeTarget]:
        """The expert's keyframes as if the task's attributes (e.g. its target) were others; for wrong actions."""
        saved = {name: getattr(self, name) for name in attributes}
        for name, value in attributes.items():
            setattr(self, name, value)
        try:
            return self.expert(world)
        finally:
            for name, value in saved.items():
                setattr(self, name, value)

    def graspable_bodies(self) -> list[int]:
        """Bodies the gripper may pick up (the planner then moves them with the hand)."""
        return []

    def on_step(self, world) -> None:
        """Called after every physics step (to track events such as button presses)."""

    @abstractmethod
    def success(self, world) -> bool:
        """Whether the instructed goal holds in the current simulator state."""

    def failure(self, world) -> Failure | None:
        """What went wrong, asked when an episode ends without success (from the current state and what
        ``on_step`` tracked); None when nothing more specific than the execution's own reason applies (a
        move that could not be planned, the step limit). By default None."""
        return None

    def scene_facts(self) -> dict:
        """Task-specific facts worth recording with the episode (object colours, positions)."""
        return {}

    # -- the goal, shown to people who write instructions (demo_factory.collect) -------------------
    # How the collection page sketches a variation's goal: "sequence" (the objects in order, left to
    # right) or "stack" (bottom-up, plus a close-up of the finished goal, `show_goal`).
    goal_sketch: str = "sequence"

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        """World points of the objects the instruction names, in its order (numbered in the pictures); by
        default none (the pictures show the scene unmarked)."""
        return []

    def goal_place(self) -> np.ndarray | None:
        """The world point where the goal is built (ringed in the pictures), or None."""
        return None

    def show_goal(self, world, variation: Variation) -> np.ndarray:
        """Move the objects into the finished goal (for a close-up picture only); returns the world point on
        top of it. Tasks with ``goal_sketch == "stack"`` move them; by default the scene stays as it is and
        the point is the goal place (the origin without one)."""
        place = self.goal_place()
        return np.zeros(3) if place is None else place


class PlacementTask(Task):
    """A task whose goal never varies: one variation ("random"); episodes differ by the scene's placement,
    drawn from the episode seed, and both splits hold that variation."""

    palette = ("random",)
    variation_kind = "placement"
    max_sequence = 1
    shared_split = True


@cache
def _enumeration(cls: type[Task]):
    """A task class's variations, their train/test split and a word-sequence index."""
    if cls.paper_numbering is not None:
        variations = paper_variations(cls.palette, cls.max_sequence, cls.paper_numbering)
        splits = {"train": variations[:cls.n_train], "test": variations[cls.n_train:cls.n_train + cls.n_test]}
        return variations, splits, {v.words: v for v in variations}
    variations = enumerate_sequences(cls.palette, cls.max_sequence)
    if cls.shared_split:
        splits = {"train": list(variations), "test": list(variations)}
    else:
        splits = split_variations(variations, cls.n_train, cls.n_test, cls.split_seed)
    return variations, splits, {v.words: v for v in variations}


def spread_positions(rng: np.random.Generator, n: int, workspace, min_spacing: float) -> list[np.ndarray]:
    """``n`` xy positions in ``workspace`` ((x0, x1), (y0, y1)), pairwise ``min_spacing`` apart."""
    (x0, x1), (y0, y1) = workspace
    while True:
        points = [np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)]) for _ in range(n)]
        if all(np.linalg.norm(a - b) >= min_spacing for i, a in enumerate(points) for b in points[i + 1:]):
            return points


def _drawn(options: list[str], episode_seed: int, stream: int) -> str:
    """One of ``options``, drawn from the episode seed (``stream`` keeps different draws of one seed apart)."""
    return options[np.random.default_rng([episode_seed, stream]).integers(len(options))]
