"""Where this plugin changes how LeRobot reads a dataset for a HiveFormer training: two reader methods.

1. History decoded once. LeRobot 0.6's `DatasetReader._query_hf_dataset` reads each key with history as
   `hf_dataset[key][rows]`. With `datasets` >= 4.4 and LeRobot's custom transform that cannot take the
   column fast path: it decodes *every* column of the history rows (every PNG of every camera), once per
   key, so HiveFormer's 11 history keys decode each image 11 times (LeRobot issues #2895 and #2315).
   `HistoryOnceReader` overrides that one method: the history rows are decoded once, with only the
   columns that have history. Its items equal the stock reader's (same keys, same tensors; tested). In a
   training it also keeps the rows it decoded (`history_cache_mib`, 1 GiB by default, per loader worker):
   every window that holds a row reads it again, and a keyframe dataset is small, so after the first
   epoch a window decodes no PNG (a tower run's loader worker took ~27 % of a core of the 2 it shared;
   80 steps of that training: `updt_s` 1.55 s with the rows kept, 1.97 s without). Rows are kept in their
   PNGs' 8 and 16 bits (`compact`), a third of their decoded size.
2. Samples as the authors train. `TrainingReader.get_item` turns the frame LeRobot's sampler drew into
   its whole episode (the window ending at the episode's last keyframe, when the episode fits in the
   history: every keyframe supervised once per sample, none ~n times as often as the last) and, where
   the dataset lists paraphrases of its tasks (`meta/task_paraphrases.json`), replaces the sample's
   instruction by one drawn among them; where it lists relabels of the episode (`meta/instruction_relabels.json`)
   and `relabel_probability` > 0, a window whose frames all lie in an episode's first n keyframes may take a
   relabel's instruction instead (a whole-episode sample then ends at its n-th keyframe).

Both apply only to the datasets HiveFormer trains on. `install()` (run when LeRobot imports the plugin)
wraps `lerobot.datasets.factory.make_dataset`, which `lerobot-train` calls: when the training
configuration's policy is HiveFormer, it first sets the policy's `n_history` to the dataset's longest
episode where none is given, and the dataset it returns reads with `TrainingReader`; any other dataset of
the process (an ACT run, a dataset opened by hand) keeps LeRobot's reader. `use_history_once(dataset)`
applies the first method alone to a dataset built by hand. Version-checked: with a LeRobot other than
0.6.x nothing is replaced and a warning says so.
"""

import dataclasses
import functools
import importlib.metadata
import json
import warnings
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets.dataset_reader import DatasetReader

from .dataset_format import PARAPHRASES_FILE, RELABELS_FILE

SUPPORTED_LEROBOT = "0.6."  # the minor version whose `_query_hf_dataset` and `get_item` this overrides
POLICY_TYPE = "hiveformer"


class HistoryOnceReader(DatasetReader):
    """LeRobot's reader, with each item's history rows decoded once for all keys with history.

    With `cache_bytes` > 0 it also keeps decoded rows (up to that many bytes, the first ones decoded) and
    decodes only the rows it does not hold.
    """

    cache_bytes = 0

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
        cache = self._decoded_rows(keys)
        missing = [row for row in rows if row not in cache]
        decoded = self._columns_view(keys)[missing] if missing else {}  # {key: [value of each missing row]}
        fresh = {row: {key: decoded[key][i] for key in keys} for i, row in enumerate(missing)}
        for row, values in fresh.items():
            if self.__dict__["_cached_bytes"] >= self.cache_bytes:
                break
            kept = {key: (compact(value), value.dtype) for key, value in values.items()}
            size = sum(stored.nbytes for stored, _ in kept.values())
            if self.__dict__["_cached_bytes"] + size <= self.cache_bytes:
                cache[row] = kept
                self.__dict__["_cached_bytes"] += size
        value = {row: fresh.get(row) or {key: expand(*kept) for key, kept in cache[row].items()} for row in rows}
        return {key: torch.stack([value[row][key] for row in relative[key]]) for key in keys}

    def _decoded_rows(self, keys: tuple[str, ...]) -> dict[int, dict]:
        """The kept rows of `keys` (row -> {key: value}), emptied when the table is reloaded."""
        caches = self._per_table("_decoded_row_caches")
        if not caches:
            self.__dict__["_cached_bytes"] = 0
        return caches.setdefault(keys, {})

    def _columns_view(self, columns: tuple[str, ...]):
        """`hf_dataset` restricted to `columns` (its transform still applies), built once per table."""
        views = self._per_table("_history_column_views")
        if columns not in views:
            views[columns] = self.hf_dataset.select_columns(list(columns))
        return views[columns]

    def _per_table(self, name: str) -> dict:
        """The reader's dict `name`, new for each table (the first read, or after `hf_dataset` was reloaded)."""
        source, store = self.__dict__.get(name, (None, {}))
        if source is not self.hf_dataset:
            store = {}
            self.__dict__[name] = (self.hf_dataset, store)
        return store


def compact(value: torch.Tensor) -> torch.Tensor:
    """A decoded value in the fewest bytes that give it back exactly through `expand`: an image's float
    channels (k/255, from 8-bit PNG) as uint8, a depth map's float millimetres (integers, from 16-bit PNG)
    as uint16, anything else as it is. A row of `make reference-unseen`'s 64x64 three-camera dataset
    keeps ~62 KB instead of ~197 KB, so its 5,874 rows fit the default 1 GiB."""
    if value.dtype != torch.float32 or value.dim() < 2:
        return value
    low, high = (float(x) for x in value.aminmax())
    for dtype, scale in ((torch.uint8, 255.0), (torch.uint16, 1.0)):
        if low >= 0 and high * scale <= torch.iinfo(dtype).max:
            stored = (value * scale).round_().to(dtype)
            if torch.equal(expand(stored, value.dtype), value):
                return stored
    return value


def expand(stored: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """The value of dtype `dtype` that `compact` kept as `stored` (itself when kept as it was). uint8 is
    divided by 255 as torchvision's `to_tensor` does (LeRobot's image decoding)."""
    if stored.dtype == dtype:
        return stored
    restored = stored.to(dtype)
    return restored.div(255) if stored.dtype == torch.uint8 else restored


class TrainingReader(HistoryOnceReader):
    """HiveFormer's training reader: whole-episode samples, paraphrased and relabelled instructions (module
    docstring). Configured by `configure_training`; without it, it reads as `HistoryOnceReader`.
    """

    whole_episodes = False
    paraphrases: dict[str, list[str]] = {}
    relabels: dict[int, list] = {}  # episode index -> [[n, instructions], ...] (`read_relabels`)
    relabel_probability = 0.0

    def get_item(self, idx) -> dict:
        rows = self._episode_rows()
        whole = self.whole_episodes and rows.fits[idx]
        if whole:
            idx = int(rows.last[idx])
        first = int(rows.first[idx])
        # A window keeps its frames: only the relabels whose keyframes hold its last one.
        relabels = [r for r in self.relabels.get(int(rows.episode[idx]), ()) if whole or r[0] > idx - first]
        instructions = None
        if relabels and float(torch.rand(())) < self.relabel_probability:
            n, instructions = relabels[int(torch.randint(len(relabels), ()))]
            idx = min(idx, first + n - 1)  # a whole episode ends at the relabel's n-th keyframe
        item = super().get_item(idx)
        alternatives = instructions or self.paraphrases.get(item["task"])
        if alternatives:
            item["task"] = alternatives[int(torch.randint(len(alternatives), ()))]
        return item

    def _episode_rows(self) -> "EpisodeRows":
        """For every row: its episode, the rows of the episode's first and last frames, and whether the episode
        fits in the history window. Built once, from the episode-index column only."""
        cached = self.__dict__.get("_episode_rows_cache")
        if cached is not None and cached[0] is self.hf_dataset:
            return cached[1]
        observed = [min(deltas) for key, deltas in (self.delta_indices or {}).items() if key.startswith("observation.")]
        window = 1 - min(observed, default=0)  # observation steps (the action has one look-back step more)
        episodes = np.asarray(self.hf_dataset.with_format(None)["episode_index"])
        rows = EpisodeRows(episodes, *(np.zeros(len(episodes), int) for _ in range(2)), np.zeros(len(episodes), bool))
        if len(episodes):
            boundaries = np.flatnonzero(np.diff(episodes)) + 1
            for start, stop in zip(np.r_[0, boundaries], np.r_[boundaries, len(episodes)], strict=True):
                rows.first[start:stop], rows.last[start:stop], rows.fits[start:stop] = start, stop - 1, stop - start <= window
        self.__dict__["_episode_rows_cache"] = (self.hf_dataset, rows)
        return rows


@dataclasses.dataclass
class EpisodeRows:
    episode: np.ndarray  # (rows,) episode index
    first: np.ndarray  # (rows,) the row of its episode's first frame
    last: np.ndarray  # (rows,) the row of its episode's last frame
    fits: np.ndarray  # (rows,) bool: the episode fits in the history window


def read_paraphrases(root) -> dict[str, list[str]]:
    """The dataset's `meta/task_paraphrases.json` ({} when it has none)."""
    path = Path(root) / PARAPHRASES_FILE
    if not path.is_file():
        return {}
    paraphrases = json.loads(path.read_text(encoding="utf-8"))
    if not isinstance(paraphrases, dict) or not all(
        isinstance(v, list) and all(isinstance(x, str) for x in v) for v in paraphrases.values()
    ):
        raise ValueError(f"{path}: expected an object mapping each task string to a list of instructions.")
    return paraphrases


def read_relabels(root) -> dict[int, list]:
    """The dataset's `meta/instruction_relabels.json` as {episode index: [[n, instructions], ...]} ({} when none)."""
    path = Path(root) / RELABELS_FILE
    if not path.is_file():
        return {}
    relabels = json.loads(path.read_text(encoding="utf-8"))
    if not isinstance(relabels, dict) or not all(
        k.isdigit() and isinstance(v, list) and all(
            isinstance(r, list) and len(r) == 2 and isinstance(r[0], int) and r[0] >= 1 and isinstance(r[1], list)
            and r[1] and all(isinstance(x, str) for x in r[1]) for r in v)
        for k, v in relabels.items()
    ):
        raise ValueError(f"{path}: expected an object mapping each episode index to a list of "
                         "[keyframes >= 1, [instruction, ...]] pairs.")
    return {int(k): v for k, v in relabels.items()}


def configure_training(dataset, policy_config) -> bool:
    """Make `dataset` read with `TrainingReader` as `policy_config` (a HiveformerConfig) asks; False if it cannot."""
    if not use_history_once(dataset):
        return False
    reader = dataset.reader
    reader.__class__ = TrainingReader
    reader.whole_episodes = bool(policy_config.whole_episodes)
    reader.cache_bytes = int(policy_config.history_cache_mib) * 2**20
    meanings = policy_config.text_encoder != "one_hot"  # one-hot codes name strings, not meanings
    reader.paraphrases = read_paraphrases(dataset.root) if policy_config.sample_paraphrases and meanings else {}
    reader.relabel_probability = float(policy_config.relabel_probability)
    reader.relabels = read_relabels(dataset.root) if reader.relabel_probability and meanings else {}
    return True


def fill_history_from_dataset(cfg) -> None:
    """`n_history` None -> the longest episode of the training dataset (its metadata only)."""
    policy = cfg.policy
    if policy.n_history is not None or not policy.use_history:
        return
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from .modeling_hiveformer import longest_episode

    meta = LeRobotDatasetMetadata(cfg.dataset.repo_id, root=cfg.dataset.root, revision=cfg.dataset.revision)
    policy.n_history = longest_episode(meta)


def supported() -> bool:
    return importlib.metadata.version("lerobot").startswith(SUPPORTED_LEROBOT)


def use_history_once(dataset) -> bool:
    """Make `dataset` (a `LeRobotDataset`) read its history with `HistoryOnceReader`; False if it cannot."""
    reader = getattr(dataset, "reader", None)
    if not supported() or reader is None or type(reader) not in (DatasetReader, HistoryOnceReader, TrainingReader):
        return False
    if type(reader) is DatasetReader:
        reader.__class__ = HistoryOnceReader
    return True


def install() -> bool:
    """Wrap `make_dataset` so that HiveFormer trainings read with `TrainingReader` (LeRobot 0.6.x only)."""
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
        hiveformer = getattr(getattr(cfg, "policy", None), "type", None) == POLICY_TYPE
        if hiveformer:
            fill_history_from_dataset(cfg)
        dataset = stock(cfg)
        if hiveformer:
            configure_training(dataset, cfg.policy)
        return dataset

    make_dataset.hiveformer_history_once = True
    factory.make_dataset = make_dataset
    return True
