"""Close drawer: push the instructed drawer of a chest, which starts pulled out, back in."""

from __future__ import annotations

import numpy as np

from demo_factory.tasks import motions
from demo_factory.tasks.base import KeyframeTarget
from demo_factory.tasks.drawers import BAR_HALF, DrawerTask, finger_reach
from demo_factory.tasks.objects import free_of_robot
from demo_factory.tasks.variations import Variation

START_OPENING = (0.09, 0.13)  # m, how far the instructed drawer starts pulled out (RLBench: 0.1)
CLOSED = 0.04  # m: RLBench's JointCondition, the joint moved 0.06 from its 0.1 start
GAP = 0.02  # m, the fingers start this far in front of the bar
OVERPUSH = 0.002  # m, the push ends this far past the shut bar's place, pressing the drawer home
BACK_OFF = 0.05  # m, the hand backs away along the axis after the push
STOP_SHORT = 0.3  # the wrong action pushes the drawer only this fraction of the way in


class CloseDrawer(DrawerTask):
    name = "close_drawer"
    description = "Push the instructed drawer (bottom, middle or top), which starts pulled out, shut."
    categories = ("motion planner",)
    # As open_drawer's: nearer, the pushes that start with the drawer out near the base fail for the middle
    # handle; farther, the top handle leaves the shoulder cameras' view.
    front_region = ((0.74, 0.77), (-0.06, 0.06))

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        d = variation.words[0]
        return [f"close the {d} drawer", f"shut the {d} drawer", f"slide the {d} drawer shut"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        self.place_chest(world, variation, rng)
        self.chest.set_opening(self.drawer, rng.uniform(*START_OPENING))

    def expert(self, world) -> list[KeyframeTarget]:
        return self._push(world, 1.0)

    def _push(self, world, fraction: float) -> list[KeyframeTarget]:
        """The closed fingers push the bar's near face ``fraction`` of the way back to where it is when shut."""
        chest = self.chest
        held, grip = chest.grip(self.drawer)
        touch = held - (BAR_HALF[0] + finger_reach()) * chest.axis  # the fingers on the bar
        start = touch - GAP * chest.axis
        end = touch + fraction * (chest.opening(self.drawer) + OVERPUSH) * chest.axis
        return [KeyframeTarget(motions.pose(start, grip), motions.CLOSED, "planned"),
                KeyframeTarget(motions.pose(end, grip), motions.CLOSED, "cartesian"),
                KeyframeTarget(motions.pose(end - BACK_OFF * chest.axis, grip), motions.CLOSED, "cartesian")]

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Push the drawer only a third of the way in. (Closing another drawer is no miss here: the others are
        already shut, and the open one sticks out across the hand's way to theirs.)"""
        return self._push(world, STOP_SHORT)

    def success(self, world) -> bool:
        return (self.chest.opening(self.drawer) <= CLOSED and self.chest.shut_except(self.drawer)
                and free_of_robot(world, self.chest.body))
