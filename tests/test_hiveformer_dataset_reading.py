"""The plugin's dataset reader: the stock LeRobot items, bit for bit, and packed depth never augmented."""

import importlib.metadata

import torch
from hiveformer_fixtures import EPISODE_LENGTHS, tiny_dataset_root
from lerobot.datasets.lerobot_dataset import LeRobotDataset
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


def test_the_plugin_installs_its_reader_on_lerobot_0_4_4():
    assert importlib.metadata.version("lerobot") == dataset_reading.PATCHED_LEROBOT_VERSION
    assert LeRobotDataset.__getitem__ is dataset_reading.read_item
    assert dataset_reading.stock_getitem is not None


def test_items_with_history_are_bit_identical_to_the_stock_reader(tiny_dataset_root):
    dataset = history_dataset(tiny_dataset_root)
    assert len(dataset) == sum(EPISODE_LENGTHS)
    for index in range(len(dataset)):  # every frame: padded windows at each episode start included
        assert_same_items(dataset_reading.stock_getitem(dataset, index), dataset[index])


def test_items_of_an_episode_subset_are_bit_identical(tiny_dataset_root):
    dataset = history_dataset(tiny_dataset_root, episodes=[1, 3])  # relative row numbers differ
    for index in range(len(dataset)):
        assert_same_items(dataset_reading.stock_getitem(dataset, index), dataset[index])


def test_items_without_history_are_bit_identical(tiny_dataset_root):
    dataset = LeRobotDataset("local/tiny", root=tiny_dataset_root)
    for index in (0, 5, len(dataset) - 1):
        assert_same_items(dataset_reading.stock_getitem(dataset, index), dataset[index])


def test_image_transforms_leave_packed_depth_alone(tiny_dataset_root):
    def invert(image: torch.Tensor) -> torch.Tensor:
        return 1.0 - image

    plain = history_dataset(tiny_dataset_root)[4]
    augmented = history_dataset(tiny_dataset_root, image_transforms=invert)[4]
    for camera in ("left_shoulder", "right_shoulder", "wrist"):
        rgb, depth = f"observation.images.{camera}", f"observation.depth.{camera}"
        assert torch.equal(augmented[rgb], 1.0 - plain[rgb])
        assert torch.equal(augmented[depth], plain[depth])
