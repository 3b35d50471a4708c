"""The chest of three drawers shared by open_drawer and close_drawer.

The chest stands on the table with its front facing the robot. Each drawer is a link on a prismatic
joint along the chest's depth axis (0 = shut, positive = pulled out towards the robot) with a little
joint friction, so that a drawer stays where it is left. Each front carries a vertical bar handle on
two posts. The hand reaches the bar pitched down (not top-down: the drawers and handles above a lower
drawer would be in the way of a vertical hand, and the Panda's wrist cannot hold the hand level that
low), its fingers closing across the bar from either side, and pulls or pushes along the chest's axis.
"""

from __future__ import annotations

import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from demo_factory.sim.world import TOP_DOWN
from demo_factory.tasks.base import Task
from demo_factory.tasks.objects import Part
from demo_factory.tasks.variations import Variation

DRAWERS = ("bottom", "middle", "top")
WALL = 0.012  # m, carcass board thickness
DEPTH = 0.2  # m, the carcass front to back
HALF_WIDTH = 0.12  # m, half the carcass width
# The chest is low and narrow so that both shoulder cameras (their view ends ~28-30 cm above the table
# there) see every handle; the slots are no lower than the hand's clearance of the bar above allows.
PLINTH = 0.015  # m, the plinth under the lowest drawer: the handles stand 6, 16 and 26 cm high
SLOT = 0.09  # m, the height of each drawer's opening (the hand at a bar clears the bar above)
DIVIDER = 0.01  # m, the board between two openings
FRONT_THICKNESS = 0.015  # m, the drawer front panel
FRONT_GAP = 0.003  # m, around a front panel inside its opening
TRAY_DEPTH = 0.17  # m, the drawer box behind the front
TRAY_HEIGHT = 0.045  # m, its side walls
TRAVEL = 0.19  # m, the joint's upper limit (the tray's back stays inside)
STANDOFF = 0.035  # m, the bar's centre in front of the drawer front (room for a fingertip behind it)
BAR_HALF = (0.008, 0.008, 0.013)  # m, the vertical handle bar
POST_HALF = (STANDOFF / 2, 0.006, 0.005)  # m, the two posts that hold it
DRAWER_MASS = 0.4  # kg, front panel and tray together
FRICTION_FORCE = 3.0  # N, the slide's friction: holds a drawer still, far below what the grip holds
SHUT = 0.01  # m, a drawer no further out than this counts as shut
# The hand's tilt from pointing straight down, towards the chest. More tilt bends the wrist to its limit
# on the pulls near the robot; less brings the back of the hand and the wrist onto the bar above. The arm's
# straight-line moves at this tilt also break down (the solver's arm posture drifts into a joint limit)
# for handles about 14-22 cm high when the chest stands nearer than ~0.74 m (the pulls end near the base);
# from 0.74 m out, every handle height from 6 to 26 cm works (IK dry runs, measured).
PITCH = np.radians(30)
FINGER_HALF_WIDTH, FINGER_TIP = 0.012, 0.008  # m, a finger's half width and its tip past the grasp frame
APPROACH = 0.06  # m, the hand starts this far in front of the bar, then moves in along the axis
CARCASS_RGBA, FRONT_RGBA, HANDLE_RGBA = (0.55, 0.38, 0.24, 1.0), (0.78, 0.62, 0.42, 1.0), (0.75, 0.75, 0.78, 1.0)
# The chest faces the robot's base, turned about its front centre by up to this either way. (RLBench turns
# it by up to pi/8 wherever it stands; a hand that must pitch towards a chest turned far from the arm's own
# direction needs a twisted wrist, which the straight pulls lose on the way.)
YAW_JITTER = 0.15


def handle_height(drawer: str) -> float:
    """The bar's centre height above the table (the middle of the drawer's opening)."""
    return PLINTH + DRAWERS.index(drawer) * (SLOT + DIVIDER) + SLOT / 2


def _carcass_parts() -> list[Part]:
    """Back (the base part), sides, top, plinth and dividers, in the chest frame: origin at the
    front's bottom centre, x into the chest, z up."""
    c = CARCASS_RGBA
    height = PLINTH + 3 * SLOT + 2 * DIVIDER + WALL
    half_h, half_d = height / 2, DEPTH / 2
    inner = HALF_WIDTH - WALL
    parts = [Part("box", (WALL / 2, HALF_WIDTH, half_h), (DEPTH - WALL / 2, 0.0, half_h), c)]
    for side in (-1, 1):
        parts.append(Part("box", (half_d, WALL / 2, half_h), (half_d, side * (HALF_WIDTH - WALL / 2), half_h), c))
    parts.append(Part("box", (half_d, inner, WALL / 2), (half_d, 0.0, height - WALL / 2), c))
    parts.append(Part("box", (half_d, inner, PLINTH / 2), (half_d, 0.0, PLINTH / 2), c))
    for i in (1, 2):
        bottom = PLINTH + i * SLOT + (i - 1) * DIVIDER
        parts.append(Part("box", (half_d, inner, DIVIDER / 2), (half_d, 0.0, bottom + DIVIDER / 2), c))
    return parts


def _drawer_parts() -> list[Part]:
    """One drawer in its joint frame (the front panel's centre): the front (first), the tray's bottom,
    sides and back, the handle's posts and bar."""
    f = FRONT_RGBA
    half_w = HALF_WIDTH - WALL - FRONT_GAP
    half_h = SLOT / 2 - FRONT_GAP
    tray_x = FRONT_THICKNESS / 2 + TRAY_DEPTH / 2
    tray_z = -half_h + TRAY_HEIGHT / 2
    thin = 0.004
    parts = [Part("box", (FRONT_THICKNESS / 2, half_w, half_h), rgba=f),
             Part("box", (TRAY_DEPTH / 2, half_w, thin), (tray_x, 0.0, -half_h + thin), f),
             Part("box", (thin, half_w, TRAY_HEIGHT / 2), (FRONT_THICKNESS / 2 + TRAY_DEPTH - thin, 0.0, tray_z), f)]
    for side in (-1, 1):
        parts.append(Part("box", (TRAY_DEPTH / 2, thin, TRAY_HEIGHT / 2), (tray_x, side * (half_w - thin), tray_z), f))
    face = -FRONT_THICKNESS / 2
    for side in (-1, 1):
        parts.append(Part("box", POST_HALF, (face - POST_HALF[0], 0.0, side * (BAR_HALF[2] - POST_HALF[2])), HANDLE_RGBA))
    parts.append(Part("box", BAR_HALF, (face - STANDOFF, 0.0, 0.0), HANDLE_RGBA))
    return parts


def _box(client: int, part: Part, shift=(0.0, 0.0, 0.0)) -> tuple[int, int]:
    """A box part's collision and visual shapes, with their frames ``shift``ed in the link frame."""
    col = p.createCollisionShape(p.GEOM_BOX, halfExtents=part.size, collisionFramePosition=shift, physicsClientId=client)
    vis = p.createVisualShape(p.GEOM_BOX, halfExtents=part.size, rgbaColor=part.rgba, visualFramePosition=shift,
                              physicsClientId=client)
    return col, vis


def finger_reach() -> float:
    """How far the closed fingers reach past the grasp frame along the chest's axis (the hand pitched)."""
    return FINGER_HALF_WIDTH * np.cos(PITCH) + FINGER_TIP * np.sin(PITCH)


class Chest:
    """The chest's body and where things are: its front centre ``front``, ``yaw``, and each drawer's
    joint (the link index of its front panel) and handle bar link."""

    def __init__(self, world, front, yaw: float):
        self.world, self.client = world, world.client
        self.front, self.yaw = np.asarray(front, dtype=float), float(yaw)
        self.orientation = tuple(Rotation.from_euler("z", self.yaw).as_quat())
        self.axis = Rotation.from_euler("z", self.yaw).apply([1.0, 0.0, 0.0])  # into the chest
        self.body, self.joints, self.bars = self._build(world)

    def _build(self, world):
        client = self.client
        base, *fixed = _carcass_parts()
        # The back board is the base, shifted off the body origin so that the chest frame is the front's bottom centre.
        base_col, base_vis = _box(client, base, base.offset)
        masses, cols, viss, positions, parents, types = [], [], [], [], [], []

        def link(part, parent, joint, mass):
            col, vis = _box(client, part)
            masses.append(mass)
            cols.append(col)
            viss.append(vis)
            positions.append(part.offset)
            parents.append(parent)
            types.append(joint)
            return len(masses)  # this link's index as a parent (links count from 1 there, 0 = base)

        for part in fixed:
            link(part, 0, p.JOINT_FIXED, 0.0)
        joints, bars = {}, {}
        drawer_parts = _drawer_parts()
        part_mass = DRAWER_MASS / len(drawer_parts)
        for name in DRAWERS:
            panel, *rest = drawer_parts
            centre = (FRONT_THICKNESS / 2, 0.0, handle_height(name))
            front = link(Part(panel.shape, panel.size, centre, panel.rgba), 0, p.JOINT_PRISMATIC, part_mass)
            joints[name] = front - 1
            for part in rest:
                bars[name] = link(part, front, p.JOINT_FIXED, part_mass) - 1
        n = len(masses)
        body = p.createMultiBody(
            baseMass=0.0, baseCollisionShapeIndex=base_col, baseVisualShapeIndex=base_vis,
            basePosition=[float(v) for v in self.front], baseOrientation=self.orientation,
            linkMasses=masses, linkCollisionShapeIndices=cols, linkVisualShapeIndices=viss,
            linkPositions=positions, linkOrientations=[(0, 0, 0, 1)] * n,
            linkInertialFramePositions=[(0, 0, 0)] * n, linkInertialFrameOrientations=[(0, 0, 0, 1)] * n,
            linkParentIndices=parents, linkJointTypes=types,
            linkJointAxis=[(-1.0, 0.0, 0.0)] * n,  # a positive joint value pulls a drawer out, towards the robot
            physicsClientId=client,
        )
        for link_index in range(-1, n):
            p.changeDynamics(body, link_index, lateralFriction=1.0, physicsClientId=client)
        for joint in joints.values():
            p.changeDynamics(body, joint, jointLowerLimit=0.0, jointUpperLimit=TRAVEL, physicsClientId=client)
            p.setJointMotorControl2(body, joint, p.VELOCITY_CONTROL, targetVelocity=0.0, force=FRICTION_FORCE,
                                    physicsClientId=client)
        return body, joints, bars

    def opening(self, drawer: str) -> float:
        """How far the drawer is pulled out (metres)."""
        return float(p.getJointState(self.body, self.joints[drawer], physicsClientId=self.client)[0])

    def set_opening(self, drawer: str, opening: float) -> None:
        p.resetJointState(self.body, self.joints[drawer], opening, 0.0, physicsClientId=self.client)

    def bar(self, drawer: str) -> np.ndarray:
        """The handle bar's centre in the world, where the drawer is now."""
        state = p.getLinkState(self.body, self.bars[drawer], computeForwardKinematics=True, physicsClientId=self.client)
        return np.array(state[4])

    def grip(self, drawer: str) -> tuple[np.ndarray, tuple[float, ...]]:
        """Where the grasp frame holds the drawer's bar now, and the hand's orientation there: turned to face
        the chest and pitched down towards it, the fingers closing across the bar."""
        rotation = Rotation.from_euler("z", self.yaw) * Rotation.from_euler("y", -PITCH) * Rotation.from_quat(TOP_DOWN)
        return self.bar(drawer), tuple(rotation.as_quat())

    def shut_except(self, drawer: str | None) -> bool:
        """Every drawer but ``drawer`` is shut."""
        return all(self.opening(name) <= SHUT for name in DRAWERS if name != drawer)


class DrawerTask(Task):
    """A task at a chest of drawers placed in front of the robot; the variation is one of its drawers."""

    palette = DRAWERS
    variation_kind = "drawer"
    max_sequence = 1
    shared_split = True
    front_region: tuple[tuple[float, float], tuple[float, float]]  # (x0, x1), (y0, y1) of the chest's front centre

    def place_chest(self, world, variation: Variation, rng: np.random.Generator) -> None:
        """The chest's front centre at a random spot of ``front_region``, facing the robot give or take a random
        yaw; the instructed drawer in ``self.drawer``."""
        (x0, x1), (y0, y1) = self.front_region
        front = (rng.uniform(x0, x1), rng.uniform(y0, y1), 0.0)
        self.chest = Chest(world, front, np.arctan2(front[1], front[0]) + rng.uniform(-YAW_JITTER, YAW_JITTER))
        self.drawer = variation.words[0]
        self.world = world

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        return [self.chest.bar(variation.words[0])]

    def scene_facts(self) -> dict:
        return {"chest_front": [round(float(v), 6) for v in self.chest.front], "chest_yaw": round(self.chest.yaw, 6),
                "openings": {name: round(self.chest.opening(name), 6) for name in DRAWERS},
                "handles": {name: [round(float(v), 6) for v in self.chest.bar(name)] for name in DRAWERS}}
