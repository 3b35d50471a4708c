"""The one place where this plugin changes LeRobot's behaviour: how `LeRobotDataset` reads an item.

Importing the plugin (which `lerobot-train` and `lerobot-eval` do before building the dataset) replaces
`LeRobotDataset.__getitem__` of LeRobot 0.4.4 with `read_item` below. Two changes, nothing else:

1. **History rows are read once, with only their columns.** With `datasets` >= 4.4 and LeRobot's
   custom transform, the stock `_query_hf_dataset` cannot take the column fast path: for every key
   with history it fetches the history rows and decodes *every* column of them (all PNG images of all
   cameras), once per key — HiveFormer's 11 history keys decode each image 11 times (LeRobot issues
   #2895 and #4392, fixed only in LeRobot 0.6, which needs Python 3.12). `read_item` decodes the
   current row's columns without history once and the history rows' columns with history once.
   The items are bit-identical to the stock path (same keys, same tensors; tested).
2. **Image augmentation never touches packed depth.** LeRobot applies `image_transforms` to every
   camera key; `observation.depth.<cam>` images hold millimetres packed into R and G, which colour
   jitter or resizing corrupt (97 % of pixels changed, by up to 9.7 m). `read_item` applies the
   transforms to the other camera keys only.

The patch is applied only to the LeRobot version it was written against; with any other version
the stock reader stays and a warning says so. `stock_getitem` keeps the original for comparison.
"""

import importlib.metadata
import warnings

import torch

PATCHED_LEROBOT_VERSION = "0.4.4"
# Camera keys that hold packed depth, not colour: image augmentation must leave them alone.
PACKED_DEPTH_PREFIX = "observation.depth."



def _columns_view(dataset, columns: tuple[str, ...]):
    """`dataset.hf_dataset` restricted to `columns` (its transform still applies), built once per table."""
    source, views = dataset.__dict__.get("_hiveformer_column_views", (None, {}))
    if source is not dataset.hf_dataset:  # first read, or the table was reloaded
        views = {}
        dataset.__dict__["_hiveformer_column_views"] = (dataset.hf_dataset, views)
    if columns not in views:
        views[columns] = dataset.hf_dataset.select_columns(list(columns))
    return views[columns]


def read_item(self, idx) -> dict:
    """`LeRobotDataset.__getitem__` of LeRobot 0.4.4 with the two changes in the module docstring."""
    self._ensure_hf_dataset_loaded()
    history_keys = [key for key in (self.delta_indices or {}) if key not in self.meta.video_keys]
    columns = self.hf_dataset.column_names
    current_columns = tuple(c for c in columns if c not in history_keys)
    item = _columns_view(self, current_columns)[idx]
    ep_idx = item["episode_index"].item()
    abs_idx = item["index"].item()

    query_indices = None
    if self.delta_indices is not None:
        query_indices, padding = self._get_query_indices(abs_idx, ep_idx)
        history = query_history_once(self, query_indices, tuple(history_keys))
        # The stock reader's key order: the row's columns, then the padding masks.
        item = {c: history[c] if c in history else item[c] for c in columns}
        item.update(padding)

    if len(self.meta.video_keys) > 0:
        current_ts = item["timestamp"].item()
        query_timestamps = self._get_query_timestamps(current_ts, query_indices)
        video_frames = self._query_videos(query_timestamps, ep_idx)
        item = {**video_frames, **item}

    if self.image_transforms is not None:
        for cam in self.meta.camera_keys:
            if not cam.startswith(PACKED_DEPTH_PREFIX):
                item[cam] = self.image_transforms(item[cam])

    task_idx = item["task_index"].item()
    item["task"] = self.meta.tasks.iloc[task_idx].name
    if "subtask_index" in self.features and self.meta.subtasks is not None:
        subtask_idx = item["subtask_index"].item()
        item["subtask"] = self.meta.subtasks.iloc[subtask_idx].name
    return item


def query_history_once(dataset, query_indices: dict[str, list[int]], keys: tuple[str, ...]) -> dict:
    """Every key's history (stacked, in query order), decoding each needed row and column once."""
    if not keys:
        return {}
    to_relative = dataset._absolute_to_relative_idx
    relative = {
        key: query_indices[key] if to_relative is None else [to_relative[i] for i in query_indices[key]]
        for key in keys
    }
    rows = sorted({row for indices in relative.values() for row in indices})
    position = {row: i for i, row in enumerate(rows)}
    decoded = _columns_view(dataset, keys)[rows]  # {key: [value of each row]}
    return {
        key: torch.stack([decoded[key][position[row]] for row in relative[key]]) for key in keys
    }


def install() -> bool:
    """Replace `LeRobotDataset.__getitem__` when LeRobot is the version this was written for."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    if LeRobotDataset.__getitem__ is read_item:
        return True
    version = importlib.metadata.version("lerobot")
    if version != PATCHED_LEROBOT_VERSION:
        warnings.warn(
            f"lerobot_policy_hiveformer: LeRobot {version} is not {PATCHED_LEROBOT_VERSION}; keeping its stock "
            "dataset reader (history reads may be slow, and image_transforms also apply to packed depth).",
            stacklevel=2,
        )
        return False
    global stock_getitem
    stock_getitem = LeRobotDataset.__getitem__
    LeRobotDataset.__getitem__ = read_item
    return True


stock_getitem = None
