"""A task's scene at the start of an episode, and what the recorder sees of it at one instant."""

from __future__ import annotations

import numpy as np

from demo_factory.record import Frame, RobotState
from demo_factory.rollout.perturbations import apply_perturbations
from demo_factory.sim import DEFAULT_CAMERAS, HOME, World
from demo_factory.tasks import Task, Variation, get_task

SETTLE_BEFORE_STEPS = 48  # let the scene come to rest before the first observation
SETTLE_AFTER_STEPS = 120  # "stable for a moment" before the success check


def start_scene(task: Task, variation: Variation, seed: int, cameras=DEFAULT_CAMERAS,
                image_size: tuple[int, int] = (128, 128), perturbations=()) -> World:
    """A new world holding `task`'s scene for `variation`, laid out from `seed`: the arm at home with the
    task's starting gripper, the scene at rest, the episode clock at 0 and the task watching every physics
    step (`task.on_step`, e.g. which buttons went down). The caller closes the world.

    ``perturbations`` names factors of `rollout.perturbations` to apply to the built scene (drawn from `seed`; what
    they drew is in ``world.perturbations``)."""
    world = World(cameras, tuple(image_size))
    try:
        world.reset_arm(HOME, gripper_open=1.0 if task.gripper_starts_open else 0.0)
        task.build_scene(world, variation, np.random.default_rng(seed))
        if perturbations:
            world.perturbations = apply_perturbations(world, task, variation, seed, perturbations)
        world.step(SETTLE_BEFORE_STEPS)
    except BaseException:
        world.close()
        raise
    world.step_count = 0  # the episode's clock starts once the scene is at rest
    world.step_callbacks.append(task.on_step)
    return world


def observe(world: World, keyframe_index: int, is_keyframe: bool, is_dense: bool) -> Frame:
    """The robot's state and every camera's images now, as one recorded frame."""
    return Frame(
        time_ns=world.time_ns,
        is_keyframe=is_keyframe,
        is_dense=is_dense,
        keyframe_index=keyframe_index,
        robot=RobotState(
            joint_positions=world.joint_positions(),
            gripper_pose=world.gripper_pose(),
            gripper_open=world.gripper_command,
            finger_width=world.finger_width(),
        ),
        cameras=world.render_cameras(),
    )


def start_views(task_name: str, variation_id: int, seed: int, names, image_size) -> dict[str, np.ndarray]:
    """Every camera's RGB at the start of an episode's scene under the named perturbations: {camera: image}."""
    task = get_task(task_name)
    world = start_scene(task, task.variation(variation_id), seed, DEFAULT_CAMERAS, tuple(image_size), tuple(names))
    try:
        return {name: view.rgb for name, view in world.render_cameras().items()}
    finally:
        world.close()
