"""Open wine bottle: unscrew the bottle's cap with two twists of the hand, then lift it off."""

from __future__ import annotations

import numpy as np
import pybullet as p

from demo_factory.tasks import motions
from demo_factory.tasks.base import KeyframeTarget, PlacementTask
from demo_factory.tasks.variations import Variation

BODY_RADIUS, BODY_LENGTH = 0.035, 0.16  # m: the bottle stands fixed on the table
SHOULDER_RADIUS, SHOULDER_LENGTH = 0.025, 0.02
NECK_RADIUS, NECK_LENGTH = 0.014, 0.05
CAP_RADIUS, CAP_LENGTH = 0.016, 0.035  # the screw cap sits on the neck's top
NECK_TOP = BODY_LENGTH + SHOULDER_LENGTH + NECK_LENGTH  # m above the table
SLIDER, CAP = 0, 1  # links: the thread's lift (prismatic, along z) and the cap's turn (revolute, about z)
SLIDER_MASS, CAP_MASS = 0.005, 0.03  # kg
THREAD_TORQUE = 0.1  # N·m: the thread's friction keeps the cap where it is left
UNSCREWED = np.radians(150)  # rad: turned this far the thread lets go (more than one twist, less than two)
LIFT_TRAVEL = 0.15  # m: how far an unscrewed cap can be pulled up (off the neck and clear of it)
LIFTED = 0.03  # m: a cap this far up is off the bottle (success)
ON_NECK = 0.002  # m: below this the cap still counts as on its thread
TWIST = np.radians(100)  # one twist of the hand (two of them unscrew the cap, with room for the fingers' give)
GRIP_BELOW_TOP = CAP_LENGTH / 2  # the grasp frame at the cap's mid height
LIFT = 0.06  # m: the expert pulls the cap this far up
REGION = ((0.42, 0.58), (-0.2, 0.2))
GLASS, NECK_RGBA, CAP_RGBA = (0.1, 0.35, 0.15, 1.0), (0.1, 0.3, 0.13, 1.0), (0.55, 0.1, 0.12, 1.0)


def _make_bottle(world, xy) -> int:
    """A fixed bottle (body, shoulder, neck) whose cap is a link on a prismatic joint (the thread's lift,
    locked until unscrewed) carrying a revolute joint about the bottle's axis (the turn)."""
    client = world.client

    def cylinder(radius, length, rgba):
        col = p.createCollisionShape(p.GEOM_CYLINDER, radius=radius, height=length, physicsClientId=client)
        vis = p.createVisualShape(p.GEOM_CYLINDER, radius=radius, length=length, rgbaColor=rgba, physicsClientId=client)
        return col, vis

    body_col, body_vis = cylinder(BODY_RADIUS, BODY_LENGTH, GLASS)
    parts = [cylinder(SHOULDER_RADIUS, SHOULDER_LENGTH, GLASS), cylinder(NECK_RADIUS, NECK_LENGTH, NECK_RGBA)]
    cap_col, cap_vis = cylinder(CAP_RADIUS, CAP_LENGTH, CAP_RGBA)
    shoulder_z = BODY_LENGTH / 2 + SHOULDER_LENGTH / 2
    neck_z = BODY_LENGTH / 2 + SHOULDER_LENGTH + NECK_LENGTH / 2
    body = p.createMultiBody(
        baseMass=0, baseCollisionShapeIndex=body_col, baseVisualShapeIndex=body_vis,
        basePosition=[float(xy[0]), float(xy[1]), BODY_LENGTH / 2],
        # links 0, 1: the slider (no shape) and the cap on it; 2, 3: shoulder and neck, fixed to the body
        linkMasses=[SLIDER_MASS, CAP_MASS, 0.0, 0.0],
        linkCollisionShapeIndices=[-1, cap_col, parts[0][0], parts[1][0]],
        linkVisualShapeIndices=[-1, cap_vis, parts[0][1], parts[1][1]],
        linkPositions=[(0, 0, NECK_TOP - BODY_LENGTH / 2 + CAP_LENGTH / 2), (0, 0, 0), (0, 0, shoulder_z),
                       (0, 0, neck_z)],
        linkOrientations=[(0, 0, 0, 1)] * 4,
        linkInertialFramePositions=[(0, 0, 0)] * 4, linkInertialFrameOrientations=[(0, 0, 0, 1)] * 4,
        linkParentIndices=[0, 1, 0, 0],
        linkJointTypes=[p.JOINT_PRISMATIC, p.JOINT_REVOLUTE, p.JOINT_FIXED, p.JOINT_FIXED],
        linkJointAxis=[(0, 0, 1)] * 4, physicsClientId=client,
    )
    p.changeDynamics(body, CAP, lateralFriction=1.5, physicsClientId=client)
    p.setJointMotorControl2(body, CAP, p.VELOCITY_CONTROL, targetVelocity=0.0, force=THREAD_TORQUE,
                            physicsClientId=client)
    # PyBullet's default joint motor would brake the slider: an unscrewed cap must come up freely.
    p.setJointMotorControl2(body, SLIDER, p.VELOCITY_CONTROL, targetVelocity=0.0, force=0.0, physicsClientId=client)
    _lock(world, body, True)
    return body


def _lock(world, body: int, locked: bool) -> None:
    """Hold the cap on the neck (the thread engaged) or let it be pulled up."""
    p.changeDynamics(body, SLIDER, jointLowerLimit=0.0, jointUpperLimit=0.0 if locked else LIFT_TRAVEL,
                     physicsClientId=world.client)


class OpenWineBottle(PlacementTask):
    name = "open_wine_bottle"
    description = "Unscrew the wine bottle's cap (two twists of the hand) and lift it off the bottle."
    categories = ("screw",)

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        return ["open the wine bottle", "screw open the wine bottle",
                "unscrew the bottle cap then remove it from the wine bottle", "take the cap off the wine bottle"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        (x0, x1), (y0, y1) = REGION
        self.xy = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        self.bottle = _make_bottle(world, self.xy)
        self.locked = True
        self.world = world

    def cap_turn(self, world) -> float:
        return float(p.getJointState(self.bottle, CAP, physicsClientId=world.client)[0])

    def cap_lift(self, world) -> float:
        return float(p.getJointState(self.bottle, SLIDER, physicsClientId=world.client)[0])

    def on_step(self, world) -> None:
        # The thread: the cap comes free once turned far enough, and catches again if turned back while on the neck
        # (a locked cap pulled hard gives a little: that is not lifting it).
        locked = self.cap_turn(world) < UNSCREWED and (self.locked or self.cap_lift(world) < ON_NECK)
        if locked != self.locked:
            _lock(world, self.bottle, locked)
            self.locked = locked

    def _twists(self, world, n: int) -> list[KeyframeTarget]:
        """Grip the cap from above, then ``n`` anticlockwise twists (letting go and turning back between them),
        then pull straight up."""
        grip = np.array([*self.xy, NECK_TOP + CAP_LENGTH - GRIP_BELOW_TOP])
        start, turned = motions.top_down(-TWIST / 2), motions.top_down(TWIST / 2)
        keyframes = motions.grasp(grip, start, above=0.08)[:3]
        for i in range(n):
            if i:
                keyframes += [KeyframeTarget(motions.pose(grip, turned), motions.OPEN, "gripper"),
                              KeyframeTarget(motions.pose(grip, start), motions.OPEN, "cartesian"),
                              KeyframeTarget(motions.pose(grip, start), motions.CLOSED, "gripper")]
            keyframes.append(KeyframeTarget(motions.pose(grip, turned), motions.CLOSED, "cartesian"))
        return keyframes + motions.lift(motions.raised(grip, LIFT), turned)

    def expert(self, world) -> list[KeyframeTarget]:
        return self._twists(world, 2)

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Twist only once (the thread still holds) and pull."""
        return self._twists(world, 1)

    def success(self, world) -> bool:
        return self.cap_lift(world) >= LIFTED

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        return [np.array([*self.xy, NECK_TOP + CAP_LENGTH])]

    def scene_facts(self) -> dict:
        return {"bottle": [round(float(v), 6) for v in self.xy], "cap_top": round(NECK_TOP + CAP_LENGTH, 6)}
