"""Narrow speed-ups of LeRobot 0.4.4's dataset writer and merge, which leave what they write unchanged.

All apply only inside :func:`faster_lerobot_writer` (the converter's episode writing and its merge of
batches) and only with LeRobot 0.4.4; with another version LeRobot's own code runs. Together they
make one process write a keyframe dataset about 2x faster (``make bench``, ``conversion`` section).

1. Image statistics from pixel counts. For every image feature of every episode, LeRobot's
   ``save_episode`` calls ``get_feature_stats``, whose ``RunningQuantileStats.update`` reduces the
   (pixels, 3) uint8 array column by column: a mean, a mean of squares, a min, a max and a 5000-bin
   ``np.histogram`` (which sorts each column). That was about 40 % of writing a keyframe dataset.
   Every one of those figures is a function of how many pixels of each channel hold each of the 256
   values, so :class:`CountedQuantileStats` takes one ``np.bincount`` per channel and derives them:

   - the sums are integers below 2**53, so ``sum / n`` is bit for bit ``np.mean``'s float64 result;
   - ``batch ** 2`` wraps around in uint8 in LeRobot (``ImageMoments`` in ``writer.py`` corrects the
     RGB figures afterwards); the counts reproduce that wrap-around too;
   - ``np.histogram`` with explicit edges counts ``edges[j] <= x < edges[j + 1]`` (the last bin
     closed) through ``searchsorted`` on sorted data; the same ``searchsorted`` on the 256 values'
     cumulative counts gives the same integers.

   Anything else (float vectors, a second update) runs LeRobot's own code.
   ``tests/test_lerobot_speedups.py`` compares every statistic with the stock code, bit for bit.

2. Those statistics read the episode's images from memory. LeRobot computes them from the PNG files
   it has just written, decoding each again (about 10 % of writing). :class:`EpisodeImages` keeps
   the arrays of the episode being written, by file, and serves them instead: PNG is lossless, so
   the decoded array is the kept one. A file not kept is read from disk as before.

3. No content hash of each episode's table. ``save_episode`` builds each episode with
   ``datasets.Dataset.from_dict``, which hashes the whole table with dill to make a fingerprint,
   about 10 % of writing. The fingerprint is a cache key of ``datasets``' ``map`` cache, which an
   in-memory episode never uses, and it ends up only in the parquet file's metadata, where it
   already changes with the output folder (the table holds the PNG paths, and the converter writes
   into a temporary folder). A random one, as ``datasets`` itself uses when hashing fails, is
   written instead. The merge's ``to_parquet_with_hf_images`` builds its tables the same way.

4. The merge reads each batch's episode table from its parquet files into memory. LeRobot's
   ``load_episodes`` goes through ``datasets.Dataset.from_parquet``, which first writes an Arrow copy
   into the cache and converts ~190 column types several times over (about half of the merge); the
   same table (same rows, same features, from the same files) is read with pyarrow instead. Calls
   with features or an episode filter (reading a dataset's data) still run LeRobot's own code.
"""

from __future__ import annotations

import contextlib
import functools

import numpy as np

SUPPORTED_LEROBOT = "0.4.4"
VALUES = np.arange(256)


@functools.cache
def _counted_stats_class():
    """:class:`CountedQuantileStats`, made on first use (LeRobot is a heavy import)."""
    from lerobot.datasets.compute_stats import RunningQuantileStats

    class CountedQuantileStats(RunningQuantileStats):
        """``RunningQuantileStats`` whose first update of a uint8 batch works from pixel counts."""

        def update(self, batch: np.ndarray) -> None:
            batch = batch.reshape(-1, batch.shape[-1])
            if self._count or batch.dtype != np.uint8 or len(batch) == 0:
                return super().update(batch)
            num_elements, channels = batch.shape
            counts = np.stack([np.bincount(batch[:, i], minlength=256) for i in range(channels)])
            present = counts > 0
            mean = (counts @ VALUES) / num_elements
            mean_of_squares = (counts @ (VALUES * VALUES % 256)) / num_elements  # uint8 squares wrap
            self._mean, self._mean_of_squares = mean.copy(), mean_of_squares.copy()
            self._min = present.argmax(axis=1).astype(np.uint8)
            self._max = (255 - present[:, ::-1].argmax(axis=1)).astype(np.uint8)
            self._histograms = [np.zeros(self._num_quantile_bins) for _ in range(channels)]
            self._bin_edges = [
                np.linspace(self._min[i] - 1e-10, self._max[i] + 1e-10, self._num_quantile_bins + 1)
                for i in range(channels)
            ]
            self._count += num_elements
            # The rest of LeRobot's update, with the batch's moments, which equal the first ones here.
            self._mean += (mean - self._mean) * (num_elements / self._count)
            self._mean_of_squares += (mean_of_squares - self._mean_of_squares) * (num_elements / self._count)
            for i in range(channels):
                below = np.concatenate([[0], np.cumsum(counts[i])])  # below[k]: pixels with a value < k
                edges = self._bin_edges[i]
                cumulative = np.concatenate([below[np.searchsorted(VALUES, edges[:-1], "left")],
                                             below[np.searchsorted(VALUES, edges[-1:], "right")]])
                self._histograms[i] += np.diff(cumulative)

    return CountedQuantileStats


class EpisodeImages:
    """The current episode's images as arrays, by the file LeRobot's ``add_frame`` queued each for."""

    def __init__(self):
        self.by_path: dict[str, np.ndarray] = {}

    def keep(self, dataset, frame: dict) -> None:
        """After ``dataset.add_frame(frame)``: remember its images (RGB uint8, height x width x 3)."""
        for key, feature in dataset.features.items():
            image = frame.get(key)
            # (LeRobot writes a 3 x W x 3 array as channels-first: such an image is left to the file.)
            if feature["dtype"] == "image" and isinstance(image, np.ndarray) and image.dtype == np.uint8 \
                    and image.ndim == 3 and image.shape[-1] == 3 and image.shape[0] != 3:
                self.by_path[dataset.episode_buffer[key][-1]] = image

    def clear(self) -> None:
        """After ``save_episode``: its images are written and counted."""
        self.by_path.clear()

    def loader(self, stock):
        """``load_image_as_numpy`` that gives a kept image instead of decoding its PNG: the same array,
        since PNG is lossless."""

        def load_image_as_numpy(fpath, dtype=np.float32, channel_first: bool = True):
            image = self.by_path.get(str(fpath))
            if image is None or dtype is not np.uint8 or not channel_first:
                return stock(fpath, dtype=dtype, channel_first=channel_first)
            return np.transpose(image, (2, 0, 1))

        return load_image_as_numpy


@contextlib.contextmanager
def faster_lerobot_writer():
    """Meanwhile, LeRobot's episode statistics use :class:`CountedQuantileStats` on the images kept in
    the :class:`EpisodeImages` it yields, ``datasets`` gives new tables a random fingerprint and
    ``load_episodes`` reads with pyarrow (LeRobot 0.4.4 only; with another version, nothing changes)."""
    import lerobot
    from datasets import arrow_dataset, fingerprint
    from lerobot.datasets import compute_stats, utils

    images = EpisodeImages()
    if lerobot.__version__ != SUPPORTED_LEROBOT:
        yield images
        return
    stock = (compute_stats.RunningQuantileStats, compute_stats.load_image_as_numpy,
             arrow_dataset.generate_fingerprint, utils.load_nested_dataset)
    compute_stats.RunningQuantileStats = _counted_stats_class()
    compute_stats.load_image_as_numpy = images.loader(stock[1])
    arrow_dataset.generate_fingerprint = lambda dataset: fingerprint.generate_random_fingerprint()
    utils.load_nested_dataset = _in_memory_loader(stock[3])
    try:
        yield images
    finally:
        (compute_stats.RunningQuantileStats, compute_stats.load_image_as_numpy,
         arrow_dataset.generate_fingerprint, utils.load_nested_dataset) = stock
        images.clear()


def _in_memory_loader(stock):
    """``load_nested_dataset`` that reads a table without features or filter into memory with pyarrow."""
    import datasets
    import pyarrow as pa
    import pyarrow.parquet as pq
    from datasets.table import InMemoryTable

    def load_nested_dataset(pq_dir, features=None, episodes=None):
        paths = sorted(pq_dir.glob("*/*.parquet"))
        if features is not None or episodes is not None or not paths:
            return stock(pq_dir, features=features, episodes=episodes)
        return datasets.Dataset(InMemoryTable(pa.concat_tables([pq.read_table(path) for path in paths])))

    return load_nested_dataset
