"""The chest of drawers' own checks: drawers stay put, joint limits hold, and the success tests (no planning)."""

import numpy as np
import pybullet as p
import pytest

from demo_factory.rollout import SETTLE_AFTER_STEPS, start_scene
from demo_factory.sim.camera import DEFAULT_CAMERAS
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


def _links_seen(world, spec, size: int = 128) -> np.ndarray:
    """A fixed camera's segmentation with link indices too: ``(body, link)`` per pixel (link -1 = base)."""
    view = p.computeViewMatrix(spec.eye, spec.target, spec.up, physicsClientId=world.client)
    projection = p.computeProjectionMatrixFOV(spec.fov_deg, 1.0, spec.near, spec.far, physicsClientId=world.client)
    seg = np.asarray(p.getCameraImage(size, size, view, projection, renderer=p.ER_TINY_RENDERER, shadow=0,
                                      flags=p.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX,
                                      physicsClientId=world.client)[4]).reshape(size, size)
    return np.stack([np.where(seg < 0, -1, seg & 0xFFFFFF), np.where(seg < 0, -2, (seg >> 24) - 1)], axis=-1)


@pytest.mark.parametrize("name", ["open_drawer", "close_drawer"])
def test_both_shoulder_cameras_see_the_instructed_handle(name):
    """A policy must see the handle the instruction names: a few whole pixels of its bar in each shoulder
    camera's 128 x 128 image, clear of the image's border (the chest's top drawer once stood above their view)."""
    task = get_task(name)
    for drawer in DRAWERS:
        for seed in range(4):
            world = start_scene(task, task.variation_of(drawer), seed, image_size=(128, 128))
            try:
                for spec in (c for c in DEFAULT_CAMERAS if not c.on_hand):
                    seen = _links_seen(world, spec)
                    bar = (seen[..., 0] == task.chest.body) & (seen[..., 1] == task.chest.bars[drawer])
                    rows, cols = np.nonzero(bar)
                    assert bar.sum() >= 8, (drawer, seed, spec.name, int(bar.sum()))
                    assert min(rows.min(), cols.min()) > 0 and max(rows.max(), cols.max()) < 127, (drawer, seed, spec.name)
            finally:
                world.close()
