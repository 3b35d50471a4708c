"""The scripted experts solve their tasks in physics, with the real planner."""

import pytest

from demo_factory.generate import job_requests, run_requests


@pytest.mark.slow
@pytest.mark.parametrize("split", ["train", "test"])
@pytest.mark.parametrize("task", ["push_buttons", "tower"])
def test_expert_succeeds_on_at_least_19_of_20_seeded_episodes(task, split):
    outcomes = list(run_requests(job_requests(task, split, 20, base_seed=0), out_dir=None))
    failures = [(o.request.variation_id, o.request.episode_seed, o.reason) for o in outcomes if not o.kept]
    assert len(outcomes) == 20
    assert len(failures) <= 1, failures
    # Every planned transition was logged with its attempts (1..10 each).
    assert all(1 <= a <= 10 for o in outcomes for a in o.attempts_per_transition)
