"""The screw tasks' mechanisms: the wine bottle's thread and the oven's placements."""

import numpy as np
import pybullet as p

from demo_factory.rollout import start_scene
from demo_factory.sim.camera import DEFAULT_CAMERAS
from demo_factory.tasks import get_task
from demo_factory.tasks import open_wine_bottle as wine
from demo_factory.tasks import turn_oven_on as oven


def _pull_cap(task, world, force: float = 20.0, steps: int = 120) -> float:
    for _ in range(steps):
        p.applyExternalForce(task.bottle, wine.CAP, (0, 0, force), (0, 0, 0), p.LINK_FRAME,
                             physicsClientId=world.client)
        world.step()
    return task.cap_lift(world)


def test_the_wine_cap_comes_off_only_once_unscrewed():
    task = get_task("open_wine_bottle")
    world = start_scene(task, task.split_variations("train")[0], 3, image_size=(32, 32))
    try:
        world.step(240)  # nothing moves by itself
        assert task.cap_turn(world) == 0.0 and task.cap_lift(world) == 0.0
        p.resetJointState(task.bottle, wine.CAP, wine.UNSCREWED - 0.3, physicsClientId=world.client)
        assert _pull_cap(task, world) < wine.ON_NECK and not task.success(world)
        p.resetJointState(task.bottle, wine.CAP, wine.UNSCREWED + 0.1, physicsClientId=world.client)
        world.step()
        assert _pull_cap(task, world) >= wine.LIFTED and task.success(world)
    finally:
        world.close()


def test_the_oven_knobs_rest_and_the_power_knob_never_faces_the_arm_head_on():
    for seed in range(8):
        task = get_task("turn_oven_on")
        world = start_scene(task, task.split_variations("train")[0], seed, image_size=(32, 32))
        try:
            knob = task.knob_point(oven.POWER_KNOB, oven.GRIP_OUT)
            assert abs(np.arctan2(knob[1], knob[0]) - task.yaw) >= oven.MIN_SKEW
            world.step(240)
            assert all(abs(task.knob_angle(world, i)) < 1e-6 for i in range(len(task.knobs)))
        finally:
            world.close()


def test_both_shoulder_cameras_see_the_oven_power_knob():
    """A policy must see the knob it turns: a few whole pixels of it in each shoulder camera's 128 x 128
    image, clear of the border (the oven's front once turned edge-on to one camera or out of its view)."""
    task = get_task("turn_oven_on")
    for seed in range(8):
        world = start_scene(task, task.split_variations("train")[0], seed, image_size=(128, 128))
        try:
            observations = world.render_cameras()
            for spec in (c for c in DEFAULT_CAMERAS if not c.on_hand):
                knob = observations[spec.name].segmentation == task.knobs[oven.POWER_KNOB]
                rows, cols = np.nonzero(knob)
                assert knob.sum() >= 20, (seed, spec.name, int(knob.sum()))
                assert min(rows.min(), cols.min()) > 0 and max(rows.max(), cols.max()) < 127, (seed, spec.name)
        finally:
            world.close()
