"""Pre- and post-processing pipelines of the HiveFormer policy.

The same standard steps as LeRobot's ACT (rename, batch, device, normalizer / unnormalizer, device),
named the same way, plus one registered step (batching of depth and calibration), so that
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

from .configuration_hiveformer import HiveformerConfig
from .dataset_format import CALIBRATION_PREFIX, DEPTH_PREFIX


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
