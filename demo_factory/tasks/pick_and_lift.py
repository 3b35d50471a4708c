"""Pick and lift: grasp the instructed coloured block and lift it up to the target sphere."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from demo_factory.tasks import motions
from demo_factory.tasks.base import Failure, KeyframeTarget, Task, spread_positions
from demo_factory.tasks.objects import held, marker
from demo_factory.tasks.palette import COLOURS, rgba
from demo_factory.tasks.variations import Variation

N_BLOCKS = 3  # the instructed block and two distractors
CUBE = 0.04
WORKSPACE = ((0.36, 0.62), (-0.22, 0.22))
MIN_SPACING = 0.11
TARGET_HEIGHT = (0.18, 0.30)
TARGET_RADIUS = 0.02
TOLERANCE = 0.03  # block centre to target centre
# An opaque colour that no block has: a translucent white sphere against the white sky was invisible to the
# policy at 64², which then lifted every block to the mean target (16 cm off).
TARGET_COLOUR = "lime"


def folded_yaw(orientation) -> float:
    """A square object's yaw folded into [-45°, 45°): any pair of faces can be grasped."""
    yaw = Rotation.from_quat(orientation).as_euler("xyz")[2]
    return float((yaw + np.pi / 4) % (np.pi / 2) - np.pi / 4)


class PickAndLift(Task):
    name = "pick_and_lift"
    description = "Grasp the instructed coloured block and lift it to the lime target sphere."
    categories = ("rotation-invariant",)
    palette = tuple(c for c in COLOURS if c != TARGET_COLOUR)
    max_sequence = 1
    n_train, n_test = 10, 9
    split_seed = 20220303
    resizable = True

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        c = variation.words[0]
        return [f"pick up the {c} block and lift it up to the target", f"grasp the {c} cube and raise it to the sphere",
                f"lift the {c} block to the target height"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        distractors = [x for x in self.palette if x not in variation.words]
        colours = [variation.words[0], *rng.choice(distractors, N_BLOCKS - 1, replace=False)]
        points = spread_positions(rng, N_BLOCKS + 1, WORKSPACE, MIN_SPACING)
        self.world = world
        self.blocks = {}
        half = CUBE * self.object_scale / 2
        for colour, xy in zip(colours, points[1:]):
            yaw = rng.uniform(-np.pi / 4, np.pi / 4)
            self.blocks[str(colour)] = world.add_box((half,) * 3, (*xy, half), rgba(str(colour)), mass=0.06,
                                                     orientation=Rotation.from_euler("z", yaw).as_quat(), friction=1.0)
        self.target = np.array([*points[0], rng.uniform(*TARGET_HEIGHT)])
        marker(world, self.target, TARGET_RADIUS, rgba(TARGET_COLOUR))
        self.instructed = variation.words[0]

    def expert(self, world) -> list[KeyframeTarget]:
        position, orientation = world.body_pose(self.blocks[self.instructed])
        grip = motions.top_down(folded_yaw(orientation))
        return motions.grasp(position, grip) + motions.reach(self.target, grip, motions.CLOSED)

    def graspable_bodies(self) -> list[int]:
        return list(self.blocks.values())

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Pick and lift a distractor block."""
        return self.expert_with(world, instructed=next(c for c in self.blocks if c != self.instructed))

    def success(self, world) -> bool:
        block = self.blocks[self.instructed]
        position, _ = world.body_pose(block)
        return float(np.linalg.norm(position - self.target)) < TOLERANCE and held(world, block)

    def failure(self, world) -> Failure | None:
        """"wrong block picked" when a distractor is in the gripper; "block off target" when the instructed block is
        held away from the target sphere; "block not held" when it is not in the gripper."""
        wrong = next((c for c, b in self.blocks.items() if c != self.instructed and held(world, b)), None)
        if wrong is not None:
            return Failure("wrong block picked", 1, f"holding the {wrong} block where {self.instructed} was instructed")
        block = self.blocks[self.instructed]
        if held(world, block):
            distance = float(np.linalg.norm(world.body_pose(block)[0] - self.target))
            return Failure("block off target", 1, f"the {self.instructed} block is held {100 * distance:.1f} cm from "
                                                  f"the target sphere (within {100 * TOLERANCE:.0f} cm counts)")
        return Failure("block not held", 1, f"the {self.instructed} block is not in the gripper")

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        """The instructed block, then the target sphere it is lifted to."""
        return [world.body_pose(self.blocks[variation.words[0]])[0], self.target]

    def scene_facts(self) -> dict:
        return {"target": [round(float(v), 6) for v in self.target],
                "blocks": {c: [round(float(v), 6) for v in self.world.body_pose(b)[0]] for c, b in self.blocks.items()}}
