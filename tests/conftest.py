"""Shared fixtures: small real recordings generated once per test session."""

from __future__ import annotations

import os

# The suite runs in one process per core (`-n auto`, pyproject.toml). Each of them, and every command a test
# starts, gets one OpenMP thread: several processes each spinning a thread per core slow one another down
# many times over.
if "PYTEST_XDIST_WORKER" in os.environ:
    os.environ["OMP_NUM_THREADS"] = "1"

import pytest  # noqa: E402

from demo_factory.generate import job_requests, run_requests  # noqa: E402

# The files that take longest (end-to-end chains), first: each is handed to a process at the start instead of
# ending the run alone (with `--dist loadfile --no-loadscope-reorder`, files are handed out in this order).
LONGEST_FIRST = ("test_reference_run_tower.py", "test_reference_run.py", "test_reference_suite.py", "test_lerobot_tools.py", "test_publish_http.py",
                 "test_dense.py", "test_evaluate.py", "test_experts.py", "test_ten_tasks.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: file order otherwise


@pytest.fixture(scope="session")
def recorded_episodes(tmp_path_factory):
    """Two push_buttons and one tower episode recorded to MCAP: ``{task: [paths]}``."""
    out = tmp_path_factory.mktemp("recordings")
    requests = job_requests("push_buttons", "train", 2, 0) + job_requests("tower", "test", 1, 0)
    outcomes = list(run_requests(requests, out))
    assert all(o.kept for o in outcomes), [o.reason for o in outcomes]
    paths: dict[str, list[str]] = {}
    for o in outcomes:
        paths.setdefault(o.request.task, []).append(o.path)
    return paths


@pytest.fixture(scope="session")
def converted_push_buttons(tmp_path_factory):
    """A small converted push_buttons dataset (32x32 cameras): its root, with one folder per split."""
    from demo_factory.cli import main

    base = tmp_path_factory.mktemp("push_buttons")
    raw, out = base / "raw", base / "lerobot"
    for split, episodes in (("train", 3), ("test", 2)):
        assert main(["generate", "--task", "push_buttons", "--split", split, "--episodes", str(episodes),
                     "--image-size", "32", "--workers", "1", "--out", str(raw / split)]) == 0
    assert main(["convert", "--in", str(raw), "--out", str(out), "--repo-id", "me/push_buttons",
                 "--val-ratio", "0.34", "--no-progress"]) == 0
    return out
