"""The long-term tasks' own checks: stack_blocks' stack test and wipe_desk's dirt tracking (no planning)."""

import numpy as np
import pybullet as p
import pytest

from demo_factory.rollout import SETTLE_AFTER_STEPS, start_scene
from demo_factory.tasks import get_task
from demo_factory.tasks.stack_blocks import CUBE, N_STACK, PLATFORM_TOP
from demo_factory.tasks.wipe_desk import SPONGE_HALF, STROKE_GAP


def _scene(name, seed=5):
    task = get_task(name)
    return task, start_scene(task, task.split_variations("train")[0], seed, image_size=(32, 32))


def _stack(task, world, blocks):
    """Teleport ``blocks`` into a tower on the platform, bottom first, and let it settle."""
    for level, block in enumerate(blocks):
        world.set_body_pose(block, (*task.platform_xy, PLATFORM_TOP + (level + 0.5) * CUBE + 0.001), (0, 0, 0, 1))
    world.step(SETTLE_AFTER_STEPS)


@pytest.mark.parametrize("case, succeeds", [("instructed", True), ("one short", False), ("distractor on top", False)])
def test_stack_blocks_needs_three_instructed_blocks_stacked_on_the_platform(case, succeeds):
    task, world = _scene("stack_blocks")
    try:
        assert not task.success(world)
        tower = {"instructed": task.blocks[:N_STACK], "one short": task.blocks[:N_STACK - 1],
                 "distractor on top": [*task.blocks[:N_STACK - 1], task.distractors[0]]}[case]
        _stack(task, world, tower)
        assert task.success(world) == succeeds
    finally:
        world.close()


def test_stack_blocks_instructions_name_the_colour_and_the_count():
    task = get_task("stack_blocks")
    for variation in task.variations:
        assert all(variation.words[0] in text and "three" in text for text in task.synthetic_instructions(variation))


def _alpha(world, body):
    return p.getVisualShapeData(body, physicsClientId=world.client)[0][7][3]


def test_wipe_desk_hides_the_spots_the_lowered_sponge_passes_over_only():
    task, world = _scene("wipe_desk")
    try:
        first, *others = task.spots
        xy = task.spot_xy[first]
        # Held high over a spot: nothing is wiped.
        world.set_body_pose(task.sponge, (*xy, 0.05), (0, 0, 0, 1))
        task.on_step(world)
        assert not task.wiped and _alpha(world, first) == 1.0
        # Lowered onto the table over it: that spot goes, the rest stay.
        world.set_body_pose(task.sponge, (*xy, SPONGE_HALF[2] + STROKE_GAP), (0, 0, 0, 1))
        task.on_step(world)
        assert first in task.wiped and _alpha(world, first) == 0.0
        assert not task.success(world) or not others
        for spot in others:
            world.set_body_pose(task.sponge, (*task.spot_xy[spot], SPONGE_HALF[2]), (0, 0, 0, 1))
            task.on_step(world)
        assert task.success(world)
        assert task.scene_facts()["wiped"] == list(range(len(task.spots)))
    finally:
        world.close()


@pytest.mark.parametrize("name", ["stack_blocks", "wipe_desk"])
def test_the_same_seed_builds_the_same_scene(name):
    facts = []
    for _ in range(2):
        task, world = _scene(name, seed=11)
        try:
            facts.append(task.scene_facts())
        finally:
            world.close()
    assert facts[0] == facts[1]
    assert np.isfinite(np.array(facts[0]["sponge" if name == "wipe_desk" else "platform"])).all()
