"""MCAP episode recordings → LeRobot v3.0 datasets, one per split, with a dataset card."""

from demo_factory.convert.converter import (
    DATASET_FORMAT_VERSION,
    ConvertError,
    ConvertOptions,
    check_dataset_provenance,
    convert,
)
from demo_factory.convert.features import (
    ACTION_SPACES,
    dataset_features,
    pack_depth,
    robot_action,
    unpack_depth,
    world_points,
)
from demo_factory.convert.result import ConvertResult
from demo_factory.convert.splits import SPLITS, split_repo_id

__all__ = [
    "ACTION_SPACES",
    "DATASET_FORMAT_VERSION",
    "SPLITS",
    "ConvertError",
    "ConvertOptions",
    "ConvertResult",
    "check_dataset_provenance",
    "convert",
    "dataset_features",
    "pack_depth",
    "robot_action",
    "split_repo_id",
    "unpack_depth",
    "world_points",
]
