"""OMPL RRTConnect in the Panda's 7-D joint space with PyBullet collision checking.

Determinism. OMPL seeds every random generator from one process-wide seed that can be set only
once, before the first planner is set up; later plans in the same process continue that sequence.
So that attempt ``i`` of a transition depends on its own seed and nothing else, each attempt runs
in a forked child of the simulation process: the child sets its seed, plans against its private
copy of the PyBullet world (it may move the robot freely there) and sends the path back through a
pipe. The parent never creates an OMPL planner, so every child starts from a pristine generator.

The first attempt of a transition first tries the straight line in joint space, checked densely: where
it is free (most tabletop moves) it is the shortest path, found without sampling, so no RRTConnect
tree is grown and nothing needs simplifying. It depends on no seed at all, so it needs no child: it
is checked in this process between ``saveState`` and ``restoreState`` (about 3 ms instead of a fork,
~9 ms here plus copy-on-write faults). They give back every position, velocity and contact point,
not the collision pairs' internal caches: in some scenes the physics afterwards differs at the 1e-7
level from a world that was never moved (recording format 4). Evaluation's ``states_valid`` too.
"""

from __future__ import annotations

import os
import pickle
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import pybullet as p

from demo_factory.sim.world import ARM_JOINTS, GRASP_LINK, JOINT_LOWER, JOINT_UPPER, World

MAX_ATTEMPTS = 10
# Robot link pairs that can collide with each other (adjacent and hand/finger pairs never do).
SELF_COLLISION_PAIRS = tuple(
    (a, b) for a in (-1, 0, 1, 2, 3) for b in (5, 6, 8, 9, 10) if b - a > 2
)
_PAIR_LINKS = tuple(sorted({link for pair in SELF_COLLISION_PAIRS for link in pair}))
# The pairs as indices into _PAIR_LINKS, beside the link ids.
_PAIRS = tuple((_PAIR_LINKS.index(a), _PAIR_LINKS.index(b), a, b) for a, b in SELF_COLLISION_PAIRS)


def attempt_seed(episode_seed: int, transition: int, attempt: int) -> int:
    """The OMPL seed of one attempt: a pure function of the episode seed, transition and attempt."""
    state = np.random.SeedSequence([episode_seed, transition, attempt]).generate_state(1)[0]
    return int(state % (2**31 - 1)) + 1  # OMPL wants a positive seed


@dataclass
class PlannerAttempt:
    """One seeded OMPL attempt for one keyframe transition (no wall-clock figures: see recorder)."""

    keyframe_index: int
    attempt: int  # 0..9
    seed: int
    status: str  # "exact", "approximate", "timeout", "invalid_start", "invalid_goal", ...
    path_length: float  # joint-space length in radians, 0 when no path


@dataclass
class PlanResult:
    """The outcome of up to ``MAX_ATTEMPTS`` attempts for one transition."""

    path: list[np.ndarray] | None  # joint waypoints from start to goal, None when every attempt failed
    attempts: list[PlannerAttempt] = field(default_factory=list)
    solve_seconds: list[float] = field(default_factory=list)  # wall-clock per attempt (not recorded in MCAP)

    @property
    def ok(self) -> bool:
        return self.path is not None


class CollisionChecker:
    """Robot-vs-scene and robot self-collision queries on a world whose robot may be moved freely."""

    def __init__(self, world: World, margin: float = 0.003, ignore_bodies=(), grasped: tuple | None = None):
        self.world = world
        self.client = world.client
        self.robot = world.robot
        self.margin = margin
        self.ignore = set(ignore_bodies)
        self.grasped = grasped  # (body, position_in_grasp, orientation_in_grasp)
        if grasped is not None:
            self.ignore.add(grasped[0])

    def set_configuration(self, q) -> None:
        p.resetJointStatesMultiDof(self.robot, ARM_JOINTS, [[v] for v in np.asarray(q, dtype=float).tolist()],
                                   physicsClientId=self.client)
        if self.grasped is not None:
            body, pos, orn = self.grasped
            state = p.getLinkState(self.robot, GRASP_LINK, computeForwardKinematics=True, physicsClientId=self.client)
            wpos, worn = p.multiplyTransforms(state[4], state[5], pos, orn)
            p.resetBasePositionAndOrientation(body, wpos, worn, physicsClientId=self.client)

    def in_collision(self) -> bool:
        p.performCollisionDetection(physicsClientId=self.client)
        for contact in p.getContactPoints(bodyA=self.robot, physicsClientId=self.client):
            other = contact[2]
            if other != self.robot and other not in self.ignore and contact[8] < self.margin:
                return True
        if self.grasped is not None:
            body = self.grasped[0]
            for contact in p.getContactPoints(bodyA=body, physicsClientId=self.client):
                if contact[2] != self.robot and contact[2] not in self.ignore and contact[8] < self.margin:
                    return True
        return self._self_collision()

    def _self_collision(self) -> bool:
        """Whether a pair of SELF_COLLISION_PAIRS touches. The exact query runs only for pairs whose
        bounding boxes overlap (PyBullet's boxes contain the shapes, so the answer is the same); most
        pairs of a configuration are far apart."""
        robot, client = self.robot, self.client
        boxes = [p.getAABB(robot, link, physicsClientId=client) for link in _PAIR_LINKS]
        for i, j, a, b in _PAIRS:
            (a_low, a_high), (b_low, b_high) = boxes[i], boxes[j]
            if (a_low[0] <= b_high[0] and b_low[0] <= a_high[0] and a_low[1] <= b_high[1]
                    and b_low[1] <= a_high[1] and a_low[2] <= b_high[2] and b_low[2] <= a_high[2]
                    and p.getClosestPoints(robot, robot, 0.0, a, b, physicsClientId=client)):
                return True
        return False

    def valid(self, q) -> bool:
        q = np.asarray(q)
        return not (np.any(q < JOINT_LOWER) or np.any(q > JOINT_UPPER)) and self._free(q)

    def _free(self, q) -> bool:
        """No collision at ``q`` (joint limits not checked)."""
        self.set_configuration(q)
        return not self.in_collision()

    def path_valid(self, path, max_step: float = 0.01) -> bool:
        """Check a joint path densely (steps of at most ``max_step`` rad per joint)."""
        for a, b in zip(path[:-1], path[1:]):
            a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
            n = max(1, int(np.ceil(np.max(np.abs(b - a)) / max_step)))
            states = a + np.linspace(0.0, 1.0, n + 1)[:, None] * (b - a)  # limits checked for all at once
            if np.any(states < JOINT_LOWER) or np.any(states > JOINT_UPPER) or not all(map(self._free, states)):
                return False
        return True


class JointPlanner:
    """Plans collision-free joint paths with up to ``MAX_ATTEMPTS`` seeded RRTConnect attempts."""

    def __init__(self, timeout: float = 2.0, resolution: float = 0.002, margin: float = 0.003):
        self.timeout = timeout
        self.resolution = resolution  # OMPL validity-checking resolution (fraction of the space extent)
        self.margin = margin

    def plan(self, world: World, start, goal, episode_seed: int, transition: int, grasped=None,
             ignore_bodies=(), max_attempts: int = MAX_ATTEMPTS) -> PlanResult:
        """Plan from ``start`` to ``goal`` joints; stops at the first exact solution."""
        result = PlanResult(path=None)
        for attempt in range(max_attempts):
            seed = attempt_seed(episode_seed, transition, attempt)
            began = time.perf_counter()
            status, path = None, None
            if attempt == 0:
                status, path = self._straight_line(world, start, goal, grasped, ignore_bodies)
            if status is None:
                status, path = self._attempt_in_child(world, start, goal, seed, grasped, ignore_bodies)
            result.solve_seconds.append(time.perf_counter() - began)
            length = float(sum(np.linalg.norm(b - a) for a, b in zip(path[:-1], path[1:]))) if path else 0.0
            result.attempts.append(PlannerAttempt(transition, attempt, seed, status, round(length, 6)))
            if status == "exact":
                result.path = path
                break
        return result

    def states_valid(self, world, configurations, grasped=None, ignore_bodies=()) -> list[bool]:
        """Collision-check joint configurations without disturbing ``world``."""
        with _restored(world):
            checker = CollisionChecker(world, self.margin, ignore_bodies, grasped)
            return [checker.valid(q) for q in configurations]

    def path_free(self, world, path, grasped=None, ignore_bodies=()) -> bool:
        """Whether a joint path is collision-free (``ignore_bodies`` aside), checked densely here, with the world
        saved before and restored after, bit for bit."""
        with _restored(world):
            return CollisionChecker(world, self.margin, ignore_bodies, grasped).path_valid(path)

    def _straight_line(self, world, start, goal, grasped, ignore_bodies):
        """``("exact", [start, goal])`` where the straight joint line is free, else ``(None, None)``."""
        straight = [np.array(start, dtype=float), np.array(goal, dtype=float)]
        return ("exact", straight) if self.path_free(world, straight, grasped, ignore_bodies) else (None, None)

    def _attempt_in_child(self, world, start, goal, seed, grasped, ignore_bodies):
        outcome = _in_child(lambda: self._solve(world, start, goal, seed, grasped, ignore_bodies))
        return outcome if isinstance(outcome, tuple) else (outcome, None)

    def _solve(self, world, start, goal, seed, grasped, ignore_bodies):
        from ompl import base as ob
        from ompl import geometric as og
        from ompl import util as ou

        checker = CollisionChecker(world, self.margin, ignore_bodies, grasped)
        if not checker.valid(start):
            return "invalid_start", None
        if not checker.valid(goal):
            return "invalid_goal", None
        ou.setLogLevel(ou.LOG_ERROR)
        ou.RNG.setSeed(seed)
        space = ob.RealVectorStateSpace(7)
        bounds = ob.RealVectorBounds(7)
        for i in range(7):
            bounds.setLow(i, float(JOINT_LOWER[i]))
            bounds.setHigh(i, float(JOINT_UPPER[i]))
        space.setBounds(bounds)
        setup = og.SimpleSetup(space)
        setup.setStateValidityChecker(lambda state: checker.valid([state[i] for i in range(7)]))
        si = setup.getSpaceInformation()
        si.setStateValidityCheckingResolution(self.resolution)
        setup.setPlanner(og.RRTConnect(si))
        start_state, goal_state = si.allocState(), si.allocState()
        for i in range(7):
            start_state[i] = float(start[i])
            goal_state[i] = float(goal[i])
        setup.setStartAndGoalStates(start_state, goal_state)
        setup.solve(self.timeout)
        if not setup.haveExactSolutionPath():
            return "timeout", None
        setup.simplifySolution()
        path = setup.getSolutionPath()
        waypoints = [np.array([path.getState(k)[i] for i in range(7)]) for k in range(path.getStateCount())]
        # Belt and braces: re-check densely, so a path through a thin obstacle is never returned.
        if not checker.path_valid(waypoints):
            return "invalid_path", None
        return "exact", waypoints


@contextmanager
def _restored(world: World):
    """Move the world's robot and bodies freely inside; afterwards it is as it was (positions,
    velocities, contact points: PyBullet's saveState / restoreState)."""
    saved = p.saveState(physicsClientId=world.client)
    try:
        yield
    finally:
        p.restoreState(saved, physicsClientId=world.client)
        p.removeState(saved, physicsClientId=world.client)


def _in_child(work):
    """Run ``work()`` in a forked child and return its (pickled) result.

    The child owns a copy-on-write copy of the whole process, PyBullet worlds included, so it may
    move robots and seed OMPL freely; nothing it does reaches the parent. A crash or exception in
    the child comes back as an ``"error: ..."`` string.
    """
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: compute, report, and leave without running any parent clean-up
        os.close(read_fd)
        try:
            outcome = work()
        except BaseException as exc:  # report, never hang the parent
            outcome = f"error: {type(exc).__name__}: {exc}"
        with os.fdopen(write_fd, "wb") as pipe:
            pickle.dump(outcome, pipe)
        os._exit(0)
    os.close(write_fd)
    with os.fdopen(read_fd, "rb") as pipe:
        data = pipe.read()
    os.waitpid(pid, 0)
    return pickle.loads(data) if data else "error: planner process died"
