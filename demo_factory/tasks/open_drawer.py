"""Open drawer: grasp the handle of the instructed drawer of a chest and pull the drawer out."""

from __future__ import annotations

import numpy as np

from demo_factory.tasks import motions
from demo_factory.tasks.base import KeyframeTarget
from demo_factory.tasks.drawers import APPROACH, DRAWERS, DrawerTask
from demo_factory.tasks.objects import free_of_robot
from demo_factory.tasks.variations import Variation

OPENED = 0.15  # m: RLBench's JointCondition on the drawer joint
PULL = 0.18  # m, the hand's straight pull along the chest's axis (the grip does not slip: 3 cm past OPENED)


class OpenDrawer(DrawerTask):
    name = "open_drawer"
    description = "Grasp the handle of the instructed drawer (bottom, middle or top) and pull the drawer open."
    categories = ("motion planner",)
    # Far enough that the pull towards the base never drives the arm into a joint limit (nearer, the middle
    # and bottom pulls fail), near and central enough that both shoulder cameras see the top handle.
    front_region = ((0.74, 0.77), (-0.06, 0.06))

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        d = variation.words[0]
        return [f"open the {d} drawer", f"grip the {d} handle and pull the {d} drawer open",
                f"slide the {d} drawer open"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        self.place_chest(world, variation, rng)

    def expert(self, world) -> list[KeyframeTarget]:
        chest = self.chest
        bar, grip = chest.grip(self.drawer)
        front_of = bar - APPROACH * chest.axis
        pulled = bar - PULL * chest.axis
        return [KeyframeTarget(motions.pose(front_of, grip), motions.OPEN, "planned"),
                KeyframeTarget(motions.pose(bar, grip), motions.OPEN, "cartesian"),
                KeyframeTarget(motions.pose(bar, grip), motions.CLOSED, "gripper"),
                KeyframeTarget(motions.pose(pulled, grip), motions.CLOSED, "cartesian"),
                # Letting go ends it: the open fingers stand clear of the bar, and any move away from the pulled
                # out bottom drawer runs into a wrist limit or the shoulder's singularity.
                KeyframeTarget(motions.pose(pulled, grip), motions.OPEN, "gripper")]

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Open another drawer."""
        return self.expert_with(world, drawer=next(d for d in DRAWERS if d != self.drawer))

    def success(self, world) -> bool:
        # RLBench checks the instructed joint only; opening every drawer is not opening "the top drawer",
        # so the others must have stayed shut here.
        return (self.chest.opening(self.drawer) >= OPENED and self.chest.shut_except(self.drawer)
                and free_of_robot(world, self.chest.body))
