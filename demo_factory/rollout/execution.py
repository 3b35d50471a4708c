"""Drives the simulated arm through keyframes: planned or Cartesian moves, then the gripper.

Used by the generator (expert keyframes) and by evaluation (predicted keyframes) alike, so a
policy's keyframes are executed exactly as the expert's are.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pybullet as p

from demo_factory.planning import JointPlanner, PlanResult
from demo_factory.sim.kinematics import Kinematics, pose_error, slerp_poses
from demo_factory.sim.world import TIME_STEP, World
from demo_factory.tasks.base import KeyframeTarget

JOINT_SPEED = 1.2  # rad/s, the fastest joint on a planned path
# Straight-line moves: 0.2 m/s, IK waypoints 1 cm apart (joint-space interpolation between them strays
# at most 0.13 mm from the line, measured). At 0.12 m/s and 5 mm they took half of a push_buttons
# episode's physics steps and most of its IK calls; every expert of both suites still succeeds.
CARTESIAN_SPEED = 0.2  # m/s along straight-line moves
CARTESIAN_TURN_SPEED = 1.0  # rad/s when the hand turns in place
CARTESIAN_STEP = 0.01  # metres between IK waypoints on a straight line
CARTESIAN_TURN_STEP = np.radians(3)  # radians between IK waypoints when the hand turns
MAX_JOINT_JUMP = 0.25  # rad between consecutive straight-line IK solutions (else: not a straight move)
SETTLE_STEPS = 120
PUSH_MOVE_MAX = 0.25  # metres: a predicted move this short whose straight line only movable objects block goes straight
GRIPPER_STEPS = (24, 144)  # at least / at most this many steps to open or close


@dataclass
class TransitionOutcome:
    """What happened when one keyframe was executed."""

    ok: bool
    reason: str | None = None  # "unreachable", "planning", "cartesian"
    plan: PlanResult | None = None


@dataclass
class KeyframeExecutor:
    """Executes keyframe targets in a world, with the seeded planner for planned moves."""

    world: World
    kinematics: Kinematics
    planner: JointPlanner
    episode_seed: int
    graspable: list[int] = field(default_factory=list)

    def execute(self, target: KeyframeTarget, transition: int, line=None) -> TransitionOutcome:
        """Reach ``target`` (planned, Cartesian or in place), then apply its gripper command; ``line``: the
        Cartesian move's joint waypoints where already solved."""
        outcome = TransitionOutcome(ok=True)
        if target.motion == "planned":
            outcome = self._planned(np.asarray(target.pose), transition)
        elif target.motion == "cartesian":
            outcome = self._cartesian(np.asarray(target.pose), line)
        if outcome.ok and target.gripper_open != self.world.gripper_command:
            self._actuate_gripper(target.gripper_open)
        return outcome

    def execute_predicted(self, pose, gripper_open: float, transition: int) -> TransitionOutcome:
        """Execute a predicted keyframe as in the HiveFormer paper's RLBench: a straight line where it can, else
        a planned path, then grip.

        The move goes straight (as the expert's own contact moves do) where its start or goal touches the scene
        on purpose (pressing, grasping, placing, lifting off, pulling out: the planner needs free ends), where the
        straight line is free, or, when short, where only movable objects (loose ones, drawers) block it: the
        move is meant to push or drag them. Otherwise the seeded OMPL planner finds the path. (RLBench's planning
        action mode also tries the straight line first, and checks no collisions.)
        """
        pose = np.asarray(pose, dtype=float).copy()
        pose[3:] /= np.linalg.norm(pose[3:]) or 1.0
        position_error, rotation_error = pose_error(self.world.gripper_pose(), pose)
        line = None
        if position_error < 1e-3 and rotation_error < 1e-2:
            motion = "gripper"
        else:
            start = self.world.joint_positions()
            goal = self.kinematics.inverse(pose, seed=start)
            if goal is None:
                return TransitionOutcome(False, "unreachable")
            grasped = self._grasped_relative()
            touches = not all(self.planner.states_valid(self.world, [start, goal], grasped))
            if not touches:
                line = self._clear_line(pose, grasped, position_error)
            motion = "cartesian" if touches or line is not None else "planned"
        return self.execute(KeyframeTarget(tuple(pose), float(gripper_open >= 0.5), motion), transition, line)

    def _clear_line(self, pose: np.ndarray, grasped, distance: float) -> list[np.ndarray] | None:
        """The joint waypoints of a straight move to ``pose`` where it exists and is free, or (within
        PUSH_MOVE_MAX) blocked by movable bodies only; else None."""
        line = self._line(pose)
        if line is None or self.planner.path_free(self.world, line, grasped):
            return line
        held = grasped[0] if grasped is not None else None
        movable = [body for body in self.world.obstacle_bodies() if body != held and _movable(self.world.client, body)]
        pushes = distance <= PUSH_MOVE_MAX and bool(movable) and self.planner.path_free(self.world, line, grasped, movable)
        return line if pushes else None

    # -- motions --------------------------------------------------------------------------
    def _planned(self, pose: np.ndarray, transition: int) -> TransitionOutcome:
        start = self.world.joint_positions()
        goal = self.kinematics.inverse(pose, seed=start)
        if goal is None:
            return TransitionOutcome(False, "unreachable")
        plan = self.planner.plan(
            self.world, start, goal, self.episode_seed, transition, grasped=self._grasped_relative()
        )
        if not plan.ok:
            return TransitionOutcome(False, "planning", plan)
        # Planning children moved their own copies of the robot, never this one.
        self._follow(plan.path, JOINT_SPEED)
        return TransitionOutcome(True, None, plan)

    def _cartesian(self, pose: np.ndarray, waypoints=None) -> TransitionOutcome:
        waypoints = waypoints or self._line(pose)
        if waypoints is None:
            return TransitionOutcome(False, "cartesian")
        distance, rotation = pose_error(self.world.gripper_pose(), pose)
        seconds = max(distance / CARTESIAN_SPEED, rotation / CARTESIAN_TURN_SPEED)
        self._follow(waypoints, speed=None, segment_seconds=max(seconds / (len(waypoints) - 1), TIME_STEP))
        return TransitionOutcome(True)

    def _line(self, pose: np.ndarray) -> list[np.ndarray] | None:
        """The joint waypoints of a straight move of the grasp frame to ``pose`` (from the current joints), or None
        where inverse kinematics fails or jumps on the way."""
        start_pose = self.world.gripper_pose()
        distance, rotation = pose_error(start_pose, pose)
        # A waypoint every CARTESIAN_STEP of travel and every CARTESIAN_TURN_STEP of turning (a wrist turn in place).
        n = max(1, int(np.ceil(distance / CARTESIAN_STEP)), int(np.ceil(rotation / CARTESIAN_TURN_STEP)))
        waypoints = [self.world.joint_positions()]
        for waypoint_pose in slerp_poses(start_pose, pose, n):
            q_next = self.kinematics.inverse(waypoint_pose, seed=waypoints[-1])
            if q_next is None or np.max(np.abs(q_next - waypoints[-1])) > MAX_JOINT_JUMP:
                return None
            waypoints.append(q_next)
        return waypoints

    def _follow(self, waypoints, speed: float | None, segment_seconds: float | None = None) -> None:
        """Track a joint path with the position controllers, then let the arm settle on its end."""
        world = self.world
        for a, b in zip(waypoints[:-1], waypoints[1:]):
            duration = segment_seconds if speed is None else float(np.max(np.abs(b - a))) / speed
            steps = max(1, int(np.ceil(duration / TIME_STEP)))
            velocity = (b - a) / (steps * TIME_STEP)
            targets = a + np.outer(np.arange(1, steps + 1) / steps, b - a)  # a + (b - a) * (i / steps)
            for target in targets:
                world.command_arm(target, velocity)
                world.step()
        goal = waypoints[-1]
        world.command_arm(goal)
        for _ in range(SETTLE_STEPS):
            positions, velocities = world.arm_state()
            if np.max(np.abs(positions - goal)) < 1e-3 and np.max(np.abs(velocities)) < 1e-2:
                break
            world.step()

    def _actuate_gripper(self, gripper_open: float) -> None:
        world = self.world
        world.set_gripper(gripper_open)
        lo, hi = GRIPPER_STEPS
        previous = world.finger_width()
        for i in range(hi):
            world.step()
            width = world.finger_width()
            if i >= lo and abs(width - previous) < 1e-5:
                break
            previous = width
        if gripper_open:
            world.grasped = None
        else:
            body = world.held_object(self.graspable)
            world.grasped = body

    def _grasped_relative(self):
        """The held body and its pose in the grasp frame, for the planner to carry it along."""
        body = self.world.grasped
        if body is None:
            return None
        client = self.world.client
        grasp = self.world.gripper_pose()
        obj_pos, obj_orn = p.getBasePositionAndOrientation(body, physicsClientId=client)
        inv_pos, inv_orn = p.invertTransform(grasp[:3].tolist(), grasp[3:].tolist())
        rel_pos, rel_orn = p.multiplyTransforms(inv_pos, inv_orn, obj_pos, obj_orn)
        return body, rel_pos, rel_orn


def _movable(client: int, body: int) -> bool:
    """A body that can move: a loose one (its base has mass) or one with a moving joint (a drawer, a lid, a knob)."""
    if p.getDynamicsInfo(body, -1, physicsClientId=client)[0] > 0:
        return True
    return any(p.getJointInfo(body, joint, physicsClientId=client)[2] != p.JOINT_FIXED
               for joint in range(p.getNumJoints(body, physicsClientId=client)))
