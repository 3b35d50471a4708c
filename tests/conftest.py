"""Shared fixtures: small real recordings generated once per test session."""

from __future__ import annotations

import pytest

from demo_factory.generate import job_requests, run_requests


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
