"""Slide block to target: push a block across the table onto a target square with the closed gripper."""

from __future__ import annotations

import numpy as np

from demo_factory.tasks import motions
from demo_factory.tasks.base import KeyframeTarget, PlacementTask
from demo_factory.tasks.objects import free_of_robot, at_rest
from demo_factory.tasks.variations import Variation

CUBE = 0.05
TARGET_HALF = 0.04  # the green square
PUSH_HEIGHT = 0.02  # grasp-frame height while pushing (fingertips 9 mm above the table)
CONTACT_GAP = 0.028  # grasp frame to the block's face when the push starts (finger half-depth + margin)
DISTANCE = (0.12, 0.2)  # start to target
TOLERANCE = 0.03  # block centre to target centre
START_REGION = ((0.4, 0.52), (-0.12, 0.12))


class SlideBlockToTarget(PlacementTask):
    name = "slide_block_to_target"
    description = "Push the red block across the table onto the green target square."
    categories = ("tools",)
    resizable = True

    @property
    def cube(self) -> float:
        """The block's edge length (m): CUBE, times ``object_scale``."""
        return CUBE * self.object_scale

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        return ["slide the block to the target", "push the red block onto the green square",
                "move the block until it is on the target"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        (x0, x1), (y0, y1) = START_REGION
        start = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        # Push away from the robot or sideways, never back towards the base (the arm would fold).
        angle = rng.uniform(-np.pi / 2, np.pi / 2)
        self.direction = np.array([np.cos(angle), np.sin(angle)])
        self.target = start + rng.uniform(*DISTANCE) * self.direction
        self.world = world
        world.add_box((TARGET_HALF, TARGET_HALF, 0.0005), (*self.target, 0.0006), (0.1, 0.7, 0.1, 1.0), mass=0.0,
                      collision=False)
        self.block = world.add_box((self.cube / 2,) * 3, (*start, self.cube / 2), (0.9, 0.1, 0.1, 1.0), mass=0.1,
                                   friction=0.6)

    def expert(self, world) -> list[KeyframeTarget]:
        position, _ = world.body_pose(self.block)
        back_off = (self.cube / 2 + CONTACT_GAP) * self.direction
        yaw = float(np.arctan2(self.direction[1], self.direction[0]))
        start = [*(position[:2] - back_off), PUSH_HEIGHT]
        end = [*(self.target - back_off + 0.004 * self.direction), PUSH_HEIGHT]
        return motions.push(start, end, motions.top_down(yaw))

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """A push that stops halfway."""
        keyframes = self.expert(world)
        start, end = np.array(keyframes[1].pose[:3]), np.array(keyframes[2].pose[:3])
        middle = tuple((start + end) / 2) + tuple(keyframes[2].pose[3:])
        return [keyframes[0], keyframes[1], KeyframeTarget(middle, 0.0, "cartesian")]

    def success(self, world) -> bool:
        position, _ = world.body_pose(self.block)
        return (float(np.linalg.norm(position[:2] - self.target)) < TOLERANCE and at_rest(world, self.block)
                and free_of_robot(world, self.block))

    def scene_facts(self) -> dict:
        return {"target": [round(float(v), 6) for v in self.target],
                "block": [round(float(v), 6) for v in self.world.body_pose(self.block)[0]]}
