"""Reach target: touch the instructed coloured sphere with the gripper; the others are distractors."""

from __future__ import annotations

import numpy as np

from demo_factory.tasks import motions
from demo_factory.tasks.base import KeyframeTarget, Task, spread_positions
from demo_factory.tasks.objects import marker
from demo_factory.tasks.palette import TOWER_COLOURS, rgba
from demo_factory.tasks.variations import Variation

N_SPHERES = 3  # the target and two distractors
RADIUS = 0.025  # the spheres are visual only, as in RLBench: the gripper passes into them
WORKSPACE = ((0.35, 0.62), (-0.22, 0.22))
HEIGHT = (0.08, 0.35)
MIN_SPACING = 0.12


class ReachTarget(Task):
    name = "reach_target"
    description = "Touch the instructed coloured sphere with the gripper; two others are distractors."
    categories = ("rotation-invariant",)
    palette = TOWER_COLOURS
    max_sequence = 1
    n_train = n_test = 10
    split_seed = 20220301
    resizable = True

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        c = variation.words[0]
        return [f"reach the {c} target", f"touch the {c} ball with the gripper", f"move the gripper to the {c} sphere"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        distractors = [x for x in self.palette if x not in variation.words]
        colours = [variation.words[0], *rng.choice(distractors, N_SPHERES - 1, replace=False)]
        self.spheres = {}
        for colour, xy in zip(colours, spread_positions(rng, N_SPHERES, WORKSPACE, MIN_SPACING)):
            self.spheres[str(colour)] = np.array([*xy, rng.uniform(*HEIGHT)])
            marker(world, self.spheres[str(colour)], RADIUS * self.object_scale, rgba(str(colour)))
        self.target = variation.words[0]

    def expert(self, world) -> list[KeyframeTarget]:
        return motions.reach(self.spheres[self.target], motions.top_down(0.0))

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Reach the other sphere."""
        other = next(c for c in self.spheres if c != self.target)
        return motions.reach(self.spheres[other], motions.top_down(0.0))

    def success(self, world) -> bool:
        return float(np.linalg.norm(world.gripper_pose()[:3] - self.spheres[self.target])) < RADIUS * self.object_scale

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        return [np.asarray(self.spheres[variation.words[0]])]

    def scene_facts(self) -> dict:
        return {"spheres": {c: [round(float(v), 6) for v in xyz] for c, xyz in self.spheres.items()}}
