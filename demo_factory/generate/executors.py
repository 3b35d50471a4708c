"""Where a job's episodes run: local processes (``process``) or a Ray cluster (``ray``).

Each executor takes the same per-episode work (`run_episode`, one recording per request), so the files are
identical whichever executor, worker count or machine produced them.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable
from pathlib import Path

from demo_factory.generate.episode import EpisodeOutcome, EpisodeRequest, run_episode
from demo_factory.generate.ray_executor import run_on_ray


def _run_in_worker(args) -> EpisodeOutcome:
    episode, request, out_dir = args
    return episode(request, out_dir)


EXECUTORS = ("process", "ray")


def run_requests(requests: list[EpisodeRequest], out_dir: str | Path | None, workers: int = 1,
                 executor: str = "process", address: str | None = None, episode: Callable = run_episode):
    """Generate every request, yielding outcomes in order.

    ``executor="process"`` uses ``workers`` local processes; ``"ray"`` schedules the same
    per-episode work on a Ray cluster (``address``, or a local one); both run ``episode(request, out_dir)``
    (default: `run_episode`). A request whose recording already exists in ``out_dir`` is not generated again.
    """
    todo = []
    for request in requests:
        existing = Path(out_dir) / request.filename if out_dir is not None else None
        if existing is not None and existing.exists():
            yield EpisodeOutcome(request, True, None, str(existing), 0, resumed=True)
        else:
            todo.append((request, out_dir))
    if executor == "ray":
        yield from run_on_ray(episode, todo, address=address, num_cpus=workers)
        return
    if workers <= 1:
        for request, folder in todo:
            yield episode(request, folder)
        return
    with multiprocessing.get_context("fork").Pool(workers, maxtasksperchild=20) as pool:
        yield from pool.imap(_run_in_worker, [(episode, request, folder) for request, folder in todo])
