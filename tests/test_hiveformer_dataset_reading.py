"""The plugin's dataset reader: LeRobot's items, bit for bit, only for HiveFormer trainings; native depth
never augmented."""

import copy
from types import SimpleNamespace

import torch
from hiveformer_fixtures import EPISODE_LENGTHS, tiny_config, tiny_dataset_root
from lerobot.configs.default import DatasetConfig
from lerobot.datasets import factory
from lerobot.datasets.dataset_reader import DatasetReader
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot_policy_hiveformer import dataset_reading

__all__ = ["tiny_dataset_root"]  # the fixture is used by name

HISTORY = 3


def history_dataset(root, episodes=None, image_transforms=None) -> LeRobotDataset:
    """The dataset as lerobot-train builds it for HiveFormer: every observation key and the action with history."""
    meta = LeRobotDataset("local/tiny", root=root).meta
    deltas = [i / meta.fps for i in range(1 - HISTORY, 1)]
    delta_timestamps = {key: deltas for key in meta.features if key.startswith("observation.")}
    delta_timestamps["action"] = deltas
    return LeRobotDataset(
        "local/tiny",
        root=root,
        episodes=episodes,
        delta_timestamps=delta_timestamps,
        image_transforms=image_transforms,
    )


def assert_same_items(stock: dict, ours: dict):
    assert list(ours) == list(stock)
    for key, value in stock.items():
        if isinstance(value, torch.Tensor):
            assert ours[key].dtype == value.dtype and torch.equal(ours[key], value), key
        else:
            assert ours[key] == value, key


def stock_and_ours(dataset: LeRobotDataset) -> tuple[LeRobotDataset, LeRobotDataset]:
    ours = copy.copy(dataset)
    ours.reader = copy.copy(dataset.reader)
    assert dataset_reading.use_history_once(ours)
    assert type(dataset.reader) is DatasetReader and type(ours.reader) is dataset_reading.HistoryOnceReader
    return dataset, ours


def training_config(root, policy) -> SimpleNamespace:
    """What `make_dataset` reads of lerobot-train's configuration."""
    return SimpleNamespace(dataset=DatasetConfig(repo_id="local/tiny", root=str(root)), policy=policy,
                           trainable_config=policy, tolerance_s=1e-4, num_workers=0)


def test_only_hiveformer_trainings_get_the_history_once_reader(tiny_dataset_root):
    assert getattr(factory.make_dataset, "hiveformer_history_once", False)  # installed by the plugin's import
    config, meta = tiny_config(tiny_dataset_root)
    hiveformer = factory.make_dataset(training_config(tiny_dataset_root, config))
    assert type(hiveformer.reader) is dataset_reading.HistoryOnceReader
    act = ACTConfig(device="cpu", input_features=config.input_features, output_features=config.output_features)
    assert type(factory.make_dataset(training_config(tiny_dataset_root, act)).reader) is DatasetReader
    assert type(LeRobotDataset("local/tiny", root=tiny_dataset_root).reader) is DatasetReader  # by hand: stock


def test_items_with_history_are_bit_identical_to_the_stock_reader(tiny_dataset_root):
    stock, ours = stock_and_ours(history_dataset(tiny_dataset_root))
    assert len(ours) == sum(EPISODE_LENGTHS)
    for index in range(len(ours)):  # every frame: padded windows at each episode start included
        assert_same_items(stock[index], ours[index])


def test_items_of_an_episode_subset_are_bit_identical(tiny_dataset_root):
    stock, ours = stock_and_ours(history_dataset(tiny_dataset_root, episodes=[1, 3]))  # relative rows differ
    for index in range(len(ours)):
        assert_same_items(stock[index], ours[index])


def test_items_without_history_are_bit_identical(tiny_dataset_root):
    stock, ours = stock_and_ours(LeRobotDataset("local/tiny", root=tiny_dataset_root))
    for index in (0, 5, len(ours) - 1):
        assert_same_items(stock[index], ours[index])


def test_image_transforms_leave_native_depth_alone(tiny_dataset_root):
    """LeRobot 0.6 knows the depth features (is_depth_map) and keeps augmentation off them."""

    def invert(image: torch.Tensor) -> torch.Tensor:
        return 1.0 - image

    plain = history_dataset(tiny_dataset_root)[4]
    augmented = history_dataset(tiny_dataset_root, image_transforms=invert)[4]
    assert plain["observation.depth.wrist"].dtype == torch.float32 and plain["observation.depth.wrist"].max() > 100
    for camera in ("left_shoulder", "right_shoulder", "wrist"):
        rgb, depth = f"observation.images.{camera}", f"observation.depth.{camera}"
        assert torch.equal(augmented[rgb], 1.0 - plain[rgb])
        assert torch.equal(augmented[depth], plain[depth])
