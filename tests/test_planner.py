"""The OMPL planner: seeded attempts, determinism across processes, and collision-free paths."""

import json
import subprocess
import sys

import numpy as np
import pytest

from demo_factory.planning import MAX_ATTEMPTS, CollisionChecker, JointPlanner, attempt_seed
from demo_factory.sim import TOP_DOWN, Kinematics, World

WALL_HALF = (0.2, 0.003, 0.25)  # a 6 mm thin wall across the workspace
WALL_CENTRE = (0.45, 0.0, 0.25)


def wall_scene():
    world = World()
    wall = world.add_box(WALL_HALF, WALL_CENTRE, (0.5, 0.5, 0.5, 1), mass=0.0)
    kinematics = Kinematics()
    start = kinematics.inverse([0.45, 0.2, 0.1, *TOP_DOWN])
    goal = kinematics.inverse([0.45, -0.2, 0.1, *TOP_DOWN])
    kinematics.close()
    world.reset_arm(start)
    return world, wall, start, goal


def test_path_across_a_thin_wall_never_touches_it():
    world, wall, start, goal = wall_scene()
    result = JointPlanner().plan(world, start, goal, episode_seed=3, transition=1)
    assert result.ok and result.attempts[-1].status == "exact"
    # Re-check every path densely (1 mrad steps) with no safety margin: no contact with the wall.
    checker = CollisionChecker(world, margin=0.0)
    assert checker.path_valid(result.path, max_step=0.001)
    assert np.allclose(result.path[0], start) and np.allclose(result.path[-1], goal)
    world.close()


def test_unreachable_goal_exhausts_exactly_ten_seeded_attempts():
    world, wall, start, _ = wall_scene()
    kinematics = Kinematics()
    inside_wall = kinematics.inverse([0.45, 0.0, 0.1, *TOP_DOWN])  # the fingers would be in the wall
    kinematics.close()
    result = JointPlanner().plan(world, start, inside_wall, episode_seed=3, transition=2)
    assert not result.ok and result.path is None
    assert len(result.attempts) == MAX_ATTEMPTS == 10
    assert [a.attempt for a in result.attempts] == list(range(10))
    assert [a.seed for a in result.attempts] == [attempt_seed(3, 2, i) for i in range(10)]
    assert len({a.seed for a in result.attempts}) == 10
    assert {a.status for a in result.attempts} == {"invalid_goal"}
    world.close()


def test_timeouts_are_retried_with_new_seeds():
    world, _, start, goal = wall_scene()
    result = JointPlanner(timeout=1e-6).plan(world, start, goal, episode_seed=1, transition=1, max_attempts=3)
    assert [a.status for a in result.attempts] == ["timeout"] * 3 and not result.ok
    world.close()


def test_same_seed_same_path_regardless_of_earlier_plans():
    world, _, start, goal = wall_scene()
    planner = JointPlanner()
    first = planner.plan(world, start, goal, episode_seed=11, transition=1).path
    planner.plan(world, start, goal, episode_seed=12, transition=1)  # something else in between
    again = planner.plan(world, start, goal, episode_seed=11, transition=1).path
    assert len(first) == len(again) and all(np.array_equal(a, b) for a, b in zip(first, again))
    world.close()


PLAN_IN_FRESH_PROCESS = """
import json, sys
sys.path.insert(0, {tests!r})
from test_planner import wall_scene
from demo_factory.planning import JointPlanner
world, _, start, goal = wall_scene()
path = JointPlanner().plan(world, start, goal, episode_seed=11, transition=1).path
print(json.dumps([list(map(float, q)) for q in path]))
"""


@pytest.mark.slow
def test_same_seed_same_path_in_two_fresh_processes():
    import pathlib

    code = PLAN_IN_FRESH_PROCESS.format(tests=str(pathlib.Path(__file__).parent))
    paths = [
        json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.splitlines()[-1])
        for _ in range(2)
    ]
    assert paths[0] == paths[1] and len(paths[0]) >= 2


def free_line_scene():
    """An empty table and two hand poses joined by a free straight joint line; the arm at the first."""
    world = World()
    kinematics = Kinematics()
    start = kinematics.inverse([0.45, 0.2, 0.2, *TOP_DOWN])
    goal = kinematics.inverse([0.5, -0.1, 0.15, *TOP_DOWN])
    kinematics.close()
    world.reset_arm(start)
    return world, start, goal


def test_a_free_straight_line_is_the_path_without_sampling():
    world, start, goal = free_line_scene()
    result = JointPlanner().plan(world, start, goal, episode_seed=5, transition=0)
    assert [a.status for a in result.attempts] == ["exact"]
    assert len(result.path) == 2 and np.array_equal(result.path[0], start) and np.array_equal(result.path[1], goal)
    world.close()


def test_the_straight_line_check_gives_the_world_back_as_it_was():
    """The straight line is checked in this process: robot and a carried box, positions and velocities,
    are exactly as before afterwards (the check moved both along the line)."""
    import pybullet as p

    world, _, goal = free_line_scene()
    box = world.add_box((0.02,) * 3, (0.3, -0.3, 0.02), (0.2, 0.8, 0.2, 1))
    world.command_arm(goal)
    world.step(5)  # moving: velocities are not zero

    def state():
        joints = p.getJointStates(world.robot, range(p.getNumJoints(world.robot, physicsClientId=world.client)),
                                  physicsClientId=world.client)
        return ([(s[0], s[1]) for s in joints], p.getBasePositionAndOrientation(box, physicsClientId=world.client),
                p.getBaseVelocity(box, physicsClientId=world.client))

    before = state()
    carried = (box, (0.0, 0.0, 0.05), (0.0, 0.0, 0.0, 1.0))
    result = JointPlanner().plan(world, world.joint_positions(), goal, episode_seed=5, transition=0, grasped=carried)
    assert [a.status for a in result.attempts] == ["exact"] and len(result.path) == 2
    assert state() == before
    world.close()


def test_self_collision_prefilter_gives_the_exhaustive_answer():
    import pybullet as p

    from demo_factory.planning.planner import SELF_COLLISION_PAIRS
    from demo_factory.sim.world import JOINT_LOWER, JOINT_UPPER

    world = World()
    checker = CollisionChecker(world)
    rng = np.random.default_rng(0)
    touching = 0
    for _ in range(300):
        checker.set_configuration(rng.uniform(JOINT_LOWER, JOINT_UPPER))
        p.performCollisionDetection(physicsClientId=world.client)
        exhaustive = any(p.getClosestPoints(world.robot, world.robot, 0.0, a, b, physicsClientId=world.client)
                         for a, b in SELF_COLLISION_PAIRS)
        assert checker._self_collision() == exhaustive
        touching += exhaustive
    assert touching > 0  # the sample holds self-collisions, so both answers were exercised
    world.close()
