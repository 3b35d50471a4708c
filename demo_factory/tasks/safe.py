"""The open safe and the banknote bundle shared by put_money_in_safe and take_money_out_safe.

The safe stands on the table with its open front facing the robot (-x) and three shelves. The
note lies along x and is always held by its rear end, so the hand stays in front of the safe
while the note slides in or out of a compartment (the top-down hand is taller than a compartment).
"""

from __future__ import annotations

import numpy as np
import pybullet as p

from demo_factory.tasks.base import Task
from demo_factory.tasks.objects import Part, add_body
from demo_factory.tasks.variations import Variation

SHELVES = ("bottom", "middle", "top")
WALL = 0.01
INNER_DEPTH, INNER_HALF_WIDTH = 0.17, 0.1
SHELF_TOPS = (0.02, 0.085, 0.15)  # the top surface of each shelf board (the forearm must clear the roof)
HEIGHT = 0.215
NOTE_HALF = (0.1, 0.025, 0.012)  # a bundle of notes: 20 x 5 x 2.4 cm
NOTE_MASS = 0.03
NOTE_RGBA = (0.45, 0.7, 0.45, 1.0)
GRIP_FROM_REAR = 0.015  # the grasp frame this far in from the note's rear end
HAND_CLEARANCE = 0.06  # the grasp frame stays this far in front of the safe (hand and wrist clear it)
SAFE_RGBA = (0.3, 0.32, 0.35, 1.0)
FRONT_REGION = ((0.52, 0.56), (-0.12, 0.12))


def safe_parts() -> list[Part]:
    """Back wall (base, at the body origin), sides, roof and shelf boards; origin = back wall centre."""
    c = SAFE_RGBA
    depth = INNER_DEPTH + WALL
    parts = [Part("box", (WALL / 2, INNER_HALF_WIDTH + WALL, HEIGHT / 2), rgba=c)]
    for side in (-1, 1):
        parts.append(Part("box", (depth / 2, WALL / 2, HEIGHT / 2), (-depth / 2, side * (INNER_HALF_WIDTH + WALL / 2), 0.0), c))
    parts.append(Part("box", (depth / 2, INNER_HALF_WIDTH, WALL / 2), (-depth / 2, 0.0, HEIGHT / 2 - WALL / 2), c))
    for top in SHELF_TOPS:
        parts.append(Part("box", (depth / 2, INNER_HALF_WIDTH, WALL / 2), (-depth / 2, 0.0, top - WALL / 2 - HEIGHT / 2), c))
    return parts


SHELF_LINKS = {name: 3 + i for i, name in enumerate(SHELVES)}  # link index of each shelf board (base = -1)


class Safe:
    """The safe's body and where things are: ``front`` is the x of its open face."""

    def __init__(self, world, front_x: float, y: float):
        self.front, self.y = front_x, y
        back = front_x + INNER_DEPTH + WALL / 2
        self.body = add_body(world, safe_parts(), (back, y, HEIGHT / 2), mass=0.0)

    def shelf_of(self, world, note: int) -> str | None:
        """The shelf the note touches, if any."""
        for name, link in SHELF_LINKS.items():
            if p.getContactPoints(note, self.body, -1, link, physicsClientId=world.client):
                return name
        return None

    def note_grasp_height(self, shelf: str) -> float:
        return SHELF_TOPS[SHELVES.index(shelf)] + NOTE_HALF[2] + 0.002

    def shelf_point(self, shelf: str) -> np.ndarray:
        """A point on a shelf's board, a note's half length inside the safe's open face."""
        return np.array([self.front + NOTE_HALF[0], self.y, SHELF_TOPS[SHELVES.index(shelf)]])

    def inside(self, position) -> bool:
        return position[0] > self.front + 0.01 and abs(position[1] - self.y) < INNER_HALF_WIDTH


class SafeTask(Task):
    """A task at an open safe placed in front of the robot; the variation is one of its shelves."""

    palette = SHELVES
    variation_kind = "shelf"
    max_sequence = 1
    shared_split = True

    def place_safe(self, world, variation: Variation, rng: np.random.Generator) -> None:
        """The safe at a random spot of FRONT_REGION; the instructed shelf in ``self.shelf``."""
        (x0, x1), (y0, y1) = FRONT_REGION
        self.safe = Safe(world, rng.uniform(x0, x1), rng.uniform(y0, y1))
        self.shelf = variation.words[0]
        self.world = world


def add_note(world, centre, z: float) -> int:
    return add_body(world, [Part("box", NOTE_HALF, rgba=NOTE_RGBA)], (*centre, z), mass=NOTE_MASS, friction=0.8)


def note_rear_grip(world, note: int) -> np.ndarray:
    """Where the grasp frame holds the note: near its rear (-x) end, at its mid height."""
    position, _ = world.body_pose(note)
    return position + [-NOTE_HALF[0] + GRIP_FROM_REAR, 0.0, 0.002]
