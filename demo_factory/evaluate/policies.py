"""Keyframe policies that ``demo-factory eval`` can run: a LeRobot checkpoint, or references.

A policy has ``name``, ``reset(env)`` at the start of each episode and ``act(env) -> (8,)``
returning the next keyframe ``[x, y, z, qx, qy, qz, qw, open]`` from ``env.frame`` (the
observation) and ``env.task_description`` (the instruction).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from demo_factory.convert.features import observation_item


class ExpertPolicy:
    """The scripted expert as a reference policy (privileged: reads the scene, not the cameras)."""

    name = "expert"

    def reset(self, env) -> None:
        pass

    def act(self, env) -> np.ndarray:
        targets = env.expert_keyframes
        target = targets[min(env.steps, len(targets) - 1)]
        return np.array([*target.pose, target.gripper_open])


class CurrentPosePolicy:
    """Always predicts the current gripper pose and opening: a floor that must score 0%."""

    name = "current_pose"

    def reset(self, env) -> None:
        pass

    def act(self, env) -> np.ndarray:
        robot = env.frame.robot
        return np.array([*robot.gripper_pose, robot.gripper_open])


def observation_batch(frame, instruction: str) -> dict:
    """One observation as a LeRobot batch of size 1, laid out like a loaded dataset frame."""
    import torch

    batch = {}
    for key, value in observation_item(frame, list(frame.cameras)).items():
        tensor = torch.from_numpy(np.ascontiguousarray(value))
        if value.dtype == np.uint8:  # images: (H, W, 3) uint8 → (3, H, W) floats in [0, 1], as LeRobot loads them
            tensor = tensor.permute(2, 0, 1).float().div(255.0)
        batch[key] = tensor[None]
    batch["task"] = [instruction]
    return batch


class LeRobotKeyframePolicy:
    """Any LeRobot policy checkpoint whose action is the keyframe ``[x, y, z, quat, open]``."""

    def __init__(self, path: str | Path, device: str = "cpu"):
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors
        from lerobot.utils.import_utils import register_third_party_plugins

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
        if action is None or tuple(action.shape) != (8,):
            raise ValueError(f"{path}: the policy's action is {action}; evaluation needs the 8-d keyframe action")

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
