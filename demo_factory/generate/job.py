"""A generation job: a typed description in (`GenerationJob`), its episodes run and recorded into its folder,
a summary out.

The requests of a job are a pure function of its parameters (episode i: variation i mod n, its own
seed); shard i/N runs every N-th of them. Re-running the same job into the same folder resumes it:
recordings already there are kept, partial ones removed.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from demo_factory.generate.episode import EpisodeOutcome, EpisodeRequest, episode_seed
from demo_factory.generate.executors import run_requests
from demo_factory.generate.folder import log_file, record_job, remove_stale_partials, summary_file
from demo_factory.rollout.perturbations import drawn_perturbations, perturbation_option
from demo_factory.tasks import Variation, get_task


def job_requests(task: str, split: str, episodes: int, base_seed: int, variations=None, perturb=None,
                 **settings) -> list[EpisodeRequest]:
    """The requests of a job: episode i uses variation i mod n and its own seed.

    The variations are the split's (by default) or the ones named by the user. ``perturb`` ({factor: probability})
    gives each episode each factor with its probability, drawn from the episode's seed (domain randomisation).
    """
    variations = variations or get_task(task).split_variations(split)
    requests = []
    for i in range(episodes):
        seed = episode_seed(base_seed, task, split, i)
        factors = drawn_perturbations(perturb, seed) if perturb else ()
        requests.append(EpisodeRequest(task, split, variations[i % len(variations)].id, seed,
                                       perturbations=factors, **settings))
    return requests


def shard_requests(requests: list[EpisodeRequest], shard: tuple[int, int] | None) -> list[EpisodeRequest]:
    """Shard ``i/N`` of a job: every N-th request from the i-th; the shards' union is the job."""
    if shard is None:
        return requests
    index, count = shard
    return requests[index::count]


@dataclass
class GenerationJob:
    """One task's job: which episodes, where, and how to run them."""

    task: str
    split: str
    episodes: int
    out: Path
    seed: int = 0
    variations: list[Variation] = field(default_factory=list)  # named variations (default: the split's)
    image_size: tuple[int, int] = (128, 128)
    dense_fps: float = 0.0
    workers: int = 1
    shard: tuple[int, int] | None = None
    executor: str = "process"
    address: str | None = None  # the Ray cluster, with executor "ray"
    perturb: dict[str, float] = field(default_factory=dict)  # {factor: probability an episode gets it}
    command: str = ""  # the command line that runs this job, for the summary (default: `command_line()`)

    def command_line(self, variation_options: list[str] | None = None) -> str:
        """The ``demo-factory generate`` command that runs this job; ``variation_options`` spell the named
        variations as the user did (default: ``--variation=<id>`` each)."""
        if variation_options is None:
            variation_options = [f"--variation={v.id}" for v in self.variations]
        return " ".join(["demo-factory", "generate", "--task", self.task, "--split", self.split, "--episodes",
                         str(self.episodes), "--seed", str(self.seed), "--out", str(self.out)]
                        + variation_options
                        + (["--image-size", "x".join(map(str, self.image_size))]
                           if tuple(self.image_size) != (128, 128) else [])
                        + (["--dense-fps", f"{self.dense_fps:g}"] if self.dense_fps else [])
                        + (["--perturb", perturbation_option(self.perturb)] if self.perturb else []))

    def requests(self) -> list[EpisodeRequest]:
        """This shard's requests (the whole job's without a shard)."""
        requests = job_requests(self.task, self.split, self.episodes, self.seed, variations=self.variations or None,
                                image_size=tuple(self.image_size), dense_fps=self.dense_fps, perturb=self.perturb)
        return shard_requests(requests, self.shard)

    def parameters(self) -> dict:
        """What identifies the job in its folder's manifest (shards share them)."""
        return {"task": self.task, "split": self.split, "episodes": self.episodes, "seed": self.seed,
                "image_size": list(self.image_size), "dense_fps": self.dense_fps,
                "variations": [v.id for v in self.variations] or None,
                **({"perturb": self.perturb} if self.perturb else {})}


def run_job(job: GenerationJob, on_outcome: Callable[[EpisodeOutcome], None] = lambda outcome: None) -> dict:
    """Run (or resume) the job into ``job.out``: the manifest, the episodes, the summary and the attempt log.
    Calls ``on_outcome`` after each episode; returns the summary (also written to the folder). A
    `ManifestMismatch` (a UsageError) when the folder holds the same job with other parameters."""
    out = Path(job.out)
    requests = job.requests()
    out.mkdir(parents=True, exist_ok=True)
    record_job(out, job.parameters())
    remove_stale_partials(out, requests)
    began = time.perf_counter()
    outcomes = []
    for outcome in run_requests(requests, out, workers=job.workers, executor=job.executor, address=job.address):
        outcomes.append(outcome)
        on_outcome(outcome)
    summary = generation_summary(job, outcomes, time.perf_counter() - began)
    summary_file(out, job.task, job.split).write_text(json.dumps(summary, indent=2) + "\n")
    with open(log_file(out, job.task, job.split), "a") as log:  # every attempt, every run
        for o in outcomes:
            if not o.resumed:
                log.write(json.dumps({"variation_id": o.request.variation_id, "episode_seed": o.request.episode_seed,
                                      "kept": o.kept, "reason": o.reason, "seconds": round(o.seconds, 3),
                                      "keyframes": o.keyframes, "planner_attempts": o.attempt_log}) + "\n")
    return summary


def generation_summary(job: GenerationJob, outcomes: list[EpisodeOutcome], total_seconds: float = 0.0) -> dict:
    """The figures a user wants after a generation run (also written to ``generation_summary_<task>_<split>.json``)."""
    fresh = [o for o in outcomes if not o.resumed]
    planning = [s for o in fresh for s in o.planning_seconds]
    attempts = Counter(a for o in fresh for a in o.attempts_per_transition)
    return {
        "command": job.command or job.command_line(),
        "task": job.task,
        "split": job.split,
        "requested": len(outcomes),
        "kept": sum(o.kept for o in outcomes),
        "already_present": sum(o.resumed for o in outcomes),
        "failed": [
            {"variation_id": o.request.variation_id, "episode_seed": o.request.episode_seed, "reason": o.reason}
            for o in outcomes if not o.kept
        ],
        "failure_reasons": dict(Counter(o.reason for o in outcomes if not o.kept)),
        "planner_attempts_histogram": {str(k): attempts[k] for k in sorted(attempts)},
        "planning_seconds_median": float(np.median(planning)) if planning else None,
        "planning_seconds_p95": float(np.percentile(planning, 95)) if planning else None,
        "seconds_per_episode": float(np.mean([o.seconds for o in fresh])) if fresh else None,
        "total_seconds": total_seconds,
    }


def summary_text(summary: dict, out: Path) -> str:
    """The summary as the lines `demo-factory generate` prints."""
    lines = [f"\n{summary['task']}/{summary['split']}: kept {summary['kept']} of {summary['requested']} episodes "
             f"({summary['already_present']} already present) in {out}"]
    if summary["failed"]:
        reasons = ", ".join(f"{k}: {v}" for k, v in summary["failure_reasons"].items())
        lines.append(f"  failed: {len(summary['failed'])} ({reasons})")
        lines += [f"    variation {f['variation_id']} seed {f['episode_seed']}: {f['reason']}" for f in summary["failed"]]
    hist = ", ".join(f"{k}: {v}" for k, v in summary["planner_attempts_histogram"].items())
    if hist:
        lines.append(f"  planner attempts per planned transition: {hist}")
        lines.append(f"  planning time per transition: median {summary['planning_seconds_median']:.3f} s, "
                     f"p95 {summary['planning_seconds_p95']:.3f} s")
    if summary["seconds_per_episode"] is not None:
        lines.append(f"  seconds per episode: {summary['seconds_per_episode']:.2f}")
    return "\n".join(lines)
