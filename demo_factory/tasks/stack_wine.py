"""Stack wine: take the bottle and stand it in the instructed slot of the wine rack."""

from __future__ import annotations

import numpy as np

from demo_factory.tasks import motions
from demo_factory.tasks.base import Failure, KeyframeTarget, Task
from demo_factory.tasks.objects import Part, add_body, resting_on, upright
from demo_factory.tasks.variations import Variation

SLOTS = ("left", "middle", "right")  # as seen from the robot: left is +y
# A slot leaves the bottle 2 cm on each side, more than a shoulder camera's pixel at the rack at 64x64 (~1.2 cm);
# docs/reference/suite.md says what narrower slots did.
SLOT_INNER = 0.095
RACK_WALL, RACK_WALL_HEIGHT, RACK_PLATE = 0.008, 0.05, 0.01
BOTTLE_RADIUS, BODY_LENGTH = 0.028, 0.12
NECK_RADIUS, NECK_LENGTH = 0.012, 0.045
GRIP_ABOVE_BOTTOM = BODY_LENGTH + NECK_LENGTH / 2  # the neck: the hand must clear the bottle top
PLACE_CLEARANCE = 0.004
TOLERANCE = 0.025  # bottle axis to slot centre: a bottle standing anywhere in the slot (1.95 cm) counts
RACK_REGION = ((0.52, 0.58), (-0.12, 0.12))
BOTTLE_REGION = ((0.36, 0.42), (-0.2, 0.2))
RACK_RGBA = (0.45, 0.3, 0.18, 1.0)


def rack_parts() -> list[Part]:
    """A plate with three square slots side by side along y; origin = plate centre."""
    pitch = SLOT_INNER + RACK_WALL
    half_w = 1.5 * pitch + RACK_WALL / 2
    half_d = SLOT_INNER / 2 + RACK_WALL
    wall_z = RACK_PLATE / 2 + RACK_WALL_HEIGHT / 2
    c = RACK_RGBA
    parts = [Part("box", (half_d, half_w, RACK_PLATE / 2), rgba=c)]
    for side in (-1, 1):  # the long walls in front and behind
        parts.append(Part("box", (RACK_WALL / 2, half_w, RACK_WALL_HEIGHT / 2), (side * (half_d - RACK_WALL / 2), 0, wall_z), c))
    for k in range(4):  # the dividers
        parts.append(Part("box", (half_d, RACK_WALL / 2, RACK_WALL_HEIGHT / 2), (0, -1.5 * pitch + k * pitch, wall_z), c))
    return parts


def bottle_parts() -> list[Part]:
    green, cork = (0.1, 0.35, 0.15, 1.0), (0.6, 0.45, 0.3, 1.0)
    return [Part("cylinder", (BOTTLE_RADIUS, BODY_LENGTH), rgba=green),
            Part("cylinder", (NECK_RADIUS, NECK_LENGTH), (0, 0, BODY_LENGTH / 2 + NECK_LENGTH / 2), cork)]


class StackWine(Task):
    name = "stack_wine"
    description = "Take the wine bottle and stand it in the instructed slot of the wine rack."
    categories = ("planning",)
    palette = SLOTS
    variation_kind = "slot"
    max_sequence = 1
    shared_split = True

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        s = variation.words[0]
        return [f"stack the wine bottle in the {s} slot of the rack", f"put the bottle into the {s} slot",
                f"place the wine in the {s} compartment of the wine rack"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        (rx0, rx1), (ry0, ry1) = RACK_REGION
        self.rack_centre = np.array([rng.uniform(rx0, rx1), rng.uniform(ry0, ry1)])
        self.rack = add_body(world, rack_parts(), (*self.rack_centre, RACK_PLATE / 2), mass=0.0)
        (bx0, bx1), (by0, by1) = BOTTLE_REGION
        self.world = world
        self.bottle = add_body(world, bottle_parts(), (rng.uniform(bx0, bx1), rng.uniform(by0, by1), BODY_LENGTH / 2),
                               mass=0.15, friction=1.0)
        self.slot = variation.words[0]

    def slot_centre(self, slot: str) -> np.ndarray:
        offset = (1 - SLOTS.index(slot)) * (SLOT_INNER + RACK_WALL)
        return self.rack_centre + [0.0, offset]

    def expert(self, world) -> list[KeyframeTarget]:
        position, _ = world.body_pose(self.bottle)
        grip = motions.top_down(0.0)
        neck = [position[0], position[1], position[2] - BODY_LENGTH / 2 + GRIP_ABOVE_BOTTOM]
        place_z = RACK_PLATE + PLACE_CLEARANCE + GRIP_ABOVE_BOTTOM
        return motions.grasp(neck, grip) + motions.place([*self.slot_centre(self.slot), place_z], grip)

    def graspable_bodies(self) -> list[int]:
        return [self.bottle]

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Put the bottle back down where it was."""
        keyframes = self.expert(world)
        put_back = keyframes[1].pose
        return keyframes[:4] + motions.place(put_back[:3], put_back[3:])

    def success(self, world) -> bool:
        position, _ = world.body_pose(self.bottle)
        return (float(np.linalg.norm(position[:2] - self.slot_centre(self.slot))) < TOLERANCE
                and upright(world, self.bottle) and resting_on(world, self.bottle, self.rack))

    def failure(self, world) -> Failure | None:
        """"wrong slot" when the bottle stands in (over) another slot of the rack, else None."""
        position, _ = world.body_pose(self.bottle)
        for slot in SLOTS:
            if slot != self.slot and float(np.linalg.norm(position[:2] - self.slot_centre(slot))) < TOLERANCE:
                return Failure("wrong slot", 1, f"the bottle is in the {slot} slot where {self.slot} was instructed")
        return None

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        """The bottle (its top), then the instructed slot of the rack."""
        top = world.body_pose(self.bottle)[0] + [0.0, 0.0, BODY_LENGTH / 2 + NECK_LENGTH]
        return [top, np.array([*self.slot_centre(variation.words[0]), RACK_PLATE + RACK_WALL_HEIGHT])]

    def scene_facts(self) -> dict:
        return {"rack": [round(float(v), 6) for v in self.rack_centre],
                "bottle": [round(float(v), 6) for v in self.world.body_pose(self.bottle)[0]]}
