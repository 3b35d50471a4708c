"""The one place where this plugin changes how LeRobot reads a dataset: keyframe history decoded once.

LeRobot 0.6's `DatasetReader._query_hf_dataset` reads each key with history as `hf_dataset[key][rows]`.
With `datasets` >= 4.4 and LeRobot's custom transform that cannot take the column fast path: it
decodes *every* column of the history rows (every PNG of every camera), once per key, so HiveFormer's
11 history keys decode each image 11 times (LeRobot issues #2895 and #2315). `HistoryOnceReader`
overrides that one method: the history rows are decoded once, with only the columns that have
history. Its items equal the stock reader's (same keys, same tensors; tested).

It is applied only to the datasets HiveFormer trains on. `install()` (run when LeRobot imports the
plugin) wraps `lerobot.datasets.factory.make_dataset`, which `lerobot-train` calls: when the training
configuration's policy is HiveFormer, the dataset it returns reads with `HistoryOnceReader`; any other
dataset of the process (an ACT run, a dataset opened by hand) keeps LeRobot's reader.
`use_history_once(dataset)` does the same for a dataset built by hand. Version-checked: with a LeRobot
other than 0.6.x nothing is replaced and a warning says so.
"""

import functools
import importlib.metadata
import warnings

import torch
from lerobot.datasets.dataset_reader import DatasetReader

SUPPORTED_LEROBOT = "0.6."  # the minor version whose `_query_hf_dataset` this overrides
POLICY_TYPE = "hiveformer"


class HistoryOnceReader(DatasetReader):
    """LeRobot's reader, with each item's history rows decoded once for all keys with history."""

    def _query_hf_dataset(self, query_indices: dict[str, list[int]]) -> dict:
        keys = tuple(key for key in query_indices if key not in self._meta.video_keys)
        if not keys:
            return {}
        to_relative = self._absolute_to_relative_idx
        relative = {
            key: query_indices[key] if to_relative is None else [to_relative[i] for i in query_indices[key]]
            for key in keys
        }
        rows = sorted({row for indices in relative.values() for row in indices})
        position = {row: i for i, row in enumerate(rows)}
        decoded = self._columns_view(keys)[rows]  # {key: [value of each row]}
        return {key: torch.stack([decoded[key][position[row]] for row in relative[key]]) for key in keys}

    def _columns_view(self, columns: tuple[str, ...]):
        """`hf_dataset` restricted to `columns` (its transform still applies), built once per table."""
        source, views = self.__dict__.get("_history_column_views", (None, {}))
        if source is not self.hf_dataset:  # first read, or the table was reloaded
            views = {}
            self.__dict__["_history_column_views"] = (self.hf_dataset, views)
        if columns not in views:
            views[columns] = self.hf_dataset.select_columns(list(columns))
        return views[columns]


def supported() -> bool:
    return importlib.metadata.version("lerobot").startswith(SUPPORTED_LEROBOT)


def use_history_once(dataset) -> bool:
    """Make `dataset` (a `LeRobotDataset`) read its history with `HistoryOnceReader`; False if it cannot."""
    reader = getattr(dataset, "reader", None)
    if not supported() or reader is None or type(reader) not in (DatasetReader, HistoryOnceReader):
        return False
    reader.__class__ = HistoryOnceReader
    return True


def install() -> bool:
    """Wrap `make_dataset` so that HiveFormer trainings read with `HistoryOnceReader` (LeRobot 0.6.x only)."""
    from lerobot.datasets import factory

    if getattr(factory.make_dataset, "hiveformer_history_once", False):
        return True
    if not supported():
        warnings.warn(
            f"lerobot_policy_hiveformer: LeRobot {importlib.metadata.version('lerobot')} is not "
            f"{SUPPORTED_LEROBOT}x; keeping its stock dataset reader (history reads may be slow).",
            stacklevel=2,
        )
        return False
    stock = factory.make_dataset

    @functools.wraps(stock)
    def make_dataset(cfg):
        dataset = stock(cfg)
        if getattr(getattr(cfg, "policy", None), "type", None) == POLICY_TYPE:
            use_history_once(dataset)
        return dataset

    make_dataset.hiveformer_history_once = True
    factory.make_dataset = make_dataset
    return True
