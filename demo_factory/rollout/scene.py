"""A task's scene at the start of an episode, and what the recorder sees of it at one instant."""

from __future__ import annotations

from collections.abc import Sequence

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

    ``perturbations`` names factors of `rollout.perturbations` to apply (drawn from `seed`; what they drew is in
    ``world.perturbations``): the "shape" ones to the task before its scene is built, the others to the scene."""
    world = World(cameras, tuple(image_size))
    try:
        world.reset_arm(HOME, gripper_open=1.0 if task.gripper_starts_open else 0.0)
        drawn = apply_perturbations(world, task, variation, seed, perturbations, before_build=True)
        task.build_scene(world, variation, np.random.default_rng(seed))
        drawn |= apply_perturbations(world, task, variation, seed, perturbations)
        world.perturbations = {name: drawn[name] for name in perturbations}
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
    """Every camera's RGB at the start of an episode's scene under the named perturbations, with their mid-episode
    changes made (a moved button shows where it goes): {camera: image}."""
    task = get_task(task_name)
    world = start_scene(task, task.variation(variation_id), seed, DEFAULT_CAMERAS, tuple(image_size), tuple(names))
    try:
        for event in world.pending_events:
            event()
        return {name: view.rgb for name, view in world.render_cameras().items()}
    finally:
        world.close()


class ExpertKeyframes(Sequence):
    """The expert's keyframes in a scene. After a perturbation moved a task object mid-episode
    (``world.scene_changes``), the keyframe asked for and those after it are the expert's again, from the scene as it
    is then; the ones before stay as they were. Iterating asks for each keyframe when the loop reaches it."""

    def __init__(self, task: Task, world: World):
        self.task, self.world = task, world
        self.keyframes = task.expert(world)
        self.seen = world.scene_changes

    def __len__(self) -> int:
        return len(self.keyframes)

    def __getitem__(self, index):
        if isinstance(index, int) and self.world.scene_changes != self.seen:
            self.keyframes = self.keyframes[:index] + self.task.expert(self.world)[index:]
            self.seen = self.world.scene_changes
        return self.keyframes[index]
