"""Take money out of safe: pull the banknote bundle off the instructed shelf and put it on the table."""

from __future__ import annotations

import numpy as np

from demo_factory.tasks import motions
from demo_factory.tasks.base import KeyframeTarget
from demo_factory.tasks.objects import resting_on
from demo_factory.tasks.safe import GRIP_FROM_REAR, HAND_CLEARANCE, NOTE_HALF, SHELF_TOPS, SHELVES, SafeTask, add_note, note_rear_grip
from demo_factory.tasks.variations import Variation

PROTRUDES = HAND_CLEARANCE + GRIP_FROM_REAR  # the note's rear end sticks out of the safe this far
PULL = 0.16  # straight pull out of the compartment
TABLE_REGION = ((0.3, 0.36), (-0.2, 0.2))  # where the grasp frame puts the note down
SAFE_CLEARANCE = 0.03
OUT_OF_SAFE = 0.08  # the note's centre must end this far in front of the safe


class TakeMoneyOutSafe(SafeTask):
    name = "take_money_out_safe"
    description = "Take the banknote bundle from the instructed shelf of the open safe and put it on the table."
    categories = ("visual occlusion",)

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        s = variation.words[0]
        return [f"take the money out of the {s} shelf of the safe", f"remove the banknotes from the {s} shelf",
                f"get the money from the {s} compartment of the safe and put it on the table"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        self.place_safe(world, variation, rng)
        # One note, on the instructed shelf: the shelves above it hide most of it from the cameras.
        top = SHELF_TOPS[SHELVES.index(self.shelf)]
        centre = (self.safe.front - PROTRUDES + NOTE_HALF[0], self.safe.y + rng.uniform(-0.04, 0.04))
        self.note = add_note(world, centre, top + NOTE_HALF[2])
        (x0, x1), (y0, y1) = TABLE_REGION
        # The note reaches 2 * NOTE_HALF[0] - GRIP_FROM_REAR ahead of the grasp frame: put it down
        # with its far end clear of the safe's front, so the carried note never touches the safe.
        x1 = min(x1, self.safe.front - (2 * NOTE_HALF[0] - GRIP_FROM_REAR) - SAFE_CLEARANCE)
        self.put_down = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1), NOTE_HALF[2] + 0.006])

    def expert(self, world) -> list[KeyframeTarget]:
        grip = motions.top_down(0.0)
        hold = note_rear_grip(world, self.note)
        pulled = hold - [PULL, 0.0, 0.0]
        return (motions.grasp(hold, grip, above=0.06)[:3]
                + motions.lift(pulled, grip)
                + motions.place(self.put_down, grip))

    def graspable_bodies(self) -> list[int]:
        return [self.note]

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Grasp the note but let go before pulling it out."""
        keyframes = self.expert(world)
        return keyframes[:3] + [KeyframeTarget(keyframes[2].pose, 1.0, "gripper")]

    def success(self, world) -> bool:
        position, _ = world.body_pose(self.note)
        return position[0] < self.safe.front - OUT_OF_SAFE and resting_on(world, self.note, world.table)

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        """The banknotes on the instructed shelf."""
        return [world.body_pose(self.note)[0]]

    def scene_facts(self) -> dict:
        return {"safe_front": round(float(self.safe.front), 6), "safe_y": round(float(self.safe.y), 6),
                "note": [round(float(v), 6) for v in self.world.body_pose(self.note)[0]]}
