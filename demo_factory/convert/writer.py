"""Writing one split as a LeRobot v3.0 dataset with LeRobot's own writer.

One process writes a small split. A larger one is cut into consecutive batches of episodes, each
written as its own LeRobot dataset by a forked process, merged in order with LeRobot's
``aggregate_datasets``; the statistics that merge gets wrong (of episode, frame and task numbers) are
recomputed, so the result is the dataset one writer makes (``tests/test_convert_parallel.py``).
demo-factory's own metadata (provenance of every episode) goes in ``meta/demo_factory.json``: LeRobot
0.6 drops unknown keys of ``meta/info.json`` when it rewrites it. A split whose instructions are the
tasks' synthetic ones also lists, in ``meta/task_paraphrases.json``, every phrasing of each task string's
variation (``Task.paraphrases``: task string -> instructions that mean the same; tens for tasks with a
grammar): a policy may train on all of them, as the HiveFormer authors do (the plugin's
``sample_paraphrases``). A keyframe split of train
recordings whose task relabels them (``Task.instruction_relabels``) lists in
``meta/instruction_relabels.json`` the other instructions each episode's first keyframes demonstrate (the
plugin's ``relabel_probability``).
"""

from __future__ import annotations

import contextlib
import io
import json
import multiprocessing
import queue
import shutil
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from lerobot_policy_hiveformer.dataset_format import PARAPHRASES_FILE, RELABELS_FILE
from tqdm import tqdm

from demo_factory.convert.features import dataset_features, dataset_frame, episode_items
from demo_factory.convert.result import SplitSummary
from demo_factory.convert.splits import PlannedEpisode, SplitPlan
from demo_factory.record import read_episode
from demo_factory.tasks.registry import get_task
from demo_factory.tasks.variations import Variation

# meta/demo_factory.json["format_version"]: 3 = LeRobot 0.6's native depth, provenance in that file;
# 2 = LeRobot 0.4's packed depth, provenance in meta/info.json; 1 = variation ids before the paper's.
DATASET_FORMAT_VERSION = 3
PROVENANCE_FILE = "meta/demo_factory.json"
# A split is cut into batches of at least this many episodes: each batch costs a process, a dataset and
# its share of the merge (~1-2 s), which below ~16 episodes a split (2 batches) costs more than it saves.
SMALLEST_BATCH = 8
IMAGE_WRITER_THREADS = 4  # PNG encoding in threads: the writer's bottleneck besides stats


@dataclass(frozen=True)
class Layout:
    """What every split of one conversion shares: features, rate and where the frames come from."""

    cameras: list[str]
    image_size: tuple[int, int]
    fps: int
    granularity: str
    action_space: str | None  # dense exports only
    stride: int  # dense exports: every stride-th recorded dense frame is kept
    recorded_fps: float
    task: str  # the task, or a multi-task dataset's suite name
    multi_task: bool


def _write_episodes(episodes: list[PlannedEpisode], root: Path, repo_id: str, layout: Layout, first_index: int,
                    advance: Callable[[int], None]) -> list[dict]:
    """Write ``episodes`` as one LeRobot dataset at ``root`` (which must not exist) with LeRobot's writer."""
    import datasets  # heavy imports (torch), only when writing
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    datasets.disable_progress_bars()  # one "Map" bar per episode otherwise; ours counts frames
    features = dataset_features(layout.cameras, layout.image_size, layout.action_space)
    dataset = LeRobotDataset.create(repo_id, layout.fps, features, root=root, use_videos=False,
                                    image_writer_threads=IMAGE_WRITER_THREADS)
    provenance = []  # meta/demo_factory.json["episodes"] rows
    try:
        for index, planned in enumerate(episodes, start=first_index):
            episode = read_episode(planned.source.path)
            items = episode_items(episode, layout.granularity, layout.action_space, layout.stride)
            for frame, action in items:
                dataset.add_frame(dataset_frame(episode, frame, planned.instruction, action))
                advance(1)
            dataset.save_episode()
            provenance.append(_provenance_row(planned, index, len(items), layout.multi_task))
        dataset.finalize()
    finally:
        if dataset.writer is not None:  # an error mid-way: the threads stop (the folder is discarded)
            dataset.writer.stop_image_writer()
    shutil.rmtree(root / "images", ignore_errors=True)  # empty once the PNGs are embedded in the parquet files
    return provenance


def _provenance_row(planned: PlannedEpisode, index: int, frames: int, multi_task: bool) -> dict:
    row = planned.human
    return {
        "episode_index": index,
        "recording": planned.source.path.name,
        "variation_id": planned.source.variation_id,
        "colours": list(planned.source.words),
        "episode_seed": planned.source.episode_seed,
        "instruction": planned.instruction,
        "frames": frames,
        **({"task": planned.source.task} if multi_task else {}),
        **({"perturbations": list(planned.source.perturbations)} if planned.source.perturbations else {}),
        **({"human_instruction_line": row.line, "author": row.author, "language": row.language,
            **({"annotation_id": row.record_id} if row.record_id else {})} if row else {}),
    }


def episode_batches(episodes: list, workers: int, smallest: int | None = None) -> list[list]:
    """Consecutive batches of ``episodes`` for ``workers`` processes, as even in size as possible and
    of at least ``smallest`` episodes (default ``SMALLEST_BATCH``) each."""
    count = max(1, min(workers, len(episodes) // (smallest or SMALLEST_BATCH)))
    bounds = [round(i * len(episodes) / count) for i in range(count + 1)]
    return [episodes[a:b] for a, b in zip(bounds[:-1], bounds[1:])]


_PROGRESS: multiprocessing.Queue | None = None  # a batch worker's line to the parent's progress bar


def _start_batch_worker(progress: multiprocessing.Queue) -> None:
    global _PROGRESS
    _PROGRESS = progress


def _write_batch(episodes, root, repo_id, layout, first_index) -> list[dict]:
    return _write_episodes(episodes, root, repo_id, layout, first_index, _PROGRESS.put)


def _write_batches(batches: list[list[PlannedEpisode]], root: Path, repo_id: str, layout: Layout,
                   advance: Callable[[int], None]) -> list[list[dict]]:
    """Each batch written by its own forked process next to ``root``, then merged into ``root`` in
    order by LeRobot's ``aggregate_datasets``."""
    from lerobot.datasets.aggregate import aggregate_datasets

    context = multiprocessing.get_context("fork")
    progress = context.Queue()
    parts = [root.parent / f".{root.name}.batch{i}" for i in range(len(batches))]
    cache = root.parent / f".{root.name}.merge-cache"
    firsts = [sum(len(b) for b in batches[:i]) for i in range(len(batches))]
    try:
        with ProcessPoolExecutor(len(batches), mp_context=context, initializer=_start_batch_worker,
                                 initargs=(progress,)) as pool:
            futures = [pool.submit(_write_batch, batch, part, repo_id, layout, first)
                       for batch, part, first in zip(batches, parts, firsts)]
            while not all(f.done() for f in futures):
                try:
                    advance(progress.get(timeout=0.2))
                except queue.Empty:
                    pass
            written = [f.result() for f in futures]  # a worker's error is raised here
        while not progress.empty():
            advance(progress.get())
        # The merge reads each batch through `datasets`, which keeps an Arrow copy of it in its cache:
        # that cache goes in a folder beside the batches, deleted with them, not in ~/.cache.
        with contextlib.redirect_stderr(io.StringIO()), _datasets_cache(cache):
            aggregate_datasets([repo_id] * len(parts), repo_id, roots=parts, aggr_root=root)
        restate_index_stats(root)
    finally:
        for folder in [*parts, cache]:
            shutil.rmtree(folder, ignore_errors=True)
    return written


@contextlib.contextmanager
def _datasets_cache(folder: Path):
    """``datasets``' cache in ``folder`` meanwhile (its HF_DATASETS_CACHE setting, read at each load)."""
    import datasets

    kept = datasets.config.HF_DATASETS_CACHE
    datasets.config.HF_DATASETS_CACHE = type(kept)(folder)
    try:
        yield
    finally:
        datasets.config.HF_DATASETS_CACHE = kept


INDEX_FEATURES = ("episode_index", "index", "task_index")


def restate_index_stats(root: Path) -> None:
    """LeRobot's ``aggregate_datasets`` merges the sources' overall statistics of the episode, frame and
    task numbers, each counted from its own 0 (LeRobot 0.6 shifts the per-episode ones, not these):
    recompute them from the merged data with LeRobot's ``compute_episode_stats`` and ``aggregate_stats``,
    per episode in ``meta/episodes`` and overall in ``meta/stats.json``, as one writer computes them."""
    import pandas as pd
    from lerobot.datasets.compute_stats import aggregate_stats, compute_episode_stats
    from lerobot.datasets.io_utils import load_stats, write_stats
    from lerobot.utils.constants import DEFAULT_FEATURES

    features = {key: DEFAULT_FEATURES[key] for key in INDEX_FEATURES}
    data = pd.concat([pd.read_parquet(path, columns=list(INDEX_FEATURES))
                      for path in sorted((root / "data").rglob("*.parquet"))], ignore_index=True)
    per_episode = {int(e): compute_episode_stats({key: rows[key].to_numpy() for key in INDEX_FEATURES}, features)
                   for e, rows in data.groupby("episode_index", sort=True)}
    for path in sorted((root / "meta" / "episodes").rglob("*.parquet")):
        episodes = pd.read_parquet(path)
        for key in INDEX_FEATURES:
            for stat in per_episode[int(episodes["episode_index"].iloc[0])][key]:
                episodes[f"stats/{key}/{stat}"] = [per_episode[int(e)][key][stat] for e in episodes["episode_index"]]
        episodes.to_parquet(path)  # as aggregate_datasets writes it
    stats = load_stats(root)
    stats.update(aggregate_stats([per_episode[e] for e in sorted(per_episode)]))
    write_stats(stats, root)


def task_paraphrases(episodes: list[PlannedEpisode]) -> dict[str, list[str]]:
    """Each synthetic instruction of the episodes -> every phrasing of its variation (``Task.paraphrases``)."""
    paraphrases: dict[str, list[str]] = {}
    for planned in episodes:
        source = planned.source
        if planned.instruction not in paraphrases:
            variation = Variation(source.variation_id, source.words)
            texts = get_task(source.task).paraphrases(variation)
            paraphrases[planned.instruction] = texts if planned.instruction in texts else [planned.instruction]
    return paraphrases


def instruction_relabels(episodes: list[PlannedEpisode]) -> dict[str, list]:
    """Episode index -> [[n, every synthetic instruction of a relabel], ...] for the episodes with relabels:
    the episode's first n keyframes also demonstrate each of those instructions."""
    relabels = {}
    for index, planned in enumerate(episodes):
        source = planned.source
        if source.relabels:
            task = get_task(source.task)
            relabels[str(index)] = [[n, task.synthetic_instructions(task.variation_of(words))] for words, n in source.relabels]
    return relabels


def write_split(plan: SplitPlan, root: Path, repo_id: str, layout: Layout, progress: tqdm | None = None,
                workers: int = 1) -> SplitSummary:
    """Write one split as a LeRobot dataset at ``root`` (which must not exist), with up to ``workers``
    processes writing consecutive batches of its episodes."""
    advance = progress.update if progress is not None else (lambda _: None)
    if "fork" not in multiprocessing.get_all_start_methods():
        workers = 1  # batches are written by forked processes (Linux); elsewhere by this one
    batches = episode_batches(plan.episodes, workers)
    if len(batches) == 1:
        parts = [_write_episodes(plan.episodes, root, repo_id, layout, 0, advance)]
    else:
        parts = _write_batches(batches, root, repo_id, layout, advance)
    episodes = [row for part in parts for row in part]
    lengths = [row["frames"] for row in episodes]
    provenance = {
        "format_version": DATASET_FORMAT_VERSION,
        "task": layout.task,
        "split": plan.name,
        "instruction_source": plan.instruction_source,
        "granularity": layout.granularity,
        "cameras": layout.cameras,
        **({"action_space": layout.action_space, "control_fps": layout.fps, "recorded_dense_fps": layout.recorded_fps}
           if layout.granularity == "dense" else {}),
        "episodes": episodes,
    }
    (root / PROVENANCE_FILE).write_text(json.dumps(provenance, indent=2) + "\n", encoding="utf-8")
    if plan.instruction_source == "synthetic":
        paraphrases = task_paraphrases(plan.episodes)
        (root / PARAPHRASES_FILE).write_text(json.dumps(paraphrases, indent=2) + "\n", encoding="utf-8")
        relabels = instruction_relabels(plan.episodes) if layout.granularity == "keyframe" else {}
        if relabels:
            (root / RELABELS_FILE).write_text(json.dumps(relabels) + "\n", encoding="utf-8")
    return SplitSummary(plan.name, repo_id, plan.instruction_source, len(plan.episodes), sum(lengths),
                        len({e.source.variation_id for e in plan.episodes}), min(lengths, default=0))
