"""Pick up cup: grasp the instructed coloured cup by its rim and lift it; another cup is a distractor."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from demo_factory.tasks import motions
from demo_factory.tasks.base import KeyframeTarget, Task, spread_positions
from demo_factory.tasks.objects import Part, add_body, held
from demo_factory.tasks.palette import TOWER_COLOURS, rgba
from demo_factory.tasks.pick_and_lift import folded_yaw
from demo_factory.tasks.variations import Variation

HALF = 0.031  # outer half width of the square cup; the open fingers span 0.072
HEIGHT = 0.08
WALL = 0.005
GRASP_BELOW_RIM = 0.02
LIFTED = 0.05  # the cup's bottom this far above the table counts as picked up
WORKSPACE = ((0.38, 0.62), (-0.2, 0.2))
MIN_SPACING = 0.14


def cup_parts(colour: str) -> list[Part]:
    """A square cup: the base part is the floor, four walls rise from it (body origin = floor centre)."""
    c = tuple(rgba(colour))
    wall_z = HEIGHT / 2 - WALL / 2
    half_h = HEIGHT / 2
    return [
        Part("box", (HALF, HALF, WALL / 2), rgba=c),
        Part("box", (WALL / 2, HALF, half_h), (HALF - WALL / 2, 0, wall_z), c),
        Part("box", (WALL / 2, HALF, half_h), (-HALF + WALL / 2, 0, wall_z), c),
        Part("box", (HALF - WALL, WALL / 2, half_h), (0, HALF - WALL / 2, wall_z), c),
        Part("box", (HALF - WALL, WALL / 2, half_h), (0, -HALF + WALL / 2, wall_z), c),
    ]


class PickUpCup(Task):
    name = "pick_up_cup"
    description = "Grasp the instructed coloured cup by its rim and lift it; a cup of another colour is a distractor."
    categories = ("multimodal",)
    palette = TOWER_COLOURS
    max_sequence = 1
    n_train = n_test = 10
    split_seed = 20220304

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        c = variation.words[0]
        return [f"pick up the {c} cup", f"grasp the {c} cup and lift it", f"lift the {c} mug off the table"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        distractor = str(rng.choice([x for x in self.palette if x not in variation.words]))
        self.world = world
        self.cups = {}
        for colour, xy in zip([variation.words[0], distractor], spread_positions(rng, 2, WORKSPACE, MIN_SPACING)):
            yaw = rng.uniform(-np.pi / 4, np.pi / 4)
            self.cups[colour] = add_body(world, cup_parts(colour), (*xy, WALL / 2), Rotation.from_euler("z", yaw).as_quat(),
                                         mass=0.08)
        self.instructed = variation.words[0]

    def expert(self, world) -> list[KeyframeTarget]:
        position, orientation = world.body_pose(self.cups[self.instructed])
        rim = position + [0, 0, HEIGHT - WALL / 2 - GRASP_BELOW_RIM]
        return motions.grasp(rim, motions.top_down(folded_yaw(orientation)))

    def graspable_bodies(self) -> list[int]:
        return list(self.cups.values())

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Pick up the distractor cup."""
        return self.expert_with(world, instructed=next(c for c in self.cups if c != self.instructed))

    def success(self, world) -> bool:
        cup = self.cups[self.instructed]
        return float(world.body_pose(cup)[0][2]) > LIFTED + WALL / 2 and held(world, cup)

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        return [world.body_pose(self.cups[variation.words[0]])[0] + [0.0, 0.0, HEIGHT]]

    def scene_facts(self) -> dict:
        return {"cups": {c: [round(float(v), 6) for v in self.world.body_pose(b)[0]] for c, b in self.cups.items()}}
