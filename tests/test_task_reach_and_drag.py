"""reach_and_drag's own checks: the target layout every drag relies on, and the success test (no planning)."""

import numpy as np
import pytest

from demo_factory.rollout import SETTLE_AFTER_STEPS, start_scene
from demo_factory.tasks import get_task
from demo_factory.tasks.reach_and_drag import CUBE_HALF, DRAG, DRAG_FAN, MIN_SPACING, N_DISTRACTORS, OFF_FAN


def _scene(seed, variation_index=0):
    task = get_task("reach_and_drag")
    return task, start_scene(task, task.split_variations("train")[variation_index], seed, image_size=(32, 32))


@pytest.mark.parametrize("seed", range(6))
def test_the_instructed_target_and_a_distractor_are_feasible_drags_and_the_scene_repeats(seed):
    task, world = _scene(seed, seed)
    try:
        facts = task.scene_facts()
        colours = list(task.targets)
        assert colours[0] == task.instructed and len(set(colours)) == len(colours)
        assert N_DISTRACTORS[0] <= len(colours) - 1 <= N_DISTRACTORS[1]
        cube = world.body_pose(task.cube)[0][:2]
        points = list(task.targets.values())
        for k, point in enumerate(points):
            drag = point - cube
            assert DRAG[0] - 1e-3 <= np.linalg.norm(drag) <= DRAG[1] + 1e-3
            low, high = DRAG_FAN if k < 2 else OFF_FAN  # towards the robot; only the first two within reach of a drag
            assert low - 1e-3 <= np.arctan2(drag[1], -drag[0]) <= high + 1e-3
        assert all(np.linalg.norm(a - b) >= MIN_SPACING for i, a in enumerate(points) for b in points[i + 1:])
    finally:
        world.close()
    again, world = _scene(seed, seed)
    try:
        assert again.scene_facts() == facts
    finally:
        world.close()


@pytest.mark.parametrize("where, succeeds", [("instructed", True), ("distractor", False), ("short", False)])
def test_success_needs_the_cube_at_rest_on_the_instructed_square(where, succeeds):
    task, world = _scene(3)
    try:
        target = task.targets[task.instructed]
        cube = world.body_pose(task.cube)[0][:2]
        xy = {"instructed": target, "distractor": next(xy for c, xy in task.targets.items() if c != task.instructed),
              "short": target + 0.05 * (cube - target) / np.linalg.norm(cube - target)}[where]
        world.set_body_pose(task.cube, (*xy, CUBE_HALF), (0, 0, 0, 1))
        world.step(SETTLE_AFTER_STEPS)
        assert task.success(world) == succeeds
    finally:
        world.close()


def test_instructions_name_the_colour_and_goal_points_are_the_cube_then_the_target():
    task, world = _scene(4)
    try:
        variation = task.split_variations("train")[0]
        assert all(variation.words[0] in text for text in task.synthetic_instructions(variation))
        cube, target = task.goal_points(world, variation)
        assert np.allclose(cube, world.body_pose(task.cube)[0])
        assert np.allclose(target[:2], task.targets[task.instructed])
    finally:
        world.close()


def test_after_the_grasp_every_keyframe_has_one_orientation_and_a_fixed_offset_from_the_cube_or_the_target():
    """What makes the task learnable: nothing after the grasp depends on the cube-to-target direction."""
    offsets = []
    for seed in range(4):
        task, world = _scene(seed, seed)
        try:
            keyframes = task.expert(world)
            cube = world.body_pose(task.cube)[0][:2]
            target = task.targets[task.instructed]
        finally:
            world.close()
        after = keyframes[4:]  # the grasp is the first four
        assert all(np.allclose(k.pose[3:], after[0].pose[3:]) for k in after)
        start, end = np.array(after[1].pose[:2]), np.array(after[2].pose[:2])
        offsets.append((start - cube, end - target))
    starts, ends = (np.array(column) for column in zip(*offsets))
    assert np.ptp(starts, axis=0).max() < 1e-9
    assert np.ptp(ends, axis=0).max() < 0.01  # the cube's slide after the stop is along the drag
