"""Benchmarks (``make bench``): generation, planner, cameras, conversion and HiveFormer figures.

Figures go to a JSON file; nothing here is a test and nothing asserts on time. ``--quick`` runs
smaller counts (for a smoke run); the defaults are the counts the issues ask for.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from unittest import mock

import numpy as np
from tqdm import tqdm

from demo_factory.generate import EpisodeRequest, episode_seed, job_requests, run_requests
from demo_factory.record import library_versions
from demo_factory.suites import SUITES
from demo_factory.tasks import MULTI_VARIATION_TASKS, TASKS, get_task
from demo_factory.tools.reference_run import REFERENCE_IMAGE_SIZE, training_environment

REPO = Path(__file__).resolve().parents[2]


def _timing(outcomes) -> dict:
    planning = [s for o in outcomes for s in o.planning_seconds]
    attempts = Counter(a for o in outcomes for a in o.attempts_per_transition)
    return {
        "episodes": len(outcomes),
        "kept": sum(o.kept for o in outcomes),
        "success_rate": sum(o.kept for o in outcomes) / max(1, len(outcomes)),
        "failure_reasons": dict(Counter(o.reason for o in outcomes if not o.kept)),
        "seconds_per_episode_mean": float(np.mean([o.seconds for o in outcomes])),
        "seconds_per_episode_median": float(np.median([o.seconds for o in outcomes])),
        "keyframes_per_episode_mean": float(np.mean([o.keyframes for o in outcomes])),
        "planning_seconds_per_transition_median": float(np.median(planning)) if planning else None,
        "planning_seconds_per_transition_p95": float(np.percentile(planning, 95)) if planning else None,
        "planner_attempts_histogram": {str(k): attempts[k] for k in sorted(attempts)},
    }


def bench_recorded_episode_speed(task_name: str, episodes: int) -> dict:
    """Seconds per recorded episode (3 cameras, 128x128, one process) on variations of length 3."""
    task = get_task(task_name)
    longest = [v for v in task.split_variations("train") if len(v.words) == 3]
    requests = [EpisodeRequest(task_name, "train", longest[i % len(longest)].id, episode_seed(99, task_name, "train", i))
                for i in range(episodes)]
    with tempfile.TemporaryDirectory() as folder:
        outcomes = list(tqdm(run_requests(requests, folder), total=episodes, desc=f"{task_name} x3 recorded"))
        sizes = [Path(o.path).stat().st_size for o in outcomes if o.kept]
    figures = _timing(outcomes)
    figures["mcap_bytes_per_episode_mean"] = float(np.mean(sizes)) if sizes else None
    return figures


def bench_throughput(task_name: str, workers: int, dense_fps: float, episodes: int) -> dict:
    """Episodes per minute of a recorded job (3 cameras, 128x128) with this many worker processes."""
    requests = job_requests(task_name, "train", episodes, base_seed=1234, dense_fps=dense_fps)
    with tempfile.TemporaryDirectory() as folder:
        began = time.perf_counter()
        outcomes = list(run_requests(requests, folder, workers=workers))
        seconds = time.perf_counter() - began
    return {"episodes": episodes, "kept": sum(o.kept for o in outcomes), "seconds": seconds,
            "episodes_per_minute": 60.0 * len(outcomes) / seconds}


def bench_expert_success(task_name: str, split: str, episodes: int) -> dict:
    """Expert success rate and planner figures over a job's episodes (no rendering)."""
    requests = job_requests(task_name, split, episodes, base_seed=0)
    outcomes = list(tqdm(run_requests(requests, None), total=episodes, desc=f"{task_name}/{split} expert"))
    return _timing(outcomes)


def bench_experts(tasks, episodes: int) -> dict:
    """Per task: expert success, keyframes and seconds per episode (train split, no rendering, two
    worker processes; seconds are per episode in its own process)."""
    figures = {}
    for task in tasks:
        requests = job_requests(task, "train", episodes, base_seed=0)
        outcomes = list(tqdm(run_requests(requests, None, workers=2), total=episodes, desc=f"{task} expert"))
        figures[task] = {key: value for key, value in _timing(outcomes).items()
                         if key in ("episodes", "kept", "success_rate", "failure_reasons", "seconds_per_episode_mean",
                                    "keyframes_per_episode_mean", "planner_attempts_histogram")}
    return figures


def _beyond_ten_tasks() -> list[str]:
    """The single-goal tasks beyond the paper's ten (those that give every category two tasks)."""
    return [name for name in TASKS if name not in SUITES["ten_tasks"] and name not in MULTI_VARIATION_TASKS]


def bench_planner(queries: int, seed: int = 0) -> dict:
    """Random feasible queries in a tabletop scene (table + four cubes): time per transition and
    success within 10 seeded attempts."""
    from demo_factory.planning import JointPlanner
    from demo_factory.planning.planner import CollisionChecker
    from demo_factory.sim import World
    from demo_factory.sim.world import JOINT_LOWER, JOINT_UPPER

    rng = np.random.default_rng(seed)
    world = World()
    for x, y in ((0.45, -0.15), (0.55, 0.1), (0.4, 0.2), (0.6, -0.05)):
        world.add_box((0.0225,) * 3, (x, y, 0.0225), (0.8, 0.2, 0.2, 1), mass=0.0)
    planner = JointPlanner()

    def feasible() -> np.ndarray:
        while True:  # a collision-free configuration with the hand above the table
            q = rng.uniform(JOINT_LOWER, JOINT_UPPER)
            world.reset_arm(q)
            if world.gripper_pose()[2] > 0.05 and CollisionChecker(world).valid(q):
                return q

    pairs = [(feasible(), feasible()) for _ in range(queries)]
    seconds, attempts, solved = [], Counter(), 0
    for index, (start, goal) in enumerate(tqdm(pairs, desc="planner queries")):
        world.reset_arm(start)
        result = planner.plan(world, start, goal, episode_seed=seed, transition=index)
        seconds.append(sum(result.solve_seconds))
        attempts[len(result.attempts)] += 1
        solved += result.ok
    world.close()
    return {"queries": queries, "success_within_10_attempts": solved / queries,
            "seconds_per_transition_median": float(np.median(seconds)),
            "seconds_per_transition_p95": float(np.percentile(seconds, 95)),
            "attempts_histogram": {str(k): attempts[k] for k in sorted(attempts)}}


def bench_episode_profile(episodes: int) -> dict:
    """Where a recorded push_buttons episode's time goes (keyframes, 3 cameras 128x128, one process):
    seconds per episode in rendering, physics steps, planning (the planner's wall time, forks
    included), inverse kinematics, MCAP encoding and writing, and the rest; and, inside those, in
    PyBullet's own stepping, rendering and IK calls."""
    import pybullet

    from demo_factory.generate import run_episode
    from demo_factory.record.writer import EpisodeWriter
    from demo_factory.sim.kinematics import Kinematics
    from demo_factory.sim.world import World

    spent = Counter()

    def timing(original, label):
        def call(*args, **kwargs):
            began = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                spent[label] += time.perf_counter() - began
        return call

    # PyBullet's own calls, inside the parts above: the floor of an episode's time without changing it.
    engine = {"stepSimulation": "step_simulation", "getCameraImage": "get_camera_image",
              "calculateInverseKinematics": "calculate_inverse_kinematics"}
    requests = job_requests("push_buttons", "train", episodes + 1, base_seed=1234)
    with contextlib.ExitStack() as patches, tempfile.TemporaryDirectory() as folder:
        for owner, name, label in [(World, "render_cameras", "render"), (World, "step", "physics"),
                                   (Kinematics, "inverse", "ik"), (EpisodeWriter, "write_frame", "encode_and_write"),
                                   (EpisodeWriter, "close", "encode_and_write"),
                                   *((pybullet, name, label) for name, label in engine.items())]:
            patches.enter_context(mock.patch.object(owner, name, timing(getattr(owner, name), label)))
        run_episode(requests[0], folder)  # warm-up: imports, caches, the process's IK solver
        spent.clear()
        began = time.perf_counter()
        for request in requests[1:]:
            spent["planning"] += sum(run_episode(request, folder).planning_seconds)
        total = time.perf_counter() - began
    figures = {label: seconds / episodes for label, seconds in spent.items()}
    inside = {label: figures.pop(label) for label in engine.values()}
    figures["other"] = total / episodes - sum(figures.values())
    return {"episodes": episodes, "seconds_per_episode": total / episodes,
            "seconds_per_episode_in": {k: round(v, 4) for k, v in sorted(figures.items())},
            "seconds_per_episode_in_pybullet_calls": {k: round(v, 4) for k, v in sorted(inside.items())}}


def bench_render(frames: int) -> dict:
    """Milliseconds to render one camera (RGB + depth + segmentation) at 128x128, per camera."""
    from demo_factory.sim import World
    from demo_factory.sim.camera import render
    from demo_factory.sim.world import HAND_LINK

    world = World()
    get_task("tower").build_scene(world, get_task("tower").variation(2000), np.random.default_rng(0))
    hand = world.link_pose(HAND_LINK)
    figures = {}
    for spec in world.cameras:
        render(world.client, spec, world.image_size, hand)  # warm the caches
        began = time.perf_counter()
        for _ in range(frames):
            render(world.client, spec, world.image_size, hand)
        figures[spec.name] = 1000.0 * (time.perf_counter() - began) / frames
    world.close()
    return {"ms_per_camera": figures}


def bench_conversion(episodes: int) -> dict:
    """Converter frames per second (one worker, and one per core) next to a plain ``LeRobotDataset.add_frame``
    loop on the same input, in the same run."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from demo_factory.convert.converter import ConvertOptions, convert
    from demo_factory.convert.features import KEYFRAME_FPS, dataset_features, dataset_frame
    from demo_factory.record import iter_episode_paths, read_episode

    with tempfile.TemporaryDirectory() as folder:
        raw = Path(folder) / "raw"
        list(run_requests(job_requests("push_buttons", "train", episodes, base_seed=77), raw, workers=os.cpu_count() or 1))
        paths = iter_episode_paths(raw)
        frames = sum(len(read_episode(p).keyframes) for p in paths)

        cores = os.cpu_count() or 1
        seconds = {}
        for workers in sorted({1, cores}):
            began = time.perf_counter()
            convert(ConvertOptions(inputs=[raw], out=Path(folder) / f"converted_{workers}", repo_id="bench/converted",
                                   val_ratio=0.0, progress=False, workers=workers), log=lambda _: None)
            seconds[workers] = time.perf_counter() - began
        converter_seconds = seconds[cores]

        began = time.perf_counter()
        first = read_episode(paths[0])
        dataset = LeRobotDataset.create("bench/reference", KEYFRAME_FPS,
                                        dataset_features(first.info.cameras, first.info.image_size),
                                        root=Path(folder) / "reference", use_videos=False)
        for path in paths:
            episode = read_episode(path)
            for frame in episode.keyframe_frames():
                dataset.add_frame(dataset_frame(episode, frame, episode.info.instruction))
            dataset.save_episode()
        dataset.finalize()
        reference_seconds = time.perf_counter() - began
    return {"episodes": len(paths), "frames": frames, "workers": cores,
            "converter_frames_per_second": frames / converter_seconds,
            "converter_one_worker_frames_per_second": frames / seconds[1],
            "reference_add_frame_loop_frames_per_second": frames / reference_seconds,
            "converter_over_reference": reference_seconds / converter_seconds}


def bench_hiveformer() -> dict:
    """The plugin's own measurement script (train step at batch 8, inference per step), on CPU."""
    result = subprocess.run([sys.executable, "-m", "lerobot_policy_hiveformer.measure_compute", "--batch-size", "8",
                             "--cpu-kernels"],
                            capture_output=True, text=True, env={**training_environment(), "HF_HUB_OFFLINE": "1"})
    if result.returncode != 0:
        return {"error": result.stderr.strip().splitlines()[-1] if result.stderr.strip() else "failed"}
    text = result.stdout
    return json.loads(text[text.index("{"):])


def _history_items_per_second(root: Path, n_history: int, items: int) -> dict:
    """Items/s of one DataLoader worker (one torch thread) reading HiveFormer's keyframe history:
    LeRobot's stock reader against the plugin's, on the same random frames of a warm dataset."""
    import random

    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot_policy_hiveformer import dataset_reading

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # what a DataLoader worker runs with
    meta = LeRobotDataset("bench/history", root=root).meta
    deltas = [i / meta.fps for i in range(1 - n_history, 1)]
    keys = [k for k in meta.features if k.startswith("observation.")] + ["action"]
    stock = LeRobotDataset("bench/history", root=root, delta_timestamps={k: deltas for k in keys})
    plugin = LeRobotDataset("bench/history", root=root, delta_timestamps={k: deltas for k in keys})
    assert dataset_reading.use_history_once(plugin)
    for index in range(len(plugin)):  # page cache warm for both readers
        plugin[index]
    frames = random.Random(0).sample(range(len(plugin)), min(items, len(plugin)))
    rates = {}
    for name, dataset, count in (("stock", stock, max(len(frames) // 6, 5)), ("plugin", plugin, len(frames))):
        began = time.perf_counter()
        for index in frames[:count]:
            dataset[index]
        rates[name] = count / (time.perf_counter() - began)
    torch.set_num_threads(threads)
    return {"history_steps": n_history, "keys_with_history": len(keys), "frames_in_dataset": len(plugin),
            "stock_items_per_second": rates["stock"], "plugin_items_per_second": rates["plugin"],
            "speedup": rates["plugin"] / rates["stock"]}


def train_step_against_kernel_floor(root: Path, steps: int, repeats: int = 10, settings: dict | None = None,
                                    rounds: int = 5) -> dict:
    """One reference-configuration training step (HiveFormer as `lerobot-train` builds it on `root`: batch 16,
    one-hot instructions, no attention dropout, `settings` (HiveformerConfig fields, e.g. `make reference`'s
    SEEN_RECIPE) over the plugin's defaults; forward, backward, AdamW step; the machine's torch threads)
    against its kernel floor: each of the step's convolutions and attention calls re-run alone with its
    backward pass (`measure_compute.kernel_calls_ms`, as the inference floor), `repeats` times in a row.

    Steps and floor are measured in alternation, `rounds` rounds of `steps // rounds` steps (at least one) then
    the floor, and the ratio is the median of the rounds' ratios: on a shared machine whose speed swings by tens
    of percent over a minute, a step and a floor measured minutes apart compare two machines. Each round draws
    its own batch, as training does: the ratio depends on the batch (a step's fixed costs weigh more in a batch
    of few keyframes; in `make reference`'s recipe one 95-keyframe batch measured 1.44-1.57x over three runs, a
    58-keyframe one 1.69x), so one batch would report that batch. Each round starts with an untimed step: the
    floor's re-runs leave the caches and the allocator with their own tensors, and the step after them ran
    10-17 % slower than the next in three rounds of five, which follows a step as in training."""
    from types import SimpleNamespace

    import torch
    from lerobot.configs.default import DatasetConfig
    from lerobot.datasets import factory
    from lerobot.policies.factory import make_policy, make_pre_post_processors
    from lerobot_policy_hiveformer import HiveformerConfig

    from demo_factory.tools.reference_run import REFERENCE_BATCH_SIZE, REFERENCE_TEXT_ENCODER

    torch.manual_seed(0)
    config = HiveformerConfig(device="cpu", text_encoder=REFERENCE_TEXT_ENCODER, attention_dropout=0.0, **(settings or {}))
    cfg = SimpleNamespace(dataset=DatasetConfig(repo_id="bench/history", root=str(root)), policy=config,
                          trainable_config=config, tolerance_s=1e-4, num_workers=0)
    dataset = factory.make_dataset(cfg)
    policy = make_policy(config, ds_meta=dataset.meta)
    preprocessor, _ = make_pre_post_processors(config, dataset_stats=dataset.meta.stats)
    loader = torch.utils.data.DataLoader(dataset, batch_size=REFERENCE_BATCH_SIZE, shuffle=True,
                                         generator=torch.Generator().manual_seed(0))
    rounds = max(rounds, 1)
    batches = [preprocessor(batch) for batch, _ in zip(itertools.cycle(loader), range(rounds))]
    optimizer = config.get_optimizer_preset().build(policy.get_optim_params())  # as lerobot-train builds it
    policy.train()

    def step(batch) -> float:
        began = time.perf_counter()
        loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        return time.perf_counter() - began

    step(batches[0])  # the first step also encodes the instructions and warms the allocator
    from lerobot_policy_hiveformer import measure_compute as measure

    durations, floors, ratios = [], [], []
    for batch in batches:
        calls = measure.record_kernel_calls(lambda batch=batch: policy.forward(batch))
        step(batch)  # after the floor's re-runs (or the recording): a step follows a step, as in training
        round_durations = [step(batch) for _ in range(max(steps // rounds, 1))]
        floor = measure.kernel_calls_ms(calls, repeats, backward=True)
        durations += round_durations
        floors.append(floor)
        ratios.append(1000 * float(np.median(round_durations)) / sum(floor.values()))
    floor = {kind: round(float(np.median([f[kind] for f in floors])), 2) for kind in floors[0]}
    recipe = {name: getattr(config, name) for name in ("whole_episodes", "stem_point_cloud")}
    return {"batch_size": REFERENCE_BATCH_SIZE, "n_history": config.n_history, **recipe,
            "keyframes_in_batch": [int((~batch["action_is_pad"]).sum()) for batch in batches],
            "threads": torch.get_num_threads(),
            "rounds": rounds, "train_step_ms": round(1000 * float(np.median(durations)), 1),
            "kernel_floor_ms": floor, "kernel_floor_total_ms": round(sum(floor.values()), 1),
            "step_over_floor": round(float(np.median(ratios)), 2),
            "step_over_floor_range": [round(min(ratios), 2), round(max(ratios), 2)]}


def bench_hiveformer_training(episodes: int, train_steps: int) -> dict:
    """HiveFormer's data path, its training step against its kernel floor and a real `lerobot-train` run in
    the reference run's CPU configuration.

    Items/s are measured on 128x128 push_buttons keyframe datasets (3 cameras, history 6, every
    observation key and the action), stock vs the plugin's reader. The training step against its kernel
    floor is measured in `make reference`'s recipe with and without the compiled CPU loops and in the plugin's
    defaults (the authors' whole-episode samples). `updt_s` / `data_s` come from `lerobot-train --policy.type=hiveformer` with the reference run's
    settings (its image size, batch, one-hot instructions, one loader worker, its recipe) on a dataset
    generated at that size.
    """
    from demo_factory.convert.converter import ConvertOptions, convert
    from demo_factory.tools.reference_run import SEEN_RECIPE, policy_flags, train_command, train_log_timings

    figures = {}
    with tempfile.TemporaryDirectory() as folder:
        for size in sorted({128, REFERENCE_IMAGE_SIZE}):
            raw, root = Path(folder) / f"raw{size}", Path(folder) / f"converted{size}"
            requests = job_requests("push_buttons", "train", episodes, base_seed=78, image_size=(size, size))
            list(run_requests(requests, raw, workers=os.cpu_count() or 1))
            convert(ConvertOptions(inputs=[raw], out=root, repo_id="bench/history", val_ratio=0.0, progress=False),
                    log=lambda _: None)
        figures["history_reading_128px"] = _history_items_per_second(Path(folder) / "converted128" / "train", 6, 120)
        reference = Path(folder) / f"converted{REFERENCE_IMAGE_SIZE}" / "train"
        # make reference's recipe (windows, 7-channel stem) with the compiled CPU loops and without them (PyTorch
        # alone, what a user without the [cpu] extra runs), then the plugin's defaults (the authors' whole episodes)
        for name, settings in (("", SEEN_RECIPE), ("_pytorch", SEEN_RECIPE | {"cpu_kernels": False}),
                               ("_whole_episodes", {"cpu_kernels": True})):
            figures[f"train_step_against_kernel_floor{name}"] = train_step_against_kernel_floor(
                reference, steps=min(train_steps, 10), settings=settings)
        output_dir = Path(folder) / "train"
        command = train_command(reference, output_dir, steps=train_steps, log_freq=5) + policy_flags(SEEN_RECIPE)
        result = subprocess.run(command, capture_output=True, text=True,
                                env={**training_environment(), "HF_HUB_OFFLINE": "1"})
        if result.returncode != 0:
            figures["lerobot_train"] = {"error": result.stderr.strip().splitlines()[-1] if result.stderr else "failed"}
        else:
            figures["lerobot_train"] = {"command": " ".join(command[1:]), "image_size": REFERENCE_IMAGE_SIZE,
                                        **train_log_timings(result.stdout + result.stderr)}
    return figures


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demo_factory.tools.bench", description=__doc__)
    parser.add_argument("--out", default="bench/results.json", help="where to write the figures (JSON)")
    parser.add_argument("--quick", action="store_true", help="small counts: a smoke run, not figures to report")
    parser.add_argument("--only", help="comma-separated sections to run (default: all): " + ", ".join(SECTIONS))
    args = parser.parse_args(argv)
    counts = QUICK if args.quick else FULL
    sections = args.only.split(",") if args.only else list(SECTIONS)
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        parser.error(f"unknown section {unknown[0]!r}; accepted: {', '.join(SECTIONS)}")
    out = Path(args.out)
    results = json.loads(out.read_text()) if out.exists() and args.only else {}
    results.update({
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "load_average_at_start": os.getloadavg()},
        "versions": library_versions(),
        "counts": counts,
    })
    for section in sections:
        began = time.time()
        results[section] = SECTIONS[section](counts)
        results[section + "_wall_seconds"] = time.time() - began
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(results, indent=2) + "\n")  # after each section: partial figures survive
    print(json.dumps(results, indent=2))
    return 0


FULL = {"speed_episodes": 20, "throughput_episodes": 60, "success_episodes": 100, "planner_queries": 1000,
        "render_frames": 100, "conversion_episodes": 30, "history_episodes": 40, "train_steps": 40}
QUICK = {"speed_episodes": 2, "throughput_episodes": 2, "success_episodes": 4, "planner_queries": 10,
         "render_frames": 5, "conversion_episodes": 3, "history_episodes": 3, "train_steps": 6}
SECTIONS = {
    "recorded_episode_speed_3_objects_3_cameras_128px": lambda c: {
        task: bench_recorded_episode_speed(task, c["speed_episodes"]) for task in ("push_buttons", "tower")},
    "episodes_per_minute": lambda c: {
        f"{task}/workers={workers}/{'dense_10fps' if dense else 'keyframes'}":
            bench_throughput(task, workers, dense, c["throughput_episodes"])
        for task in ("push_buttons", "tower") for workers in (1, 2) for dense in (0.0, 10.0)},
    "expert_success": lambda c: {
        f"{task}/{split}": bench_expert_success(task, split, c["success_episodes"])
        for task in ("push_buttons", "tower") for split in ("train", "test")},
    "ten_tasks_expert": lambda c: bench_experts(SUITES["ten_tasks"], c["success_episodes"]),
    "beyond_ten_tasks_expert": lambda c: bench_experts(_beyond_ten_tasks(), c["success_episodes"]),
    "planner": lambda c: bench_planner(c["planner_queries"]),
    "episode_profile": lambda c: bench_episode_profile(c["speed_episodes"]),
    "camera_render": lambda c: bench_render(c["render_frames"]),
    "conversion": lambda c: bench_conversion(c["conversion_episodes"]),
    "hiveformer_cpu": lambda c: bench_hiveformer(),
    "hiveformer_training": lambda c: bench_hiveformer_training(c["history_episodes"], c["train_steps"]),
}


if __name__ == "__main__":
    raise SystemExit(main())
