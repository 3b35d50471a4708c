"""The converter's speed-ups of LeRobot's writer write what LeRobot's own code writes."""

import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import json
import shutil

import numpy as np
import pandas as pd
import pytest
from lerobot.datasets import compute_stats
from lerobot.datasets.compute_stats import get_feature_stats

from demo_factory.convert.converter import ConvertOptions, convert
from demo_factory.convert.features import dataset_frame, depth_key, image_key
from demo_factory.convert.lerobot_speedups import faster_lerobot_writer
from demo_factory.record import read_episode

RNG = np.random.default_rng(0)
SYNTHETIC = {
    "full range": RNG.integers(0, 256, (6, 3, 64, 64), dtype=np.uint8),
    "narrow range": RNG.integers(3, 9, (5, 3, 32, 32), dtype=np.uint8),
    "constant": np.full((3, 3, 16, 16), 7, np.uint8),
    "extremes": np.concatenate([np.zeros((2, 1, 8, 8), np.uint8), np.full((2, 1, 8, 8), 255, np.uint8),
                                RNG.integers(0, 2, (2, 1, 8, 8), dtype=np.uint8)], axis=1),
    "one pixel": RNG.integers(0, 256, (1, 3, 1, 1), dtype=np.uint8),
}


def _assert_identical(stock: dict, fast: dict):
    assert stock.keys() == fast.keys()
    for key in stock:
        assert stock[key].dtype == fast[key].dtype and stock[key].shape == fast[key].shape, key
        assert np.array_equal(stock[key], fast[key]), (key, stock[key], fast[key])


def _both(array, axis, keepdims) -> tuple[dict, dict]:
    stock = get_feature_stats(array, axis=axis, keepdims=keepdims)
    with faster_lerobot_writer():
        fast = get_feature_stats(array, axis=axis, keepdims=keepdims)
    return stock, fast


@pytest.mark.parametrize("name", SYNTHETIC)
def test_image_statistics_are_lerobots_bit_for_bit(name):
    _assert_identical(*_both(SYNTHETIC[name], (0, 2, 3), True))


def test_statistics_of_rendered_rgb_and_packed_depth_are_lerobots_bit_for_bit(recorded_episodes):
    episode = read_episode(recorded_episodes["push_buttons"][0])
    frames = [dataset_frame(episode, frame, episode.info.instruction) for frame in episode.keyframe_frames()]
    for camera in episode.info.cameras:
        for key in (image_key(camera), depth_key(camera)):
            images = np.stack([frame[key] for frame in frames]).transpose(0, 3, 1, 2)  # as LeRobot samples them
            _assert_identical(*_both(images, (0, 2, 3), True))


def test_other_features_and_other_lerobot_versions_run_lerobots_code(monkeypatch):
    vectors = RNG.normal(size=(20, 8)).astype(np.float32)
    _assert_identical(*_both(vectors, 0, False))
    stock = compute_stats.RunningQuantileStats
    with faster_lerobot_writer():
        assert compute_stats.RunningQuantileStats is not stock
    assert compute_stats.RunningQuantileStats is stock  # restored
    import lerobot

    monkeypatch.setattr(lerobot, "__version__", "0.5.0")
    with faster_lerobot_writer():
        assert compute_stats.RunningQuantileStats is stock


@pytest.mark.parametrize("workers", [1, 2])
def test_a_converted_split_is_the_one_lerobots_own_code_writes(recorded_episodes, tmp_path, monkeypatch, workers):
    """One writer, or two batches merged (LeRobot's merge reads the batches' episode tables)."""
    from demo_factory.convert import writer

    monkeypatch.setattr(writer, "SMALLEST_BATCH", 1)
    raw = tmp_path / "raw"
    raw.mkdir()
    for path in recorded_episodes["push_buttons"]:
        shutil.copy(path, raw)

    def converted(name: str):
        out = tmp_path / name
        convert(ConvertOptions(inputs=[raw], out=out, repo_id="me/speedups", val_ratio=0.0, progress=False,
                               workers=workers), log=lambda _: None)
        return out / "train"

    decoded = []  # (in this process: with 2 workers the batches are written by forked ones)
    stock_loader = compute_stats.load_image_as_numpy
    monkeypatch.setattr(compute_stats, "load_image_as_numpy", lambda *a, **k: decoded.append(a) or stock_loader(*a, **k))
    fast = converted("fast")
    assert decoded == []  # every image's statistics came from the kept arrays
    import lerobot

    monkeypatch.setattr(lerobot, "__version__", "0.5.0")  # another version: LeRobot's own code throughout
    stock = converted("stock")
    assert bool(decoded) == (workers == 1)  # LeRobot's own code decoded the PNGs again
    assert json.loads((fast / "meta" / "stats.json").read_text()) == json.loads((stock / "meta" / "stats.json").read_text())
    for relative in ("meta/episodes/chunk-000/file-000.parquet", "data/chunk-000/file-000.parquet"):
        a, b = pd.read_parquet(fast / relative), pd.read_parquet(stock / relative)
        assert list(a.columns) == list(b.columns) and len(a) == len(b)
        for column in a.columns:
            for x, y in zip(a[column], b[column]):
                assert np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y, column
