"""Turn oven on: grip the left-most knob on the oven's front panel and turn it anticlockwise a quarter turn."""

from __future__ import annotations

import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from demo_factory.tasks.base import KeyframeTarget, PlacementTask
from demo_factory.tasks.motions import CLOSED, OPEN, pose
from demo_factory.tasks.objects import Part, add_body, free_of_robot, hold_where_left
from demo_factory.tasks.variations import Variation

# The oven, in its own frame: the front faces -x (the robot, at zero yaw), the origin is the body's centre.
# Small and low enough that the shoulder cameras see its front: their view ends about 30 cm above the table there.
OVEN_HALF = (0.12, 0.15, 0.13)  # m: 24 x 30 x 26 cm
DOOR_HALF = (0.006, 0.13, 0.08)  # the glass door on the lower front
DOOR_CENTRE_Z = -0.035  # m above the oven's centre
HANDLE_RADIUS, HANDLE_LENGTH = 0.008, 0.2  # the door's bar handle, along y
HANDLE_Z, HANDLE_OUT = 0.025, 0.03  # m above the centre; m in front of the door
PANEL_HALF = (0.004, 0.14, 0.035)  # the control panel strip above the door
KNOB_Z = 0.085  # m above the oven's centre (the knobs' axes): 0.215 m above the table
KNOB_YS = (0.09, 0.0, -0.09)  # left to right as seen from the front (left is +y at zero yaw)
POWER_KNOB = 0  # the left-most knob switches the oven on (RLBench's)
DISC_RADIUS, DISC_LENGTH = 0.022, 0.012  # the knob's round base, flush on the panel
GRIP_HALF = (0.015, 0.006, 0.021)  # the knob's grip bar: depth, thickness, height (vertical when off)
GRIP_OUT = DISC_LENGTH + GRIP_HALF[0]  # the grip bar's centre in front of the panel
KNOB_MASS = 0.05  # kg per knob link
# N·m: the knob's detent friction keeps it where it is left; stiff enough that the fingers letting go do
# not drag it back (at 0.3 N·m they did, by up to 0.5 rad)
FRICTION_TORQUE = 1.0
TURNED_ON = 1.5  # rad: RLBench's JointCondition on the oven knob
UNTOUCHED = np.radians(10)
TURN = np.radians(115)  # the hand's turn: past TURNED_ON with room for the fingers' give
APPROACH = 0.08  # m: the hand lines up this far in front of the grip bar before going in
CENTRE_REGION = ((0.6, 0.68), (0.02, 0.12))  # the oven's centre (x, y)
# rad: the oven's turn about z. RLBench turns it by up to ±45°, but both shoulder cameras must see the power
# knob's face, and the knob must face away from the arm (MIN_SKEW): a front turned towards one camera turns
# away from the other, and these angles (the front turned a little to +y, the oven left of centre) keep the
# panel at least ~7° off edge-on for both while the knob faces 24° or more away from the arm.
YAW_RANGE = (np.radians(-20), np.radians(-5))
# The arm cannot hold the hand level and pointing straight away from its base at knob height (the wrist
# would have to flip past its limits), so a scene whose power knob faces the base within this is drawn again.
MIN_SKEW = np.radians(24)
STEEL, DARK, GLASS = (0.75, 0.75, 0.78, 1.0), (0.12, 0.12, 0.13, 1.0), (0.2, 0.22, 0.25, 1.0)
KNOB_RGBA, GRIP_RGBA = (0.85, 0.85, 0.87, 1.0), (0.1, 0.1, 0.1, 1.0)

_ALONG_X = tuple(Rotation.from_euler("y", np.pi / 2).as_quat())  # a cylinder's axis turned from z to x
_ALONG_Y = tuple(Rotation.from_euler("x", np.pi / 2).as_quat())
# The level grasp frame in the oven's frame: z into the panel (+x), fingers closing along y, x down.
_LEVEL = Rotation.from_matrix([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])


def oven_parts() -> list[Part]:
    """Body (base), door, door handle, control panel."""
    front = -OVEN_HALF[0]
    panel_z = OVEN_HALF[2] - PANEL_HALF[2] - 0.01
    return [
        Part("box", OVEN_HALF, rgba=STEEL),
        Part("box", DOOR_HALF, (front - DOOR_HALF[0], 0.0, DOOR_CENTRE_Z), GLASS),
        Part("cylinder", (HANDLE_RADIUS, HANDLE_LENGTH), (front - 2 * DOOR_HALF[0] - HANDLE_OUT, 0.0, HANDLE_Z), STEEL,
             _ALONG_Y),
        *[Part("box", (HANDLE_OUT / 2, HANDLE_RADIUS, HANDLE_RADIUS),
               (front - 2 * DOOR_HALF[0] - HANDLE_OUT / 2, side * (HANDLE_LENGTH / 2 - HANDLE_RADIUS), HANDLE_Z), STEEL)
          for side in (-1, 1)],
        Part("box", PANEL_HALF, (front - PANEL_HALF[0], 0.0, panel_z), DARK),
    ]


def _make_knob(world, position, orientation) -> int:
    """A knob on a revolute joint about the panel's normal: a round base and a grip bar across it.

    The body's origin sits on the panel's face; its frame is the oven's, so the joint axis -x points
    at the viewer and a positive angle is an anticlockwise turn as seen from the front.
    """
    client = world.client
    disc_col = p.createCollisionShape(p.GEOM_CYLINDER, radius=DISC_RADIUS, height=DISC_LENGTH,
                                      collisionFrameOrientation=_ALONG_X, physicsClientId=client)
    disc_vis = p.createVisualShape(p.GEOM_CYLINDER, radius=DISC_RADIUS, length=DISC_LENGTH, rgbaColor=KNOB_RGBA,
                                   visualFrameOrientation=_ALONG_X, physicsClientId=client)
    grip_col = p.createCollisionShape(p.GEOM_BOX, halfExtents=GRIP_HALF, physicsClientId=client)
    grip_vis = p.createVisualShape(p.GEOM_BOX, halfExtents=GRIP_HALF, rgbaColor=GRIP_RGBA, physicsClientId=client)
    body = p.createMultiBody(
        baseMass=0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=-1,
        basePosition=[float(v) for v in position], baseOrientation=[float(v) for v in orientation],
        linkMasses=[KNOB_MASS, KNOB_MASS], linkCollisionShapeIndices=[disc_col, grip_col],
        linkVisualShapeIndices=[disc_vis, grip_vis],
        linkPositions=[(-DISC_LENGTH / 2, 0, 0), (-(DISC_LENGTH / 2 + GRIP_HALF[0]), 0, 0)],
        linkOrientations=[(0, 0, 0, 1)] * 2,
        linkInertialFramePositions=[(0, 0, 0)] * 2, linkInertialFrameOrientations=[(0, 0, 0, 1)] * 2,
        linkParentIndices=[0, 1], linkJointTypes=[p.JOINT_REVOLUTE, p.JOINT_FIXED],
        linkJointAxis=[(-1, 0, 0), (0, 0, 1)], physicsClientId=client,
    )
    hold_where_left(world, body, (0, 1), FRICTION_TORQUE)
    return body


class TurnOvenOn(PlacementTask):
    name = "turn_oven_on"
    description = "Grip the left-most knob on the oven's front panel and turn it anticlockwise to switch the oven on."
    categories = ("screw",)

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        return ["turn on the oven",
                "grip the left most knob on the oven and rotate it anticlockwise to turn the oven on",
                "turn the left most knob on the oven to switch the oven on",
                "twist the oven's left knob to switch it on", "preheat the oven"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        (x0, x1), (y0, y1) = CENTRE_REGION
        while True:
            self.centre = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1), OVEN_HALF[2]])
            self.yaw = float(rng.uniform(*YAW_RANGE))
            self.rotation = Rotation.from_euler("z", self.yaw)
            knob = self.knob_point(POWER_KNOB, GRIP_OUT)
            if abs(np.arctan2(knob[1], knob[0]) - self.yaw) >= MIN_SKEW:
                break
        orientation = tuple(self.rotation.as_quat())
        self.oven = add_body(world, oven_parts(), self.centre, orientation, mass=0.0)
        self.knobs = [_make_knob(world, self.knob_point(i, 0.0), orientation) for i in range(len(KNOB_YS))]
        self.world = world

    def knob_point(self, index: int, out: float) -> np.ndarray:
        """A world point on knob ``index``'s axis, ``out`` metres in front of the panel's face."""
        local = [-OVEN_HALF[0] - 2 * PANEL_HALF[0] - out, KNOB_YS[index], KNOB_Z]
        return self.centre + self.rotation.apply(local)

    def knob_angle(self, world, index: int) -> float:
        return float(p.getJointState(self.knobs[index], 0, physicsClientId=world.client)[0])

    def _turn_knob(self, index: int, turn: float) -> list[KeyframeTarget]:
        """Go in horizontally along the knob's axis, close across the upright grip bar, turn about the axis, let go."""
        start = self.rotation * _LEVEL
        # A positive knob angle is a turn about the oven's -x (towards the viewer).
        turned = self.rotation * Rotation.from_rotvec([-turn, 0, 0]) * _LEVEL
        grip, out = self.knob_point(index, GRIP_OUT), self.knob_point(index, GRIP_OUT + APPROACH)
        q0, q1 = tuple(start.as_quat()), tuple(turned.as_quat())
        return [
            KeyframeTarget(pose(out, q0), OPEN, "planned"),
            KeyframeTarget(pose(grip, q0), OPEN, "cartesian"),
            KeyframeTarget(pose(grip, q0), CLOSED, "gripper"),
            KeyframeTarget(pose(grip, q1), CLOSED, "cartesian"),
            KeyframeTarget(pose(grip, q1), OPEN, "gripper"),
            KeyframeTarget(pose(out, q1), OPEN, "cartesian"),
        ]

    def expert(self, world) -> list[KeyframeTarget]:
        return self._turn_knob(POWER_KNOB, TURN)

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Turn the power knob only half as far. (Not the knob next to it: turned to face both shoulder
        cameras, the oven leaves the middle knob facing the arm too squarely for a level hand.)"""
        return self._turn_knob(POWER_KNOB, TURN / 2)

    def success(self, world) -> bool:
        others = [i for i in range(len(self.knobs)) if i != POWER_KNOB]
        return (self.knob_angle(world, POWER_KNOB) >= TURNED_ON
                and all(abs(self.knob_angle(world, i)) <= UNTOUCHED for i in others)
                and free_of_robot(world, self.knobs[POWER_KNOB]))

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        return [self.knob_point(POWER_KNOB, GRIP_OUT)]

    def scene_facts(self) -> dict:
        return {"oven_centre": [round(float(v), 6) for v in self.centre], "oven_yaw": round(self.yaw, 6),
                "knobs": [[round(float(v), 6) for v in self.knob_point(i, GRIP_OUT)] for i in range(len(self.knobs))],
                "power_knob": POWER_KNOB}
