"""Take umbrella out of umbrella stand: grasp the handle and lift the umbrella straight up out of the stand."""

from __future__ import annotations

import numpy as np
import pybullet as p

from demo_factory.tasks import motions
from demo_factory.tasks.base import KeyframeTarget, PlacementTask
from demo_factory.tasks.objects import Part, add_body, held

STAND_INNER, STAND_WALL, STAND_HEIGHT, STAND_PLATE = 0.07, 0.008, 0.15, 0.01
SHAFT_RADIUS, SHAFT_LENGTH = 0.008, 0.28
CANOPY_RADIUS, CANOPY_LENGTH, CANOPY_LOW = 0.024, 0.16, 0.05  # the folded canopy, from 5 cm above the tip
HANDLE_HALF = (0.011, 0.011, 0.025)
GRIP_BELOW_TOP = 0.02
LIFT = 0.25  # straight up: the tip ends 10 cm above the stand's rim
CLEAR = 0.02  # the tip this far above the rim counts as out
STAND_REGION = ((0.45, 0.58), (-0.18, 0.18))
HANDLE_LINK = 0  # links are numbered from 0 after the base (the shaft)


def stand_parts() -> list[Part]:
    c = (0.2, 0.25, 0.45, 1.0)
    outer = STAND_INNER / 2 + STAND_WALL
    z = STAND_HEIGHT / 2 - STAND_PLATE / 2  # walls stand on the table, around the plate
    parts = [Part("box", (outer, outer, STAND_PLATE / 2), rgba=c)]
    for side in (-1, 1):
        parts.append(Part("box", (STAND_WALL / 2, outer, STAND_HEIGHT / 2), (side * (outer - STAND_WALL / 2), 0, z), c))
        parts.append(Part("box", (outer - STAND_WALL, STAND_WALL / 2, STAND_HEIGHT / 2), (0, side * (outer - STAND_WALL / 2), z), c))
    return parts


def umbrella_parts() -> list[Part]:
    """Shaft (the base, origin at its centre), handle on top, folded canopy around the lower shaft."""
    return [
        Part("cylinder", (SHAFT_RADIUS, SHAFT_LENGTH), rgba=(0.2, 0.2, 0.2, 1.0)),
        Part("box", HANDLE_HALF, (0, 0, SHAFT_LENGTH / 2 + HANDLE_HALF[2]), (0.45, 0.25, 0.1, 1.0)),
        Part("cylinder", (CANOPY_RADIUS, CANOPY_LENGTH), (0, 0, -SHAFT_LENGTH / 2 + CANOPY_LOW + CANOPY_LENGTH / 2),
             (0.6, 0.1, 0.15, 1.0)),
    ]


class TakeUmbrellaOutOfUmbrellaStand(PlacementTask):
    name = "take_umbrella_out_of_umbrella_stand"
    description = "Grasp the umbrella's handle and lift it straight up out of its stand."
    categories = ("precision",)

    def synthetic_instructions(self, variation) -> list[str]:
        return ["take the umbrella out of the umbrella stand", "lift the umbrella out of the stand",
                "grasp the umbrella by its handle and pull it out of the stand"]

    def build_scene(self, world, variation, rng: np.random.Generator) -> None:
        (x0, x1), (y0, y1) = STAND_REGION
        self.stand_xy = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        self.stand = add_body(world, stand_parts(), (*self.stand_xy, STAND_PLATE / 2), mass=0.0)
        yaw = rng.uniform(-np.pi / 4, np.pi / 4)
        self.world = world
        self.umbrella = add_body(world, umbrella_parts(), (*self.stand_xy, STAND_PLATE + SHAFT_LENGTH / 2 + 0.001),
                                 p.getQuaternionFromEuler((0, 0, yaw)), mass=0.12, friction=1.0)

    def handle_pose(self, world) -> tuple[np.ndarray, float]:
        state = p.getLinkState(self.umbrella, HANDLE_LINK, physicsClientId=world.client)
        yaw = p.getEulerFromQuaternion(state[5])[2]
        return np.array(state[4]), float((yaw + np.pi / 4) % (np.pi / 2) - np.pi / 4)

    def expert(self, world) -> list[KeyframeTarget]:
        handle, yaw = self.handle_pose(world)
        grip = motions.top_down(yaw)
        hold = handle + [0.0, 0.0, HANDLE_HALF[2] - GRIP_BELOW_TOP]
        return motions.grasp(hold, grip, above=0.08)[:3] + motions.lift(hold + [0.0, 0.0, LIFT], grip)

    def graspable_bodies(self) -> list[int]:
        return [self.umbrella]

    def tip_height(self, world) -> float:
        position, orientation = world.body_pose(self.umbrella)
        return float(p.multiplyTransforms(position, orientation, (0, 0, -SHAFT_LENGTH / 2), (0, 0, 0, 1))[0][2])

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Lift the umbrella only part of the way."""
        keyframes = self.expert(world)
        short = np.array(keyframes[2].pose[:3]) + [0.0, 0.0, 0.06]
        return keyframes[:3] + motions.lift(short, keyframes[2].pose[3:])

    def success(self, world) -> bool:
        return self.tip_height(world) > STAND_HEIGHT + CLEAR and held(world, self.umbrella)

    def scene_facts(self) -> dict:
        return {"stand": [round(float(v), 6) for v in self.stand_xy],
                "umbrella": [round(float(v), 6) for v in self.world.body_pose(self.umbrella)[0]]}
