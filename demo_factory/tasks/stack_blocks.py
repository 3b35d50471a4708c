"""Stack blocks: stack three blocks of the instructed colour on the platform; blocks of another colour are distractors."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from demo_factory.tasks import motions
from demo_factory.tasks.base import Failure, KeyframeTarget, Task, spread_positions
from demo_factory.tasks.objects import at_rest, free_of_robot, held, upright
from demo_factory.tasks.palette import TOWER_COLOURS, rgba
from demo_factory.tasks.pick_and_lift import folded_yaw
from demo_factory.tasks.variations import Variation

N_STACK = 3  # blocks to stack: the tower's height that stacks reliably
N_TARGET = 4  # blocks of the instructed colour (one more than needed, as in RLBench, so any three will do)
N_DISTRACTORS = 2  # blocks of one other colour
CUBE = 0.045  # edge length (m); the open gripper spans 0.08
CUBE_MASS = 0.08
PLATFORM_HALF = (0.045, 0.045, 0.0025)  # a thin fixed slab; its colour is no palette colour
PLATFORM_RGBA = (0.42, 0.27, 0.13, 1.0)
PLATFORM_TOP = 2 * PLATFORM_HALF[2]
WORKSPACE = ((0.34, 0.62), (-0.25, 0.25))
MIN_SPACING = 0.11  # between block centres and the platform's: room for the open fingers beside a block
ABOVE = 0.10  # approach height above a grasp or place pose
PLACE_CLEARANCE = 0.004  # release a block this far above its resting height
STACK_TOLERANCE = 0.02  # xy distance of a block's centre from the centre of the one below it
ON_PLATFORM = PLATFORM_HALF[0]  # xy distance of the bottom block's centre from the platform's: over the slab
HEIGHT_TOLERANCE = 0.01
NUMBERS = {2: "two", 3: "three", 4: "four"}


class StackBlocks(Task):
    name = "stack_blocks"
    description = (f"Stack {N_STACK} of the {N_TARGET} blocks of the instructed colour on the platform; "
                   f"{N_DISTRACTORS} blocks of another colour are distractors.")
    categories = ("long term",)
    palette = TOWER_COLOURS
    max_sequence = 1
    n_train = n_test = 10
    split_seed = 20220317
    resizable = True

    @property
    def cube(self) -> float:
        """The block's edge length (m): CUBE, times ``object_scale``."""
        return CUBE * self.object_scale

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        c, n = variation.words[0], NUMBERS[N_STACK]
        return [
            f"stack {n} {c} blocks on the platform",
            f"build a tower of {n} {c} cubes on the platform",
            f"place {n} of the {c} blocks on top of each other on the platform",
            f"pick up and set down {n} {c} blocks on top of each other on the platform",
        ]

    # -- scene ----------------------------------------------------------------------------
    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        colour = variation.words[0]
        distractor = str(rng.choice([x for x in self.palette if x != colour]))
        points = spread_positions(rng, 1 + N_TARGET + N_DISTRACTORS, WORKSPACE, MIN_SPACING)
        self.world = world
        self.colour, self.distractor = colour, distractor
        self.platform_xy = points[0]
        self.platform_yaw = float(rng.uniform(-np.pi / 4, np.pi / 4))
        self.platform = world.add_box(PLATFORM_HALF, (*self.platform_xy, PLATFORM_HALF[2]), PLATFORM_RGBA, mass=0.0,
                                      orientation=Rotation.from_euler("z", self.platform_yaw).as_quat())
        half = self.cube / 2
        self.blocks: list[int] = []  # the instructed colour's
        self.distractors: list[int] = []
        for index, xy in enumerate(points[1:]):
            yaw = rng.uniform(-np.pi / 4, np.pi / 4)
            block = world.add_box((half,) * 3, (*xy, half), rgba(colour if index < N_TARGET else distractor),
                                  mass=CUBE_MASS, orientation=Rotation.from_euler("z", yaw).as_quat(), friction=1.0)
            (self.blocks if index < N_TARGET else self.distractors).append(block)

    def chosen(self, world) -> list[int]:
        """The blocks the expert stacks, bottom first: the instructed colour's nearest to the platform."""
        distance = {b: float(np.linalg.norm(world.body_pose(b)[0][:2] - self.platform_xy)) for b in self.blocks}
        return sorted(self.blocks, key=distance.get)[:N_STACK]

    def expert(self, world) -> list[KeyframeTarget]:
        return self._stack(world, self.chosen(world))

    def _stack(self, world, blocks: list[int]) -> list[KeyframeTarget]:
        keyframes = []
        on_platform = motions.top_down(self.platform_yaw)
        for level, block in enumerate(blocks):
            position, orientation = world.body_pose(block)
            place_z = PLATFORM_TOP + (level + 0.5) * self.cube + PLACE_CLEARANCE
            keyframes += motions.grasp(position, motions.top_down(folded_yaw(orientation)), ABOVE)
            keyframes += motions.place([*self.platform_xy, place_z], on_platform, ABOVE)
        return keyframes

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Stack two instructed blocks and then a distractor on top instead of the third."""
        chosen = self.chosen(world)
        return self._stack(world, [*chosen[:N_STACK - 1], self.distractors[0]])

    def graspable_bodies(self) -> list[int]:
        return [*self.blocks, *self.distractors]

    def success(self, world) -> bool:
        """``N_STACK`` instructed blocks each resting on the one below, the bottom one on the platform, none
        touched by the robot (RLBench: the blocks detected on the platform, the gripper empty)."""
        return len(self.stacked(world)[0]) == N_STACK

    def stacked(self, world) -> tuple[list[int], np.ndarray, float]:
        """The instructed blocks that rest in the stack, bottom first, and where the next one would go: (blocks,
        the top surface they leave, its xy tolerance)."""
        below, tolerance = np.array([*self.platform_xy, PLATFORM_TOP]), ON_PLATFORM
        stack, remaining = [], list(self.blocks)
        for _ in range(N_STACK):
            on_it = [b for b in remaining if self._rests_on(world, b, below, tolerance)]
            if not on_it:
                break
            stack.append(on_it[0])
            remaining.remove(on_it[0])
            below, tolerance = world.body_pose(on_it[0])[0] + [0.0, 0.0, self.cube / 2], STACK_TOLERANCE
        return stack, below, tolerance

    def failure(self, world) -> Failure | None:
        """"wrong block stacked" when a distractor rests where the next block goes; "block still held" when the
        gripper holds an instructed block at the end; else "stack incomplete", each at the first level missing."""
        stack, below, tolerance = self.stacked(world)
        level = len(stack) + 1
        if any(self._rests_on(world, b, below, tolerance) for b in self.distractors):
            return Failure("wrong block stacked", level, f"a {self.distractor} block (not in the instruction) stands "
                                                         f"where {self.colour} block {level} goes")
        if any(held(world, b) for b in self.blocks):
            return Failure("block still held", level, f"{len(stack)} of {N_STACK} blocks stacked, one more in the "
                                                      "gripper, never let go")
        return Failure("stack incomplete", level, f"{len(stack)} of {N_STACK} {self.colour} blocks stacked")

    def _rests_on(self, world, block: int, top: np.ndarray, tolerance: float) -> bool:
        """The block sits on the surface centred at ``top`` (within ``tolerance`` in xy), upright, still and
        free of the robot."""
        position, _ = world.body_pose(block)
        return (float(np.linalg.norm(position[:2] - top[:2])) < tolerance
                and abs(float(position[2]) - self.cube / 2 - float(top[2])) < HEIGHT_TOLERANCE
                and upright(world, block) and at_rest(world, block) and free_of_robot(world, block))

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        """The instructed colour's blocks the expert stacks, bottom first (their tops)."""
        return [world.body_pose(b)[0] + [0.0, 0.0, self.cube / 2] for b in self.chosen(world)]

    def goal_place(self) -> np.ndarray:
        return np.array([*self.platform_xy, PLATFORM_TOP])

    def scene_facts(self) -> dict:
        def where(body):
            return [round(float(v), 6) for v in self.world.body_pose(body)[0]]
        return {
            "colour": self.colour,
            "distractor_colour": self.distractor,
            "platform": [round(float(v), 6) for v in self.platform_xy],
            "blocks": [where(b) for b in self.blocks],
            "distractors": [where(b) for b in self.distractors],
        }
