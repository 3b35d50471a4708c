"""The chest of drawers' own checks: drawers stay put, joint limits hold, and the success tests (no planning)."""

import pybullet as p
import pytest

from demo_factory.rollout import SETTLE_AFTER_STEPS, start_scene
from demo_factory.tasks import get_task
from demo_factory.tasks.close_drawer import CLOSED
from demo_factory.tasks.drawers import DRAWERS, TRAVEL
from demo_factory.tasks.open_drawer import OPENED


def _scene(name, drawer, seed=5):
    task = get_task(name)
    return task, start_scene(task, task.variation_of(drawer), seed, image_size=(32, 32))


@pytest.mark.parametrize("name", ["open_drawer", "close_drawer"])
def test_drawers_stay_where_they_are_left_and_within_their_travel(name):
    task, world = _scene(name, "middle")
    chest = task.chest
    try:
        before = {d: chest.opening(d) for d in DRAWERS}
        world.step(2 * 240)
        assert all(abs(chest.opening(d) - before[d]) < 1e-4 for d in DRAWERS)
        for pull, limit in ((-80.0, TRAVEL), (80.0, 0.0)):  # out towards the robot, then back in
            for _ in range(240):
                p.applyExternalForce(chest.body, chest.joints["top"], (pull * chest.axis).tolist(),
                                     chest.bar("top").tolist(), p.WORLD_FRAME, physicsClientId=world.client)
                world.step()
            assert chest.opening("top") == pytest.approx(limit, abs=3e-3)
    finally:
        world.close()


def test_open_drawer_needs_the_instructed_drawer_out_and_the_others_shut():
    task, world = _scene("open_drawer", "top")
    try:
        task.chest.set_opening("top", OPENED + 0.01)
        world.step(SETTLE_AFTER_STEPS)
        assert task.success(world)
        task.chest.set_opening("bottom", OPENED + 0.01)  # opening every drawer is not opening the top one
        world.step(SETTLE_AFTER_STEPS)
        assert not task.success(world)
    finally:
        world.close()


def test_close_drawer_needs_the_instructed_drawer_nearly_shut():
    task, world = _scene("close_drawer", "bottom")
    try:
        assert task.chest.opening("bottom") > CLOSED
        task.chest.set_opening("bottom", CLOSED + 0.01)
        world.step(SETTLE_AFTER_STEPS)
        assert not task.success(world)
        task.chest.set_opening("bottom", CLOSED - 0.01)
        world.step(SETTLE_AFTER_STEPS)
        assert task.success(world)
    finally:
        world.close()
