"""Policies that ``demo-factory eval`` can run: a LeRobot checkpoint, or references.

A policy has ``name``, ``reset(env)`` at the start of each episode and ``act(env) -> (8,)``, the
action for ``env.frame`` (the observation) and ``env.task_description`` (the instruction) in the
environment's action space (``env.action_space_name``): the next keyframe ``[x, y, z, qx, qy, qz, qw,
open]`` for a ``KeyframeEnv``; for a ``DenseEnv`` the next control tick's ``joints`` (7 positions +
gripper command) or ``ee`` (grasp-frame pose + gripper command).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from demo_factory.convert.features import ACTION_SIZE, observation_item, robot_action
from demo_factory.planning import JointPlanner
from demo_factory.record import RobotState
from demo_factory.rollout import ExpertKeyframes, KeyframeExecutor


class ExpertPolicy:
    """The scripted expert as a reference policy (privileged: reads the scene, not the cameras).

    In a keyframe environment it emits the expert's keyframes. In a dense one it replays the expert's
    dense actions: at ``reset`` it runs the expert (the same keyframes, planner and seeds as the
    generator) in a copy of the episode's scene and keeps the robot's state at every control tick;
    then the action at tick t is the state at tick t + 1, exactly as a dense export labels its frames.
    """

    name = "expert"

    def reset(self, env) -> None:
        self.trajectory = expert_trajectory(env) if env.action_space_name != "keyframe" else None

    def act(self, env) -> np.ndarray:
        if self.trajectory is not None:
            robot = self.trajectory[min(env.steps + 1, len(self.trajectory) - 1)]
            return robot_action(robot, env.action_space_name).astype(np.float64)
        targets = env.expert_keyframes
        target = targets[min(env.steps, len(targets) - 1)]
        return np.array([*target.pose, target.gripper_open])


def expert_trajectory(env) -> list[RobotState]:
    """The robot's state at every control tick (tick 0 = the start) while the expert solves ``env``'s
    current episode in a copy of its scene."""
    from demo_factory.evaluate.env import episode_world

    world, task = episode_world(env.episode, env.image_size)
    states: list[RobotState] = []

    def record(w) -> None:
        if w.step_count % env.period == 0:
            states.append(RobotState(w.joint_positions(), w.gripper_pose(), w.gripper_command, w.finger_width()))

    try:
        record(world)
        world.step_callbacks.append(record)
        executor = KeyframeExecutor(world, env.kinematics, JointPlanner(), env.episode.seed, task.graspable_bodies())
        for transition, target in enumerate(ExpertKeyframes(task, world), start=1):
            if not executor.execute(target, transition).ok:
                break
    finally:
        world.close()
    return states


class CurrentPosePolicy:
    """Always predicts the current state (gripper pose and opening, or the joints): a floor that must
    score 0%."""

    name = "current_pose"

    def reset(self, env) -> None:
        pass

    def act(self, env) -> np.ndarray:
        robot = env.frame.robot
        if env.action_space_name != "keyframe":
            return robot_action(robot, env.action_space_name).astype(np.float64)
        return np.array([*robot.gripper_pose, robot.gripper_open])


def observation_batch(frame, instruction: str) -> dict:
    """One observation as a LeRobot batch of size 1, laid out like a loaded dataset frame."""
    import torch

    batch = {}
    for key, value in observation_item(frame, list(frame.cameras)).items():
        tensor = torch.from_numpy(np.ascontiguousarray(value, np.float32 if value.dtype == np.uint16 else None))
        if value.dtype == np.uint8:  # images: (H, W, 3) uint8 → (3, H, W) floats in [0, 1], as LeRobot loads them
            tensor = tensor.permute(2, 0, 1).float().div(255.0)
        elif value.dtype == np.uint16:  # depth: (H, W, 1) mm → (1, H, W) float mm, as LeRobot loads it
            tensor = tensor.permute(2, 0, 1)
        batch[key] = tensor[None]
    batch["task"] = [instruction]
    return batch


class LeRobotPolicy:
    """Any LeRobot policy checkpoint with an 8-d action: a keyframe ``[x, y, z, quat, open]`` or a dense
    ``joints`` / ``ee`` action. ``select_action`` is called once per step; policies that predict action
    chunks (ACT, diffusion) serve them from their own queue and predict again when it runs dry."""

    def __init__(self, path: str | Path, device: str = "cpu"):
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors
        from lerobot.utils.import_utils import register_third_party_plugins

        import demo_factory.evaluate.gym_layout  # noqa: F401  (registers the step older checkpoints' pre-processors name)

        register_third_party_plugins()  # finds lerobot_policy_* plugins such as HiveFormer
        self.torch = torch
        path = str(path)
        config = PreTrainedConfig.from_pretrained(path)
        config.pretrained_path = path
        config.device = device
        self.policy = get_policy_class(config.type).from_pretrained(path, config=config)
        self.policy.eval()
        self.preprocessor, self.postprocessor = make_pre_post_processors(
            config, pretrained_path=path, preprocessor_overrides={"device_processor": {"device": device}},
        )
        self.name = f"{config.type} ({Path(path).name})"
        action = config.output_features.get("action")
        if action is None or tuple(action.shape) != (ACTION_SIZE,):
            raise ValueError(f"{path}: the policy's action is {action}; evaluation needs a {ACTION_SIZE}-d action "
                             "(keyframe, joints or ee)")

    def reset(self, env) -> None:
        self.policy.reset()
        self.preprocessor.reset()
        self.postprocessor.reset()

    def act(self, env) -> np.ndarray:
        batch = self.preprocessor(observation_batch(env.frame, env.task_description))
        with self.torch.inference_mode():
            action = self.policy.select_action(batch)
        action = self.postprocessor(action)
        return action.detach().cpu().numpy().reshape(-1)[:8].astype(np.float64)
