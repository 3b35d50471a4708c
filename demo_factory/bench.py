"""Benchmarks (``make bench``): generation speed, planner timing and expert success.

Figures go to a JSON file; nothing here is a test and nothing asserts on time.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
from tqdm import tqdm

from demo_factory.generate import EpisodeRequest, episode_seed, job_requests, library_versions, run_requests
from demo_factory.tasks import get_task


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
        "planning_seconds_per_transition_median": float(np.median(planning)) if planning else None,
        "planning_seconds_per_transition_p95": float(np.percentile(planning, 95)) if planning else None,
        "planner_attempts_histogram": {str(k): attempts[k] for k in sorted(attempts)},
    }


def bench_recorded_episode_speed(task_name: str, episodes: int) -> dict:
    """Seconds per recorded episode (3 cameras, 128x128) on variations of length 3."""
    task = get_task(task_name)
    longest = [v for v in task.split_variations("train") if len(v.colours) == 3]
    requests = [EpisodeRequest(task_name, "train", longest[i % len(longest)].id, episode_seed(99, task_name, "train", i))
                for i in range(episodes)]
    with tempfile.TemporaryDirectory() as folder:
        outcomes = list(tqdm(run_requests(requests, folder), total=episodes, desc=f"{task_name} x3 recorded"))
        sizes = [Path(o.path).stat().st_size for o in outcomes if o.kept]
    figures = _timing(outcomes)
    figures["mcap_bytes_per_episode_mean"] = float(np.mean(sizes)) if sizes else None
    return figures


def bench_expert_success(task_name: str, split: str, episodes: int) -> dict:
    """Expert success rate and planner figures over a job's episodes (no rendering)."""
    requests = job_requests(task_name, split, episodes, base_seed=0)
    outcomes = list(tqdm(run_requests(requests, None), total=episodes, desc=f"{task_name}/{split} expert"))
    return _timing(outcomes)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demo_factory.bench", description=__doc__)
    parser.add_argument("--out", default="bench/results.json", help="where to write the figures (JSON)")
    parser.add_argument("--episodes", type=int, default=100, help="episodes per task and split for success rates")
    parser.add_argument("--speed-episodes", type=int, default=20, help="recorded episodes per task for speed")
    args = parser.parse_args(argv)
    began = time.time()
    results = {
        "machine": {"cpu_count": __import__("os").cpu_count(), "platform": platform.platform(),
                    "python": platform.python_version()},
        "versions": library_versions(),
        "recorded_episode_speed_3_objects_3_cameras_128px": {
            task: bench_recorded_episode_speed(task, args.speed_episodes) for task in ("push_buttons", "tower")
        },
        "expert_success": {
            f"{task}/{split}": bench_expert_success(task, split, args.episodes)
            for task in ("push_buttons", "tower") for split in ("train", "test")
        },
    }
    results["total_seconds"] = time.time() - began
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
