"""Batches of a split written by several processes and merged make the dataset one writer makes."""

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from demo_factory.convert.converter import ConvertOptions, convert
from demo_factory.convert.writer import episode_batches
from demo_factory.tasks import get_task


def test_batches_are_consecutive_even_and_not_too_small():
    episodes = list(range(7))
    assert episode_batches(episodes, 1, smallest=2) == [episodes]
    assert sorted(len(b) for b in episode_batches(episodes, 2, smallest=2)) == [3, 4]
    assert sorted(len(b) for b in episode_batches(episodes, 8, smallest=2)) == [2, 2, 3]  # at least 2 each
    assert episode_batches([0, 1, 2], 4, smallest=2) == [[0, 1, 2]]
    assert episode_batches(episodes, 2) == [episodes]  # by default a batch holds at least SMALLEST_BATCH
    assert len(episode_batches(list(range(16)), 2)) == 2
    for workers in (1, 2, 3, 8):
        assert [e for batch in episode_batches(episodes, workers, smallest=2) for e in batch] == episodes


@pytest.fixture
def small_batches(monkeypatch):
    """Batches of 2 episodes, so that these few recordings are written in several; returns the number of
    batches each merge took."""
    from lerobot.datasets import aggregate

    from demo_factory.convert import writer

    monkeypatch.setattr(writer, "SMALLEST_BATCH", 2)
    merged = []
    original = aggregate.aggregate_datasets
    monkeypatch.setattr(aggregate, "aggregate_datasets",
                        lambda repo_ids, *args, **kwargs: merged.append(len(repo_ids)) or original(repo_ids, *args, **kwargs))
    return merged


@pytest.fixture(scope="module")
def recordings(tmp_path_factory, write_recording):
    folder = tmp_path_factory.mktemp("raw")
    for i, variation in enumerate(get_task("push_buttons").split_variations("train")[:8]):
        write_recording(folder, "push_buttons", "train", variation, 300 + i, keyframes=3 + i % 3)
    return folder


def _convert(recordings, out: Path, workers: int) -> Path:
    convert(ConvertOptions(inputs=[recordings], out=out, repo_id="me/parallel", val_ratio=0.25, progress=False,
                           workers=workers, human_instructions=None), log=lambda _: None)
    return out


def _files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


def _assert_same_frame(a: pd.DataFrame, b: pd.DataFrame):
    assert list(a.columns) == list(b.columns) and len(a) == len(b)
    for column in a.columns:
        for x, y in zip(a[column], b[column]):
            if isinstance(x, dict):  # an embedded image: PNG bytes and path
                assert x == y, column
            elif isinstance(x, (np.ndarray, list)) and np.asarray(x).dtype.kind == "f":
                np.testing.assert_allclose(np.asarray(x, dtype=float), np.asarray(y, dtype=float), rtol=1e-12, err_msg=column)
            elif isinstance(x, np.ndarray):
                assert np.array_equal(x, y), column
            else:
                assert x == y or (isinstance(x, float) and np.isclose(x, y, rtol=1e-12)), column


def _assert_close(a, b, where=""):
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            _assert_close(a[key], b[key], f"{where}/{key}")
    else:
        np.testing.assert_allclose(np.asarray(a, dtype=float), np.asarray(b, dtype=float), rtol=1e-12, err_msg=where)


@pytest.mark.parametrize("workers", [2, 3])
def test_parallel_batches_give_the_dataset_of_one_writer(recordings, tmp_path, workers, small_batches, monkeypatch):
    import datasets

    user_cache = tmp_path / "hf_datasets_cache"
    monkeypatch.setattr(datasets.config, "HF_DATASETS_CACHE", user_cache)
    one = _convert(recordings, tmp_path / "one", workers=1)
    many = _convert(recordings, tmp_path / "many", workers=workers)
    assert small_batches == [workers]  # train (6 episodes) in batches of 3 or 2; val (2) in one
    assert not user_cache.exists()  # the merge's Arrow copies went with the batches
    assert sorted(p.name for p in tmp_path.iterdir()) == ["many", "one"]  # no batch or cache folder left
    for split in ("train", "val"):
        a, b = one / split, many / split
        assert _files(a) == _files(b), split
        info_a, info_b = (json.loads((r / "meta" / "info.json").read_text()) for r in (a, b))
        assert info_a == info_b
        provenance_a, provenance_b = (json.loads((r / "meta" / "demo_factory.json").read_text()) for r in (a, b))
        assert provenance_a == provenance_b
        assert provenance_a["episodes"][-1]["episode_index"] == info_a["total_episodes"] - 1
        _assert_close(json.loads((a / "meta" / "stats.json").read_text()),
                      json.loads((b / "meta" / "stats.json").read_text()), split)
        for relative in _files(a):
            if relative.endswith(".parquet"):
                _assert_same_frame(pd.read_parquet(a / relative), pd.read_parquet(b / relative))
    train = json.loads((one / "train" / "meta" / "info.json").read_text())
    assert train["total_episodes"] == 6  # so the train split was really written in batches
    _assert_same_items(one / "train", many / "train")


def _assert_same_items(a: Path, b: Path):
    """LeRobot reads both the same, item by item."""
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    first, second = (LeRobotDataset("me/parallel_train", root=root) for root in (a, b))
    assert len(first) == len(second) and first.meta.episodes["episode_index"] == second.meta.episodes["episode_index"]
    for index in range(len(first)):
        x, y = first[index], second[index]
        assert x.keys() == y.keys()
        for key in x:
            assert torch.equal(x[key], y[key]) if isinstance(x[key], torch.Tensor) else x[key] == y[key], (index, key)


def test_workers_below_one_are_refused_before_anything_is_written(recordings, tmp_path):
    from demo_factory.convert.converter import ConvertError

    with pytest.raises(ConvertError, match="--workers 0 is out of range; accepted: a whole number >= 1"):
        convert(ConvertOptions(inputs=[recordings], out=tmp_path / "x", repo_id="me/x", workers=0, progress=False))
    assert not (tmp_path / "x").exists()
