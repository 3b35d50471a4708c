"""A generation job's output folder: what it holds and how an interrupted job resumes in it.

A folder holds the recordings (``<task>_<split>_var<id>_seed<seed>.mcap``; ``.<name>.partial`` while one is
being written), the manifest of the jobs run into it (``manifest.json``: their parameters, so that a
resumed job must be the same job), one generation summary and one attempt log per job, and the report.
The converter and the report find the summaries with `SUMMARY_GLOB`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from demo_factory.errors import UsageError

MANIFEST_FILE = "manifest.json"
SUMMARY_GLOB = "generation_summary*.json"
REPORT_FILES = ("report.json", "report.md", "report.png")


def summary_file(folder: Path, task: str, split: str) -> Path:
    """The job's generation summary (the figures of its last run)."""
    return folder / f"generation_summary_{task}_{split}.json"


def log_file(folder: Path, task: str, split: str) -> Path:
    """The job's attempt log: one line per episode generated, every run appended."""
    return folder / f"generation_log_{task}_{split}.jsonl"


def is_generation_file(name: str) -> bool:
    """Whether a file name is one that generation writes into its folder."""
    return (name.endswith(".mcap") or name.endswith(".mcap.partial") or name in (MANIFEST_FILE, *REPORT_FILES)
            or (name.startswith("generation_summary") and name.endswith(".json"))
            or (name.startswith("generation_log") and name.endswith(".jsonl")))


class ManifestMismatch(UsageError, ValueError):
    """Resuming a job into a folder whose manifest recorded other parameters."""


def record_job(folder: Path, parameters: dict) -> None:
    """Record a job's parameters in the folder's manifest, or refuse if the same job had others.

    A folder may hold several jobs (e.g. a task's train and test splits); a job is identified by
    its task and split. Shards of a job share its parameters.
    """
    path = folder / MANIFEST_FILE
    manifest = json.loads(path.read_text()) if path.exists() else {"jobs": {}}
    key = f"{parameters['task']}/{parameters['split']}"
    previous = manifest["jobs"].get(key)
    if previous is not None and previous != parameters:
        differences = "; ".join(
            f"{name}: {previous.get(name)!r} before, {parameters.get(name)!r} now"
            for name in sorted(set(previous) | set(parameters)) if previous.get(name) != parameters.get(name)
        )
        raise ManifestMismatch(f"{folder} already holds the {key} job with other parameters ({differences}); "
                               "use the same parameters to resume it, or another folder")
    manifest["jobs"][key] = parameters
    partial = path.with_name(f".{MANIFEST_FILE}.partial")
    partial.write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    os.replace(partial, path)


def remove_stale_partials(folder: Path, requests) -> int:
    """Delete partial files an interrupted run of these requests left behind; returns how many."""
    removed = 0
    for request in requests:
        partial = folder / f".{request.filename}.partial"
        if partial.exists():
            partial.unlink()
            removed += 1
    return removed
