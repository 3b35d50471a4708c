"""Tower: stack the instructed coloured cubes in order on a target spot (HiveFormer's multi-variation task)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from demo_factory.tasks import motions
from demo_factory.tasks.base import KeyframeTarget, Task, spread_positions
from demo_factory.tasks.palette import TOWER_COLOURS, rgba
from demo_factory.tasks.variations import PaperNumbering, Variation

N_CUBES = 4  # the instructed 1-3 plus distractors
CUBE = 0.045  # edge length (m); the open gripper spans 0.08
CUBE_MASS = 0.08
WORKSPACE = ((0.36, 0.62), (-0.25, 0.25))
MIN_SPACING = 0.11
ABOVE = 0.10  # approach height above a grasp or place pose
PLACE_CLEARANCE = 0.004  # release a cube this far above its resting height
POSITION_TOLERANCE = 0.02  # xy distance from the target spot that still counts as on it
HEIGHT_TOLERANCE = 0.01


class Tower(Task):
    name = "tower"
    description = "Stack 1-3 instructed coloured cubes in order on the target spot; other cubes are distractors."
    categories = ("planning",)
    paper_name = "tower3"
    palette = TOWER_COLOURS
    # The fork keeps 200 sequences (200 per length, then 200 of the 420); its 100 test variations
    # 100-199 are exactly the colour sequences of the authors' annotations.json. Ids 200 on are the
    # other sequences (see ``paper_variations``), never in a split, nameable as unseen variations.
    paper_numbering = PaperNumbering("tower3", per_length=200, total=200)

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        c = variation.words
        if len(c) == 1:
            return [
                f"put the {c[0]} cube on the target",
                f"place the {c[0]} block on the grey square",
                f"move the {c[0]} cube onto the target spot",
            ]
        return [
            f"stack the {c[0]} cube on the target" + "".join(f", then the {x} cube on top" for x in c[1:]),
            "build a tower of the " + ", ".join(c[:-1]) + f" and {c[-1]} cubes, from the bottom up, on the target",
            f"place the {c[0]} block on the grey square" + "".join(f" and then put the {x} block on it" for x in c[1:]),
        ]

    # -- scene ----------------------------------------------------------------------------
    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        distractors = [x for x in self.palette if x not in variation.words]
        colours = list(variation.words) + list(rng.choice(distractors, N_CUBES - len(variation.words), replace=False))
        points = spread_positions(rng, N_CUBES + 1, WORKSPACE, MIN_SPACING)
        self.world = world
        self.instructed = variation
        self.target = points[0]
        half = CUBE / 2
        world.add_box((0.035, 0.035, 0.0005), (*self.target, 0.0006), (0.6, 0.6, 0.6, 1.0), mass=0.0, collision=False)
        self.cubes: dict[str, int] = {}
        for colour, xy in zip(colours, points[1:]):
            yaw = rng.uniform(-np.pi / 4, np.pi / 4)
            orientation = Rotation.from_euler("z", yaw).as_quat()
            self.cubes[colour] = world.add_box((half, half, half), (*xy, half), rgba(colour), mass=CUBE_MASS,
                                               orientation=orientation, friction=1.0)

    def grasp_yaw(self, colour: str) -> float:
        """The cube's yaw folded into [-45°, 45°): any face pair can be grasped."""
        _, orientation = self.world.body_pose(self.cubes[colour])
        yaw = Rotation.from_quat(orientation).as_euler("xyz")[2]
        return float((yaw + np.pi / 4) % (np.pi / 2) - np.pi / 4)

    def expert(self, world) -> list[KeyframeTarget]:
        keyframes = []
        for level, colour in enumerate(self.instructed.words):
            position, _ = world.body_pose(self.cubes[colour])
            place_z = (level + 0.5) * CUBE + PLACE_CLEARANCE
            keyframes += motions.grasp(position, motions.top_down(self.grasp_yaw(colour)), ABOVE)
            keyframes += motions.place([*self.target, place_z], motions.top_down(0.0), ABOVE)
        return keyframes

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Stack a cube the instruction does not name at the bottom instead of the first one."""
        distractor = next(c for c in self.cubes if c not in self.instructed.words)
        wrong = Variation(self.instructed.id, (distractor, *self.instructed.words[1:]))
        return self.expert_with(world, instructed=wrong)

    def graspable_bodies(self) -> list[int]:
        return list(self.cubes.values())

    def success(self, world) -> bool:
        for level, colour in enumerate(self.instructed.words):
            position, _ = world.body_pose(self.cubes[colour])
            if np.linalg.norm(position[:2] - self.target) > POSITION_TOLERANCE:
                return False
            if abs(position[2] - (level + 0.5) * CUBE) > HEIGHT_TOLERANCE:
                return False
        return True

    goal_sketch = "stack"

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        return [world.body_pose(self.cubes[colour])[0] + [0.0, 0.0, CUBE / 2] for colour in variation.words]

    def goal_place(self) -> np.ndarray:
        return np.array([*self.target, 0.0])

    def show_goal(self, world, variation: Variation) -> np.ndarray:
        for level, colour in enumerate(variation.words):
            position = (float(self.target[0]), float(self.target[1]), (level + 0.5) * CUBE)
            world.set_body_pose(self.cubes[colour], position, (0, 0, 0, 1))
        return np.array([*self.target, len(variation.words) * CUBE])

    def scene_facts(self) -> dict:
        return {
            "target": [round(float(v), 6) for v in self.target],
            "cubes": {c: [round(float(v), 6) for v in self.world.body_pose(b)[0]] for c, b in self.cubes.items()},
        }

