"""Put money in safe: take the banknote bundle from the table and slide it onto the instructed shelf."""

from __future__ import annotations

import numpy as np

from demo_factory.tasks import motions
from demo_factory.tasks.base import Failure, KeyframeTarget
from demo_factory.tasks.objects import at_rest, free_of_robot
from demo_factory.tasks.safe import GRIP_FROM_REAR, HAND_CLEARANCE, NOTE_HALF, SafeTask, add_note, note_rear_grip
from demo_factory.tasks.variations import Variation

NOTE_REGION = ((0.38, 0.42), (-0.2, 0.2))
INSERT_TRAVEL = 0.15  # the straight slide into the compartment (starts with the note 2.5 cm out)


class PutMoneyInSafe(SafeTask):
    name = "put_money_in_safe"
    description = "Take the banknote bundle off the table and put it on the instructed shelf of the open safe."
    categories = ("visual occlusion",)

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        s = variation.words[0]
        return [f"put the money away in the safe on the {s} shelf", f"place the banknotes on the {s} shelf of the safe",
                f"stash the money in the {s} compartment of the safe"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        self.place_safe(world, variation, rng)
        (nx0, nx1), (ny0, ny1) = NOTE_REGION
        self.note = add_note(world, (rng.uniform(nx0, nx1), rng.uniform(ny0, ny1)), NOTE_HALF[2])

    def expert(self, world) -> list[KeyframeTarget]:
        grip = motions.top_down(0.0)
        z = self.safe.note_grasp_height(self.shelf)
        inserted = np.array([self.safe.front - HAND_CLEARANCE, self.safe.y, z])
        outside = inserted - [INSERT_TRAVEL, 0.0, 0.0]
        return (motions.grasp(note_rear_grip(world, self.note), grip)
                + [KeyframeTarget(motions.pose(outside, grip), motions.CLOSED, "planned"),
                   KeyframeTarget(motions.pose(inserted, grip), motions.CLOSED, "cartesian"),
                   KeyframeTarget(motions.pose(inserted, grip), motions.OPEN, "gripper"),
                   KeyframeTarget(motions.pose(outside, grip), motions.OPEN, "cartesian")])

    def graspable_bodies(self) -> list[int]:
        return [self.note]

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Put the money on another shelf."""
        return self.expert_with(world, shelf=next(s for s in self.palette if s != self.shelf))

    def success(self, world) -> bool:
        position, _ = world.body_pose(self.note)
        return (self.safe.inside(position) and self.safe.shelf_of(world, self.note) == self.shelf
                and at_rest(world, self.note) and free_of_robot(world, self.note))

    def failure(self, world) -> Failure | None:
        """"wrong shelf" when the money lies inside the safe on another shelf, else None."""
        position, _ = world.body_pose(self.note)
        shelf = self.safe.shelf_of(world, self.note) if self.safe.inside(position) else None
        if shelf is not None and shelf != self.shelf:
            return Failure("wrong shelf", 1, f"the money is on the {shelf} shelf where {self.shelf} was instructed")
        return None

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        """The banknotes, then the instructed shelf."""
        return [world.body_pose(self.note)[0], self.safe.shelf_point(variation.words[0])]

    def scene_facts(self) -> dict:
        return {"safe_front": round(float(self.safe.front), 6), "safe_y": round(float(self.safe.y), 6),
                "note": [round(float(v), 6) for v in self.world.body_pose(self.note)[0]], "grip_from_rear": GRIP_FROM_REAR}
