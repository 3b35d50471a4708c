"""The plugin's dataset reader: LeRobot's items, bit for bit, only for HiveFormer trainings; whole-episode
samples with paraphrased or relabelled instructions there; native depth never augmented."""

import copy
import json
import shutil
from collections import Counter
from types import SimpleNamespace

import pytest
import torch
from hiveformer_fixtures import EPISODE_LENGTHS, INSTRUCTIONS, tiny_config, tiny_dataset_root
from lerobot.configs.default import DatasetConfig
from lerobot.datasets import factory
from lerobot.datasets.dataset_reader import DatasetReader
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot_policy_hiveformer import dataset_reading

__all__ = ["tiny_dataset_root"]  # the fixture is used by name

HISTORY = 3


def history_dataset(root, episodes=None, image_transforms=None, history=HISTORY) -> LeRobotDataset:
    """The dataset as lerobot-train builds it for HiveFormer: every observation key and the action with history
    (the action one step longer: the look-back action)."""
    meta = LeRobotDataset("local/tiny", root=root).meta
    deltas = [i / meta.fps for i in range(1 - history, 1)]
    delta_timestamps = {key: deltas for key in meta.features if key.startswith("observation.")}
    delta_timestamps["action"] = [i / meta.fps for i in range(-history, 1)]
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


def test_only_hiveformer_trainings_get_the_training_reader(tiny_dataset_root):
    assert getattr(factory.make_dataset, "hiveformer_history_once", False)  # installed by the plugin's import
    config, meta = tiny_config(tiny_dataset_root)
    hiveformer = factory.make_dataset(training_config(tiny_dataset_root, config))
    assert type(hiveformer.reader) is dataset_reading.TrainingReader
    act = ACTConfig(device="cpu", input_features=config.input_features, output_features=config.output_features)
    assert type(factory.make_dataset(training_config(tiny_dataset_root, act)).reader) is DatasetReader
    assert type(LeRobotDataset("local/tiny", root=tiny_dataset_root).reader) is DatasetReader  # by hand: stock


def test_a_training_without_n_history_gets_the_longest_episode(tiny_dataset_root):
    config, _ = tiny_config(tiny_dataset_root, n_history=None)
    dataset = factory.make_dataset(training_config(tiny_dataset_root, config))
    assert config.n_history == max(EPISODE_LENGTHS) == 6
    assert dataset[0]["observation.state"].shape[0] == 6


def episode_of_each_frame() -> list[tuple[int, int]]:
    """(first frame, last frame) of the episode of every frame of the tiny dataset."""
    spans, start = [], 0
    for length in EPISODE_LENGTHS:
        spans += [(start, start + length - 1)] * length
        start += length
    return spans


def test_whole_episode_samples_are_the_stock_window_of_the_episode_end(tiny_dataset_root):
    """Every frame drawn gives its whole episode: the stock item of the episode's last frame, every real
    step of it an action target; an episode longer than the history keeps the stock window."""
    config, _ = tiny_config(tiny_dataset_root, n_history=5)  # episodes of 4, 5, 4 frames fit; 6 does not
    dataset = factory.make_dataset(training_config(tiny_dataset_root, config))
    stock = history_dataset(tiny_dataset_root, history=5)
    for index, (first, last) in enumerate(episode_of_each_frame()):
        fits = last - first + 1 <= 5
        assert_same_items(stock[last if fits else index], dataset[index])
        if fits:
            assert int((~dataset[index]["action_is_pad"]).sum()) == last - first + 1


def test_whole_episodes_off_keeps_the_stock_windows(tiny_dataset_root):
    config, _ = tiny_config(tiny_dataset_root, n_history=6, whole_episodes=False)
    dataset = factory.make_dataset(training_config(tiny_dataset_root, config))
    stock = history_dataset(tiny_dataset_root, history=6)
    for index in range(len(dataset)):
        assert_same_items(stock[index], dataset[index])



def test_kept_rows_give_the_stock_items_and_spare_the_decoding(tiny_dataset_root, monkeypatch):
    """A training reader keeps the history rows it decoded (up to `history_cache_mib`): its items stay the
    stock reader's, a second epoch decodes nothing, and a budget that holds a few rows holds no more."""
    config, _ = tiny_config(tiny_dataset_root, n_history=6, whole_episodes=False)
    dataset = factory.make_dataset(training_config(tiny_dataset_root, config))
    stock = history_dataset(tiny_dataset_root, history=6)
    reader = dataset.reader
    assert reader.cache_bytes == config.history_cache_mib * 2**20 > 0
    for index in range(len(dataset)):
        assert_same_items(stock[index], dataset[index])
    (kept,) = reader.__dict__["_decoded_row_caches"][1].values()
    assert sorted(kept) == list(range(len(dataset)))  # every row, decoded once
    # kept in the PNGs' bits: 8-bit colour, 16-bit depth; the other values as decoded
    dtypes = {key.split(".")[1] if key.startswith("observation.") else key: stored.dtype
              for key, (stored, _) in kept[0].items()}
    assert dtypes["images"] == torch.uint8 and dtypes["depth"] == torch.uint16
    assert dtypes["calibration"] == dtypes["state"] == torch.float32
    with monkeypatch.context() as patch:
        patch.setattr(type(reader), "_columns_view", lambda *_: pytest.fail("decoded a kept row again"))
        for index in range(len(dataset)):
            assert_same_items(stock[index], dataset[index])

    row_bytes = sum(stored.nbytes for stored, _ in kept[0].values())
    small = factory.make_dataset(training_config(tiny_dataset_root, config))
    small.reader.cache_bytes = 3 * row_bytes
    for index in reversed(range(len(small))):
        assert_same_items(stock[index], small[index])
    (kept,) = small.reader.__dict__["_decoded_row_caches"][1].values()
    assert len(kept) == 3 and small.reader.__dict__["_cached_bytes"] <= 3 * row_bytes


@pytest.fixture
def paraphrased_root(tiny_dataset_root, tmp_path):
    root = tmp_path / "tiny"
    shutil.copytree(tiny_dataset_root, root)
    (root / dataset_reading.PARAPHRASES_FILE).write_text(json.dumps({INSTRUCTIONS[0]: ["press maroon", "maroon!"]}))
    return root


def test_training_samples_draw_their_instruction_among_the_paraphrases(paraphrased_root):
    config, _ = tiny_config(paraphrased_root)
    dataset = factory.make_dataset(training_config(paraphrased_root, config))
    torch.manual_seed(0)
    drawn = Counter(dataset[0]["task"] for _ in range(200))  # frame 0: episode 0, INSTRUCTIONS[0]
    assert set(drawn) == {"press maroon", "maroon!"} and min(drawn.values()) > 60
    assert dataset[4]["task"] == INSTRUCTIONS[1]  # episode 1: no paraphrases listed, unchanged
    # One-hot codes name strings, not meanings: no paraphrases there; nor with the switch off.
    for overrides in ({"text_encoder": "one_hot"}, {"sample_paraphrases": False}):
        config, _ = tiny_config(paraphrased_root, **overrides)
        assert factory.make_dataset(training_config(paraphrased_root, config))[0]["task"] == INSTRUCTIONS[0]


def test_a_malformed_paraphrase_file_is_refused_in_one_line(paraphrased_root):
    (paraphrased_root / dataset_reading.PARAPHRASES_FILE).write_text(json.dumps({INSTRUCTIONS[0]: "press maroon"}))
    config, _ = tiny_config(paraphrased_root)
    with pytest.raises(ValueError, match="task_paraphrases.json: expected an object"):
        factory.make_dataset(training_config(paraphrased_root, config))


@pytest.fixture
def relabelled_root(tiny_dataset_root, tmp_path):
    root = tmp_path / "tiny"
    shutil.copytree(tiny_dataset_root, root)
    relabels = {"0": [[2, ["press maroon first"]], [3, ["maroon, then navy", "maroon and navy"]]], "3": [[3, ["x"]]]}
    (root / dataset_reading.RELABELS_FILE).write_text(json.dumps(relabels))
    return root


def test_relabelled_samples_take_a_relabel_that_demonstrates_them(relabelled_root):
    """With relabel_probability, a sample of a relabelled episode takes, that often, one of its relabels, with
    an instruction among the relabel's: a whole-episode sample ends at the relabel's n-th keyframe, a window
    keeps its frames and draws among the relabels whose n keyframes hold them; episodes without relabels
    stay as they were."""
    lengths = {"press maroon first": 2, "maroon, then navy": 3, "maroon and navy": 3, "x": 3}
    config, _ = tiny_config(relabelled_root, n_history=5, relabel_probability=0.5)
    dataset = factory.make_dataset(training_config(relabelled_root, config))
    stock = history_dataset(relabelled_root, history=5)
    torch.manual_seed(0)
    drawn = Counter()
    for _ in range(200):
        item = dataset[2]  # a frame of episode 0 (frames 0-3), whose whole episode fits in the history
        drawn[item["task"]] += 1
        n = lengths.get(item["task"], 4)
        assert_same_items({**stock[n - 1], "task": item["task"]}, item) and int((~item["action_is_pad"]).sum()) == n
    assert drawn[INSTRUCTIONS[0]] in range(75, 126) and min(drawn.values()) > 10 and len(drawn) == 4
    for index, (first, last) in enumerate(episode_of_each_frame()[4:13], start=4):  # episodes 1 and 2: none listed
        assert_same_items(stock[last], dataset[index])
    # Windows ending at every frame (episode 3 is longer than the history): a window keeps its frames and takes
    # a relabel whose keyframes hold them, or none.
    config, _ = tiny_config(relabelled_root, n_history=5, relabel_probability=1.0, whole_episodes=False)
    dataset = factory.make_dataset(training_config(relabelled_root, config))
    for index, (first, _) in enumerate(episode_of_each_frame()):
        if first in (0, 13):
            held = {t for t, n in lengths.items() if index - first < n and (t == "x") == (first == 13)}
            item = dataset[index]
            assert_same_items({**stock[index], "task": item["task"]}, item)
            tasks = {dataset[index]["task"] for _ in range(20)}
            assert tasks == held if held else tasks <= set(INSTRUCTIONS)
    for overrides in ({}, {"relabel_probability": 1.0, "text_encoder": "one_hot"}):  # 0, or one-hot codes: none
        off, _ = tiny_config(relabelled_root, n_history=5, **overrides)
        assert factory.make_dataset(training_config(relabelled_root, off)).reader.relabels == {}


def test_a_malformed_relabel_file_is_refused_in_one_line(relabelled_root):
    (relabelled_root / dataset_reading.RELABELS_FILE).write_text(json.dumps({"0": [[0, ["press maroon"]]]}))
    config, _ = tiny_config(relabelled_root, relabel_probability=1.0)
    with pytest.raises(ValueError, match="instruction_relabels.json: expected an object"):
        factory.make_dataset(training_config(relabelled_root, config))


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


def test_kept_values_come_back_exactly_in_their_own_dtype():
    """`compact` keeps 8-bit colour as uint8 and integer millimetres as uint16, anything else as it is, and
    `expand` gives back the decoded value bit for bit, leaving values that were not compacted alone."""
    colour = torch.arange(256, dtype=torch.float32).div(255).view(1, 16, 16)
    depth = torch.tensor([[0.0, 612.0], [65535.0, 1.0]])
    fractional = torch.tensor([[0.3, 0.5]])
    raw_bytes = torch.tensor([[3, 200]], dtype=torch.uint8)
    for value, dtype in ((colour, torch.uint8), (depth, torch.uint16), (fractional, torch.float32),
                         (raw_bytes, torch.uint8)):
        stored = dataset_reading.compact(value)
        assert stored.dtype == dtype
        restored = dataset_reading.expand(stored, value.dtype)
        assert restored.dtype == value.dtype and torch.equal(restored, value)
