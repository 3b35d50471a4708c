"""Generation: expert demonstrations, recorded to MCAP.

Owns the episode (`run_episode`: a task's scene, its expert's keyframes executed with the rollout, the
recording), the job (`GenerationJob` in, `run_job` runs or resumes it, a summary out), the job folder
(manifest, partial files, summary and log names: `folder`), the executors (local processes or Ray) and the
generation report. Reads tasks and instruction files; writes ``.mcap`` recordings, ``manifest.json``,
``generation_summary_*.json``, ``generation_log_*.jsonl`` and ``report.*`` into the job's folder.
"""

from demo_factory.generate.episode import EpisodeOutcome, EpisodeRequest, episode_seed, run_episode
from demo_factory.generate.executors import EXECUTORS, run_requests
from demo_factory.generate.folder import (
    MANIFEST_FILE,
    REPORT_FILES,
    SUMMARY_GLOB,
    ManifestMismatch,
    is_generation_file,
    record_job,
    remove_stale_partials,
)
from demo_factory.generate.job import GenerationJob, job_requests, run_job, shard_requests, summary_text
from demo_factory.generate.report import write_report

__all__ = [
    "EXECUTORS",
    "MANIFEST_FILE",
    "REPORT_FILES",
    "SUMMARY_GLOB",
    "EpisodeOutcome",
    "EpisodeRequest",
    "GenerationJob",
    "ManifestMismatch",
    "episode_seed",
    "is_generation_file",
    "job_requests",
    "record_job",
    "remove_stale_partials",
    "run_episode",
    "run_job",
    "run_requests",
    "shard_requests",
    "summary_text",
    "write_report",
]
