"""Reach and drag: grasp a hooked stick and drag a cube with it onto the target square of the instructed colour."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from demo_factory.tasks import motions
from demo_factory.tasks.base import Failure, KeyframeTarget, Task
from demo_factory.tasks.objects import Part, add_body, at_rest, free_of_robot, held
from demo_factory.tasks.palette import TOWER_COLOURS, rgba
from demo_factory.tasks.variations import Variation

# The stick: a 30 x 2 x 2 cm handle along its x axis with a short cross piece (the hook) at its +x end, reaching
# out to its +y side. The hook is what gets behind the cube: a straight stick lying flat would have to pass over it.
HANDLE_HALF = (0.15, 0.01, 0.01)  # m, half extents
HOOK_HALF = (0.01, 0.045, 0.01)  # m, half extents: 9 cm of reach beside the handle's axis
HOOK_OFFSET = (HANDLE_HALF[0] - HOOK_HALF[0], HOOK_HALF[1], 0.0)  # hook centre in the stick frame
HOOK_FACE = HOOK_OFFSET[0] - HOOK_HALF[0]  # m: stick-frame x of the hook's inner face (the face that pulls)
STICK_MASS = 0.06  # kg
# Grip near the stick's balance point (the hook moves it ~3 cm towards the hook), so that its weight hardly
# twists it about the fingers' closing axis while it is carried.
GRIP_X = 0.03  # m along the stick from its centre
GRIP_LIFT = 0.002  # grasp frame above the handle's centre (fingertips ~4 mm above the table)
CUBE_HALF = 0.025  # m
CUBE_MASS = 0.08  # kg
CUBE_FRICTION = 0.5
TARGET_HALF = 0.035  # m, half side of a target square
# Where the stick lies at the start: on the robot's left, beside the cube and the targets, hook end away
# from the robot and the hook pointing outwards (+y).
STICK_REGION = ((0.38, 0.46), (0.27, 0.31))
STICK_YAW = 0.25  # rad, at most this far from the world x axis
CUBE_REGION = ((0.64, 0.70), (-0.12, 0.0))
CUBE_YAW = 0.2  # rad, at most this far from the world axes (the hook and the handle square it up as they pull)
# The stick drags with the hand turned square to the world (yaw 0: handle along x, hook end away from the robot,
# hook reaching +y), whichever the target: every keyframe after the grasp has the same orientation and lies at a
# fixed offset from the cube or the target square, which a policy can read from the scene. The cube rides in the
# corner between the hook and the handle, so a drag may go towards the robot (-x) and to its left (+y) by up to
# DRAG_FAN: the hook's inner face pulls, the handle's side pushes.
# The hand then ends >= 0.34 m from the base: closer in, lifting the low hand folds the elbow to its limit.
DRAG = (0.12, 0.21)  # m, cube start to a target centre
DRAG_FAN = (0.0, 0.85)  # rad from the robot's -x towards +y: the targets a drag can reach
OFF_FAN = (-0.7, -0.2)  # rad: where a second distractor lies, a square that no drag with this stick reaches
MIN_SPACING = 0.1  # m between target centres (3 cm between the squares)
N_DISTRACTORS = (1, 2)  # distractor squares of other colours: the first within DRAG_FAN, a second off it
START_GAP = 0.015  # m: the hook's inner face beyond the cube's far face where it is lowered
CLEARANCE = 0.003  # m between the handle and the cube's near side where the hook is lowered
HOVER = 0.006  # m: the stick's bottom above the table while dragging (no table friction on the stick)
ABOVE = 0.08  # m: the stick is carried this far above its dragging height (the hook clears the 5 cm cube)
SLIDE = 0.004  # m: the cube slides on this far after the hook stops
BACK_OFF = (0.01, -0.008)  # m, world xy: the hook and the handle leave the cube before the stick is lifted
TOLERANCE = 0.03  # m: cube centre to the target centre (the cube then lies mostly on the 7 cm square)


def stick_parts() -> list[Part]:
    wood = (0.55, 0.35, 0.2, 1.0)
    return [Part("box", HANDLE_HALF, rgba=wood), Part("box", HOOK_HALF, HOOK_OFFSET, wood)]


def _yaw_of(orientation) -> float:
    return float(Rotation.from_quat(orientation).as_euler("xyz")[2])


def _rotate(yaw: float, local) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([c * local[0] - s * local[1], s * local[0] + c * local[1]])


def _fan_targets(rng: np.random.Generator, cube: np.ndarray, n: int) -> list[np.ndarray]:
    """``n`` target centres ``MIN_SPACING`` apart, each ``DRAG`` from ``cube`` towards the robot: the first two
    within ``DRAG_FAN`` (feasible drags), any further one ``OFF_FAN``."""
    while True:
        angles = np.concatenate([rng.uniform(*DRAG_FAN, min(n, 2)), rng.uniform(*OFF_FAN, max(n - 2, 0))])
        distances = rng.uniform(*DRAG, n)
        points = [cube + d * np.array([-np.cos(a), np.sin(a)]) for a, d in zip(angles, distances)]
        if all(np.linalg.norm(a - b) >= MIN_SPACING for i, a in enumerate(points) for b in points[i + 1:]):
            return points


class ReachAndDrag(Task):
    name = "reach_and_drag"
    description = ("Grasp the hooked stick, lower its hook behind the cube and drag the cube onto the target square of "
                   "the instructed colour; squares of other colours are distractors.")
    categories = ("tools",)
    palette = TOWER_COLOURS
    max_sequence = 1
    n_train = n_test = 10
    split_seed = 20220307

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        c = variation.words[0]
        return [f"use the stick to drag the cube onto the {c} target",
                f"pick up the stick and pull the cube onto the {c} square",
                f"hook the cube with the stick and drag it to the {c} target",
                f"drag the block onto the {c} target using the stick"]

    def build_scene(self, world, variation: Variation, rng: np.random.Generator) -> None:
        self.world = world
        self.instructed = variation.words[0]
        (cx0, cx1), (cy0, cy1) = CUBE_REGION
        cube_xy = np.array([rng.uniform(cx0, cx1), rng.uniform(cy0, cy1)])
        n_distractors = int(rng.integers(N_DISTRACTORS[0], N_DISTRACTORS[1] + 1))
        others = [c for c in self.palette if c != self.instructed]
        colours = [self.instructed, *(str(c) for c in rng.choice(others, n_distractors, replace=False))]
        self.targets = dict(zip(colours, _fan_targets(rng, cube_xy, len(colours))))
        for colour, xy in self.targets.items():
            world.add_box((TARGET_HALF, TARGET_HALF, 0.0005), (*xy, 0.0006), rgba(colour), mass=0.0, collision=False)
        # The cube roughly square to the stick, so the hook meets a face rather than a corner.
        cube_yaw = rng.uniform(-CUBE_YAW, CUBE_YAW)
        self.cube_start = cube_xy
        self.cube = world.add_box((CUBE_HALF,) * 3, (*cube_xy, CUBE_HALF), (0.85, 0.85, 0.9, 1.0), mass=CUBE_MASS,
                                  orientation=Rotation.from_euler("z", cube_yaw).as_quat(), friction=CUBE_FRICTION)
        (sx0, sx1), (sy0, sy1) = STICK_REGION
        stick_yaw = rng.uniform(-STICK_YAW, STICK_YAW)
        self.stick = add_body(world, stick_parts(), (rng.uniform(sx0, sx1), rng.uniform(sy0, sy1), HANDLE_HALF[2]),
                              Rotation.from_euler("z", stick_yaw).as_quat(), mass=STICK_MASS, friction=1.0)

    def expert(self, world) -> list[KeyframeTarget]:
        stick_position, stick_orientation = world.body_pose(self.stick)
        stick_yaw = _yaw_of(stick_orientation)
        grip = [*(stick_position[:2] + _rotate(stick_yaw, (GRIP_X, 0.0))), HANDLE_HALF[2] + GRIP_LIFT]
        # Held with the fingers across the handle, the stick keeps its yaw relative to the hand: turned to yaw 0,
        # its handle lies along x with the hook's inner face HOOK_FACE - GRIP_X ahead of the grasp frame.
        cube = world.body_pose(self.cube)[0][:2]
        target = self.targets[self.instructed]
        extent = CUBE_HALF * (np.cos(CUBE_YAW) + np.sin(CUBE_YAW))  # a turned cube's extent from its centre
        ahead = HOOK_FACE - GRIP_X
        # Lowered with the hook's face START_GAP beyond the cube and the handle CLEARANCE beside it ...
        start = cube + (extent + START_GAP - ahead, -(extent + HANDLE_HALF[1] + CLEARANCE))
        # ... and stopped where the cube, squared up in the corner between the two, comes to rest on the target.
        away = (cube - target) / np.linalg.norm(cube - target)
        end = target + (CUBE_HALF - ahead, -(CUBE_HALF + HANDLE_HALF[1])) + SLIDE * away
        backed = end + BACK_OFF
        drag_z = HANDLE_HALF[2] + GRIP_LIFT + HOVER
        orientation = motions.top_down(0.0)
        return (motions.grasp(grip, motions.top_down(stick_yaw))
                + motions.reach([*start, drag_z + ABOVE], orientation, motions.CLOSED)
                + motions.lift([*start, drag_z], orientation)
                + motions.lift([*end, drag_z], orientation)
                + motions.lift([*backed, drag_z], orientation)
                + motions.lift([*backed, drag_z + ABOVE], orientation))

    def graspable_bodies(self) -> list[int]:
        return [self.stick]

    def wrong_keyframes(self, world) -> list[KeyframeTarget]:
        """Drag the cube onto a distractor square instead."""
        distractor = next(c for c in self.targets if c != self.instructed)
        return self.expert_with(world, instructed=distractor)

    def success(self, world) -> bool:
        position, _ = world.body_pose(self.cube)
        return (float(np.linalg.norm(position[:2] - self.targets[self.instructed])) < TOLERANCE
                and at_rest(world, self.cube) and free_of_robot(world, self.cube))

    def failure(self, world) -> Failure | None:
        """"cube on wrong target" when the cube rests on a distractor square; "cube not moved" when it is within
        1 cm of where it started, with "stick not held" when the stick is not in the gripper either; else "cube
        off target", with its distance."""
        cube = world.body_pose(self.cube)[0][:2]
        wrong = next((c for c, xy in self.targets.items() if c != self.instructed
                      and np.linalg.norm(cube - xy) < TOLERANCE), None)
        if wrong is not None:
            return Failure("cube on wrong target", None, f"the cube is on the {wrong} square, not the {self.instructed}")
        if np.linalg.norm(cube - self.cube_start) < 0.01:
            if not held(world, self.stick):
                return Failure("stick not held", None, "the cube never moved and the stick is not in the gripper")
            return Failure("cube not moved", None, "the stick is held but the cube never moved")
        distance = float(np.linalg.norm(cube - self.targets[self.instructed]))
        return Failure("cube off target", None, f"the cube is {100 * distance:.1f} cm from the {self.instructed} "
                                                f"square's centre (success within {100 * TOLERANCE:.0f} cm)")

    def scene_facts(self) -> dict:
        stick_position, stick_orientation = self.world.body_pose(self.stick)
        return {"targets": {c: [round(float(v), 6) for v in xy] for c, xy in self.targets.items()},
                "cube": [round(float(v), 6) for v in self.world.body_pose(self.cube)[0]],
                "stick": [round(float(v), 6) for v in stick_position],
                "stick_yaw": round(_yaw_of(stick_orientation), 6)}

    def goal_points(self, world, variation: Variation) -> list[np.ndarray]:
        """The cube and the instructed target square, in the instruction's order."""
        return [world.body_pose(self.cube)[0], np.array([*self.targets[variation.words[0]], 0.0])]
