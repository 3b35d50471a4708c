"""Conversion: MCAP episode recordings → LeRobot v3.0 datasets, one per split, with a dataset card.

Owns the dataset layout (`features`: feature names, shapes, native depth, actions), the split plan
(`splits`: train / val / unseen test splits and their instruction sources), the conversion run
(`converter`: options, checks, survey, plan), the split writer (`writer`: LeRobot's writer in one process or
in parallel batches merged with LeRobot's `aggregate_datasets`), the card (`card`) and the training
commands that fit each export (`usage`). Reads ``.mcap`` recordings, the
generation summaries beside them and human-instruction files; writes one LeRobot dataset folder per split
(provenance in ``meta/demo_factory.json``, read back by `read_dataset_provenance`), ``README.md``
and ``contact_sheet.png`` into the output folder, all at once (a staging folder renamed at the end).
"""

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
    depth_mm,
    pack_depth,
    robot_action,
    world_points,
)
from demo_factory.convert.result import ConvertResult
from demo_factory.convert.splits import DATASET_SPLITS, split_repo_id

__all__ = [
    "ACTION_SPACES",
    "DATASET_FORMAT_VERSION",
    "DATASET_SPLITS",
    "ConvertError",
    "ConvertOptions",
    "ConvertResult",
    "check_dataset_provenance",
    "convert",
    "dataset_features",
    "depth_mm",
    "pack_depth",
    "robot_action",
    "split_repo_id",
    "world_points",
]
