"""Keyframe builders shared by every task's expert: approach, grasp, place, press, push, reach.

Each returns the keyframes of one motion: a planned (collision-free) move to a pose above the
contact, straight Cartesian moves into and out of contact, and gripper commands in place.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from demo_factory.sim.world import TOP_DOWN
from demo_factory.tasks.base import KeyframeTarget

OPEN, CLOSED = 1.0, 0.0
ABOVE = 0.10  # default approach height above a grasp or place pose


def top_down(yaw: float = 0.0) -> tuple[float, ...]:
    """The top-down grasp orientation turned by ``yaw`` about the world z axis."""
    rotation = Rotation.from_euler("z", yaw) * Rotation.from_quat(TOP_DOWN)
    return tuple(rotation.as_quat())


def pose(position, orientation) -> tuple[float, ...]:
    return (*(float(v) for v in position), *orientation)


def raised(position, height: float) -> np.ndarray:
    return np.asarray(position, dtype=float) + [0.0, 0.0, height]


def reach(position, orientation, gripper_open: float = OPEN) -> list[KeyframeTarget]:
    """A planned move of the grasp frame to ``position``."""
    return [KeyframeTarget(pose(position, orientation), gripper_open, "planned")]


def grasp(position, orientation, above: float = ABOVE, switch_keyframe: bool = True) -> list[KeyframeTarget]:
    """Approach from above, close the fingers on the object, and lift it back to the approach height."""
    return _down_switch_up(position, orientation, above, OPEN, CLOSED, switch_keyframe)


def place(position, orientation, above: float = ABOVE, switch_keyframe: bool = True) -> list[KeyframeTarget]:
    """Carry the held object above ``position``, lower it there, let go and back off upwards."""
    return _down_switch_up(position, orientation, above, CLOSED, OPEN, switch_keyframe)


def _down_switch_up(position, orientation, above: float, before: float, after: float,
                    switch_keyframe: bool = True) -> list[KeyframeTarget]:
    """Above ``position`` (planned), straight down, the gripper from ``before`` to ``after``, straight up.

    With ``switch_keyframe`` the gripper's switch is a keyframe of its own, at the pose the move down reached
    (4 keyframes); without it the move down ends with the switch (3): the executor reaches a keyframe's pose,
    then applies its gripper command, so the motion is the same, with one keyframe fewer to predict."""
    over = pose(raised(position, above), orientation)
    at = pose(position, orientation)
    down = KeyframeTarget(at, before if switch_keyframe else after, "cartesian")
    switch = [KeyframeTarget(at, after, "gripper")] if switch_keyframe else []
    return [KeyframeTarget(over, before, "planned"), down, *switch, KeyframeTarget(over, after, "cartesian")]


def lift(position, orientation, gripper_open: float = CLOSED) -> list[KeyframeTarget]:
    """A straight move (e.g. lifting a held object) to ``position``."""
    return [KeyframeTarget(pose(position, orientation), gripper_open, "cartesian")]


def press(top, orientation, approach: float, depth: float, gripper_open: float = CLOSED) -> list[KeyframeTarget]:
    """Press straight down ``depth`` below ``top`` (grasp-frame heights) and come back up."""
    over = pose(raised(top, approach), orientation)
    pressed = pose(raised(top, -depth), orientation)
    return [
        KeyframeTarget(over, gripper_open, "planned"),
        KeyframeTarget(pressed, gripper_open, "cartesian"),
        KeyframeTarget(over, gripper_open, "cartesian"),
    ]


def push(start, end, orientation, above: float = ABOVE) -> list[KeyframeTarget]:
    """Lower the closed gripper at ``start``, push in a straight line to ``end``, then rise."""
    return [
        KeyframeTarget(pose(raised(start, above), orientation), CLOSED, "planned"),
        KeyframeTarget(pose(start, orientation), CLOSED, "cartesian"),
        KeyframeTarget(pose(end, orientation), CLOSED, "cartesian"),
        KeyframeTarget(pose(raised(end, above), orientation), CLOSED, "cartesian"),
    ]
