"""MCAP episode recordings → one LeRobot v3.0 dataset per split, plus a dataset card.

Two passes: every recording is read and checked first (so a bad file stops the run before anything
is written), then each split is written with LeRobot's own writer into a hidden folder next to the
output, which is moved into place only when everything succeeded. Writing a split (in one process,
or in batches merged into one dataset) is ``convert.writer``'s.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from demo_factory.convert.features import ACTION_SPACES, DEFAULT_ACTION_SPACE, GRANULARITIES, KEYFRAME_FPS, episode_frames
from demo_factory.convert.card import write_card
from demo_factory.convert.result import ConvertResult
from demo_factory.convert.splits import SourceEpisode, SplitPlan, plan_splits, split_repo_id
from demo_factory.convert.writer import DATASET_FORMAT_VERSION, PROVENANCE_FILE, Layout, write_split
from demo_factory.errors import UsageError
from demo_factory.generate.folder import SUMMARY_GLOB
from demo_factory.instructions import HumanInstruction, load_human_instructions, shipped_human_instructions
from demo_factory.instructions.human import sentence_rows
from demo_factory.record import Episode, RecordingError, iter_episode_paths, read_episode
from demo_factory.tasks import TASKS, get_task

MULTI_TASK = "multi_task"  # the dataset's task label when the inputs' tasks form no named suite


class ConvertError(UsageError, ValueError):
    """A problem the user can fix (bad option, bad input); the message is one line."""


@dataclass
class ConvertOptions:
    inputs: list[Path]  # folders (searched recursively) or .mcap files
    out: Path
    repo_id: str
    granularity: str = "keyframe"
    action_space: str | None = None  # dense only: "joints" (default) or "ee"; keyframe exports: None
    fps: int | None = None  # dense only: the control rate, a divisor of the recorded dense rate (default: that rate)
    val_ratio: float = 0.1
    human_instructions: Path | None = None  # None: the file shipped for the task, if any
    task: str | None = None  # None: every task found in the inputs (several make a multi-task dataset)
    skip_invalid: bool = False
    overwrite: bool = False
    progress: bool = True
    workers: int | None = None  # processes writing a split's episode batches (None: one per CPU core)


def find_recordings(inputs: list[Path]) -> list[Path]:
    """Every complete recording under the inputs (folders recursively), sorted, without repeats."""
    found: list[Path] = []
    for item in inputs:
        if item.is_file():
            found.append(item)
        elif item.is_dir():
            for folder in [item, *sorted(p for p in item.rglob("*") if p.is_dir() and not p.name.startswith("."))]:
                found += iter_episode_paths(folder)
        else:
            raise ConvertError(f"input {item} does not exist; expected a folder of .mcap recordings or a .mcap file")
    unique = sorted({p.resolve(): p for p in found}.values())
    if not unique:
        raise ConvertError(f"no .mcap recordings found in {', '.join(map(str, inputs))}")
    return unique


def find_generation_summaries(inputs: list[Path]) -> list[dict]:
    """The generator's summaries (command, requested, kept, failures) found in the input folders."""
    summaries = []
    for item in inputs:
        if item.is_dir():
            for path in sorted(item.rglob(SUMMARY_GLOB)):
                try:
                    summaries.append(json.loads(path.read_text(encoding="utf-8")))
                except (OSError, ValueError):
                    continue  # a damaged summary only costs the card its generation figures
    return summaries


def check_options(options: ConvertOptions) -> None:
    """Refuse bad option values before any work, one line each."""
    if options.granularity not in GRANULARITIES:
        raise ConvertError(f"unknown granularity {options.granularity!r}; accepted: {', '.join(GRANULARITIES)}")
    if options.action_space is not None and options.action_space not in ACTION_SPACES:
        raise ConvertError(f"unknown --action-space {options.action_space!r}; accepted: {', '.join(ACTION_SPACES)}")
    if options.granularity != "dense" and (options.action_space is not None or options.fps is not None):
        option = "--action-space" if options.action_space is not None else "--fps"
        raise ConvertError(f"{option} applies to --granularity dense only (a keyframe export's action is the next "
                           "keyframe's pose and open state)")
    if options.workers is not None and options.workers < 1:
        raise ConvertError(f"--workers {options.workers} is out of range; accepted: a whole number >= 1")
    if options.fps is not None and options.fps < 1:
        raise ConvertError(f"--fps {options.fps} is out of range; accepted: a whole number of frames per second >= 1")
    if not 0.0 <= options.val_ratio < 1.0:
        raise ConvertError(f"--val-ratio {options.val_ratio} is out of range; accepted: 0 <= ratio < 1")
    owner, _, name = options.repo_id.partition("/")
    allowed = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789-_.")
    if not owner or not name or "/" in name or not set(owner + name) <= allowed:
        raise ConvertError(f"--repo-id {options.repo_id!r} is not a Hub repo id; expected owner/name "
                           "(letters, digits, '-', '_', '.')")
    if options.task is not None and options.task not in TASKS:
        raise ConvertError(f"unknown task {options.task!r}; accepted: {', '.join(TASKS)}")
    out = options.out.resolve()
    if out.exists() and not options.overwrite:
        raise ConvertError(f"output {options.out} already exists; pass --overwrite to replace it")
    if out.exists() and not out.is_dir():
        raise ConvertError(f"output {options.out} is a file; expected a folder path")
    for item in options.inputs:
        if item.resolve() == out or out in item.resolve().parents:
            raise ConvertError(f"input {item} lies inside the output {options.out}; choose another --out")
    if options.human_instructions is not None and not options.human_instructions.is_file():
        raise ConvertError(f"--human-instructions {options.human_instructions} is not a file")


def _check_episode(episode: Episode, path: Path, granularity: str) -> None:
    """Content checks a recording must pass to become dataset episodes (RecordingError otherwise)."""
    info = episode.info
    indices = [k.index for k in episode.keyframes]
    if indices != list(range(len(indices))) or not indices:
        raise RecordingError(f"{path}: keyframe markers {indices} are not 0..K-1")
    if [f.keyframe_index for f in episode.keyframe_frames()] != indices:
        raise RecordingError(f"{path}: keyframe observations do not match the {len(indices)} keyframe markers")
    if granularity == "dense" and not episode.dense_frames():
        raise RecordingError(f"{path}: no dense frames (recorded with dense_fps 0); "
                             "convert with --granularity keyframe or generate with dense frames")
    if info.task in TASKS:
        task = get_task(info.task)
        if info.split not in ("train", "test"):
            raise RecordingError(f"{path}: unknown split {info.split!r}; accepted: train, test")
        try:  # test recordings may be of named unseen variations, never of training ones (and vice versa)
            task.check_split_membership(task.variation(info.variation_id), info.split)
        except ValueError as exc:
            raise RecordingError(f"{path}: {exc}") from None


def dense_stride(recorded_fps: float, fps: int | None, path: Path) -> int:
    """Every how many recorded dense frames one becomes a dataset frame at ``fps`` (None: all of them)."""
    if fps is None:
        return 1
    stride = recorded_fps / fps
    if stride < 1 - 1e-9 or abs(stride - round(stride)) > 1e-6:
        divisors = [f for f in range(1, int(recorded_fps) + 1) if abs(recorded_fps / f - round(recorded_fps / f)) < 1e-6]
        raise ConvertError(f"--fps {fps} does not divide the recorded dense rate {recorded_fps:g} fps of {path.name}; "
                           f"accepted: {', '.join(map(str, divisors)) or 'none (not a whole rate)'}")
    return int(round(stride))


def _source(episode: Episode, path: Path, granularity: str, stride: int = 1) -> SourceEpisode:
    info = episode.info
    attempts = Counter(a.keyframe_index for a in info.planner_attempts)
    return SourceEpisode(
        path=path, task=info.task, split=info.split, variation_id=info.variation_id,
        words=tuple(info.variation), episode_seed=info.episode_seed, instruction=info.instruction,
        frames=len(episode_frames(episode, granularity, stride)),
        keyframes=len(episode.keyframes),
        planner_attempts=tuple(attempts[k] for k in sorted(attempts)),
        exact_attempts=sum(a.status == "exact" for a in info.planner_attempts),
        success=info.success,
        versions=tuple(sorted(info.versions.items())),
        relabels=_relabels(info),
        perturbations=tuple(info.perturbations),
    )


def _relabels(info) -> tuple[tuple[tuple[str, ...], int], ...]:
    """A train recording's instruction relabels (``Task.instruction_relabels``), none of a test variation."""
    if info.task not in TASKS or info.split != "train":
        return ()
    task = get_task(info.task)
    test = set(task.split_variations("test"))
    relabels = task.instruction_relabels(task.variation(info.variation_id), info.extra)
    return tuple((v.words, n) for v, n in relabels if v not in test)


@dataclass
class _Survey:
    sources: list[SourceEpisode]
    invalid: list[tuple[Path, str]]
    other_tasks: dict[str, int]
    task: str  # the task, or for a multi-task dataset its suite's name (else "multi_task")
    cameras: list[str]
    image_size: tuple[int, int]
    fps: int
    tasks: tuple[str, ...] = ()  # every task whose recordings are converted
    stride: int = 1  # dense exports: every stride-th recorded dense frame is kept
    recorded_fps: float = 0.0


def survey(paths: list[Path], options: ConvertOptions) -> _Survey:
    """Read and check every recording; keep what the plan needs (pass 1)."""
    sources: list[SourceEpisode] = []
    layouts: dict[Path, tuple] = {}
    invalid: list[tuple[Path, str]] = []
    for path in tqdm(paths, desc="checking recordings", unit="file", disable=not options.progress):
        try:
            episode = read_episode(path, images=False)  # images are decoded once, when written
            _check_episode(episode, path, options.granularity)
        except RecordingError as exc:
            if not options.skip_invalid:
                raise ConvertError(f"{exc} (pass --skip-invalid to leave such files out)") from None
            invalid.append((path, str(exc).removeprefix(f"{path}: ")))
            continue
        stride = dense_stride(episode.info.dense_fps, options.fps, path) if options.granularity == "dense" else 1
        sources.append(_source(episode, path, options.granularity, stride))
        info = episode.info
        layouts[path] = (tuple(info.cameras), tuple(info.image_size), info.dense_fps)
    tasks = Counter(s.task for s in sources)
    if options.task is not None:
        task = options.task
        if task not in tasks:
            raise ConvertError(f"no recordings of task {task!r} in the inputs (found: {_counts(tasks)})")
    elif len(tasks) == 1:
        task = next(iter(tasks))
    elif not tasks:
        raise ConvertError("no valid recordings left to convert")
    else:  # a multi-task dataset: each frame's task string is its episode's instruction, as always
        from demo_factory.suites import suite_of

        task = suite_of(tasks) or MULTI_TASK
    converted = tuple(sorted(tasks)) if options.task is None else (task,)
    other_tasks = {t: n for t, n in tasks.items() if t not in converted}
    sources = [s for s in sources if s.task in converted]
    first = sources[0].path
    cameras, image_size, dense_fps = layouts[first]
    kept = []
    for s in sources:
        if layouts[s.path] != layouts[first]:
            problem = (f"cameras {list(layouts[s.path][0])}, image size {layouts[s.path][1]}, dense fps {layouts[s.path][2]} "
                       f"differ from {first.name}'s {list(cameras)}, {image_size}, {dense_fps}")
            if not options.skip_invalid:
                raise ConvertError(f"{s.path}: {problem}; one dataset needs one layout (pass --skip-invalid to leave it out)")
            invalid.append((s.path, problem))
        elif not s.success:
            invalid.append((s.path, "the expert did not succeed in this episode"))
        else:
            kept.append(s)
    fps, stride = KEYFRAME_FPS, 1
    if options.granularity == "dense":
        stride = dense_stride(dense_fps, options.fps, first)
        fps = options.fps or int(round(dense_fps))
        if abs(dense_fps / stride - fps) > 1e-6 or fps <= 0:
            raise ConvertError(f"dense rate {dense_fps} fps of {first} is not a whole number; LeRobot needs integer fps "
                               "(pass --fps with a whole divisor of it)")
    return _Survey(kept, invalid, other_tasks, task, list(cameras), image_size, fps, converted, stride, dense_fps)


def convert_command(options: ConvertOptions, task: str) -> str:
    """The ``demo-factory convert`` command line for these options."""
    inputs = " ".join(str(p) for p in options.inputs)
    parts = [f"demo-factory convert --in {inputs} --out {options.out} --repo-id {options.repo_id}"]
    if options.task is not None:
        parts.append(f"--task {task}")
    if options.granularity != "keyframe":
        parts.append(f"--granularity {options.granularity}")
    if options.action_space is not None:
        parts.append(f"--action-space {options.action_space}")
    if options.fps is not None:
        parts.append(f"--fps {options.fps}")
    if options.val_ratio != ConvertOptions.val_ratio:
        parts.append(f"--val-ratio {options.val_ratio}")
    if options.human_instructions is not None:
        parts.append(f"--human-instructions {options.human_instructions}")
    if options.skip_invalid:
        parts.append("--skip-invalid")
    return " ".join(parts)


def _counts(counter: Counter) -> str:
    return ", ".join(f"{k}: {v}" for k, v in sorted(counter.items()))


def _load_human_rows(options: ConvertOptions, task: str) -> tuple[Path | None, list[HumanInstruction] | None]:
    path = options.human_instructions or shipped_human_instructions(task)
    if path is None:
        return None, None
    try:
        rows = [r for r in load_human_instructions(path) if r.task == task]
    except ValueError as exc:
        raise ConvertError(str(exc)) from None
    return path, rows


def check_dataset_provenance(provenance: dict | None, root: Path | str) -> dict:
    """A converted split's provenance (``meta/demo_factory.json``), refused (``ConvertError``, one line)
    when it is missing or from a dataset format this demo-factory does not read."""
    if not provenance:
        raise ConvertError(f"{root}: not a demo-factory dataset (no {PROVENANCE_FILE}; LeRobot's dataset tools do "
                           "not carry it over: evaluate with --task TASK --splits train,test instead)")
    found = provenance.get("format_version", 1)
    if found != DATASET_FORMAT_VERSION:
        why = ("is older (variation numbering or packed depth of LeRobot 0.4); convert its recordings again"
               if found < DATASET_FORMAT_VERSION else "is newer than this demo-factory reads; upgrade demo-factory")
        raise ConvertError(f"{root}: dataset format version {found} {why} (this demo-factory reads version "
                           f"{DATASET_FORMAT_VERSION})")
    return provenance


def read_dataset_provenance(split_root: Path | str) -> tuple[dict, dict]:
    """A converted split's ``meta/info.json`` and its checked provenance (``check_dataset_provenance``):
    ``(info, provenance)``; a ``ConvertError`` for a folder that is not a converted split."""
    info_path = Path(split_root) / "meta" / "info.json"
    if not info_path.is_file():
        raise ConvertError(f"{split_root}: not a converted split (no meta/info.json)")
    info = json.loads(info_path.read_text(encoding="utf-8"))
    provenance_path = Path(split_root) / PROVENANCE_FILE
    if provenance_path.is_file():
        provenance = json.loads(provenance_path.read_text(encoding="utf-8"))
    else:  # datasets written for LeRobot 0.4 kept it in info.json
        provenance = info.get("demo_factory")
    return info, check_dataset_provenance(provenance, split_root)


def plan_multi_task_splits(sources: list[SourceEpisode], tasks, val_ratio: float) -> dict[str, SplitPlan]:
    """Each task's splits planned alone (its own val hold-out), then merged split by split in task order."""
    merged: dict[str, SplitPlan] = {}
    for task in tasks:
        plans, _ = plan_splits([s for s in sources if s.task == task], val_ratio, None)
        for name, plan in plans.items():
            merged.setdefault(name, SplitPlan(name, plan.instruction_source)).episodes.extend(plan.episodes)
    return merged


def convert(options: ConvertOptions, log: Callable[[str], None] = print) -> ConvertResult:
    """Run a whole conversion; raises ``ConvertError`` for problems the user can fix."""
    began = time.perf_counter()
    check_options(options)
    action_space = (options.action_space or DEFAULT_ACTION_SPACE) if options.granularity == "dense" else None
    paths = find_recordings(options.inputs)
    found = survey(paths, options)
    if len(found.tasks) == 1:
        human_file, human_rows = _load_human_rows(options, found.task)
        usable = None if human_rows is None else sentence_rows(human_rows)[0]
        plans, assignment = plan_splits(found.sources, options.val_ratio, usable)
    else:
        human_file, human_rows, assignment = None, None, None
        plans = plan_multi_task_splits(found.sources, found.tasks, options.val_ratio)
    skipped_splits = []
    for name, plan in plans.items():
        if plan.episodes:
            continue
        if name == "test_unseen_human" and len(found.tasks) > 1:
            why = "human-written instructions are matched per task: convert a task alone for this split"
        elif name == "test_unseen_human" and human_rows is None:
            why = f"no human-instruction file for {found.task} (pass --human-instructions FILE)"
        elif name == "test_unseen_human" and any(s.split == "test" for s in found.sources):
            why = f"no row of {human_file} names a test variation that has recordings"
        elif name == "test_unseen_paraphrased" and any(s.split == "test" for s in found.sources):
            why = f"{', '.join(found.tasks)}: no held-out phrasings"
        elif name == "val" and plans["train"].episodes:
            why = "--val-ratio 0 or a single train episode"
        elif name in ("train", "val"):
            why = "no recordings of train variations"
        else:
            why = "no recordings of test variations"
        skipped_splits.append((name, why))
        log(f"skipping split {name}: {why}")
    to_write = [plan for plan in plans.values() if plan.episodes]
    layout = Layout(found.cameras, found.image_size, found.fps, options.granularity, action_space, found.stride,
                    found.recorded_fps, found.task, len(found.tasks) > 1)
    workers = options.workers or os.cpu_count() or 1
    out = options.out
    staging = out.parent / f".{out.name}.partial-{os.getpid()}"
    out.parent.mkdir(parents=True, exist_ok=True)
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir()
    summaries = []
    try:
        with tqdm(total=sum(p.frames for p in to_write), desc="writing", unit="frame",
                  disable=not options.progress) as bar:
            for plan in to_write:
                bar.set_postfix_str(plan.name)
                summaries.append(write_split(plan, staging / plan.name, split_repo_id(options.repo_id, plan.name),
                                             layout, bar, workers))
        result = ConvertResult(
            out=out, repo_id=options.repo_id, task=found.task, granularity=options.granularity, fps=found.fps,
            cameras=found.cameras, image_size=found.image_size, splits=summaries, skipped_splits=skipped_splits,
            invalid=found.invalid, sources=found.sources, human_file=human_file, human_assignment=assignment,
            human_rows=human_rows,
            seconds=0.0, frames_written=sum(s.frames for s in summaries), command=convert_command(options, found.task),
            other_tasks=found.other_tasks, action_space=action_space, recorded_fps=found.recorded_fps,
            generation_summaries=[g for g in find_generation_summaries(options.inputs) if g.get("task") in found.tasks],
        )
        write_card(staging, result, plans)  # after the datasets: it reads their first frames
        if out.exists():
            retired = out.parent / f".{out.name}.old-{os.getpid()}"
            out.rename(retired)
            staging.rename(out)
            shutil.rmtree(retired)
        else:
            staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    result.seconds = time.perf_counter() - began
    return result
