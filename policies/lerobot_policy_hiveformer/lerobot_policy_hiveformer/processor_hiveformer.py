"""Pre- and post-processing pipelines of the HiveFormer policy.

The same standard steps as LeRobot's ACT (rename, batch, device, normalizer / unnormalizer, device),
named the same way, plus two registered steps (gym observation layout; batching of depth and
calibration), so that
`lerobot-eval` overrides and `--policy.path` reloading work. The normalizer
steps are kept for that reason but are identities: HiveFormer's configuration only accepts IDENTITY
(images, depth in millimetres, calibration, state and action are all consumed in physical units), and the
point cloud is rebuilt inside the policy so that `select_action` works on raw observations.
"""

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from lerobot.configs.types import PipelineFeatureType, PolicyFeature
from lerobot.processor import (
    AddBatchDimensionProcessorStep,
    DeviceProcessorStep,
    NormalizerProcessorStep,
    ObservationProcessorStep,
    PolicyAction,
    PolicyProcessorPipeline,
    ProcessorStepRegistry,
    RenameObservationsProcessorStep,
    UnnormalizerProcessorStep,
)
from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action
from lerobot.utils.constants import POLICY_POSTPROCESSOR_DEFAULT_NAME, POLICY_PREPROCESSOR_DEFAULT_NAME

from .configuration_hiveformer import CALIBRATION_PREFIX, DEPTH_PREFIX, IMAGES_PREFIX, HiveformerConfig

ENVIRONMENT_STATE = "observation.environment_state"
CALIBRATION_SIZE = 20  # fx, fy, cx, cy, then the 4x4 world-from-camera transform


@dataclass
@ProcessorStepRegistry.register(name="hiveformer_add_batch_dimension")
class AddBatchDimensionToDepthAndCalibrationStep(ObservationProcessorStep):
    """Batch the depth and calibration of a single observation, as LeRobot's step does for images/state.

    LeRobot's AddBatchDimensionProcessorStep only knows `observation.state` and `observation.images.*`;
    without this step a rollout would feed unbatched `observation.depth.*` (3, H, W) and
    `observation.calibration.*` (20,) to the policy.
    """

    def observation(self, observation: dict[str, Tensor]) -> dict[str, Tensor]:
        observation = dict(observation)
        for key, value in observation.items():
            if not isinstance(value, Tensor):
                continue
            if key.startswith(DEPTH_PREFIX) and value.dim() == 3:
                observation[key] = value.unsqueeze(0)
            elif key.startswith(CALIBRATION_PREFIX) and value.dim() == 1:
                observation[key] = value.unsqueeze(0)
        return observation

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features


def unpack_gym_depth(packed: Tensor) -> Tensor:
    """(..., 3, H, W) packed depth as [0, 1] floats (R = mm // 256, G = mm % 256) -> (..., 1, H, W) mm."""
    high = torch.round(packed[..., 0:1, :, :] * 255.0)
    low = torch.round(packed[..., 1:2, :, :] * 255.0)
    return high * 256.0 + low


@dataclass
@ProcessorStepRegistry.register(name="hiveformer_gym_observation_layout")
class GymObservationLayoutStep(ObservationProcessorStep):
    """Accept observations from a gym environment run by `lerobot-eval`, which can only deliver
    `pixels`, `agent_pos` and `environment_state`.

    A gym observation's images must be uint8 RGB, so such an environment sends each camera's depth
    packed into an image, `observation.images.<cam>_depth` with R = mm // 256 and G = mm % 256 (LeRobot
    hands it over as [0, 1] floats), and the cameras' calibration vectors concatenated, in the order of
    the policy's cameras, as `observation.environment_state` (B, 20 * n_cameras). This step maps them
    to the dataset layout (`observation.depth.<cam>` as (B, 1, H, W) millimetres, LeRobot's native
    depth; `observation.calibration.<cam>`); observations already in that layout pass unchanged.
    """

    cameras: list[str] | None = None  # the policy's cameras, in the order of its image features

    def observation(self, observation: dict[str, Tensor]) -> dict[str, Tensor]:
        observation = dict(observation)
        for camera in self.cameras or []:
            gym_depth = f"{IMAGES_PREFIX}{camera}_depth"
            if gym_depth in observation and DEPTH_PREFIX + camera not in observation:
                observation[DEPTH_PREFIX + camera] = unpack_gym_depth(observation.pop(gym_depth))
        calibrations = observation.get(ENVIRONMENT_STATE)
        missing = [c for c in self.cameras or [] if CALIBRATION_PREFIX + c not in observation]
        if missing and isinstance(calibrations, Tensor):
            per_camera = calibrations.reshape(*calibrations.shape[:-1], len(self.cameras), CALIBRATION_SIZE)
            for index, camera in enumerate(self.cameras):
                observation[CALIBRATION_PREFIX + camera] = per_camera[..., index, :]
            observation.pop(ENVIRONMENT_STATE)
        return observation

    def get_config(self) -> dict[str, Any]:
        return {"cameras": self.cameras}

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features


def make_hiveformer_pre_post_processors(
    config: HiveformerConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """Pre-processor (rename, batch, batch depth/calibration, device, normalizer) and
    post-processor (unnormalizer, to CPU)."""
    input_steps = [
        RenameObservationsProcessorStep(rename_map={}),
        GymObservationLayoutStep(cameras=config.camera_names),
        AddBatchDimensionProcessorStep(),
        AddBatchDimensionToDepthAndCalibrationStep(),
        DeviceProcessorStep(device=config.device),
        NormalizerProcessorStep(
            features={**config.input_features, **config.output_features},
            norm_map=config.normalization_mapping,
            stats=dataset_stats,
            device=config.device,
        ),
    ]
    output_steps = [
        UnnormalizerProcessorStep(
            features=config.output_features, norm_map=config.normalization_mapping, stats=dataset_stats
        ),
        DeviceProcessorStep(device="cpu"),
    ]
    return (
        PolicyProcessorPipeline[dict[str, Any], dict[str, Any]](
            steps=input_steps,
            name=POLICY_PREPROCESSOR_DEFAULT_NAME,
        ),
        PolicyProcessorPipeline[PolicyAction, PolicyAction](
            steps=output_steps,
            name=POLICY_POSTPROCESSOR_DEFAULT_NAME,
            to_transition=policy_action_to_transition,
            to_output=transition_to_policy_action,
        ),
    )
