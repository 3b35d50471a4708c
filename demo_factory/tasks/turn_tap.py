"""Turn tap: grasp the handle of the instructed tap (left or right) and turn it a quarter turn."""

from __future__ import annotations

import numpy as np
import pybullet as p

from demo_factory.tasks import motions
from demo_factory.tasks.base import Failure, KeyframeTarget, Task
from demo_factory.tasks.objects import free_of_robot, hold_where_left
from demo_factory.tasks.variations import Variation

TAPS = ("left", "right")  # as seen from the robot: left is +y
BASE_HALF = (0.03, 0.11, 0.01)  # the plate both taps stand on
COLUMN_RADIUS, COLUMN_HEIGHT = 0.012, 0.07
HANDLE_HALF = (0.045, 0.008, 0.008)  # a bar across the column's top, along x at rest
TAP_SPACING = 0.15
TURNED = np.radians(70)  # a handle turned this far counts as turned
UNTOUCHED = np.radians(10)
QUARTER_TURN = np.pi / 2
FRICTION_TORQUE = 0.3  # N·m: the valve's friction keeps the handle where it is left
REGION = ((0.45, 0.58), (-0.08, 0.08))
METAL, HANDLE_RGBA = (0.7, 0.7, 0.72, 1.0), (0.15, 0.35, 0.75, 1.0)


def _make_tap(world, position) -> int:
    """A fixed column with a handle bar on a revolute joint about the vertical axis."""
    client = world.client
    column_col = p.createCollisionShape(p.GEOM_CYLINDER, radius=COLUMN_RADIUS, height=COLUMN_HEIGHT, physicsClientId=client)
    column_vis = p.createVisualShape(p.GEOM_CYLINDER, radius=COLUMN_RADIUS, length=COLUMN_HEIGHT, rgbaColor=METAL,
                                     physicsClientId=client)
    handle_col = p.createCollisionShape(p.GEOM_BOX, halfExtents=HANDLE_HALF, physicsClientId=client)
    handle_vis = p.createVisualShape(p.GEOM_BOX, halfExtents=HANDLE_HALF, rgbaColor=HANDLE_RGBA, physicsClientId=client)
    body = p.createMultiBody(
        baseMass=0, baseCollisionShapeIndex=column_col, baseVisualShapeIndex=column_vis,
        basePosition=[float(position[0]), float(position[1]), 2 * BASE_HALF[2] + COLUMN_HEIGHT / 2],
        linkMasses=[0.05], linkCollisionShapeIndices=[handle_col], linkVisualShapeIndices=[handle_vis],
        linkPositions=[(0, 0, COLUMN_HEIGHT / 2 + HANDLE_HALF[2])], linkOrientations=[(0, 0, 0, 1)],
        linkInertialFramePositions=[(0, 0, 0)], linkInertialFrameOrientations=[(0, 0, 0, 1)],
        linkParentIndices=[0], linkJointTypes=[p.JOINT_REVOLUTE], linkJointAxis=[(0, 0, 1)],
        physicsClientId=client,
    )
    hold_where_left(world, body, (0,), FRICTION_TORQUE)
    return body


class TurnTap(Task):
    name = "turn_tap"
    description = "Grasp the instructed tap's handle and turn it a quarter turn; the other tap stays shut."
    categories = ("multimodal",)
    palette = TAPS
    variation_kind = "tap"
    max_sequence = 1
    shared_split = True

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        t = variation.words[0]
        return [f"turn the {t} tap", f"rotate the {t} tap's handle a quarter turn", f"open the {t} tap"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        (x0, x1), (y0, y1) = REGION
        centre = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        world.add_box(BASE_HALF, (*centre, BASE_HALF[2]), METAL, mass=0.0)
        self.taps = {name: _make_tap(world, centre + [0.0, side * TAP_SPACING / 2])
                     for name, side in (("left", 1), ("right", -1))}
        self.target = variation.words[0]
        self.world = world

    def handle_angle(self, world, tap: str) -> float:
        return float(p.getJointState(self.taps[tap], 0, physicsClientId=world.client)[0])

    def expert(self, world) -> list[KeyframeTarget]:
        body = self.taps[self.target]
        column, _ = world.body_pose(body)
        grip = column + [0.0, 0.0, COLUMN_HEIGHT / 2 + HANDLE_HALF[2]]
        # Fingers close across the bar (world y at rest), then the hand turns a quarter turn about
        # the tap's axis, carrying the handle with it.
        start, turned = motions.top_down(0.0), motions.top_down(QUARTER_TURN)
        return [
            *motions.grasp(grip, start, above=0.08)[:3],
            KeyframeTarget(motions.pose(grip, turned), motions.CLOSED, "cartesian"),
            KeyframeTarget(motions.pose(grip, turned), motions.OPEN, "gripper"),
            KeyframeTarget(motions.pose(motions.raised(grip, 0.08), turned), motions.OPEN, "cartesian"),
        ]

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Turn the other tap."""
        return self.expert_with(world, target=next(t for t in self.taps if t != self.target))

    def success(self, world) -> bool:
        other = next(t for t in TAPS if t != self.target)
        return (abs(self.handle_angle(world, self.target)) >= TURNED
                and abs(self.handle_angle(world, other)) <= UNTOUCHED
                and free_of_robot(world, self.taps[self.target]))

    def failure(self, world) -> Failure | None:
        """"wrong tap turned" (the other handle moved past 10°), "tap turned too little" (the instructed one moved
        10-70°), else None."""
        other = next(t for t in TAPS if t != self.target)
        angle, other_angle = (np.degrees(abs(self.handle_angle(world, t))) for t in (self.target, other))
        if other_angle > np.degrees(UNTOUCHED):
            return Failure("wrong tap turned", 1, f"the {other} tap turned {other_angle:.0f}° where {self.target} was "
                                                  f"instructed")
        if np.degrees(UNTOUCHED) < angle < np.degrees(TURNED):
            return Failure("tap turned too little", 1, f"the {self.target} tap turned {angle:.0f}°, a turn counts from "
                                                       f"{np.degrees(TURNED):.0f}°")
        return None

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        """The instructed tap's handle."""
        return [world.body_pose(self.taps[variation.words[0]])[0] + [0.0, 0.0, COLUMN_HEIGHT / 2 + 2 * HANDLE_HALF[2]]]

    def scene_facts(self) -> dict:
        return {"taps": {t: [round(float(v), 6) for v in self.world.body_pose(b)[0]] for t, b in self.taps.items()}}
