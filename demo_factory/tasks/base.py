"""The task interface: variations, instructions, scene, expert keyframes and success check."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from demo_factory.tasks.variations import SPLITS, Variation, enumerate_sequences, split_variations


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


class Task(ABC):
    """A multi-variation tabletop task. Subclasses register themselves in ``registry``."""

    name: str
    description: str
    category: str
    palette: tuple[str, ...]
    max_sequence: int = 3
    n_train: int = 100
    n_test: int = 100
    split_seed: int = 0
    gripper_starts_open: bool = True

    # -- variations -----------------------------------------------------------------------
    @cached_property
    def variations(self) -> list[Variation]:
        """Every variation of the task, in its fixed enumeration order (``id`` = index)."""
        return enumerate_sequences(self.palette, self.max_sequence)

    @cached_property
    def splits(self) -> dict[str, list[Variation]]:
        """The disjoint train and test variation sets."""
        return split_variations(self.variations, self.n_train, self.n_test, self.split_seed)

    def split_variations(self, split: str) -> list[Variation]:
        if split not in SPLITS:
            raise ValueError(f"unknown split {split!r}; accepted: {', '.join(SPLITS)}")
        return self.splits[split]

    def variation(self, variation_id: int) -> Variation:
        return self.variations[variation_id]

    # -- instructions ---------------------------------------------------------------------
    @abstractmethod
    def synthetic_instructions(self, variation: Variation) -> list[str]:
        """Every synthetic rendering of the variation's instruction (one per template)."""

    def instruction(self, variation: Variation, episode_seed: int) -> str:
        """The synthetic instruction of one episode: a template chosen from the episode seed."""
        options = self.synthetic_instructions(variation)
        return options[np.random.default_rng([episode_seed, 7]).integers(len(options))]

    # -- simulation -----------------------------------------------------------------------
    @abstractmethod
    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        """Add the task's objects to ``world`` (a ``demo_factory.sim.World``)."""

    @abstractmethod
    def expert(self, world) -> list[KeyframeTarget]:
        """The scripted expert: keyframes from the scene's state (no rendering, no planning)."""

    def graspable_bodies(self) -> list[int]:
        """Bodies the gripper may pick up (the planner then moves them with the hand)."""
        return []

    def on_step(self, world) -> None:
        """Called after every physics step (to track events such as button presses)."""

    @abstractmethod
    def success(self, world) -> bool:
        """Whether the instructed goal holds in the current simulator state."""

    def scene_facts(self) -> dict:
        """Task-specific facts worth recording with the episode (object colours, positions)."""
        return {}


def spread_positions(rng: np.random.Generator, n: int, workspace, min_spacing: float) -> list[np.ndarray]:
    """``n`` xy positions in ``workspace`` ((x0, x1), (y0, y1)), pairwise ``min_spacing`` apart."""
    (x0, x1), (y0, y1) = workspace
    while True:
        points = [np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)]) for _ in range(n)]
        if all(np.linalg.norm(a - b) >= min_spacing for i, a in enumerate(points) for b in points[i + 1:]):
            return points
