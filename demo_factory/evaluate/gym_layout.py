"""The environment's processor step for ``lerobot-eval``: demo-factory's gym observations back in the dataset's layout.

A gym observation's images must be uint8, so demo-factory's environment sends each camera's depth packed into an
image (``observation.images.<cam>_depth``, R = mm // 256, G = mm % 256; ``features.pack_depth``) and the cameras'
calibration vectors concatenated in camera order (``observation.environment_state``). `GymObservationLayoutStep`,
which ``DemoFactoryEnv.get_env_processors`` hands to ``lerobot-eval``, turns them back into
``observation.depth.<cam>`` (millimetres, LeRobot's native depth) and ``observation.calibration.<cam>``, the
features a policy trained on a converted dataset reads.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from lerobot.configs.types import PipelineFeatureType, PolicyFeature
from lerobot.processor import ObservationProcessorStep, ProcessorStepRegistry
from torch import Tensor

from demo_factory.convert.features import CALIBRATION_SIZE, calibration_key, depth_key, image_key
from demo_factory.sim import CAMERA_NAMES

ENVIRONMENT_STATE = "observation.environment_state"


def unpack_gym_depth(packed: Tensor) -> Tensor:
    """(..., 3, H, W) packed depth as [0, 1] floats (R = mm // 256, G = mm % 256) -> (..., 1, H, W) millimetres."""
    high = torch.round(packed[..., 0:1, :, :] * 255.0)
    low = torch.round(packed[..., 1:2, :, :] * 255.0)
    return high * 256.0 + low


@dataclass
@ProcessorStepRegistry.register(name="demo_factory_gym_observation_layout")
class GymObservationLayoutStep(ObservationProcessorStep):
    """Packed depth and concatenated calibrations of a ``lerobot-eval`` gym observation -> the dataset's features;
    observations already in that layout pass unchanged."""

    cameras: list[str] = field(default_factory=lambda: list(CAMERA_NAMES))  # the environment's, in its order

    def observation(self, observation: dict[str, Tensor]) -> dict[str, Tensor]:
        observation = dict(observation)
        for camera in self.cameras:
            packed = f"{image_key(camera)}_depth"
            if packed in observation and depth_key(camera) not in observation:
                observation[depth_key(camera)] = unpack_gym_depth(observation.pop(packed))
        calibrations = observation.get(ENVIRONMENT_STATE)
        missing = [c for c in self.cameras if calibration_key(c) not in observation]
        if missing and isinstance(calibrations, Tensor):
            per_camera = calibrations.reshape(*calibrations.shape[:-1], len(self.cameras), CALIBRATION_SIZE)
            for index, camera in enumerate(self.cameras):
                observation[calibration_key(camera)] = per_camera[..., index, :]
            observation.pop(ENVIRONMENT_STATE)
        return observation

    def get_config(self) -> dict[str, Any]:
        return {"cameras": self.cameras}

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features


@dataclass
@ProcessorStepRegistry.register(name="hiveformer_gym_observation_layout")
class SavedGymObservationLayoutStep(GymObservationLayoutStep):
    """The same step under the name HiveFormer checkpoints saved before it moved here from the policy's
    pre-processor, so that their ``policy_preprocessor.json`` still loads (after the environment's step it has
    nothing left to do)."""
